"""The first hour of a new user, through the real `tune` command in subprocesses (issue 13, items 1 and 2).

A machine without ../shared (IMTUNE_SHARED points at a missing folder), HOME in tmp, and a local HTTP server on
127.0.0.1 standing in for the data's public home (IMTUNE_DOWNLOAD_BASE): it serves the real Strecha scenes from
../shared/data in the upstream URL layout. Nothing is fetched from the internet.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import DATA, ROOT
from tests.test_data_download import STRECHA_PREFIX, _closed_port_url, server  # noqa: F401

MAIN_JOB = ["--feature", "sift", "--ransac", "degensac"]


def tune(*args, env, timeout=600):
    return subprocess.run([sys.executable, "-m", "tuner", *args], capture_output=True, text=True, cwd=env["_CWD"],
                          env={k: v for k, v in env.items() if k != "_CWD"}, timeout=timeout)


def one_line_error(r, *needles):
    """Exit 2, exactly one line on stderr starting with `tune: error:`, no traceback, every needle in it."""
    assert r.returncode == 2, (r.returncode, r.stdout[-2000:], r.stderr[-2000:])
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tune: error: "), r.stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


@pytest.fixture
def user(tmp_path):
    """The environment of a new user: own HOME, no ../shared, no IMTUNE_* settings, an empty working folder."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("IMTUNE_") and k != "XDG_DATA_HOME"}
    home = tmp_path / "home"
    (tmp_path / "cwd").mkdir()
    home.mkdir()
    env.update(HOME=str(home), IMTUNE_SHARED=str(tmp_path / "no-shared"), IMTUNE_CACHE=str(tmp_path / "cache"),
               IMTUNE_STUDIES=str(tmp_path / "studies"), IMTUNE_GT=str(tmp_path / "gt"), _CWD=str(tmp_path / "cwd"),
               PYTHONPATH=str(ROOT))
    env["TORCH_HOME"] = os.environ.get("TORCH_HOME", "")
    if (ROOT / "imtune.yaml").is_file():
        pytest.skip(f"{ROOT / 'imtune.yaml'} exists and would name the data")
    return env


def download_home(env) -> Path:
    if env.get("IMTUNE_DATA_HOME"):
        return Path(env["IMTUNE_DATA_HOME"])
    try:
        import platformdirs  # noqa: F401
    except ImportError:
        return Path(env["HOME"]) / ".local" / "share" / "imtune" / "data"
    pytest.skip("platformdirs installed: the download location is platform-specific")


def mirror_strecha(root: Path) -> None:
    """The real ../shared/data/strecha files, served where the upstream repository has them (symlinks)."""
    src = DATA / "strecha"
    if not src.is_dir():
        pytest.skip(f"real data not found at {src} (expected ../shared beside the project)")
    for scene in sorted(p for p in src.iterdir() if p.is_dir()):
        for sub in ("images", "gt_dense_cameras"):
            d = root / STRECHA_PREFIX / scene.name / sub
            d.mkdir(parents=True)
            for f in (scene / sub).iterdir():
                (d / f.name).symlink_to(f)


# -- item 2: the command line itself ---------------------------------------------------------------------------

def test_bare_tune_prints_a_short_help_and_starts_nothing(user, tmp_path):
    r = tune(env=user)
    assert r.returncode == 0, r.stderr
    lines = [ln.strip() for ln in r.stdout.splitlines() if ln.strip()]
    examples = [ln for ln in lines if ln.startswith("tune ")]
    assert examples[0] == "tune --feature sift --ransac degensac"
    assert len(r.stdout.splitlines()) < 30 and "Commands:" in r.stdout
    assert r.stderr == ""
    assert not (tmp_path / "studies").exists() and not (tmp_path / "cache").exists()


def test_version(user):
    from importlib.metadata import version
    r = tune("--version", env=user)
    assert r.returncode == 0, r.stderr
    out = r.stdout.strip()
    assert out.startswith(f"imtune {version('imtune')}")
    if (ROOT / ".git").is_dir():  # a clone (tuner.study.code_version reads .git/HEAD)
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        if head:
            assert out.endswith(f"+g{head[:10]}"), out


