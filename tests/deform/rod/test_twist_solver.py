import functools

import pytest
import torch

from deform.rod.energy import bending_energy, curvature_projections, rod_geometry, twisting_energy
from deform.rod.twist_solver import gradient_and_hessian, solve_theta
from deform.rod.twist_theseus import theseus_theta
from tests.deform.rod.helpers import random_params, random_rod, twisted_frame


def _problem(seed, batch=4, n=11, wbar=0.15):
    x, gen = random_rod(batch, n, bend=0.4, seed=seed)
    d1, t = twisted_frame(x, gen, twist=0.5)
    geo = rod_geometry(x, d1, t)
    a, b = curvature_projections(geo)
    p = random_params(batch, n, gen, wbar_scale=wbar)
    ends = torch.randn(2, batch, generator=gen, dtype=torch.float64)
    return a, b, geo.m_ref, ends, p


def test_analytic_theta_gradient_and_hessian_match_autograd():
    a, b, m_ref, _ends, p = _problem(0, batch=2)
    theta = torch.randn(a.shape[0] + 1, 2, dtype=torch.float64, requires_grad=True)
    energy = bending_energy(a, b, theta, p.beta, p.rest_vor, p.wbar) + twisting_energy(
        theta, m_ref, p.gamma, p.rest_vor
    )
    (g_auto,) = torch.autograd.grad(energy.sum(), theta, create_graph=True)
    g, diag, off = gradient_and_hessian(theta, a, b, m_ref, p.beta, p.gamma, p.rest_vor, p.wbar)
    assert torch.allclose(g, g_auto[1:-1], atol=1e-12)
    hess_row = torch.autograd.grad(g_auto[3].sum(), theta)[0]
    assert torch.allclose(hess_row[3], diag[2], atol=1e-12)
    assert torch.allclose(hess_row[4], off[2], atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_newton_and_theseus_agree(seed):
    a, b, m_ref, ends, p = _problem(seed)
    fast = solve_theta(a, b, m_ref, ends, p.beta, p.gamma, p.rest_vor, p.wbar, tol=1e-12)
    ref = theseus_theta(a, b, m_ref, ends, p.beta, p.gamma, p.rest_vor, p.wbar)
    assert (fast - ref).abs().max() < 1e-6
    g, _, _ = gradient_and_hessian(fast, a, b, m_ref, p.beta, p.gamma, p.rest_vor, p.wbar)
    assert g.abs().max() < 1e-9
    assert torch.equal(fast[[0, -1]], ends)


def test_implicit_gradients_match_finite_differences_and_theseus():
    """Theseus differentiated through its converged Gauss-Newton iterations ('unroll') gives the exact
    implicit gradient; its 'implicit' mode linearises with the Gauss-Newton Hessian and is only
    approximate for this energy (non-zero residuals at the minimum), so it is not the reference."""
    a, b, m_ref, ends, p = _problem(4, batch=2, n=8)
    theseus_unrolled = functools.partial(theseus_theta, backward_mode="unroll", max_iterations=80)
    w = torch.randn(a.shape[0] + 1, 2, dtype=torch.float64)

    def objective(beta, m, solver):
        th = solver(a, b, m, ends, beta, p.gamma, p.rest_vor, p.wbar)
        return (th * w).sum()

    beta = p.beta.clone().requires_grad_(True)
    m = m_ref.clone().requires_grad_(True)
    gb_fast, gm_fast = torch.autograd.grad(objective(beta, m, solve_theta), (beta, m))
    gb_th, gm_th = torch.autograd.grad(objective(beta, m, theseus_unrolled), (beta, m))
    assert torch.allclose(gb_fast, gb_th, rtol=1e-4, atol=1e-6 * gb_fast.abs().max())
    assert torch.allclose(gm_fast, gm_th, rtol=1e-4, atol=1e-6)
    h = 1e-6
    with torch.no_grad():
        for i in range(3):
            dm = torch.zeros_like(m_ref)
            dm[i, 1] = h
            fd = (objective(p.beta, m_ref + dm, solve_theta) - objective(p.beta, m_ref - dm, solve_theta)) / (
                2 * h
            )
            assert abs(float(fd) - float(gm_fast[i, 1])) < 1e-5 * max(1.0, abs(float(fd)))
            db = torch.zeros_like(p.beta)
            db[i + 2, 0] = h * 1e-3
            fd = (objective(p.beta + db, m_ref, solve_theta) - objective(p.beta - db, m_ref, solve_theta)) / (
                2 * h * 1e-3
            )
            assert abs(float(fd) - float(gb_fast[i + 2, 0])) < 1e-4 * max(1.0, abs(float(fd)))


def test_branch_free_iterations_stop_each_rod_by_the_checked_rule():
    """Sync-free iterations (for compiled code) stop each rod by the checked loop's rule. Warm-started
    as in a simulation step, every rod converges within them and ends exactly as when solved alone;
    with a single one, the checked loop that follows gives the plain batched result."""
    a, b, m_ref, ends, p = _problem(3)
    args = (m_ref, ends, p.beta, p.gamma, p.rest_vor, p.wbar)
    exact = solve_theta(a, b, *args, tol=1e-13, max_iter=200)
    noise = torch.randn(exact.shape, generator=torch.Generator().manual_seed(0), dtype=exact.dtype)
    noise[:, 0] *= 1e-3  # one rod much closer than the others: it stops earlier
    warm = exact + 1e-3 * noise
    batch = solve_theta(a, b, *args, theta_init=warm, branch_free=6)
    for r in range(a.shape[-1]):
        rod = slice(r, r + 1)
        one = (
            m_ref[:, rod],
            ends[:, rod],
            p.beta,
            p.gamma,
            p.rest_vor[:, rod],
            p.wbar,
        )  # beta, gamma, wbar shared
        alone = solve_theta(a[..., rod], b[..., rod], *one, theta_init=warm[:, rod])
        assert torch.equal(batch[:, rod], alone)
    plain = solve_theta(a, b, *args, theta_init=warm)
    assert torch.equal(solve_theta(a, b, *args, theta_init=warm, branch_free=1), plain)


def test_without_rest_curvature_the_closed_form_is_newtons_minimum_with_its_gradients(monkeypatch):
    """No rest curvature: the angles come from twist_minimiser, not Newton; the same angles (Newton
    forced by a rest curvature that requires grad, at zero) and the same implicit gradients."""
    a, b, m_ref, ends, p = _problem(5, wbar=0.0)
    gamma = (p.gamma * torch.linspace(0.5, 2.0, p.gamma.shape[0], dtype=torch.float64)[:, None]).detach()
    w = torch.randn(a.shape[0] + 1, a.shape[-1], dtype=torch.float64)

    def solved(wbar_requires_grad: bool):
        m = m_ref.clone().requires_grad_(True)
        g = gamma.clone().requires_grad_(True)
        wbar = p.wbar.clone().requires_grad_(wbar_requires_grad)
        theta = solve_theta(a, b, m, ends, p.beta, g, p.rest_vor, wbar, tol=1e-14)
        return theta, torch.autograd.grad((theta * w).sum(), (m, g))

    import deform.rod.twist_solver as ts

    calls = []
    newton_theta = ts.newton_theta
    monkeypatch.setattr(ts, "newton_theta", lambda *a, **k: calls.append(1) or newton_theta(*a, **k))
    assert not p.wbar.any()
    closed, closed_grads = solved(False)
    assert calls == []
    newton, newton_grads = solved(True)
    assert calls == [1]
    assert (closed - newton).abs().max() < 1e-12
    for c, n in zip(closed_grads, newton_grads, strict=True):
        assert (c - n).abs().max() < 1e-9 * n.abs().max()
    grad, _, _ = gradient_and_hessian(closed.detach(), a, b, m_ref, p.beta, gamma, p.rest_vor, p.wbar)
    assert grad.abs().max() < 1e-12
    assert torch.equal(closed[[0, -1]], ends)


def test_groups_of_rods_are_each_solved_as_alone():
    """``groups``: consecutive runs of rods iterate until their own rods converge (several models in
    one batch): each run ends as when solved alone, where the batch-wide loop goes on for all."""
    a, b, m_ref, ends, p = _problem(5, batch=4)
    args = (m_ref, ends, p.beta, p.gamma, p.rest_vor, p.wbar)
    exact = solve_theta(a, b, *args, tol=1e-13, max_iter=200)
    noise = torch.randn(exact.shape, generator=torch.Generator().manual_seed(1), dtype=exact.dtype)
    noise[:, :2] *= 1e-4  # the first run of two rods much closer: it stops earlier
    warm = exact + 1e-2 * noise
    grouped = solve_theta(a, b, *args, theta_init=warm, groups=2)
    for g in range(2):
        rods = slice(2 * g, 2 * g + 2)
        one = (m_ref[:, rods], ends[:, rods], p.beta, p.gamma, p.rest_vor[:, rods], p.wbar)
        alone = solve_theta(a[..., rods], b[..., rods], *one, theta_init=warm[:, rods])
        assert torch.allclose(grouped[:, rods], alone, rtol=0, atol=1e-15)
    assert not torch.equal(solve_theta(a, b, *args, theta_init=warm), grouped)  # the batch-wide loop


def test_closed_form_groups_solve_each_run_by_its_own_method():
    """``closed_form_groups``: the leading runs of rods (no rest curvature) take the closed form to
    the bit, the other runs the iterative solve as alone, with its implicit gradient (a stack of
    models of which some fit a rest curvature)."""
    a, b, m_ref, ends, p = _problem(6, batch=6)
    wbar = torch.cat(
        [torch.zeros(*p.wbar.shape[:-1], 2, dtype=p.wbar.dtype), p.wbar.expand(-1, -1, -1, 4)], -1
    )
    wbar = wbar.clone().requires_grad_(True)  # the last two runs of two rods fit a rest curvature
    args = (m_ref, ends, p.beta, p.gamma, p.rest_vor)
    split = solve_theta(a, b, *args, wbar, groups=3, closed_form_groups=1)
    head, tail = slice(0, 2), slice(2, 6)

    def on(rods, wbar_part, **kw):  # the solve of these rods alone
        return solve_theta(
            a[..., rods], b[..., rods], m_ref[:, rods], ends[:, rods], p.beta, p.gamma, p.rest_vor[:, rods],
            wbar_part, **kw,
        )  # fmt: skip

    closed = on(head, torch.zeros_like(p.wbar))
    assert torch.equal(split[:, head], closed)
    iterative = on(tail, wbar[..., tail], groups=2)
    assert torch.equal(split[:, tail], iterative)
    (g_split,) = torch.autograd.grad(split.sum(), wbar)
    (g_tail,) = torch.autograd.grad(iterative.sum(), wbar)
    assert torch.equal(g_split, g_tail) and g_tail[..., tail].abs().max() > 0
    # the whole batch through the iterative solve is not the closed form to the bit
    assert not torch.equal(solve_theta(a, b, *args, wbar, groups=3)[:, head], closed)
    with pytest.raises(ValueError, match="closed_form_groups"):
        solve_theta(a, b, *args, wbar, groups=3, closed_form_groups=4)
