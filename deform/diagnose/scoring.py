"""Held-out scoring: is a candidate's improvement on check/ real, and worth its parameters?

Per check recording ``r`` the relative improvement ``d_r = (e_ref,r - e_cand,r) / e_ref,r`` over a
reference refitted with the same budget (so extra optimisation alone earns nothing). A candidate is
significant when the lower bound of a bootstrap interval (over recordings) of the mean of ``d_r`` is
positive AND the mean exceeds ``min_gain + per_param * k`` (``k`` parameters): a parameter penalty
in the spirit of BIC, calibrated on planted-effect data (see docs/diagnose.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_GAIN = 0.04
PER_PARAM = 0.01
CONFIDENCE = 0.90


@dataclass
class Score:
    improvement: float  # mean relative reduction of the check L1
    ci_low: float
    ci_high: float
    threshold: float
    significant: bool


def bootstrap_ci(values: np.ndarray, confidence: float = CONFIDENCE, n_boot: int = 4000, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean over recordings."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(values), size=(n_boot, len(values)))
    means = values[idx].mean(1)
    a = (1 - confidence) / 2
    return float(np.quantile(means, a)), float(np.quantile(means, 1 - a))


def score(reference: np.ndarray, candidate: np.ndarray, n_params: int, min_gain: float = MIN_GAIN,
          per_param: float = PER_PARAM) -> Score:
    d = (reference - candidate) / reference
    lo, hi = bootstrap_ci(d)
    thr = min_gain + per_param * n_params
    mean = float(d.mean())
    return Score(mean, lo, hi, thr, bool(lo > 0 and mean > thr))
