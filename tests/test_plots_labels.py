"""Plots say what they show (tuner.plots): the plotly figure objects of a report, read back — one title per
figure, axis titles with units (r, eta in px, Gamma in iterations on a log axis with readable ticks,
seconds), US spelling, and hints that name the command filling a gap. The studies are made with Optuna
directly (the attributes imtune's objective writes), stored in a real SQLite storage."""
import re

import pytest

B = 0.5


def _study(storage, name, covisibility=True, root="/data/strecha", n=8, seed=0):
    import numpy as np
    import optuna
    from optuna.distributions import FloatDistribution, IntDistribution
    from optuna.trial import create_trial
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    rng = np.random.default_rng(seed)
    st = optuna.create_study(study_name=name, storage=storage, direction="maximize")
    for k, v in {"task": "stereo", "feature": "sift", "num_features": 2048, "ransac": "degensac",
                 "budget": {"seconds_per_pair": B, "gamma_max": 20000},
                 "data": {"root": root, "val_scenes": ["fountain-P11"]}, "imtune": 1}.items():
        st.set_user_attr(k, v)
    dist = {"ratio": FloatDistribution(0.6, 1.0), "threshold": FloatDistribution(0.1, 2.0, log=True),
            "max_iters": IntDistribution(100, 20000, log=True)}
    cov = ({"0+": {"mAA10": 0.5, "pairs": 10}, "0.1+": {"mAA10": 0.55, "pairs": 8}} if covisibility
           else {"0+": {"mAA10": 0.0, "pairs": 0}, "unknown": {"mAA10": 0.5, "pairs": 10}})
    for _ in range(n):
        med = float(rng.uniform(0.1, 0.9))
        st.add_trial(create_trial(
            value=float(rng.uniform(0.2, 0.7)), distributions=dist,
            params={"ratio": float(rng.uniform(0.6, 1.0)), "threshold": float(np.exp(rng.uniform(np.log(0.1), np.log(2)))),
                    "max_iters": int(np.exp(rng.uniform(np.log(100), np.log(20000))))},
            constraints={"budget": med - B},
            user_attrs={"ransac_seconds_median": med, "feasible": med <= B,
                        "scenes": {"fountain-P11": {"mAA10": 0.5, "accuracy": [0.1 * k for k in range(1, 11)],
                                                    "covisibility": cov}}}))
    return st


@pytest.fixture
def sections(tmp_path):
    from tuner.plots import report_sections
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    _study(storage, "plots-a")
    _study(storage, "plots-b", seed=1)  # a second study of the same task: the eta curves compare them
    return report_sections(storage, "plots-a", tmp_path), storage


def _title(fig):
    return fig.layout.title.text


def test_every_figure_has_one_title_and_axis_titles_with_units(sections):
    secs, _ = sections
    figs = {s.title: s.fig for s in secs if s.fig is not None}
    assert len(figs) == 8, [s.title for s in secs]
    for title, fig in figs.items():
        assert _title(fig) == title and title
        assert fig.layout.xaxis.title.text and fig.layout.yaxis.title.text, title
        # no annotation repeats the title (one title per figure)
        assert all(title not in (a.text or "") for a in fig.layout.annotations), title
    by = {re.sub(r"\W+", " ", t).strip(): f for t, f in figs.items()}

    def get(prefix):
        return next(f for t, f in by.items() if t.startswith(prefix))

    h = get("Optimization history")
    assert h.layout.xaxis.title.text == "trial number" and h.layout.yaxis.title.text == "mAA(10°) (validation)"
    assert "over budget (never frozen)" in [tr.name for tr in h.data]
    imp = get("Parameter importances")
    assert set(imp.data[0].y) == {"r", "eta (px)", "Gamma (iterations)"}
    con = get("Validation mAA 10 over inlier threshold eta and ratio test r")
    axes = {con.layout.xaxis.title.text, con.layout.yaxis.title.text}
    assert axes == {"inlier threshold eta (px)", "ratio test r"}
    eta_axis = con.layout.xaxis if con.layout.xaxis.title.text.startswith("inlier") else con.layout.yaxis
    assert eta_axis.type == "log" and "1" in eta_axis.ticktext and len(eta_axis.ticktext) >= 3
    cost = get("Validation mAA 10 vs estimator CPU time per pair")
    assert cost.layout.xaxis.title.text == "median estimator CPU time per pair (s)"
    assert any("budget B = 0.5 s" in (a.text or "") for a in cost.layout.annotations)
    g = get("Validation mAA 10 vs RANSAC iteration cap Gamma")
    assert g.layout.xaxis.title.text == "iteration cap Gamma (iterations, log scale)" and g.layout.xaxis.type == "log"
    # readable log ticks: 1-2-5 per decade, thousands as "k", no exponents
    assert list(g.layout.xaxis.ticktext)[-4:] == ["2k", "5k", "10k", "20k"]
    assert all(re.fullmatch(r"\d+(\.\d+)?k?", t) for t in g.layout.xaxis.ticktext)
    curves = get("Best mAA 10 vs inlier threshold eta")
    assert curves.layout.xaxis.title.text == "inlier threshold eta (px, log scale)"
    assert {tr.name for tr in curves.data} == {"plots-a", "plots-b"}
    acc = get("Accuracy vs angular threshold")
    assert acc.layout.xaxis.title.text == "angular threshold (°)"
    assert acc.layout.yaxis.title.text == "accuracy (fraction of pairs within the threshold)"
    cov = get("Stereo mAA 10 by co visibility")
    assert cov.layout.yaxis.title.text == "mAA(10°)"


