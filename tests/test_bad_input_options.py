"""Bad option values that used to be accepted and then gave wrong numbers or ran the wrong thing (the bad-input
sweep of the options): each is now one line on stderr naming the culprit, exit 2 — or, for data files, a loaded
Scene that says so. Every case calls the CLI's ``main([...])`` in-process on tiny inputs; where the old code
would have gone on to real work, the command line also carries a cheap mistake further down (an unknown feature,
a folder with no data) so that it fails fast there with a message that does not name the culprit under test."""
from __future__ import annotations

import pytest

from tests.conftest import DATA


def _cli(args, capsys):
    from tuner.cli import main
    capsys.readouterr()
    try:
        rc = main([str(a) for a in args])
    except SystemExit as e:  # argparse's errors exit as the console script would (tuner.cli._Parser.error)
        rc = e.code
    out = capsys.readouterr()
    return rc, out.out, out.err


def _one_line_error(rc, err, *needles):
    assert rc == 2, err
    assert "Traceback" not in err and "internal error" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tune: error:"), err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


@pytest.fixture
def isolated(tmp_path, monkeypatch):
    """Caches, studies and a folder holding no data set, all under tmp_path (the old code may get that far)."""
    monkeypatch.setenv("IMTUNE_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("IMTUNE_STUDIES", str(tmp_path / "studies"))
    (tmp_path / "nodata").mkdir()
    return tmp_path


# ------------------------------------------------------------------------------ 1. explicitly empty values

NOSUCH = ["--feature", "no-such-feature"]  # the old code stops here (before any data is read) when "" got through
EMPTY_CASES = [
    (["findings", "--quick", "--only", "", "--data", "{nodata}"], "--only", "ids such as 1,2,4"),
    (["findings", "--quick", "--only=", "--data", "{nodata}"], "--only", "ids such as 1,2,4"),
    (["findings", "--data", "", "--only", "99"], "--data", "data folder"),
    (["findings", "--val-scenes", "", "--only", "99"], "--val-scenes", "scene names"),
    (["findings", "--test-scenes", " ", "--only", "99"], "--test-scenes", "scene names"),
    (["evaluate", "--data", "", *NOSUCH], "--data", "data folder"),
    (["evaluate", "--config", "", *NOSUCH], "--config", "configuration file"),
    (["evaluate", "--scenes", "", *NOSUCH], "--scenes", "scene names"),
    (["evaluate", "--bags", "", *NOSUCH], "--bags", "bag sizes"),
    (["run", "--reference", "", *NOSUCH], "--reference", "study name or none"),
    (["run", "--study", "", *NOSUCH], "--study", "study name"),
    (["run", "--scenes", "", *NOSUCH], "--scenes", "scene names"),
    (["run", "--test-scenes", "", *NOSUCH], "--test-scenes", "scene names"),
    (["--data", "", *NOSUCH], "--data", "data folder"),  # the main job (= run)
    (["viz", "--pairs", "", *NOSUCH], "--pairs", "pairs such as"),
    (["viz", "--out", "", *NOSUCH], "--out", "path"),
    (["plot", "--out", "", "--study", "x", "--studies-dir", "{nodata}"], "--out", "path"),
    (["compare", "--scenes", "", "no-such-a", "no-such-b"], "--scenes", "scene names"),
    (["test", "--scenes", "", "--study", "no-such", "--studies-dir", "{nodata}"], "--scenes", "scene names"),
]


@pytest.mark.parametrize("argv, option, hint", EMPTY_CASES, ids=[" ".join(c[0][:2]) + f" {c[1]}" for c in EMPTY_CASES])
def test_an_empty_value_is_an_error_naming_the_option(argv, option, hint, isolated, capsys):
    argv = [a.format(nodata=isolated / "nodata") for a in argv]
    rc, out, err = _cli(argv, capsys)
    line = _one_line_error(rc, err, f"{option} is empty", hint)
    assert "leave the option out" in line
    assert not (isolated / "studies").exists() and not (isolated / "cache").exists()  # nothing started


def test_an_empty_value_of_a_required_option_does_not_say_leave_it_out(isolated, capsys):
    rc, out, err = _cli(["test", "--study", "", "--studies-dir", isolated / "nodata"], capsys)
    line = _one_line_error(rc, err, "--study is empty")
    assert "leave the option out" not in line


def test_an_empty_environment_variable_still_means_unset(isolated, monkeypatch, capsys):
    import json
    if not (DATA / "strecha").is_dir():
        pytest.skip(f"real data not found at {DATA}")
    monkeypatch.setenv("IMTUNE_DATA", "")  # the usual convention: as if not set, the next rule finds the data
    monkeypatch.setenv("IMTUNE_DATA_HOME", str(isolated / "nodata"))
    rc, out, err = _cli(["data", "scenes", "--json"], capsys)
    assert rc == 0, err
    assert "fountain-P11" in [s["scene"] for s in json.loads(out)["scenes"]]


# ------------------------------------------------------------------------------ 7. dashboard --host

def test_dashboard_refuses_an_empty_host(isolated, capsys):
    rc, out, err = _cli(["dashboard", "--host", "", "--studies-dir", isolated / "nodata"], capsys)
    _one_line_error(rc, err, "--host is empty", "127.0.0.1")
    from pipeline.errors import ImtuneError
    from tuner.dashboard import serve
    with pytest.raises(ImtuneError, match="--host is empty"):  # the Python call too: "" would bind every interface
        serve(None, host=" ", port=8080, studies_dir=isolated / "nodata", quiet=True)


def test_dashboard_exposure_warning_is_complete():
    from tuner.dashboard import exposure_warning
    for local in ("127.0.0.1", "localhost", "::1"):
        assert exposure_warning(local) is None
    w = exposure_warning("0.0.0.0")
    assert w.startswith("warning:") and "every network interface (0.0.0.0)" in w and "--host 127.0.0.1" in w
    assert "every network interface (::)" in exposure_warning("::")
    w = exposure_warning("192.168.1.7")
    assert "192.168.1.7" in w and not w.rstrip().endswith(" on")


# ------------------------------------------------------------------------------ 2. a scene named twice

TWICE_CASES = [
    (["evaluate", "--scenes", "fountain-P11,fountain-P11", *NOSUCH], "--scenes"),
    (["evaluate", "--scenes", "fountain-P11, entry-P10 ,fountain-P11", *NOSUCH], "--scenes"),
    (["run", "--test-scenes", "entry-P10,entry-P10", *NOSUCH], "--test-scenes"),
    (["findings", "--val-scenes", "fountain-P11,fountain-P11", "--only", "99"], "--val-scenes"),
    (["findings", "--test-scenes", "entry-P10,entry-P10", "--only", "99"], "--test-scenes"),
    (["compare", "--scenes", "fountain-P11,fountain-P11", "no-such-a", "no-such-b"], "--scenes"),
    (["test", "--scenes", "entry-P10,entry-P10", "--study", "no-such", "--studies-dir", "{nodata}"], "--scenes"),
]


@pytest.mark.parametrize("argv, option", TWICE_CASES, ids=[" ".join(c[0][:3]) for c in TWICE_CASES])
def test_a_scene_named_twice_is_an_error(argv, option, isolated, capsys):
    argv = [a.format(nodata=isolated / "nodata") for a in argv]
    rc, out, err = _cli(argv, capsys)
    _one_line_error(rc, err, f"argument {option}", "is named twice")


def test_a_scene_list_naming_no_scene_is_an_error(isolated, capsys):
    rc, out, err = _cli(["evaluate", "--scenes", ",", *NOSUCH], capsys)
    _one_line_error(rc, err, "argument --scenes", "names no scene")


@pytest.fixture
def two_images(tmp_path):
    from tests.conftest import copy_strecha_subset
    return copy_strecha_subset(tmp_path / "data", ["0004.jpg", "0005.jpg"])


def test_load_scenes_refuses_a_scene_named_twice(two_images):
    from pipeline.errors import ImtuneError
    from tuner.evaluate import load_scenes
    with pytest.raises(ImtuneError, match="'fountain-P11' is named twice"):
        load_scenes(two_images, ["fountain-P11", "fountain-P11"], ground_truth=False)
    with pytest.raises(ImtuneError, match="named twice"):
        load_scenes(two_images, "fountain-P11,fountain-P11", ground_truth=False)
    assert [s.name for s in load_scenes(two_images, "fountain-P11", ground_truth=False)] == ["fountain-P11"]


def test_a_scene_listed_twice_in_splits_yaml_is_an_error(two_images, isolated, capsys):
    splits = two_images / "splits.yaml"
    splits.write_text("val: [fountain-P11, fountain-P11]\ntest: []\n")
    rc, out, err = _cli(["data", "scenes", "--data", two_images], capsys)
    _one_line_error(rc, err, str(splits), "'fountain-P11' is listed twice in 'val'")


# ------------------------------------------------------------------------------ 3. pairs_with_gt.txt: duplicates, self-pairs

SCANNET = DATA / "scannet_sample"


@pytest.fixture
def scannet_lines():
    if not (SCANNET / "pairs_with_gt.txt").is_file():
        pytest.skip(f"real data not found at {SCANNET}")
    return (SCANNET / "pairs_with_gt.txt").read_text().splitlines()


def _load_list(tmp_path, lines):
    from pipeline.data.pairs_with_gt import load_pairs_with_gt
    f = tmp_path / "pairs_with_gt.txt"
    f.write_text("\n".join(lines) + "\n")
    return f, load_pairs_with_gt(SCANNET, pairs_file=f, verify=False)  # images: the real sample's


def test_the_real_pairs_list_loads_every_pair_once(scannet_lines, tmp_path):
    _, scene = _load_list(tmp_path, scannet_lines)
    assert len(scene.pairs) == 15 and len({frozenset((p.i, p.j)) for p in scene.pairs}) == 15


def test_a_pair_listed_twice_names_both_lines(scannet_lines, tmp_path):
    from pipeline.errors import ImtuneError
    n = len(scannet_lines)
    with pytest.raises(ImtuneError) as e:
        _load_list(tmp_path, scannet_lines + ["# a comment", scannet_lines[2]])  # line 3 again, as line n + 2
    msg = str(e.value)
    assert str(tmp_path / "pairs_with_gt.txt") in msg and f"lines 3 and {n + 2}" in msg and "listed twice" in msg
    assert "\n" not in msg


def test_a_pair_listed_in_both_orders_is_the_same_pair(scannet_lines, tmp_path):
    from pipeline.errors import ImtuneError
    a, b, *rest = scannet_lines[4].split()
    # b a with the inverse pose: a well-formed line, the same pair of images
    import numpy as np
    T = np.linalg.inv(np.array(rest[20:36], float).reshape(4, 4))
    swapped = " ".join([b, a, rest[0], rest[1], *rest[11:20], *rest[2:11], *(f"{x:.10g}" for x in T.ravel())])
    with pytest.raises(ImtuneError, match=r"lines 5 and 16: the pair .* listed twice"):
        _load_list(tmp_path, scannet_lines + [swapped])


def test_a_line_pairing_an_image_with_itself_is_malformed(scannet_lines, tmp_path):
    from pipeline.errors import ImtuneError
    a, b, *rest = scannet_lines[0].split()
    with pytest.raises(ImtuneError) as e:
        _load_list(tmp_path, [" ".join([a, a, *rest])] + scannet_lines[1:])
    msg = str(e.value)
    assert f"{tmp_path / 'pairs_with_gt.txt'}, line 1" in msg and f"pairs image {a} with itself" in msg


# ------------------------------------------------------------------------------ 4. seeds beyond 31 bits

@pytest.mark.parametrize("argv", [
    ["evaluate", *NOSUCH, "--seed"], ["run", *NOSUCH, "--seed"], ["calibrate", *NOSUCH, "--seed"],
    ["findings", "--only", "99", "--seed"], ["compare", "no-such-a", "no-such-b", "--seed"],
    ["evaluate", *NOSUCH, "--bag-seed"],
], ids=lambda a: f"{a[0]} {a[-1]}")
@pytest.mark.parametrize("seed", [2**31, 2**32, 2**32 + 1, 2**64])
def test_a_seed_above_31_bits_is_refused(argv, seed, isolated, capsys):
    rc, out, err = _cli([*argv, seed], capsys)  # 2**31 ran as 0, 2**32 + 1 as 1: silently another seed's results
    _one_line_error(rc, err, f"argument {argv[-1]}", "at most 2147483647", f"'{seed}'")


def test_the_seed_range_in_configurations_and_repeated_runs():
    from pipeline.config import SEED_MAX, GeometryConfig, run_seed
    from pipeline.errors import ImtuneError
    from pipeline.tasks import make_task
    from tuner.freeze import pipeline_from_dict
    assert SEED_MAX == 2**31 - 1 and GeometryConfig(seed=SEED_MAX).seed == SEED_MAX
    for bad in (2**31, 2**32 + 1, -1):
        with pytest.raises(ImtuneError, match="seed must be an integer from 0 to 2147483647"):
            GeometryConfig(seed=bad)
    with pytest.raises(ImtuneError, match="seed must be an integer from 0 to 2147483647"):  # a configuration file
        pipeline_from_dict({"feature": {"name": "sift"}, "geometry": {"ransac": "degensac", "seed": 2**32}})
    # the k-th test run uses seed + k, as before, and wraps inside the range instead of leaving it
    task = make_task("stereo")
    conf = pipeline_from_dict({"feature": {"name": "sift"}, "geometry": {"ransac": "degensac", "seed": 7}})
    assert [task.for_run(conf, k)[1].geometry.seed for k in range(3)] == [7, 8, 9]
    top = pipeline_from_dict({"feature": {"name": "sift"}, "geometry": {"ransac": "degensac", "seed": SEED_MAX}})
    assert [task.for_run(top, k)[1].geometry.seed for k in range(3)] == [SEED_MAX, 0, 1]
    assert run_seed(5, 2) == 7
    from pipeline.tasks.multiview import MultiviewConfig
    with pytest.raises(ImtuneError, match="multiview seed must be"):
        MultiviewConfig(seed=2**31)


def test_findings_refuses_a_seed_above_31_bits_from_python(tmp_path):
    from pipeline.errors import ImtuneError
    from tuner.findings import FindingsSettings, run_findings
    with pytest.raises(ImtuneError, match="seed must be an integer from 0 to 2147483647"):
        run_findings(FindingsSettings(data_root=tmp_path, studies_dir=tmp_path / "studies", seed=2**32, only=[1]),
                     write=False)


# ------------------------------------------------------------------------------ 5. Gamma beyond what the estimators take

@pytest.mark.parametrize("value", ["2147483648", "99999999999999999999999"])
def test_max_iters_above_the_estimators_limit_is_refused(value, isolated, capsys):
    rc, out, err = _cli(["evaluate", *NOSUCH, "--max-iters", value], capsys)  # was printed as given, clamped to 2**31-1
    _one_line_error(rc, err, "argument --max-iters", "at most 2147483647", value)
    from pipeline.config import GeometryConfig
    from pipeline.errors import ImtuneError
    with pytest.raises(ImtuneError, match="max-iters must be at most 2147483647"):
        GeometryConfig(max_iters=int(value))
    assert GeometryConfig(max_iters=2**31 - 1).max_iters == 2**31 - 1


def test_fix_max_iters_above_the_estimators_limit_is_refused():
    from pipeline.errors import ImtuneError
    from tuner.space import load_space
    with pytest.raises(ImtuneError, match=r"--fix max_iters: .* must be at most 2147483647"):
        load_space(None, feature="sift", estimator="degensac", fixes=["max_iters=1e30"])


@pytest.fixture
def tiny(tmp_path, monkeypatch):
    """Two real fountain-P11 images, caches and studies under tmp_path."""
    from tests.conftest import copy_strecha_subset
    monkeypatch.setenv("IMTUNE_CACHE", str(tmp_path / "cache"))
    return copy_strecha_subset(tmp_path / "data", ["0004.jpg", "0005.jpg"])


FAST = ["--num-features", "256", "--jobs", "1", "--quiet"]


def test_a_pinned_gamma_above_any_gamma_max_warns_before_the_study(tiny, tmp_path, capsys):
    # --test-scenes nosuch stops the run at its preflight, after the warning and before any calibration or trial
    rc, out, err = _cli(["run", "--data", tiny, *FAST, "--studies-dir", tmp_path / "st", "--fix", "max_iters=99999999",
                         "--test-scenes", "nosuch"], capsys)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 2, err
    assert lines[0].startswith("warning: --fix max_iters=99999999 is above") and "1,000,000" in lines[0], err
    assert "will exceed the 0.5 s per pair budget on most pairs" in lines[0]
    assert lines[1].startswith("tune: error: test scene 'nosuch'")


def test_a_pinned_gamma_above_the_calibrated_gamma_max_warns(tiny, tmp_path, capsys):
    st = tmp_path / "st"
    rc, out, err = _cli(["calibrate", "--data", tiny, *FAST, "--studies-dir", st, "--pairs", "1", "--budget", "0.005",
                         "--json"], capsys)
    assert rc == 0, err
    import json
    gmax = json.loads(out)["gamma_max"]["0.005"]
    assert gmax < 900_000
    run = ["run", "--data", tiny, *FAST, "--studies-dir", st, "--budget", "0.005", "--test-scenes", "nosuch"]
    rc, out, err = _cli([*run, "--fix", "max_iters=900000"], capsys)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 2, err
    assert lines[0].startswith(f"warning: --fix max_iters=900000 is above Gamma_max(0.005 s) = {gmax:,} calibrated "
                               "for degensac on this machine"), err
    rc, out, err = _cli([*run, "--fix", f"max_iters={gmax}"], capsys)  # at Gamma_max: no warning
    assert rc == 2 and "warning" not in err and len(err.strip().splitlines()) == 1, err



TWO_IMAGES_NO_BAG = ("tune: error: validation scene 'fountain-P11': nothing for the multiview task to evaluate (fewer "
                     "than 3 images, the smallest bag)")


def test_a_fix_the_task_does_not_use_is_said_not_silently_dropped(tiny, tmp_path, capsys):
    """`--task multiview --fix threshold=1` was dropped without a word (COLMAP runs its own RANSAC): the user
    believed eta pinned. The run stops at its preflight, after the warning: the validation scene's 2 images make no
    multiview bag (and --test-scenes nosuch would stop it next)."""
    rc, out, err = _cli(["run", "--data", tiny, *FAST, "--task", "multiview", "--studies-dir", tmp_path / "st",
                         "--fix", "threshold=1.0", "--fix", "max_iters=100",
                         "--test-scenes", "nosuch"], capsys)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 2, err
    assert lines[0] == ("warning: --fix threshold, max_iters: the multiview task does not use them (it uses ratio, "
                        "strategy); ignored"), err
    assert lines[1].startswith(TWO_IMAGES_NO_BAG), err


def test_stereo_options_of_a_multiview_run_are_said_not_silently_dropped(tiny, tmp_path, capsys):
    """`tune run --task multiview --max-pairs 2 --budget 0.1 --covisibility 0.3` ran every bag, untimed, without a word
    (COLMAP reconstructs whole bags with its own RANSAC): the user believed the run cut short and budgeted. One warning
    line, as for a --fix the task does not use; the run then stops at its preflight (2 images make no multiview bag)."""
    rc, out, err = _cli(["run", "--data", tiny, *FAST, "--task", "multiview", "--studies-dir", tmp_path / "st",
                         "--max-pairs", "2", "--budget", "0.1", "--covisibility", "0.3", "--test-scenes", "nosuch"],
                        capsys)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 2, err
    assert lines[0] == ("warning: --max-pairs, --budget, --covisibility: the multiview task does not use them (COLMAP "
                        "reconstructs each bag whole, with its own RANSAC, untimed; --bags sets the work); ignored"), err
    assert lines[1].startswith(TWO_IMAGES_NO_BAG), err


def test_a_fix_given_twice_with_two_values_is_one_line(tiny, tmp_path, capsys):
    """`--fix ratio=0.8 --fix ratio=0.9` pinned 0.9 without a word (the last won); the same value twice is fine."""
    rc, out, err = _cli(["run", "--data", tiny, *FAST, "--studies-dir", tmp_path / "st", "--fix", "ratio=0.8",
                         "--fix", "ratio=0.9"], capsys)
    _one_line_error(rc, err, "--fix ratio is given twice (ratio=0.8 and ratio=0.9): give it once")
    assert not (tmp_path / "st" / "optuna.db").exists()
    from tuner.space import parse_fixes
    assert parse_fixes(["ratio=0.8", "ratio=0.8"]) == {"ratio": "0.8"}

# ------------------------------------------------------------------------------ 8. --warm-start checked before the study exists

def test_an_unknown_warm_start_source_leaves_no_study(tiny, tmp_path, capsys):
    import optuna
    st = tmp_path / "st"
    rc, out, err = _cli(["run", "--data", tiny, *FAST, "--studies-dir", st, "--fix", "max_iters=1000", "--no-test",
                         "--n-trials", "1", "--study", "ws1", "--warm-start", "nosuch"], capsys)
    _one_line_error(rc, err, "--warm-start nosuch", "no study 'nosuch'")
    db = st / "optuna.db"
    assert not db.exists() or optuna.get_all_study_names(f"sqlite:///{db}") == []


# ------------------------------------------------------------------------------ 6. findings: an unusable cache folder

def test_findings_preflight_refuses_a_cache_folder_that_cannot_be_created(tmp_path, capsys, monkeypatch):
    import optuna

    from tests.conftest import copy_strecha_subset
    data = copy_strecha_subset(tmp_path / "data", ["0004.jpg", "0005.jpg"])
    copy_strecha_subset(data, ["0000.jpg", "0001.jpg"], scene="entry-P10")  # a validation and a test scene
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a regular file where the cache's parent should be\n")  # tests run as root: no chmod
    cache = blocker / "cache"
    st = tmp_path / "studies"
    rc, out, err = _cli(["findings", "--quick", "--only", "1", "--data", data, "--cache", cache, "--studies-dir", st,
                         "--quiet"], capsys)
    _one_line_error(rc, err, f"cannot create the cache folder {cache}", f"{blocker} is a file", "--cache")
    assert optuna.get_all_study_names(f"sqlite:///{st / 'optuna.db'}") == []  # before any study
    from pipeline.cache import H5Cache
    from pipeline.errors import ImtuneError
    with pytest.raises(ImtuneError, match="is a file, not a folder"):
        H5Cache(blocker).check_writable()  # the folder itself a file
    H5Cache(tmp_path / "fresh" / "cache").check_writable()  # created, written, left empty
    assert list((tmp_path / "fresh" / "cache").iterdir()) == []


# ------------------------------------------------------------------------------ 9. results / table --task: the task registry

@pytest.mark.parametrize("command", ["results", "table"])
def test_an_unknown_task_lists_the_tasks(command, tmp_path, capsys):
    import optuna
    optuna.create_study(study_name="other", storage=f"sqlite:///{tmp_path / 'optuna.db'}")  # a storage to read
    rc, out, err = _cli([command, "--task", "bogus", "--studies-dir", tmp_path], capsys)
    line = _one_line_error(rc, err, "--task", "unknown task 'bogus'", "stereo", "multiview")
    assert "no tested" not in line


# ------------------------------------------------------------------------------ 10. compare: the verdict rule of findings

def test_compare_verdict_needs_the_interval_and_the_sign_flip_test():
    from tuner.compare import verdict
    from tuner.findings.analysis import directional
    # the interval excludes 0 but the exact sign-flip test does not confirm it: not "A better"
    assert verdict({"ci": [-0.12, -0.004], "difference": -0.05, "p_value": 0.242}) == "no significant difference"
    assert verdict({"ci": [-0.12, -0.004], "difference": -0.05, "p_value": 0.01}) == "A better"
    assert verdict({"ci": [0.01, 0.2], "difference": 0.1, "p_value": 0.003}) == "B better"
    assert verdict({"ci": [-0.01, 0.2], "difference": 0.1, "p_value": 0.003}) == "no significant difference"
    # one rule for both commands
    words = {"B better": "holds", "A better": "does not hold", "no significant difference": "inconclusive"}
    for ci in ([-0.2, -0.01], [-0.01, 0.01], [0.01, 0.2], [0.0, 0.1]):
        for p in (0.001, 0.049, 0.05, 0.242, 1.0):
            assert words[verdict({"ci": ci, "difference": sum(ci) / 2, "p_value": p})] == directional(ci, p), (ci, p)


def test_test_reports_compare_with_the_reference_by_the_same_rule():
    from tuner.select import comparison_text
    c = {"difference": 0.05, "ci": [0.004, 0.1], "p_value": 0.242, "significant": True, "pairs": 24}
    line = comparison_text({"label": "paper defaults", "mAA10": 0.4, "comparison": c})
    assert line.endswith("no significant difference"), line


def test_compare_states_its_verdict_rule(tiny, tmp_path, capsys):
    import json

    import yaml
    conf = tmp_path / "a.yaml"
    conf.write_text(yaml.safe_dump({"config": {"feature": {"name": "sift", "num_features": 256},
                                               "geometry": {"ransac": "degensac", "max_iters": 1000}}}))
    common = [conf, conf, "--data", tiny, "--cache", tmp_path / "cache", "--studies-dir", tmp_path, "--quiet",
              "--ci-resamples", "200"]
    rc, out, err = _cli(["compare", *common], capsys)
    assert rc == 0, err
    assert "| no significant difference |" in out
    assert ("verdict: B or A is better only when the 95% CI of B - A excludes 0 and the paired sign-flip test agrees "
            "(p < 0.05); otherwise no significant difference (the rule of tune findings)") in out
    rc, out, err = _cli(["compare", *common, "--json"], capsys)
    res = json.loads(out)
    assert rc == 0 and res["overall"]["verdict"] == "no significant difference" and "sign-flip" in res["verdict_rule"]


def test_compare_of_several_sources_states_the_adjusted_levels_in_its_verdict_rule(tiny, tmp_path, capsys):
    """With three sources the two comparisons with A are one family: the table gave 97.5% CIs and Holm-adjusted p,
    but the verdict line under it still read 'the 95% CI of B - A excludes 0 ... (p < 0.05)', a level it does not
    use. The line (and the JSON's verdict_rule) now names the Bonferroni level 1 - 0.05 / 2 = 97.5% and the
    Holm-adjusted p; the comparisons' own ci_level says the same."""
    import json

    import yaml
    conf = tmp_path / "a.yaml"
    conf.write_text(yaml.safe_dump({"config": {"feature": {"name": "sift", "num_features": 256},
                                               "geometry": {"ransac": "degensac", "max_iters": 1000}}}))
    common = [conf, conf, conf, "--data", tiny, "--cache", tmp_path / "cache", "--studies-dir", tmp_path, "--quiet",
              "--ci-resamples", "200"]
    rc, out, err = _cli(["compare", *common], capsys)
    assert rc == 0, err
    verdict_line = next(line for line in out.splitlines() if line.startswith("verdict: "))
    assert verdict_line == ("verdict: Bi or A is better only when the 97.5% CI of Bi - A excludes 0 and the paired "
                            "sign-flip test agrees (its p Holm-adjusted over the 2 comparisons < 0.05); otherwise no "
                            "significant difference (the rule of tune findings, adjusted for multiplicity)"), out
    assert "95% CI" not in verdict_line and "97.5% bootstrap CI" in out and "multiplicity: 2 comparisons" in out
    rc, out, err = _cli(["compare", *common, "--json"], capsys)
    res = json.loads(out)
    assert rc == 0 and len(res) == 2
    for c in res:
        assert c["overall"]["ci_level"] == pytest.approx(0.975)
        assert "97.5% CI" in c["verdict_rule"] and "Holm-adjusted" in c["verdict_rule"]



def test_compare_says_a_multiview_study_runs_with_untuned_eta_and_gamma(tiny, tmp_path, capsys):
    """A multiview study tunes r only (COLMAP runs its own RANSAC); `tune compare --task stereo` runs its frozen eta
    0.5 px and Gamma on the stereo pairs and says so on stderr (the JSON is unchanged). Without --task a multiview
    study is compared on bags (test_tuner_multiview::test_compare_of_a_multiview_study_pairs_its_bags)."""
    import yaml
    sdir = tmp_path / "studies"
    (sdir / "mv").mkdir(parents=True)
    (sdir / "mv" / "frozen.yaml").write_text(yaml.safe_dump({
        "study": "mv", "trial": 0, "task": "multiview", "params": {"ratio": 0.74}, "fixed": {"strategy": "both"},
        "config": {"feature": {"name": "sift", "num_features": 256}, "matching": {"ratio": 0.74},
                   "geometry": {"ransac": "degensac", "threshold": 0.5, "max_iters": 1000}}}))
    conf = tmp_path / "a.yaml"
    conf.write_text(yaml.safe_dump({"config": {"feature": {"name": "sift", "num_features": 256},
                                               "geometry": {"ransac": "degensac", "max_iters": 1000}}}))
    rc, out, err = _cli(["compare", conf, "mv", "--data", tiny, "--cache", tmp_path / "cache", "--studies-dir", sdir,
                         "--quiet", "--ci-resamples", "200", "--task", "stereo"], capsys)
    assert rc == 0, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0] == ("warning: mv is a multiview study: it tuned ratio only; on these stereo "
                                            "pairs it runs with its file's eta 0.5 px and Gamma 1000 as they are, "
                                            "untuned"), err
    assert "| no significant difference |" in out or "better |" in out
    assert "B: mv (trial #0): sift 256 · r 0.74 both · degensac η 0.5 px, Γ 1000 " in out, out  # what runs here

