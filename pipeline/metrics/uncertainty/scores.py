"""Per-pair (per-bag) mAA scores, their range and the defaults every interval and test uses (see the package doc)."""
from __future__ import annotations

import math

import numpy as np

from pipeline.metrics.pose import mean_average_accuracy

DEFAULT_RESAMPLES = 2000



DEFAULT_LEVEL = 0.95



#: the standard deviation over repeated test runs is the sample one (``Task.aggregate``, the ``mAA<tau>_std`` of
#: :func:`combine_runs_interval`): the runs are a sample of seeds; ddof 0 reads 0.82 of it at 3 runs
STD_DDOF = 1



#: the range of a pair's (a bag's) mAA score: the two pseudo-scores every scene's resamples include (module doc)
SCORE_RANGE = (0.0, 1.0)



def _stats():
    """scipy.stats, imported on first use: it takes about 1 s to import, and every `tune` command (its help, a
    one-line error) imports this module through the task registry."""
    from scipy import stats
    return stats



# ------------------------------------------------------------------------------------------ scores

def _errors_array(errors) -> np.ndarray:
    """float array of errors; "inf" strings (JSON files) -> inf, None -> inf (a failure)."""
    return np.array([math.inf if e is None else float(e) for e in errors], float)



def pair_scores(errors, tau: int = 10) -> np.ndarray:
    """Per-pair contribution to mAA(tau): the fraction of thresholds 1..tau degrees that the pair's
    error is within (1 = within 1 deg, 0 = above tau deg or failed). mAA(tau) is their mean."""
    e = _errors_array(errors)
    ks = np.arange(1, int(tau) + 1, dtype=float)
    return (e[:, None] <= ks[None, :]).mean(axis=1) if e.size else np.zeros(0)



def maa_from_errors(errors, tau: int = 10) -> float:
    """mAA(tau) of a list of pair errors (degrees; inf = failure). Exactly
    :func:`pipeline.metrics.pose.mean_average_accuracy` (it is called): 0 for no pairs."""
    return mean_average_accuracy(_errors_array(errors), int(tau))


def score_range() -> tuple:
    """:data:`SCORE_RANGE` as ``pipeline.metrics.uncertainty`` holds it when called: the intervals read it there, so
    that setting the package's name (a caller, a test without pseudo-scores) keeps working after the split."""
    import pipeline.metrics.uncertainty as package
    return package.SCORE_RANGE
