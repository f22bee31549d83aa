"""Tables as in the paper (tuner.formatting, the `tune table` part of tuner.reports): precision by column,
the mean row, and the exact LaTeX structure (booktabs, right-aligned numbers, $r$ / $\\eta$ / $\\Gamma$
headers, caption, escaping) on known inputs."""
import csv
import io
import json

import pytest
from optuna.distributions import FloatDistribution, IntDistribution
from optuna.trial import create_trial

from tuner.formatting import Columns, column_kind, format_value, latex_escape, latex_header, render, with_mean_row
from tuner.reports import StudyInfo, render_table, settings_rows

DIST = {"ratio": FloatDistribution(0.6, 1.0), "threshold": FloatDistribution(0.1, 10.0, log=True),
        "max_iters": IntDistribution(100, 100000, log=True)}


def info(feature, nf, est, value, ratio, eta=None, gamma=None, task="stereo", budget=0.5, scenes=("fountain-P11",)):
    params = {"ratio": ratio}
    if eta is not None:
        params.update(threshold=eta, max_iters=gamma)
    best = create_trial(value=value, params=params, distributions={k: DIST[k] for k in params})
    attrs = {"imtune": 1, "task": task, "budget": {"seconds_per_pair": budget} if task == "stereo" else {},
             "data": {"val_scenes": list(scenes)}}
    return StudyInfo(name=f"{feature}-{nf}-{est}-{task}", task=task, feature=feature, num_features=nf, ransac=est,
                     attrs=attrs, best=best, n_complete=5, test=None)


STEREO = [info("sift", 8000, "degensac", 0.61, 0.8512, 0.5123, 48213),
          info("sift", 8000, "magsac++", 0.64, 0.875, 1.25, 20000),
          info("root_sift", 2048, "degensac", 0.5, 0.9, 0.75, 10000)]
MULTIVIEW = [info("sift", 8000, "degensac", 0.7, 0.95, task="multiview")]


def test_precision_by_column():
    assert [column_kind(c) for c in ("NM", "NI degensac", "NF", "features", "Gamma magsac++", "mAA10 degensac",
                                     "mAA(10°)", "r", "r_multiview", "eta degensac", "B", "SR", "TL", "scene")] == \
        ["int", "int", "int", "int", "int", "maa", "maa", "ratio", "ratio", "sig3", "sig3", "pct", "tl", ""]
    assert format_value("NI", 123.6) == "124" and format_value("NM", 2047.0) == "2047"
    assert format_value("mAA10", 0.51249) == "0.512" and format_value("mAA5", 1.0) == "1.000"
    assert format_value("r", 0.8512) == "0.85" and format_value("eta degensac", 0.51234) == "0.512"
    assert format_value("eta magsac++", 12.345) == "12.3" and format_value("Gamma degensac", 48213) == "48213"
    assert format_value("ransac_seconds_median", 0.123456) == "0.123"
    assert format_value("mAA10", None) == "-" and format_value("ATE", float("inf")) == "inf"
    assert format_value("scene", "fountain-P11") == "fountain-P11"


def test_mean_row_only_for_several_scenes():
    cols = ["scene", "NI", "mAA10", "pairs"]
    one = [{"scene": "fountain-P11", "NI": 100.0, "mAA10": 0.5, "pairs": 10}]
    assert with_mean_row(one, cols) == one  # a mean of one scene says nothing
    two = one + [{"scene": "Herz-Jesus-P8", "NI": 51.0, "mAA10": 0.25, "pairs": 6}]
    out = with_mean_row(two, cols, skip=("pairs",))
    assert len(out) == 3 and out[-1]["scene"] == "mean over 2 scenes"
    assert out[-1]["NI"] == pytest.approx(75.5) and out[-1]["mAA10"] == pytest.approx(0.375)
    assert "pairs" not in out[-1]
    # a column some scenes lack is left empty rather than averaged over fewer scenes than the label says
    gap = two + [{"scene": "entry-P10", "NI": 10.0, "pairs": 3}]
    m = with_mean_row(gap, cols)[-1]
    assert m["scene"] == "mean over 3 scenes" and "mAA10" not in m and m["NI"] == pytest.approx(161 / 3)
    md = render(out, "markdown", cols)
    assert md.splitlines()[-1] == "| mean over 2 scenes |  76 | 0.375 |     - |"