def test_compare_of_a_stereo_and_a_multiview_study_is_refused(tiny, tmp_path, capsys):
    """`tune compare S MV` of a stereo and a multiview study: each was tuned for another task, and the comparison ran
    on stereo pairs, MV with an eta and Gamma never tuned. Without --task it is now one line naming both and the two
    --task values; a multiview option given to a stereo comparison is refused the same way."""
    import yaml
    sdir = tmp_path / "studies"
    config = {"feature": {"name": "sift", "num_features": 256}, "matching": {"ratio": 0.74},
              "geometry": {"ransac": "degensac", "threshold": 0.5, "max_iters": 1000}}
    for name, task, params in (("mv", "multiview", {"ratio": 0.74}), ("s", "stereo", {"ratio": 0.74, "threshold": 0.5})):
        (sdir / name).mkdir(parents=True)
        (sdir / name / "frozen.yaml").write_text(yaml.safe_dump({"study": name, "trial": 0, "task": task,
                                                                 "params": params, "config": config}))
    common = ["--data", tiny, "--cache", tmp_path / "cache", "--studies-dir", sdir, "--quiet", "--ci-resamples", "200"]
    rc, _, err = _cli(["compare", "s", "mv", *common], capsys)
    _one_line_error(rc, err, "s is a stereo study", "mv a multiview study", "--task stereo", "--task multiview")
    rc, _, err = _cli(["compare", "s", "s", "--bags", "5:3", *common], capsys)
    _one_line_error(rc, err, "--bags", "--task multiview")
    assert not (tmp_path / "cache").exists()  # refused before any evaluation