@pytest.mark.parametrize("args,needles", [
    (["evalute"], ["unknown command 'evalute' (did you mean 'evaluate'?)"]),
    (["data", "downlod"], ["unknown command 'data downlod' (did you mean 'download'?)"]),
    (["data", "download", "strecah"], ["unknown data set 'strecah' (did you mean 'strecha'?)"]),
    (["--task", "mutliview"], ["--task: unknown task 'mutliview' (did you mean 'multiview'?)"]),
    (["--sampler", "rnadom"], ["--sampler: unknown sampler 'rnadom' (did you mean 'random'?)"]),
    (["evaluate", "--task", "sterep"], ["unknown task 'sterep' (did you mean 'stereo'?)"]),
    (["evaluate", "--feature", "sfit"], ["unknown feature 'sfit'", "did you mean 'sift'"]),
    (["evaluate", "--ransac", "degensak"], ["unknown estimator 'degensak'", "did you mean 'degensac'?"]),
])
def test_unknown_names_get_did_you_mean(user, args, needles):
    one_line_error(tune(*args, env=user), *needles)


def test_every_option_help_shows_its_default():
    """Every option of every command (that has a default) renders with it, the formatter being set once."""
    import argparse

    from tuner.cli import build_parser
    ap = build_parser()
    todo, seen = [("tune", ap)], 0
    while todo:
        name, p = todo.pop()
        fmt = p._get_formatter()
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                todo += [(f"{name} {k}", sp) for k, sp in a.choices.items()]
                continue
            if not a.option_strings or a.default is argparse.SUPPRESS:
                continue
            text = fmt._format_action(a).lower()
            assert "default" in text or "(else " in text or a.required and "(required)" in text, \
                f"{name} {a.option_strings[0]}: {text.strip()}"
            seen += 1
    assert seen > 100


def test_run_help_shows_defaults(user):
    r = tune("run", "--help-all", env=user)  # `-h` names the less used options; --help-all describes every one
    assert r.returncode == 0, r.stderr
    flat = " ".join(r.stdout.split())
    for s in ("--confidence CONFIDENCE RANSAC confidence tau (the protocol fixes 0.999999) (default: 0.999999)",
              "--num-features NUM_FEATURES keypoints per image "
              "(paper: 2048 or 8000) (default: 8000)", "--fginn FGINN: 2nd neighbour > 10 px from the first "
              "(default: off)"):
        assert s in flat, s


def test_test_help_says_what_its_defaults_are(user):
    """`tune test -h` showed "--test-budget TEST_BUDGET (default: none)", "--max-pairs MAX_PAIRS (default: none)",
    "--cache CACHE (default: none)" and no words for --study, --runs, --json, --quiet: the real defaults are the
    study's test budget and pairs per scene and $IMTUNE_CACHE."""
    r = tune("test", "-h", env=user)
    assert r.returncode == 0, r.stderr
    flat = " ".join(r.stdout.split())
    assert "(default: none)" not in flat, flat
    for s in ("--test-budget TEST_BUDGET median estimator CPU seconds per pair allowed on test (default: the study's",
              "--max-pairs MAX_PAIRS at most N pairs per scene (evenly spread; default: the study's",
              "--cache CACHE cache folder (else $IMTUNE_CACHE or ~/.cache/imtune)",
              "--runs RUNS test runs, each with its own estimator seed, averaged (default: 3)",
              "--study STUDY the study whose frozen settings are tested (required)"):
        assert s in flat, s


def test_pipeline_options_help_says_units_and_real_defaults(user):
    """`tune evaluate -h` / `tune run -h` showed "--mr-size MR_SIZE ... (default: none)" (the descriptor's own:
    3 for SIFT, 6 for the learned ones), "--scenes SCENES ... (default: none)" (every scene for evaluate, the
    validation split for run) and bare "--distance-threshold ... (default: none)", "--clahe ... (default: none)",
    "--confidence ..." with no unit or meaning."""
    flat = {c: " ".join(tune(c, h, env=user).stdout.split()) for c, h in (("evaluate", "-h"), ("run", "--help-all"))}
    for c, text in flat.items():
        for s in ("descriptor support scale (SIFT mrSize: the patch is 4 x mr_size sigmas) (default: the "
                  "descriptor's own, 3 for SIFT, 6 for the learned ones)",
                  "--distance-threshold DISTANCE_THRESHOLD drop a match whose descriptor distance exceeds this (L2 "
                  "for float descriptors, bits for binary ones) (default: none, no threshold)",
                  "--clahe {none,detector,descriptor,both} CLAHE contrast equalisation of the image the detector "
                  "and/or the descriptor sees (default: none)",
                  "--confidence CONFIDENCE RANSAC confidence tau (the protocol fixes 0.999999) (default: 0.999999)",
                  "--matcher {exact,flann,lightglue} nearest neighbours: exact brute force, or OpenCV FLANN "
                  "(approximate); or lightglue, the learned matcher (features aliked and disk;",
                  "instead of r) (default: exact)"):
            assert s in text, (c, s)
    assert "--scenes SCENES comma-separated scene names, each once (default: every scene of the data)" in flat["evaluate"]
    assert "--scenes SCENES comma-separated validation scenes, each once (default: the data set's validation split)" in flat["run"]