def test_latex_exact_structure():
    rows = with_mean_row([{"scene": "fountain_P11", "NI": 120.4, "mAA10": 0.51234},
                          {"scene": "Herz-Jesus-P8", "NI": 99.6, "mAA10": 0.4}], ["scene", "NI", "mAA10"])
    cols = Columns(["scene", "NI", "mAA10"], caption="Stereo test results (3 runs) & 50% of pairs")
    assert render(rows, "latex", cols).splitlines() == [
        r"\begin{table}[t]",
        r"\centering",
        r"\caption{Stereo test results (3 runs) \& 50\% of pairs}",
        r"\begin{tabular}{lrr}",
        r"\toprule",
        r"scene & NI & mAA($10^\circ$) \\",
        r"\midrule",
        r"fountain\_P11 & 120 & 0.512 \\",
        r"Herz-Jesus-P8 & 100 & 0.400 \\",
        r"\midrule",
        r"mean over 2 scenes & 110 & 0.456 \\",
        r"\bottomrule",
        r"\end{tabular}",
        r"\end{table}",
    ]
    assert latex_header("eta degensac") == r"$\eta$ degensac"
    assert latex_header("Gamma cv_ransac") == r"$\Gamma$ cv\_ransac"
    assert latex_header("r") == "$r$" and latex_header("mAA(5°)") == r"mAA($5^\circ$)"
    assert latex_escape("a_b{c}#1~^$\\") == r"a\_b\{c\}\#1\textasciitilde{}\textasciicircum{}\$\textbackslash{}"


def test_settings_table_latex_exact():
    rows, cols = settings_rows(STEREO, "latex", multiview=MULTIVIEW)
    tex = render_table(rows, cols, "latex").splitlines()
    assert tex[0] == r"\begin{table}[t]" and tex[1] == r"\centering"
    assert tex[2] == (r"\caption{Optimal settings on the validation scenes fountain-P11: ratio test $r$ (stereo: from "
                      r"the estimator study with the best validation mAA($10^\circ$); multiview: COLMAP), inlier "
                      r"threshold $\eta$ (px) and maximum iterations $\Gamma$ of each estimator under the time budget "
                      r"$B = 0.5$\,s per pair (median estimator CPU time). Validation ground truth: not recorded (written "
                      r"before imtune recorded it).}")  # these studies' records predate it
    assert tex[3:] == [
        r"\begin{tabular}{lrrrrrrrrlrr}",
        r"\toprule",
        r"feature & features & $r$ stereo & $r$ multiview & $\eta$ degensac & $\Gamma$ degensac & $\eta$ magsac++ & "
        r"$\Gamma$ magsac++ & $B$ (s) & $r$ from & val.\ mAA($10^\circ$) & val.\ multiview mAA($10^\circ$) \\",
        r"\midrule",
        r"root\_sift & 2048 & 0.90 & -- & 0.75 & 10000 & -- & -- & 0.5 & degensac & 0.500 & -- \\",
        r"sift & 8000 & 0.88 & 0.95 & 0.512 & 48213 & 1.25 & 20000 & 0.5 & magsac++ & 0.640 & 0.700 \\",
        r"\bottomrule",
        r"\end{tabular}",
        r"\end{table}",
    ]