# ------------------------------------------------------------------------------ 11. what an interrupted command says

def test_each_command_says_what_an_interruption_leaves():
    from tuner.cli import RESUME_NOTE, build_parser
    ap = build_parser()

    def note(*argv):
        return getattr(ap.parse_args(list(argv)), "on_interrupt", None)
    assert note("run") == RESUME_NOTE and note("findings") == RESUME_NOTE  # studies resume
    assert "resume" not in note("test", "--study", "x") and "written only when it finishes" in note("test", "--study", "x")
    assert "resume" not in note("calibrate")
    for cmd in (["evaluate"], ["table"], ["results"], ["dashboard"], ["plot"], ["studies"]):  # nothing to keep
        assert note(*cmd) is None, cmd


def test_a_terminated_test_run_does_not_promise_a_resume(tiny, tmp_path, capsys):
    """SIGTERM (a scheduler's time limit) in the middle of `tune test`'s runs, in this very process: the message
    says the test run is not written and to rerun it, not that completed trials are kept and it resumes."""
    import os
    import signal
    import threading
    import time

    from tuner import cli
    st = tmp_path / "st"
    rc, out, err = _cli(["run", "--data", tiny, *FAST, "--studies-dir", st, "--n-trials", "1", "--no-test",
                         "--fix", "max_iters=1000", "--study", "s"], capsys)
    assert rc == 0, err
    caught = []
    previous = signal.signal(signal.SIGTERM, lambda *a: caught.append(a))  # a late signal must not end pytest

    def terminate_while_running():
        deadline = time.time() + 60
        while time.time() < deadline and signal.getsignal(signal.SIGTERM) is not cli._raise_terminated:
            time.sleep(0.01)
        time.sleep(1.0)  # inside the 2000 runs (about 20 ms each here)
        if signal.getsignal(signal.SIGTERM) is cli._raise_terminated:
            os.kill(os.getpid(), signal.SIGTERM)
    killer = threading.Thread(target=terminate_while_running, daemon=True)
    killer.start()
    try:
        rc, out, err = _cli(["test", "--study", "s", "--studies-dir", st, "--scenes", "fountain-P11", "--runs", "2000",
                             "--reference", "none", "--ci", "none", "--jobs", "1", "--quiet"], capsys)
    finally:
        killer.join(timeout=70)
        signal.signal(signal.SIGTERM, previous)
    assert rc == 128 + signal.SIGTERM, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines[-1] == ("tune: terminated (SIGTERM); a test run is written only when it finishes (test.json keeps "
                         "the last finished one); rerun the command"), err
    assert "resume" not in err and not (st / "s" / "test.json").exists()


