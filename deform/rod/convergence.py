"""What the solvers of one step report about convergence, for code that cannot branch on data.

A compiled or ahead-of-time step runs fixed iteration counts (``branch_free``); the twist solver and
the projection then leave their own stopping measures here, per rod, so the caller can redo the
rods that did not converge without evaluating anything twice (:meth:`DeformModel.unconverged_from_report`).
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class ConvergenceReport:
    """Per-rod flags of one step, filled by the solvers that ran.

    Attributes:
        length_error: (B,) each rod's largest relative edge error after the branch-free sweeps of
            the projection (NaN counts as unconverged); None until the projection ran.
        twist_unconverged: (B,) bool, rods whose branch-free Newton iterations on the material
            angles had not met the solver's stopping rule; None with the Theseus solver.
    """

    length_error: Tensor | None = None
    twist_unconverged: Tensor | None = None


class _ExportSettings(threading.local):
    loops = True  # per thread: two threads may export steps of different batch sizes at once


_EXPORT = _ExportSettings()


@contextmanager
def loops_when_exported(enabled: bool) -> Iterator[None]:
    """Within: :func:`masked_loop` exports a ``while_loop`` (``enabled``) or unrolled iterations.

    Why both: a loop compiles once and exits early, which wins where a step is overhead-bound (one
    rod, tens of rods); unrolled, inductor can plan the memory of the whole step, which wins for a
    thousand rods (:func:`deform.aot.exports_loops`)."""
    before, _EXPORT.loops = _EXPORT.loops, enabled
    try:
        yield
    finally:
        _EXPORT.loops = before


def masked_loop(body: Callable, carry: tuple[Tensor, ...], active: Tensor, count: int):
    """Up to ``count`` iterations of ``body(carry, active) -> (carry, active)``, where ``body`` masks
    its updates to the rods still ``active`` (a bool tensor per rod), so iterating a converged rod
    changes nothing. Eager and under ``torch.compile``: a plain loop of ``count``. While exporting
    (the ahead-of-time step, :mod:`deform.aot`; unless :func:`loops_when_exported` says otherwise):
    one ``while_loop`` that stops when no rod is active or after ``count``.

    Why: unrolled, each iteration is a copy of the body in the compiled graph, and the graph's size
    sets the compile time (the loop step's package took 48 s with 6 twist iterations and 3 sweeps,
    84 s with 12 and 6); as a loop the body is compiled once and an easy step (most are: two
    iterations) exits early.

    Returns:
        ``(carry, active)`` after the iterations.
    """
    if not (torch.compiler.is_exporting() and _EXPORT.loops):
        for _ in range(count):
            carry, active = body(carry, active)
        return carry, active
    from torch._higher_order_ops import while_loop

    # carried flat: the loop's state must keep its layout from one iteration to the next, and a
    # batch of one rod has a size-1 dimension whose stride export leaves symbolic
    shapes = [c.shape for c in carry]
    batch = active.shape

    def cond(i, active, *flat):
        return (i < count) & active.any()

    def step(i, active, *flat):
        carry = tuple(f.reshape(s) for f, s in zip(flat, shapes))
        carry, active = body(carry, active.reshape(batch))
        return (i + 1, active.reshape(-1).clone(), *(c.reshape(-1).clone() for c in carry))

    start = (
        torch.zeros((), dtype=torch.int64),
        active.reshape(-1).clone(),
        *(c.reshape(-1).clone() for c in carry),
    )
    out = while_loop(cond, step, start)
    return tuple(f.reshape(s) for f, s in zip(out[2:], shapes)), out[1].reshape(batch)


def merge_reports(into: ConvergenceReport, reports: list[ConvergenceReport]) -> None:
    """Fill ``into`` with the worst of several steps' reports (a frame stepped in substeps): the
    largest length error per rod (NaN kept) and every rod any step left with unconverged angles."""
    lengths = [r.length_error for r in reports if r.length_error is not None]
    if lengths:
        into.length_error = functools.reduce(torch.maximum, lengths)
    twists = [r.twist_unconverged for r in reports if r.twist_unconverged is not None]
    if twists:
        into.twist_unconverged = functools.reduce(torch.logical_or, twists)
