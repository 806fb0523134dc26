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
        model.extensions[0].raw.copy_(torch.tensor([2 * ax, 0.0]))  # ax = raw / 2
    return model


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
    assert float(model.log_beta.max() - model.log_beta.min()) == 0.0
    assert float(model.log_gamma.max() - model.log_gamma.min()) == 0.0
    assert math.isclose(float(model.log_drag), math.log(1e-4), rel_tol=1e-6)
    assert not model.log_drag.requires_grad
    with pytest.raises(UsageError, match="not part of DEFORM"):
        without(DeformModel(cfg), ["external_force"])


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


def test_cli_refuses_a_bad_term_in_one_line_before_reading_data():
    out = subprocess.run(
        [sys.executable, "-m", "deform.cli", "train", "--rod", "DLO2", "--term", "actuation_delay"],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 2
    assert len(out.stderr.strip().splitlines()) == 1 and "actuation_delay" in out.stderr
