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


def thomas(diag: Tensor, off: Tensor, rhs: Tensor) -> tuple[Tensor, Tensor]:
    """Thomas algorithm (Gaussian elimination without pivoting) for symmetric tridiagonal systems.

    Args:
        diag: (..., k) diagonal.
        off: (..., k-1) off-diagonal.
        rhs: (..., k) right-hand side.

    Returns:
        ``(x, ok)``: x (..., k), ok (...) bool, every pivot positive (the matrix is positive definite).
    """
    k = diag.shape[-1]
    c: list = []  # modified super-diagonal
    d: list = []  # modified right-hand side
    pivot = diag[..., 0]
    ok = pivot > 0
    c.append(off[..., 0] / pivot if k > 1 else None)
    d.append(rhs[..., 0] / pivot)
    for i in range(1, k):
        pivot = diag[..., i] - off[..., i - 1] * c[i - 1]
        ok = ok & (pivot > 0)
        c.append(off[..., i] / pivot if i < k - 1 else None)
        d.append((rhs[..., i] - off[..., i - 1] * d[i - 1]) / pivot)
    x = [None] * k
    x[-1] = d[-1]
    for i in range(k - 2, -1, -1):
        x[i] = d[i] - c[i] * x[i + 1]
    return torch.stack(x, dim=-1), ok


def solve_tridiagonal_pd(diag: Tensor, off: Tensor, rhs: Tensor) -> tuple[Tensor, Tensor]:
    """Solve and report positive definiteness per system: ``(x, ok)``; ``x`` is meaningless where not ok.

    Args:
        diag: (..., k) diagonal.
        off: (..., k-1) off-diagonal (symmetric).
        rhs: (..., k) right-hand side.

    Returns:
        ``(x, ok)``: x (..., k), ok (...) bool.
    """
    if diag.shape[-1] <= DENSE_MAX and not torch.compiler.is_compiling():
        chol, info = torch.linalg.cholesky_ex(to_dense(diag, off))
        return torch.cholesky_solve(rhs.unsqueeze(-1), chol).squeeze(-1), info == 0
    return thomas(diag, off, rhs)


def solve_tridiagonal(diag: Tensor, off: Tensor, rhs: Tensor) -> Tensor:
    """Solve a system known to be non-singular (used for the implicit gradient).

    Args:
        diag: (..., k) diagonal.
        off: (..., k-1) off-diagonal (symmetric).
        rhs: (..., k) right-hand side.

    Returns:
        (..., k) the solution.
    """
    if diag.shape[-1] <= DENSE_MAX and not torch.compiler.is_compiling():
        return torch.linalg.solve(to_dense(diag, off), rhs.unsqueeze(-1)).squeeze(-1)
    return thomas(diag, off, rhs)[0]
