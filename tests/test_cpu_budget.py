"""The time budget B is estimator CPU time (issue 31): a library call that waits costs nothing against B, one that
computes does, and CPU-bound neighbours on the machine do not change the measured cost. Stored calibrations and
studies timed in wall-clock seconds are never mixed with CPU-time ones."""
from __future__ import annotations

import json
import multiprocessing as mp
import time

import numpy as np
import pytest

from tests.conftest import DATA

# a pure horizontal translation: x2 = x1 + (10, 0), so F = [e']_x with e' = (1, 0, 0): x2^T F x1 = y1 - y2 = 0
F_TRANSLATION = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
SECONDS_PER_ITER = 2e-7  # the fake estimators' cost model: Gamma x this many seconds per call


def _points(n: int = 40):
    rng = np.random.default_rng(0)
    p1 = rng.uniform(0, 500, (n, 2))
    return p1, p1 + np.array([10.0, 0.0])


def _spin_cpu(seconds: float) -> None:
    """Busy-wait until this process has used ``seconds`` of CPU (not wall) time."""
    c0 = time.process_time()
    x = 0
    while time.process_time() - c0 < seconds:
        x += 1


def _fake_estimators():
    from pipeline.geometry.base import Estimator, RawSolution, timed

    class Sleeper(Estimator):
        """Waits (an I/O-bound or descheduled call): wall time, no CPU time."""
        name = "test-sleeper"

        def _solve(self, pts1, pts2, threshold, confidence, max_iters, seed, sizes):
            with timed() as t:
                time.sleep(max_iters * SECONDS_PER_ITER)
            return RawSolution(F_TRANSLATION.copy(), None, t.seconds)

    class Spinner(Estimator):
        """Computes: CPU time."""
        name = "test-spinner"

        def _solve(self, pts1, pts2, threshold, confidence, max_iters, seed, sizes):
            with timed() as t:
                _spin_cpu(max_iters * SECONDS_PER_ITER)
            return RawSolution(F_TRANSLATION.copy(), None, t.seconds)
    return Sleeper, Spinner


@pytest.fixture
def fakes(monkeypatch):
    """The two fake estimators registered for the test only (the registry and the instance cache restored)."""
    from pipeline.geometry import _INSTANCES, ESTIMATORS
    sleeper, spinner = _fake_estimators()
    monkeypatch.setitem(ESTIMATORS._items, sleeper.name, sleeper)
    monkeypatch.setitem(ESTIMATORS._items, spinner.name, spinner)
    monkeypatch.delitem(_INSTANCES, sleeper.name, raising=False)
    monkeypatch.delitem(_INSTANCES, spinner.name, raising=False)
    return sleeper.name, spinner.name


def test_a_waiting_estimator_costs_no_cpu_seconds_and_a_computing_one_does(fakes):
    from pipeline.geometry import estimate
    sleeper, spinner = fakes
    p1, p2 = _points()
    gamma = 1_000_000  # 0.2 s of the cost model
    slept = estimate(sleeper, p1, p2, threshold=0.5, confidence=0.99, max_iters=gamma)
    spun = estimate(spinner, p1, p2, threshold=0.5, confidence=0.99, max_iters=gamma)
    assert slept.ok and spun.ok and slept.num_inliers == len(p1)  # the truth F: every point an inlier
    assert slept.wall_seconds >= 0.2 and slept.seconds < 0.05, (slept.seconds, slept.wall_seconds)
    assert spun.seconds >= 0.2 and spun.wall_seconds >= spun.seconds * 0.95, (spun.seconds, spun.wall_seconds)


