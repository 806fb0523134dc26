import pytest
import torch

from deform.rod import geometry as G
from deform.rod.inextensibility import enforce_inextensibility, max_relative_error, unweighted_inv_mass
from tests.deform.rod.helpers import random_rod


def _perturbed(seed=0, batch=3, n=13):
    x, gen = random_rod(batch, n, seed=seed)
    rest = G.norm(G.edges(x))
    mass = torch.rand(n, batch, generator=gen, dtype=torch.float64) + 0.5
    xp = x + 0.01 * torch.randn(x.shape, generator=gen, dtype=torch.float64)
    return x, xp, rest, mass


@pytest.mark.parametrize("method", ["projection", "gauss_seidel"])
def test_projection_preserves_linear_momentum_and_restores_lengths(method):
    _, xp, rest, mass = _perturbed()
    assert max_relative_error(xp, rest) > 0.05
    y = enforce_inextensibility(xp, 1.0 / mass, rest, tol=1e-9, max_sweeps=2000, method=method)
    assert max_relative_error(y, rest) < 1e-9
    momentum_change = (mass.unsqueeze(-2) * (y - xp)).sum(0)
    assert momentum_change.abs().max() < 1e-12


def test_gripped_vertices_do_not_move_and_free_ones_are_restored():
    x, xp, rest, mass = _perturbed(1)
    grip = [0, 1, 11, 12]
    xp[grip] = x[grip]
    inv = 1.0 / mass
    inv[grip] = 0.0
    y = enforce_inextensibility(xp, inv, rest, tol=1e-8)
    assert torch.equal(y[grip], xp[grip])
    assert max_relative_error(y, rest, inv) < 1e-8


def test_heavier_vertex_moves_less():
    x = torch.tensor([[0.0, 0, 0], [0.12, 0, 0]], dtype=torch.float64)[..., None]  # (2, 3, 1 rod)
    rest = torch.tensor([[0.1]], dtype=torch.float64)
    mass = torch.tensor([[1.0], [3.0]], dtype=torch.float64)
    y = enforce_inextensibility(x, 1.0 / mass, rest, tol=1e-12)
    moved = G.norm(y - x)[:, 0]
    assert torch.allclose(moved, torch.tensor([0.015, 0.005], dtype=torch.float64))
    y_unweighted = enforce_inextensibility(x, unweighted_inv_mass(1.0 / mass), rest, tol=1e-12)
    assert torch.allclose(G.norm(y_unweighted - x)[:, 0], torch.tensor([0.01, 0.01], dtype=torch.float64))


def test_projection_is_differentiable():
    _, xp, rest, mass = _perturbed(2, batch=1, n=6)
    xp.requires_grad_(True)
    y = enforce_inextensibility(xp, 1.0 / mass, rest, tol=1e-10)
    (g,) = torch.autograd.grad(y[3, 0, 0], xp)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


@pytest.mark.parametrize("method", ["projection", "gauss_seidel"])
def test_projection_gradient_matches_finite_differences(method):
    """Training backpropagates through the projection: its autograd gradient with respect to the
    predicted positions, the rest lengths and the inverse masses equals central finite differences
    (float64, small rod, a gripped vertex). ``tol=0`` makes the sweep count fixed, so the function is
    smooth; with a tolerance a perturbation could change the number of sweeps (a jump of order tol)."""
    _, xp, rest, mass = _perturbed(4, batch=2, n=5)
    inv = 1.0 / mass
    inv[0] = 0.0  # held: must not move, and gets no gradient through its (zero) weight
    xp, rest, inv = (t.clone().requires_grad_(True) for t in (xp, rest, inv))

    def project(xp, rest, inv):
        return enforce_inextensibility(xp, inv, rest, tol=0.0, max_sweeps=3, method=method)

    assert torch.autograd.gradcheck(project, (xp, rest, inv), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_branch_free_sweeps_stop_each_rod_by_the_checked_rule():
    """Sync-free sweeps (for compiled code) stop each rod once its own error is below tol: with
    enough of them each rod ends exactly as when projected alone; with a single one, the checked
    loop that follows gives the plain batched result."""
    _, xp, rest, mass = _perturbed(2, batch=4)
    xp[..., 0] = (xp[..., 0] - xp[:1, :, 0]) * 1.0002 + xp[:1, :, 0]  # one rod nearly right: fewer sweeps
    y = enforce_inextensibility(xp, 1.0 / mass, rest, tol=1e-4, branch_free=20)
    for r in range(4):
        rod = slice(r, r + 1)
        alone = enforce_inextensibility(xp[..., rod], 1.0 / mass[:, rod], rest[:, rod], tol=1e-4)
        # equal to rounding: the batch's reductions over x, y, z may add in another order (one
        # more or fewer sweep would differ by about tol)
        assert torch.allclose(y[..., rod], alone, rtol=0, atol=1e-14)
    assert max_relative_error(y, rest) < 1e-4
    plain = enforce_inextensibility(xp, 1.0 / mass, rest, tol=1e-4)
    assert torch.equal(enforce_inextensibility(xp, 1.0 / mass, rest, tol=1e-4, branch_free=1), plain)
    assert not torch.equal(y, plain)  # the nearly-right rod was swept less in the first


def test_groups_of_rods_are_each_projected_as_alone():
    """``groups``: consecutive runs of rods sweep until their own rods are within tol (several
    models in one batch): each run ends as when projected alone."""
    x, xp, rest, mass = _perturbed(2, batch=4)
    xp[..., :2] = x[..., :2] + 1e-5 * (xp[..., :2] - x[..., :2])  # the first run nearly right: fewer sweeps
    y = enforce_inextensibility(xp, 1.0 / mass, rest, tol=1e-4, groups=2)
    for g in range(2):
        rods = slice(2 * g, 2 * g + 2)
        alone = enforce_inextensibility(xp[..., rods], 1.0 / mass[:, rods], rest[:, rods], tol=1e-4)
        assert torch.allclose(y[..., rods], alone, rtol=0, atol=1e-14)
    assert not torch.equal(enforce_inextensibility(xp, 1.0 / mass, rest, tol=1e-4), y)  # batch-wide
