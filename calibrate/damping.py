r"""The damping that the training windows cannot see, set on the training clips' longer predictions.

The model's velocity damping :math:`c` takes a free motion down as :math:`e^{-c t}`. Training
predicts windows of 1 s (:class:`calibrate.fit.Budget` ``horizon``), and for a light rope
(:math:`c \approx 0.3`/s, a time constant of 3 s) a window barely sees it: the residual network
absorbs much of what the damping would do there, and the identification leaves it where the
windows' noise puts it (DLO1 from camera clips: 0.10-0.12/s, the mocap-trained model 0.34/s; the
report's held-out profile cannot tell it from 1/8 to 8 times). Over the paper's 5 s open loop it
decides how far the rope swings on.

So after training, the damping alone is scaled by the factor :math:`f` whose open-loop prediction
from the *training* tracks over ``horizon`` (3 s) fits their clouds best
(:func:`calibrate.fit.prediction_fit`): a grid :math:`f = 2^{k/2}`, :math:`k = -4..4`, then the
quarter octaves either side of the best. The held-out clips are not used; they still judge the
round. The damping moves only when a factor fits better than the trained value by more than
``min_gain``: a flat profile keeps what training found. The same fits give the range the clips tell
the damping within (:func:`calibrate.identifiability.told_range` around the value set), which the
report states.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from calibrate.identifiability import scaled, told_range
from deform import DeformModel

COARSE = tuple(2 ** (k / 2) for k in range(-4, 5))  # 1/4 .. 4, half octaves
FINE = (2**-0.25, 2**0.25)  # then a quarter octave either side of the best
MAX_FITS = len(COARSE) + len(FINE)  # rollouts the search makes at most (the trained value is in COARSE)


def settle_damping(
    model: DeformModel,
    fit: Callable[[DeformModel], float],
    min_gain: float = 0.005,
    tolerance: float = 0.01,
) -> tuple[DeformModel, dict]:
    """The model with its damping scaled by the factor that ``fit`` scores best (module docstring).

    Args:
        model: the trained model (not changed).
        fit: a model's open-loop fit against the training clips' clouds [m] (lower is better; NaN
            when no clip is long enough).
        min_gain: the share by which the best factor must beat the trained damping to replace it.
        tolerance: the share by which a fit must be worse than the set damping's to tell a value
            apart from it (the calibration's, :data:`calibrate.fit.MIN_GAIN`).

    Returns:
        ``(model, search)``: the model (a copy when its damping changed, else ``model``) and what the
        search found: ``factor``, ``damping_per_s`` before and after, ``fits`` by factor [m] and
        ``told_within_per_s`` ([low, high]: the nearest searched values either side of the one set
        that fit worse by more than ``tolerance``; None where none does).
    """
    fits: dict[float, float] = {}

    def score(f: float) -> float:
        """The fit at factor ``f`` (each factor rolled out once); a diverged rollout (NaN) loses."""
        key = round(f, 6)
        if key not in fits:
            fits[key] = fit(scaled(model, "damping_per_s", f)) if f != 1.0 else fit(model)
        return fits[key] if math.isfinite(fits[key]) else math.inf

    before = float(model.damping.detach().mean())
    base = score(1.0)
    if not math.isfinite(base):
        return model, {
            "factor": 1.0,
            "damping_per_s": [before, before],
            "fits": {},
            "told_within_per_s": [None, None],
            "note": "no clip long enough",
        }
    best = min(COARSE, key=score)
    best = min((best, *(best * g for g in FINE)), key=score)
    factor = best if score(best) < base * (1.0 - min_gain) else 1.0
    out = model if factor == 1.0 else scaled(model, "damping_per_s", factor)
    after = float(out.damping.detach().mean())
    chosen = round(factor, 6)
    span = told_range({f / chosen: v for f, v in fits.items()}, fits[chosen], tolerance)
    return out, {
        "factor": round(factor, 4),
        "damping_per_s": [before, after],
        "fits": {f"{f:g}": v for f, v in sorted(fits.items())},
        "told_within_per_s": [None if f is None else after * f for f in span],
    }