def test_calibrate_says_it_takes_no_storage(tmp_path, capsys):
    """`tune calibrate --storage URL` was accepted and ignored (a calibration lives in <studies dir>/budgets.json):
    a user expecting workers to share it through PostgreSQL got nothing. One line, the password never echoed."""
    rc, out, err = _cli(["calibrate", "--storage", "postgresql://u:s3cret@127.0.0.1:1/db", "--studies-dir",
                         tmp_path / "studies"], capsys)
    _one_line_error(rc, err, "argument --storage", "budgets.json", "drop --storage", "--studies-dir")
    assert "s3cret" not in err and not (tmp_path / "studies").exists()


# ------------------------------------------------------------------------------ a study that fixed max_iters

def test_a_fixed_gamma_says_no_gamma_max_was_calibrated(tiny, tmp_path, capsys):
    """With --fix max_iters no calibration is made: the frozen table printed 'Gamma_max None' and the HTML report
    'Gamma_max = None iterations'. Both now say it was not calibrated, and why."""
    st = tmp_path / "st"
    rc, out, err = _cli(["run", "--data", tiny, *FAST, "--studies-dir", st, "--fix", "max_iters=500", "--no-test",
                         "--n-trials", "1", "--study", "fixed-gamma"], capsys)
    assert rc == 0, err
    assert "None" not in out and "Gamma_max not calibrated (max_iters fixed)" in out, out
    rc, out, err = _cli(["plot", "--study", "fixed-gamma", "--studies-dir", st], capsys)
    assert rc == 0, err
    html = (st / "fixed-gamma" / "report.html").read_text()
    assert "Gamma_max = None" not in html and "Gamma_max not calibrated (max_iters fixed)" in html



