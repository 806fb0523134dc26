r"""Vertex-major layout: the rod's own axes first, the batch of rods as the last, contiguous axis.

Why: a step's solvers run along the rod (a tridiagonal recursion over the vertices, one edge after
the other), so a rod's own values are processed one after the other, but the rods of a batch are
independent. With the rods innermost in memory (``(n, 3, B)`` instead of ``(B, n, 3)``), each
operation of the step is one contiguous loop over the rods, which compiled code vectorises; batch-
first, inductor's loops ran over 3 to 13 values of one rod and did not (a projection of 1024 rods,
two sweeps compiled on one thread: 0.09 ms vertex-major against 0.39 ms batch-first). The physics
(:mod:`deform.rod`) is written vertex-major; :class:`deform.model.RodState` and everything outside
the step stay batch-first, and convert at the step's boundary with these two functions.
"""

from __future__ import annotations

from torch import Tensor


def vertex_major(t: Tensor, event_dims: int, batch: tuple[int, ...] | None = None) -> Tensor:
    """``t`` (*batch, *event) as (*event, B), the batch flattened into one trailing axis.

    Args:
        t: a tensor whose last ``event_dims`` axes belong to one rod.
        event_dims: axes per rod (2 for vertices ``(n, 3)``, 1 for per-edge scalars ``(m,)``).
        batch: the batch shape to broadcast ``t`` to first (None: ``t``'s own; ``()``: one rod).

    Returns:
        (*event, B), contiguous.
    """
    event = t.shape[t.dim() - event_dims :]
    if batch is not None:
        t = t.expand(*batch, *event)
    if t.dim() == event_dims + 1 and t.shape[0] == 1 and t.is_contiguous():
        return t.view(*event, 1)  # one rod: the same memory either way (the 100 Hz loop's step)
    return t.reshape(-1, *event).movedim(0, -1).contiguous()


def batch_major(t: Tensor, batch: tuple[int, ...]) -> Tensor:
    """The inverse of :func:`vertex_major`: (*event, B) back to (*batch, *event).

    Args:
        t: (*event, B).
        batch: the batch shape.

    Returns:
        (*batch, *event), contiguous.
    """
    if t.shape[-1] == 1 and t.is_contiguous():
        return t.view(*batch, *t.shape[:-1])
    return t.movedim(-1, 0).reshape(*batch, *t.shape[:-1]).contiguous()
