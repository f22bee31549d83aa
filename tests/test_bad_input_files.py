"""Bad input files and folders through the real `tune` CLI: each cause we can name is one line `tune: error: ...`
naming the culprit, exit 2 — never "internal error", a traceback, or a password.

Covered: malformed storage URLs that carry a password; binary (non-UTF-8) files given as configuration, search
space, reference, comparison source, frozen.yaml or imtune.yaml, and YAML's string ``1e5``; journal storages
that are not Optuna journals (binary, text, unknown operations, a device, a folder, a FIFO); studies folders
that cannot be written; `tune viz --out` on a file or in a folder that cannot be written; an unbounded
``--ci-resamples``; a download base URL that is no URL; unknown COLMAP camera models and non-positive image
sizes for `tune data build-gt`; invalid calibrations in budgets.json; non-finite or negative numbers in a
frozen.yaml.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ROOT, copy_strecha_subset

SECRET = "Zq7-secret-pw"
BINARY = bytes(range(128, 256)) * 4 + b"\n\xff\xfe\x00"  # no valid UTF-8 sequence


def tune(*args, env: dict | None = None, cwd: Path | str = ROOT, timeout: float = 120, **kw):
    """`python -m tuner ARGS` in a real process (no IMTUNE_DEBUG; extra environment ``env``, None: unset)."""
    e = dict(os.environ, PYTHONPATH=str(ROOT))
    e.pop("IMTUNE_DEBUG", None)
    e.update(env or {})
    e = {k: v for k, v in e.items() if v is not None}
    return subprocess.run([sys.executable, "-m", "tuner", *map(str, args)], cwd=cwd, env=e, capture_output=True,
                          text=True, timeout=timeout, stdin=subprocess.DEVNULL, **kw)


def one_line_error(r, *needles: str) -> str:
    """The single stderr line of a user error (exit 2), which must contain every needle."""
    assert r.returncode == 2, (r.returncode, r.stdout[-1000:], r.stderr[-3000:])
    assert "Traceback" not in r.stderr and "internal error" not in r.stderr, r.stderr[-3000:]
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("tune: error: "), r.stderr[-3000:]
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def data3(tmp_path_factory):
    """3 real Strecha images of fountain-P11 (3 pairs)."""
    return copy_strecha_subset(tmp_path_factory.mktemp("bad-files-data"), ["0003.jpg", "0004.jpg", "0005.jpg"])


# -- 1. a malformed storage URL never shows its password ---------------------------------------------------

@pytest.mark.parametrize("url", [f"postgresql:/user:{SECRET}@127.0.0.1:1/db", f"postgresql//user:{SECRET}@127.0.0.1:1/db",
                                 f"user:{SECRET}@127.0.0.1:1/db", f"postgresql:user:{SECRET}@127.0.0.1:1/db",
                                 f"postgresql:/user:a@{SECRET}@127.0.0.1:1/db"])
def test_malformed_storage_url_masks_the_password(url, tmp_path):
    r = tune("studies", "--storage", url, "--studies-dir", tmp_path / "studies")
    line = one_line_error(r, "malformed storage URL", "127.0.0.1:1/db", "***")
    assert SECRET not in r.stdout + r.stderr, line
    from tuner.storage import mask_url, scrub
    assert SECRET not in mask_url(url) and SECRET not in scrub(f"error in {url}", url)
    assert not (tmp_path / "studies").exists()


# -- 2. binary files where text is expected; YAML's string 1e5 -----------------------------------------------

def _binary(tmp: Path, name: str = "bin.yaml") -> Path:
    f = tmp / name
    f.parent.mkdir(parents=True, exist_ok=True)
    f.write_bytes(BINARY)
    return f


def _frozen_study(tmp: Path, content: bytes | str) -> Path:
    """A studies folder holding study X whose frozen.yaml is ``content``; returns the folder."""
    sdir = tmp / "studies"
    (sdir / "X").mkdir(parents=True)
    f = sdir / "X" / "frozen.yaml"
    f.write_bytes(content) if isinstance(content, bytes) else f.write_text(content)
    return sdir


NOT_UTF8 = {  # setup(tmp, data) -> (argv, culprit, cwd or None)
    "evaluate-config": lambda t, d: (["evaluate", "--config", _binary(t), "--data", d], _binary(t), None),
    "run-space": lambda t, d: (["run", "--space", _binary(t), "--data", d, "--studies-dir", t / "studies",
                                "--storage", f"sqlite:///{t}/optuna.db"], _binary(t), None),
    "run-reference": lambda t, d: (["run", "--reference", _binary(t), "--data", d, "--studies-dir", t / "studies",
                                    "--storage", f"sqlite:///{t}/optuna.db"], _binary(t), None),
    "compare-source": lambda t, d: (["compare", _binary(t, "a.yaml"), _binary(t, "b.yaml"), "--data", d],
                                    _binary(t, "a.yaml"), None),
    "viz-config": lambda t, d: (["viz", "--config", _binary(t), "--data", d, "--out", t / "viz"], _binary(t), None),
    "viz-compare": lambda t, d: (["viz", "--compare", _binary(t, "a.yaml"), _binary(t, "b.yaml"), "--data", d,
                                  "--out", t / "viz"], _binary(t, "a.yaml"), None),
    "test-frozen": lambda t, d: (["test", "--study", "X", "--studies-dir", _frozen_study(t, BINARY), "--data", d],
                                 t / "studies" / "X" / "frozen.yaml", None),
    "imtune-yaml": lambda t, d: (["data", "scenes"], _binary(t / "cwd", "imtune.yaml"), t / "cwd"),
    "splits-yaml": lambda t, d: (["data", "scenes", "--data", t / "data"],
                                 _splits(t, d), None),
}


def _splits(tmp: Path, data: Path) -> Path:
    import shutil
    shutil.copytree(data, tmp / "data")
    return _binary(tmp / "data", "splits.yaml")


@pytest.mark.parametrize("case", list(NOT_UTF8))
def test_binary_file_is_named_as_not_utf8_text(case, tmp_path, data3):
    argv, culprit, cwd = NOT_UTF8[case](tmp_path, data3)
    env = {"IMTUNE_STUDIES": str(tmp_path / "studies"), "IMTUNE_CACHE": str(tmp_path / "cache")}
    env["IMTUNE_DATA"] = None  # imtune.yaml is rule 3
    r = tune(*argv, env=env, cwd=cwd or ROOT)
    one_line_error(r, str(culprit), "is not a UTF-8 text file")
    assert not (tmp_path / "optuna.db").exists()


def test_a_device_or_folder_as_config_file_is_never_read(tmp_path):
    # /dev/zero would be read forever; a folder was "does not exist"
    one_line_error(tune("evaluate", "--config", "/dev/zero"), "/dev/zero", "not a regular file")
    one_line_error(tune("evaluate", "--config", tmp_path), str(tmp_path), "is a folder")



def test_a_folder_named_splits_yaml_is_named_not_skipped(tmp_path, data3):
    """A folder at <data>/splits.yaml was skipped as if there were no splits file: the default split was used
    (here fountain-P11 tuned on) without a word of the folder."""
    import shutil
    data = tmp_path / "data"
    shutil.copytree(data3, data)
    (data / "splits.yaml" / "inside").mkdir(parents=True)
    r = tune("data", "scenes", "--data", data)
    one_line_error(r, f"splits file {data / 'splits.yaml'} is a folder")
    assert (data / "splits.yaml" / "inside").is_dir()


def test_a_folder_named_imtune_yaml_is_named_not_skipped(tmp_path, data3):
    """A folder at ./imtune.yaml was skipped for the next rule (the project's imtune.yaml, the download location,
    ../shared/data): another data folder was used without a word of it."""
    cwd = tmp_path / "cwd"
    (cwd / "imtune.yaml" / "inside").mkdir(parents=True)
    r = tune("data", "scenes", env={"IMTUNE_DATA": None}, cwd=cwd)
    one_line_error(r, f"project configuration {cwd / 'imtune.yaml'} is a folder")

@pytest.mark.parametrize("text,needle,hint", [
    ("feature: sift\nmax_iters: 1e5\n", "max-iters must be a number, got '1e5'", "write 1.0e+5 or 100000"),
    ("geometry: {ransac: degensac, threshold: 5e-1}\n", "got '5e-1'", "write 5.0e-1 or 0.5"),
])
def test_yaml_exponent_without_dot_says_how_to_write_it(text, needle, hint, tmp_path, data3):
    f = tmp_path / "c.yaml"
    f.write_text(text)
    one_line_error(tune("evaluate", "--config", f, "--data", data3), str(f), needle, hint)


def test_search_space_exponent_without_dot_says_how_to_write_it(tmp_path, data3):
    f = tmp_path / "space.yaml"
    f.write_text("params:\n  max_iters: {low: 1e3, high: 100000, log: true}\n")
    r = tune("run", "--space", f, "--data", data3, "--studies-dir", tmp_path / "studies",
             "--storage", f"sqlite:///{tmp_path}/optuna.db")
    one_line_error(r, str(f), "params.max_iters", "got '1e3'", "write 1.0e+3 or 1000")


# -- 3. a journal storage that is not an Optuna journal ------------------------------------------------------

JOURNALS = {  # name -> content
    "binary": BINARY,
    "text": b"hello world\nsecond line\n",
    "text-one-line": b"hello world\n",  # Optuna skips a bad last line: it passed for an empty journal
    "unknown-op-code": b'{"op_code": 99, "worker_id": "w"}\n',
    "no-op-code": b'{"a": 1}\n',
    "json-list": b"[1, 2]\n",
}


@pytest.mark.parametrize("cmd", ["studies", "run"])
@pytest.mark.parametrize("content", list(JOURNALS))
def test_corrupt_journal_is_one_line(content, cmd, tmp_path, data3):
    j = tmp_path / "optuna.log"
    j.write_bytes(JOURNALS[content])
    extra = ["--data", data3, "--num-features", "512", "--n-trials", "1", "--no-test", "--quiet"] if cmd == "run" else []
    r = tune(cmd, "--storage", f"journal:{j}", "--studies-dir", tmp_path / "studies", *extra,
             env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, str(j), "is not an Optuna journal file")
    assert j.read_bytes() == JOURNALS[content]  # left as it was


def test_a_journal_cut_short_is_refused_before_it_is_broken(tmp_path, data3):
    """A journal whose last record was cut short (a crash or a full disk mid-write): Optuna skips that record but
    appends the next one right after its bytes, so `tune run` (resume) died with "tune: internal error:
    AttributeError: ... '_last_created_trial_id_by_this_process'" and left one invalid line in the middle of the
    journal (every later reading fails). Now one line naming the file and the exact truncate that drops the partial
    record; the file is left as it was, and after that truncate the study resumes with its trials."""
    import re
    j = tmp_path / "optuna.log"
    run = ["run", "--storage", f"journal:{j}", "--studies-dir", tmp_path / "studies", "--data", data3, "--study", "s",
           "--num-features", "512", "--calibration-pairs", "2", "--no-test", "--quiet", "--jobs", "1"]
    env = {"IMTUNE_CACHE": str(tmp_path / "cache")}
    r = tune(*run, "--n-trials", "2", env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    raw = j.read_bytes()
    last = raw.rstrip(b"\n").rfind(b"\n") + 1  # the start of the last record
    cut = raw[: last + (len(raw) - last) // 2]
    j.write_bytes(cut)
    for argv in (run + ["--n-trials", "3"], ["studies", "--storage", f"journal:{j}"]):
        line = one_line_error(tune(*argv, env=env), f"journal storage {j} ends in a record cut short")
        assert j.read_bytes() == cut
    keep = int(re.search(r"`truncate -s (\d+) ", line).group(1))
    assert keep == last and f"`truncate -s {last} {j}`" in line
    os.truncate(j, keep)
    r = tune(*run, "--n-trials", "3", env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "trials: 3 complete" in r.stdout, r.stdout


def test_a_real_journal_still_opens(tmp_path):
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend
    j = tmp_path / "good.log"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    optuna.create_study(study_name="s", storage=JournalStorage(JournalFileBackend(str(j)))).optimize(
        lambda t: t.suggest_float("x", 0, 1), n_trials=1)
    r = tune("studies", "--storage", f"journal:{j}", "--studies-dir", tmp_path / "studies")
    assert r.returncode == 0 and "| s " in r.stdout, r.stderr


@pytest.mark.parametrize("bad", [b"not json at all\n", b'{"a": 1}\n', b"[1, 2]\n"])
def test_a_journal_damaged_in_the_middle_names_the_line(bad, tmp_path):
    """A journal with one damaged record among good ones said "is not an Optuna journal file, or is corrupt (...)"
    without saying where: the user had a file of thousands of lines to search. Now the first bad line's number."""
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend
    j = tmp_path / "good.log"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    optuna.create_study(study_name="s", storage=JournalStorage(JournalFileBackend(str(j)))).optimize(
        lambda t: t.suggest_float("x", 0, 1), n_trials=2)
    lines = j.read_bytes().splitlines(keepends=True)
    assert len(lines) > 5
    j.write_bytes(b"".join(lines[:4] + [bad] + lines[4:]))
    line = one_line_error(tune("studies", "--storage", f"journal:{j}", "--studies-dir", tmp_path / "studies"),
                          f"journal storage {j} is not an Optuna journal file, or is corrupt")
    assert "first at line 5)" in line, line


