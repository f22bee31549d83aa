"""The findings report: ``<studies dir>/findings/report.html`` (one section per finding: claim, paper, the rule,
the studies with links to their frozen settings and test results, the measured numbers with 95% intervals,
the paired difference, the verdict, a plot), ``report.md`` (the same text) and ``findings.json``."""
from __future__ import annotations

import datetime as _dt
import html
import json
import math
from pathlib import Path

from pipeline.errors import ImtuneError
from tuner.findings.analysis import __doc__ as RULES_DOC
from tuner.findings.definitions import BY_ID, SMALL_GAIN

RULE_TEXT = {
    "better": "paired bootstrap of mAA(10)(B) - mAA(10)(A) on the same test pairs: the 95% CI containing 0 -> "
              "inconclusive; otherwise, when the paired sign-flip test agrees (p < 0.05), CI above 0 -> holds, below "
              "0 -> does not hold, and inconclusive when it does not",
    "better_replicated": "the tuned difference mAA(10)(B) - mAA(10)(A) over K tuning replicates x the same test "
                         "pairs (variance components: pairs, tuning and seed noise each counted once; t test): the "
                         "95% CI containing 0 -> inconclusive; otherwise CI above 0 -> holds, below 0 -> does not "
                         "hold; inconclusive whenever a side has fewer than 3 replicates",
    "small_gain_replicated": f"the tuned difference mAA(10)(B) - mAA(10)(A) over K tuning replicates x the same "
                             f"test pairs (variance components; t interval): CI upper end <= {SMALL_GAIN:g} -> holds "
                             f"(at most a small gain), lower end > {SMALL_GAIN:g} -> does not hold, otherwise "
                             "inconclusive; inconclusive whenever a side has fewer than 3 replicates",
    "small_gain": f"paired bootstrap of mAA(10)(B) - mAA(10)(A): CI upper end <= {SMALL_GAIN:g} -> holds (at most a "
                  f"small gain), lower end > {SMALL_GAIN:g} -> does not hold, otherwise inconclusive",
    "regions": "flat region of the optimum = range of the parameter over the feasible trials whose validation "
               "mAA(10) lies within the best trial's 95% interval; regions that do not overlap -> the optimal "
               "values differ; both regions inside one narrow band (r: 0.05, eta: a factor 1.5) -> the same; "
               "otherwise unclear. Holds when every group differs, does not hold when one is the same, else "
               "inconclusive",
}


def rules_text(code: str = "`") -> str:
    """The analysis module's account of the rules, for a reader of the report: Sphinx roles dropped, literals
    marked with ``code`` (a backtick in Markdown, nothing in HTML), the named margin given its value."""
    import re
    text = re.sub(r":(?:func|data|mod|class):`~?([^`]+)`", code + r"\1" + code, RULES_DOC.strip())
    text = re.sub(r"``([^`]+)``", code + r"\1" + code, text)
    return text.replace("SMALL_GAIN (in mAA(10), 0..1)", f"{SMALL_GAIN:g} mAA(10)").replace("SMALL_GAIN", f"{SMALL_GAIN:g}")


def _num(v, d=4):
    if v is None:
        return "-"
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        return f"{v:.{d}f}"
    return str(v)


def _p(v) -> str:
    """A p-value to 3 decimals; below 0.001 "< 0.001" (the sign-flip p is never 0: at least 1 / (1 + resamples));
    below 0.05 with as many more decimals as it takes not to read 0.050 (0.0496: a verdict needs p < 0.05)."""
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        if v < 0.001:
            return "< 0.001"
        if v < 0.05:
            for d in range(3, 10):
                if float(f"{v:.{d}f}") < 0.05:
                    return f"{v:.{d}f}"
    return _num(v, 3)


def _n(count, word: str, plural: str | None = None) -> str:
    """"1 feasible trial", "2 feasible trials": a count with its noun in the right number (``plural``: when not
    ``word`` + "s")."""
    return f"{count} {word if count == 1 else (plural or word + 's')}"


def _p_is(v) -> str:
    """"p = 0.005" or "p < 0.001"."""
    t = _p(v)
    return f"p {t}" if t.startswith("<") else f"p = {t}"


def _ci(ci, d=4):
    return "-" if not ci else f"[{_num(float(ci[0]), d)}, {_num(float(ci[1]), d)}]"


def ground_truth_line(fs, names: list) -> str:
    """Where the scenes' poses come from (their own: Strecha's laser scan, a calibration, a pairs list; or imtune's
    SfM by `tune data build-gt`), as the stereo studies see them (the default ground-truth folder)."""
    from tuner.evaluate import load_scenes
    from tuner.formatting import ground_truth_origins, ground_truth_text
    try:
        scenes = load_scenes(Path(fs.data_root), list(names), split="all") if names else []
    except ImtuneError as e:  # the report of a run that could not load them says why elsewhere
        return f"unknown ({e})"
    return ground_truth_text(ground_truth_origins(scenes)) or "none"