def test_calibrate_help_states_one_true_default_each(user):
    """`tune calibrate -h` said "--budget BUDGET B in seconds per pair (repeatable; default 0.5 and 1.0) (default:
    none)" (two defaults, one wrong), and "(default: none)" for --calibration-ratio / --calibration-threshold,
    which come from the search space's 'calibration' section, and for --max-pairs (every pair)."""
    r = tune("calibrate", "-h", env=user)
    assert r.returncode == 0, r.stderr
    flat = " ".join(r.stdout.split())
    options = flat.split("options:", 1)[1].split("pipeline:", 1)[0]  # calibrate's own options
    assert "(default: none)" not in options, options
    for s in ("--budget BUDGET B: median estimator CPU seconds per pair (repeatable) (default: 0.5 and 1.0)",
              "--calibration-ratio CALIBRATION_RATIO ratio test r of the timed matches (default: the search "
              "space's 'calibration' section)",
              "--calibration-threshold CALIBRATION_THRESHOLD eta (px) used while timing (default: the search "
              "space's 'calibration' section)",
              "--max-pairs MAX_PAIRS pairs per scene considered (default: every pair)"):
        assert s in flat, s


def test_run_help_says_what_no_seed_means(user):
    """`tune run -h` said "--seed SEED random seed, 0 to 2147483647 (default: none)": the seed seeds the sampler
    (each worker deriving its own) and the estimators, and without it the sampler is unseeded and the estimators
    take 0."""
    flat = " ".join(tune("run", "-h", env=user).stdout.split())
    assert ("--seed SEED seed of the sampler (each worker derives its own from it and its first trial) and of the "
            "seeded estimators, 0 to 2147483647 (default: none: an unseeded sampler, estimator seed 0)") in flat, flat


def test_top_help_names_every_data_subcommand(user):
    """`tune -h` listed "data  data sets: download, scenes": build-gt, the README's ground-truth step, was missing."""
    flat = " ".join(tune("-h", env=user).stdout.split())
    assert "data data sets: download, scenes, build-gt (ground truth)" in flat, flat


def test_run_help_names_the_default_space_and_pairs(user):
    """`tune run -h`: "--space SPACE search-space YAML replacing the default of the estimator family (default: none)"
    and "--max-pairs MAX_PAIRS ... (default: none)": the family's space and every pair are the defaults."""
    flat = " ".join(tune("run", "-h", env=user).stdout.split())
    assert ("--space SPACE search-space YAML replacing the default of the estimator family (default: "
            "search_spaces/<family>.yaml, with its per-feature overrides)") in flat, flat
    assert ("--max-pairs MAX_PAIRS use at most N pairs per scene (evenly spread; quick runs) (default: every pair; "
            "20 on the built-in Strecha split)") in flat


def test_build_gt_help_names_where_it_writes_as_the_readme_does(user):
    """`tune data build-gt -h` said "Written to $IMTUNE_CACHE/gt (or --gt-dir)"; $IMTUNE_GT comes first and
    ~/.cache/imtune/gt last (README, and its own --gt-dir help)."""
    flat = " ".join(tune("data", "build-gt", "-h", env=user).stdout.split())
    assert ("Written to --gt-dir, else $IMTUNE_GT, $IMTUNE_CACHE/gt or ~/.cache/imtune/gt, never into the data "
            "folder") in flat, flat


# -- item 1: data that just works ------------------------------------------------------------------------------