def _fifo(tmp: Path) -> Path:
    p = tmp / "fifo.log"
    os.mkfifo(p)
    return p


@pytest.mark.parametrize("cmd", ["studies", "run"])
@pytest.mark.parametrize("what,path,kind", [
    ("dev-null", lambda t: Path("/dev/null"), "is a device"),
    ("folder", lambda t: t, "is a folder"),
    ("fifo", _fifo, "is a FIFO"),  # opened for reading it blocks until a writer comes
])
def test_journal_path_that_is_not_a_regular_file_is_refused_unopened(what, path, kind, cmd, tmp_path, data3):
    p = path(tmp_path)
    extra = ["--data", data3, "--num-features", "512", "--n-trials", "1", "--no-test", "--quiet"] if cmd == "run" else []
    r = tune(cmd, "--storage", f"journal:{p}", "--studies-dir", tmp_path / "studies", *extra,
             env={"IMTUNE_CACHE": str(tmp_path / "cache")}, timeout=30)
    one_line_error(r, f"journal storage {p} {kind}")
    assert not Path(f"{p}.lock").exists() and not (tmp_path / "studies").exists()


def test_a_folder_at_the_journal_lock_is_refused_not_retried_forever(tmp_path, data3):
    """Optuna's journal lock is a symbolic link <journal>.lock it creates and removes (a stale one is released after
    30 s); a folder there made `tune run` wait those 30 s without a word, then Optuna renamed the user's folder away
    to <journal>.lock<uuid>.renamed. Now one line naming it, the folder left where it is."""
    j = tmp_path / "optuna.log"
    (tmp_path / "optuna.log.lock").mkdir()
    r = tune("run", "--storage", f"journal:{j}", "--studies-dir", tmp_path / "studies", "--data", data3,
             "--num-features", "512", "--n-trials", "1", "--no-test", "--quiet", timeout=90,
             env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, f"{j}.lock is a folder where journal storage {j} takes its lock")
    assert (tmp_path / "optuna.log.lock").is_dir() and not list(tmp_path.glob("*.renamed"))


