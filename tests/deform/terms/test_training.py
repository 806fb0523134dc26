"""Physics terms trained into DEFORM (deform.terms): attach, save and load, ablations, bad names."""

import math
import subprocess
import sys

import pytest
import torch

from deform import DeformModel, generate_recording, load_rod_config
from deform.errors import UsageError
from deform.terms import attach, attached_names, check_names, without
from deform.train import TrainConfig, train


def _wind(model: DeformModel, ax: float) -> DeformModel:
    attach(model, ["external_force"])
    with torch.no_grad():
        model.extensions[0].set_field(ax, 0.0)
    return model


def test_a_wind_saved_by_an_older_version_loads_with_the_same_field():
    # before tool v10 the wind was stored as its components (a = raw / 2); such checkpoints still load
    model = _wind(DeformModel(load_rod_config("DLO2")), 0.0)
    state = {k: v for k, v in model.state_dict().items() if "extensions.0." not in k or k.endswith(".s")}
    state["extensions.0.raw"] = torch.tensor([-1.2, 0.8], dtype=torch.float64)
    model.load_state_dict(state)
    assert model.extensions[0].params() == pytest.approx({"ax_m_per_s2": -0.6, "ay_m_per_s2": 0.4})


def test_unknown_and_untrainable_terms_are_refused_with_the_reason():
    with pytest.raises(UsageError, match="unknown term 'wind'"):
        check_names(["wind"])
    with pytest.raises(UsageError, match="gripper poses"):
        check_names(["actuation_delay"])
    check_names(["internal_damping", "stiffness_variation"])


def test_a_model_with_a_term_saves_and_loads_the_term(tmp_path):
    cfg = load_rod_config("DLO2")
    model = _wind(DeformModel(cfg), 0.7)
    attach(model, ["internal_damping", "external_force"])  # external_force only once
    assert attached_names(model) == ["external_force", "internal_damping"]
    rec = generate_recording(DeformModel(cfg), n_frames=30, seed=0)
    x = torch.tensor(rec.positions, dtype=torch.float64)
    grips = x[None, 2:, [0, 1, -2, -1]]
    model.options.residual = False
    pred, _ = model.rollout(model.initial_state(x[None, 0], x[None, 1]), grips)
    model.save(tmp_path / "m.pt")
    back = DeformModel.load(tmp_path / "m.pt")
    assert attached_names(back) == ["external_force", "internal_damping"]
    pred_back, _ = back.rollout(back.initial_state(x[None, 0], x[None, 1]), grips)
    assert torch.equal(pred, pred_back)
    plain = DeformModel(cfg)
    plain.options.residual = False
    pred_plain, _ = plain.rollout(plain.initial_state(x[None, 0], x[None, 1]), grips)
    assert (pred - pred_plain).abs().max() > 1e-3  # the term acts (a 0.7 m/s^2 wind over 28 steps)


def test_ablation_keeps_stiffness_uniform_and_drag_at_its_floor(tmp_path):
    cfg = load_rod_config("DLO2")
    model = DeformModel(cfg)
    with torch.no_grad():
        model.log_beta.add_(torch.linspace(-0.5, 0.5, model.n - 2))
    recs = [generate_recording(DeformModel(cfg), n_frames=30, seed=s) for s in range(2)]
    tcfg = TrainConfig(
        iterations=3,
        batch=2,
        horizon=10,
        curriculum=(),
        coarse_sysid=False,
        residual=False,
        log_every=3,
        without=("stiffness_variation", "aerodynamic_drag"),
    )
    result = train(model, recs[:1], recs[1:], tcfg, tmp_path, progress=False)
    assert result["without"] == ["stiffness_variation", "aerodynamic_drag"]
    assert (model.log_beta.max() - model.log_beta.min()).item() == 0.0
    assert (model.log_gamma.max() - model.log_gamma.min()).item() == 0.0
    assert math.isclose(model.log_drag.item(), math.log(1e-4), rel_tol=1e-6)
    assert not model.log_drag.requires_grad
    with pytest.raises(UsageError, match="not part of this model"):
        without(DeformModel(cfg), ["external_force"])


def test_without_an_added_term_the_model_carries_detaches_it_and_steps_as_the_plain_model():
    cfg = load_rod_config("DLO2")
    plain = DeformModel(cfg)
    carrying = DeformModel(cfg)
    carrying.load_state_dict(plain.state_dict())
    attach(carrying, ["internal_damping", "external_force"])
    with torch.no_grad():
        carrying.extensions[1].set_field(0.7, 0.0)  # a wind that moves the rod
    without(carrying, ["external_force"])
    assert attached_names(carrying) == ["internal_damping"]
    without(carrying, ["internal_damping"])
    assert attached_names(carrying) == []
    rec = generate_recording(plain, n_frames=20, seed=0)
    x = torch.tensor(rec.positions, dtype=torch.float64)
    grips = x[None, 2:, [0, 1, -2, -1]]
    for m in (plain, carrying):
        m.options.residual = False
    a, _ = plain.rollout(plain.initial_state(x[None, 0], x[None, 1]), grips)
    b, _ = carrying.rollout(carrying.initial_state(x[None, 0], x[None, 1]), grips)
    assert torch.equal(a, b)