def test_no_data_and_no_network(user, tmp_path):
    """The main job on a machine with no data and no network: one line naming what is missing and the command,
    exit 2, and nothing half-made anywhere."""
    user[("IMTUNE_DOWNLOAD_BASE")] = _closed_port_url()
    home = download_home(user)
    line = one_line_error(tune(*MAIN_JOB, env=user), "no data", str(home / "strecha"), "downloading it failed",
                          "`tune data download strecha`", "--data DIR")
    assert "Connection refused" in line
    assert not [p for p in tmp_path.rglob("*") if "strecha" in p.name or "imtune" in p.name]
    assert not (Path(user["HOME"]) / ".local").exists()
    # a command that does not download says what to run
    one_line_error(tune("evaluate", env=user), "no data", "`tune data download strecha`", "--data DIR")
    one_line_error(tune("data", "scenes", env=user), "no data", "`tune data download strecha`")
    # `tune data download` itself, offline: one line, nothing left
    one_line_error(tune("data", "download", "strecha", "--quiet", env=user), "download failed", "Connection refused")
    assert not (Path(user["HOME"]) / ".local").exists()


@pytest.mark.parametrize("data_home", [False, True], ids=["default-location", "IMTUNE_DATA_HOME"])
def test_download_then_every_command_finds_it(user, tmp_path, server, data_home):  # noqa: F811
    mirror, base = server
    mirror_strecha(mirror)
    if data_home:
        user["IMTUNE_DATA_HOME"] = str(tmp_path / "datahome")
    home = download_home(user)
    user["IMTUNE_DOWNLOAD_BASE"] = base
    r = tune("data", "download", "strecha", env=user)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"strecha: ready in {home / 'strecha'}"
    assert "Traceback" not in r.stderr and "no --data" in r.stderr
    got = home / "strecha"
    assert sorted(p.name for p in got.iterdir()) == ["Herz-Jesus-P25", "Herz-Jesus-P8", "castle-P19", "castle-P30",
                                                     "entry-P10", "fountain-P11"]
    assert [p.name for p in home.iterdir()] == ["strecha"]  # no temporary folder left
    for f in ("fountain-P11/images/0004.jpg", "entry-P10/gt_dense_cameras/0009.jpg.camera"):
        assert (got / f).read_bytes() == (DATA / "strecha" / f).read_bytes()  # already 1536x1024: kept as is

    user["IMTUNE_DOWNLOAD_BASE"] = _closed_port_url()  # from now on: no network needed
    r = tune("data", "scenes", "--json", env=user)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["data"] == str(got) and out["rule"] == "download location"
    assert out["detail"] == ("$IMTUNE_DATA_HOME" if data_home else "~/.local/share/imtune/data")
    # the measured default split (benchmarks/results/default-split-and-freeze-rules.md): fountain and Herz-Jesus validate, entry and castle test
    assert {s["scene"]: s["split"] for s in out["scenes"]} == {"fountain-P11": "val", "Herz-Jesus-P8": "val",
                                                                "Herz-Jesus-P25": "val", "entry-P10": "test",
                                                                "castle-P19": "test", "castle-P30": "test"}
    assert out["max_pairs"] == 20
    r = tune("data", "scenes", env=user)
    assert r.stdout.splitlines()[0] == f"data: {got}  (found by {out['rule']} ({out['detail']}))"

    if data_home:
        return  # the evaluate run below is the same for both
    r = tune("evaluate", "--feature", "sift", "--num-features", "1024", "--ransac", "degensac", "--threshold", "1",
             "--scenes", "Herz-Jesus-P8", "--json", "--quiet", env=user)
    assert r.returncode == 0, r.stderr[-2000:]
    ev = json.loads(r.stdout)
    assert ev["data"] == str(got)
    st = ev["stereo"]
    assert st["pairs"] == 28 and set(st["scenes"]) == {"Herz-Jesus-P8"}
    assert st["NI"] > 30 and st["mAA10"] > 0.3  # laser ground truth, easy scene: a broken pose would fail this