def test_only_the_computing_estimator_counts_against_the_budget(fakes):
    """Known truth: the spinner's cost is Gamma x 2e-7 CPU s, so Gamma_max(0.1 s) = 500,000; the sleeper costs no CPU
    at any cap, so its Gamma_max is the ceiling (with wall time, as before, both gave ~500,000)."""
    from tuner.budget import GAMMA_CEILING, Calibration, _measure, cap_timer
    sleeper, spinner = fakes
    p1, p2 = _points()
    matches = [(p1, p2, ((600.0, 600.0), (600.0, 600.0)))] * 3
    B = 0.1
    got = {}
    for name in (sleeper, spinner):
        wall: list = []
        with cap_timer(name, matches, 0.5, 0.99) as time_cap:
            curve = _measure(name, time_cap, B, GAMMA_CEILING, progress=False, wall_curve=wall)
        got[name] = Calibration(estimator=name, feature={}, ratio=0.9, threshold=0.5, pairs=3,
                                curve=[list(c) for c in curve]).gamma_max(B)
        assert [w[0] for w in wall] == [c[0] for c in curve]  # wall time recorded at every cap, beside it
        assert wall[-1][1] >= curve[-1][0] * SECONDS_PER_ITER * 0.95, (wall, curve)  # both waited / spun that long
    assert got[sleeper] == GAMMA_CEILING, got
    assert 0.8 * 500_000 <= got[spinner] <= 1.02 * 500_000, got


# -- a real estimator beside CPU-bound neighbours --------------------------------------------------------------------

def _hog(seconds: float) -> None:  # module level: a spawned process imports it
    t_end = time.monotonic() + seconds
    x = 0
    while time.monotonic() < t_end:
        x += 1


def _sift_matches(scene, pairs, n_features=2048, ratio=0.8):
    """Tentative matches of real image pairs: OpenCV SIFT + Lowe's ratio test (what `tune calibrate` times)."""
    import cv2
    sift = cv2.SIFT_create(n_features)
    feats = {}
    for name in {n for p in pairs for n in p}:
        img = cv2.imread(str(scene / "images" / name), cv2.IMREAD_GRAYSCALE)
        kp, desc = sift.detectAndCompute(img, None)
        feats[name] = (np.array([k.pt for k in kp], np.float64), desc, (img.shape[1], img.shape[0]))
    bf = cv2.BFMatcher(cv2.NORM_L2)
    out = []
    for a, b in pairs:
        (ka, da, sa), (kb, db, sb) = feats[a], feats[b]
        good = [m for m, n in bf.knnMatch(da, db, k=2) if m.distance < ratio * n.distance]
        out.append((ka[[m.queryIdx for m in good]], kb[[m.trainIdx for m in good]], (sa, sb)))
    return out


def _medians(time_cap, caps, repeats=2):
    """Median CPU and wall seconds per pair at each cap (every pair timed ``repeats`` times)."""
    out = {}
    for g in caps:
        got = [x for _ in range(repeats) for x in time_cap(g)]
        out[g] = (float(np.median([c for c, _ in got])), float(np.median([w for _, w in got])))
    return out


def test_real_calibration_beside_two_cpu_hogs_measures_what_it_measures_alone():
    """DEGENSAC on real fountain-P11 SIFT matches, 2 caps, timed alone and then beside two spinning processes (as many
    as this machine's 2 CI cores): the median CPU seconds per pair stay within 1.6x (wall time roughly doubled: the
    issue measured 1.9-2.1x on 2 cores, and this test failed that way before the budget was CPU time)."""
    scene = DATA / "strecha" / "fountain-P11"
    if not scene.is_dir():
        pytest.skip(f"real data not found at {scene}")
    from pipeline.geometry import ESTIMATORS
    try:
        ESTIMATORS.get("degensac").check_available()
    except Exception as e:  # noqa: BLE001 - an optional library
        pytest.skip(str(e))
    from tuner.budget import cap_timer
    matches = _sift_matches(scene, [("0000.jpg", "0001.jpg"), ("0001.jpg", "0002.jpg")])
    caps = (4_000, 16_000)
    with cap_timer("degensac", matches, 0.5, 0.999999, seed=0) as time_cap:
        time_cap(1000)  # warm up (imports, first-call allocations)
        quiet = _medians(time_cap, caps)
        ctx = mp.get_context("spawn")
        hogs = [ctx.Process(target=_hog, args=(60.0,), daemon=True) for _ in range(2)]
        for h in hogs:
            h.start()
        try:
            time.sleep(1.0)  # both spinning (a spawned child imports for a moment first)
            loaded = _medians(time_cap, caps)
        finally:
            for h in hogs:
                h.terminate()
            for h in hogs:
                h.join(10)
    for g in caps:
        q, h = quiet[g][0], loaded[g][0]
        assert q > 0 and h <= 1.6 * q and h >= q / 1.6, (g, quiet, loaded)
    print("CPU, wall median s per pair (quiet, beside two hogs):", quiet, loaded)