def test_settings_table_values_and_formats():
    rows, cols = settings_rows(STEREO, "markdown", multiview=MULTIVIEW)
    sift = next(r for r in rows if r["feature"] == "sift")
    # r comes from the study with the best validation mAA(10): magsac++ (0.64 > 0.61)
    assert sift["r"] == 0.875 and sift["r from"] == "magsac++" and sift["r_multiview"] == 0.95
    assert sift["eta degensac"] == 0.5123 and sift["Gamma degensac"] == 48213 and sift["B"] == 0.5
    md = render_table(rows, cols, "markdown").splitlines()
    assert md[0].startswith("| feature ") and "| Gamma degensac |" in md[0] and "| r_multiview |" in md[0]
    assert md[1].startswith("|---") and "--:|" in md[1]  # numeric columns right-aligned
    assert md[-1].startswith("Table: Optimal settings on the validation scenes fountain-P11")
    recs = list(csv.DictReader(io.StringIO(render_table(rows, cols, "csv"))))
    assert recs[1]["Gamma magsac++"] == "20000" and recs[1]["eta degensac"] == "0.512" and recs[1]["r"] == "0.88"
    js = json.loads(render_table(*settings_rows(STEREO, "json", multiview=MULTIVIEW), "json"))
    assert js[1]["studies"]["degensac"]["params"]["max_iters"] == 48213  # json keeps every study's values


def test_settings_table_budget_per_estimator_when_studies_differ():
    studies = [info("sift", 8000, "degensac", 0.61, 0.85, 0.5, 48213, budget=0.5),
               info("sift", 8000, "magsac++", 0.64, 0.88, 1.25, 20000, budget=1.0)]
    rows, cols = settings_rows(studies, "markdown")
    assert "B" not in cols and rows[0]["B degensac"] == 0.5 and rows[0]["B magsac++"] == 1.0
    tex = render_table(rows, cols, "latex")
    assert r"$B$ degensac (s)" in tex and r"$B$ of each study (columns $B$, s per pair)" in tex


def test_settings_table_without_multiview_still_names_the_column():
    rows, cols = settings_rows(STEREO[:1], "markdown")
    assert rows[0]["r_multiview"] is None and "r_multiview" in cols
    assert render_table(rows, cols, "markdown").splitlines()[2].split("|")[4].strip() == "-"


def test_settings_table_multiview_only():
    rows, cols = settings_rows([], "latex", multiview=[info("sift", 1024, "degensac", 0.4, 0.93, task="multiview",
                                                            scenes=("fountain_P11",))])
    assert list(cols) == ["feature", "features", "r_multiview", "mAA10 mv val"]
    tex = render_table(rows, cols, "latex").splitlines()
    assert tex[2] == (r"\caption{Optimal ratio test $r$ for multiview reconstruction (COLMAP, which runs its own "
                      r"RANSAC) on the validation scenes fountain\_P11. Validation ground truth: not recorded (written "
                      r"before imtune recorded it).}")
    assert tex[3] == r"\begin{tabular}{lrrr}" and tex[7] == r"sift & 1024 & 0.93 & 0.400 \\"


def test_tune_test_table_shows_each_scenes_seconds(tmp_path):
    """`tune test` printed '-' under match_seconds and ransac_seconds in every scene row (the per-scene test
    figures kept only the median estimator seconds), so a one-scene test table showed no timing at all while
    `tune evaluate` shows both. Real `tune test` on 3 fountain-P11 images with a frozen file."""
    from tests.conftest import copy_strecha_subset
    from tests.test_bad_input_files import _frozen_study, _frozen_text, tune
    data = copy_strecha_subset(tmp_path / "data", ["0003.jpg", "0004.jpg", "0005.jpg"])
    sdir = _frozen_study(tmp_path, _frozen_text(data))
    r = tune("test", "--study", "X", "--studies-dir", sdir, "--storage", f"sqlite:///{tmp_path}/none.db", "--runs", "1",
             "--reference", "none", "--ci", "none", "--jobs", "1", "--quiet", env={"IMTUNE_CACHE": str(tmp_path / "c")})
    assert r.returncode == 0, r.stderr[-2000:]
    lines = r.stdout.splitlines()
    assert max(len(ln) for ln in lines if ln.startswith("|")) <= 100, r.stdout  # split by columns, scene in each
    heads = [ln for ln in lines if ln.startswith("| scene")]
    rows = [ln for ln in lines if ln.startswith("| fountain-P11")]
    cells = {}
    for head, row in zip(heads, rows):
        cells.update(zip([c.strip() for c in head.split("|")], [c.strip() for c in row.split("|")]))
    for col in ("match_seconds", "ransac_seconds"):
        assert cells[col] not in ("-", "") and float(cells[col]) >= 0, (col, row)
    t = json.loads((sdir / "X" / "test.json").read_text())
    assert {"match_seconds", "ransac_seconds"} <= set(t["mean"]["scenes"]["fountain-P11"])


