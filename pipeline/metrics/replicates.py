"""Tuned figures and tuned comparisons over K tuning replicates x N test pairs: one variance-components model.

Model (a two-way crossed random-effects design, replicates x pairs, one observation per cell):

    score[k, j] = mu + a_k + e_j + (ae)_kj

a_k: the tuning effect of replicate k (which optimum the study froze; variance sigma_t^2), e_j: the effect of test
pair j (which pairs were sampled), (ae)_kj: everything that differs between replicates pair by pair -- the estimator
seed and the tuning x pair interaction (variance sigma_r^2, possibly different per pair). All replicates are tested
on the same pairs. The grand mean's variance is

    Var(mean) = sigma_t^2 / K + sigma_e^2 / N + sigma_r^2 / (K N)

and it is estimated from the ANOVA mean squares, each source counted once (Cornfield & Tukey 1956; Searle, Casella &
McCulloch, *Variance Components*, 1992, ch. 4):

- pair part V_p = Var over pairs of the replicate-averaged column means / N, scene-stratified (the scenes are fixed
  strata; the variance of a stratified mean, Cochran, *Sampling Techniques*, 1977, 5.3). It holds sigma_e^2 / N and
  the interaction's sigma_r^2 / (K N): the pair x seed noise lives here and only here;
- tuning part T = max(0, s_rows^2 - MS_res / N) / K: s_rows^2, the sample variance of the K replicate figures, holds
  sigma_t^2 + sigma_r^2 / N; MS_res (the two-way interaction mean square) estimates sigma_r^2, so subtracting
  MS_res / N removes the seed noise that V_p already counts. (The earlier model added s_rows^2 / K to a pair
  bootstrap and counted sigma_r^2 / (K N) twice: intervals too wide, tests that lost power.)

The interval is mean +- t_{df} sqrt(V_p + T) with df by Satterthwaite (1946) over the mean squares (V_p on its
strata's df, s_rows^2 on K - 1, MS_res on (K - 1)(N - 1), the last with a negative coefficient); the p-value is the
same t test's (exact under the normal model at every level, not a normal tail rescaled to match at alpha). A paired
difference A - B on the same pairs uses the per-pair differences of the two sides' column means for V_p and adds
both sides' tuning parts.

What a side with K = 1 cannot give: its tuning variance. A figure with K = 1 gets the pair interval and
``tuning_variance_measured`` False. A comparison with one side at K = 1 takes that side's tuning variance equal to
the other side's (a stated assumption: exact when both are the same method; ``assumption`` says so) and gives no
verdict; with both at K = 1 it gives the pair-only figures and no verdict. ``benchmarks/verdict_calibration.py``
measures coverage, false positives and power of these functions on synthetic data with known truth.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import special

from pipeline.metrics.uncertainty.paired import format_p  # the project's p format (on its side of alpha)

TIE_TOLERANCE = 1e-12
NOT_MEASURED = "the tuning variance was not measured (1 replicate): the interval covers test pairs only"
#: power and target difference of the "could detect" / planning lines (mAA units)
POWER = 0.80
PLAN_DIFFERENCE = 0.05
PLAN_K = (3, 5, 10)
#: the Monte-Carlo draws of the P(A > B) interval
PAB_DRAWS = 2000
#: a tuned figure from fewer test pairs than this in some scene, above NEAR_CEILING, gets :data:`FEW_PAIRS_NOTE`
FEW_PAIRS = 10
NEAR_CEILING = 0.7
FEW_PAIRS_NOTE = ("fewer than 10 test pairs in a scene and a figure near the ceiling: intervals like this one "
                  "covered as little as 0.91 for 0.95 in the calibration benchmark (scores near 1 are skewed); "
                  "test on more pairs")
#: the fewest replicates per side for a tuned verdict: K = 2 leaves the tuning variance one degree of freedom, and
#: the calibration benchmark measured the interval of a K = 2 figure covering 0.89-0.91 where tuning dominates
MIN_VERDICT_K = 3
#: the spread over pairs of a real difference, as a share of it (see :meth:`ReplicatedDifference.se_at`): under
#: a probit link the per-pair effect of a method shift is proportional to phi(Phi^-1(score)), whose coefficient of
#: variation over the pairs of the calibration benchmark's world (pair log errors spread 0.45) is about 0.6; the
#: median se at the truth grew there as if by 0.4-0.65. Over 14 verdict cells simulated to choose it (400-600 data
#: sets each, :meth:`ReplicatedDifference.df_at` included), 0.4 / 0.5 / 0.6 put the power at the median "could
#: detect" figure in 0.75-0.85 / 0.75-0.86 / 0.75-0.88. An assumption about how real differences spread over
#: pairs: docs/statistics.md states it.
EFFECT_CV = 0.5
#: the confidence level of the replicate term at which the df are computed (see ``_variance``)
DF_BOUND = 0.40


@dataclass(frozen=True)
class Components:
    """Variance components of one side (score^2 units): ``k`` replicates x ``n`` pairs. ``row_var``: sample variance
    of the K replicate figures (nan at K = 1); ``ms_res``: the replicate x pair interaction mean square (seed and
    tuning x pair noise of one pair, nan at K = 1); ``tuning_var``: sigma_t^2 = max(0, row_var - ms_res / n)."""

    k: int
    n: int
    row_var: float
    ms_res: float

    @property
    def measured(self) -> bool:
        return self.k > 1

    @property
    def tuning_var(self) -> float:
        return max(0.0, self.row_var - self.ms_res / self.n) if self.measured else math.nan


@dataclass(frozen=True)
class ReplicatedInterval:
    """Mean of a tuned figure over replicates and pairs, with its interval (same units); ``df`` of its t quantile."""

    mean: float
    low: float
    high: float
    replicates: int
    se_pairs: float
    se_between: float
    tuning_variance_measured: bool
    df: float = math.inf
    #: a caveat the calibration benchmark measured for this design ("" when none), e.g. :data:`FEW_PAIRS_NOTE`
    note: str = ""


@dataclass(frozen=True)
class ReplicatedDifference:
    """A - B of two tuned configurations on the same pairs (interval at 1 - alpha, two-sided t-test p).

    ``p_a_beats_b`` (with ``p_a_beats_b_ci``): the probability that one new tuning of A scores above one new tuning
    of B on the same N test pairs, Phi(delta / sigma_1) under the model (the common-language effect size of McGraw &
    Wong 1992 over replicates; see :func:`_pab`); None when neither side measured its tuning variance. ``mde``: the
    smallest |A - B| this comparison detects with 80% power at its alpha, each variance part taken at its
    median-unbiased value (:meth:`power_at`). ``plan``: what K and how many test pairs would detect
    ``PLAN_DIFFERENCE``. ``assumption``: the assumption the figures rest on when a side has K = 1 (then no verdict),
    else None."""

    diff: float
    low: float
    high: float
    p_value: float
    tuning_variance_measured: bool
    df: float = math.inf
    se: float = 0.0
    alpha: float = 0.05
    replicates: tuple[int, int] = (1, 1)
    pairs: int = 0
    strata: int = 1
    assumption: str | None = None
    components: dict = field(default_factory=dict)
    #: (s^2, df) of one replicate's figure per side (empty: no side measured it)
    row_terms: tuple = ()
    seed: int = 0
    plan_target: float = PLAN_DIFFERENCE
    #: the variance parts of ``se`` as (value, df): each replicate part (with its 1 / K coefficient) and the
    #: pair-effect part (possibly negative; see ``_variance``)
    var_terms: tuple = ()
    #: the figures (plain means) of A and of B, in [0, 1] for mAA scores: :meth:`se_at` scales the lower one's
    #: replicate part by the slope of the scale there
    side_means: tuple = ()

    # computed on first use: each solves for a power or draws a bootstrap, which the many comparisons of a
    # simulation do not all need
    @functools.cached_property
    def power_se(self) -> float:
        """The standard error that the power statements use: each variance part at its median-unbiased value
        (s^2 df / chi2_df(0.5)), floored at ``se``. Why: an estimated variance on few df is below its truth more
        often than above (chi-square with 2 df: 61% of its mass below its mean), so power computed at the
        estimate over-promised -- with the truth at the median "could detect" figure, 0.70 was reached for 0.80
        at 3 vs 3 replicates. Each part separately, not the sum at its Welch df: a K = 3 replicate part on 2 df
        needs far more correction than a pair part on tens -- except the two sides' replicate parts on the same
        df (K_A = K_B), which are corrected as one sum (:func:`median_unbiased_factors`: why there). The
        calibration benchmark measures the power reached at the median of the figures (``power_at_mde``)."""
        if not self.var_terms:
            return self.se
        rows, (pair, dfp) = self._row_parts, self.var_terms[-1]
        parts = [v * f for (v, _), f in zip(rows, self._row_factors)] + [max(pair, 0.0) * median_unbiased(dfp)]
        return max(self.se, math.sqrt(sum(parts)))

    @property
    def _row_parts(self) -> list:
        return [(max(v, 0.0), d) for v, d in self.var_terms[:-1]]

    @functools.cached_property
    def _row_factors(self) -> list:
        """The median-unbiasing factor of each replicate part (:func:`median_unbiased_factors`: two sides with the
        same K are corrected as one sum)."""
        return median_unbiased_factors(self._row_parts)

    def se_at(self, effect: float) -> float:
        """The standard error the test would have if the true |A - B| were ``effect``: :attr:`power_se` (each part
        median-unbiased) with two changes that a bounded score brings, both measured in the calibration benchmark
        (``python benchmarks/verdict_calibration.py``; the truth at the median "could detect" figure reached 0.73
        with 5 vs 5 replicates on 8 pairs and 0.90 with 3 vs 3 and a large tuning sd before them):

        - a real difference is not the same on every pair: on a score bounded in [0, 1] a method shift moves pairs
          in mid-range more than pairs near 0 or 1 (a probit link: the effect on a pair is proportional to the
          slope phi(Phi^-1(score))), so the per-pair differences spread by about ``EFFECT_CV`` x effect and the
          pair part grows by (EFFECT_CV effect)^2 / N. Null data carry no trace of it (in the benchmark's world the
          median se at the truth was a third above the null's with 8 test pairs and a small tuning sd);
        - the side that falls by ``effect`` moves toward 0, where its score varies less: its replicate part is
          scaled by the ratio of the probit slopes at its figure now and at the figure minus ``effect``
          (:func:`_slope_ratio`), to its first power, not the square a small shift would give (why: there). Which
          side falls: the lower one (B at a tie). A borrowed side (K = 1) keeps its part unscaled.

        At ``effect`` 0 it is :attr:`power_se`."""
        return self._at(effect)[0]

    def df_at(self, effect: float) -> float:
        """The df the test would have at a true |A - B| of ``effect``: Welch-Satterthwaite's over the very parts
        :meth:`se_at` sums -- each at its median-unbiased value, the pair part grown and the falling side's
        replicate part scaled. Why: the spread of a real difference raises the pair part's share, and with it the
        test's df; power at the null's df under-promised where replicate parts on 2 df dominate (3 vs 3 at 8
        pairs: 0.93 reached at the median figure against 0.80).

        Why the median-unbiased parts and not the raw estimates: the power is stated at those parts, and their df
        must be theirs. With raw parts a K = 3 side
        (2 df, raised most by the correction) weighed too little in the df: with 3 vs 5 replicates, 30 pairs and a
        large tuning sd the df at the truth's median figure came out 6.4 where Welch's over the true parts is 5.0,
        and the power reached 0.69-0.71 for 0.80 (fresh seeds, 1000 data sets). ``df`` at ``effect`` 0 (the
        test's own df). Comparisons with a side below MIN_VERDICT_K keep the bounded df of :func:`_variance`."""
        return self._at(effect)[1]

    def _at(self, effect: float) -> tuple[float, float]:
        e = abs(effect)
        if not self.var_terms or e == 0:
            return self.power_se, self.df
        hetero = (EFFECT_CV * e) ** 2 / max(self.pairs, 1)
        var = self.power_se ** 2 + hetero
        rows = self._row_parts
        factors = self._row_factors
        if len(rows) == 2 and self.side_means:  # both sides measured: the falling side's part scales
            low = 1 if self.side_means[1] <= self.side_means[0] else 0
            v, d = rows[low]
            shrink = _slope_ratio(self.side_means[low], e)  # its first power: see _slope_ratio
            var -= v * factors[low] * (1.0 - shrink)
            rows[low] = (v * shrink, d)
        pair, dfp = self.var_terms[-1]
        if min(self.replicates) < MIN_VERDICT_K:  # the bounded df of such comparisons (see ``_variance``)
            rows = [(v * d / _chi2_quantile(DF_BOUND, d), d) for v, d in rows]
            df = _welch([*rows, (max(pair, 0.0) + hetero, dfp)])[1]
        else:  # the df of the very parts ``var`` sums: each at its median-unbiased value
            df = _welch([*((v * f, d) for (v, d), f in zip(rows, factors)),
                         (max(pair, 0.0) * median_unbiased(dfp) + hetero, dfp)])[1]
        return math.sqrt(max(var, 0.0)), df

    def power_at(self, effect: float) -> float:
        """The power of this comparison's test (at its alpha) when the true |A - B| is ``effect``, at
        :meth:`se_at` and :meth:`df_at` (``effect``): what 'could detect' means (``power_at(mde)`` is 0.80)."""
        se, df = self._at(effect)
        if se <= 0:
            return 1.0 if effect else self.alpha
        return power(abs(effect) / se, df, self.alpha)

    @functools.cached_property
    def mde(self) -> float:
        """The smallest true |A - B| with :meth:`power_at` 0.80 (scipy's brentq up to 60 power_se, at least 1, as
        :func:`detectable` searches; inf where nothing there reaches it: df < 1, or the spread of a difference over
        very few pairs growing as fast as the difference)."""
        from scipy.optimize import brentq
        if self.power_se <= 0:
            return 0.0
        top = max(1.0, 60.0 * self.power_se)
        if self.power_at(top) < POWER:
            return math.inf
        if self.power_at(1e-9) >= POWER:  # a variance of ~0 (identical replicates): any difference is detected
            return 0.0
        return float(brentq(lambda e: self.power_at(e) - POWER, 1e-9, top, xtol=1e-5))

    @functools.cached_property
    def plan(self) -> str:
        if not self.row_terms or self.mde <= self.plan_target:  # it detects the target already: nothing to plan
            return ""
        c = self.components
        ka, kb = self.replicates
        ka, kb = (ka, kb) if self.assumption is None else (max(ka, kb), max(ka, kb))  # a borrowed side: the other's
        dfr = ((ka - 1) * (self.pairs - 1), (kb - 1) * (self.pairs - 1))
        # each estimated component at its median-unbiased value, as :attr:`power_se` (the two sides' like
        # components on equal df as one sum: :func:`median_unbiased_factors`)
        fia, fib = median_unbiased_factors([(c["interaction_a"] / ka, dfr[0]), (c["interaction_b"] / kb, dfr[1])])
        fta, ftb = median_unbiased_factors([(c["tuning_a"] / ka, ka - 1), (c["tuning_b"] / kb, kb - 1)])
        return plan_text(self.pairs * max(0.0, c["pair_effects"]) * median_unbiased(c["pairs_df"]),
                         c["interaction_a"] * fia, c["interaction_b"] * fib, c["tuning_a"] * fta, c["tuning_b"] * ftb,
                         alpha=self.alpha, target=self.plan_target, n_now=self.pairs, strata=self.strata,
                         side_means=self.side_means if self.assumption is None else ())

    @functools.cached_property
    def _pab(self) -> tuple[float, tuple[float, float]] | None:
        if not self.row_terms:
            return None
        return _pab(self.diff, self.se, self.df, list(self.row_terms), self.seed, self.alpha,
                    borrowed=self.assumption is not None)

    @property
    def p_a_beats_b(self) -> float | None:
        return self._pab[0] if self._pab else None

    @property
    def p_a_beats_b_ci(self) -> tuple[float, float] | None:
        return self._pab[1] if self._pab else None

    @property
    def verdict_allowed(self) -> bool:
        """Both sides have at least MIN_VERDICT_K replicates: only then can the comparison say 'significant'."""
        return min(self.replicates) >= MIN_VERDICT_K

    @property
    def significant(self) -> bool:
        return self.verdict_allowed and self.p_value < self.alpha

    def verdict(self, a: str = "A", b: str = "B", b_tuned: bool = True) -> str:
        """One line: the difference ``a`` - ``b``, its interval and p; 'significant' only where both sides have
        K >= MIN_VERDICT_K; an inconclusive one says what it could have detected and what would detect PLAN_DIFFERENCE.
        ``b_tuned`` False: B is not a tuned configuration (the paper defaults), so only A's K = 1 is missing."""
        ka, kb = self.replicates
        pct = f"{100 * (1 - self.alpha):.0f}%"
        head = (f"{a} - {b} = {self.diff:+.4f} [{self.low:+.4f}, {self.high:+.4f}] ({pct}), "
                f"p = {format_p(self.p_value, self.alpha)}")
        if not self.verdict_allowed:
            once = [name for name, k, tuned in ((a, ka, True), (b, kb, b_tuned)) if k < 2 and tuned]
            if once:
                who = " and ".join(once)
                was = "were" if len(once) > 1 else "was"
                why = f"{who} {was} tuned once (K = 1): the tuning variance was not measured"
            else:
                why = ("K = 2 rests the tuning variance on one degree of freedom, too few for a calibrated verdict "
                       "(the calibration benchmark: intervals covering 0.89-0.91 for 0.95)")
            return f"{head} {self.assumption_text()}; no tuned verdict: {why}; rerun with --replicates 3"
        if self.significant:
            line = f"{head}: significant"
        else:
            line = (f"{head}: inconclusive: could detect |{a} - {b}| >= {self.mde:.3f}" if math.isfinite(self.mde)
                    else f"{head}: inconclusive: no difference would be detected with {POWER:.0%} power")
            if self.plan:
                line += f"; {self.plan}"
        if self.p_a_beats_b is not None and self.p_a_beats_b_ci is not None:
            lo, hi = self.p_a_beats_b_ci
            line += f"; P({a} > {b}) = {self.p_a_beats_b:.2f} [{lo:.2f}, {hi:.2f}]"
        return line

    def assumption_text(self) -> str:
        if self.assumption:
            return f"(assuming {self.assumption})"
        return "(over test pairs only)" if not self.tuning_variance_measured else "(K = 2 x 2)"


# -- the components -------------------------------------------------------------------------------------------

def _check(scores, strata) -> tuple[np.ndarray, np.ndarray]:
    scores = np.asarray(scores, dtype=float)
    if scores.ndim != 2 or scores.shape[1] < 2 or scores.shape[0] < 1:
        raise ValueError(f"scores must be replicates x pairs with >= 2 pairs, got shape {scores.shape}")
    if not np.all(np.isfinite(scores)):
        raise ValueError("scores must be finite (a failed pair scores 0)")
    strata = np.zeros(scores.shape[1], int) if strata is None else np.asarray(strata)
    if strata.shape != (scores.shape[1],):
        raise ValueError(f"strata must have one entry per pair ({scores.shape[1]}), got {strata.shape}")
    return scores, strata


def pair_part(values: np.ndarray, strata: np.ndarray) -> tuple[float, float]:
    """(variance, df) of the plain mean of per-pair ``values`` (N,) sampled within fixed ``strata``: the stratified
    estimator (1 / N^2) sum_s n_s s_s^2 with Satterthwaite's df over the strata (Cochran 1977, 5.4). A stratum of one
    pair has no within variance: then the strata are pooled (one stratum; conservative)."""
    values = np.asarray(values, float)
    n = values.size
    names = np.unique(strata)
    sizes = [int(np.sum(strata == s)) for s in names]
    if min(sizes) < 2:
        names, sizes, strata = np.array([0]), [n], np.zeros(n, int)
    terms, dfs = [], []
    for s, ns in zip(names, sizes):
        v = values[strata == s]
        terms.append(ns * float(np.var(v, ddof=1)) / n**2)
        dfs.append(ns - 1)
    var = float(sum(terms))
    den = sum(t * t / d for t, d in zip(terms, dfs))
    df = var * var / den if den > 0 else float(sum(dfs))
    return var, float(df)


def components(scores: np.ndarray) -> Components:
    """The side's :class:`Components` from its K x N score matrix (plain means; scale the columns beforehand for a
    weighted mean). MS_res = sum of squared two-way residuals / ((K - 1)(N - 1)): E[MS_res] is the mean over pairs
    of the interaction variance, heteroscedastic pairs included."""
    k, n = scores.shape
    if k < 2:
        return Components(k, n, math.nan, math.nan)
    rows = scores.mean(axis=1)
    resid = scores - rows[:, None] - scores.mean(axis=0)[None, :] + scores.mean()
    ms_res = float(np.sum(resid**2) / ((k - 1) * (n - 1)))
    return Components(k, n, float(np.var(rows, ddof=1)), ms_res)


def _welch(terms: list[tuple[float, float]]) -> tuple[float, float]:
    """(sum, Welch-Satterthwaite df) of non-negative variance terms (value, df): df = (sum v)^2 / sum v^2 / df_i
    (Satterthwaite 1946; Welch 1947). inf for a zero sum."""
    var = float(sum(v for v, _ in terms))
    den = sum(v * v / d for v, d in terms if v > 0 and d > 0)
    return var, (var * var / den if den > 0 and var > 0 else math.inf)


def _variance(vp: float, dfp: float, sides: list[tuple[Components, float]], n: int,
              bound_df: bool = True) -> tuple[float, float, float]:
    """(variance, df, pair-effect part) of a mean (one side) or a difference (two sides) over replicates x pairs.

    ``vp`` (on ``dfp`` df): the stratified variance of the mean of the replicate-averaged pair values, which holds
    the pair effects' variance / N AND each side's interaction (seed, tuning x pair) variance / (K N). ``sides``:
    (components, coefficient) per side whose replicate figures enter with that coefficient (1 / K, or
    1 / K_A + 1 / K_B for a borrowed side). Grouped so that each source is counted once and no term is subtracted
    in the df: variance = sum coef * row_var (the replicate figures' own variance: tuning + their seed noise at N
    pairs, on K - 1 df each) + (vp - sum coef * ms_res / N) (the pair effects alone: the interaction that the rows
    already hold taken out of the pair part). The pair-effect part is kept unbiased, not truncated at 0: under "same
    method" it is 0 in truth, and max(0, .) inflated the variance enough to hold false positives at 3.8% instead of
    5%. Its df is the pair part's; a negative part enters the sum but not the df, and the sum is floored at half the
    replicates' part (a guard; rare). A plug-in Satterthwaite df over the ungrouped terms (row_var and -ms_res / N
    with its negative coefficient) came out at a median 2.8 where the statistic behaved as t with 4 df: 1.5% false
    positives at 5% (the calibration benchmark).

    The df: Welch-Satterthwaite's plug-in df is too large when a replicate term with K - 1 = 1 or 2 df falls low by
    chance (chi-square with 1 df has a quarter of its mass below 0.1): the t quantile then shrinks exactly when the
    true variance is underestimated (coverage 0.908 at K = 2 with a large tuning sd). So the df is computed with each
    replicate term at its upper DF_BOUND confidence limit, row_var (K - 1) / chi2_{K-1}(DF_BOUND) -- the spirit of
    Graybill & Wang's (1980) modified large-sample bounds; a rule written here because no library has one for a
    mean. On normal scores (30 pairs, K = 2, 3, 5, tuning sd 0.01-0.1) DF_BOUND 0.3 / 0.4 / 0.5 covered K = 2 with a
    large tuning sd 0.946 / 0.938 / 0.930, and held 3-vs-3 false positives at 3.4-4.9% each; 0.4 is the middle. The
    calibration benchmark measures it on mAA scores.

    ``bound_df`` False: the plug-in df. :func:`replicated_difference` asks for it when both sides measured their
    tuning variance on K >= 3 replicates: the sum of two independent replicate variances (>= 4 df together) falls
    low far less often than one, and the bound there only cost power (the calibration benchmark's world at 3 vs 3
    replicates, 30 pairs, small tuning sd, 3000 data sets: power at a true 0.05 of 0.203 with the bound and 0.229
    without, false positives at .05 of 4.6% and 5.0%; one K = 3 figure without the bound covered 0.913 at 200 pairs
    with a large tuning sd, 0.932 with it)."""
    rows = [(coef * c.row_var, c.k - 1) for c, coef in sides if c.measured]
    inter = sum(coef * c.ms_res / n for c, coef in sides if c.measured)
    pair_effects = vp - inter if rows else vp
    var, _ = _welch([*rows, (max(0.0, pair_effects), dfp)])
    # the df with each replicate term at its upper DF_BOUND confidence limit (the variance itself stays unbiased)
    bounded = [(v * d / _chi2_quantile(DF_BOUND, d), d) for v, d in rows] if bound_df else rows
    _, df = _welch([*bounded, (max(0.0, pair_effects), dfp)])
    if pair_effects < 0:
        var = max(var + pair_effects, 0.5 * var)
    return var, df, pair_effects


def _chi2_quantile(q: float, df: float) -> float:
    return float(special.chdtri(df, 1.0 - q))  # chdtri(df, y) is the chi-square quantile of upper tail y


def _slope_ratio(m: float, effect: float) -> float:
    """phi(Phi^-1(m - effect)) / phi(Phi^-1(m)): how much less (or more) a score at mean ``m`` moves per unit of a
    latent shift after falling by ``effect``, under a probit link (both clipped into [1e-4, 1 - 1e-4]).

    :meth:`ReplicatedDifference.se_at` scales the falling side's replicate part by this ratio, not by its square.
    The square is the delta method: right when the noise that makes the part is small on the scale where the
    link bends. The replicate part is the variance of a side's figure over replicates: its tuning shift plus, per
    pair, seed and tuning x pair noise as wide as the spread of the pairs themselves, on a score that counts the
    thresholds (a decade of pose error) an error passes. A pair's score then varies like a share of thresholds
    passed, its variance like p (1 - p) at its level p, and p (1 - p) falls with the level like phi(Phi^-1(p)),
    the first power of the slope (the two ratios agree within 10% for levels in 0.2..0.7). Measured in the
    calibration benchmark's world (1000 data sets a cell, truth at the median "could detect" figure): the falling
    side's mean replicate part was 0.87 / 0.91 / 0.92 of the null's (3 vs 5 at 30 pairs and a large tuning sd,
    3 vs 3 at 8 pairs and a small one, 5 vs 5 at 30 and a large one), where this ratio gives 0.89 / 0.90 / 0.94
    and its square 0.79 / 0.81 / 0.89. The square under-stated the se at the truth, and the power reached fell
    to 0.70-0.75 where a large tuning sd dominates; the ratio itself gave 0.74-0.88 in all 27 verdict cells on
    two fresh seeds (``benchmarks/verdict_power_probe.py``)."""
    lo, hi = 1e-4, 1 - 1e-4
    z0 = float(special.ndtri(min(max(m, lo), hi)))
    z1 = float(special.ndtri(min(max(m - effect, lo), hi)))
    return math.exp(-0.5 * (z1 * z1 - z0 * z0))


def median_unbiased_factors(parts: list[tuple[float, float]]) -> list[float]:
    """The factor that makes each of independent variance parts (value, df) median-unbiased in their sum: its own
    ``median_unbiased(df)``, except that parts on the same df are corrected together at the Welch-Satterthwaite df
    of their sum (one factor for all of them).

    Why: the median of a sum is not the sum of the medians. Two independent parts on d df each with equal
    expectations sum to a variance on 2 d df exactly (chi2_d + chi2_d = chi2_2d), whose median-unbiasing factor is
    that of 2 d df: 1.19 at two sides with K = 3 (d = 2), where each part at its own 2 df took 1.44 and put the
    median of the corrected sum about 20% above the truth. The detectable difference came out too large: with the
    truth at its median, 3 vs 3 replicates on 200 pairs with a small tuning sd reached a power of 0.84-0.85 for 0.80
    on two 1000-data-set probes (``benchmarks/verdict_power_probe.py``) and 0.89 in a 400-data-set run; the normal
    model alone (chi-square parts, no bounded scores) gave 0.84-0.85 with the separate factors and 0.80-0.81 with
    the joint one.

    Parts on equal df are exchangeable, so the Welch df of their sum (between d and 2 d) does not depend on which
    of them was estimated low. Parts on different df keep their own factors: there the plug-in df of a sum rises
    exactly when the few-df part is estimated low (the part that needs the correction most; see ``_variance``),
    and the joint factor took 3 vs 5 replicates down to a power of 0.69-0.81."""
    factors = [median_unbiased(d) for _, d in parts]
    for d in {d for _, d in parts}:
        same = [i for i, (_, di) in enumerate(parts) if di == d]
        if len(same) > 1:
            f = median_unbiased(_welch([(max(parts[i][0], 0.0), d) for i in same])[1])
            for i in same:
                factors[i] = f
    return factors


def median_unbiased(df: float) -> float:
    """The factor df / chi2_df(0.5) that makes a variance estimate on ``df`` df (s^2 ~ sigma^2 chi2_df / df)
    median-unbiased: 1.44 at 2 df, 1.19 at 4, 1.03 at 30, 1 at inf."""
    if not math.isfinite(df) or df <= 0:
        return 1.0
    return df / _chi2_quantile(0.5, df)


# -- a tuned figure -------------------------------------------------------------------------------------------

def replicated_interval(scores, strata=None, *, alpha: float = 0.05, **_ignored) -> ReplicatedInterval:
    """Interval of the grand mean of ``scores`` (K replicates x N pairs; plain mean) at 1 - alpha: the model of the
    module doc. K = 1: the pair interval alone (``tuning_variance_measured`` False)."""
    scores, strata = _check(scores, strata)
    k, n = scores.shape
    vp, dfp = pair_part(scores.mean(axis=0), strata)
    c = components(scores)
    var, df, pe = _variance(vp, dfp, [(c, 1.0 / k)], n)
    m = float(scores.mean())
    half = t_quantile(1 - alpha / 2, df) * math.sqrt(var) if var > 0 else 0.0
    se_b = math.sqrt(c.row_var / k) if c.measured else 0.0
    return ReplicatedInterval(m, m - half, m + half, k, math.sqrt(max(pe, 0.0)), se_b, c.measured, df)


def scene_weights(strata: np.ndarray) -> np.ndarray:
    """Per-pair factor N w_p (w_p = 1 / (n_scenes n_scene_pairs)) that makes a plain mean the benchmark's mean over
    scenes (each scene's pair mean, scenes weighing alike)."""
    names, counts = np.unique(strata, return_counts=True)
    per = dict(zip(names.tolist(), counts.tolist()))
    return np.array([len(strata) / (len(names) * per[s]) for s in strata.tolist()])


def replicated_maa_interval(scores, strata, *, alpha: float = 0.05, **_ignored) -> ReplicatedInterval:
    """The tuned mAA `tune` reports: the model of :func:`replicated_interval` on ``scores`` (K x N per-pair mAA
    scores in [0, 1]) weighted as the benchmark's mAA (the mean over scenes of each scene's pair mean), its
    interval formed on the logit scale (:func:`logit_interval`). ``note``: :data:`FEW_PAIRS_NOTE` where a scene has
    fewer than FEW_PAIRS pairs and the figure is above NEAR_CEILING (where the benchmark measured it short)."""
    scores, strata = _check(scores, strata)
    weighted = scores * scene_weights(strata)[None, :]
    iv = replicated_interval(weighted, strata, alpha=alpha)
    # near a bound of the score (the figure above NEAR_CEILING or below 1 - NEAR_CEILING), the df at most the pair
    # part's own (the df of K = 1). Why: the model's df pools the replicate figures' K - 1 df with the pair-effect
    # part's, as if each were chi-square; near the ceiling the per-pair scores are skewed (a few low pairs among
    # many at 1), so the pair variance from 4 pairs a scene is far less stable than chi-square on its df, and a df
    # above it narrows the interval exactly where the figure is high by chance. Measured at 8 test pairs near
    # mAA(10) 0.89 (600 simulated data sets per cell of the calibration benchmark's world): K = 5 covered
    # 0.887-0.937 with the pooled df and 0.932-0.972 with the cap; K = 1 (df = the pair part's) 0.940-0.970.
    # Mid-scale (mAA(10) 0.57) the scores are not skewed, the pooled df covered 0.93-0.98 and the cap took it to
    # 0.99: not applied there.
    df = iv.df
    if not 1.0 - NEAR_CEILING <= iv.mean <= NEAR_CEILING:
        df = min(df, pair_part(weighted.mean(axis=0), strata)[1])
    q = t_quantile(1 - alpha / 2, df)
    half = (iv.high - iv.mean) / t_quantile(1 - alpha / 2, iv.df) if iv.high > iv.mean else 0.0
    lo, hi = logit_interval(iv.mean, half, q)
    few = min(np.unique(strata, return_counts=True)[1]) < FEW_PAIRS and iv.mean > NEAR_CEILING
    return ReplicatedInterval(iv.mean, lo, hi, iv.replicates, iv.se_pairs, iv.se_between,
                              iv.tuning_variance_measured, df, FEW_PAIRS_NOTE if few else "")


def logit_interval(mean: float, se: float, q: float) -> tuple[float, float]:
    """[lo, hi] of a mean of scores in [0, 1] with standard error ``se`` and quantile ``q``: mean +- q se on the
    logit scale (the delta method: se / (m (1 - m)) there), mapped back. Why: per-pair scores near 1 are skewed,
    and a sample whose mean is high by chance has a small spread (correlation -0.8 between the figure and its se
    at 2 scenes x 4 pairs near mAA 0.9), so the symmetric interval missed low: with 8 test pairs near mAA 0.89 it
    covered 0.77-0.89, the arcsine-square-root scale 0.83-0.93, the logit scale 0.88-0.96 (``python
    benchmarks/verdict_calibration.py --figure-scales``). Pseudo-scores at 0 and 1 in each scene covered 0.99-1.00
    (far too wide at 4 pairs a scene) and a bounded df for the pair strata changed nothing (simulations of the
    same world). A mean at 0 or 1, or se 0: the point."""
    if se <= 0 or mean <= 0.0 or mean >= 1.0:
        return max(0.0, min(1.0, mean)), max(0.0, min(1.0, mean))
    g = math.log(mean / (1.0 - mean))
    s = se / (mean * (1.0 - mean))
    return float(special.expit(g - q * s)), float(special.expit(g + q * s))


# -- a tuned comparison ---------------------------------------------------------------------------------------

def t_quantile(p: float, df: float) -> float:
    """Student's t quantile (scipy.special.stdtrit: the same function as stats.t.ppf without its per-call
    overhead, which dominated the calibration benchmark); df inf is the normal."""
    return float(special.stdtrit(df, p))


def one_sample_t(x, alpha: float = 0.05) -> tuple[float, list[float] | None, float | None, float | None]:
    """(mean, its 1 - alpha Student t interval, se, the two-sided one-sample t test's p against 0) of ``x`` (scipy).
    One value: no interval, se or p. Every value equal: the interval is the point, se 0, p 1 at 0 and 0 elsewhere.
    The one place frozen - reference over runs, over replicates and over seeds is computed."""
    from scipy import stats
    x = np.asarray(x, float)
    mean = float(x.mean())
    if len(x) < 2:
        return mean, None, None, None
    se = float(x.std(ddof=1) / math.sqrt(len(x)))
    if se == 0:
        return mean, [mean, mean], 0.0, (1.0 if mean == 0 else 0.0)
    half = float(stats.t.ppf(1 - alpha / 2, len(x) - 1)) * se
    return mean, [mean - half, mean + half], se, float(stats.ttest_1samp(x, 0.0).pvalue)


def t_two_sided_p(t: float, df: float) -> float:
    return float(min(1.0, 2.0 * special.stdtr(df, -abs(t))))


def power(effect: float, df: float, alpha: float) -> float:
    """Power of the two-sided t test at ``alpha`` when the true difference is ``effect`` standard errors, the
    variance estimated on ``df`` degrees of freedom: the noncentral t (scipy.special.nctdtr), not the normal
    approximation, which over-promises at the few df of K = 3 replicates."""
    q = t_quantile(1 - alpha / 2, df)
    if not math.isfinite(df):
        return float(special.ndtr(effect - q) + special.ndtr(-effect - q))
    upper, lower = (float(np.nan_to_num(special.nctdtr(df, effect, x), nan=0.0)) for x in (q, -q))  # nan: underflow
    return min(1.0, max(0.0, 1.0 - upper + lower))


def detectable(se: float, df: float, alpha: float, target_power: float = POWER) -> float:
    """The smallest true |difference| that the t test with standard error ``se`` on ``df`` df detects with
    ``target_power`` at ``alpha`` (``power`` solved for the effect by scipy's brentq)."""
    from scipy.optimize import brentq
    if se <= 0:
        return 0.0
    if power(60.0, df, alpha) < target_power:  # df < 1: no practical effect size is detectable
        return math.inf
    return float(brentq(lambda e: power(e, df, alpha) - target_power, 0.0, 60.0, xtol=1e-4)) * se


def _planned_se_df(k: int, n: int, strata: int, pair_var: float, res_a: float, res_b: float, tune_a: float,
                   tune_b: float, shrink: tuple[float, float] = (1.0, 1.0)) -> tuple[float, float]:
    """(se, df) of a difference at K replicates per side and n pairs, from the estimated components: each side's
    replicate part times its ``shrink`` (see :meth:`ReplicatedDifference.se_at`), the df Welch's over these
    parts, as :meth:`ReplicatedDifference.df_at` forms them."""
    rows = [(shrink[0] * (tune_a + res_a / n) / k, k - 1), (shrink[1] * (tune_b + res_b / n) / k, k - 1)]
    var, df = _welch([*rows, (pair_var / n, max(1, n - strata))])
    return math.sqrt(var), df


def plan_text(pair_var: float, res_a: float, res_b: float, tune_a: float, tune_b: float, *, alpha: float,
              target: float = PLAN_DIFFERENCE, n_now: int = 0, strata: int = 1, max_pairs: int = 20000,
              side_means: tuple = ()) -> str:
    """What K (both sides, from ``PLAN_K``) and how many test pairs would detect ``target`` with 80% power at
    ``alpha``, from the estimated components (per pair: pair effects ``pair_var``, each side's interaction
    ``res_*``; tuning ``tune_*``), the df and power as :func:`power` computes them; the first K that reaches it
    with at most ``max_pairs`` pairs, and at least the pairs there are now.

    The power is the one :meth:`ReplicatedDifference.power_at` states for a true difference of ``target``: the
    per-pair variance grows by (EFFECT_CV target)^2 (a real difference spreads over pairs) and, given
    ``side_means`` (A's and B's figures), the lower side's replicate part is scaled by :func:`_slope_ratio` at
    ``target`` (it falls toward 0, where a bounded score varies less). With the null's se the plan promised 80%
    at designs where the comparison's own "could detect" line, formed at the same design, promised less."""
    hetero = (EFFECT_CV * target) ** 2
    shrink = (1.0, 1.0)
    if len(side_means) == 2:
        s = _slope_ratio(min(side_means), target)
        shrink = (s, 1.0) if side_means[0] < side_means[1] else (1.0, s)
    for k in PLAN_K:
        def ok(n: int, k: int = k) -> bool:
            se, df = _planned_se_df(k, n, strata, pair_var + hetero, res_a, res_b, tune_a, tune_b, shrink)
            return se == 0 or power(target / se, df, alpha) >= POWER
        if not ok(max_pairs):
            continue
        lo, hi = max(2, strata + 1), max_pairs
        if ok(lo):
            hi = lo
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if ok(mid) else (mid, hi)
        return f"K = {k} and {max(hi, n_now)} test pairs would detect {target:.2f}"
    return (f"even K = {PLAN_K[-1]} with {max_pairs} test pairs would not detect {target:.2f}: the tuning "
            "variance alone is too large")


def p_a_beats_b(a_means, b_means) -> float:
    """Fraction of (i, j) replicate pairs with A_i > B_j, ties (within 1e-12) counted half: the empirical version of
    :attr:`ReplicatedDifference.p_a_beats_b`, without an interval (kept for readers of older outputs)."""
    a = np.asarray(a_means, float)[:, None]
    b = np.asarray(b_means, float)[None, :]
    tie = np.abs(a - b) <= TIE_TOLERANCE
    return float((((a > b) & ~tie).sum() + 0.5 * tie.sum()) / (a.size * b.size))


def _pab(diff: float, se: float, df: float, row_terms: list[tuple[float, int]], seed: int, alpha: float,
         borrowed: bool = False) -> tuple[float, tuple[float, float]] | None:
    """P(one new tuning of A > one of B on the same N pairs) = Phi(delta / sigma_1), sigma_1^2 = s_A^2 + s_B^2 the
    variance of the difference of two single tunings (``row_terms``: (s^2, df) of one replicate's figure per side;
    ``borrowed``: both entries are the one measured side's). Written here: no library gives this quantity.

    Estimate: Phi(diff / sqrt(s_1^2 - se^2)). For diff ~ N(delta, se^2), E[Phi(diff / c)] = Phi(delta /
    sqrt(c^2 + se^2)), so c^2 = sigma_1^2 - se^2 makes it unbiased (with c^2 floored at s_1^2 / 4). The plug-in
    Phi(diff / s_1) ran 0.02-0.04 low under a real difference: Phi bends, and diff is noisy on the scale of s_1.

    Interval: the 2.5% and 97.5% quantiles of Phi(d* / sigma_1*) over draws of d* = diff - se T_df (the comparison's
    own t) and sigma_1*^2 = s_1^2 nu / chi2_nu (the fiducial distribution of a variance on nu df, nu the Welch df of
    the replicate parts). Under the null it holds 0.5 exactly when the t test does not reject. The parametric
    bootstrap it replaced drew s_1^2 chi2_nu / nu (a new estimate around the old one, not the truth given the
    estimate) and covered 0.89 at a true difference of 0.09 (3 vs 3, 30 pairs)."""
    s2 = sum(v for v, _ in row_terms)
    if not row_terms:
        return None
    if s2 <= 0:
        est = 0.5 if diff == 0 else float(diff > 0)
        return est, (est, est)
    nu = float(row_terms[0][1]) if borrowed else _welch([(v, float(d)) for v, d in row_terms])[1]
    rng = np.random.default_rng(seed)
    t = rng.standard_t(df if math.isfinite(df) else 1e6, PAB_DRAWS)
    d = diff - se * t if se > 0 else np.full(PAB_DRAWS, diff)
    v = s2 * nu / rng.chisquare(nu, PAB_DRAWS) if math.isfinite(nu) else np.full(PAB_DRAWS, s2)
    lo, hi = (float(x) for x in np.quantile(special.ndtr(d / np.sqrt(v)), [alpha / 2, 1 - alpha / 2]))
    est = float(special.ndtr(diff / math.sqrt(max(s2 - se * se, s2 / 4))))
    return min(max(est, lo), hi), (lo, hi)


def replicated_difference(a, b, strata=None, *, alpha: float = 0.05, seed: int = 0, plan_target: float = PLAN_DIFFERENCE,
                          **_ignored) -> ReplicatedDifference:
    """A - B of ``a`` (K_A x N) and ``b`` (K_B x N) on the same N pairs (plain means: scale the columns beforehand
    for the benchmark's weighting): the model of the module doc, its t interval and p, P(A > B) with an interval,
    the detectable difference and a plan. A side with K = 1 borrows the other side's tuning variance (stated in
    ``assumption``); both at K = 1: pairs only. No verdict unless both sides have K >= MIN_VERDICT_K (3)."""
    a, strata = _check(a, strata)
    b, _ = _check(b, strata)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"A and B must be tested on the same pairs: {a.shape[1]} vs {b.shape[1]}")
    ka, kb, n = a.shape[0], b.shape[0], a.shape[1]
    per_pair = a.mean(axis=0) - b.mean(axis=0)
    d = float(per_pair.mean())
    vp, dfp = pair_part(per_pair, strata)
    ca, cb = components(a), components(b)
    assumption = None
    if ca.measured and cb.measured:
        sides = [(ca, 1.0 / ka), (cb, 1.0 / kb)]
        tune_a, tune_b, res_a, res_b = ca.tuning_var, cb.tuning_var, ca.ms_res, cb.ms_res
        rows = [(ca.row_var, ka - 1), (cb.row_var, kb - 1)]
    elif ca.measured or cb.measured:  # one side tuned once: its replicate variance taken equal to the other's
        c, one = (ca, "A") if ca.measured else (cb, "B")
        other = "B" if one == "A" else "A"
        sides = [(c, 1.0 / ka + 1.0 / kb)]
        tune_a = tune_b = c.tuning_var
        res_a = res_b = c.ms_res
        rows = [(c.row_var, c.k - 1), (c.row_var, c.k - 1)]
        assumption = (f"{other}'s tuning varies as {one}'s, measured over {c.k} replicates: exact when both are the "
                      "same method")
    else:
        sides, rows = [], []
        tune_a = tune_b = res_a = res_b = 0.0
    # both sides with K >= 3: the plug-in df (see ``_variance``); a borrowed side or K = 2: bounded
    var, df, pair_effects = _variance(vp, dfp, sides, n, bound_df=min(ka, kb) < MIN_VERDICT_K)
    se = math.sqrt(max(var, 0.0))
    if se == 0.0:
        p = 1.0 if d == 0.0 else 0.0
        half = 0.0
    else:
        p = t_two_sided_p(d / se, df)
        half = t_quantile(1 - alpha / 2, df) * se
    measured = ca.measured and cb.measured
    parts = [(coef * c.row_var, c.k - 1) for c, coef in sides if c.measured] + [(pair_effects, dfp)]
    return ReplicatedDifference(
        d, d - half, d + half, p, measured, df=df, se=se, alpha=alpha, replicates=(ka, kb), pairs=n,
        strata=len(np.unique(strata)), assumption=assumption,
        components={"pairs": vp, "pairs_df": dfp, "pair_effects": pair_effects, "tuning_a": tune_a,
                    "tuning_b": tune_b, "interaction_a": res_a, "interaction_b": res_b},
        row_terms=tuple(rows), seed=seed, plan_target=plan_target, var_terms=tuple(parts),
        side_means=(float(a.mean()), float(b.mean())))


def difference_block(d: ReplicatedDifference, a: str = "A", b: str = "B", b_tuned: bool = True) -> dict:
    """The JSON fields every caller records of a tuned comparison (same names in test.json, compare and findings);
    ``a``, ``b``, ``b_tuned``: the names in its verdict line (:meth:`ReplicatedDifference.verdict`)."""
    return {"difference": d.diff, "ci": [d.low, d.high], "p_value": d.p_value, "df": d.df, "se": d.se,
            "significant": d.significant, "verdict_allowed": d.verdict_allowed,
            "tuning_variance_measured": d.tuning_variance_measured, "replicates": list(d.replicates),
            "p_a_beats_b": d.p_a_beats_b,
            "p_a_beats_b_ci": list(d.p_a_beats_b_ci) if d.p_a_beats_b_ci is not None else None,
            "detectable": d.mde, "plan": d.plan, "assumption": d.assumption, "verdict": d.verdict(a, b, b_tuned),
            "components": dict(d.components)}


# -- tuned rows of a table (records of replicates) ------------------------------------------------------------

def _replicate_matrix(replicates, tau: int) -> dict:
    """{(scene, pair): [score of replicate 1, ...]} from ``replicates`` (per replicate, a list of test runs, each a
    list of pair records {scene, pair, err}): each replicate's pair score averaged over its runs."""
    from pipeline.metrics.uncertainty.scores import pair_scores
    out: dict = {}
    for k, runs in enumerate(replicates):
        acc: dict = {}
        for run in runs:
            for r, v in zip(run, pair_scores([x["err"] for x in run], tau)):
                p = r["pair"]
                acc.setdefault((str(r["scene"]), tuple(p) if isinstance(p, list) else p), []).append(float(v))
        for key, vals in acc.items():
            out.setdefault(key, [math.nan] * len(replicates))[k] = float(np.mean(vals))
    return {key: v for key, v in out.items() if not any(math.isnan(x) for x in v)}


def replicated_records_value(replicates, tau: int = 10) -> float:
    """The tuned mAA(tau) of ``replicates`` (as :func:`_replicate_matrix`): the mean over replicates of the mean over
    scenes of each scene's pair mean."""
    m = _replicate_matrix(replicates, tau)
    if not m:
        return 0.0
    keys = sorted(m, key=str)
    strata = np.array([k[0] for k in keys])
    return float((np.array([m[k] for k in keys]).T * scene_weights(strata)[None, :]).mean())


def replicated_records_comparison(recs_a, recs_b, tau: int = 10, level: float = 0.95, seed: int = 0,
                                  **_ignored) -> dict:
    """B - A of two tuned rows given as replicates of test runs (see :func:`_replicate_matrix`), on the pairs every
    replicate of both scored, scene-weighted: :func:`replicated_difference` with the keys the ranking reads
    (``significant`` False whenever a side has K = 1: no tuned verdict, the rank is shared). ValueError without
    common pairs."""
    ma, mb = _replicate_matrix(recs_a, tau), _replicate_matrix(recs_b, tau)
    keys = sorted(set(ma) & set(mb), key=str)
    if len(keys) < 2:
        raise ValueError("no common pairs")
    strata = np.array([k[0] for k in keys])
    w = scene_weights(strata)[None, :]
    a = np.array([ma[k] for k in keys]).T * w
    b = np.array([mb[k] for k in keys]).T * w
    d = replicated_difference(b, a, strata, alpha=1 - level, seed=seed)
    return {"difference": d.diff, "ci": [d.low, d.high], "p_value": d.p_value, "significant": d.significant,
            "pairs": len(keys), "replicates": [a.shape[0], b.shape[0]], "verdict_allowed": d.verdict_allowed,
            "mde": d.mde}


METHOD = ("variance components of a replicates x pairs crossed design (pair part: scene-stratified variance of the "
          "replicate-averaged pair scores; tuning part: s^2 of the replicate figures minus the interaction mean "
          "square / N, so pair x seed noise counts once), t with Satterthwaite df, t-test p "
          "(pipeline.metrics.replicates)")