def trials_held(out: dict | None) -> str:
    """What the run's studies hold, beside the trial target: a study reused from an earlier run with a larger
    --trials holds more (its optimum is frozen among all of them). "" without studies that record it."""
    held = {}
    for f in (out or {}).get("findings") or []:
        for st in ((f.get("measured") or {}).get("studies") or {}).values():
            n = (st.get("compute") or {}).get("trials")
            if n is not None:
                held[st["study"]] = int(n)
    if not held:
        return ""
    lo, hi = min(held.values()), max(held.values())
    if len(held) == 1:
        return f"; the study of this report holds {_n(lo, 'finished trial')}"
    span = f"{lo} finished trials each" if lo == hi else f"{lo}-{hi} finished trials per study"
    return f"; the {len(held)} studies of this report hold {span}"


def settings_lines(fs, out: dict | None = None) -> list[str]:
    """The report's header lines on the run's settings; ``out`` (the findings) adds the trials its studies hold."""
    m = fs.mode()
    from tuner.findings import resolved_splits
    from tuner.findings.runner import multiview_bags, multiview_notes
    from tuner.storage import storage_label
    val, test, split_source = resolved_splits(fs)
    mode = ("--quick (a reduced but real version: not the protocol; with so few trials a study can freeze a poor "
            "optimum, so a verdict may reflect one study's tuning rather than the method: rerun without --quick "
            "before citing one)") if fs.quick else "full protocol"
    return [
        f"mode: {mode}",
        f"features per image: {m['num_features']} (finding 9 also runs {2048 if m['num_features'] == 8000 else 8000})",
        f"trials per study: target {m['trials_effective']} (the multiview study: its r grid, at most as many)"
        f"{trials_held(out)}; pairs per scene: {m['max_pairs'] or 'all'}; "
        f"test runs: {m['test_runs']}; multiview bags (size:count): "
        + ", ".join(f"{size}:{count}" for size, count in multiview_bags(fs))
        + ("" if m.get("multiview_bags") else " (the protocol's)")
        + "".join(f"; {note}" for note in multiview_notes(fs)),
        f"budget: {fs.budget:g} s per pair on validation (median estimator CPU time), {fs.test_budget:g} s on test",
        f"data: {fs.data_root}; validation scenes: {', '.join(val) or 'none'}; test scenes: {', '.join(test) or 'none'} "
        f"(from {split_source})",
        f"ground truth: {ground_truth_line(fs, val + test)}",
        f"storage: {storage_label(fs.storage, fs.studies_dir)}; studies dir: {fs.studies_dir}",
        f"intervals: 95%, stratified bootstrap over test pairs ({fs.n_resamples} resamples, seed {fs.seed}); "
        f"paired differences on the same pairs; p: two-sided paired sign-flip test (Monte Carlo, {fs.n_resamples} "
        f"sign patterns: p >= {1 / (1 + fs.n_resamples):.1g})",
        (f"tuning replicates: {fs.replicates} per stereo study (studies NAME, NAME-r2, ...; each with its own sampler "
         "and estimator seeds from --seed): every tuned figure is the mean over replicates and every comparison's "
         "interval holds the tuning variance (variance components of replicates x pairs, each source counted once, "
         "t with Satterthwaite df), with P(B > A) for one new tuning of each and its interval" if fs.replicates > 1 else
         "tuning replicates: 1 (the tuning variance was not measured: every interval covers test pairs and test "
         "runs only, and a rerun with another --seed can freeze other optima; --replicates 3 measures it)"),
        f"sampling: every study's sampler is seeded from --seed {fs.seed}, so studies searching the same space draw "
        "the same first (random start-up) candidates: common random numbers, which sharpen their paired "
        "comparisons; with few trials (--quick) they can share every candidate, and findings 6 and 7 then compare "
        "optima chosen among the same candidates",
        "paper references: section / figure / table numbers, quotes and numbers checked against the text of "
        "arXiv:2003.01587v5; values only readable off a plot are marked 'not verified'",
    ]


def _pct_ci(ci) -> str:
    """" [95% CI -60.1%, -40.2%]" of a relative difference's interval (paired_relative), "" without one."""
    if not ci:
        return ""
    return f" [95% CI {100 * ci[0]:+.1f}%, {100 * ci[1]:+.1f}%]"