def test_us_spelling_throughout(sections):
    secs, _ = sections
    texts = []
    for s in secs:
        texts += [s.title, s.note]
        if s.fig is not None:
            lay = s.fig.layout
            texts += [lay.xaxis.title.text or "", lay.yaxis.title.text or ""]
            texts += [a.text or "" for a in lay.annotations] + [tr.name or "" for tr in s.fig.data]
    joined = " ".join(texts).lower()
    for british in ("optimis", "colour", "visualis", "labell", "analys", "normalis", "behaviour"):
        assert british not in joined, british


def test_log_ticks():
    from tuner.plots import log_ticks
    t = log_ticks(0.13, 1.7, "")
    assert t["tickvals"] == [0.2, 0.5, 1.0] and t["ticktext"] == ["0.2", "0.5", "1"]
    assert log_ticks(0.4, 1.6)["ticktext"] == ["0.5", "0.7", "1", "1.5"]  # under a decade: finer steps
    t = log_ticks(100, 50000)
    assert t["ticktext"] == ["100", "200", "500", "1k", "2k", "5k", "10k", "20k", "50k"]
    assert len(log_ticks(1.1, 1.3)["tickvals"]) >= 2  # a narrow range still gets two ticks


def test_hint_names_build_gt_without_covisibility(tmp_path):
    from tuner.plots import report_sections, write_report
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    _study(storage, "no-cov", covisibility=False, root="/data/my scenes")
    secs = report_sections(storage, "no-cov", tmp_path)
    cov = [s for s in secs if "co-visibility" in s.title]
    assert len(cov) == 1 and cov[0].fig is None
    assert "no co-visibility for fountain-P11: run `tune data build-gt --data /data/my scenes`" in cov[0].note
    # the HTML: a heading only where there is no figure (a figure carries its own title)
    html = write_report(storage, "no-cov", tmp_path / "report.html", studies_dir=tmp_path).read_text()
    assert html.count("<h2>") == sum(s.fig is None for s in secs) == 1
    assert html.count('class="plotly-graph-div"') == sum(s.fig is not None for s in secs)
    assert "tune data build-gt --data /data/my scenes" in html and "Optimization history" in html


def test_single_trial_hint_names_the_command(tmp_path):
    from tuner.plots import report_sections
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    _study(storage, "one", n=1)
    secs = {s.title: s for s in report_sections(storage, "one", tmp_path)}
    imp = secs["Parameter importances"]
    assert imp.fig is None and "--study one and a larger --n-trials" in imp.note


def test_importances_say_their_method_and_follow_a_known_dependence(tmp_path):
    """mAA = 0.6 r' + 0.3 eta' + 0 Gamma' (each primed parameter uniform on [0, 1] over 200 random trials): r must
    matter most, Gamma not at all. The figure names its method (PED-ANOVA, optuna-dashboard's; it said fANOVA and
    'fraction of variance' while Optuna computed PED-ANOVA) and, when every trial has the same value, says the
    importances are equal by construction (Optuna's UserWarning used to reach stderr)."""
    import warnings

    import numpy as np
    import optuna
    from optuna.distributions import FloatDistribution, IntDistribution
    from optuna.trial import create_trial

    from tuner.plots import fig_importances
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    rng = np.random.default_rng(3)
    dist = {"ratio": FloatDistribution(0.6, 1.0), "threshold": FloatDistribution(0.1, 2.0),
            "max_iters": IntDistribution(1000, 100000)}
    st = optuna.create_study(direction="maximize")
    for _ in range(200):
        u = rng.uniform(size=3)
        st.add_trial(create_trial(value=float(0.6 * u[0] + 0.3 * u[1]), distributions=dist,
                                  params={"ratio": 0.6 + 0.4 * u[0], "threshold": 0.1 + 1.9 * u[1],
                                          "max_iters": int(1000 + 99000 * u[2])}))
    fig = fig_importances(st)
    imp = dict(zip(fig.data[0].y, fig.data[0].x))
    assert set(imp) == {"r", "eta (px)", "Gamma (iterations)"}
    assert imp["r"] > imp["eta (px)"] > imp["Gamma (iterations)"], imp
    assert imp["Gamma (iterations)"] < 0.05 and sum(imp.values()) == pytest.approx(1.0, abs=0.01), imp
    assert "PED-ANOVA" in fig.layout.title.text and "fANOVA" not in fig.layout.title.text
    assert "best 10% of trials" in fig.layout.xaxis.title.text
    assert not fig.layout.annotations

    same = optuna.create_study(direction="maximize")  # every trial at mAA 1.0 (an easy scene): nothing to tell apart
    for k in range(6):
        same.add_trial(create_trial(value=1.0, distributions=dist,
                                    params={"ratio": 0.7 + 0.05 * k, "threshold": 0.5, "max_iters": 2000 + k}))
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # nothing escapes to stderr
        fig = fig_importances(same)
    assert any("equal by construction" in (a.text or "") for a in fig.layout.annotations)