def _renamed(s: StudyInfo, name: str, best="keep", test=None) -> StudyInfo:
    import dataclasses
    return dataclasses.replace(s, name=name, best=s.best if best == "keep" else best, test=test)


def test_several_studies_of_one_estimator_show_the_best_validated_one():
    """Two studies of sift 8000 + degensac in one storage (a second --study name, a findings study, an unfinished
    one): the row took eta and Gamma from whichever was listed last, here one without a feasible trial, so it said
    'eta -' beside the r of the tuned study. Now the study with the best validation value gives the estimator's
    columns, in the settings table and in the results table (and their JSON)."""
    from tuner.reports import results_rows
    good = STEREO[0]
    worse = _renamed(info("sift", 8000, "degensac", 0.55, 0.7, 2.0, 999), "sift-8000-degensac-other")
    unfinished = _renamed(good, "zz-unfinished", best=None)
    for group in ([good, worse, unfinished], [unfinished, worse, good]):
        rows, cols = settings_rows(group, "markdown")
        assert (rows[0]["eta degensac"], rows[0]["Gamma degensac"], rows[0]["r"]) == (0.5123, 48213, 0.851)
        js = json.loads(render_table(*settings_rows(group, "json"), "json"))
        assert js[0]["studies"]["degensac"]["study"] == good.name
    t_good = {"NF": 8000, "NI": 300.0, "mAA10": 0.6, "mAA10_ci": [0.5, 0.7]}
    t_other = {"NF": 8000, "NI": 10.0, "mAA10": 0.9, "mAA10_ci": [0.8, 1.0]}  # better on test, worse on validation
    tested = [_renamed(good, good.name, test=t_good), _renamed(worse, worse.name, best=worse.best, test=t_other)]
    for group in (tested, tested[::-1]):
        rows, _ = results_rows(group, "json")
        assert (rows[0]["NI degensac"], rows[0]["mAA10 degensac"]) == (300.0, 0.6)
        assert rows[0]["studies"]["degensac"]["study"] == good.name


def _with_pairs(st, pairs, name):
    st.attrs["data"]["pairs"] = pairs
    return StudyInfo(**{**st.__dict__, "name": name})


