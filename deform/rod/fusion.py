"""Straight-line pieces of a differentiable step, fused by ``torch.compile`` (forward and backward).

Why: the discrepancy tool descends many small models (13 vertices, a dozen windows each); a step
with its backward is ~370 tiny autograd nodes whose cost is their count, not their arithmetic.
Inductor fuses each pure piece (geometry and curvature projections, the closed-form forces, a
length-projection sweep) into a few C++ kernels, forward and backward; the data-dependent loops
(the twist solve, the sweeps' stopping rule) stay eager between them. Unlike :mod:`deform.compiled`
(whole inference steps, padded to bucket sizes) the pieces are compiled with symbolic sizes, once
for every batch of rods (once per vertex count: the tridiagonal solve loops over the edges), and
they keep first-order autograd.

Only steps with gradients are fused (the descents, where the backward gains most): a forward-only
batch of the same rods gained nothing in a diagnosis, and every traced variant costs a process about
2.5 s. Compiling costs a minute or two the first time (inductor caches it on disk for later
processes). Anything that fails to compile (no C++ compiler, an unsupported build) runs eagerly
after one warning; ``DEFORM_COMPILE=0`` in the environment keeps every piece eager.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from typing import Generic, ParamSpec, TypeVar

import torch
import torch.fx.experimental._config as shape_config

log = logging.getLogger("deform.fusion")

P = ParamSpec("P")
R = TypeVar("R")

_failed: list[str] = []  # set once a compile failed: every piece is eager from then on


def fusion_enabled() -> bool:
    """Whether fused pieces are wanted: not switched off by ``DEFORM_COMPILE=0`` and no compile
    has failed in this process."""
    return os.environ.get("DEFORM_COMPILE", "1") != "0" and not _failed


class Fused(Generic[P, R]):
    """``fn`` compiled on first call (symbolic sizes), or ``fn`` itself when fusion is off, without
    gradients, inside another compiled graph (which inlines it anyway), or after a failed compile."""

    def __init__(self, fn: Callable[P, R]):
        self.fn = fn
        self._compiled: Callable[P, R] | None = None

    def __call__(self, *args: P.args, **kwargs: P.kwargs) -> R:
        if not fusion_enabled() or not torch.is_grad_enabled() or torch.compiler.is_compiling():
            return self.fn(*args, **kwargs)
        if self._compiled is None:
            self._compiled = torch.compile(self.fn, dynamic=True)
        try:
            # sizes that happen to be equal (12 windows of a 13-vertex rod: 12 edges) get symbols of
            # their own, not one shared one that a loop over the edges would then fix for the batch
            with shape_config.patch(use_duck_shape=False):
                return self._compiled(*args, **kwargs)
        except Exception as exc:  # a missing compiler or an unsupported build: eager from now on
            if not _failed:
                log.warning("fused pieces unavailable (%s: %s); stepping eagerly", type(exc).__name__, exc)
            _failed.append(type(exc).__name__)
            return self.fn(*args, **kwargs)
