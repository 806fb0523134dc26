"""The compiled inference step gives the eager step's values (it is only faster), pads batches to
bucket sizes without changing results, and falls back to eager when compilation fails."""
import pytest
import torch

from deform import generate_recording, gripped_indices, load_model
from deform.compiled import CompiledStep, bucket_size, rollout


@pytest.fixture(scope="module")
def model():
    return load_model("DLO1")  # the shipped model: residual network and identified parameters


@pytest.fixture(scope="module")
def start(model):
    rec = generate_recording(model, n_frames=40, seed=5)
    X = torch.tensor(rec.positions).unsqueeze(0).expand(3, -1, -1, -1).clone()
    X[1:, :, :, 2] += torch.tensor([0.01, -0.02])[:, None, None]  # three different rods
    X[2, :, :, 0] *= 0.98
    return model.initial_state(X[:, 0], X[:, 1]), X[:, 2:, gripped_indices(model.n)]


def test_bucket_sizes():
    assert [bucket_size(b) for b in (1, 3, 64, 65, 1024, 2000)] == [1, 4, 64, 128, 1024, 2000]


def test_compiled_rollout_matches_eager(model, start):
    state, grips = start
    eager = rollout(model, state, grips)
    step = CompiledStep(model)
    compiled = rollout(step, state, grips)  # batch 3, padded to the bucket of 4
    assert step.active, "torch.compile failed on this machine (see the warning)"
    assert compiled.shape == eager.shape
    # the motion amplifies rounding differences of reordered arithmetic; 1 um over 38 steps
    assert (compiled - eager).abs().max() < 1e-6


def test_failed_compilation_falls_back_to_eager(model, start, monkeypatch):
    state, grips = start
    step = CompiledStep(model)

    def broken(*args, **kwargs):
        raise RuntimeError("no C++ compiler")

    monkeypatch.setattr(step, "_step_fn", lambda: broken)
    out = step(state, grips[:, 0])
    assert not step.active
    assert torch.equal(out.x, model.step(state, grips[:, 0]).x)
