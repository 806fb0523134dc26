"""The one-graph step shared by the compiled step (:mod:`deform.compiled`) and the ahead-of-time
package (:mod:`deform.aot`): what both trace, the inputs they trace it with, and inductor's options.

Its own module so that ``compiled`` can use ``aot`` without ``aot`` importing ``compiled`` back.
"""

from __future__ import annotations

import torch
from torch import Tensor

from deform.model import DeformModel, RodState, VertexMajorState, gripped_indices
from deform.rod.convergence import ConvergenceReport
from deform.rod.layout import vertex_major

# a C++ wrapper calls the kernels without a Python frame each (a step is ~30 kernels); memory
# planning takes a step's ~370 intermediate buffers from one allocation instead of one each (0.90x
# per one-graph step at B = 1, 0.93-0.95x at B = 64 and per predict rollout, in interleaved A/B
# runs; the same first-time compile, 110-125 s per graph)
COMPILE_OPTIONS = {"cpp_wrapper": True, "memory_planning": True}


def branch_free_step(
    model: DeformModel,
    state: VertexMajorState,
    grip_next: Tensor | None,
    branch_free: tuple[int, int],
    network_dtype: torch.dtype | None = None,
) -> tuple[VertexMajorState, Tensor]:
    """``model.step`` with fixed iterations, and which rods it left unconverged (by the solvers'
    own flags): what the one-graph step computes, compiled or ahead of time. Vertex-major in and
    out (:mod:`deform.rod.layout`): the callers convert outside the graph, where inside it each
    kernel would read a transposed input and not vectorise across rods.

    Args:
        model: the model.
        state: :class:`deform.model.VertexMajorState` of B rods.
        grip_next: (4, 3, B) gripped vertices at the new time, or None (nothing held).
        branch_free: (twist iterations, projection sweeps).
        network_dtype: the residual network's arithmetic (None: float32).

    Returns:
        ``(new state, unconverged)``: unconverged (B,) bool.
    """
    report = ConvergenceReport()
    new = model.step_vertex_major(
        state, grip_next, branch_free=branch_free, report=report, network_dtype=network_dtype
    )
    return new, model.unconverged_from_report(report)


def rod_at_rest(model: DeformModel, batch: int, dtype: torch.dtype) -> tuple[RodState, Tensor]:
    """``batch`` straight rods at rest and their gripped vertices: inputs to compile a step for
    (only shapes and dtype matter).

    Args:
        model: the model.
        batch: rods.
        dtype: of the state.

    Returns:
        ``(state, grip)``: grip (batch, 4, 3).
    """
    n, rest = model.n, model.rest_lengths().to(dtype)
    x = torch.zeros(n, 3, dtype=dtype)
    x[:, 0] = torch.cat([torch.zeros(1, dtype=dtype), torch.cumsum(rest, 0)])
    state = model.static_state(x.expand(batch, n, 3).clone(), rest=rest.expand(batch, -1).clone())
    return state, state.x[:, gripped_indices(n)].clone()


def rod_at_rest_vertex_major(
    model: DeformModel, batch: int, dtype: torch.dtype
) -> tuple[VertexMajorState, Tensor]:
    """:func:`rod_at_rest` vertex-major, as the one-graph step takes it (only shapes, strides and
    dtype matter when it is compiled for them).

    Args:
        model: the model.
        batch: rods.
        dtype: of the state.

    Returns:
        ``(state, grip)``: grip (4, 3, batch).
    """
    state, grip = rod_at_rest(model, batch, dtype)
    return state.vertex_major(), vertex_major(grip, 2)
