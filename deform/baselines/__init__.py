"""Baselines beside DEFORM, all with the predictor interface of :mod:`deform.evaluate`:
attribute ``n``, ``initial_state(x0, x1)`` (torch (B, n, 3) frames 0 and 1) returning a state with
``x`` (B, n, 3), and ``step(state, grip_next)`` with ``grip_next`` (B, 4, 3) the gripped vertices
0, 1, n-2, n-1 at the next frame.

- ``hold_shape``: the interior shape of frame 1 held still, gripped vertices following the inputs.
- ``der_initial``: plain discrete elastic rod (DEFORM without the residual network), the rod
  config's initial parameters.
- ``der_identified``: the same with physical parameters identified on the train recordings
  (``weights/der_ROD.pt``).
- ``xpbd``: an XPBD rope (distance and bending constraints), compliances and damping tuned on the
  train recordings (``weights/xpbd_ROD.json``).
- ``bilstm``: a bidirectional LSTM over the vertices in the style of Yan et al. 2020, trained on
  the train recordings (``weights/bilstm_ROD.pt``).

``load_baseline(name, rod, path=None)``: ``path`` overrides the shipped weight file.
Training of everything: ``benchmarks/baselines.py``.
"""

from __future__ import annotations

from pathlib import Path

from deform.errors import UsageError

WEIGHT_DIR = Path(__file__).resolve().parent / "weights"

BASELINES = ("hold_shape", "der_initial", "der_identified", "xpbd", "bilstm")


class UnknownBaselineError(UsageError):
    """A method name that is not one of :data:`BASELINES`."""


class MissingWeightsError(UsageError, FileNotFoundError):
    """A baseline whose trained weights are not on disk."""


def load_baseline(name: str, rod: str, path: str | None = None):
    """A predictor for ``rod`` (a rod config name such as ``DLO1``). Unknown names raise
    :class:`UnknownBaselineError`, missing weight files :class:`MissingWeightsError` (both
    :class:`deform.errors.UsageError`, which the CLI reports as one line).

    Args:
        name: ``hold_shape``, ``der_initial``, ``der_identified``, ``xpbd`` or ``bilstm``.
        rod: a rod config name.
        path: a weights file instead of the default one (where the baseline has weights).

    Returns:
        An object with ``n``, ``initial_state`` and ``step``, as :func:`deform.evaluate.predict_recordings` takes.
    """
    if name == "hold_shape":
        from deform.baselines.hold_shape import HoldShape
        from deform.config import load_rod_config

        return HoldShape(load_rod_config(rod).n_vertices)
    if name == "der_initial":
        from deform.baselines.der import der_initial

        return der_initial(rod)
    if name == "der_identified":
        from deform.baselines.der import der_identified

        return der_identified(rod, path)
    if name == "xpbd":
        from deform.baselines.xpbd import load_xpbd

        return load_xpbd(rod, path)
    if name == "bilstm":
        from deform.baselines.bilstm import load_bilstm

        return load_bilstm(rod, path)
    raise UnknownBaselineError(f"unknown method {name!r}; known: deform, {', '.join(BASELINES)}")
