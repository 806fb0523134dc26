"""Every shipped model, and a model carrying each physics term, at every entry point of the model:
``load_model``, the eager float64 step (the service's loop, ``deform eval``), the float32 predict
step (the service's rollout), the one-graph step that the compiled and ahead-of-time steps trace
(eagerly, traced by ``torch.export`` and by dynamo, and built once by AOTInductor), and
``deform eval``. Every hook of the term library keeps the dtype it is given.

Why (issue 52): DLO4, the one shipped model with the wind term, failed the service's float32
predict step ("expected scalar type Float but found Double") while DLO1 passed, and no test ran it.
The service with each model: tests/service/test_every_model.py.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from deform import DeformModel, generate_recording, load_model, load_rod_config, save_recording
from deform.aot import _BranchFreeStep, exports_loops
from deform.cli import main as deform_main
from deform.compiled import LOOP_BRANCH_FREE, PREDICT_BRANCH_FREE, CompiledStep, RolloutStep, rollout
from deform.rod.convergence import loops_when_exported
from deform.step_graph import branch_free_step, rod_at_rest, rod_at_rest_vertex_major
from deform.terms.library import LIBRARY, make_term
from tests.model_matrix import (
    ALL_TERMS,
    SHIPPED,
    SMALL_VERTICES,
    TERMS,
    save_term_models,
    shipped_models,
)

MODELS = (*SHIPPED, *TERMS, ALL_TERMS)
FIELDS = ("x", "v", "d1", "theta")


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    return save_term_models(tmp_path_factory.mktemp("term-models"))


def _load(name, checkpoints) -> DeformModel:
    return load_model(name if name in SHIPPED else checkpoints[name])


def _moving(grip: torch.Tensor, steps: int) -> torch.Tensor:
    """(B, steps, 4, 3): the grippers ``grip`` (B, 4, 3) lifted by 5 mm a step: a step that moves."""
    lift = torch.zeros(steps, 1, 3, dtype=grip.dtype)
    lift[..., 2] = 0.005 * torch.arange(1, steps + 1, dtype=grip.dtype)[:, None]
    return grip[:, None] + lift


def _dtypes(state) -> dict:
    return {name: getattr(state, name).dtype for name in FIELDS}


def test_the_matrix_holds_every_shipped_model():
    assert shipped_models() == SHIPPED


@pytest.mark.parametrize("name", MODELS)
def test_load_then_an_eager_step_and_a_float32_predict_step(name, checkpoints):
    model = _load(name, checkpoints)
    if name in TERMS or name == ALL_TERMS:  # a checkpoint brings its terms back
        assert model.n == SMALL_VERTICES
    with torch.no_grad():
        # the loop's (and eval's) step: float64, eager, checked loops
        state, grip = rod_at_rest(model, 2, torch.float64)
        new = model.step(state, _moving(grip, 1)[:, 0])
        assert set(_dtypes(new).values()) == {torch.float64}, _dtypes(new)
        assert torch.isfinite(new.x).all() and (new.x - state.x).abs().max() > 0
        # predict's rollout: float32 (workers.predict_dtype), eager (its fallback and its redo)
        state32, grip32 = rod_at_rest(model, 3, torch.float32)
        new32 = model.step(state32, _moving(grip32, 1)[:, 0])
        assert set(_dtypes(new32).values()) == {torch.float32}, _dtypes(new32)
        assert (new32.x.double() - new.x[:1]).abs().max() < 1e-4  # the same step, in float32
        out = rollout(RolloutStep(model, enabled=False), state32, _moving(grip32, 3))
        assert out.shape == (3, 3, model.n, 3) and torch.isfinite(out).all()


@pytest.mark.parametrize("name", MODELS)
def test_the_one_graph_step_keeps_the_dtype(name, checkpoints):
    """What the compiled and ahead-of-time steps trace, run eagerly: float32 at predict's fixed
    iterations, float64 at the loop's."""
    model = _load(name, checkpoints)
    for dtype, branch_free in ((torch.float32, PREDICT_BRANCH_FREE), (torch.float64, LOOP_BRANCH_FREE)):
        state, grip = rod_at_rest_vertex_major(model, 2, dtype)
        with torch.no_grad():
            new, unconverged = branch_free_step(model, state, grip, branch_free)
        assert set(_dtypes(new).values()) == {dtype}, (dtype, _dtypes(new))
        assert unconverged.shape == (2,) and torch.isfinite(new.x).all()


@pytest.mark.parametrize("name", sorted(LIBRARY))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_every_hook_of_the_term_library_keeps_the_dtype(name, dtype):
    """Each term's ``acceleration``, ``mass`` and ``bind`` give the dtype of what they are given
    (its parameters are float64; a predict state is float32)."""
    n = 8
    term = make_term(name, n, np.linspace(0.0, 1.0, n))
    if hasattr(term, "fix_rest"):
        term.fix_rest(torch.full((n - 1,), 0.1, dtype=torch.float64))
    x = torch.randn(3, n, 3, dtype=dtype)
    v, mass, rest = (
        torch.randn(3, n, 3, dtype=dtype),
        torch.rand(3, n, dtype=dtype) + 0.01,
        x.new_full((3, n - 1), 0.1),
    )
    with torch.no_grad():
        if hasattr(term, "acceleration"):
            assert term.acceleration(x, v, mass, rest).dtype == dtype
        if hasattr(term, "mass"):
            assert term.mass(mass).dtype == dtype
        exprs = {"log_beta": torch.zeros(n - 2, dtype=dtype), "wbar": torch.zeros(n - 2, 2, 2, dtype=dtype)}
        assert {k: t.dtype for k, t in term.bind(exprs).items()} == dict.fromkeys(exprs, dtype)


