"""The compiled inference step gives the eager step's values (it is only faster), pads batches to
bucket sizes without changing results, and falls back to eager when compilation fails. Tests that
compile are marked ``compile`` (skipped without a C++ compiler, see tests/conftest.py)."""

import math

import pytest
import torch

from deform import generate_recording, gripped_indices, load_model, overstretched
from deform.compiled import (
    LOOP_BRANCH_FREE,
    PREDICT_BRANCH_FREE,
    CompiledStep,
    RolloutStep,
    bucket_size,
    rollout,
)
from deform.model import RodState
from deform.rod.inextensibility import max_relative_error
from deform.rod.layout import vertex_major


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


@pytest.mark.compile
def test_compiled_rollout_matches_eager(model, start):
    state, grips = start
    eager = rollout(model, state, grips)
    step = CompiledStep(model)
    compiled = rollout(step, state, grips)  # batch 3, padded to the bucket of 4
    assert step.active, "torch.compile failed on this machine (see the warning)"
    assert compiled.shape == eager.shape
    # the motion amplifies rounding differences of reordered arithmetic; 1 um over 38 steps
    assert (compiled - eager).abs().max() < 1e-6


@pytest.mark.compile
def test_one_graph_step_matches_eager_per_rod(model, start):
    """The real-time loop's step (one graph, masked iterations, eager redo of unconverged rods)
    gives each rod what the eager step gives it alone."""
    state, grips = start
    step = CompiledStep(model, branch_free=LOOP_BRANCH_FREE)
    compiled = rollout(step, state.index([1]), grips[1:2])
    assert step.active, "torch.compile failed on this machine (see the warning)"
    eager = rollout(model, state.index([1]), grips[1:2])
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


def test_unconverged_flags_only_rods_off_tolerance(model, start):
    state, grips = start
    new = model.step(state, grips[:, 0])
    assert not model.unconverged(state, new).any()
    stretched = RodState(new.x.clone(), new.v, new.d1, new.theta, new.rest)
    stretched.x[1, 6, 2] -= 0.01  # a free vertex of rod 1 off by 1 cm: two edges stretched
    twisted = RodState(new.x, new.v, new.d1, new.theta.clone(), new.rest)
    twisted.theta[2, 5] += 0.05  # rod 2's angles off the minimum
    assert model.unconverged(state, stretched).tolist() == [False, True, False]
    assert model.unconverged(state, twisted).tolist() == [False, False, True]


@pytest.mark.compile
def test_sudden_jump_is_redone_eagerly(model, start):
    """A grip that jumps 5 cm in one step needs more projection sweeps than the compiled step
    makes: that rod is stepped again by the checked eager loop and the result stays within tol."""
    state, grips = start
    step = CompiledStep(model, branch_free=PREDICT_BRANCH_FREE)  # the graph predict compiles (fewer to build)
    state = model.step(state, grips[:, 0])  # the twist angles solved (the start has none)
    state = step(state, grips[:, 1])
    assert step.redone == 0
    jump = grips[:, 2].clone()
    jump[0, 2:] += torch.tensor([0.05, 0.0, 0.0], dtype=jump.dtype)
    out = step(state, jump)
    assert step.redone == 1
    for r in range(3):  # each rod as the eager step gives it alone (rod 0 is exactly that step)
        eager = model.step(state.index([r]), jump[r : r + 1])
        assert (out.x[r] - eager.x[0]).abs().max() < (1e-15 if r == 0 else 1e-6)
    assert not model.unconverged(state, out).any()


@pytest.mark.compile
def test_rollout_step_one_graph_while_converged(model, start):
    """Predict's rollout: steps that converge in the one-graph step keep it, and each rod then
    gets what the eager step gives it alone."""
    state, grips = start
    state, grips = (
        model.step(state, grips[:, 0]),
        grips[:, 1:],
    )  # the twist angles solved (the start has none)
    step = RolloutStep(model)
    out = rollout(step, state, grips)
    assert step.active and step.redone == 0
    for r in range(3):
        alone = rollout(model, state.index([r]), grips[r : r + 1])
        assert (out[r] - alone[0]).abs().max() < 1e-6