def test_a_quick_study_beside_the_main_one_does_not_replace_its_settings():
    """`tune findings --quick` writes a SIFT 8k DEGENSAC study tuned on 12 pairs beside the main job's (55 pairs) in
    one storage; the table took the one with the higher validation value, a number of another pair set (on 12 pairs
    0.9 beats 0.88 by chance), and showed its 10-trial settings as the optimum, unsaid. Now the study tuned on more
    validation pairs wins, and a warning names the two validation sets."""
    main = _with_pairs(info("sift", 8000, "degensac", 0.88, 0.85, 0.5, 48213), 55, "sift-8000-degensac-stereo")
    quick = _with_pairs(info("sift", 8000, "degensac", 0.90, 0.70, 1.5, 2000), 12, "findings-9-quick")
    said = []
    for order in ([main, quick], [quick, main]):
        said.clear()
        rows, _ = settings_rows(order, "json", warn=said.append)
        assert rows[0]["eta degensac"] == 0.5 and rows[0]["Gamma degensac"] == 48213 and rows[0]["r"] == 0.85
        assert rows[0]["studies"]["degensac"]["study"] == "sift-8000-degensac-stereo"
        assert said == [], said  # one study shown: nothing mixed
    other = _with_pairs(info("sift", 8000, "magsac++", 0.7, 0.8, 1.25, 20000), 12, "findings-2-quick-magsac")
    rows, _ = settings_rows([main, quick, other], "markdown", warn=said.append)
    assert len(said) == 1 and "fountain-P11 (55 pairs): sift-8000-degensac-stereo" in said[0] \
        and "fountain-P11 (12 pairs): findings-2-quick-magsac" in said[0], said
    # among studies of one pair set the better validation value still wins; a study without a frozen trial loses
    a = _with_pairs(info("sift", 8000, "degensac", 0.70, 0.8, 0.3, 1000), 55, "a")
    b = _with_pairs(info("sift", 8000, "degensac", 0.75, 0.9, 0.4, 2000), 55, "b")
    empty = _with_pairs(info("sift", 8000, "degensac", 0.1, 0.8, 0.3, 1000), 99, "c")
    empty = StudyInfo(**{**empty.__dict__, "best": None})
    rows, _ = settings_rows([a, b, empty], "json")
    assert rows[0]["studies"]["degensac"]["study"] == "b"


def frozen_row(text: str, name: str) -> str:
    """The row of the frozen table named ``name``, its note's continuation rows (empty first cell) joined to it."""
    lines = text.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.startswith(f"| {name} "))
    out = [lines[i].rstrip(" |")]
    for ln in lines[i + 1:]:
        cells = ln.split("|")
        if not ln.startswith("|") or cells[1].strip():
            break
        out.append(cells[-2].strip())
    return " ".join(x.strip() for x in out)


def test_frozen_table_states_the_budget_statistic_of_the_frozen_trial():
    """The frozen-settings table printed "budget | 0.5 s/pair" and, in the validation row, "ransac_seconds 0.5769"
    (the mean over pairs) for a trial within budget: the budget is on the median (0.3415 s here), which the table
    never showed, so a feasible optimum read as over budget. The budget row now gives the frozen trial's median
    and names the mean as such."""
    from tuner.commands.study import frozen_table
    f = {"study": "x", "trial": 16, "task": "stereo", "task_options": {"min_covisibility": 0.1, "max_pairs": None},
         "params": {"max_iters": 65992, "ratio": 0.8524, "threshold": 0.4496}, "fixed": {"strategy": "both"},
         "budget": {"seconds_per_pair": 0.5, "statistic": "median estimator seconds per pair", "gamma_max": 190000},
         "validation": {"mAA10": 0.8509, "mAA10_ci": [0.7525, 0.94], "mAA5": 0.8473, "pairs": 55, "NF": 8000.0,
                        "NM": 1437.3, "NI": 1282.8, "failed": 0, "match_seconds": 0.0932, "ransac_seconds": 0.5769,
                        "ransac_seconds_median": 0.3415, "ransac_seconds_p90": 1.607}}
    text = frozen_table(f)
    budget = frozen_row(text, "budget")
    assert "median 0.342 s/pair" in budget and "mean 0.577" in budget, budget
    assert max(len(ln) for ln in text.splitlines() if ln.startswith("|")) <= 100, text  # notes on rows of their own