def test_dev_full_as_journal_is_refused_before_reading(tmp_path, data3):
    # /dev/full reads endless zeros with no line end: Optuna read it until the OOM killer came; the address-space
    # limit makes an unfixed build fail within seconds with MemoryError instead (exit 1), never the machine
    import resource
    lim = 4 << 30

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))
    r = tune("run", "--storage", "journal:/dev/full", "--data", data3, "--studies-dir", tmp_path / "studies",
             "--num-features", "512", "--n-trials", "1", "--no-test", "--quiet", timeout=60, preexec_fn=limit,
             env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, "journal storage /dev/full is a device")


# -- 4. a studies folder that cannot be written ---------------------------------------------------------------

def _study_cmd(cmd: str, data: Path) -> list:
    if cmd == "run":
        return ["run", "--data", data, "--num-features", "512", "--n-trials", "1", "--no-test", "--quiet"]
    return ["calibrate", "--data", data, "--num-features", "512", "--quiet"]


@pytest.mark.parametrize("cmd", ["run", "calibrate"])
@pytest.mark.parametrize("how", ["under-a-file", "is-a-file", "env-under-a-file"])
def test_studies_folder_that_cannot_be_written_is_one_line(cmd, how, tmp_path, data3):
    f = tmp_path / "a-file"
    f.write_text("a file where a folder should be\n")
    folder = f if how == "is-a-file" else f / "studies"
    args, env = _study_cmd(cmd, data3), {"IMTUNE_CACHE": str(tmp_path / "cache")}
    if how.startswith("env"):
        env["IMTUNE_STUDIES"] = str(folder)  # ENOTDIR, as EROFS and EACCES: the folder cannot be made
    else:
        args += ["--studies-dir", folder]
    r = tune(*args, env=env)
    one_line_error(r, f"studies folder {folder}", "--studies-dir", "IMTUNE_STUDIES")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file"]  # nothing made, not even the cache


def test_budget_lock_in_a_folder_that_cannot_be_made_is_one_line(tmp_path):
    # the Python API's own guard (tune run / calibrate check the folder before): budgets.json.lock under a file
    from pipeline.errors import ImtuneError
    from tuner.budget import BUDGETS_FILE, _locked
    f = tmp_path / "a-file"
    f.write_text("x\n")
    with pytest.raises(ImtuneError, match=r"studies folder .*a-file/studies is not a folder.*--studies-dir"):
        with _locked(f / "studies" / BUDGETS_FILE):
            pass


def _can_mount() -> str | None:
    import shutil
    if os.geteuid() != 0 or not shutil.which("unshare"):
        return "needs root and unshare(1) to mount a private read-only tmpfs"
    r = subprocess.run(["unshare", "-m", "sh", "-c", "mount -t tmpfs -o ro,size=64k tmpfs /mnt"], capture_output=True)
    return None if r.returncode == 0 else f"cannot mount a tmpfs in a private namespace: {r.stderr.decode().strip()}"


@pytest.mark.parametrize("cmd", ["run", "calibrate"])
def test_studies_folder_on_a_read_only_file_system_is_one_line(cmd, tmp_path, data3):
    why = _can_mount()
    if why:
        pytest.skip(why)
    mnt = tmp_path / "ro"
    mnt.mkdir()
    tune_cmd = " ".join(f"'{a}'" for a in [sys.executable, "-m", "tuner", *_study_cmd(cmd, data3),
                                           "--studies-dir", mnt / "studies"])
    r = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o ro,size=64k tmpfs '{mnt}' || exit 99; "
                        f"exec {tune_cmd}"], capture_output=True, text=True, cwd=ROOT, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(ROOT), IMTUNE_CACHE=str(tmp_path / "cache")))
    one_line_error(r, f"studies folder {mnt / 'studies'} is not writable (Read-only file system)", "--studies-dir")


def test_a_full_disk_is_found_before_any_work(tmp_path):
    """A full tmpfs: the up-front folder checks (studies folder, cache folder) say "is full" and leave nothing,
    although an empty folder can still be made there (a new folder takes no block on tmpfs)."""
    why = _can_mount()
    if why:
        pytest.skip(why)
    mnt = tmp_path / "full"
    mnt.mkdir()
    code = ("from pipeline.fileio import check_writable_folder\n"
            "from pipeline.cache import H5Cache\n"
            "import os, sys\n"
            "os.mkdir(sys.argv[1] + '/still-makes-folders')\n"
            "os.rmdir(sys.argv[1] + '/still-makes-folders')\n"
            "for check in (lambda: check_writable_folder(sys.argv[1] + '/studies', 'studies folder', 'pass it'),\n"
            "              lambda: H5Cache(sys.argv[1] + '/cache').check_writable()):\n"
            "    try:\n"
            "        check()\n"
            "        print('NO ERROR')\n"
            "    except Exception as e:\n"
            "        print(e)\n"
            "print('LEFT', *sorted(os.listdir(sys.argv[1])))\n")
    r = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o size=64k tmpfs '{mnt}' || exit 99; "
                        f"dd if=/dev/zero of='{mnt}/fill' bs=4k count=64 2>/dev/null; "
                        f"exec '{sys.executable}' -c \"$0\" '{mnt}'", code],
                       capture_output=True, text=True, cwd=ROOT, timeout=120, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].startswith(f"studies folder {mnt / 'studies'} is full (No space left on device)"), r.stdout
    assert lines[1].startswith(f"cache folder {mnt / 'cache'} is full (No space left on device)"), r.stdout
    assert "--cache" in lines[1] and lines[2] == "LEFT fill", r.stdout


# -- 5. tune viz --out on a file, or where nothing can be written ---------------------------------------------

VIZ = ["viz", "--num-features", "512", "--scenes", "fountain-P11", "--worst", "1", "--best", "0", "--random", "0",
       "--quiet"]


@pytest.mark.parametrize("how", ["existing-file", "under-a-file"])
def test_viz_out_that_is_no_writable_folder_is_one_line(how, tmp_path, data3):
    f = tmp_path / "a-file"
    f.write_text("x\n")
    out = f if how == "existing-file" else f / "viz"
    r = tune(*VIZ, "--data", data3, "--out", out, env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, f"--out folder {out} is not a folder", "give --out a folder")
    assert f.read_text() == "x\n" and sorted(p.name for p in tmp_path.iterdir()) == ["a-file"]


def test_viz_gallery_in_a_folder_that_cannot_be_made_is_one_line(tmp_path, data3):
    f = tmp_path / "a-file"
    f.write_text("x\n")
    r = tune(*VIZ, "--data", data3, "--out", tmp_path / "viz", "--gallery", f / "g.html",
             env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, f"gallery folder {f} is not a folder", "--no-gallery")


def test_viz_out_on_a_read_only_file_system_is_one_line(tmp_path, data3):
    why = _can_mount()
    if why:
        pytest.skip(why)
    mnt = tmp_path / "ro"
    mnt.mkdir()
    cmd = " ".join(f"'{a}'" for a in [sys.executable, "-m", "tuner", *VIZ, "--data", data3, "--out", mnt / "viz"])
    r = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o ro,size=64k tmpfs '{mnt}' || exit 99; "
                        f"exec {cmd}"], capture_output=True, text=True, cwd=ROOT, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(ROOT), IMTUNE_CACHE=str(tmp_path / "cache")))
    one_line_error(r, f"--out folder {mnt / 'viz'} is not writable (Read-only file system)")


# -- 6. --ci-resamples has an upper bound ------------------------------------------------------------------------

@pytest.mark.parametrize("cmd", [["evaluate", "--num-features", "512"], ["compare", "A", "B"], ["test", "--study", "X"],
                                 ["run", "--num-features", "512", "--n-trials", "1", "--no-test"]])