@pytest.mark.slow
def test_training_with_an_added_term_finds_a_planted_wind(tmp_path):
    """Recordings from the model with a 1 m/s^2 wind along x; training the plain model with the
    external_force term (physics only) finds a wind along +x and beats the same training without it."""
    cfg = load_rod_config("DLO2")
    truth = _wind(DeformModel(cfg), 1.0)
    truth.options.residual = False
    recs = [generate_recording(truth, n_frames=60, seed=s) for s in range(3)]
    common = dict(
        iterations=30,
        batch=4,
        horizon=20,
        curriculum=(),
        residual=False,
        coarse_sysid=False,
        log_every=10,
        lr_physics=0.15,
    )
    results = {}
    for name, terms in (("with", ("external_force",)), ("without", ())):
        model = DeformModel(cfg)
        results[name] = train(
            model, recs[:2], recs[2:], TrainConfig(**common, terms=terms), tmp_path / name, progress=False
        )
        if terms:
            ax = float(model.extensions[0].params()["ax_m_per_s2"])
    assert 0.1 < ax < 1.5  # the right direction; short windows let masses and rest curvature share it
    # DEFORM without the term absorbs much of the wind in its free masses and rest curvature
    assert results["with"]["best_val_l1_m"] < 0.95 * results["without"]["best_val_l1_m"]


@pytest.mark.slow
def test_cli_refuses_a_bad_term_in_one_line_before_reading_data():
    out = subprocess.run(
        [sys.executable, "-m", "deform.cli", "train", "--rod", "DLO2", "--term", "actuation_delay"],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 2
    assert len(out.stderr.strip().splitlines()) == 1 and "actuation_delay" in out.stderr


def _damped_model(nu_raw: float = math.log(50.0)) -> DeformModel:
    model = DeformModel(load_rod_config("DLO1"))
    model.options.residual = False
    with torch.no_grad():
        model.nominal_rest.copy_(torch.linspace(0.02, 0.11, model.n - 1, dtype=torch.float64))
    attach(model, ["internal_damping"])
    with torch.no_grad():
        model.extensions[0].log_nu.fill_(nu_raw)
    return model


def test_internal_damping_on_fixed_rest_lengths_is_the_per_recording_operator_there():
    """The trained model's damping is fixed on its typical edge lengths (so the step exports); on
    those lengths it is the same operator the discrepancy tool builds per recording, it leaves a
    rigid translation alone and it only removes energy."""
    model = _damped_model()
    term = model.extensions[0]
    torch.manual_seed(0)
    x = torch.randn(3, model.n, 3, dtype=torch.float64)
    v = torch.randn(3, model.n, 3, dtype=torch.float64)
    rest = model.nominal_rest.expand(3, -1).clone()
    mass = model.vertex_mass(rest.T).T  # the model's arrays are vertex-major, a term's batch-first
    fixed = term.acceleration(x, v, mass, rest)
    del term.fixed_lam, term.fixed_U, term.fixed_si
    per_recording = term.acceleration(x, v, mass, rest)
    assert torch.allclose(fixed, per_recording, atol=1e-12 * float(per_recording.abs().max()))
    assert fixed.abs().max() > 1e-3  # it acts
    term.fix_rest(model.nominal_rest)
    translation = torch.ones(1, model.n, 3, dtype=torch.float64)
    assert term.acceleration(x[:1], translation, mass[:1], rest[:1]).abs().max() < 1e-9
    power = (mass.unsqueeze(-1) * v * fixed).sum((-1, -2))  # dE/dt of the kinetic energy
    assert (power < 0).all()


class _Step(torch.nn.Module):
    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, x, v, d1, theta, rest, grip):
        from deform.model import VertexMajorState
        from deform.step_graph import branch_free_step

        new, _ = branch_free_step(self.model, VertexMajorState(x, v, d1, theta, rest), grip, (2, 2))
        return new.x


@pytest.mark.slow
def test_a_model_with_internal_damping_exports_its_step(tmp_path):
    """The service runs a trained model's step ahead of time (torch.export): a term must not need
    Python state per call (a cache keyed on a tensor's address broke the export)."""
    from deform.step_graph import rod_at_rest_vertex_major

    model = _damped_model()
    model.save(tmp_path / "m.pt")
    model = DeformModel.load(tmp_path / "m.pt")  # the operator is fixed again after loading
    state, grip = rod_at_rest_vertex_major(model, 2, torch.float64)
    v = state.v.clone()  # a bending motion the damping acts on (~0.2 m/s^2), which the solvers converge on
    v[:, 2] = 0.01 * torch.sin(torch.linspace(0, math.pi, model.n, dtype=torch.float64))[:, None]
    args = (state.x, v, state.d1, state.theta, state.rest, grip)
    with torch.no_grad():
        exported = torch.export.export(_Step(model), args, strict=False)
        assert torch.allclose(exported.module()(*args), _Step(model)(*args), atol=1e-12)
