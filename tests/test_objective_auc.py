"""--objective auc10: a real tiny study (fountain-P11, 4 pairs, 2 trials) maximises the pose AUC@10, records it,
freezes and tests with it; a resume with another objective is refused in one line."""
import json

import pytest
import yaml

from tests.test_tuner_study import STRECHA, load, quick, tune, tuner_cache  # noqa: F401 (fixture)

pytestmark = pytest.mark.skipif(not STRECHA.is_dir(), reason=f"real data not found at {STRECHA}")


def test_auc10_study_maximises_and_records_auc(tmp_path, tuner_cache):  # noqa: F811
    args = quick(tmp_path, "--n-trials", "2", "--seed", "1", "--objective", "auc10", "--test-runs", "1",
                 ransac="cv-ransac", pairs=4)
    tune(*args, cache=tuner_cache, check=True)
    name = "sift-2048-cv-ransac-stereo-auc10"
    st = load(f"sqlite:///{tmp_path}/optuna.db", name)
    assert st.user_attrs["objective"]["name"] == "auc10"
    done = [t for t in st.trials if t.state.name == "COMPLETE"]
    assert done
    for t in done:  # the trial's value is its AUC@10, not its mAA(10)
        assert t.value == pytest.approx(t.user_attrs["auc10"])
        assert 0.0 <= t.user_attrs["auc10"] <= 1.0
    frozen = yaml.safe_load((tmp_path / name / "frozen.yaml").read_text())
    assert frozen["objective"]["name"] == "auc10"
    test = json.loads((tmp_path / name / "test.json").read_text())
    assert test["objective"]["name"] == "auc10"
    assert {"auc5", "auc10", "auc20", "mAA10"} <= set(test["mean"])
    # the same study resumed without --objective (mAA10): refused in one line, exit 2
    r = tune(*quick(tmp_path, "--n-trials", "3", "--study", name, ransac="cv-ransac", pairs=4), cache=tuner_cache)
    assert r.returncode == 2 and "maximises auc10" in r.stderr and r.stderr.strip().count("\n") == 0, r.stderr
    # an mAA10 study beside it: tables refuse to rank the two as one, --objective picks one, `studies` says which
    tune(*quick(tmp_path, "--n-trials", "1", "--study", "plain", "--no-test", ransac="cv-ransac", pairs=4),
         cache=tuner_cache, check=True)
    storage = ["--storage", f"sqlite:///{tmp_path}/optuna.db", "--studies-dir", str(tmp_path)]
    for cmd in ("results", "table"):
        r = tune(cmd, *storage, cache=tuner_cache)
        assert r.returncode == 2 and "different objectives (auc10: 1, mAA10: 1)" in r.stderr, r.stderr
        assert r.stderr.strip().count("\n") == 0
    r = tune("results", *storage, "--objective", "auc10", "--format", "json", cache=tuner_cache, check=True)
    assert name in r.stdout and "plain" not in r.stdout
    rows = {x["study"]: x for x in json.loads(tune("studies", *storage, "--json", cache=tuner_cache, check=True).stdout)}
    assert rows[name]["objective"] == "auc10" and rows["plain"]["objective"] == "mAA10"
    best = st.trials[rows[name]["best trial"]]
    assert rows[name]["best value"] == pytest.approx(best.user_attrs["auc10"])
    assert rows[name]["best mAA10"] == pytest.approx(best.user_attrs["mAA10"])
    # tune compare refuses to compare an auc10 study with an mAA10 one (before any evaluation)
    r = tune("compare", name, "plain", "--studies-dir", str(tmp_path), "--data", str(STRECHA), cache=tuner_cache)
    assert r.returncode == 2 and "different objectives" in r.stderr and r.stderr.strip().count("\n") == 0, r.stderr
    # the results table shows the test's auc10 beside mAA10
    js = json.loads(tune("results", *storage, "--objective", "auc10", "--format", "json", cache=tuner_cache,
                         check=True).stdout)
    test = json.loads((tmp_path / name / "test.json").read_text())
    assert js[0]["auc10 cv-ransac"] == pytest.approx(test["mean"]["auc10"], abs=1e-4)
    md = tune("results", *storage, "--objective", "auc10", cache=tuner_cache, check=True).stdout
    assert "auc10 cv-ransac" in md.splitlines()[0]
