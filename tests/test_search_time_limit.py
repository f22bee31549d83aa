"""The search's time limit (`--timeout`, 300 s by default for a stereo study: the main job's bound): the search stops
between trials once it is spent, and the study still freezes and tests, saying that it stopped early."""
import json

import pytest

from tests.test_tuner_study import STRECHA, quick, tune, tuner_cache  # noqa: F401

pytestmark = pytest.mark.skipif(not STRECHA.is_dir(), reason=f"real data not found at {STRECHA}")


def test_time_limit_stops_the_search_then_freezes_and_tests(tmp_path, tuner_cache):  # noqa: F811
    args = quick(tmp_path / "st", "--n-trials", "50", "--timeout", "1", "--fix", "max_iters=1000", "--seed", "1",
                 "--test-runs", "1", "--reference", "none", pairs=4)
    args[args.index("--budget") + 1] = "0.5"
    out = json.loads(tune(*args, "--json", cache=tuner_cache, check=True).stdout)
    assert out["worker"]["time_limit"] == 1
    n = len(out["worker"]["trials_run"])
    assert 1 <= n < 50 and out["worker"]["target"] == 50
    assert out["frozen"] is not None and out["test"] is not None  # frozen and tested as a full search would be
    # a rerun of the same command runs further trials (the study's target is still 50): resume, not restart
    r = tune(*args, "--quiet", cache=tuner_cache, check=True)
    assert "search: stopped at its time limit of 1 s (--timeout; 0 = none) before the target of 50 trials" in r.stdout
    assert "this worker ran 1" in r.stdout or "this worker ran 2" in r.stdout


def test_default_bound_is_the_tasks():
    from pipeline.tasks import TASKS
    from tuner.commands.study import _timeout

    class Args:
        timeout = None
        task = "stereo"
    assert _timeout(Args) == 300.0 == TASKS.get("stereo").search_seconds
    Args.task = "multiview"
    assert _timeout(Args) is None
    Args.task = "reconstruction"
    assert _timeout(Args) is None  # one evaluation takes minutes: no default bound
    Args.timeout = 0.0
    Args.task = "stereo"
    assert _timeout(Args) is None  # 0 = no limit
    Args.timeout = 42.0
    assert _timeout(Args) == 42.0