def test_main_job_downloads_and_goes_on(user, tmp_path, server):  # noqa: F811
    """No data but a network (the local mirror): the main job says so in one line, downloads into the download
    location, then tunes (one tiny trial here, no test run)."""
    mirror, base = server
    mirror_strecha(mirror)
    user["IMTUNE_DOWNLOAD_BASE"] = base
    home = download_home(user)
    # Gamma pinned at 100 iterations: the one trial is far inside the 0.5 s budget, so it can be frozen
    r = tune(*MAIN_JOB, "--num-features", "512", "--n-trials", "1", "--max-pairs", "2", "--chunk-pairs", "2",
             "--calibration-pairs", "2", "--fix", "max_iters=100", "--no-test", "--json", "--quiet", env=user)
    assert r.returncode == 0, r.stderr[-3000:]
    first = r.stderr.splitlines()[0]
    assert first.startswith("tune: no data found; downloading the default data set strecha (206 files from "
                            "127.0.0.1:") and first.endswith(f"into {home / 'strecha'}"), r.stderr
    assert (home / "strecha" / "fountain-P11" / "images" / "0010.jpg").is_file()
    out = json.loads(r.stdout)
    assert out["counts"]["complete"] + out["counts"]["pruned"] == 1
    assert (tmp_path / "studies" / "optuna.db").is_file()


def test_ctrl_c_during_download_leaves_nothing(user, tmp_path):
    """A real SIGINT to `tune data download` while a file is in flight: exit 130, one line, nothing on disk."""
    import functools
    import http.server
    import signal
    import threading

    mirror = tmp_path / "mirror"
    mirror_strecha(mirror)
    reached, release = threading.Event(), threading.Event()

    class Stalling(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            if self.path.endswith("fountain-P11/images/0002.jpg"):  # the third file: two are already in
                reached.set()
                release.wait(60)
            return super().do_GET()

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Stalling, directory=str(mirror)))
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        user["IMTUNE_DOWNLOAD_BASE"] = f"http://127.0.0.1:{httpd.server_address[1]}"
        home = download_home(user)
        env = {k: v for k, v in user.items() if k != "_CWD"}
        p = subprocess.Popen([sys.executable, "-m", "tuner", "data", "download", "strecha", "--quiet"],
                             cwd=user["_CWD"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert reached.wait(120), "the download never reached the stalled file"
        assert [q.name for q in home.iterdir()][0].startswith(".strecha-download-")  # work in progress exists
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        release.set()
        httpd.shutdown()
        httpd.server_close()
    assert p.returncode == 130, (p.returncode, err)
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("tune: interrupted")
    assert not (Path(user["HOME"]) / ".local").exists()  # temporary folder and the folders it needed: gone


# -- item 9: two set-up commands, and CI runs the README's ------------------------------------------------------

def _setup_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Set-up", 1)[1].split("\n## ", 1)[0]
    out: list[str] = []
    for ln in section.splitlines():
        if not (ln.startswith("    ") and ln.strip()):
            continue
        if out and out[-1].endswith("\\"):  # a command broken with ` \` to fit 100 columns: one command
            out[-1] = out[-1][:-1].rstrip() + " " + ln.strip()
        else:
            out.append(ln.strip())
    return out


def test_readme_has_two_setup_commands_and_ci_runs_the_test_one():
    main, test = _setup_commands()  # exactly two
    assert main == "bash .ci/install.sh && .venv/bin/tune --feature sift --ransac degensac"
    assert test.startswith("bash .ci/install.sh --test && ") and "pytest" in test
    run = (ROOT / ".ci" / "run").read_text().splitlines()
    assert test in [ln.strip() for ln in run]
    script = (ROOT / ".ci" / "install.sh").read_text()
    # the Python-only install touches no system package: apt-get and sudo appear only in the --test branch
    test_branch = script.split('if [ "$TEST" -eq 1 ]; then', 1)[1].split("\nfi\n", 1)[0]
    outside = "\n".join(ln for ln in script.replace(test_branch, "").splitlines() if not ln.lstrip().startswith("#"))
    assert "apt-get install" in test_branch and "apt-get" not in outside and "$SUDO" not in outside
    assert "torch==2.13.0" in script and "CUDA" in script  # the pin says why it is there


def test_install_script_options():
    r = subprocess.run(["bash", str(ROOT / ".ci" / "install.sh"), "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "--test" in r.stdout
    r = subprocess.run(["bash", str(ROOT / ".ci" / "install.sh"), "--bogus"], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--bogus" in r.stderr
