"""Which datasets can validate reconstruction settings (issue 44): the spread of the IMC score over random
configurations of the search space, per dataset, and Optuna's parameter importances over those trials.

    python benchmarks/reconstruction_spread.py --data /tmp/imc-all --dataset imc2023_heritage --n 20 \\
        --studies-dir /tmp/spread-studies --trial-timeout 120 --write   # --mapper global, --space FILE

It runs ``tune --task reconstruction --data D --scenes DATASET --no-test --sampler random --pruner none --n-trials N``
(the study's first trial is the task's defaults, ``Task.start_at_defaults``; the other N - 1 are drawn at random from
``search_spaces/reconstruction.yaml``), then reads the study: the score of the defaults, and the minimum, quartiles,
maximum and standard deviation of the random trials' scores. A dataset whose random trials all score alike cannot
rank settings. The importances are Optuna's PED-ANOVA (what optuna-dashboard shows; fANOVA needs scikit-learn) over the
random trials, at a target quantile of 0.3: with 20 trials they are rough, and a parameter's importance means something only where the spread it explains is larger than the
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
#: PED-ANOVA's target quantile: with about ten trials Optuna's 0.1 (the best trial alone) tells nothing apart
TOP = 0.3


def measure(dataset: str, studies: list[tuple[str, str]], mapper: str = "incremental", space: str | None = None) -> dict:
    """The dataset's score in every complete trial of ``studies`` ((studies dir, study name) pairs; a trial's
    per-dataset score is its user attribute ``scenes``), one per distinct parameter set; the task's defaults
    (the trial marked ``start``) apart. Trials pruned at the mapping bound (``--trial-timeout``: user attribute
    ``pruned_reason``) have no score: they are counted (``pruned``), never scored 0 nor dropped silently."""
    import optuna
    from optuna.trial import TrialState
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    seen: dict = {}
    defaults = None
    pruned: dict = {}
    for sdir, name in studies:
        study = optuna.load_study(study_name=name, storage=f"sqlite:///{Path(sdir) / 'optuna.db'}")
        for t in study.get_trials(deepcopy=False, states=(TrialState.PRUNED,)):
            pruned.setdefault(tuple(sorted(t.params.items())), str(t.user_attrs.get("pruned_reason", "pruned")))
        for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
            sc = (t.user_attrs.get("scenes") or {}).get(dataset)
            if not sc or sc.get("score") is None:
                continue
            if t.user_attrs.get("start") == "task defaults":
                defaults = float(sc["score"])
                continue
            seen.setdefault(tuple(sorted(t.params.items())), (float(sc["score"]), t))
    v = np.array([x for x, _ in seen.values()], float)
    if not len(v):
        raise SystemExit(f"no trial of {dataset} in {studies}")
    if space is None:  # the task's own file for that mapper, named: it has changed (the global mapper's, 7 Dec 2026)
        from pipeline.tasks.reconstruction import ReconstructionTask
        space = f"search_spaces/{ReconstructionTask(mapper=mapper).space_file}"
    row = {"dataset": dataset, "mapper": mapper, "space": space, "n_random": len(v), "defaults": defaults,
           "pruned": len(pruned), "pruned_reasons": sorted(pruned.values()),
           "min": float(v.min()), "q25": float(np.percentile(v, 25)), "median": float(np.median(v)),
           "q75": float(np.percentile(v, 75)), "max": float(v.max()), "sd": float(v.std(ddof=1)) if len(v) > 1 else None,
           "zero": int((v == 0).sum()), "studies": [n for _, n in studies]}
    if len(v) >= 4:
        sub = optuna.create_study(direction="maximize")
        for x, t in seen.values():
            sub.add_trial(optuna.trial.create_trial(params=t.params, distributions=t.distributions, value=x))
        import warnings
        with warnings.catch_warnings(record=True) as caught:  # Optuna warns where it returns equal importances
            warnings.simplefilter("always", UserWarning)
            imp = optuna.importance.get_param_importances(
                sub, evaluator=optuna.importance.PedAnovaImportanceEvaluator(target_quantile=TOP))
        row["importances"] = {k: float(x) for k, x in imp.items()}
        row["importances_equal"] = any("will be equal" in str(w.message) for w in caught)
    return row


def write(row: dict) -> None:
    jpath, mpath = RESULTS / f"{NAME}.json", RESULTS / f"{NAME}.md"
    old = json.loads(jpath.read_text()) if jpath.is_file() else {"rows": []}
    def key(r):
        return r["dataset"], r.get("mapper", "incremental"), Path(r.get("space") or "reconstruction.yaml").name
    old["rows"] = [r for r in old["rows"] if key(r) != key(row)] + [row]
    jpath.write_text(json.dumps(old, indent=2) + "\n")
    write_md(old, mpath)


def _f(x) -> str:
    return "?" if x is None else f"{x:.3f}"


#: short names of datasets in the table, so that it fits a page (the dataset's folder in ../shared/data)
ALIASES = {"imc2023_theather_imc2024_church": "imc2025"}


def _mapper(r: dict) -> str:
    """The row's mapper, and its search space where it is not `reconstruction.yaml` (every row's space before the
    global mapper had its own file; a row without one was searched in it)."""
    name = Path(r["space"]).name if r.get("space") else "reconstruction.yaml"
    return r.get("mapper", "incremental") + (f" (`{name}`)" if name != "reconstruction.yaml" else "")


def _span(rows: list) -> str:
    """How many trials in how many dimensions the importances of ``rows`` come from ("7 to 19 trials in 7 to 9
    dimensions")."""
    rows = [r for r in rows if r.get("importances")]
    if not rows:
        return "no row has enough trials"

    def rng(xs):
        return f"{min(xs)}" if min(xs) == max(xs) else f"{min(xs)} to {max(xs)}"
    return (f"{rng([r['n_random'] for r in rows])} trials in {rng([len(r['importances']) for r in rows])} "
            "dimensions")


def write_md(old: dict, mpath: Path) -> None:
    s = ["| dataset, mapper | scored | pruned | defaults | min (# at 0) | quartiles | max | sd |",
         "| --- | ---: | ---: | ---: | ---: | --- | ---: | ---: |"]
    imp, cmds = [], []
    for r in sorted(old["rows"], key=lambda r: (r["dataset"], r.get("mapper", "incremental"), r.get("space") or "")):
        name = f"`{ALIASES.get(r['dataset'], r['dataset'])}`, {_mapper(r)}"
        lo = _f(r["min"]) + (f" ({r['zero']})" if r["zero"] else "")
        s.append(f"| {name} | {r['n_random']} | {r.get('pruned', '?')} | {_f(r['defaults'])} | {lo} | "
                 f"{_f(r['q25'])}, {_f(r['median'])}, {_f(r['q75'])} | {_f(r['max'])} | {_f(r['sd'])} |")
        if r.get("importances") and r.get("importances_equal"):
            imp.append(f"- `{r['dataset']}`, {_mapper(r)}: equal by construction "
                       "(too few trials, or all alike).")
        elif r.get("importances"):
            top = sorted(r["importances"].items(), key=lambda kv: -kv[1])
            imp.append(f"- `{r['dataset']}`, {_mapper(r)}: "
                       + ", ".join(f"{k} {x:.2f}" for k, x in top) + ".")
        why = "; ".join(r.get("pruned_reasons") or [])
        cmds.append(f"- `{r['dataset']}`, {_mapper(r)}, {r['date']}: `{r['command']}`"
                    + (f" (pruned: {why})" if why else "") + (f" ({r['note']})" if r.get("note") else ""))
    text = ["The IMC score per dataset and mapper of settings drawn from `search_spaces/reconstruction.yaml`, or "
            "the space the row names in `search_spaces/` (2048 features, one run each), beside the task's defaults. With `--studies`, the settings are those "
            "the named studies tried (random draws, then TPE's; studies at one sampler seed draw the same settings "
            "but Gamma, which scales with each study's calibrated Gamma_max); without, a random-sampler study's "
            "(the defaults, then random draws). `scored`: distinct settings with a score, the defaults apart; "
            "`pruned`: drawn settings whose trial was pruned (at the mapping bound `--trial-timeout`, or over the "
            "budget: each reason follows its command below); they have no score and are not in the figures (`?`: "
            "not recorded by the studies read); `min (# at 0)`: the lowest score and how "
            "many scored 0. "
            "`imc2025` is the dataset `imc2023_theather_imc2024_church` of `../shared/data/imc2025`.", "",
            "<!-- --8<-- [start:spread] -->", *s, "<!-- --8<-- [end:spread] -->", "",
            "<!-- --8<-- [start:importances] -->", "Optuna's PED-ANOVA importances over those trials (how much each "
            f"parameter decides reaching the best 30% of them; they sum to 1; {_span(old['rows'])}: rough). "
            "The global mapper does not read the incremental mapper's four thresholds (`init_min_num_inliers`, "
            "`abs_pose_min_num_inliers`, `abs_pose_max_error`, `filter_max_reproj_error`): whatever importance "
            "they get in a global row, searched in `reconstruction.yaml`, is what these few trials give to a parameter that "
            "does nothing.", "", *imp, "<!-- --8<-- [end:importances] -->", "",
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
    ap.add_argument("--mapper", default="incremental", choices=["incremental", "global"],
                    help="the mapper (tune's --mapper); the row says which")
    ap.add_argument("--trial-timeout", default=None, metavar="SECONDS|auto",
                    help="tune's bound on a trial's mapping: a trial beyond it is pruned, and counted as such")
    ap.add_argument("--space", default=None, help="tune's --space (a search-space YAML; the row names it)")
    ap.add_argument("--studies-dir", default=None, help="where the study is written (outside the checkout)")
    ap.add_argument("--record-only", action="store_true", help="do not run: read the study")
    ap.add_argument("--studies", default=None, metavar="DIR:NAME,...",
                    help="do not run: read the dataset's scores in the trials of these studies (a study validated on "
                         "several datasets records each one's score)")
    ap.add_argument("--note", default=None, help="a remark recorded after the row's command (e.g. a study stopped early)")
    ap.add_argument("--write", action="store_true", help=f"merge the row into benchmarks/results/{NAME}.{{md,json}}")
    a = ap.parse_args(argv)
    if a.n < 5:
        ap.error("--n must be at least 5 (the defaults and 4 random trials)")
    if a.trial_timeout is not None and a.trial_timeout != "auto":
        try:
            if float(a.trial_timeout) <= 0:
                raise ValueError
        except ValueError:
            ap.error(f"--trial-timeout: {a.trial_timeout!r} is neither a positive number of seconds nor 'auto'")
    if a.space is not None and not Path(a.space).is_file():
        ap.error(f"--space: no file {a.space}")
    a.study = (f"spread-{a.dataset}" + ("" if a.mapper == "incremental" else f"-{a.mapper}")
               + ("" if a.space is None else f"-{Path(a.space).stem}"))
    if not a.studies and not a.studies_dir:
        ap.error("give --studies-dir (a new random study) or --studies (trials of studies already run)")
    args = ["--task", "reconstruction", "--data", a.data, "--scenes", a.dataset, "--no-test", "--sampler", "random",
            "--pruner", "none", "--confirm", "0", "--n-trials", str(a.n), "--num-features", str(a.num_features), "--seed", str(a.seed),
            "--studies-dir", a.studies_dir, "--study", a.study, "--mapper", a.mapper]
    if a.trial_timeout is not None:
        args += ["--trial-timeout", a.trial_timeout]
    if a.space is not None:
        args += ["--space", a.space]
    if a.studies:
        pairs = [tuple(x.rsplit(":", 1)) for x in a.studies.split(",")]
        if any(len(x) != 2 for x in pairs):
            ap.error("--studies takes DIR:NAME[,DIR:NAME...]")
        row = measure(a.dataset, pairs, a.mapper, a.space)
        row.update(command=f"python benchmarks/reconstruction_spread.py --data {a.data} --dataset {a.dataset} "
                           f"--studies {a.studies}", date=_dt.date.today().isoformat())
        print(json.dumps(row, indent=2))
        if a.write:
            write(row)
        return 0
    if not a.record_only:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
        rc = subprocess.call([sys.executable, "-m", "tuner", *args], env=env)
        if rc != 0:
            print(f"tune exited with {rc}", file=sys.stderr)
            return 1
    row = measure(a.dataset, [(a.studies_dir, a.study)], a.mapper, a.space)
    # the command that reproduces the row (without --record-only, which only re-reads the study)
    given = list(sys.argv[1:] if argv is None else argv)
    if "--note" in given:
        del given[given.index("--note"):given.index("--note") + 2]
    own = " ".join(x for x in given if x != "--record-only" and not x.startswith("--note="))
    row.update(command=f"python benchmarks/reconstruction_spread.py {own} (runs: tune {' '.join(args)})",
               date=_dt.date.today().isoformat())
    if a.note:
        row["note"] = a.note
    print(json.dumps(row, indent=2))
    if a.write:
        write(row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