def test_ci_resamples_beyond_the_bound_is_refused_while_parsing(cmd, tmp_path, data3):
    # 99,999,999,999 resamples asked scipy's bootstrap for 2 TiB: MemoryError after the whole evaluation
    r = tune(*cmd, "--data", data3, "--scenes", "fountain-P11", "--quiet", "--ci-resamples", "99999999999",
             env={"IMTUNE_CACHE": str(tmp_path / "cache"), "IMTUNE_STUDIES": str(tmp_path / "studies")})
    one_line_error(r, "argument --ci-resamples: must be at most 100,000", "99999999999")


def test_ci_resamples_at_the_bound_parses():
    from tuner.argtypes import MAX_RESAMPLES
    from tuner.cli import build_parser
    ap = build_parser()
    for argv in (["evaluate"], ["compare", "A", "B"], ["test", "--study", "X"], ["run"]):
        assert ap.parse_args([*argv, "--ci-resamples", str(MAX_RESAMPLES)]).ci_resamples == MAX_RESAMPLES



@pytest.mark.parametrize("cmd", [["evaluate", "--num-features", "512"], ["compare", "A", "B"], ["test", "--study", "X"],
                                 ["run", "--num-features", "512", "--n-trials", "1", "--no-test"], ["findings"]])
@pytest.mark.parametrize("n", ["1", "99"])
def test_too_few_ci_resamples_are_refused_by_every_command(n, cmd, tmp_path, data3):
    """`tune compare --ci-resamples 1` printed mAA10 0.8667 [0.8000, 0.8000] and B - A +0.1000 [+0.2000, +0.2000]
    (intervals missing their own estimate) and numpy warnings; evaluate / test / run refused fewer than 100."""
    r = tune(*cmd, "--data", data3, "--quiet", "--ci-resamples", n,
             env={"IMTUNE_CACHE": str(tmp_path / "cache"), "IMTUNE_STUDIES": str(tmp_path / "studies")})
    one_line_error(r, "argument --ci-resamples: must be >= 100 for a 95% interval", n)
    from tuner.argtypes import MIN_RESAMPLES
    from tuner.cli import build_parser
    assert build_parser().parse_args([*cmd, "--ci-resamples", str(MIN_RESAMPLES)]).ci_resamples == MIN_RESAMPLES

# -- 7. a download base URL that is no URL ---------------------------------------------------------------------

@pytest.mark.parametrize("base", ["not a url", "ftp//mirror/x", "/srv/mirror", f"htp://u:{SECRET}@mirror/x",
                                  "http://mirror:port/x", "http://"])
@pytest.mark.parametrize("how", ["option", "env"])
def test_download_base_url_that_is_no_url_is_one_line(base, how, tmp_path):
    dest = tmp_path / "dest"
    if how == "option":
        r = tune("data", "download", "strecha", "--dest", dest, "--base-url", base, "--quiet")
        where = "--base-url"
    else:
        r = tune("data", "download", "strecha", "--dest", dest, "--quiet", env={"IMTUNE_DOWNLOAD_BASE": base})
        where = "$IMTUNE_DOWNLOAD_BASE"
    line = one_line_error(r, f"{where} '", "is not a download URL", "http://HOST/PATH", "file:///PATH")
    assert SECRET not in r.stdout + r.stderr, line
    assert not dest.exists()


def test_download_progress_line_never_shows_a_mirror_password():
    from pipeline.data.download import describe_source
    shown = describe_source("strecha", f"http://u:{SECRET}@127.0.0.1:8/mirror")
    assert shown.endswith("from 127.0.0.1:8") and SECRET not in shown, shown


# -- 8. tune data build-gt: camera model and image size -----------------------------------------------------------

