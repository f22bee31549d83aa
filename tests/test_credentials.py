"""No storage credential is ever shown or stored: every URL form (password in the userinfo, unencoded '@',
password / sslpassword / passfile / sslkey as query parameters), every place (run header, JSON output,
dashboard start-up line, error messages including driver exceptions, study attributes, frozen files,
reports) and a full dump of a real PostgreSQL storage grepped for the secrets."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest

from pipeline.errors import ImtuneError
from tests.conftest import ROOT, copy_strecha_subset
from tuner.storage import classify, mask_url, scrub, storage_fault

SECRET = "Zq7-secret-pw"

# (url as typed, secrets that must not appear, parts that must stay visible)
MASK_CASES = [
    (f"postgresql://imtune:{SECRET}@db.example:5432/optuna", [SECRET], ["imtune", "db.example:5432/optuna"]),
    (f"postgresql://imtune@127.0.0.1:5432/optuna?password={SECRET}", [SECRET], ["imtune@127.0.0.1:5432/optuna"]),
    (f"postgresql://imtune@127.0.0.1/optuna?sslmode=require&sslpassword={SECRET}", [SECRET], ["sslmode=require"]),
    (f"postgresql://u@h/db?passfile=/home/u/{SECRET}.pgpass", [SECRET], ["u@h/db"]),
    (f"postgresql://u@h/db?sslkey=/keys/{SECRET}.key&sslcert=/keys/client.crt", [SECRET], ["client.crt"]),
    ("postgresql://u:left-Part@right-Part@dbhost/db", ["left-Part", "right-Part"], ["dbhost/db"]),
    ("postgresql://u:left-Part@right-Part@dbhost:5432/db?password=other-Secret", ["left-Part", "right-Part",
                                                                                  "other-Secret"], ["dbhost:5432"]),
    ("postgresql://u:c0lon:Part@mid-Part@[::1]:5432/db", ["c0lon:Part", "mid-Part"], ["[::1]:5432/db"]),
    (f"mysql+pymysql://root:{SECRET}@127.0.0.1/optuna?ssl_key=/k/{SECRET}2", [SECRET], ["root", "127.0.0.1/optuna"]),
    (f"postgresql://imtune:{SECRET.replace('-', '%40')}@h/db", [SECRET.replace("-", "%40"), SECRET.replace("-", "@")],
     ["imtune", "h/db"]),
    # SQLAlchemy cannot parse these (bad port): the regex fallback still masks
    (f"postgresql://u:{SECRET}@h:notaport/db", [SECRET], ["h:notaport/db"]),
    (f"postgresql://u:{SECRET}@h:5432/db?password", [SECRET], ["h:5432/db"]),
]


@pytest.mark.parametrize("url,secrets,visible", MASK_CASES)
def test_mask_url_hides_every_secret(url, secrets, visible):
    shown = mask_url(url)
    for s in secrets:
        assert s not in shown, shown
    for v in visible:
        assert v in shown, shown
    assert "***" in shown


@pytest.mark.parametrize("path", ["journal:/tmp/studies/optuna.log", "/tmp/studies/optuna.log",
                                  "sqlite:////tmp/my-pass/optuna.db", "sqlite:///studies/optuna.db"])
def test_paths_are_untouched(path):
    assert mask_url(path) == path


@pytest.mark.parametrize("url,user,password,host,query", [
    ("postgresql://u:left-Part@right-Part@dbhost:5432/db", "u", "left-Part@right-Part", "dbhost", {}),
    ("postgresql://u:a@b:c@dbhost:5432/db", "u", "a@b:c", "dbhost", {}),  # SQLAlchemy alone cannot parse it
    ("postgresql://u:pa@ss@[::1]:5432/db", "u", "pa@ss", "::1", {}),
    ("postgresql://u:pw@dbhost/db?application_name=a@b", "u", "pw", "dbhost", {"application_name": "a@b"}),
    ("postgresql://u:pa@ss@dbhost/db?application_name=a@b", "u", "pa@ss", "dbhost", {"application_name": "a@b"}),
    ("postgresql://us@er@dbhost/db", "us@er", None, "dbhost", {}),
])
def test_unencoded_at_connects_with_the_whole_password(url, user, password, host, query):
    from sqlalchemy.engine import make_url
    kind, norm = classify(url)
    u = make_url(norm)
    assert kind == "rdb" and (u.username, u.password, u.host, dict(u.query)) == (user, password, host, query)


@pytest.mark.parametrize("text,url", [
    # psycopg2 / libpq DSN text and URLs embedded in driver exceptions
    (f"invalid dsn: host=127.0.0.1 port=5 password={SECRET} dbname=optuna", None),
    (f"invalid dsn: host=127.0.0.1 password='{SECRET} x' dbname=optuna", None),
    (f"(psycopg2.OperationalError) could not connect to postgresql://u:{SECRET}@h/db\n(Background ...)", None),
    ("connection to server at \"h\" failed for postgresql://u:left-Part@right-Part@h/db", None),
    (f"Could not parse SQLAlchemy URL from string 'postgresql://u@h/db?password={SECRET}&x=1'", None),
    (f"error near {SECRET} in statement", f"postgresql://u:{SECRET}@h/db"),
    (f"error near {SECRET} in statement", f"postgresql://u@h/db?sslpassword={SECRET}"),
    (f"PGPASSWORD={SECRET} psql failed", None),
])
def test_scrub_masks_exception_text(text, url):
    out = scrub(text, url)
    for s in (SECRET, "left-Part", "right-Part"):
        assert s not in out, out
    assert "\n" not in out


def test_scrub_keeps_ordinary_text():
    assert scrub("--fix monkey=3: unknown parameter") == "--fix monkey=3: unknown parameter"
    assert scrub("ratio must be in (0, 1], got 2") == "ratio must be in (0, 1], got 2"


def test_storage_errors_are_masked():
    for url in (f"postgresql://u@127.0.0.1:1/db?password={SECRET}", f"postgresql://u:{SECRET}@127.0.0.1:1/db",
                f"postgres://u:{SECRET}@h/db", f"bogus://u:{SECRET}@h/db", f"postgresql://u:{SECRET}@h:x/db"):
        with pytest.raises(ImtuneError) as e:
            from tuner.storage import open_storage
            open_storage(url, heartbeat=None)
        assert SECRET not in str(e.value) and "\n" not in str(e.value)
    # a storage fault mid-run names the storage masked
    import sqlalchemy.exc
    err = sqlalchemy.exc.OperationalError("SELECT 1", {}, Exception(
        f"server closed the connection unexpectedly (postgresql://u:{SECRET}@h/db)"))
    msg = storage_fault(err, f"postgresql://u@h/db?password={SECRET}")
    assert msg and SECRET not in msg and "lost the connection" in msg


# -- the real CLI on a real PostgreSQL server -------------------------------------------------------

@pytest.fixture(scope="module")
def pg():
    from tests.pgserver import PgServer
    srv = PgServer(password=SECRET)
    try:
        # a second role whose password has every URL delimiter, typed unencoded in the URL
        srv.sql("CREATE ROLE odd LOGIN PASSWORD %s", ("left-Part@right-Part:x/y?z",))
        srv.sql("GRANT imtune TO odd")  # the same tables
        yield srv
    finally:
        srv.close()


@pytest.fixture(scope="module")
def subset(tmp_path_factory):
    return copy_strecha_subset(tmp_path_factory.mktemp("cred-data"), ["0003.jpg", "0004.jpg", "0005.jpg"])


ODD_SECRETS = ["left-Part", "right-Part", "x/y?z"]


def _tune(*args, cache, timeout=300):
    env = dict(os.environ, IMTUNE_CACHE=str(cache))
    env.pop("IMTUNE_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "tuner", *map(str, args)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout, stdin=subprocess.DEVNULL)


def _quick(data, studies, storage, study):
    return ["run", "--data", data, "--feature", "sift", "--num-features", "1024", "--ransac", "degensac",
            "--scenes", "fountain-P11", "--test-scenes", "fountain-P11", "--max-pairs", "3", "--chunk-pairs", "3",
            "--budget", "0.2", "--calibration-pairs", "2", "--studies-dir", studies, "--storage", storage,
            "--study", study, "--seed", "1"]


def _one_line_error(r):
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("tune: error: "), r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    return lines[0]


def test_no_credential_anywhere(pg, subset, tmp_path):
    cache, studies = tmp_path / "cache", tmp_path / "studies"
    base = f"127.0.0.1:{pg.port}/{pg.db}"
    as_query = f"postgresql://imtune@{base}?password={SECRET}"
    as_userinfo = pg.url
    odd = f"postgresql://odd:left-Part@right-Part:x/y?z@{base}"
    outputs = []

    def run(*args, ok=True):
        r = _tune(*args, cache=cache)
        outputs.append(r.stdout + r.stderr)
        if ok:
            assert r.returncode == 0, r.stderr[-3000:]
        return r

    # a study through the query-parameter form: the run header and the outcome name the storage masked
    r = run(*_quick(subset, studies, as_query, "cred-q"), "--n-trials", "2", "--test-runs", "1")
    assert f"study cred-q in postgresql://imtune@{base}?password=*** (created" in r.stderr
    assert f"study cred-q  (postgresql://imtune@{base}?password=***)" in r.stdout
    # the same storage through the password-in-userinfo form, JSON output
    r = run(*_quick(subset, studies, as_userinfo, "cred-u"), "--n-trials", "2", "--no-test", "--json")
    assert json.loads(r.stdout)["storage"] == f"postgresql://imtune:***@{base}"
    # the role with '@', ':', '/' and '?' in its password, typed unencoded: it connects, nothing leaks
    r = run(*_quick(subset, studies, odd, "cred-odd"), "--n-trials", "2", "--no-test")
    assert f"postgresql://odd:***@{base}" in r.stderr
    for args in (["studies"], ["table"], ["results"]):
        run(*args, "--storage", as_query, "--studies-dir", studies)
    run("plot", "--study", "cred-q", "--storage", odd, "--studies-dir", studies)
    run("test", "--study", "cred-u", "--storage", as_userinfo, "--studies-dir", studies, "--runs", "1",
        "--max-pairs", "3", "--scenes", "fountain-P11")

    # error messages: wrong password (each form), an option libpq rejects (psycopg2's own exception text),
    # SSL secrets on a closed port, an unparseable port
    wrong = [f"postgresql://imtune@{base}?password=not-{SECRET}",
             f"postgresql://imtune:not-{SECRET}@{base}",
             f"postgresql://odd:left-Part@right-Part-no@{base}",
             f"postgresql://imtune@{base}?password={SECRET}&bogus_option=1",
             f"postgresql://imtune@127.0.0.1:1/{pg.db}?sslpassword={SECRET}&sslkey=/k/{SECRET}.key&passfile=/{SECRET}",
             f"postgresql://imtune:{SECRET}@127.0.0.1:notaport/{pg.db}"]
    for url in wrong:
        r = run("studies", "--storage", url, "--studies-dir", studies, ok=False)
        line = _one_line_error(r)
        assert "***" in line, line
    r = run("--storage", f"postgresql://imtune@{base}?password=not-{SECRET}", "--studies-dir", studies,
            "--data", subset, ok=False)
    assert "password authentication failed" in _one_line_error(r)

    # the dashboard's start-up line
    from tests.pgserver import free_port
    port = free_port()
    env = dict(os.environ, IMTUNE_CACHE=str(cache))
    p = subprocess.Popen([sys.executable, "-m", "tuner", "dashboard", "--storage", as_query, "--port", str(port),
                          "--studies-dir", str(studies)], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        line = p.stderr.readline()
        assert f"http://127.0.0.1:{port}/" in line and "?password=***" in line, line
        outputs.append(line)
    finally:
        p.send_signal(signal.SIGINT)
        try:
            so, se = p.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
            so, se = p.communicate()
        outputs.append(so + se)

    # grep: every output, every file the studies wrote, every row of every table of the storage
    files = {str(f): f.read_text(errors="replace") for f in studies.rglob("*") if f.is_file()}
    assert any(f.endswith("frozen.yaml") for f in files) and any(f.endswith("test.json") for f in files)
    assert any(f.endswith("report.html") for f in files)
    dump = pg.dump()
    assert "cred-q" in dump and "cred-odd" in dump
    texts = {"outputs": "\n".join(outputs), "dump": dump, **files}
    found = {where: s for where, t in texts.items() for s in [SECRET, *ODD_SECRETS] if s in t}
    print(f"credentials found: {len(found)} in {len(texts)} texts ({len(outputs)} outputs, {len(files)} files, "
          f"a {len(dump)}-character dump of {dump.count('-- ')} tables)")
    assert found == {}


def test_paths_shown_as_given(tmp_path):
    """SQLite and journal paths are shown as given (nothing to mask, nothing altered)."""
    from tuner.storage import storage_label
    assert storage_label(f"sqlite:///{tmp_path}/optuna.db") == f"sqlite:///{tmp_path}/optuna.db"
    assert storage_label(None, tmp_path) == f"sqlite:///{tmp_path.resolve()}/optuna.db"
    assert storage_label(f"journal:{tmp_path}/passwords.log") == f"journal:{tmp_path}/passwords.log"


CRASHING_TASK = '''
from pipeline.tasks import TASKS
from pipeline.tasks.stereo import StereoTask


@TASKS.register("crash", "a plugin task whose evaluation fails with a connection string in its message")
class CrashTask(StereoTask):
    name = "crash"

    def evaluate(self, scenes, conf, cache=None, on_step=None):
        raise RuntimeError("could not connect to postgresql://imtune:Pl8ginS3cret@127.0.0.1:1/results")
'''


@pytest.mark.parametrize("debug", [False, True])
def test_an_unexpected_error_never_shows_a_password_not_even_with_imtune_debug(subset, tmp_path, debug):
    """A bug outside our code (here a plugin's) whose message carries a URL with a password: one masked line, or
    with IMTUNE_DEBUG=1 the whole traceback, every line masked."""
    plugin = tmp_path / "crash_task.py"
    plugin.write_text(CRASHING_TASK)
    env = dict(os.environ, IMTUNE_CACHE=str(tmp_path / "c"), IMTUNE_PLUGINS=str(plugin))
    env.pop("IMTUNE_DEBUG", None)
    if debug:
        env["IMTUNE_DEBUG"] = "1"
    r = subprocess.run([sys.executable, "-m", "tuner", "evaluate", "--task", "crash", "--data", str(subset),
                        "--feature", "sift", "--num-features", "512", "--ransac", "degensac", "--quiet"],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=300, stdin=subprocess.DEVNULL)
    assert r.returncode == 1, (r.returncode, r.stderr[-2000:])
    out = r.stdout + r.stderr
    assert "Pl8ginS3cret" not in out, out[-2000:]
    assert "postgresql://imtune:***@127.0.0.1:1/results" in out, out[-2000:]
    if debug:
        assert "Traceback (most recent call last)" in r.stderr and "CrashTask" not in r.stdout
        assert "raise RuntimeError" in r.stderr  # the traceback's lines, each kept on its own line
    else:
        assert [ln for ln in r.stderr.splitlines() if ln.strip()] == [
            "tune: internal error: RuntimeError: could not connect to postgresql://imtune:***@127.0.0.1:1/results "
            "(set IMTUNE_DEBUG=1 for details)"]


def test_a_password_from_pgpassword_keeps_it_out_of_the_command_line(pg, tmp_path):
    """The README's advice: leave the password out of the URL and set PGPASSWORD, which the driver reads."""
    import optuna
    optuna.create_study(study_name="pgpassword-probe", storage=pg.url.replace("postgresql://", "postgresql+psycopg2://"))
    url = pg.url.replace(f":{SECRET}@", "@")
    assert SECRET not in url
    env = dict(os.environ, IMTUNE_CACHE=str(tmp_path / "cache"))
    env.pop("PGPASSWORD", None)
    args = [sys.executable, "-m", "tuner", "studies", "--storage", url, "--studies-dir", str(tmp_path)]
    r = subprocess.run(args, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "no password supplied" in r.stderr, r.stderr
    r = subprocess.run(args, cwd=ROOT, env={**env, "PGPASSWORD": SECRET}, capture_output=True, text=True, timeout=120)
    # connected with the driver's PGPASSWORD: the probe study listed (tune studies warns that another program made
    # it, naming it: the word "password" in its name is no password error)
    assert SECRET not in r.stdout + r.stderr, r.stderr
    assert "no password supplied" not in r.stderr and "authentication failed" not in r.stderr, r.stderr
    assert r.returncode == 0 and "pgpassword-probe" in r.stdout and "cannot open storage" not in r.stderr, r.stderr
