"""Random bent and twisted rods for the physics tests, vertex-major (``deform.rod.layout``)."""

import torch

from deform.rod import geometry as G
from deform.rod.energy import ElasticParams


def random_rod(batch: int = 4, n: int = 11, bend: float = 0.4, seed: int = 0, dtype=torch.float64):
    """(n, 3, batch) vertices of rods 0.1 m per edge, bent at random, and the generator."""
    gen = torch.Generator().manual_seed(seed)
    steps = torch.tensor([1.0, 0, 0], dtype=dtype)[:, None] + bend * torch.randn(
        n, 3, batch, generator=gen, dtype=dtype
    )
    x = torch.cumsum(G.normalize(steps) * 0.1, dim=0)
    return x, gen


def random_params(batch: int, n: int, gen, dtype=torch.float64, wbar_scale: float = 0.1) -> ElasticParams:
    return ElasticParams(
        beta=torch.rand(n - 2, 1, generator=gen, dtype=dtype) * 1e-3 + 5e-4,
        gamma=torch.rand(n - 2, 1, generator=gen, dtype=dtype) * 1e-3 + 5e-4,
        wbar=wbar_scale * torch.randn(n - 2, 2, 2, 1, generator=gen, dtype=dtype),
        rest_vor=torch.rand(n - 2, batch, generator=gen, dtype=dtype) * 0.05 + 0.18,
    )


def twisted_frame(x: torch.Tensor, gen, twist: float = 0.3):
    """Reference frame of ``x`` carried in time from a perturbed configuration: nonzero reference twist."""
    x_prev = x + 0.02 * torch.randn(x.shape, generator=gen, dtype=x.dtype)
    t_prev = G.normalize(G.edges(x_prev))
    d1_prev = G.space_parallel_frame(t_prev)
    angle = twist * torch.randn(t_prev.shape[0], t_prev.shape[-1], generator=gen, dtype=x.dtype).unsqueeze(-2)
    d2_prev = G.cross(t_prev, d1_prev)
    d1_prev = torch.cos(angle) * d1_prev + torch.sin(angle) * d2_prev
    t = G.normalize(G.edges(x))
    return G.time_transport(d1_prev, t_prev, t), t