def test_fix_max_iters_calibrated_pins_gamma_to_the_calibrated_gamma_max(tiny, tmp_path, capsys):
    """--fix max_iters=calibrated (accepted by the --fix check, documented in tuner/space.py) made no
    calibration, then 'internal error: TypeError: int() argument must be ... not NoneType'."""
    import yaml
    st = tmp_path / "st"
    rc, out, err = _cli(["run", "--data", tiny, *FAST, "--studies-dir", st, "--fix", "max_iters=calibrated",
                         "--calibration-pairs", "1", "--no-test", "--n-trials", "1", "--study", "calibrated-gamma"],
                        capsys)
    # Gamma_max(B) is the cap whose median time is at the budget: the one trial pinned there may time just over
    # it on a loaded machine (CI's other test process), a clean "no feasible trial" stop, not the bug. The pin is
    # checked in the storage either way; the frozen file too when the trial was within budget.
    assert rc == 0 or (rc == 2 and "no feasible completed trial yet" in err and "internal error" not in err), err
    import optuna
    study = optuna.load_study(study_name="calibrated-gamma", storage=f"sqlite:///{st / 'optuna.db'}")
    gmax = study.user_attrs["budget"]["gamma_max"]
    assert isinstance(gmax, int) and gmax > 0
    assert study.user_attrs["search_space_resolved"]["fixed"]["max_iters"] == gmax
    assert [t.state.name for t in study.trials] == ["COMPLETE"]
    if rc == 0:
        frozen = yaml.safe_load((st / "calibrated-gamma" / "frozen.yaml").read_text())
        assert frozen["budget"]["gamma_max"] == gmax
        assert frozen["fixed"]["max_iters"] == frozen["config"]["geometry"]["max_iters"] == gmax