def test_a_study_with_another_strategy_or_pinned_settings_gets_its_own_row():
    """One storage holds the main SIFT + DEGENSAC study ('both', everything tuned) and `tune findings`' variants of
    the same feature and estimator: 'uni' / 'either' matching, OpenCV RANSAC at OpenCV's defaults (eta 3 px and
    Gamma 1000 pinned, confidence 0.99). The tables grouped rows by feature and count alone and showed, per
    estimator, the study with the best validation value: an 'either' study that validated higher took the 'sift'
    row's eta, Gamma and test mAA(10), unsaid. Now such a study is its own row, its variant in the feature name."""
    from tuner.reports import results_rows

    def variant(st, name, strategy="both", fixed=None, confidence=0.999999):
        st.attrs.update(pipeline={"matching": {"strategy": strategy},
                                  "geometry": {"ransac": st.ransac, "confidence": confidence}},
                        search_space_resolved={"params": {}, "fixed": dict(fixed or {})})
        return StudyInfo(**{**st.__dict__, "name": name})
    main = variant(info("sift", 8000, "degensac", 0.80, 0.85, 0.5, 48213), "sift-8000-degensac-stereo")
    either = variant(info("sift", 8000, "degensac", 0.86, 0.70, 1.5, 2000), "findings-4-either", strategy="either")
    tuned_cv = variant(info("sift", 8000, "cv-ransac", 0.70, 0.80, 0.4, 9000), "findings-1-tuned")
    defaults = variant(info("sift", 8000, "cv-ransac", 0.75, 0.86, 3.0, 1000), "findings-1-defaults",
                       fixed={"threshold": 3.0, "max_iters": 1000}, confidence=0.99)
    rows, _ = settings_rows([either, main, defaults, tuned_cv], "json")
    by = {r["feature"]: r for r in rows}
    assert set(by) == {"sift", "sift+either", "sift+eta3px+Gamma1000+conf0.99"}, set(by)
    assert (by["sift"]["eta degensac"], by["sift"]["Gamma degensac"]) == (0.5, 48213)
    assert (by["sift"]["eta cv-ransac"], by["sift"]["Gamma cv-ransac"]) == (0.4, 9000)
    assert by["sift+either"]["eta degensac"] == 1.5 and by["sift+either"]["eta cv-ransac"] is None
    tests = {main.name: 0.6, either.name: 0.9, tuned_cv.name: 0.5, defaults.name: 0.2}
    tested = [StudyInfo(**{**s.__dict__, "test": {"NF": 8000, "NI": 100.0, "mAA10": tests[s.name]}})
              for s in (either, main, defaults, tuned_cv)]
    rows, _ = results_rows(tested, "json")
    by = {r["feature"]: r for r in rows}
    assert by["sift"]["mAA10 degensac"] == 0.6 and by["sift"]["mAA10 cv-ransac"] == 0.5
    assert by["sift+either"]["mAA10 degensac"] == 0.9


def test_frozen_table_rounds_the_validation_figures_as_every_table_does():
    """The frozen table's validation row read "validation mAA10 | 0.851 [0.753, 0.940] | ... mAA5 0.8473 ...
    match_seconds 0.09316": mAA(5) to 4 digits beside mAA(10) to 3 in one row; every other table shows an mAA to 3
    decimals and seconds to 3 significant digits (tuner.formatting)."""
    from tuner.commands.study import frozen_table
    f = {"study": "x", "trial": 1, "task": "stereo", "params": {"ratio": 0.85}, "fixed": {},
         "budget": {"seconds_per_pair": 0.5},
         "validation": {"mAA10": 0.85091, "mAA10_ci": [0.75254, 0.94], "mAA5": 0.84727, "pairs": 55, "NF": 8000.0,
                        "NM": 1437.3, "NI": 1282.8, "failed": 0, "match_seconds": 0.093162, "ransac_seconds": 0.57693,
                        "ransac_seconds_median": 0.3415}}
    row = frozen_row(frozen_table(f), "validation mAA10")
    assert "0.851 [0.753, 0.940]" in row and "mAA5 0.847," in row, row
    assert "match_seconds 0.0932," in row and "NM 1437," in row, row