@pytest.mark.slow
def test_the_ahead_of_time_graph_exports_with_every_term(checkpoints):
    """``torch.export`` of the one-graph step as the service's packages are made (deform.aot), for
    the model carrying every term: predict's float32 step for 64 plans and the loop's float64 step.
    (The C++ compile after it: test_the_compiled_steps_run_with_every_term; the shipped models'
    own packages: tests/service/test_every_model.py.)"""
    model = _load(ALL_TERMS, checkpoints)
    for dtype, branch_free, batch in (
        (torch.float32, PREDICT_BRANCH_FREE, 64),
        (torch.float64, LOOP_BRANCH_FREE, 1),
    ):
        state, grip = rod_at_rest_vertex_major(model, batch, dtype)
        args = (state.x, state.v, state.d1, state.theta, state.rest, grip)
        with torch.no_grad(), loops_when_exported(exports_loops(batch)):
            exported = torch.export.export(_BranchFreeStep(model, branch_free), args, strict=False)
        (outputs,) = [node.args[0] for node in exported.graph.nodes if node.op == "output"]
        assert [o.meta["val"].dtype for o in outputs] == [dtype] * 5 + [torch.bool]


@pytest.mark.slow
def test_the_torch_compile_graph_traces_with_every_term(checkpoints, monkeypatch):
    """The compiled step (``torch.compile`` of the one-graph step, deform.compiled) traced by dynamo
    and AOTAutograd in both dtypes; inductor's C++ is left out (``aot_eager``), which is where a
    dtype mismatch would fail."""
    import deform.compiled as compiled

    model = _load(ALL_TERMS, checkpoints)
    real = torch.compile
    monkeypatch.setattr(
        compiled.torch, "compile", lambda fn, **kw: real(fn, backend="aot_eager", dynamic=False)
    )
    torch._dynamo.reset()
    for dtype, branch_free in ((torch.float32, PREDICT_BRANCH_FREE), (torch.float64, LOOP_BRANCH_FREE)):
        step = CompiledStep(model, branch_free=branch_free)
        state, grip = rod_at_rest(model, 2, dtype)
        with torch.no_grad():
            new = step(state, _moving(grip, 1)[:, 0])
            eager = model.step(state, _moving(grip, 1)[:, 0])
        assert step.active, "the compiled path fell back to eager (see the warning)"
        assert set(_dtypes(new).values()) == {dtype}
        assert (new.x - eager.x).abs().max() < (1e-4 if dtype == torch.float32 else 1e-9)
    torch._dynamo.reset()


@pytest.mark.slow
@pytest.mark.compile
def test_the_compiled_steps_run_with_every_term(checkpoints):
    """One AOTInductor package of the model carrying every term, as predict builds it (float32,
    predict's iterations), built, loaded and run: the same values as the eager float32 step."""
    model = _load(ALL_TERMS, checkpoints)
    step = RolloutStep(model, ahead_of_time=True, compile_checked=False)
    state, grip = rod_at_rest(model, 2, torch.float32)
    grips = _moving(grip, 3)
    out = rollout(step, state, grips)
    assert step.fast.ahead_of_time and step.fast.active, "no ahead-of-time step (see the warning)"
    assert out.dtype == torch.float32
    eager = rollout(model, state, grips)
    assert (out - eager).abs().max() < 1e-4


# ----- deform eval ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """One short simulated recording per vertex count of the matrix's models (12, 13, 8)."""
    out = {}
    for rod, n in (("DLO1", 13), ("DLO2", 12), ("DLO4", SMALL_VERTICES)):
        cfg = load_rod_config(rod).model_copy(update={"n_vertices": n})
        d = tmp_path_factory.mktemp(f"recordings-{n}")
        save_recording(d / "0.pkl", generate_recording(DeformModel(cfg), n_frames=30, seed=1).positions)
        out[n] = d
    return out


def _eval(args, capsys) -> dict:
    code = deform_main(["eval", *args, "--json", "--steps", "20"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    return json.loads(captured.out)


@pytest.mark.parametrize("name", MODELS)
def test_deform_eval_runs(name, checkpoints, recordings, capsys):
    if name in SHIPPED:
        args = ["--rod", name]
        n = load_model(name).n
    else:
        args = ["--rod", "DLO4", "--model", str(checkpoints[name])]
        n = SMALL_VERTICES
    result = _eval([*args, "--recordings", str(recordings[n])], capsys)
    assert result["recordings"] == 1 and result["steps"] == 20 and 0 <= result["l1_m"] < 0.1


@pytest.mark.slow
@pytest.mark.parametrize("name", SHIPPED)
def test_deform_eval_on_a_recorded_rope(name, data_root, tmp_path, capsys):
    """With the data: one recording of the rod (its eval split, else its training split)."""
    split = data_root / name / "eval"
    if not split.is_dir():
        split = data_root / name / "train"
    shutil.copy(sorted(split.glob("*.pkl"))[0], tmp_path / "0.pkl")
    result = _eval(["--rod", name, "--recordings", str(tmp_path)], capsys)
    assert result["recordings"] == 1 and 0 < result["l1_m"] < 0.05