def test_pareto_span_without_a_pareto_objective_is_refused(tiny, tmp_path, capsys):
    """--pareto-span sizes a pareto study's Gamma range; on an mAA10 study it was ignored, unsaid. One line before
    any work (no storage made)."""
    st = tmp_path / "st"
    rc, _, err = _cli(["run", "--data", tiny, *FAST, "--studies-dir", st, "--pareto-span", "2", "--no-test",
                       "--n-trials", "1", "--fix", "max_iters=500"], capsys)
    _one_line_error(rc, err, "--pareto-span 2 applies to a pareto study only", "add --objective pareto")
    assert not (st / "optuna.db").exists()

# ------------------------------------------------------------------------------ viz --bag on stereo figures

@pytest.mark.parametrize("extra, what", [([], "--task stereo draws stereo pairs"),
                                         (["--task", "stereo"], "--task stereo draws stereo pairs")])
def test_viz_bag_without_the_multiview_task_is_refused(extra, what, tiny, tmp_path, capsys):
    """`tune viz --bag 5:0` without --task multiview drew stereo pairs and ignored the bag, unsaid. One line
    naming --bag and the fix, before any feature is computed (nothing written)."""
    out = tmp_path / "figs"
    rc, _, err = _cli(["viz", "--data", tiny, "--feature", "sift", "--num-features", "256", "--bag", "5:0",
                       "--out", out, "--cache", tmp_path / "cache", *extra], capsys)
    _one_line_error(rc, err, "--bag 5:0", what, "add --task multiview")
    assert not out.exists()


