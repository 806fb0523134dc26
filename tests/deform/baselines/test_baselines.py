"""Baselines (issue 6): interface, gripped inputs followed exactly, finite output, XPBD edge lengths,
Bi-LSTM training on synthetic data, load_baseline errors, `deform eval --method` end to end."""

import json

import numpy as np
import pytest
import torch

from deform import DeformModel, ModelOptions, generate_recording, gripped_indices, load_rod_config
from deform.baselines import BASELINES, load_baseline
from deform.baselines.bilstm import BiLSTMDynamics, train_bilstm
from deform.baselines.bilstm import weight_path as bilstm_weights
from deform.baselines.der import der_initial
from deform.baselines.der import weight_path as der_weights
from deform.baselines.hold_shape import HoldShape
from deform.baselines.xpbd import XPBDParams, XPBDRope
from deform.baselines.xpbd import weight_path as xpbd_weights
from deform.cli import main
from deform.errors import UsageError
from deform.evaluate import evaluate


@pytest.fixture(scope="module")
def recordings():
    model = DeformModel(load_rod_config("DLO2"), ModelOptions(residual=False))
    return [generate_recording(model, n_frames=60, seed=s) for s in range(3)]


def _predictors():
    n = load_rod_config("DLO2").n_vertices
    return {
        "hold_shape": HoldShape(n),
        "der_initial": der_initial("DLO2"),
        "xpbd": XPBDRope.for_rod("DLO2", XPBDParams(alpha_stretch=1e-8, alpha_bend=1.0, damping=1.0)),
        "bilstm": BiLSTMDynamics(n),
    }


def _rollout(model, X):
    idx = gripped_indices(model.n)
    with torch.no_grad():
        state = model.initial_state(X[:, 0], X[:, 1])
        out = []
        for k in range(2, X.shape[1]):
            state = model.step(state, X[:, k, idx])
            out.append(state.x)
    return torch.stack(out, 1)


@pytest.mark.parametrize("name", ["hold_shape", "der_initial", "xpbd", "bilstm"])
def test_follows_gripped_inputs_exactly_with_finite_output(name, recordings):
    model = _predictors()[name]
    X = torch.tensor(np.stack([r.positions[:40] for r in recordings]), dtype=torch.float64)
    P = _rollout(model, X)
    assert P.shape == (3, 38, model.n, 3)
    assert torch.isfinite(P).all()
    idx = gripped_indices(model.n)
    assert torch.equal(P[:, :, idx], X[:, 2:, idx])
    assert (P[:, :, 2:-2] - X[:, 2:, 2:-2]).abs().mean() < 0.1  # stays in the neighbourhood of the truth


def test_evaluate_accepts_every_baseline(recordings):
    for name, model in _predictors().items():
        res = evaluate(model, recordings[:2], steps=20)
        assert np.isfinite(res["l1_m"]) and res["steps"] == 20, name


def test_xpbd_keeps_edge_lengths_close_to_rest(recordings):
    rope = XPBDRope.for_rod("DLO2", XPBDParams(alpha_stretch=1e-8, alpha_bend=1.0, damping=1.0))
    X = torch.tensor(recordings[0].positions[None], dtype=torch.float64)
    P = _rollout(rope, X).numpy()[0]
    rest = np.linalg.norm(np.diff(recordings[0].positions[0], axis=0), axis=-1)
    lengths = np.linalg.norm(np.diff(P, axis=1), axis=-1)
    assert np.abs(lengths / rest - 1).max() < 0.02


def test_bilstm_loss_falls_on_synthetic_data(recordings):
    torch.manual_seed(0)
    idx = gripped_indices(recordings[0].n_vertices)
    W = torch.tensor(np.stack([r.positions[10:40] for r in recordings]), dtype=torch.float64)

    def loss(m):
        with torch.no_grad():
            return float(
                (m.rollout(m.initial_state(W[:, 0], W[:, 1]), W[:, 2:, idx]) - W[:, 2:]).abs().mean()
            )

    before = loss(BiLSTMDynamics(recordings[0].n_vertices, hidden=32))
    model, info = train_bilstm(
        recordings,
        [],
        recordings[0].n_vertices,
        iterations=80,
        batch=8,
        hidden=32,
        curriculum=((0, 5), (20, 20)),
        lr=3e-3,
        val_every=20,
    )
    after = loss(model)
    assert np.isfinite(after) and after < 0.7 * before, (before, after, info["log"])


def test_load_baseline_rejects_unknown_names():
    with pytest.raises(ValueError) as err:
        load_baseline("lstm9000", "DLO1")
    assert isinstance(err.value, UsageError)
    for name in BASELINES:
        assert name in str(err.value)


def test_load_baseline_builds_untrained_methods():
    assert load_baseline("hold_shape", "DLO1").n == 13
    assert load_baseline("der_initial", "DLO3").n == 12


@pytest.mark.parametrize("rod", ["DLO1", "DLO2", "DLO3", "DLO4", "DLO5"])
def test_shipped_weights_load(rod):
    for name, path in (
        ("bilstm", bilstm_weights(rod)),
        ("xpbd", xpbd_weights(rod)),
        ("der_identified", der_weights(rod)),
    ):
        if not path.is_file():
            pytest.skip(f"{path} not trained yet")
        model = load_baseline(name, rod)
        assert model.n == load_rod_config(rod).n_vertices


def test_cli_eval_method_on_real_data(data_root, capsys):
    if not bilstm_weights("DLO1").is_file():
        pytest.skip("Bi-LSTM weights not trained")
    assert main(["eval", "--rod", "DLO1", "--method", "bilstm", "--json", "--steps", "50"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["method"] == "bilstm" and result["steps"] == 50 and 0 < result["l1_m"] < 0.05


def test_cli_eval_rejects_unknown_method(data_root, capsys):
    assert main(["eval", "--rod", "DLO1", "--method", "nope"]) == 2
    assert "known" in capsys.readouterr().err


@pytest.mark.slow
def test_module_cli_unknown_method_is_a_one_line_error(tmp_path):
    import os
    import subprocess
    import sys

    from deform import save_recording

    model = DeformModel(load_rod_config("DLO2"), ModelOptions(residual=False))
    save_recording(tmp_path / "0.pkl", generate_recording(model, n_frames=10, seed=0, warmup_s=0.1).positions)
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "deform.cli",
            "eval",
            "--rod",
            "DLO2",
            "--recordings",
            str(tmp_path),
            "--method",
            "nope",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert out.returncode == 2 and "unknown method 'nope'" in out.stderr and "Traceback" not in out.stderr