def paper_comparison(f: dict) -> str | None:
    """The paper's headline number beside ours, where the paper gives one (findings 1, 2, 3, 4), from the
    measured figures; also stored as ``measured["paper_comparison"]``."""
    m = f["measured"]
    st = m.get("studies") or {}
    pn = BY_ID[f["id"]].paper_numbers  # the paper's figures, stated once in the definitions

    def maa(role):
        s = st.get(role) or {}
        return s.get("mAA10") if s.get("ok") else None
    txt = None
    if f["id"] == 1 and maa("defaults") is not None and maa("tuned"):
        ours = (maa("defaults") - maa("tuned")) / maa("tuned")
        paper = pn["relative_change_of_defaults"]
        ci = (m.get("relative_change_of_defaults") or {}).get("ci")
        m["paper_comparison"] = {"paper": paper, "ours": ours, "ours_ci": ci,
                                 "what": "relative mAA(10) change of the defaults vs tuned"}
        txt = (f"relative mAA(10) of the defaults vs tuned: paper (validation) {100 * paper:+.1f}%, "
               f"here (test) {100 * ours:+.1f}%{_pct_ci(ci)}")
    elif f["id"] == 3 and maa("tuned") is not None and maa("gamma1000"):
        ours = (maa("tuned") - maa("gamma1000")) / maa("gamma1000")
        lo, hi = pn["relative_gain"]
        ci = m.get("relative_ci") if m.get("relative_to") == "gamma1000" else None
        m["paper_comparison"] = {"paper": [lo, hi], "ours": ours, "ours_ci": ci,
                                 "what": "relative gain of lifting Gamma = 1000"}
        txt = (f"relative gain of lifting Gamma = 1000: paper (validation) +{100 * lo:.0f}% to +{100 * hi:.0f}%, "
               f"here (test) {100 * ours:+.1f}%{_pct_ci(ci)}")
    elif f["id"] == 2:
        g = {r: s.get("gamma_max") for r, s in st.items() if s.get("ok")}
        if g:
            paper = pn["gamma_max"]
            # the paper's figure is the best Gamma within the budget: beside it, ours both ways, the largest
            # Gamma within the budget (calibrated) and the Gamma the tuning froze
            frozen = {r: (st[r].get("params") or {}).get("max_iters", (st[r].get("fixed") or {}).get("max_iters"))
                      for r in g}
            m["paper_comparison"] = {"paper": dict(paper), "ours": g, "ours_frozen": frozen,
                                     "what": "Gamma_max at 0.5 s (paper: Table 14's optimal Gamma); ours_frozen: "
                                             "the frozen Gamma"}
            ranking = m.get("ranking")
            if ranking:  # '>' only where the paired test separates them: shared ranks are '~'
                groups: list[list[str]] = []
                for row in ranking:
                    if groups and row.get("shared"):
                        groups[-1].append(row["name"])
                    else:
                        groups.append([row["name"]])
                order = " > ".join(" ~ ".join(g) for g in groups) + " ('~': not significantly different)"
            else:
                order = " > ".join(sorted((r for r in st if maa(r) is not None), key=lambda r: -maa(r)))
            ceiling = sorted(r for r in g if g[r] and st[r].get("gamma_max_at_ceiling"))
            if ceiling:  # a lower bound: the budget never bound Gamma there, unlike the paper's figures
                m["paper_comparison"]["ours_at_ceiling"] = ceiling
            txt = ("Gamma at 0.5 s: paper " + ", ".join(f"{r} {v // 1000}k" for r, v in paper.items())
                   + "; here Gamma_max " + ", ".join((f"{r} >= {v:,}" if r in ceiling else f"{r} {v:,}") if v
                                                     else f"{r} -" for r, v in g.items())
                   + (" ('>=': the search ceiling; the calibration never reached the budget there"
                      + "".join(f"; {_n(st[r]['trials_over_budget'], r + ' trial')} ran over it" for r in ceiling
                                if st[r].get("trials_over_budget")) + ")" if ceiling else "")
                   + "; frozen Gamma " + ", ".join(f"{r} {int(v):,}" if v else f"{r} -" for r, v in frozen.items())
                   + "; test mAA(10) order here: " + order)
    elif f["id"] == 4:
        r = {k: ((s.get("params") or {}).get("ratio")) for k, s in st.items() if s.get("ok")}
        if r:
            paper = pn["either_ratio"]
            m["paper_comparison"] = {"paper": {"either": paper}, "ours": r, "what": "optimal r per strategy"}
            txt = f"optimal r: paper 'either' ~{paper:g}; here " + ", ".join(f"{k} {v:.3f}" for k, v in r.items() if v)
    return txt