@pytest.mark.parametrize("what", ["config", "study", "compare"])
def test_viz_pipeline_option_beside_a_configuration_is_refused(what, tiny, tmp_path, capsys):
    """`tune viz --config FILE --ratio 0.5` (or --study / --compare with a pipeline option) drew the file's or the
    study's settings and ignored the typed option, unsaid. One line naming it, before any figure."""
    conf = tmp_path / "a.yaml"
    conf.write_text("feature: sift\nnum_features: 256\nratio: 0.8\n")
    st = tmp_path / "st"
    (st / "X").mkdir(parents=True)
    (st / "X" / "frozen.yaml").write_text("study: X\ntrial: 0\nconfig:\n  feature: {name: sift, num_features: 256}\n")
    src, opt = {"config": (["--config", conf], ["--ratio", "0.5"]), "study": (["--study", "X"], ["--num-features", "512"]),
                "compare": (["--compare", conf, "X"], ["--ransac", "magsac"])}[what]
    out = tmp_path / "figs"
    rc, _, err = _cli(["viz", "--data", tiny, *src, *opt, "--studies-dir", st, "--out", out, "--cache",
                       tmp_path / "cache"], capsys)
    _one_line_error(rc, err, f"{opt[0]} does not apply with --{what}", "drop it")
    assert not out.exists()


@pytest.mark.parametrize("opts, needle", [
    (["--worst", "0", "--best", "0", "--random", "0"], "--worst 0 --best 0 --random 0 selects no pair to draw"),
    (["--no-gallery", "--gallery", "g.html"], "--gallery g.html does not apply with --no-gallery"),
])
def test_viz_options_that_draw_nothing_or_contradict_are_refused(opts, needle, tiny, tmp_path, capsys):
    """`tune viz --worst 0 --best 0 --random 0` evaluated every pair, then wrote an empty gallery, exit 0; --gallery
    beside --no-gallery was ignored. One line each, before any feature is computed (nothing written)."""
    out = tmp_path / "figs"
    rc, _, err = _cli(["viz", "--data", tiny, "--feature", "sift", "--num-features", "256", "--quiet", "--out", out,
                       "--cache", tmp_path / "cache", *opts], capsys)
    _one_line_error(rc, err, needle)
    assert not out.exists() and not (tmp_path / "cache").exists()


def test_test_reference_of_another_task_says_what_it_never_tuned(tiny, tmp_path, capsys):
    """`tune test --reference MV` (or `tune run --reference MV`) with MV a multiview study: the stereo test was compared
    with MV's r and its untuned eta 0.5 px and Gamma 1000, labelled like any tuned study, unsaid (`tune compare`
    says so). Now one warning line naming them."""
    import yaml
    sdir = tmp_path / "studies"
    config = {"feature": {"name": "sift", "num_features": 256}, "matching": {"ratio": 0.74},
              "geometry": {"ransac": "degensac", "threshold": 0.5, "max_iters": 1000}}
    for name, task, params in (("mv", "multiview", {"ratio": 0.74}), ("s", "stereo", {"ratio": 0.74, "threshold": 0.5})):
        (sdir / name).mkdir(parents=True)
        (sdir / name / "frozen.yaml").write_text(yaml.safe_dump({
            "study": name, "trial": 0, "task": task, "params": params, "config": config,
            "data": {"root": str(tiny), "test_scenes": ["fountain-P11"]}}))
    rc, out, err = _cli(["test", "--study", "s", "--reference", "mv", "--runs", "1", "--cache", tmp_path / "cache",
                         "--studies-dir", sdir, "--quiet", "--ci-resamples", "200", "--jobs", "1"], capsys)
    assert rc == 0, err
    warnings = [ln for ln in err.splitlines() if "--reference" in ln]
    assert warnings == ["warning: --reference mv is a multiview study: it tuned ratio for the multiview task, not for "
                        "the stereo test it is compared on; its eta 0.5 px, Gamma 1000 were never tuned and run as "
                        "they are"], err


def test_viz_gallery_not_named_html_is_refused_and_the_file_kept(tiny, tmp_path, capsys):
    """`tune viz --gallery studies/S/frozen.yaml` (a slip for --config) wrote the gallery's HTML over the study's frozen
    settings (or over a test.json, an image), exit 0. Now one line before any work, the file untouched."""
    victim = tmp_path / "frozen.yaml"
    victim.write_text("study: S\n")
    rc, _, err = _cli(["viz", "--data", tiny, "--feature", "sift", "--num-features", "256", "--quiet", "--worst", "1",
                       "--best", "0", "--random", "0", "--out", tmp_path / "figs", "--cache", tmp_path / "cache",
                       "--gallery", victim], capsys)
    _one_line_error(rc, err, f"--gallery {victim}: tune viz writes the gallery as an HTML page", "name it .html")
    assert victim.read_text() == "study: S\n" and not (tmp_path / "cache").exists()


def _frozen_only(sdir, name: str, task: str, root):
    """A studies folder holding study ``name``'s frozen.yaml alone (``task``, r 0.8, 256 SIFT, DEGENSAC, tested on
    fountain-P11 of ``root``): ``sdir``."""
    import yaml
    (sdir / name).mkdir(parents=True)
    (sdir / name / "frozen.yaml").write_text(yaml.safe_dump({
        "study": name, "trial": 0, "task": task, "params": {"ratio": 0.8},
        "config": {"feature": {"name": "sift", "num_features": 256}, "geometry": {"ransac": "degensac"}},
        "data": {"root": str(root), "test_scenes": ["fountain-P11"]}}))
    return sdir