def test_build_gt_unknown_camera_model_lists_pycolmaps(tmp_path, data3):
    import pycolmap
    r = tune("data", "build-gt", "--data", data3, "--method", "sfm", "--gt-dir", tmp_path / "gt", "--camera-model",
             "BOGUS", "--num-features", "256", "--quiet", env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    known = [n for n in pycolmap.CameraModelId.__members__ if n != "INVALID"]
    assert "SIMPLE_PINHOLE" in known and "OPENCV" in known
    one_line_error(r, "unknown COLMAP camera model 'BOGUS'", "choose from " + ", ".join(known))
    assert not (tmp_path / "gt").exists()


def test_build_gt_camera_model_names_are_pycolmaps():
    import pycolmap

    from pipeline.data.ground_truth import GTConfig, camera_models
    from pipeline.errors import ImtuneError
    assert camera_models() == [n for n in pycolmap.CameraModelId.__members__ if n != "INVALID"]
    for name in camera_models():
        GTConfig(camera_model=name)
    with pytest.raises(ImtuneError, match=r"'pinhole' \(did you mean 'PINHOLE'"):
        GTConfig(camera_model="pinhole")
    for size in (0, -5, 2.5):
        with pytest.raises(ImtuneError, match="max_image_size"):
            GTConfig(max_image_size=size)


@pytest.mark.parametrize("size", ["0", "-5"])
def test_build_gt_non_positive_image_size_is_refused(size, tmp_path, data3):
    r = tune("data", "build-gt", "--data", data3, "--gt-dir", tmp_path / "gt", "--num-features", "256", "--quiet",
             f"--max-image-size={size}", env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, "argument --max-image-size: must be >= 1", size)
    assert not (tmp_path / "gt").exists()



@pytest.mark.parametrize("scenes,needle", [(",", "',' names no scene"),
                                           ("fountain-P11,fountain-P11", "scene 'fountain-P11' is named twice")])
def test_build_gt_scenes_naming_no_scene_is_refused(scenes, needle, tmp_path, data3):
    """`tune data build-gt --scenes ,` built every scene of the data (minutes each) without a word: the list named none;
    the other commands' --scenes refused it. Now the same one line, before any build."""
    r = tune("data", "build-gt", "--data", data3, "--gt-dir", tmp_path / "gt", "--num-features", "256", "--quiet",
             "--scenes", scenes, env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, "argument --scenes: ", needle)
    assert not (tmp_path / "gt").exists()


@pytest.mark.parametrize("json_out", [False, True])
def test_build_gt_on_a_folder_without_scenes_is_one_line(json_out, tmp_path):
    """An empty folder (or one of other files) was exit 0 with nothing printed: a build that did nothing, unsaid."""
    (tmp_path / "empty").mkdir()
    r = tune("data", "build-gt", "--data", tmp_path / "empty", "--gt-dir", tmp_path / "gt", "--quiet",
             *(["--json"] if json_out else []), env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, f"no scenes in {tmp_path / 'empty'}", "tune data scenes")
    assert not (tmp_path / "gt").exists()

# -- 9. invalid calibrations in budgets.json -----------------------------------------------------------------------

def _calibrate(data: Path, sdir: Path, cache: Path, *extra):
    return tune("calibrate", "--data", data, "--num-features", "512", "--ransac", "cv-ransac", "--budget", "0.002",
                "--pairs", "2", "--jobs", "1", "--studies-dir", sdir, "--quiet", *extra,
                env={"IMTUNE_CACHE": str(cache)})


@pytest.fixture(scope="module")
def budgets(tmp_path_factory, data3):
    """A real budgets.json (a calibration measured here, ~1 s) and its cache: (json text, cache folder)."""
    tmp = tmp_path_factory.mktemp("bad-files-budgets")
    r = _calibrate(data3, tmp / "studies", tmp / "cache")
    assert r.returncode == 0, r.stderr
    return (tmp / "studies" / "budgets.json").read_text(), tmp / "cache"


def _curve_median(c, v):
    if len(c["curve"]) < 2:  # a loaded machine: the first cap was already over the tiny budget, one point measured
        cap, med, p90 = c["curve"][0]
        c["curve"].append([cap * 2, med, p90])
    c["curve"][1][1] = v


def _curve_cap(c, v):
    c["curve"][0][0] = v


def _all_medians(c, v):
    for pt in c["curve"]:
        pt[1] = pt[2] = v


BAD_CALIBRATIONS = {  # name -> (change, what the message says)
    "median-nan": (lambda c: _curve_median(c, float("nan")), "curve[1]: the median seconds"),
    "median-string": (lambda c: _curve_median(c, "fast"), "curve[1]: the median seconds"),
    "medians-negative": (lambda c: _all_medians(c, -0.5), "curve[0]: the median seconds"),  # was Gamma_max 1
    "cap-negative": (lambda c: _curve_cap(c, -100), "curve[0]: the cap max_iters"),
    "cap-nan": (lambda c: _curve_cap(c, float("nan")), "curve[0]: the cap max_iters"),
    "ceiling-negative": (lambda c: c.update(ceiling=-5), "'ceiling' must be a positive integer"),
    "ceiling-string": (lambda c: c.update(ceiling="1e6"), "'ceiling' must be a positive integer"),
    "curve-empty": (lambda c: c.update(curve=[]), "'curve' must be a non-empty list"),
    "not-a-mapping": (None, "expected a mapping"),
}


def _spoil(sdir: Path, text: str, case: str) -> str:
    import json
    store = json.loads(text)
    (key,) = store
    change, _ = BAD_CALIBRATIONS[case]
    if change is None:
        store[key] = [1, 2, 3]
    else:
        change(store[key])
    sdir.mkdir(parents=True, exist_ok=True)
    (sdir / "budgets.json").write_text(json.dumps(store))
    return key


@pytest.mark.parametrize("case", list(BAD_CALIBRATIONS))
def test_invalid_stored_calibration_is_one_line_never_used(case, budgets, tmp_path, data3):
    text, cache = budgets
    sdir = tmp_path / "studies"
    key = _spoil(sdir, text, case)
    r = _calibrate(data3, sdir, cache)
    one_line_error(r, f"{sdir / 'budgets.json'}: the stored calibration {key!r} is invalid", BAD_CALIBRATIONS[case][1],
                   "delete that entry", "tune calibrate --force")


@pytest.mark.parametrize("case", ["medians-negative", "median-nan"])
def test_tune_run_never_uses_an_invalid_calibration(case, budgets, tmp_path, data3):
    # negative times gave Gamma_max = 1 silently: every trial ran with Gamma 1 under a false "search ceiling" warning
    text, cache = budgets
    sdir = tmp_path / "studies"
    key = _spoil(sdir, text, case)
    r = tune("run", "--data", data3, "--num-features", "512", "--ransac", "cv-ransac", "--jobs", "1", "--n-trials", "1",
             "--no-test", "--quiet", "--studies-dir", sdir, "--storage", f"sqlite:///{tmp_path}/optuna.db",
             env={"IMTUNE_CACHE": str(cache)})
    one_line_error(r, f"the stored calibration {key!r} is invalid", "tune run --recalibrate")


def test_force_measures_an_invalid_calibration_again(budgets, tmp_path, data3):
    import json
    text, cache = budgets
    sdir = tmp_path / "studies"
    key = _spoil(sdir, text, "median-nan")
    r = _calibrate(data3, sdir, cache, "--force")
    assert r.returncode == 0, r.stderr
    from tuner.budget import calibration_problem
    assert calibration_problem(json.loads((sdir / "budgets.json").read_text())[key]) is None


DAMAGED_STORES = {  # name -> (bytes, what the message says)
    "truncated": (None, "is not valid JSON"),
    "a-list": (b"[1, 2]\n", "a JSON list, not an object of calibrations"),
    "binary": (b"\x89PNG\r\n\x1a\n\x00\x00", "is not valid JSON (byte 0x89 at offset 0"),
}


@pytest.mark.parametrize("case", list(DAMAGED_STORES))
@pytest.mark.parametrize("force", [False, True])
def test_a_damaged_budgets_json_is_one_line_and_kept(case, force, budgets, tmp_path, data3):
    """A budgets.json that is no JSON object: one line naming it, before any measuring, and the file left as it was
    (it was silently replaced by a file holding only the next calibration: every other one lost)."""
    text, cache = budgets
    sdir = tmp_path / "studies"
    sdir.mkdir()
    raw = DAMAGED_STORES[case][0]
    raw = text.encode()[: len(text) // 2] if raw is None else raw  # a copy cut short
    (sdir / "budgets.json").write_bytes(raw)
    r = _calibrate(data3, sdir, cache, *(["--force"] if force else []))
    one_line_error(r, f"{sdir / 'budgets.json'}", DAMAGED_STORES[case][1], "delete it")
    assert (sdir / "budgets.json").read_bytes() == raw
    r = tune("run", "--data", data3, "--num-features", "512", "--ransac", "cv-ransac", "--jobs", "1", "--n-trials",
             "1", "--no-test", "--quiet", "--studies-dir", sdir, "--storage", f"sqlite:///{tmp_path}/optuna.db",
             env={"IMTUNE_CACHE": str(cache)})
    one_line_error(r, f"{sdir / 'budgets.json'}", DAMAGED_STORES[case][1])
    assert (sdir / "budgets.json").read_bytes() == raw


# -- 10. a frozen.yaml whose numbers are not sound -------------------------------------------------------------------

FROZEN = """\
study: X
trial: 3
value: 0.75
task: stereo
task_options: {{min_covisibility: 0.1, max_pairs: null}}
feature: sift
num_features: 512
ransac: cv-ransac
params: {{max_iters: 20000, ratio: 0.8, threshold: 1.0}}
fixed: {{strategy: both}}
config:
  feature: {{name: sift, num_features: 512}}
  matching: {{ratio: 0.8, strategy: both}}
  geometry: {{ransac: cv-ransac, threshold: 1.0, max_iters: 20000, seed: 0}}
budget: {{seconds_per_pair: 0.5, test_seconds_per_pair: 1.0, gamma_max: 50000, gamma_max_test: 100000}}
data: {{root: {root}, val_scenes: [fountain-P11], test_scenes: [fountain-P11]}}
validation: {{mAA10: 0.75, mAA5: 0.5, ransac_seconds: 0.01, ransac_seconds_median: 0.01, pairs: 3}}
"""

BAD_FROZEN = {  # (text to replace, replacement, the key named)
    "value-nan": ("value: 0.75", "value: .nan", "value must be a finite number"),
    "gamma-max-inf": ("gamma_max: 50000", "gamma_max: .inf", "budget.gamma_max must be a positive integer"),
    "gamma-max-zero": ("gamma_max: 50000", "gamma_max: 0", "budget.gamma_max must be a positive integer"),
    "budget-negative": ("seconds_per_pair: 0.5", "seconds_per_pair: -1", "budget.seconds_per_pair must be a finite"),
    "test-budget-nan": ("test_seconds_per_pair: 1.0", "test_seconds_per_pair: .nan", "budget.test_seconds_per_pair"),
    "max-iters-1e5": ("params: {max_iters: 20000", "params: {max_iters: 1e5", "params.max_iters must be a positive integer"),
    "seconds-negative": ("ransac_seconds: 0.01", "ransac_seconds: -3", "validation.ransac_seconds must be a finite"),
    "validation-inf": ("mAA5: 0.5", "mAA5: .inf", "validation.mAA5 must be a finite number"),
    "key-twice": ("value: 0.75", "value: 0.75\nvalue: 0.99", "key 'value' is given twice (lines 3 and 4)"),
}


def _frozen_text(data: Path, case: str | None = None) -> str:
    text = FROZEN.format(root=data)
    if case:
        old, new, _ = BAD_FROZEN[case]
        assert old in text
        text = text.replace(old, new, 1)
    return text


def test_the_sound_frozen_file_loads(tmp_path, data3):
    from tuner.freeze import load_frozen
    sdir = _frozen_study(tmp_path, _frozen_text(data3))
    assert load_frozen(sdir, "X")["budget"]["gamma_max"] == 50000


@pytest.mark.parametrize("case", list(BAD_FROZEN))
def test_tune_test_refuses_a_frozen_file_with_unsound_numbers(case, tmp_path, data3):
    sdir = _frozen_study(tmp_path, _frozen_text(data3, case))
    r = tune("test", "--study", "X", "--studies-dir", sdir, "--storage", f"sqlite:///{tmp_path}/none.db", "--runs", "1",
             "--max-pairs", "2", "--reference", "none", "--ci", "none", "--jobs", "1", "--quiet",
             env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, f"{sdir / 'X' / 'frozen.yaml'}: {BAD_FROZEN[case][2]}")
    assert not (sdir / "X" / "test.json").exists()


@pytest.mark.parametrize("case", ["gamma-max-inf", "budget-negative"])
def test_a_frozen_file_given_as_config_is_checked_too(case, tmp_path, data3):
    f = tmp_path / "frozen.yaml"
    f.write_text(_frozen_text(data3, case))
    r = tune("evaluate", "--config", f, "--data", data3, "--quiet", env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, f"{f}: {BAD_FROZEN[case][2]}")



@pytest.mark.parametrize("task", ["foo"])  # a task that is no name: test_a_frozen_file_of_the_wrong_shape_...
def test_a_frozen_files_unknown_task_names_the_file(task, tmp_path, data3):
    """`tune evaluate --config frozen.yaml` takes the file's task: an unknown one said "unknown task 'foo'" with no
    word of the file it came from."""
    f = tmp_path / "frozen.yaml"
    f.write_text(_frozen_text(data3).replace("task: stereo", f"task: {task}", 1))
    r = tune("evaluate", "--config", f, "--data", data3, "--quiet", env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, f"--config {f}: task: unknown task")


FROZEN_SHAPES = {  # (text to replace, replacement, what the line says): a frozen file cut short or hand-edited
    # `tune test` of the frozen file alone: "tune: internal error: AttributeError: 'str' object has no attribute 'get'"
    "budget-text": ("budget: {seconds_per_pair: 0.5, test_seconds_per_pair: 1.0, gamma_max: 50000, "
                    "gamma_max_test: 100000}", "budget: fast", "budget must be a mapping, got 'fast'"),
    "data-list": ("data: {root: ", "data: [here]\nunused: {root: ", "data must be a mapping, got ['here']"),
    "task-options-text": ("task_options: {min_covisibility: 0.1, max_pairs: null}", "task_options: all",
                          "task_options must be a mapping, got 'all'"),
    "task-list": ("task: stereo", "task: [stereo]", "task must be a task name, got ['stereo']"),
    # "scene 'n' is named twice (f, o, u, n, t, a, i, n, ...)": a string read as a list of characters
    "test-scenes-text": ("test_scenes: [fountain-P11]", "test_scenes: fountain-P11",
                         "data.test_scenes must be a list of scene names, got 'fountain-P11'"),
    # "holds the frozen settings of study None, not 'X' (copied from another study?)"
    "no-study": ("study: X\n", "", "no study (cut short"),
    # `tune test` without --max-pairs silently tested every pair (73 for fountain) instead of failing
    "max-pairs-text": ("max_pairs: null}", "max_pairs: x}", "task_options.max_pairs must be a positive integer"),
    # "co-visibility must be a number, got 'lots'": no word of which file
    "covisibility-text": ("{min_covisibility: 0.1,", "{min_covisibility: lots,",
                          "task_options.min_covisibility must be a number in [0, 1], got 'lots'"),
    # "configuration: num_features must be a number": no word of which file
    "config-value": ("feature: {name: sift, num_features: 512}", "feature: {name: sift, num_features: many}",
                     "num_features must be a number, got 'many'"),
    # "not a frozen-settings file (no 'config')" of a file that is empty
    "empty": (None, "", "is empty (cut short?)"),
}


@pytest.mark.parametrize("case", list(FROZEN_SHAPES))
def test_a_frozen_file_of_the_wrong_shape_is_one_line_naming_it(case, tmp_path, data3):
    old, new, needle = FROZEN_SHAPES[case]
    text = _frozen_text(data3)
    assert old is None or old in text
    sdir = _frozen_study(tmp_path, new if old is None else text.replace(old, new, 1))
    frozen = sdir / "X" / "frozen.yaml"
    before = frozen.read_bytes()
    r = tune("test", "--study", "X", "--studies-dir", sdir, "--storage", f"sqlite:///{tmp_path}/none.db", "--runs", "1",
             "--max-pairs", "2", "--reference", "none", "--ci", "none", "--jobs", "1", "--quiet",
             env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, str(frozen), needle)
    assert not (sdir / "X" / "test.json").exists() and frozen.read_bytes() == before
    if case in ("budget-text", "task-list", "test-scenes-text"):  # the same line from every reader of the study
        for argv in (["evaluate", "--config", "X", "--data", data3], ["compare", "X", "X", "--data", data3],
                     ["viz", "--study", "X", "--data", data3, "--out", tmp_path / "viz"]):
            r = tune(*argv, "--studies-dir", sdir, "--quiet", env={"IMTUNE_CACHE": str(tmp_path / "cache")})
            one_line_error(r, str(frozen), needle)


@pytest.mark.parametrize("cmd", ["evaluate", "compare", "viz"])
def test_a_frozen_file_that_is_a_folder_is_named_as_one(cmd, tmp_path, data3):
    """A folder named frozen.yaml in a study's folder: "'X' is neither a config file nor a study with frozen
    settings (.../frozen.yaml does not exist)" -- it does exist, as a folder."""
    sdir = tmp_path / "studies"
    frozen = sdir / "X" / "frozen.yaml"
    (frozen / "inside").mkdir(parents=True)
    argv = {"evaluate": ["evaluate", "--config", "X"], "compare": ["compare", "X", "X"],
            "viz": ["viz", "--study", "X", "--out", tmp_path / "viz"]}[cmd]
    r = tune(*argv, "--data", data3, "--studies-dir", sdir, "--quiet", env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, f"{frozen} is a folder")
    assert (frozen / "inside").is_dir()


# -- a configuration file's values of the wrong type (YAML config and IMC method JSON) ------------------------

_IMC_STEREO = '"config_phototourism_stereo": {"geom": {"method": "cmp-degensac-f", "threshold": 0.5}%s}'
BAD_CONFIG_VALUES = {  # name: (file name, text, what the error line says)
    "upright-quoted-false": ("c.yaml", 'feature: {num_features: 512, upright: "false"}', "upright must be true or false"),
    "fginn-string": ("c.yaml", "matching: {fginn: maybe}", "fginn must be true or false, got 'maybe'"),
    "low-threshold-off-string": ("c.yaml", 'feature: {low_threshold: "off"}', "low_threshold must be true or false"),
    "max-side-negative": ("c.yaml", "feature: {max_side: -5}", "max_side must be >= 0"),
    "num-features-fraction": ("c.yaml", "feature: {num_features: 512.5}", "num_features must be an integer"),
    "options-number": ("c.yaml", "feature: {options: 5}", "feature.options must be a mapping"),
    "options-triple": ("c.yaml", "feature: {options: [[a, 1, 2]]}", "feature.options must be a mapping"),
    "options-flat-list": ("c.yaml", "feature: {options: [5]}", "feature.options must be a mapping"),
    "custom-matches-number": ("c.yaml", "matching: {custom_matches: 5}", "custom_matches must be a string"),
    # the pre-filter's own option check said "prefilter 'gms': unknown option(s) bogus" without naming the file
    "prefilter-option-unknown": ("c.yaml", "matching: {prefilter: gms, prefilter_options: {bogus: 1}}",
                                 "prefilter 'gms': unknown option(s) bogus"),
    "imc-num-keypoints-text": ("m.json", '{"config_common": {"num_keypoints": "many"}, %s}' % (_IMC_STEREO % ""),
                               "num_features must be a number, got 'many'"),
    "imc-common-not-object": ("m.json", '{"config_common": "sift", %s}' % (_IMC_STEREO % ""),
                              "config_common must be an object"),
    "imc-matcher-not-object": ("m.json", '{"config_common": {}, %s}' % (_IMC_STEREO % ', "matcher": "nn"'),
                               "config_phototourism_stereo.matcher must be an object"),
    "imc-ratio-nan": ("m.json", '{"config_common": {}, %s}' % (_IMC_STEREO % ', "matcher": {"filtering": '
                                                               '{"type": "snn_ratio_pairwise", "threshold": NaN}}'),
                      "ratio r must be a finite number"),
    "imc-threshold-text": ("m.json", '{"config_common": {}, "config_phototourism_stereo": {"geom": '
                                     '{"method": "cmp-degensac-f", "threshold": "x"}}}', "inlier threshold must be a number"),
    "imc-max-iter-fraction": ("m.json", '{"config_common": {}, "config_phototourism_stereo": {"geom": '
                                        '{"method": "cmp-degensac-f", "max_iter": 1000.5}}}', "max-iters must be an integer"),
    # the outlier filter was ignored: the method evaluated without its CNe, unsaid
    "imc-outlier-filter-cne": ("m.json", '{"config_common": {}, %s}' % (_IMC_STEREO % ', "outlier_filter": '
                                                                         '{"method": "cne-bp-nd"}'),
                               "cne needs trained weights"),
    # an unknown filtering type was no ratio test at all, L1 was L2, num_nn 3 one neighbour: each unsaid
    "imc-filtering-type-unknown": ("m.json", '{"config_common": {}, %s}' % (_IMC_STEREO % ', "matcher": {"filtering": '
                                                                             '{"type": "snn_ratio", "threshold": 0.8}}'),
                                   "filtering: type 'snn_ratio' is not supported"),
    "imc-distance-l1": ("m.json", '{"config_common": {}, %s}' % (_IMC_STEREO % ', "matcher": {"distance": "L1"}'),
                        "matcher: distance 'L1' is not supported"),
    "imc-num-nn-3": ("m.json", '{"config_common": {}, %s}' % (_IMC_STEREO % ', "matcher": {"num_nn": 3}'),
                     "matcher: num_nn 3 is not supported"),
    # the method's own matches were replaced by imtune's matcher (r 1, no ratio test), unsaid
    "imc-use-custom-matches": ("m.json", '{"config_common": {}, %s}' % (_IMC_STEREO % ', "use_custom_matches": true'),
                               "use_custom_matches is true: the method's matches are its own h5 files"),
    "imc-outlier-filter-unknown": ("m.json", '{"config_common": {}, %s}' % (_IMC_STEREO % ', "outlier_filter": '
                                                                             '{"method": "magic"}'),
                                   "outlier_filter: method 'magic' is not supported (supported: none, cne-bp-nd)"),
}


@pytest.mark.parametrize("case", list(BAD_CONFIG_VALUES))
def test_config_value_of_the_wrong_type_is_one_line_naming_the_file(case, tmp_path, data3):
    """A quoted "false" was truthy (the option silently on), NaN became r = 1 (no ratio test), and the rest were
    an internal error (TypeError, ValueError, AttributeError)."""
    name, text, needle = BAD_CONFIG_VALUES[case]
    f = tmp_path / name
    f.write_text(text + "\n")
    r = tune("evaluate", "--config", f, "--data", data3, "--quiet", "--jobs", "1",
             env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, f"{f}: ", needle)


def test_integral_floats_in_a_config_are_integers(tmp_path, data3):
    """YAML's ``num_features: 512.0`` / ``max_iters: 100.0`` are the integers (they reached OpenCV as floats: an
    internal error), and the label shows Γ 100, not 100.0."""
    f = tmp_path / "c.yaml"
    f.write_text("feature: {num_features: 512.0}\ngeometry: {max_iters: 100.0, seed: 3.0}\n")
    r = tune("evaluate", "--config", f, "--data", data3, "--quiet", "--jobs", "1", "--ci", "none",
             env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Γ 100)" in r.stdout and "100.0" not in r.stdout.splitlines()[0], r.stdout[:500]
    from pipeline.config_files import load_config_file
    conf = load_config_file(f).conf
    assert (type(conf.feature.num_features), type(conf.geometry.max_iters), type(conf.geometry.seed)) == (int,) * 3



def test_imc_method_with_config_common_null_is_read_as_empty(tmp_path, data3):
    """``"config_common": null`` was taken as no section when reading the method, then an internal error
    (AttributeError: 'NoneType' object has no attribute 'get') when labelling it."""
    f = tmp_path / "m.json"
    f.write_text('{"config_common": null, %s}\n' % (_IMC_STEREO % ""))
    r = tune("evaluate", "--config", f, "--data", data3, "--num-features", "512", "--quiet", "--jobs", "1",
             "--ci", "none", env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"config {f} (m: sift" in r.stdout.splitlines()[0], r.stdout[:500]

# -- tune plot --out that cannot be written ---------------------------------------------------------------

@pytest.mark.parametrize("page", [["--study", "plots-a"], ["--pareto", "plots-a"]])
@pytest.mark.parametrize("how", ["under-a-file", "is-a-folder", "a-png-name"])
def test_plot_out_that_cannot_be_written_is_one_line_before_drawing(how, page, tmp_path):
    """A file in the way of --out's folder was an internal error (FileExistsError from mkdir)."""
    from tests.test_plots_labels import _study
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    _study(storage, "plots-a")
    (tmp_path / "afile").write_text("x")
    out, needle = {"under-a-file": (tmp_path / "afile" / "r.html", "a file is in the way"),
                   "is-a-folder": (tmp_path, "is a folder"),
                   # an HTML page was written under a picture's name
                   "a-png-name": (tmp_path / "p.png", "writes an interactive HTML page (plotly); name it .html")}[how]
    r = tune("plot", *page, "--storage", storage, "--studies-dir", tmp_path / "studies", "--out", out)
    one_line_error(r, "--out", needle)
    assert (tmp_path / "afile").read_text() == "x" and not (tmp_path / "p.png").exists()


@pytest.mark.parametrize("page,default", [(["--study", "plots-a"], "plots-a/report.html"),
                                          (["--pareto", "plots-a"], "pareto.html")])
def test_plot_default_page_that_is_a_folder_is_one_line_and_kept(page, default, tmp_path):
    """A folder where the study's report.html (or pareto.html) goes said "cannot write ...: Is a directory" after
    drawing the page, with no word of what to do."""
    from tests.test_plots_labels import _study
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    _study(storage, "plots-a")
    folder = tmp_path / "studies" / default
    (folder / "inside").mkdir(parents=True)
    r = tune("plot", *page, "--storage", storage, "--studies-dir", tmp_path / "studies")
    one_line_error(r, f"{folder} is a folder where tune plot writes its page", "move it away, or give --out")
    assert (folder / "inside").is_dir()


@pytest.mark.parametrize("text,key", [("config:\n  feature: {num_features: 512}\ngeometry: {threshold: 2.0}\n", "geometry"),
                                      ("config:\n  feature: {num_features: 512}\nratio: 0.7\n", "ratio"),
                                      ("config:\n  feature: {num_features: 512}\nmax-iters: 10\n", "max-iters")])
def test_values_beside_config_are_refused_not_ignored(text, key, tmp_path, data3):
    """`geometry: {threshold: 2.0}` or `ratio: 0.7` next to `config:` was read as nothing: the evaluation ran with
    eta 0.5 and r 1 and said so only in its header. A frozen.yaml (study + trial) keeps its descriptive keys."""
    f = tmp_path / "c.yaml"
    f.write_text(text)
    r = tune("evaluate", "--config", f, "--data", data3, "--quiet", "--jobs", "1",
             env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, f"{f}: {key!r} is beside 'config:'", "move it under config:")
    from pipeline.config_files import load_config_file
    frozen = tmp_path / "frozen.yaml"
    frozen.write_text("study: s\ntrial: 1\nfeature: sift\nnum_features: 512\nransac: degensac\n" + text.split("\n", 2)[0]
                      + "\n  feature: {num_features: 512}\n")
    assert load_config_file(frozen).kind == "frozen"


# -- a key given twice: YAML and JSON keep the last without a word ---------------------------------------------

@pytest.mark.parametrize("name,text,needle", [
    ("c.yaml", "geometry: {threshold: 2.0}\nfeature: {num_features: 512}\ngeometry: {max_iters: 100}\n",
     "key 'geometry' is given twice (lines 1 and 3)"),  # ran with eta 0.5: the threshold was dropped
    ("c.yaml", "geometry: {threshold: 1.0, threshold: 2.0}\n", "key 'threshold' is given twice (lines 1 and 1)"),
    ("c.json", '{"geometry": {"threshold": 2.0}, "geometry": {"max_iters": 100}}', "key 'geometry' is given twice"),
])
def test_config_file_key_given_twice_is_one_line(name, text, needle, tmp_path, data3):
    f = tmp_path / name
    f.write_text(text)
    r = tune("evaluate", "--config", f, "--data", data3, "--quiet", "--jobs", "1",
             env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, f"{f}: {needle}", "write it once")


def test_search_space_or_splits_key_given_twice_is_one_line(tmp_path, data3):
    """A search space listing ratio twice (a range, then a scalar) searched with ratio pinned to the scalar."""
    space = tmp_path / "space.yaml"
    space.write_text("params:\n  ratio: {type: float, low: 0.6, high: 1.0}\n  threshold: {type: float, low: 0.1, "
                     "high: 2.0}\n  ratio: 0.8\n")
    env = {"IMTUNE_CACHE": str(tmp_path / "cache")}
    r = tune("run", "--data", data3, "--space", space, "--studies-dir", tmp_path / "st", "--n-trials", "1", "--quiet",
             env=env)
    one_line_error(r, f"search space {space}: key 'ratio' is given twice (lines 2 and 4)")
    assert not (tmp_path / "st" / "optuna.db").exists()
    import shutil
    data = tmp_path / "data"
    shutil.copytree(data3, data)
    (data / "splits.yaml").write_text("val: [fountain-P11]\ntest: []\nval: []\n")
    r = tune("data", "scenes", "--data", data, env=env)
    one_line_error(r, f"{data / 'splits.yaml'}: key 'val' is given twice (lines 1 and 3)")


def test_yaml_merge_keys_are_no_duplicates():
    from pipeline.fileio import load_yaml
    assert load_yaml("a: &x {t: 1}\nb:\n  <<: *x\n  m: 2\n", "f") == {"a": {"t": 1}, "b": {"t": 1, "m": 2}}


@pytest.mark.parametrize("text,needle", [
    # every match filtered: every pair failed, mAA 0, exit 0
    ("matching: {prefilter: gms, prefilter_options: {threshold: .inf}}\n", "prefilter 'gms': option threshold=inf"),
    ("feature: {name: orb, options: {n_levels: .inf}}\n", "feature 'orb': option n_levels=inf"),  # OverflowError
    ("feature: {options: {edge_threshold: .nan}}\n", "feature 'sift': option edge_threshold=nan"),
])
def test_non_finite_extractor_or_prefilter_option_in_a_file_is_one_line(text, needle, tmp_path, data3):
    """--feature-option refuses nan / inf while parsing; the same values from a configuration file reached the
    extractor or pre-filter."""
    f = tmp_path / "c.yaml"
    f.write_text("feature: {num_features: 512}\n" + text if not text.startswith("feature") else
                 text.replace("{", "{num_features: 512, ", 1))
    r = tune("evaluate", "--config", f, "--data", data3, "--quiet", "--jobs", "1", "--ci", "none",
             env={"IMTUNE_CACHE": str(tmp_path / "cache")})
    one_line_error(r, needle, "must be a finite number")


@pytest.mark.parametrize("attr", ["budget", "pipeline", "search_space_resolved"])
def test_a_study_without_its_imtune_attributes_is_one_line(attr, tmp_path, data3):
    """A study marked as imtune's whose attribute budget (pipeline, search_space_resolved) is gone (edited in the
    dashboard or by SQL, or written by another version): `tune test` was 'internal error: KeyError: 'budget''. Now
    one line naming the study and the attribute."""
    import sqlite3
    sd = tmp_path / "studies"
    env = {"IMTUNE_CACHE": str(tmp_path / "cache")}
    # Gamma pinned and a 5 s budget: its one trial must be feasible (in CI, a calibrated Gamma_max under load once
    # put it over the 0.5 s default: 'no feasible completed trial yet', a correct stop this test is not about)
    r = tune("run", "--data", data3, "--studies-dir", sd, "--study", "s", "--num-features", "256", "--n-trials", "1",
             "--fix", "max_iters=1000", "--budget", "5", "--jobs", "1", "--no-test", "--quiet", env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    with sqlite3.connect(sd / "optuna.db") as c:
        c.execute("DELETE FROM study_user_attributes WHERE key = ?", (attr,))
    r = tune("test", "--study", "s", "--studies-dir", sd, "--data", data3, "--runs", "1", "--reference", "none",
             "--jobs", "1", "--quiet", env=env)
    one_line_error(r, f"study 's' lacks its imtune attribute {attr} (edited, or written by another version of imtune)")


def test_studies_lists_another_programs_study_without_a_best_maa10(tmp_path, capsys):
    """`tune studies` on a storage shared with other Optuna work showed a foreign study's best value as its "best
    mAA10". Now none is shown for it, and one warning line names it."""
    import optuna

    from tuner.cli import main
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    optuna.logging.set_verbosity(optuna.logging.ERROR)
    optuna.create_study(study_name="theirs", storage=url).optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
    capsys.readouterr()
    assert main(["studies", "--storage", url, "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["study"] == "theirs" and row["complete"] == 2 and row["best mAA10"] is None
    assert main(["studies", "--storage", url]) == 0
    assert capsys.readouterr().err.strip() == "warning: theirs: not created by imtune (no mAA10 to show)"


def test_plot_of_another_programs_study_is_one_line(tmp_path, capsys):
    """`tune plot --study THEIRS` drew a report titled "imtune study THEIRS" with its values as mAA(10). Now one line."""
    import optuna

    from tuner.cli import main
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    optuna.logging.set_verbosity(optuna.logging.ERROR)
    optuna.create_study(study_name="theirs", storage=url).optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
    capsys.readouterr()
    assert main(["plot", "--study", "theirs", "--storage", url, "--studies-dir", str(tmp_path / "s")]) == 2
    assert capsys.readouterr().err.strip() == ("tune: error: study 'theirs' was not created by imtune: no report of "
                                               "it to draw (optuna-dashboard shows any study: tune dashboard)")
    assert not list(tmp_path.rglob("report.html"))