def _study_rows(f: dict) -> list[list[str]]:
    rows = []
    for role, s in (f["measured"].get("studies") or {}).items():
        if not s.get("ok"):
            rows.append([role, s["study"], "-", "not run", "-", "-", "-", s.get("reason", "")])
            continue
        p = s.get("params") or {}
        ps = ", ".join(f"{k}={_num(v, 3) if isinstance(v, float) else v}" for k, v in p.items())
        fx = s.get("fixed") or {}
        if fx:
            ps += "; fixed: " + ", ".join(f"{k}={v}" for k, v in fx.items())
        c = s.get("compute") or {}
        cost = ""
        if c:
            tun = (c.get("calibration_seconds") or 0.0) + (c.get("trial_seconds") or 0.0)
            cost = f"; tuning {tun / 60:.1f} min" + (f", test {c['test_seconds'] / 60:.1f} min"
                                                       if c.get("test_seconds") is not None else "")
        rep = s.get("replicated")
        if rep:  # the tuned figure is the replicates' mean; each replicate's own figure and frozen r, eta, Gamma
            cost += (f"; {rep['K']} replicates, test mAA10 each "
                     + ", ".join(_num(e.get("mAA10")) for e in rep["replicates"])
                     + "".join(f"; {k} {_num(v[0], 3)}..{_num(v[1], 3)}" for k, v in (rep.get("spread") or {}).items()))
        rows.append([role, s["study"], _num(s.get("validation_mAA10")), _num(s.get("mAA10")), _ci(s.get("mAA10_ci")),
                     _num(s.get("mAA5")), ps,
                     f"Gamma_max {'>= ' if s.get('gamma_max_at_ceiling') else ''}"
                     f"{format(s['gamma_max'], ',') if s.get('gamma_max') else '-'}"
                     f"{_ceiling_note(s) if s.get('gamma_max_at_ceiling') else ''}; "
                     f"{_n(s.get('trials', 0), 'feasible trial')}; "
                     f"{_n(s['pairs'], 'test pair') if s.get('pairs') else '- test pairs'} x {s.get('test_runs') or '-'} "
                     f"run{'' if s.get('test_runs') == 1 else 's'}{cost}"])
    return rows


def _ceiling_note(s: dict) -> str:
    """What a Gamma_max at the search ceiling means for one study: the calibration (at its own r and eta) never
    reached the budget; it said "the budget never bound Gamma" beside trials that ran over the budget."""
    over = s.get("trials_over_budget") or 0
    return (" (the search ceiling: the calibration never reached the budget"
            + (f", yet {over} completed trial{'s' * (over != 1)} ran over it" if over else "") + ")")


def study_warnings(f: dict) -> list[str]:
    """"<role>: <warning>" for each warning of each study's freeze (``frozen.yaml`` ``warnings``: an optimum on a
    bound of the search space, Gamma_max at the search ceiling, every trial 0), which qualify the values shown."""
    return [f"{role}: {w}" for role, s in (f["measured"].get("studies") or {}).items() if s.get("ok")
            for w in s.get("warnings") or []]


# "val. mAA(10)": the frozen trial's, on the validation scenes it was chosen on. Beside the test figure it tells a
# reader whether a difference was already there when tuning or appeared only on the test scenes (a frozen optimum
# that did not generalise: one easy validation scene ties many settings).
STUDY_COLS = ["role", "study", "val. mAA(10)", "test mAA(10)", "95% CI", "test mAA(5)", "frozen parameters", "notes"]


def _md_table(cols, rows) -> str:
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    out += ["| " + " | ".join(str(c).replace("|", "/") for c in r) + " |" for r in rows]
    return "\n".join(out)


def _compared(f: dict) -> str:
    """What the headline difference is a difference of: "B - A" (test mAA(10)), or the parameter of a regions rule."""
    key = (f.get("measured") or {}).get("key")
    if f.get("difference") is None or not key:  # why not, where the analysis says it (a study that did not run)
        return (f.get("measured") or {}).get("reason") or "-"
    text = key.replace(" vs ", " - ", 1) if " vs " in key else key
    deciders = (f.get("measured") or {}).get("decided_by")
    if deciders:  # the verdict combines several relations and the key alone would read otherwise
        text += "; verdict from " + ", ".join(f"{d['b']} - {d['a']}: {d['status']}" for d in deciders)
    return text


def summary_lines(findings: list[dict]) -> list[str]:
    """What `tune findings` prints: a header, then per finding its verdict, the key difference (test mAA(10) B - A,
    or the optimal values of findings 6 and 7) with its 95% CI and p, what it is a difference of, and the claim."""
    head = (f"{'#':>2}  {'verdict':<14} {'difference [95% CI]':<27} {'p':<7} difference of (test mAA(10) B - A "
            "unless named) | finding")
    out = [head]
    for f in findings:
        num = isinstance(f.get("difference"), (int, float))
        d = f"{f['difference']:+.4f}" if num else ""
        if num and f.get("ci"):
            d += f" [{f['ci'][0]:+.4f}, {f['ci'][1]:+.4f}]"
        p = f"p {_p(f['p_value'])}" if num and isinstance(f.get("p_value"), (int, float)) else ""
        why = (f.get("measured") or {}).get("reason") if not num else None
        title = BY_ID[f["id"]].title if f.get("id") in BY_ID else ""
        tail = f"{_compared(f)} | {title}" if num else (f"{why} | {title}" if why else title)
        tv = _tuning_cell(f) if num else "-"
        tv = "tuning variance " + tv if tv != "-" else ""
        out.append(f"{f['id']:>2}  {f['verdict']:<14} {d:<27} {p:<7} {tail}".rstrip() + (f" | {tv}" if tv else ""))
    return out