@pytest.mark.compile
def test_rollout_step_redoes_an_unconverged_step_with_the_checked_step(model, start):
    """A grip jumping 5 cm needs more sweeps than the one graph holds: that rod's step is redone
    alone by the checked loops, not left unconverged; the other rods keep the one graph's result
    (what they get alone), and the following steps go back to the one graph."""
    state, grips = start
    state, grips = (
        model.step(state, grips[:, 0]),
        grips[:, 1:],
    )  # the twist angles solved (the start has none)
    jump = grips.clone()
    jump[0, 3:, 2:] += torch.tensor([0.05, 0.0, 0.0], dtype=jump.dtype)
    step = RolloutStep(model)
    out = rollout(step, state, jump)
    # the jump's step, and with the shipped DLO1 (internal damping) the one after it: then the one graph
    # again, with no pause (three misses in a row would pause it)
    assert 1 <= step.redone <= 2 and step.paused == 0
    for k in range(out.shape[1]):  # every step within the projection's tolerance
        assert (
            max_relative_error(vertex_major(out[:, k], 2), vertex_major(state.rest, 1))
            < model.options.pbd_tol
        )
    for r in (1, 2):  # untouched by the jerked rod's redo (a whole-batch redo sweeps them on)
        alone = rollout(model, state.index([r]), jump[r : r + 1])
        assert (out[r] - alone[0]).abs().max() < 1e-6
    # the checked step throughout: the same motion within the solver tolerance (0.1 mm here)
    ref = rollout(CompiledStep(model), state, jump)
    assert (out - ref).abs().max() < 5e-4


@pytest.mark.compile
def test_rollout_step_pauses_the_fast_graph_after_misses_in_a_row(model, start, monkeypatch):
    """A batch that keeps needing more than the one graph stops paying for the wasted attempts:
    after ``max_misses`` in a row the fast graph pauses for 1, 2, 4, ... steps, so it is tried a
    number of times logarithmic in the rollout's length, and every step is the checked step's.
    (The fast graph is made to miss every time: the rule, not the physics, is under test.)"""
    state, grips = start
    step = RolloutStep(model)
    real = step.fast.attempt_vertex_major  # what a rollout calls (its state vertex-major, rods last)
    monkeypatch.setattr(
        step.fast,
        "attempt_vertex_major",
        lambda s, g: (real(s, g)[0], torch.ones(s.x.shape[-1], dtype=torch.bool)),
    )
    out = rollout(step, state, grips)
    steps, rods = (
        grips.shape[1],
        grips.shape[0],
    )  # 38 steps: tried at 0, 1, 2, then after pauses at 4, 7, 12, 21
    assert step.redone == rods * (step.max_misses + 4) and step.paused == 5
    assert step.redone < rods * (step.max_misses + math.log2(steps) + 1)
    ref = rollout(CompiledStep(model), state, grips)
    assert (out - ref).abs().max() < 1e-6


@pytest.mark.compile
def test_rollout_step_does_not_redo_an_overstretched_rod(model, start):
    """A rod pulled farther apart than it is long has no shape that meets its lengths: the fast
    graph's result stands (the checked step would only sweep longer without converging), while
    the rods beside it keep what they get alone."""
    state, grips = start
    state, grips = (
        model.step(state, grips[:, 0]),
        grips[:, 1:],
    )  # the twist angles solved (the start has none)
    pulled = grips.clone()
    pulled[0, :, 2:, 0] += 0.6
    assert overstretched(pulled[0], state.rest[0]).all()
    step = RolloutStep(model)
    out = rollout(step, state, pulled)
    assert step.redone == 0
    for r in (1, 2):
        alone = rollout(model, state.index([r]), pulled[r : r + 1])
        assert (out[r] - alone[0]).abs().max() < 1e-6