def test_breakdown_is_of_the_frozen_trial_not_the_best(tmp_path):
    """A study frozen with --select one-se: the accuracy-by-scene figure (titled "frozen trial") drew the best
    trial's validation curve next to the frozen trial's test curves (trial 33 beside trial 16 in a real study).
    Here one-se provably picks trial 1: all three trials lie within one SE of the best (SE = 0.2 / 1.96 ~ 0.10),
    and trial 1's r = 0.8 is the centre of r 0.6, 0.8, 1.0 on the search range [0.6, 1.0]."""
    import optuna
    from optuna.distributions import FloatDistribution
    from optuna.trial import create_trial

    from tuner.plots import report_sections
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    st = optuna.create_study(study_name="onese", storage=storage, direction="maximize")
    for k, v in {"task": "stereo", "feature": "sift", "num_features": 2048, "ransac": "degensac", "imtune": 1,
                 "select": "one-se", "budget": {"seconds_per_pair": B, "gamma_max": 20000},
                 "search_space_resolved": {"params": {"ratio": {"type": "float", "low": 0.6, "high": 1.0}},
                                           "fixed": {}},
                 "data": {"root": "/data/strecha", "val_scenes": ["fountain-P11"]}}.items():
        st.set_user_attr(k, v)
    accs = {0: 0.9, 1: 0.5, 2: 0.3}
    for i, (r, val) in enumerate([(0.6, 0.90), (0.8, 0.88), (1.0, 0.87)]):
        st.add_trial(create_trial(
            value=val, distributions={"ratio": FloatDistribution(0.6, 1.0)}, params={"ratio": r},
            constraints={"budget": 0.1 - B},
            user_attrs={"ransac_seconds_median": 0.1, "feasible": True, "mAA10_ci": [val - 0.1, min(1.0, val + 0.1)],
                        "scenes": {"fountain-P11": {"mAA10": val, "accuracy": [accs[i]] * 10}}}))
    secs = report_sections(storage, "onese", tmp_path)
    acc = next(s.fig for s in secs if s.fig is not None and s.title.startswith("Accuracy vs angular threshold"))
    (tr,) = [t for t in acc.data if "validation" in t.name]
    assert "trial 1" in tr.name and list(tr.y) == [0.5] * 10, (tr.name, list(tr.y))


def test_history_legend_explains_the_grey_over_budget_points(tmp_path):
    """Optuna draws infeasible trials grey and leaves them out of the legend: the history figure showed unexplained
    grey points (5 over-budget trials of the README job); the legend now names them."""
    from tuner.plots import INFEASIBLE, fig_history
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    st = _study(storage, "grey", n=12, seed=2)
    assert any(t.constraints["budget"] > 0 for t in st.trials)  # the helper made some trials over budget
    fig = fig_history(st)
    (grey,) = [tr for tr in fig.data if tr.name == INFEASIBLE]
    assert grey.showlegend is not False
    assert all(tr.showlegend is not False for tr in fig.data if len(tr.x or ()) > 0)


def test_gamma_max_label_sits_on_its_line_on_the_log_axis(tmp_path):
    """The Gamma figure's x axis is logarithmic, where plotly places an annotation at x = log10(value); the
    'Gamma_max = ... (budget)' label was given x = Gamma_max itself (10^20000 on this axis), so it never showed
    beside its red line (the README job's report: a bare dashed line). Gamma_max is 20000 here."""
    import math as _m

    from tuner.plots import fig_gamma
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    st = _study(storage, "gmax")
    fig = fig_gamma(st)
    assert fig.layout.xaxis.type == "log"
    (line,) = [s for s in fig.layout.shapes if s.x0 == s.x1]
    assert line.x0 == 20000
    (label,) = [a for a in fig.layout.annotations if "Gamma_max" in (a.text or "")]
    assert label.text == "Gamma_max = 20k (budget)"
    assert label.x == pytest.approx(_m.log10(20000))


