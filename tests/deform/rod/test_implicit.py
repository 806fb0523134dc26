import math

import pytest
import torch

from deform import DeformModel, ModelOptions
from deform.config import generic_rod
from deform.model import generic_model, gripped_indices
from deform.rod.implicit import (
    apply_implicit_filter,
    bending_operator,
    implicit_bending_velocity,
    implicit_filter,
    solve_band2_pd,
    step_ratio,
)
from deform.step_graph import rod_at_rest

N = 12
HELD = gripped_indices(N)


def _random_rods(batch: int = 3, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    rest = torch.rand(N - 1, batch, generator=gen, dtype=torch.float64) * 0.05 + 0.07
    beta = torch.rand(N - 2, batch, generator=gen, dtype=torch.float64) * 0.03 + 1e-3
    mass = torch.rand(N, batch, generator=gen, dtype=torch.float64) * 5e-3 + 1e-3
    v = torch.randn(N, 3, batch, generator=gen, dtype=torch.float64)
    v_held = torch.randn(len(HELD), 3, batch, generator=gen, dtype=torch.float64)
    return rest, beta, mass, v, v_held


def test_the_operator_is_the_models_bending_hessian_at_a_straight_rod():
    """K against central differences of the model's own forces (transverse y, uneven stiffness)."""
    cfg = generic_rod(1.0, 0.05, N).model_copy(update=dict(bend_stiffness=0.01, twist_stiffness=0.007))
    model = DeformModel(cfg, ModelOptions(residual=False)).eval()
    with torch.no_grad():
        model.log_beta.add_(torch.linspace(-0.5, 0.5, N - 2))
    state, _ = rod_at_rest(model, 1, torch.float64)
    x0, h = state.x.clone(), 1e-5

    def force_y(dy):
        x = x0.clone()
        x[0, :, 1] += dy
        with torch.no_grad():
            return model.forces(model.reposition(state, x, torch.zeros_like(x)))[0][0, :, 1]

    hessian = torch.stack(
        [(force_y(h * e) - force_y(-h * e)) / (2 * h) for e in torch.eye(N, dtype=torch.float64)], 1
    )
    beta = model.log_beta.detach().exp().to(torch.float64)[:, None]
    K = bending_operator(beta, state.rest.T)[0]
    assert torch.allclose(-hessian, K, rtol=1e-5, atol=1e-6 * float(K.abs().max()))


def test_the_operator_leaves_rigid_motion_alone():
    """A translation and (uneven spacing) a displacement linear in arc length bend nothing."""
    rest, beta, *_ = _random_rods()
    K = bending_operator(beta, rest)
    s = torch.cat([torch.zeros(1, rest.shape[1], dtype=rest.dtype), rest.cumsum(0)]).T  # (B, n)
    for u in (torch.ones_like(s), s):
        assert (K @ u.unsqueeze(-1)).abs().max() < 1e-9 * K.abs().max()


def test_the_filter_is_the_backward_euler_step_of_the_linear_bending():
    """(M_f + dt^2 K_ff) v_f = M_f v_hat_f - dt^2 K_fg v_g, the held rows untouched; the band solve
    (compiled code's) gives the same values."""
    rest, beta, mass, v, v_held = _random_rods()
    dt = 0.01
    out = apply_implicit_filter(v, v_held, implicit_filter(beta, rest, mass, dt, HELD), HELD)
    free = [i for i in range(N) if i not in HELD]
    K = bending_operator(beta, rest)
    K_ff, K_fg, m_f = K[:, free][:, :, free], K[:, free][:, :, HELD], mass[free].T.unsqueeze(-1)
    v_f, out_f, v_g = (t.permute(2, 0, 1) for t in (v[free], out[free], v_held))
    lhs = m_f * out_f + dt**2 * K_ff @ out_f
    rhs = m_f * v_f - dt**2 * K_fg @ v_g
    assert torch.allclose(lhs, rhs, atol=1e-12)
    assert torch.equal(out[HELD], v[HELD])
    band = implicit_bending_velocity(v, v_held, beta, rest, mass, dt, HELD)
    assert torch.allclose(band, out, atol=1e-12)


def test_band_solve_matches_a_dense_solve_and_rejects_nothing_it_should_not():
    gen = torch.Generator().manual_seed(3)
    G = torch.randn(4, 7, 9, generator=gen, dtype=torch.float64)
    A = G.transpose(-1, -2) @ G + torch.eye(9, dtype=torch.float64)
    band = torch.ones(9, 9).triu(-2).tril(2).bool()
    A = torch.where(band, A, torch.zeros_like(A)) + 10 * torch.eye(9, dtype=torch.float64)  # banded, PD
    rhs = torch.randn(4, 9, 3, generator=gen, dtype=torch.float64)
    assert torch.allclose(solve_band2_pd(A, rhs), torch.linalg.solve(A, rhs), atol=1e-12)


def test_the_step_ratio_is_the_stiffest_modes_turn_per_step():
    """One free vertex between held ones: omega^2 = K_ii / m_i exactly."""
    rest = torch.full((4, 1), 0.1, dtype=torch.float64)
    beta = torch.full((3, 1), 2e-3, dtype=torch.float64)
    mass = torch.full((5, 1), 4e-3, dtype=torch.float64)
    K = bending_operator(beta, rest)[0]
    ratio = step_ratio(beta, rest, mass, 0.01, [0, 1, 3, 4])
    assert float(ratio) == pytest.approx(math.sqrt(float(K[2, 2]) / 4e-3) * 0.01, rel=1e-12)


def _top_speed_after_bend_and_hold(model: DeformModel) -> float:
    """Grippers 30 % of the length closer over 0.5 s, then held 2 s: the top speed in the last 0.5 s."""
    state, grip = rod_at_rest(model, 1, torch.float64)
    far = torch.zeros_like(grip)
    far[:, 2:, 0] = -0.3 * float(state.rest.sum())
    far[:, 2:, 1] = 0.02
    top = 0.0
    with torch.no_grad():
        for k in range(1, 251):
            state = model.step(state, grip + min(k / 50, 1.0) * far)
            if k > 200:
                top = max(top, float(state.v.norm(dim=-1).amax()))
    return top


def test_a_stiff_short_rope_comes_to_rest_implicitly_and_rings_explicitly():
    """A 50 cm rope at the generic stiffness (step ratio 2.1): explicit, it rings at metres a second
    after it is bent and held; with the implicit bending it comes to rest."""
    model = generic_model(0.5, 0.05)
    assert model.cfg.implicit_bending and model.bending_step_ratio() > 1.5
    assert _top_speed_after_bend_and_hold(model) < 0.05
    model.cfg.implicit_bending = False
    assert _top_speed_after_bend_and_hold(model) > 1.0


def test_the_scheme_is_chosen_by_the_step_ratio_and_kept_in_the_model_file(tmp_path):
    assert not generic_model(1.0, 0.05).cfg.implicit_bending  # ratio about 0.5
    model = generic_model(0.5, 0.05)
    path = tmp_path / "short.pt"
    model.save(path)
    assert DeformModel.load(path).cfg.implicit_bending


def test_the_implicit_step_is_differentiable_in_the_stiffness():
    """Training descends through the filter: a finite-difference check of d(x after 5 steps)/d log_beta."""
    model = generic_model(0.5, 0.05)
    state, grip = rod_at_rest(model, 1, torch.float64)
    move = torch.zeros_like(grip)
    move[:, 2:, 2] = 0.01

    def end_height(shift: float, create_graph: bool):
        with torch.no_grad():
            model.log_beta.fill_(math.log(model.cfg.bend_stiffness) + shift)
        s = state
        for k in range(1, 6):
            s = model.step(s, grip + k * move, create_graph=create_graph)
        return s.x[0, 5, 2]

    model.log_beta.grad = None
    end_height(0.0, True).backward()
    analytic = float(model.log_beta.grad.sum())
    h = 1e-4
    numeric = (float(end_height(h, False)) - float(end_height(-h, False))) / (2 * h)
    assert analytic == pytest.approx(numeric, rel=1e-2)  # the solvers stop at their tolerances
    assert abs(numeric) > 1e-7  # the check sees the stiffness at all


def test_substeps_are_steps_of_a_fraction_of_the_frame_with_the_grippers_in_between():
    """A frame in 3 substeps equals 3 steps of a model whose frame is a third as long, the grippers
    moved a third of the way each time (no residual: it is added once a frame)."""
    cfg = generic_rod(0.5, 0.05, N).model_copy(update=dict(implicit_bending=True))
    whole = DeformModel(cfg.model_copy(update=dict(substeps=3)), ModelOptions(residual=False)).eval()
    third = DeformModel(cfg.model_copy(update=dict(dt=cfg.dt / 3)), ModelOptions(residual=False)).eval()
    third.load_state_dict(whole.state_dict())
    state, grip = rod_at_rest(whole, 2, torch.float64)
    move = torch.zeros_like(grip)
    move[:, 2:, 0] = -0.02
    move[1, :, 2] = 0.01
    with torch.no_grad():
        a = whole.step(state, grip + move)
        b = state
        for k in (1, 2, 3):
            b = third.step(b, grip + move * (k / 3))
    assert torch.allclose(a.x, b.x, atol=1e-12) and torch.allclose(a.v, b.v, atol=1e-10)
    one = DeformModel(cfg, ModelOptions(residual=False)).eval()  # the frame in one step: not the same
    one.load_state_dict(whole.state_dict())
    with torch.no_grad():
        assert (one.step(state, grip + move).x - a.x).abs().max() > 1e-6


def test_the_stiffest_light_cable_takes_substeps_and_comes_to_rest():
    """1 m, 20 g at EI 0.1 N m^2 (step ratio about 10): one implicit step a frame still rings after a
    bend; the substeps chosen keep each under IMPLICIT_RATIO_MAX and bring it to rest."""
    from deform.model import IMPLICIT_RATIO_MAX

    cfg = generic_rod(1.0, 0.02, N).model_copy(update=dict(bend_stiffness=0.1, twist_stiffness=0.07))
    model = DeformModel(cfg, ModelOptions(residual=False)).eval()
    assert model.choose_bending_scheme()
    ratio = model.bending_step_ratio()
    assert model.cfg.substeps == math.ceil(ratio / IMPLICIT_RATIO_MAX) > 1
    assert _top_speed_after_bend_and_hold(model) < 0.1
    model.cfg.substeps = 1
    assert _top_speed_after_bend_and_hold(model) > 1.0