def _difference_text(f: dict) -> str:
    m = f["measured"]
    if f["verdict"] == "not run":
        return f"Not run here: {m.get('reason') or m.get('missing')}"
    if f["verdict"] == "not run yet":
        return f"Not run yet (not selected by --only, and its studies are not all finished): {m.get('reason')}"
    if m.get("rule") == "regions":
        parts = []
        from tuner.findings.analysis import UNITS
        unit = f" {UNITS[m['parameter']]}" if UNITS.get(m["parameter"]) else ""
        for role, r in (m.get("regions") or {}).items():
            parts.append(f"{role}: optimum {m['parameter']} = {_num(r['optimum'], 3)}{unit}, flat region "
                         f"{_ci(r['region'], 3)}{unit} ({r['trials_within']} of {_n(r['trials'], 'feasible trial')} with "
                         f"validation mAA(10) within the optimum's 95% interval {_ci(r['validation_ci'], 3)})")
        for g in m.get("groups") or []:
            why = m.get("regions_missing") or {}
            parts.append(f"{g['group']}: {g['status']}" + (
                f" (missing: {'; '.join(f'{r}: {why[r]}' if r in why else r for r in g['missing'])})"
                if g["missing"] else ""))
        return "; ".join(parts)
    rel = m.get("relative_difference")
    txt = (f"{m.get('key')}: difference {_num(f['difference'])} mAA(10), 95% CI {_ci(f['ci'])}, "
           f"{_p_is(f['p_value'])}")
    if m.get("p_b_beats_a") is not None:
        pci = m.get("p_b_beats_a_ci")
        txt += (f", P(B > A) = {m['p_b_beats_a']:.2f}" + (f" [{pci[0]:.2f}, {pci[1]:.2f}]" if pci else "")
                + " for one new tuning of each")
    if f["verdict"] == "inconclusive" and isinstance(m.get("detectable"), (int, float)):
        txt += f"; could detect |B - A| >= {m['detectable']:.3f}" + (f" ({m['plan']})" if m.get("plan") else "")
    if rel is not None:
        txt += f" ({100 * rel:+.1f}%{_pct_ci(m.get('relative_ci'))} relative to {m.get('relative_to')})"
    def bonferroni(r) -> str:
        return (f" (deciding alone, tested at the Bonferroni level over the relations: {100 * r['level']:.3g}% CI "
                f"{_ci(r['ci_at_level'])}, needs p < {1 - r['level']:.3g})" if r.get("level") else "")
    key = m.get("key") or ""
    # the key relation is stated first: "B vs A", or finding 12's "B (the best on validation of ...) vs A"
    is_key = [key.startswith(f"{r['b']} vs {r['a']}") or (key.startswith(f"{r['b']} (") and key.endswith(f" vs {r['a']}"))
              for r in m.get("relations") or []]
    for r, k in zip(m.get("relations") or [], is_key):
        if k and r.get("level"):
            txt += f" -> {r.get('status')}{bonferroni(r)}"
    rels = [r for r, k in zip(m.get("relations") or [], is_key) if not k]
    for r in rels:
        txt += (f"; {r['b']} vs {r['a']}: {_num(r['difference'])} {_ci(r['ci'])}, {_p_is(r['p_value'])}"
                + (f" -> {r['status']}" if r.get("status") else "") + bonferroni(r))
    return txt + (f"; {tuning_text(m)}" if tuning_text(m) else "")


def tuning_text(m: dict) -> str:
    """Whether a finding's interval holds the tuning variance: "K = 3 x 3 tuning replicates ..." or the note that
    it was not measured ("" for a finding with no difference measured)."""
    if "tuning_variance_measured" not in m:
        return ""
    if m["tuning_variance_measured"]:
        ka, kb = m.get("replicates") or ["?", "?"]
        return (f"{ka} x {kb} tuning replicates: the interval holds the tuning variance (variance components: "
                "pairs, tuning, seed noise counted once)")
    if m.get("rule") == "regions" or "groups" in m:
        return "the tuning variance was not measured: the flat regions are those of one tuning (replicate 1)"
    from pipeline.metrics.replicates import NOT_MEASURED
    return NOT_MEASURED + "; rerun with --replicates 3 to measure it"


def _tuning_cell(f: dict) -> str:
    m = f.get("measured") or {}
    if "tuning_variance_measured" not in m or f.get("verdict") in ("not run", "not run yet"):
        return "-"
    if not m["tuning_variance_measured"]:
        return "not measured"
    p = m.get("p_b_beats_a")
    return f"K={'x'.join(str(k) for k in m.get('replicates') or [])}" + (f", P(B>A) {p:.2f}" if p is not None else "")


