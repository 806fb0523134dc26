r"""How well the clips pin down each physical parameter of the calibrated model.

Each parameter is scaled by factors around the value found, the rest of the model held, and the
held-out prediction fit (:func:`calibrate.fit.prediction_fit`, against the clouds) is measured. The
range a parameter is *told* within is bracketed by the nearest factors, on a grid from 1/8 to 8,
whose fit leaves the found model's by more than ``tolerance``:

.. math:: \mathrm{fit}(f\,p) > (1 + \mathrm{tol})\,\mathrm{fit}(p).

A side with no such factor is open: the clips do not bound the parameter there, and within the grid
any value on that side predicts the held-out motion as well. Why not a Laplace
1-sigma (as ``deform diagnose`` gives): the fit's noise model is unknown (surface points, dropouts,
a tracked start), and a profile over factors needs none; it also sees the residual network absorb
a change, which a local curvature would not.
"""

from __future__ import annotations

import copy
import math

import torch

from deform import DeformModel

FACTORS = (1 / 8, 1 / 4, 1 / 2, 2**-0.5, 2**-0.25, 2**0.25, 2**0.5, 2.0, 4.0, 8.0)

# parameter -> (the model's log-parameter it scales, unit)
PARAMETERS = {
    "bend_stiffness_Nm2": ("log_beta", "N m^2"),
    "damping_per_s": ("log_damping", "1/s"),
    "drag_per_m": ("log_drag", "1/m"),
}
FITS = 1 + len(PARAMETERS) * len(FACTORS)  # held-out fits parameter_ranges makes (for the time limit)


def scaled(model: DeformModel, parameter: str, factor: float) -> DeformModel:
    """A copy of ``model`` with ``parameter`` (a key of :data:`PARAMETERS`) times ``factor``."""
    out = copy.deepcopy(model)
    with torch.no_grad():
        getattr(out, PARAMETERS[parameter][0]).add_(math.log(factor))
    return out


def told_range(fits: dict[float, float], best: float, tolerance: float) -> tuple[float | None, float | None]:
    """``(low, high)`` factors: on each side of 1, the nearest grid factor whose fit leaves
    ``(1 + tolerance) * best``, so that every value the clips cannot tell from the one found lies
    between them; None on a side where the fit never leaves it (the grid's end reached).

    Args:
        fits: held-out fit [m] per factor.
        best: the found model's fit [m].
        tolerance: relative worsening that counts as telling a parameter apart.
    """
    bound = best * (1 + tolerance)

    def first_out(side):
        for f in side:
            if not fits[f] <= bound:  # NaN (a diverged rollout) tells it apart too
                return f
        return None

    low = first_out(sorted((f for f in fits if f < 1), reverse=True))
    return low, first_out(sorted(f for f in fits if f > 1))


def parameter_ranges(model: DeformModel, fit, tolerance: float) -> dict:
    """Per parameter of :data:`PARAMETERS`: the value found, the held-out fit at each factor and the
    range the clips tell it within (module docstring).

    Args:
        model: the calibrated model.
        fit: ``fit(model) -> float``, the held-out prediction fit [m].
        tolerance: relative worsening that tells a value apart (calibrate's MIN_GAIN).

    Returns:
        ``{"held_out_fit_m", "tolerance", "parameters": {parameter: {"found", "unit",
        "fit_by_factor", "told_within": [low, high] (values; None: not bounded on that side),
        "told": bool}}}``; no parameter when the found model's fit is not finite (nothing to tell
        values apart with).
    """
    best = fit(model)
    out: dict = {"held_out_fit_m": best, "tolerance": tolerance, "parameters": {}}
    if not math.isfinite(best):  # nothing held out to tell values apart with
        return out
    for name, (attr, unit) in PARAMETERS.items():
        values = getattr(model, attr).detach().double().exp()
        found = float(values.median())
        fits = {f: fit(scaled(model, name, f)) for f in FACTORS}
        low, high = told_range(fits, best, tolerance)
        out["parameters"][name] = {
            "found": found,
            "unit": unit,
            "fit_by_factor": {f"{f:.3g}": fits[f] for f in FACTORS},
            "told_within": [None if low is None else found * low, None if high is None else found * high],
            "told": low is not None and high is not None,
        }
    return out
