"""The reconstruction benchmarks' records: `reconstruction_speed.py` merges a dataset measured later beside the
ones before it (each keeping its own command and date, the page's section rendered from the quoted dataset), and
`reconstruction_heldout.py`'s study-time section models the search before issue 44 as trials x the old
configuration's seconds per evaluation of the same validation datasets. Expected figures are written by hand."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str, results: Path):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.RESULTS = results  # write into the test's folder, never the checkout's results
    return mod


def _res(before: float, now: float) -> dict:
    def one(sec, feat, g, sl):
        return {"seconds": sec, "all": [sec], "phases": {"features": 0.0, "pairs": sec / 2, "mapping": sec / 4},
                "score": 0.5, "feature": feat, "eta": 1.0, "Gamma": g, "shortlist": sl}
    return {"before issue 44": one(before, "sift", 50_000, 10), "defaults now": one(now, "colmap-sift", 10_000, 20),
            "ratio_now_over_before": now / before}


def test_speed_records_merge_per_dataset(tmp_path):
    mod = _load("reconstruction_speed", tmp_path)
    mod.write({"command": "cmd A", "date": "2026-12-01", "datasets": {mod.QUOTED: _res(60.0, 30.0)}})
    mod.write({"command": "cmd B", "date": "2026-12-02", "datasets": {"heritage": _res(20.0, 10.0)}})
    rec = json.loads((tmp_path / "reconstruction-speed.json").read_text())
    assert set(rec["datasets"]) == {mod.QUOTED, "heritage"}
    assert rec["datasets"][mod.QUOTED]["command"] == "cmd A"
    assert rec["datasets"]["heritage"]["date"] == "2026-12-02"
    md = (tmp_path / "reconstruction-speed.md").read_text()
    section = md.split("[start:evaluation]")[1].split("[end:evaluation]")[0]
    assert "cmd A" in section and "cmd B" not in section  # the page quotes the 76-image dataset only
    assert "| 60.0 | 30.0 | 15.0 |" in section and "| 30.0 | 15.0 | 7.5 |" in section


def test_heldout_study_time_models_the_search_before(tmp_path):
    speed = _load("reconstruction_speed", tmp_path)
    speed.write({"command": "c", "date": "d", "datasets": {"a": _res(30.0, 10.0), "b": _res(12.0, 6.0)}})
    mod = _load("reconstruction_heldout", tmp_path)
    assert mod.before_seconds(["a", "b"]) == 42.0
    assert mod.before_seconds(["a", "missing"]) is None
    row = {"study": "s", "trials": 30, "validation": ["a", "b"], "wall_seconds": 1500.0, "search_seconds": 1200.0,
           "trial_seconds": [50.0, 10.0, 30.0, 200.0], "pruned": {"3": "bound"}}
    lines = mod.study_times([row])
    table_row = next(x for x in lines if x.startswith("| s |"))
    # 4 trials, 1 pruned; median of 10/30/50/200 by the upper middle = 50; search 20.0 min, run 25.0 min;
    # before: 30 x 42 s = 21 min
    assert table_row == "| s | 30 | 3 / 1 | 50 | 20.0 | 25.0 | 21 |"
    assert mod.study_times([{**row, "wall_seconds": None}]) == []


def test_heldout_replicated_section_reads_the_replicated_block(tmp_path):
    mod = _load("reconstruction_heldout", tmp_path)
    block = {"objective": "score", "K": 3, "score": 0.4, "score_ci": [0.3, 0.5],
             "replicates": [{"study": f"s{k}", "trial": k, "score": 0.4, "runs": 2} for k in range(3)],
             "reference": {"score": 0.36, "difference": 0.04, "ci": [-0.01, 0.09], "p_value": 0.071,
                           "verdict": "inconclusive", "per_replicate": [0.03, 0.04, 0.05]}}
    listed = block.pop("replicates")  # test.json holds the list beside the block, as record_replicated writes it
    lines = mod.replicated_section([{"study": "s0", "validation": ["v"], "test": [mod.QUOTED_TEST],
                                     "replicated": block, "replicates": listed}, {"study": "other"}])
    assert "| v | imc2025 | 3 x 2 | 0.400 [0.300, 0.500] | 0.360 | +0.040 [-0.010, +0.090] | 0.071 |" in lines
    assert any(x.startswith("- s0: inconclusive.") and "+0.030, +0.040, +0.050" in x and "s2 (trial #2) 0.400" in x
               for x in lines)
    assert mod.replicated_section([{"study": "other"}]) == []