def test_test_workers_of_a_stereo_study_is_refused(tiny, tmp_path, capsys):
    """`tune test --study S --workers 2` (multiview bag processes) of a stereo study ran the test with --workers
    ignored, unsaid. One line before any work."""
    sdir = _frozen_only(tmp_path / "studies", "s", "stereo", tiny)
    rc, _, err = _cli(["test", "--study", "s", "--workers", "2", "--runs", "1", "--reference", "none", "--cache",
                       tmp_path / "cache", "--studies-dir", sdir, "--quiet", "--jobs", "1"], capsys)
    _one_line_error(rc, err, "--workers is an option of the multiview / reconstruction task (its parallel processes), "
                             "and study s is a stereo study: drop --workers")
    assert not (sdir / "s" / "test.json").exists()


def test_test_max_pairs_of_a_multiview_study_is_said(tiny, tmp_path, capsys):
    """`tune test --study MV --max-pairs 2` tested every bag, the option ignored, unsaid. One warning line (the test
    then stops here: 2 images make no multiview bag)."""
    sdir = _frozen_only(tmp_path / "studies", "mv", "multiview", tiny)
    rc, _, err = _cli(["test", "--study", "mv", "--max-pairs", "2", "--runs", "1", "--reference", "none", "--cache",
                       tmp_path / "cache", "--studies-dir", sdir, "--quiet"], capsys)
    assert err.splitlines()[0] == ("warning: --max-pairs: the multiview task does not use it (COLMAP reconstructs each "
                                   "bag whole, with its own RANSAC, untimed); ignored"), err


@pytest.mark.parametrize("extra, why", [([], "without --study (or a frozen.yaml) naming its scenes"),
                                        (["--scenes", "fountain-P11"], "beside --scenes")])
def test_viz_split_that_chooses_nothing_is_refused(extra, why, tiny, tmp_path, capsys):
    """`tune viz --split val` picks a study's validation scenes: without a study, or beside --scenes, it was ignored
    (the data's scenes, or the named ones, drawn), unsaid. One line before any work."""
    rc, _, err = _cli(["viz", "--data", tiny, "--feature", "sift", "--num-features", "256", "--quiet", "--split", "val",
                       "--out", tmp_path / "figs", "--cache", tmp_path / "cache", *extra], capsys)
    _one_line_error(rc, err, f"--split val chooses a study's validation or test scenes, and does not apply {why}")
    assert not (tmp_path / "cache").exists()


@pytest.mark.parametrize("opts, needle", [
    (["--num", "5"], "--num does not apply here: --worst / --best / --random pick the pairs of one configuration"),
    (["--pairs", "0004.jpg|0005.jpg", "--worst", "3"], "--worst does not apply here: --pairs / --pair name the pairs"),
    (["--task", "multiview", "--random", "4"], "--random does not apply here: --task multiview draws multiview bags"),
    (["--compare", "a.yaml", "a.yaml", "--best", "1"], "--best does not apply here: --compare draws the --num pairs"),
])
def test_viz_pair_choices_that_do_not_apply_are_refused(opts, needle, tiny, tmp_path, capsys):
    """`tune viz --num 5` without --compare, --worst beside --pairs, --random with --task multiview, --best with
    --compare: each was ignored (other pairs, or none, drawn), unsaid. One line before any work."""
    (tmp_path / "a.yaml").write_text("feature: sift\nnum_features: 256\n")
    opts = [str(tmp_path / o) if o == "a.yaml" else o for o in opts]
    pipeline = [] if "--compare" in opts else ["--feature", "sift", "--num-features", "256"]
    rc, _, err = _cli(["viz", "--data", tiny, *pipeline, "--quiet", "--out", tmp_path / "figs", "--cache",
                       tmp_path / "cache", *opts], capsys)
    _one_line_error(rc, err, needle, "drop it")
    assert not (tmp_path / "cache").exists()


def test_evaluate_estimator_options_of_a_multiview_evaluation_are_said(tmp_path, capsys):
    """`tune evaluate --task multiview --threshold 2 --ransac magsac`: COLMAP runs its own RANSAC, the options were
    ignored (and shown in the configuration line as if used), unsaid. One warning line, with the task's notes."""
    from tests.conftest import copy_strecha_subset
    data = copy_strecha_subset(tmp_path / "data", ["0003.jpg", "0004.jpg", "0005.jpg"])
    gt = ["--gt-dir", tmp_path / "gt"]
    rc, _, err = _cli(["data", "build-gt", "--data", data, "--num-features", "1024", "--max-image-size", "1024",
                       "--quiet", *gt], capsys)
    assert rc == 0, err
    rc, _, err = _cli(["evaluate", "--data", data, "--task", "multiview", "--bags", "3:1", "--num-features", "256",
                       "--threshold", "2", "--ransac", "magsac", "--quiet", "--cache", tmp_path / "cache", *gt], capsys)
    assert rc == 0, err
    assert err.strip() == ("warning: --ransac, --threshold: the multiview task does not use them (COLMAP "
                           "reconstructs each bag whole, with its own RANSAC); ignored"), err


def test_a_resume_with_another_sampler_says_so_and_each_trial_records_its_sampler(tiny, tmp_path, capsys):
    """Resuming a study with another --sampler was allowed (it changes no measurement) but unsaid: the study's
    'sampler' attribute kept the creator's (tpe) while this worker drew its trials at random. Now one warning,
    and every trial records the sampler that drew it."""
    import optuna
    st = tmp_path / "st"
    common = ["run", "--data", tiny, *FAST, "--studies-dir", st, "--fix", "max_iters=500", "--no-test",
              "--study", "two-samplers"]
    rc, _, err = _cli([*common, "--n-trials", "1"], capsys)
    assert rc == 0 and "sampler" not in err, err
    rc, _, err = _cli([*common, "--n-trials", "2", "--sampler", "random"], capsys)
    assert rc == 0, err
    said = [ln for ln in err.splitlines() if "sampler" in ln]
    assert len(said) == 1 and "created with sampler tpe" in said[0] and "samples with random" in said[0], err
    study = optuna.load_study(study_name="two-samplers", storage=f"sqlite:///{st / 'optuna.db'}")
    assert study.user_attrs["sampler"] == "tpe"
    assert [t.user_attrs.get("sampler") for t in study.trials] == ["tpe", "random"]