@pytest.mark.compile
def test_solver_flags_agree_with_a_recomputed_check(model, start):
    """The one-graph step's convergence read from the solvers' own flags flags the same rods as a
    second evaluation of its result (``DeformModel.unconverged``): none on a plain step, the jerked
    rod on a jump."""
    state, grips = start
    state = model.step(state, grips[:, 0])
    jump = grips[:, 1].clone()
    jump[1, 2:] += torch.tensor([0.05, 0.0, 0.0], dtype=jump.dtype)
    step = CompiledStep(model, branch_free=PREDICT_BRANCH_FREE)
    for g, expected in ((grips[:, 1], [False, False, False]), (jump, [False, True, False])):
        new, reported = step.attempt(state, g)
        assert step.active, "torch.compile failed on this machine (see the warning)"
        assert reported.tolist() == model.unconverged(state, new).tolist() == expected


@pytest.mark.parametrize("min_batch", [1, 4])
def test_rollout_step_network_precision_reaches_every_path(model, start, monkeypatch, min_batch):
    """A bfloat16 network is used in the fast step and in the redo of a rod it leaves unconverged
    from ``BFLOAT16_MIN_BATCH`` rods per step on, and the float32 network below (here: the batch
    of 3, and the redo of 1 rod, against a threshold of 1 or 4)."""
    import deform.nn.precision as precision

    monkeypatch.setattr(precision, "BFLOAT16_MIN_BATCH", min_batch)
    state, grips = start
    state, grips = model.step(state, grips[:, 0]), grips[:, 1:12]

    def eager_rollout(network_dtype):
        s, out = state, []
        with torch.no_grad():
            for k in range(grips.shape[1]):
                s = model.step(s, grips[:, k], network_dtype=network_dtype)
                out.append(s.x)
        return torch.stack(out, 1)

    low, full = eager_rollout(torch.bfloat16), eager_rollout(None)
    assert (low - full).abs().max() > 0  # the shipped model's network is trained: precision shows
    step = RolloutStep(model, enabled=False, network_dtype=torch.bfloat16)
    real = step.fast.attempt_vertex_major
    monkeypatch.setattr(  # rod 0 "unconverged" at every step: redone alone by the checked loops
        step.fast, "attempt_vertex_major", lambda s, g: (real(s, g)[0], torch.tensor([True, False, False]))
    )
    out = rollout(step, state, grips)
    assert step.redone == grips.shape[1]
    expected = low if min_batch == 1 else full
    assert torch.equal(out[1:], expected[1:])
    # rod 0 stepped alone: the same arithmetic to rounding, far below the precisions' difference
    assert (out[0] - expected[0]).abs().max() < 1e-3 * (low - full).abs().max()


@pytest.mark.compile
def test_one_graph_step_of_a_model_in_substeps_matches_eager():
    """A 30 cm rope known by length and mass takes implicit bending in substeps; the one-graph step
    (substeps unrolled, their reports merged) gives the eager step's values. Predict's iterations:
    the loop's (6, 3) unroll the same way, in a larger graph that is slower to compile."""
    from deform.model import generic_model

    model = generic_model(0.3, 0.05)
    assert model.cfg.implicit_bending and model.cfg.substeps > 1
    rec = generate_recording(model, n_frames=20, seed=2)
    X = torch.tensor(rec.positions).unsqueeze(0)
    state, grips = model.initial_state(X[:, 0], X[:, 1]), X[:, 2:, gripped_indices(model.n)]
    step = CompiledStep(model, branch_free=PREDICT_BRANCH_FREE)
    compiled = rollout(step, state, grips)
    assert step.active, "torch.compile failed on this machine (see the warning)"
    assert (compiled - rollout(model, state, grips)).abs().max() < 1e-6
    assert step.redone == 0  # the merged report found every substep converged
