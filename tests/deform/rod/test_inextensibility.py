import pytest
import torch

from deform.rod.inextensibility import enforce_inextensibility, max_relative_error, unweighted_inv_mass
from tests.deform.rod.helpers import random_rod


def _perturbed(seed=0, batch=3, n=13):
    x, gen = random_rod(batch, n, seed=seed)
    rest = (x[:, 1:] - x[:, :-1]).norm(dim=-1)
    mass = torch.rand(batch, n, generator=gen, dtype=torch.float64) + 0.5
    xp = x + 0.01 * torch.randn(x.shape, generator=gen, dtype=torch.float64)
    return x, xp, rest, mass


@pytest.mark.parametrize("method", ["projection", "gauss_seidel"])
def test_projection_preserves_linear_momentum_and_restores_lengths(method):
    _, xp, rest, mass = _perturbed()
    assert max_relative_error(xp, rest) > 0.05
    y = enforce_inextensibility(xp, 1.0 / mass, rest, tol=1e-9, max_sweeps=2000, method=method)
    assert max_relative_error(y, rest) < 1e-9
    momentum_change = (mass.unsqueeze(-1) * (y - xp)).sum(1)
    assert momentum_change.abs().max() < 1e-12


def test_gripped_vertices_do_not_move_and_free_ones_are_restored():
    x, xp, rest, mass = _perturbed(1)
    grip = [0, 1, 11, 12]
    xp[:, grip] = x[:, grip]
    inv = 1.0 / mass
    inv[:, grip] = 0.0
    y = enforce_inextensibility(xp, inv, rest, tol=1e-8)
    assert torch.equal(y[:, grip], xp[:, grip])
    assert max_relative_error(y, rest, inv) < 1e-8


def test_heavier_vertex_moves_less():
    x = torch.tensor([[[0.0, 0, 0], [0.12, 0, 0]]], dtype=torch.float64)
    rest = torch.tensor([[0.1]], dtype=torch.float64)
    mass = torch.tensor([[1.0, 3.0]], dtype=torch.float64)
    y = enforce_inextensibility(x, 1.0 / mass, rest, tol=1e-12)
    moved = (y - x).norm(dim=-1)[0]
    assert torch.allclose(moved, torch.tensor([0.015, 0.005], dtype=torch.float64))
    y_unweighted = enforce_inextensibility(x, unweighted_inv_mass(1.0 / mass), rest, tol=1e-12)
    assert torch.allclose((y_unweighted - x).norm(dim=-1)[0], torch.tensor([0.01, 0.01], dtype=torch.float64))


def test_projection_is_differentiable():
    _, xp, rest, mass = _perturbed(2, batch=1, n=6)
    xp.requires_grad_(True)
    y = enforce_inextensibility(xp, 1.0 / mass, rest, tol=1e-10)
    (g,) = torch.autograd.grad(y[0, 3, 0], xp)
    assert torch.isfinite(g).all() and g.abs().sum() > 0
