"""Several `tune` workers on one study in a real PostgreSQL server that this test starts on loopback."""
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from tests.conftest import DATA, ROOT
from tests.pgserver import free_port as _free_port  # one copy of each
from tests.pgserver import pg_bin as _pg_bin

STRECHA = DATA / "strecha"
PASSWORD = "pw-Secr3t-imtune"
pytestmark = [pytest.mark.postgres,
              pytest.mark.skipif(not STRECHA.is_dir(), reason=f"real data not found at {STRECHA}")]


@pytest.fixture(scope="module")
def postgres():
    """A throw-away PostgreSQL cluster on 127.0.0.1:<free port>; yields its URL (with a password)."""
    pg = _pg_bin()
    if pg is None:
        pytest.skip("PostgreSQL server binaries not found (/usr/lib/postgresql/*/bin; .ci/install.sh installs "
                    "Debian's postgresql)")
    try:
        import psycopg2  # noqa: F401
    except ImportError:
        pytest.skip("psycopg2 is not installed (pip install psycopg2-binary)")
    root = os.geteuid() == 0
    if root:
        try:
            subprocess.run(["id", "postgres"], check=True, capture_output=True)
        except (subprocess.CalledProcessError, FileNotFoundError):
            pytest.skip("running as root but there is no 'postgres' user to run the server as")
    d = Path(tempfile.mkdtemp(prefix="imtune-pg-"))
    as_pg = ["runuser", "-u", "postgres", "--"] if root else []
    pwfile = d / "pw"
    pwfile.write_text(PASSWORD + "\n")
    if root:
        shutil.chown(d, "postgres")
        shutil.chown(pwfile, "postgres")
    port = _free_port()
    data = d / "data"
    run = lambda *a, **kw: subprocess.run(as_pg + list(a), check=True, capture_output=True, text=True,  # noqa: E731
                                          stdin=subprocess.DEVNULL, timeout=120, **kw)
    try:
        run(str(pg / "initdb"), "-D", str(data), "-U", "imtune", f"--pwfile={pwfile}", "-A", "scram-sha-256",
            "--no-sync")
        run(str(pg / "pg_ctl"), "-D", str(data), "-l", str(d / "log"), "-w", "-t", "60", "-o",
            f"-p {port} -k {d} -c listen_addresses=127.0.0.1 -c fsync=off", "start")
        run(str(pg / "createdb"), "-h", "127.0.0.1", "-p", str(port), "-U", "imtune", "optuna",
            env=dict(os.environ, PGPASSWORD=PASSWORD))
    except subprocess.CalledProcessError as e:
        shutil.rmtree(d, ignore_errors=True)
        pytest.fail(f"could not start PostgreSQL: {e.stderr or e.stdout}")
    try:
        yield f"postgresql://imtune:{PASSWORD}@127.0.0.1:{port}/optuna"
    finally:
        subprocess.run(as_pg + [str(pg / "pg_ctl"), "-D", str(data), "-m", "immediate", "-w", "stop"],
                       capture_output=True, stdin=subprocess.DEVNULL, timeout=60)
        shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(scope="session")
def tuner_cache(tmp_path_factory):
    d = tmp_path_factory.getbasetemp() / "tuner-cache"
    d.mkdir(exist_ok=True)
    return str(d)


def test_three_workers_on_postgres(postgres, tmp_path, tuner_cache):
    import optuna
    from optuna.trial import TrialState

    from tuner.storage import open_storage
    args = ["--data", str(STRECHA), "--feature", "sift", "--num-features", "2048", "--ransac", "degensac",
            "--scenes", "fountain-P11", "--max-pairs", "8", "--chunk-pairs", "4", "--budget", "0.1",
            "--calibration-pairs", "4", "--studies-dir", str(tmp_path), "--storage", postgres,
            "--n-trials", "12", "--no-test", "--json", "--study", "pg-shared"]
    env = dict(os.environ, IMTUNE_CACHE=tuner_cache)
    procs = []
    for _ in range(3):
        procs.append(subprocess.Popen([sys.executable, "-m", "tuner", *args], cwd=ROOT, env=env,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
        time.sleep(0.3)
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (so, se) in zip(procs, outs):
        assert p.returncode == 0, se[-2000:]
        assert PASSWORD not in so and PASSWORD not in se  # masked everywhere
    parsed = [json.loads(so) for so, _ in outs]
    assert all(o["storage"] == postgres.replace(PASSWORD, "***") for o in parsed)
    runs = [set(o["worker"]["trials_run"]) for o in parsed]
    assert sum(1 for r in runs if r) >= 2  # the work was shared
    for a in range(3):
        for b in range(a + 1, 3):
            assert not (runs[a] & runs[b])  # no trial run twice
    st = optuna.load_study(study_name="pg-shared", storage=open_storage(postgres, heartbeat=None))
    finished = {t.number for t in st.trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)}
    assert finished == runs[0] | runs[1] | runs[2]  # every trial recorded, none lost
    assert len(finished) == 12  # exactly the target: no trial beyond it counts
    # a trial two workers created in the same instant is a surplus trial (tuner/workers.py): failed unevaluated,
    # user attribute "surplus", no parameter; nothing else may be left unfinished
    left = [t for t in st.trials if t.number not in finished]
    assert all(t.state == TrialState.FAIL and t.user_attrs.get("surplus") and not t.params for t in left), left
    assert sorted(t.number for t in st.trials) == list(range(len(st.trials)))
    assert PASSWORD not in json.dumps(st.user_attrs)
    for t in st.trials:
        assert PASSWORD not in json.dumps(t.user_attrs)
    # the reports read the same storage
    r = subprocess.run([sys.executable, "-m", "tuner", "table", "--storage", postgres, "--studies-dir", str(tmp_path)],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "sift" in r.stdout and PASSWORD not in r.stdout + r.stderr


def test_wrong_password_is_one_masked_line(postgres, tmp_path):
    bad = postgres.replace(PASSWORD, "not-the-password")
    r = subprocess.run([sys.executable, "-m", "tuner", "--storage", bad, "--studies-dir", str(tmp_path),
                        "--data", str(STRECHA)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "not-the-password" not in r.stderr and "***" in r.stderr
    assert r.stderr.strip().count("\n") == 0 and "password authentication failed" in r.stderr
