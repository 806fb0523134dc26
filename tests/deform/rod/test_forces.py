import torch

from deform.rod.energy import curvature_projections, rod_geometry, total_energy
from deform.rod.forces import rod_forces
from deform.rod.twist_solver import solve_theta
from tests.deform.rod.helpers import random_params, random_rod, twisted_frame


def test_closed_form_forces_equal_minus_autograd_of_energy():
    x, gen = random_rod(4, 10, bend=0.5, seed=3)
    d1, t = twisted_frame(x, gen)
    p = random_params(4, 10, gen, wbar_scale=0.3)
    theta = torch.randn(9, 4, generator=gen, dtype=torch.float64)
    mass = torch.rand(10, 4, generator=gen, dtype=torch.float64)
    xa = x.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(total_energy(xa, theta, d1, t, p, mass).sum(), xa)
    geo = rod_geometry(x, d1, t)
    a, b = curvature_projections(geo)
    force = rod_forces(x, geo, a, b, theta, p, mass)
    assert torch.allclose(force, -grad, rtol=1e-9, atol=1e-9 * grad.abs().max())


def test_forces_at_minimising_angles_match_finite_differences_of_minimised_energy():
    """Envelope theorem: d/dx min_theta E(x, theta) equals the partial derivative at theta*."""
    x, gen = random_rod(1, 9, bend=0.4, seed=5)
    d1, t = twisted_frame(x, gen)
    p = random_params(1, 9, gen, wbar_scale=0.2)
    mass = torch.rand(9, 1, generator=gen, dtype=torch.float64)
    ends = torch.tensor([[0.2], [-0.4]], dtype=torch.float64)

    def min_energy(xx):
        geo = rod_geometry(xx, d1, t)  # frame carried along from t
        a, b = curvature_projections(geo)
        th = solve_theta(a, b, geo.m_ref, ends, p.beta, p.gamma, p.rest_vor, p.wbar, tol=1e-13)
        return total_energy(xx, th, d1, t, p, mass), (geo, a, b, th)

    _, (geo, a, b, th) = min_energy(x)
    force = rod_forces(x, geo, a, b, th, p, mass)
    h = 1e-6
    fd = torch.zeros_like(x)
    for i in range(9):
        for k in range(3):
            dx = torch.zeros_like(x)
            dx[i, k, 0] = h
            fd[i, k, 0] = -(min_energy(x + dx)[0] - min_energy(x - dx)[0]) / (2 * h)
    assert torch.allclose(force, fd, rtol=1e-5, atol=1e-6 * fd.abs().max())


def test_internal_forces_sum_to_zero_and_gravity_pulls_down():
    x, gen = random_rod(2, 8, seed=7)
    d1, t = twisted_frame(x, gen)
    p = random_params(2, 8, gen, wbar_scale=0.3)
    mass = torch.full((8, 2), 0.003, dtype=torch.float64)
    geo = rod_geometry(x, d1, t)
    a, b = curvature_projections(geo)
    theta = torch.randn(7, 2, generator=gen, dtype=torch.float64)
    force = rod_forces(x, geo, a, b, theta, p, mass)
    total = force.sum(0)  # (3, rods)
    expected = torch.zeros_like(total)
    expected[2] = -9.81 * mass.sum(0)
    assert torch.allclose(total, expected, atol=1e-10)