def test_the_test_table_says_its_seconds_are_per_pair_means():
    """`tune test` printed columns match_seconds / ransac_seconds (0.588 for entry-P10) under a line "within the 1.0
    s/pair test budget: yes" without saying they are per pair, nor that they are means while the budget is on the
    median (0.437 there): a reader could not tell the unit, nor why a mean above B can be within it."""
    from tuner.commands.study import test_table
    sc = {"pairs": 45, "NF": 8000.0, "NM": 1394.8, "NI": 1094.8, "mAA5": 0.36, "mAA10": 0.463, "failed": 0.0,
          "match_seconds": 0.0869, "ransac_seconds": 0.588, "ransac_seconds_median": 0.437}
    t = {"task": "stereo", "trial": 16, "runs": [{}, {}, {}], "std": {"mAA10": 0.005},
         "budget": {"test_seconds_per_pair": 1.0, "within_budget": True},
         "mean": {**sc, "scenes": {"entry-P10": dict(sc)}}}
    text = test_table(t)
    assert "seconds per pair" in text and "mean over the pairs" in text and "median" in text, text


def test_a_ratio_just_below_one_is_not_printed_as_no_ratio_test():
    """r is printed to 2 decimals (as in the paper's tables), so the quick findings' DoG+MKD optimum r = 0.9964 read
    "1.00" in `tune table`: r = 1 is the protocol's "no ratio test", which that study did not use."""
    assert format_value("r", 0.9964) == "0.996" and format_value("r_multiview", 0.998) == "0.998"
    assert format_value("r", 1.0) == "1.00" and format_value("r", 0.8512) == "0.85"


def test_a_one_run_test_says_it_has_no_spread_not_std_0():
    """`tune test --runs 1` printed "(1 runs, mean; mAA10 std 0)": one run has no spread over runs, and "std 0" read
    as a perfectly stable result. Three runs keep their std."""
    from tuner.commands.study import test_table
    sc = {"pairs": 45, "NF": 8000.0, "NM": 1394.8, "NI": 1094.8, "mAA5": 0.36, "mAA10": 0.463, "failed": 0.0}
    t = {"task": "stereo", "trial": 16, "runs": [{}], "std": {"mAA10": 0.0},
         "budget": {"test_seconds_per_pair": 1.0, "within_budget": True},
         "mean": {**sc, "scenes": {"entry-P10": dict(sc)}}}
    head = test_table(t).splitlines()[0]
    assert "(1 run, mean; one run: no spread over runs" in head and "std" not in head, head
    t = {**t, "runs": [{}, {}, {}], "std": {"mAA10": 0.0107}}
    assert "(3 runs, mean; mAA10 sample std over the runs 0.0107" in test_table(t).splitlines()[0]


def test_a_reused_test_result_gets_the_sample_std_over_its_runs():
    """A test.json written while the std over runs was the population one (ddof 0: 0.163 for runs at mAA(10) 0.2,
    0.4, 0.6) kept it when `tune test` reused the file. It is recomputed from the runs' figures as the sample std
    (0.2), the reference's too, and labelled (std_ddof 1); a file already labelled is left alone."""
    from pipeline.tasks.stereo import StereoTask
    from tuner.freeze import _refresh_std
    runs = [{"mAA10": v, "mAA5": v / 2, "NI": 100.0 * v, "scenes": {}} for v in (0.2, 0.4, 0.6)]
    old = {"runs": runs, "std": {"mAA10": 0.1633, "mAA5": 0.0816, "NI": 16.33},
           "reference": {"runs": runs, "std": {"mAA10": 0.1633}}}
    assert _refresh_std(old, StereoTask(jobs=1))
    assert old["std"]["mAA10"] == pytest.approx(0.2) and old["std"]["NI"] == pytest.approx(20.0)
    assert old["reference"]["std"]["mAA10"] == pytest.approx(0.2) and old["std_ddof"] == 1
    assert not _refresh_std(old, StereoTask(jobs=1))
