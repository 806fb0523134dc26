r"""Batched solve of symmetric tridiagonal systems ``H x = r``.

``diag`` is (..., k), ``off`` is (..., k-1) (the super- and sub-diagonal). Small systems go through a
dense batched LU (one kernel call beats k Python-level Thomas sweeps); large ones use the O(k)
Thomas algorithm, vectorised over the batch.
"""
from __future__ import annotations

import torch
from torch import Tensor

DENSE_MAX = 24


def to_dense(diag: Tensor, off: Tensor) -> Tensor:
    return torch.diag_embed(diag) + torch.diag_embed(off, offset=1) + torch.diag_embed(off, offset=-1)


def thomas(diag: Tensor, off: Tensor, rhs: Tensor) -> Tensor:
    k = diag.shape[-1]
    c = []  # modified super-diagonal
    d = []  # modified right-hand side
    denom = diag[..., 0]
    c.append(off[..., 0] / denom if k > 1 else None)
    d.append(rhs[..., 0] / denom)
    for i in range(1, k):
        denom = diag[..., i] - off[..., i - 1] * c[i - 1]
        c.append(off[..., i] / denom if i < k - 1 else None)
        d.append((rhs[..., i] - off[..., i - 1] * d[i - 1]) / denom)
    x = [None] * k
    x[-1] = d[-1]
    for i in range(k - 2, -1, -1):
        x[i] = d[i] - c[i] * x[i + 1]
    return torch.stack(x, dim=-1)


def solve_tridiagonal(diag: Tensor, off: Tensor, rhs: Tensor) -> Tensor:
    if diag.shape[-1] <= DENSE_MAX:
        return torch.linalg.solve(to_dense(diag, off), rhs.unsqueeze(-1)).squeeze(-1)
    return thomas(diag, off, rhs)