def _multiview_study(tmp_path) -> str:
    """A multiview study "mv" (only r searched, 3 complete trials) in a SQLite storage under tmp_path: its URL."""
    import optuna
    from optuna.distributions import FloatDistribution
    from optuna.trial import create_trial
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    st = optuna.create_study(study_name="mv", storage=storage, direction="maximize")
    for k, v in {"task": "multiview", "feature": "sift", "num_features": 2048, "ransac": "degensac", "imtune": 1,
                 "budget": {"seconds_per_pair": B}, "data": {"root": "/data/strecha", "val_scenes": ["fountain-P11"]}}.items():
        st.set_user_attr(k, v)
    for i, r in enumerate((0.8, 0.85, 0.9)):
        st.add_trial(create_trial(value=0.9 + 0.01 * i, distributions={"ratio": FloatDistribution(0.6, 1.0)},
                                  params={"ratio": r}, user_attrs={"feasible": True}))
    return storage


def test_a_multiview_report_does_not_ask_for_an_eta_it_never_searches(tmp_path):
    """A multiview study (COLMAP runs its own RANSAC; only r is searched) had its 'mAA vs eta across studies' section
    say "needs studies with at least 2 trials within budget that search eta: run more trials", a hint no number of
    trials can satisfy; it now says the task does not search eta."""
    from tuner.plots import report_sections
    storage = _multiview_study(tmp_path)
    sec = next(s for s in report_sections(storage, "mv", tmp_path) if "eta across studies" in s.title)
    assert sec.fig is None and "run more trials" not in sec.note, sec.note
    assert "multiview" in sec.note and "does not search eta" in sec.note, sec.note


def test_a_multiview_report_header_states_no_estimator_budget(tmp_path):
    """The multiview study's report opened with "budget B = 0.5 s per pair (median estimator CPU time), Gamma_max not
    calibrated": a budget its task never applies (no estimator of imtune's is timed; COLMAP runs its own RANSAC)."""
    from tuner.plots import write_report
    storage = _multiview_study(tmp_path)
    page = write_report(storage, "mv", tmp_path / "report.html", studies_dir=tmp_path).read_text()
    head = page[page.index("<h1>"):page.index("</p>")]
    assert "budget B = 0.5" not in head and "Gamma_max" not in head, head
    assert "no estimator budget" in head, head
    assert "trials: 3 complete, 0 pruned" in head and "over budget" not in head, head  # was "(0 over budget)"


def test_contour_legend_names_its_black_and_grey_points(tmp_path):
    """The eta-r contour drew trials as black and grey dots (Optuna's 'Feasible Trial' / 'Infeasible Trial', hidden
    from the legend): nothing said the grey ones are over budget, never frozen. The legend now names both."""
    from tuner.plots import FEASIBLE, INFEASIBLE, fig_contour
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    st = _study(storage, "dots", n=12, seed=2)
    fig = fig_contour(st)
    dots = {tr.name: tr for tr in fig.data if tr.type == "scatter" and len(tr.x or ()) > 0}
    assert set(dots) == {FEASIBLE, INFEASIBLE}, set(dots)
    assert all(tr.showlegend is not False for tr in dots.values())


def test_eta_curves_sit_at_the_geometric_centres_of_their_log_bins(tmp_path):
    """The best-mAA-per-eta-bin curve is drawn on a log eta axis: its bins are equal in log eta, and each point sits
    at its bin's geometric centre (the middle on that axis), not the arithmetic one. Two trials at 0.1 and 10 px
    make two bins, [0.1, 1] and [1, 10] px: points at 0.316 and 3.16 px (arithmetic centres: 0.55 and 5.5)."""
    import optuna
    from optuna.distributions import FloatDistribution
    from optuna.trial import create_trial

    from tuner.plots import fig_eta_curves
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    storage = f"sqlite:///{tmp_path / 'o.db'}"
    st = optuna.create_study(study_name="eta", storage=storage, direction="maximize")
    st.set_user_attr("imtune", 1)
    st.set_user_attr("task", "stereo")
    dist = {"threshold": FloatDistribution(0.05, 20.0, log=True)}
    for eta, v in ((0.1, 0.4), (10.0, 0.6)):
        st.add_trial(create_trial(params={"threshold": eta}, distributions=dist, value=v))
    fig = fig_eta_curves(storage, st)
    (tr,) = fig.data
    assert fig.layout.xaxis.type == "log"
    assert list(tr.x) == pytest.approx([10 ** -0.5, 10 ** 0.5], rel=2e-3) and list(tr.y) == [0.4, 0.6]