# -- wall-clock calibrations and studies stored before -----------------------------------------------------------------

@pytest.fixture
def tiny(tmp_path, monkeypatch):
    """Two real fountain-P11 images, caches and studies under tmp_path."""
    from tests.conftest import copy_strecha_subset
    monkeypatch.setenv("IMTUNE_CACHE", str(tmp_path / "cache"))
    return copy_strecha_subset(tmp_path / "data", ["0004.jpg", "0005.jpg"])


FAST = ["--num-features", "256", "--jobs", "1", "--quiet"]


def _cli(args, capsys):
    from tuner.cli import main
    capsys.readouterr()
    try:
        rc = main([str(a) for a in args])
    except SystemExit as e:
        rc = e.code
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_a_stored_wall_clock_calibration_is_measured_again_in_cpu_seconds(tiny, tmp_path, capsys):
    st = tmp_path / "st"
    cmd = ["calibrate", "--data", tiny, *FAST, "--studies-dir", st, "--pairs", "1", "--budget", "0.005", "--json"]
    rc, out, err = _cli(cmd, capsys)
    assert rc == 0, err
    first = json.loads(out)["calibration"]
    assert first["clock"] == "cpu" and len(first["wall_curve"]) == len(first["curve"])
    # the same entry as imtune stored it before the CPU-time budget: no clock, wall-clock seconds
    store = st / "budgets.json"
    data = json.loads(store.read_text())
    (key, entry), = data.items()
    old = {k: v for k, v in entry.items() if k not in ("clock", "wall_curve")}
    old["created"] = "2026-01-01T00:00:00+00:00"
    store.write_text(json.dumps({key: old}))
    rc, out, err = _cli(cmd, capsys)
    assert rc == 0, err
    again = json.loads(out)["calibration"]
    assert again["created"] != old["created"] and again["clock"] == "cpu", again  # measured again, not reused
    assert json.loads(store.read_text())[key]["clock"] == "cpu"  # and the stored entry replaced
    rc, out, err = _cli(cmd, capsys)  # a CPU-time one is reused
    assert rc == 0 and json.loads(out)["calibration"]["created"] == again["created"]


def test_a_study_timed_in_wall_clock_seconds_is_refused_with_one_line(tiny, tmp_path, capsys):
    import optuna

    from tuner.storage import open_storage
    st = tmp_path / "st"
    storage = f"sqlite:///{tmp_path / 'studies.db'}"
    run = ["run", "--data", tiny, *FAST, "--studies-dir", st, "--storage", storage, "--fix", "max_iters=1000",
           "--no-test", "--study", "old-study"]  # a pinned Gamma: no calibration
    rc, out, err = _cli([*run, "--n-trials", "1"], capsys)
    assert rc == 0, err
    study = optuna.load_study(study_name="old-study", storage=open_storage(storage, heartbeat=None))
    assert study.user_attrs["budget_clock"] == "cpu"
    study.set_user_attr("budget_clock", None)  # as a study made before the CPU-time budget (no such attribute)
    rc, out, err = _cli([*run, "--n-trials", "2"], capsys)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and "wall-clock seconds" in lines[0] and "--study" in lines[0], err


# -- what the records say ----------------------------------------------------------------------------------------------