def plot_finding(f: dict):
    """A plotly figure: the studies' test mAA(10) with 95% intervals, or the flat regions (findings 6 and 7);
    None when there is nothing to draw."""
    import plotly.graph_objects as go
    m = f["measured"]
    if m.get("rule") == "regions":
        regs = m.get("regions") or {}
        if not regs:
            return None
        fig = go.Figure()
        for role, r in regs.items():
            fig.add_trace(go.Scatter(x=r["region"], y=[role, role], mode="lines", line={"width": 10}, opacity=0.5,
                                     name=f"{role}: flat region", showlegend=False))
            fig.add_trace(go.Scatter(x=[r["optimum"]], y=[role], mode="markers", marker={"size": 10, "color": "crimson"},
                                     name=f"{role}: optimum", showlegend=False))
        sym = {"ratio": "ratio test r", "threshold": "inlier threshold eta (px, log scale)"}.get(m["parameter"],
                                                                                               m["parameter"])
        fig.update_layout(title=f"Finding {f['id']}: flat regions of the optimal {m['parameter']} (dot: optimum)",
                          xaxis_title=sym, yaxis_title="study", height=300 + 20 * len(regs))
        if m["parameter"] == "threshold":  # searched on a log scale: 0.1 px and 10 px regions side by side
            fig.update_xaxes(type="log")
        return fig
    st = [(role, s) for role, s in (m.get("studies") or {}).items() if s.get("ok") and s.get("mAA10") is not None]
    if not st:
        return None
    fig = go.Figure(go.Bar(
        x=[r for r, _ in st], y=[s["mAA10"] for _, s in st],
        error_y={"type": "data", "symmetric": False, "array": [max(0.0, s["mAA10_ci"][1] - s["mAA10"]) for _, s in st],
                 "arrayminus": [max(0.0, s["mAA10"] - s["mAA10_ci"][0]) for _, s in st]},
        hovertext=[s["study"] for _, s in st]))
    fig.update_layout(title=f"Finding {f['id']}: test mAA(10°) with 95% intervals", xaxis_title="study (role)",
                      yaxis_title="test mAA(10°)", yaxis_range=[0, 1], height=340)
    return fig


def study_reports(out: dict, fs) -> dict:
    """Write each study's own report (``tuner.plots.write_report``) beside its frozen settings; name -> path."""
    from pipeline.errors import ImtuneError
    from tuner.freeze import study_dir
    from tuner.plots import write_report as study_report
    from tuner.storage import open_storage
    names = sorted({n for f in out["findings"] for n in f["studies"]})
    if not names:
        return {}
    storage = open_storage(fs.storage, heartbeat=None, studies_dir=fs.studies_dir)
    done = {}
    for n in names:
        try:
            done[n] = study_report(storage, n, study_dir(fs.studies_dir, n) / "report.html", fs.studies_dir)
        except ImtuneError:
            continue
    return done


def compute_total(out: dict) -> dict | None:
    """The compute the report's studies recorded, each study once (a shared calibration once): calibration,
    trials (COMPLETE and PRUNED) and test seconds, summed; what a run resumed across sessions cost in all, less
    the feature extraction, k-NN tables and ground truth that the cache holds. Every study the run used counts,
    also one that ran its trials and could not be frozen (no feasible trial: ``frozen`` False), whose number is
    ``not_frozen``. None without studies."""
    seen, unfrozen = {}, set()
    for f in out["findings"]:
        for st in ((f.get("measured") or {}).get("studies") or {}).values():
            if st.get("compute"):
                seen[st["study"]] = st["compute"]
                if not st.get("ok") and not st.get("frozen", False):
                    unfrozen.add(st["study"])
    if not seen:
        return None
    cals = {}
    for name, c in seen.items():
        if c.get("calibration_seconds") is not None:
            cals[c.get("calibration_created") or name] = float(c["calibration_seconds"])
    trial = sum(float(c.get("trial_seconds") or 0.0) for c in seen.values())
    test = sum(float(c["test_seconds"]) for c in seen.values() if c.get("test_seconds") is not None)
    missing = sorted(n for n, c in seen.items() if c.get("test_seconds") is None and c.get("tested", True))
    cal = sum(cals.values())
    return {"studies": len(seen), "calibration_seconds": cal, "trial_seconds": trial, "test_seconds": test,
            "total_seconds": cal + trial + test, "tests_not_timed": missing, "not_frozen": sorted(unfrozen),
            "tested": sum(1 for c in seen.values() if c.get("tested", True))}


def _compute_line(c: dict) -> str:
    untimed = len(c["tests_not_timed"])
    test = "test not recorded" if untimed and untimed == c["studies"] else f"test {c['test_seconds'] / 60:.1f} min"
    if c.get("tested", 1) == 0:  # no study has a test run yet (none frozen, or --no-test): not "test 0.0 min"
        test = "no test run"
    nf = len(c.get("not_frozen") or [])
    studies = f"the {c['studies']} stud{'y' if c['studies'] == 1 else 'ies'}" + (
        f" ({nf} of which could not be frozen; their reasons in the findings' tables)" if nf else "")
    line = (f"compute recorded by {studies}: {c['total_seconds'] / 3600:.2f} h (calibration "
            f"{c['calibration_seconds'] / 60:.1f} min, trials {c['trial_seconds'] / 3600:.2f} h, {test}; features, "
            "k-NN tables and ground truth come from the cache and are not counted)")
    if 0 < untimed < c["studies"]:
        line += f"; {_n(untimed, 'test')} written before test time was recorded: not counted"
    return line


