r"""Residual graph network on the rod's vertices (the paper's learned correction of the integration).

Two ``GCNConv`` layers (sum aggregation, symmetric normalisation ``D^-1/2 (A + I) D^-1/2``) over the
chain graph of the vertices, then a two-layer MLP head with ReLU, returning a velocity correction per
vertex. Inputs are positions relative to the rod's centroid (so that the network does not learn the
workspace) and velocities, both scaled to O(1).

``forward`` uses the layers' own weights with the normalised adjacency of the chain applied as its
three diagonals (each vertex, the one before, the one after): the same arithmetic as
``GCNConv.forward`` (a test checks) without the scatter overhead, which matters at a 1 ms step
budget. Why not the dense (n, n) product: compiled, the diagonals fuse into the neighbouring
element-wise kernels, while a batched matrix product stays a library call per layer (0.93-0.96x
per predict step at 64 rods, scratch A/B of 2026-11-23; values equal to float32 rounding).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch_geometric.nn import GCNConv

POS_SCALE = 0.5  # metres
VEL_SCALE = 1.0  # metres per second
OUT_SCALE = 0.01  # metres per second per step


def chain_edge_index(n: int) -> Tensor:
    """The rod's graph for torch-geometric: each vertex joined to its neighbours, both directions.

    Args:
        n: vertices.

    Returns:
        (2, 2 (n-1)) edge index.
    """
    src = torch.arange(n - 1)
    return torch.stack([torch.cat([src, src + 1]), torch.cat([src + 1, src])])


def gcn_dense_adjacency(n: int, dtype=torch.float32) -> Tensor:
    """The GCN propagation matrix ``D^-1/2 (A + I) D^-1/2`` of the chain as a dense matrix (a
    compiled step multiplies by it instead of scattering over the edge index).

    Args:
        n: vertices.
        dtype: of the matrix.

    Returns:
        (n, n).
    """
    a = torch.eye(n, dtype=dtype)
    idx = torch.arange(n - 1)
    a[idx, idx + 1] = 1.0
    a[idx + 1, idx] = 1.0
    d = a.sum(-1).rsqrt()
    return d[:, None] * a * d[None, :]


class ResidualGNN(nn.Module):
    def __init__(self, n_vertices: int, hidden: int = 32):
        super().__init__()
        self.n_vertices = n_vertices
        self.conv1 = GCNConv(6, hidden, aggr="add")
        self.conv2 = GCNConv(hidden, hidden, aggr="add")
        self.head = nn.Sequential(nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 3))
        nn.init.zeros_(self.head[2].weight)  # starts as pure physics
        nn.init.zeros_(self.head[2].bias)
        adjacency = gcn_dense_adjacency(n_vertices)
        # A_hat[i, i], A_hat[i, i-1] (0 for the first vertex), A_hat[i, i+1] (0 for the last), as (n, 1)
        self.register_buffer("adj_self", torch.diagonal(adjacency)[:, None].clone(), persistent=False)
        self.register_buffer(
            "adj_prev", F.pad(torch.diagonal(adjacency, -1), (1, 0))[:, None], persistent=False
        )
        self.register_buffer(
            "adj_next", F.pad(torch.diagonal(adjacency, 1), (0, 1))[:, None], persistent=False
        )
        self.register_buffer("edge_index", chain_edge_index(n_vertices), persistent=False)

    @staticmethod
    def features(x: Tensor, v: Tensor) -> Tensor:
        """(..., n, 3) positions and velocities -> (..., n, 6): positions about the centroid, both scaled.

        Compiled, the centroid is a sum of the n vertex rows, not ``x.mean(-2)``: inductor's CPU
        code for that reduction (13 rows of 3) opens a parallel region per rod, which made it 30 %
        of a compiled step at 1024 rods (1.3 ms of 4.3; as a sum of rows, 0.08 ms). Eager, the mean
        is one call instead of 2n (25 us less per step)."""
        if torch.compiler.is_compiling():
            centroid = (sum(x.unbind(-2)) / x.shape[-2]).unsqueeze(-2)
        else:
            centroid = x.mean(dim=-2, keepdim=True)
        rel = (x - centroid) / POS_SCALE
        return torch.cat([rel, v / VEL_SCALE], dim=-1)

    def _propagate(self, conv: GCNConv, h: Tensor) -> Tensor:
        r"""GCN layer on the chain: :math:`\hat A (h W^T) + b`, :math:`\hat A` tridiagonal, in ``h``'s dtype."""
        dtype = h.dtype
        y = F.linear(h, conv.lin.weight.to(dtype))
        prev = F.pad(y[..., :-1, :], (0, 0, 1, 0))  # row i holds y[i-1] (zeros for i = 0)
        nxt = F.pad(y[..., 1:, :], (0, 0, 0, 1))  # row i holds y[i+1] (zeros for i = n-1)
        return (
            self.adj_self.to(dtype) * y
            + self.adj_prev.to(dtype) * prev
            + self.adj_next.to(dtype) * nxt
            + conv.bias.to(dtype)
        )

    def forward(self, x: Tensor, v: Tensor, dtype: torch.dtype | None = None) -> Tensor:
        """(..., n, 3) positions and velocities -> (..., n, 3) velocity correction in ``x``'s dtype.
        ``dtype``: the layers' arithmetic (None: ``x``'s; bfloat16 for batched rollouts, see
        :mod:`deform.nn.precision`)."""
        h = self.features(x, v)
        h = h if dtype is None else h.to(dtype)
        h = torch.relu(self._propagate(self.conv1, h))
        h = torch.relu(self._propagate(self.conv2, h))
        hidden, out = self.head[0], self.head[2]
        h = torch.relu(F.linear(h, hidden.weight.to(h.dtype), hidden.bias.to(h.dtype)))
        h = F.linear(h, out.weight.to(h.dtype), out.bias.to(h.dtype))
        return h.to(x.dtype) * OUT_SCALE

    def forward_pyg(self, x: Tensor, v: Tensor) -> Tensor:
        """Reference path through ``GCNConv.forward`` on a single (n, 3) rod (used by tests)."""
        h = self.features(x, v)
        h = torch.relu(self.conv1(h, self.edge_index))
        h = torch.relu(self.conv2(h, self.edge_index))
        return self.head(h) * OUT_SCALE
