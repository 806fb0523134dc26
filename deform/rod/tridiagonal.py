r"""Batched solve of symmetric tridiagonal systems ``H x = r``.

``diag`` is (..., k), ``off`` is (..., k-1) (the super- and sub-diagonal). Small systems go through a
dense batched Cholesky (one kernel call beats k Python-level sweeps); large ones use the O(k)
Thomas algorithm, vectorised over the batch. Both report per system whether ``H`` is positive
definite (all pivots positive), which the Newton solver uses to pick its step.

Compiled code always takes the Thomas algorithm: inductor fuses its unrolled recursion into one
loop, where each LAPACK call would be a separate library call with its own checks.
"""

from __future__ import annotations

import torch
from torch import Tensor

DENSE_MAX = 128  # a dense Cholesky of 128 x 128 still beats a Python-level Thomas sweep


def to_dense(diag: Tensor, off: Tensor) -> Tensor:
    """The dense symmetric matrix of a tridiagonal system (tests and small problems).

    Args:
        diag: (..., k) diagonal.
        off: (..., k-1) off-diagonal.

    Returns:
        (..., k, k).
    """
    return torch.diag_embed(diag) + torch.diag_embed(off, offset=1) + torch.diag_embed(off, offset=-1)


def thomas(diag: Tensor, off: Tensor, rhs: Tensor, dim: int = -1) -> tuple[Tensor, Tensor]:
    """Thomas algorithm (Gaussian elimination without pivoting) for symmetric tridiagonal systems.

    Args:
        diag: (..., k) diagonal.
        off: (..., k-1) off-diagonal.
        rhs: (..., k) right-hand side.
        dim: the axis of the unknowns (0 for vertex-major arrays, :mod:`deform.rod.layout`).

    Returns:
        ``(x, ok)``: x shaped as ``rhs``; ok bool, one per system, every pivot positive (the
        matrix is positive definite).
    """
    k = diag.shape[dim]
    diag_, off_, rhs_ = diag.unbind(dim), off.unbind(dim), rhs.unbind(dim)
    c: list = []  # modified super-diagonal
    d: list = []  # modified right-hand side
    pivot = diag_[0]
    ok = pivot > 0
    c.append(off_[0] / pivot if k > 1 else None)
    d.append(rhs_[0] / pivot)
    for i in range(1, k):
        pivot = diag_[i] - off_[i - 1] * c[i - 1]
        ok = ok & (pivot > 0)
        c.append(off_[i] / pivot if i < k - 1 else None)
        d.append((rhs_[i] - off_[i - 1] * d[i - 1]) / pivot)
    x = [None] * k
    x[-1] = d[-1]
    for i in range(k - 2, -1, -1):
        x[i] = d[i] - c[i] * x[i + 1]
    return torch.stack(x, dim=dim), ok


def solve_tridiagonal_pd(diag: Tensor, off: Tensor, rhs: Tensor, dim: int = -1) -> tuple[Tensor, Tensor]:
    """Solve and report positive definiteness per system: ``(x, ok)``; ``x`` is meaningless where not ok.

    Args:
        diag: (..., k) diagonal.
        off: (..., k-1) off-diagonal (symmetric).
        rhs: (..., k) right-hand side.
        dim: the axis of the unknowns (as for :func:`thomas`).

    Returns:
        ``(x, ok)``: x shaped as ``rhs``, ok bool per system.
    """
    if diag.shape[dim] <= DENSE_MAX and not torch.compiler.is_compiling():
        diag, off, rhs = (t.movedim(dim, -1) for t in (diag, off, rhs))
        chol, info = torch.linalg.cholesky_ex(to_dense(diag, off))
        return torch.cholesky_solve(rhs.unsqueeze(-1), chol).squeeze(-1).movedim(-1, dim), info == 0
    return thomas(diag, off, rhs, dim)


def solve_tridiagonal(diag: Tensor, off: Tensor, rhs: Tensor, dim: int = -1) -> Tensor:
    """Solve a system known to be non-singular (used for the implicit gradient).

    Args:
        diag: (..., k) diagonal.
        off: (..., k-1) off-diagonal (symmetric).
        rhs: (..., k) right-hand side.
        dim: the axis of the unknowns (as for :func:`thomas`).

    Returns:
        The solution, shaped as ``rhs``.
    """
    if diag.shape[dim] <= DENSE_MAX and not torch.compiler.is_compiling():
        diag, off, rhs = (t.movedim(dim, -1) for t in (diag, off, rhs))
        return torch.linalg.solve(to_dense(diag, off), rhs.unsqueeze(-1)).squeeze(-1).movedim(-1, dim)
    return thomas(diag, off, rhs, dim)[0]