def test_summaries_report_cpu_and_wall_seconds_apart():
    """Known truth: the budget statistic (ransac_seconds_median) is the median of the records' CPU seconds, the wall
    median is reported beside it; a multiview summary gives the mean CPU seconds per bag beside the wall seconds."""
    from pipeline.tasks.multiview import summarize_bags
    from pipeline.tasks.stereo import StereoTask, summarize
    recs = [{"err": 1.0, "NM": 10, "NI": 8, "match_seconds": 0.0, "ransac_seconds": c, "ransac_wall_seconds": w}
            for c, w in [(0.1, 0.5), (0.2, 0.3), (0.3, 0.9)]]
    s = summarize(recs, 100.0)
    assert s["ransac_seconds_median"] == pytest.approx(0.2) and s["ransac_wall_seconds_median"] == pytest.approx(0.5)
    assert StereoTask().budget_seconds(s) == pytest.approx(0.2)  # the budget bounds CPU time, not wall time
    bag = {"success": True, "RC": 100.0, "NL": 10, "TL": 3.0, "errors": [1.0], "ATE": None, "NM": 5.0}
    mv = summarize_bags([{**bag, "seconds": 4.0, "cpu_seconds": 6.0}, {**bag, "seconds": 2.0, "cpu_seconds": 2.0}])
    assert mv["seconds"] == pytest.approx(3.0) and mv["cpu_seconds"] == pytest.approx(4.0)


# -- an estimator run in-process is timed with one thread, as in a pool worker ---------------------------------------

SEEN_THREADS: list[dict] = []


def _thread_counts() -> dict:
    """The thread counts of every pool this process has loaded: BLAS / OpenMP (threadpoolctl), OpenCV, torch."""
    import cv2
    import torch
    from threadpoolctl import threadpool_info
    out = {f"{i['internal_api']}:{i['filepath'].rsplit('/', 1)[-1]}": i["num_threads"] for i in threadpool_info()}
    out.update(cv2=cv2.getNumThreads(), torch=torch.get_num_threads())
    return out


@pytest.fixture
def counting(monkeypatch):
    """An estimator (``test-threads``) that records the thread counts it runs under."""
    from pipeline.geometry import _INSTANCES, ESTIMATORS
    from pipeline.geometry.base import Estimator, RawSolution, timed

    class Counting(Estimator):
        name = "test-threads"

        def _solve(self, pts1, pts2, threshold, confidence, max_iters, seed, sizes):
            with timed() as t:
                SEEN_THREADS.append(_thread_counts())
            return RawSolution(F_TRANSLATION.copy(), None, t.seconds)
    monkeypatch.setitem(ESTIMATORS._items, Counting.name, Counting)
    monkeypatch.delitem(_INSTANCES, Counting.name, raising=False)
    SEEN_THREADS.clear()
    return Counting.name


@pytest.mark.skipif(__import__("os").cpu_count() < 2, reason="one CPU: every pool has one thread anyway")
def test_an_in_process_estimator_is_timed_with_one_thread_and_the_pools_are_restored(counting, tiny, tmp_path, capsys):
    """--jobs 1 (a trial, a test run, `tune evaluate`) and a calibration timed alone run the estimator in this
    process, whose BLAS pool had 2 threads: after the k-NN product its idle thread spun on the process's CPU clock
    (+20-55% of pydegensac's CPU seconds measured). Now every pool has one thread while the estimator runs, as in
    a pool worker, and its own size again afterwards."""
    before = _thread_counts()
    assert max(before.values()) >= 2, before  # else this test could not fail
    rc, _, err = _cli(["evaluate", "--data", tiny, "--ransac", counting, "--threshold", "1.0", *FAST], capsys)
    assert rc == 0, err
    rc, _, err = _cli(["calibrate", "--data", tiny, "--ransac", counting, *FAST, "--studies-dir", tmp_path / "st",
                       "--pairs", "1", "--budget", "0.001", "--force"], capsys)
    assert rc == 0, err
    assert len(SEEN_THREADS) >= 2, SEEN_THREADS
    for seen in SEEN_THREADS:
        assert set(seen.values()) == {1}, seen
    after = _thread_counts()  # (libraries loaded meanwhile join the list: those before are compared)
    assert {k: after[k] for k in before} == before, after
