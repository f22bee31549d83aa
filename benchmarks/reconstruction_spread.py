"""Which datasets can validate reconstruction settings (issue 44): the spread of the IMC score over random
configurations of the search space, per dataset, and Optuna's parameter importances over those trials.

    python benchmarks/reconstruction_spread.py --data /tmp/imc-all --dataset imc2023_heritage --n 12 \\
        --studies-dir /tmp/spread-studies --write

It runs ``tune --task reconstruction --data D --scenes DATASET --no-test --sampler random --pruner none --n-trials N``
(the study's first trial is the task's defaults, ``Task.start_at_defaults``; the other N - 1 are drawn at random from
``search_spaces/reconstruction.yaml``), then reads the study: the score of the defaults, and the minimum, quartiles,
maximum and standard deviation of the random trials' scores. A dataset whose random trials all score alike cannot
rank settings. The importances are Optuna's default evaluator (fANOVA) over the random trials: with a dozen trials
they are rough, and a parameter's importance means something only where the spread it explains is larger than the
run-to-run noise of one configuration (docs/reconstruction.md). ``--write`` merges the dataset's row into
``benchmarks/results/reconstruction-spread.{md,json}``.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results"
NAME = "reconstruction-spread"


def measure(a) -> dict:
    import optuna
    from optuna.trial import TrialState
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.load_study(study_name=a.study, storage=f"sqlite:///{Path(a.studies_dir) / 'optuna.db'}")
    done = [t for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)) if t.value is not None]
    defaults = [t for t in done if t.user_attrs.get("start") == "task defaults"]
    rand = [t for t in done if t.user_attrs.get("start") != "task defaults"]
    v = np.array([t.value for t in rand], float)
    row = {"dataset": a.dataset, "n_random": len(rand),
           "defaults": defaults[0].value if defaults else None,
           "min": float(v.min()), "q25": float(np.percentile(v, 25)), "median": float(np.median(v)),
           "q75": float(np.percentile(v, 75)), "max": float(v.max()), "sd": float(v.std(ddof=1)) if len(v) > 1 else None,
           "zero": int((v == 0).sum())}
    if len(rand) >= 4:
        sub = optuna.create_study(direction="maximize")
        for t in rand:
            sub.add_trial(t)
        imp = optuna.importance.get_param_importances(sub, evaluator=optuna.importance.FanovaImportanceEvaluator(
            seed=0))
        row["importances"] = {k: float(x) for k, x in imp.items()}
    return row


def write(row: dict) -> None:
    jpath, mpath = RESULTS / f"{NAME}.json", RESULTS / f"{NAME}.md"
    old = json.loads(jpath.read_text()) if jpath.is_file() else {"rows": []}
    old["rows"] = [r for r in old["rows"] if r["dataset"] != row["dataset"]] + [row]
    jpath.write_text(json.dumps(old, indent=2) + "\n")
    write_md(old, mpath)


def _f(x) -> str:
    return "?" if x is None else f"{x:.3f}"


def write_md(old: dict, mpath: Path) -> None:
    s = ["| dataset | random trials | defaults | min | quartiles | max | sd | score 0 |",
         "| --- | ---: | ---: | ---: | --- | ---: | ---: | ---: |"]
    imp, cmds = [], []
    for r in old["rows"]:
        s.append(f"| `{r['dataset']}` | {r['n_random']} | {_f(r['defaults'])} | {_f(r['min'])} | "
                 f"{_f(r['q25'])}, {_f(r['median'])}, {_f(r['q75'])} | {_f(r['max'])} | {_f(r['sd'])} | {r['zero']} |")
        if r.get("importances"):
            top = sorted(r["importances"].items(), key=lambda kv: -kv[1])
            imp.append(f"- `{r['dataset']}`: " + ", ".join(f"{k} {x:.2f}" for k, x in top) + ".")
        cmds.append(f"- `{r['dataset']}`, {r['date']}: `{r['command']}`")
    text = ["The IMC score of random configurations of `search_spaces/reconstruction.yaml` per dataset (2048 "
            "features, incremental mapper, one run each), beside the task's defaults.", "",
            "<!-- --8<-- [start:spread] -->", *s, "<!-- --8<-- [end:spread] -->", "",
            "<!-- --8<-- [start:importances] -->", "Optuna's fANOVA importances over the random trials (they sum to 1; "
            "a dozen trials: rough):", "", *imp, "<!-- --8<-- [end:importances] -->", "",
            "<!-- --8<-- [start:commands] -->", "Commands (`benchmarks/reconstruction_spread.py`):", "", *cmds,
            "<!-- --8<-- [end:commands] -->", ""]
    mpath.write_text("\n".join(text))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="a folder of IMC-format datasets")
    ap.add_argument("--dataset", required=True, help="the dataset measured")
    ap.add_argument("--n", type=int, default=12, help="trials: the defaults, then N - 1 random ones")
    ap.add_argument("--num-features", type=int, default=2048)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--studies-dir", required=True, help="where the study is written (outside the checkout)")
    ap.add_argument("--record-only", action="store_true", help="do not run: read the study")
    ap.add_argument("--write", action="store_true", help=f"merge the row into benchmarks/results/{NAME}.{{md,json}}")
    a = ap.parse_args(argv)
    if a.n < 5:
        ap.error("--n must be at least 5 (the defaults and 4 random trials)")
    a.study = f"spread-{a.dataset}"
    args = ["--task", "reconstruction", "--data", a.data, "--scenes", a.dataset, "--no-test", "--sampler", "random",
            "--pruner", "none", "--n-trials", str(a.n), "--num-features", str(a.num_features), "--seed", str(a.seed),
            "--studies-dir", a.studies_dir, "--study", a.study]
    if not a.record_only:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
        rc = subprocess.call([sys.executable, "-m", "tuner", *args], env=env)
        if rc != 0:
            print(f"tune exited with {rc}", file=sys.stderr)
            return 1
    row = measure(a)
    row.update(command="tune " + " ".join(args), date=_dt.date.today().isoformat())
    print(json.dumps(row, indent=2))
    if a.write:
        write(row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
