"""`--warm-start STUDY` (tuner.study.warm_start): the frozen optimum and the best feasible trials of other studies
in the same storage enqueued as a new study's first trials, projected into its space; real small studies on real
Strecha images (2048 SIFT, DEGENSAC, SQLite)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.conftest import DATA, ROOT, copy_strecha_subset

STRECHA = DATA / "strecha"


def test_projection_clips_drops_and_filters():
    from tuner.space import Param, SearchSpace
    from tuner.study import project_params
    space = SearchSpace(params={
        "ratio": Param("ratio", "float", 0.7, 0.95),
        "threshold": Param("threshold", "float", 0.1, 2.0, log=True),
        "max_iters": Param("max_iters", "int", 1000, 42000, log=True),
        "strategy": Param("strategy", "categorical", choices=["both", "either"])})
    got = project_params({"ratio": 0.99, "threshold": 0.05, "max_iters": 987654.6, "strategy": "uni",
                          "fginn_px": 10.0}, space)
    assert got == {"ratio": 0.95, "threshold": 0.1, "max_iters": 42000}  # clipped; Gamma capped; 'uni' and unknown dropped
    assert isinstance(got["max_iters"], int)
    assert project_params({"ratio": 0.8, "max_iters": 1234.4, "strategy": "either"}, space) == \
        {"ratio": 0.8, "max_iters": 1234, "strategy": "either"}
    stepped = SearchSpace(params={"ratio": Param("ratio", "float", 0.6, 1.0, step=0.05)})
    assert project_params({"ratio": 0.83}, stepped) == pytest.approx({"ratio": 0.85})
    assert project_params({"threshold": float("nan")}, space) == {}


needs_data = pytest.mark.skipif(not STRECHA.is_dir(), reason=f"real data not found at {STRECHA}")


@pytest.fixture(scope="module")
def data4(tmp_path_factory):
    return copy_strecha_subset(tmp_path_factory.mktemp("warm-data4"), ["0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg"])


def tune(cache, *args):
    return subprocess.run([sys.executable, "-m", "tuner", *map(str, args)], capture_output=True, text=True, cwd=ROOT,
                          env=dict(os.environ, IMTUNE_CACHE=str(cache)), timeout=900)


@needs_data
def test_warm_started_study_on_real_studies(tmp_path, data4):
    import optuna

    from tuner.protocol import best_feasible
    from tuner.storage import open_storage
    cache, storage = tmp_path / "cache", f"sqlite:///{tmp_path}/w.db"
    common = ["--data", data4, "--feature", "sift", "--scenes", "fountain-P11", "--max-pairs", "6",
              "--chunk-pairs", "3", "--storage", storage, "--studies-dir", tmp_path, "--no-test", "--quiet",
              "--sampler", "random", "--seed", "8", "--pruner", "none", "--jobs", "2"]
    # the source: 1024 SIFT, Gamma searched up to 20000 (wider than the target's 1000..5000)
    src_space = tmp_path / "src.yaml"
    src_space.write_text("params:\n  ratio: {type: float, low: 0.6, high: 1.0}\n"
                         "  threshold: {type: float, low: 0.1, high: 3.0, log: true}\n"
                         "  max_iters: {type: int, low: 1000, high: 20000, log: true}\n")
    r = tune(cache, *common, "--num-features", "1024", "--space", src_space, "--budget", "10", "--n-trials", "6",
             "--study", "src")
    assert r.returncode == 0, r.stderr[-2000:]
    dst_space = tmp_path / "dst.yaml"
    dst_space.write_text("params:\n  ratio: {type: float, low: 0.7, high: 0.9}\n"
                         "  threshold: {type: float, low: 0.2, high: 1.0, log: true}\n"
                         "  max_iters: {type: int, low: 1000, high: 5000, log: true}\n")
    r = tune(cache, *common, "--num-features", "2048", "--space", dst_space, "--budget", "10", "--n-trials", "5",
             "--study", "dst", "--warm-start", "src")
    assert r.returncode == 0, r.stderr[-2000:]
    st = open_storage(storage, heartbeat=None)
    src = optuna.load_study(study_name="src", storage=st)
    dst = optuna.load_study(study_name="dst", storage=st)
    enq = dst.user_attrs["warm_start"]
    assert 1 <= len(enq) <= 4 and enq[0]["trial"] == best_feasible(src).number  # the optimum first
    for e, t in zip(enq, dst.trials):
        assert t.user_attrs["warm_start"] == f"src#{e['trial']}" and t.params == e["params"]
        sp = src.trials[e["trial"]].params
        assert t.params["ratio"] == pytest.approx(min(max(sp["ratio"], 0.7), 0.9))
        assert t.params["threshold"] == pytest.approx(min(max(sp["threshold"], 0.2), 1.0))
        assert t.params["max_iters"] == min(max(sp["max_iters"], 1000), 5000)  # capped by this study's range
    # the rest were sampled as usual; a rerun (the study has trials) enqueues nothing more
    r = tune(cache, *common, "--num-features", "2048", "--space", dst_space, "--budget", "10", "--n-trials", "6",
             "--study", "dst", "--warm-start", "src")
    assert r.returncode == 0, r.stderr[-2000:]
    dst = optuna.load_study(study_name="dst", storage=st)
    assert len(dst.trials) == 6 and sum("warm_start" in t.user_attrs for t in dst.trials) == len(enq)
    # an unknown source: one line naming the studies, exit 2
    r = tune(cache, *common, "--num-features", "2048", "--space", dst_space, "--budget", "10", "--n-trials", "6",
             "--study", "dst", "--warm-start", "nosuch")
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "nosuch" in lines[0] and "src" in lines[0], r.stderr
    print(f"WARM START: {len(enq)} trials from src projected into dst ({[e['params'] for e in enq]})")


@needs_data
def test_warm_start_carries_the_sources_fixed_values(tmp_path, data4):
    """A source that fixed r and Gamma (--fix) and searched eta: its optimum is (eta*, r 0.9, Gamma 500). A study
    searching all three started from eta* with r and Gamma drawn at random (r 0.70, Gamma 878,818 here: over the
    budget), which is no warm start from that optimum."""
    import optuna

    from tuner.storage import open_storage
    cache, storage = tmp_path / "cache", f"sqlite:///{tmp_path}/w.db"
    common = ["--data", data4, "--feature", "sift", "--num-features", "512", "--scenes", "fountain-P11",
              "--max-pairs", "3", "--storage", storage, "--studies-dir", tmp_path, "--no-test", "--quiet",
              "--sampler", "random", "--seed", "3", "--pruner", "none", "--jobs", "1", "--n-trials", "1"]
    space = tmp_path / "space.yaml"
    space.write_text("params:\n  ratio: {type: float, low: 0.6, high: 1.0}\n"
                     "  threshold: {type: float, low: 0.1, high: 2.0, log: true}\n"
                     "  max_iters: {type: int, low: 100, high: 20000, log: true}\n")
    r = tune(cache, *common, "--space", space, "--fix", "ratio=0.9", "--fix", "max_iters=500", "--study", "src")
    assert r.returncode == 0, r.stderr[-2000:]
    r = tune(cache, *common, "--space", space, "--budget", "10", "--study", "dst", "--warm-start", "src")
    assert r.returncode == 0, r.stderr[-2000:]
    st = open_storage(storage, heartbeat=None)
    src = optuna.load_study(study_name="src", storage=st)
    dst = optuna.load_study(study_name="dst", storage=st)
    assert set(src.trials[0].params) == {"threshold"}
    first = dst.trials[0]
    assert first.user_attrs["warm_start"] == "src#0"
    assert first.params == {"threshold": pytest.approx(src.trials[0].params["threshold"]), "ratio": 0.9,
                            "max_iters": 500}
    assert dst.user_attrs["warm_start"][0]["params"]["max_iters"] == 500


def test_start_at_defaults_enqueues_the_base_values_first():
    """A new reconstruction study's first trial is its base configuration's values of the searched parameters
    (values chosen here, not the task's), clipped into the space; nothing with the grid sampler or once trials
    exist. Optuna's own in-memory storage; no data."""
    import dataclasses

    import optuna

    from pipeline.config import GeometryConfig, MapperConfig, MatchConfig, PipelineConfig
    from pipeline.tasks import task_class
    from tuner.space import Param, SearchSpace
    from tuner.study import start_at_defaults
    assert task_class("reconstruction").start_at_defaults and not task_class("stereo").start_at_defaults
    space = SearchSpace(params={
        "ratio": Param("ratio", "float", 0.6, 1.0),
        "threshold": Param("threshold", "float", 0.1, 4.0, log=True),
        "max_iters": Param("max_iters", "int", 1000, 20000, log=True),
        "min_inliers": Param("min_inliers", "int", 10, 100, log=True),
        "init_min_num_inliers": Param("init_min_num_inliers", "int", 15, 200, log=True)})
    base = dataclasses.replace(PipelineConfig(), matching=MatchConfig(ratio=0.77),
                               geometry=GeometryConfig(threshold=2.5, max_iters=50_000),
                               mapper=MapperConfig(min_inliers=21, init_min_num_inliers=40))
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="maximize")
    said = []
    got = start_at_defaults(study, space, base, "tpe", say=said.append)
    want = {"ratio": 0.77, "threshold": 2.5, "max_iters": 20000, "min_inliers": 21, "init_min_num_inliers": 40}
    assert got == want  # Gamma 50,000 clipped to the space's 20,000
    t = study.ask()  # what the sampler hands the first trial for each searched parameter
    drawn = {n: (t.suggest_int(n, p.low, p.high, log=p.log) if p.type == "int"
                 else t.suggest_float(n, p.low, p.high, log=p.log)) for n, p in space.params.items()}
    assert drawn == want and t.user_attrs["start"] == "task defaults"
    assert study.user_attrs["start_at_defaults"] == want and "the task's defaults" in said[0]
    study.tell(t, 0.5)
    assert start_at_defaults(study, space, base, "tpe") is None  # a study with trials (a resume): nothing
    fresh = optuna.create_study(direction="maximize")
    assert start_at_defaults(fresh, space, base, "grid") is None and not fresh.get_trials()