#: what `tune findings` writes under ``<studies dir>/findings``
OUTPUTS = ("report.html", "report.md", "findings.json")


def check_outputs(studies_dir) -> None:
    """Before any study: the findings folder can be created and written, and none of :data:`OUTPUTS` is a folder
    (found only when the report was written, after every study: a file in the folder's place was an internal
    error, FileExistsError). One-line ImtuneError naming the culprit."""
    from pipeline.errors import ImtuneError
    from pipeline.fileio import check_writable_folder
    root = Path(studies_dir) / "findings"
    check_writable_folder(root, "findings folder", "move what is in the way, or choose another --studies-dir")
    for name in OUTPUTS:
        if (root / name).is_dir():
            raise ImtuneError(f"{root / name} is a folder where tune findings writes its {name}: move it away, or "
                              "choose another --studies-dir")


def _ids(ids: list) -> str:
    """[1, 2, 3, 5, 7, 8, 9] -> "1-3, 5, 7-9"."""
    parts: list[list[int]] = []
    for i in sorted(ids):
        if parts and i == parts[-1][-1] + 1:
            parts[-1].append(i)
        else:
            parts.append([i])
    return ", ".join(str(p[0]) if len(p) == 1 else f"{p[0]}-{p[-1]}" for p in parts)


def _work_done(out: dict) -> str:
    """What running the findings this invocation ran added to their studies (``ran_now`` of each distinct study):
    a rerun over finished studies ran no trial and no test, and "this run: every finding" must not read as if it
    had tuned them all again. A study that could not run or be frozen records nothing (its trials may still have
    run): it is counted apart, never as "already finished". "" when no study records it (none of them could run)."""
    work: dict[str, dict] = {}
    others: set[str] = set()
    for f in out["findings"]:
        if f.get("this_run", "ran") != "ran":
            continue
        for s in ((f.get("measured") or {}).get("studies") or {}).values():
            if s.get("ran_now") is not None:
                work[s["study"]] = s["ran_now"]
            else:
                others.add(s["study"])
    if not work:
        return ""
    n, trained = len(work), sum(1 for w in work.values() if w["trials"])
    tested = sum(1 for w in work.values() if w["test"])
    apart = f"; {len(others)} could not be run or frozen (their rows say why)" if others else ""
    if not trained and not tested:
        if others:
            return f"; no new trial or test run in {n} of their {n + len(others)} studies" + apart
        return ("; its study was" if n == 1 else "; both of their studies were" if n == 2 else
                f"; all {n} of their studies were") + \
            " already finished and tested: re-analysed, no new trial or test run"
    trials = sum(w["trials"] for w in work.values())
    return (f"; new in their {_n(n, 'study', 'studies')}: trials in {trained} ({_n(trials, 'trial')}), test runs in "
            f"{tested}" + apart)


def this_run_line(out: dict, fs) -> str:
    """The report's first header line: which findings this invocation ran (``--only``), which it re-analysed from
    their finished studies and which are not run yet, with the command that runs those."""
    from tuner.findings.runner import findings_command
    by: dict[str, list] = {}
    for f in out["findings"]:
        by.setdefault(f.get("this_run", "ran"), []).append(f["id"])
    ran = by.get("ran", [])
    if not by.get("reused") and not by.get("not run yet"):
        return f"this run: every finding ({_ids(ran)})" + _work_done(out)
    line = f"this run: finding{'s' * (len(ran) != 1)} {_ids(ran)} (--only {','.join(map(str, ran))})" + _work_done(out)
    if by.get("reused"):
        line += (f"; re-analysed from their finished studies in the storage (no new trial or test run): "
                 f"{_ids(by['reused'])}")
    if by.get("not run yet"):
        line += (f"; not run yet: {_ids(by['not run yet'])} (their studies are not all finished; run them with "
                 f"{findings_command(fs, by['not run yet'])})")
    return line


def write_report(out: dict, fs, seconds: float = 0.0) -> Path:
    """Write report.md, report.html and findings.json under ``<studies dir>/findings``; returns report.html."""
    from tuner.freeze import atomic_write
    root = Path(fs.studies_dir) / "findings"
    root.mkdir(parents=True, exist_ok=True)
    import plotly.io as pio
    reports = study_reports(out, fs)
    first = True  # plotly.js embedded once, with the first figure (the report works offline)
    report = root / "report.html"
    out["report"] = str(report)
    when = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    head = [this_run_line(out, fs)] + settings_lines(fs, out) + [f"wall time of this run: {seconds / 60:.1f} min; "
                                                            f"written {when}"]
    total = compute_total(out)
    if total is not None:  # the header only: findings.json keeps its two keys
        head.append(_compute_line(total))
    verdict_rows = [[f["id"], BY_ID[f["id"]].title, f["verdict"], _compared(f), _num(f["difference"]), _ci(f["ci"]),
                     _p(f["p_value"]), _tuning_cell(f)] for f in out["findings"]]
    vcols = ["#", "finding", "verdict", "difference of", "difference", "95% CI", "p", "tuning variance"]
    md = ["# imtune: the paper's findings on this data", "", *[f"- {h}" for h in head], "",
          _md_table(vcols, verdict_rows), ""]
    body = [f"<h1>imtune: the paper's findings on this data</h1><ul>{''.join(f'<li>{html.escape(h)}</li>' for h in head)}</ul>",
            _html_table(vcols, verdict_rows)]
    for f in out["findings"]:
        d = BY_ID[f["id"]]
        rule = RULE_TEXT[d.rule]
        if d.rule in ("better", "small_gain") and (f.get("measured") or {}).get("tuning_variance_measured"):
            rule = RULE_TEXT[f"{d.rule}_replicated"]
        md += [f"## {f['id']}. {d.title} — {f['verdict']}", "", f"Paper: {f['claim']} ({f['paper']})", "",
               f"Rule: {rule}.", ""]
        if d.notes:
            md += [f"Settings: {d.notes}", ""]
        versus = paper_comparison(f)
        md += [f"Measured: {_difference_text(f)}", ""] + ([f"Paper vs here: {versus}", ""] if versus else [])
        rows = _study_rows(f)  # none for a finding not run (yet)
        md += [_md_table(STUDY_COLS, rows), ""] if rows else []
        warns = study_warnings(f)
        md += [f"Warnings (the studies' frozen settings): {'; '.join(warns)}", ""] if warns else []
        fig = plot_finding(f)
        div = pio.to_html(fig, full_html=False, include_plotlyjs=first) if fig is not None else ""
        first = first and fig is None
        links = " ".join(_study_links(n, reports, fs.studies_dir) for n in f["studies"])
        body.append(
            f"<section id='finding-{f['id']}'><h2>{f['id']}. {html.escape(d.title)} — "
            f"<span class='v {f['verdict'].replace(' ', '-')}'>{html.escape(f['verdict'])}</span></h2>"
            f"<p><b>Paper</b>: {html.escape(f['claim'])} <i>({html.escape(f['paper'])})</i></p>"
            f"<p><b>Rule</b>: {html.escape(rule)}.</p>"
            + (f"<p><b>Settings</b>: {html.escape(d.notes)}</p>" if d.notes else "")
            + f"<p><b>Measured</b>: {html.escape(_difference_text(f))}</p>"
            + (f"<p><b>Paper vs here</b>: {html.escape(versus)}</p>" if versus else "")
            + (_html_table(STUDY_COLS, rows) if rows else "")
            + (f"<p><b>Warnings</b> (the studies' frozen settings): {html.escape('; '.join(warns))}</p>" if warns else "")
            + div
            + (f"<p><b>Studies</b>: {links}</p>" if links else "") + "</section>")
        md += [f"Studies: {', '.join(f['studies']) or 'none'} (their reports: ../<study>/report.html)", ""]
    md += ["## How the verdicts are decided", "", rules_text(), ""]
    body.append(f"<h2>How the verdicts are decided</h2><pre>{html.escape(rules_text(''))}</pre>")
    style = ("body{font-family:sans-serif;max-width:70em;margin:1em auto;line-height:1.4}table{border-collapse:collapse}"
             "td,th{border:1px solid #ccc;padding:2px 6px;font-size:90%}.v{padding:0 4px}.holds{background:#cfc}"
             ".does-not-hold{background:#fcc}.inconclusive{background:#eee}.not-run,.not-run-yet{background:#ffd}")
    atomic_write(report, "<!doctype html><html><head><meta charset='utf-8'><title>imtune findings</title>"
                         f"<style>{style}</style></head><body>{''.join(body)}</body></html>")
    atomic_write(root / "report.md", "\n".join(md))
    atomic_write(root / "findings.json", json.dumps(_jsonable(out), indent=2))
    return report


def _study_links(name: str, reports: dict, studies_dir) -> str:
    """A study's name linked to its report, then its frozen settings and test results: each link to a file that
    exists (a study never tested, as finding 6's multiview study, has no test.json: it says so instead)."""
    from tuner.freeze import study_dir
    folder = study_dir(studies_dir, name)
    n = html.escape(name)
    main = "report.html" if name in reports else "frozen.yaml" if (folder / "frozen.yaml").is_file() else None
    head = f'<a href="../{n}/{main}">{n}</a>' if main else n
    files = [f'<a href="../{n}/{fn}">{label}</a>' if (folder / fn).is_file() else f"no {label}"
             for fn, label in (("frozen.yaml", "frozen"), ("test.json", "test"))]
    return f"{head} ({', '.join(files)})"


def _html_table(cols, rows) -> str:
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in cols)
    b = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{b}</table>"


def _jsonable(o):
    if isinstance(o, float) and not math.isfinite(o):
        return None if math.isnan(o) else ("inf" if o > 0 else "-inf")
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    try:
        import numpy as np
        if isinstance(o, np.generic):
            return _jsonable(o.item())
    except ImportError:
        pass
    return o
