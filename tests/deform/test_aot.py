"""The ahead-of-time step gives the torch.compile one-graph step's values, is built once per model
and reused from disk, never runs with weights the model no longer has, and falls back to
torch.compile when it cannot be built. Packages go to the session's own ``$DEFORM_CACHE`` (see
tests/conftest.py), so the first test builds one: nothing is reused from, or left in, the user's cache."""

import os
from pathlib import Path

import pytest
import torch

import deform.aot as aot
from deform import generate_recording, gripped_indices, load_model
from deform.compiled import RolloutStep, rollout

BRANCH_FREE = (2, 2)

pytestmark = [pytest.mark.compile, pytest.mark.slow]


@pytest.fixture(scope="module")
def model():
    return load_model("DLO1")


@pytest.fixture(scope="module")
def start(model):
    rec = generate_recording(model, n_frames=30, seed=6)
    X = torch.tensor(rec.positions).unsqueeze(0).expand(3, -1, -1, -1).clone()
    X[1:, :, :, 2] += torch.tensor([0.01, -0.02])[:, None, None]  # three different rods, a bucket of 4
    return model.initial_state(X[:, 0], X[:, 1]), X[:, 2:, gripped_indices(model.n)]


@pytest.fixture(scope="module")
def built(model, start):
    """A rollout through the ahead-of-time step (its package built or loaded once for the module)."""
    state, grips = start
    step = RolloutStep(model, branch_free=BRANCH_FREE, ahead_of_time=True)
    out = rollout(step, state, grips)
    assert step.fast.ahead_of_time, "the ahead-of-time step could not be built here (see the warning)"
    return step, out


def test_same_values_as_the_compiled_one_graph_step(model, start, built):
    state, grips = start
    step, out = built
    compiled = rollout(RolloutStep(model, branch_free=BRANCH_FREE), state, grips)
    eager = rollout(model, state, grips)
    assert torch.equal(out, compiled)  # the same graph and kernels, only entered differently
    assert (out - eager).abs().max() < 1e-6
    assert step.redone == 0, "the fast graph must have run (else the comparison proves nothing)"


def test_the_package_is_entered_through_its_flat_call(model, start, built, monkeypatch):
    """Each step goes through the loader's flat call, not the package's own ``__call__`` (which
    parses its tree specs from JSON on every call: 35 us of a 157 us step at one rod)."""
    state, grips = start
    step, _ = built
    (aot_step,) = step.fast._aot.values()
    flat, calls = aot_step._run_flat, []
    monkeypatch.setattr(aot_step, "_run_flat", lambda args: calls.append(len(args)) or flat(args))
    step.fast.attempt(model.step(state, grips[:, 0]), grips[:, 1])
    assert calls == [6]  # x, v, d1, theta, rest, grip


def test_packages_are_kept_in_the_sessions_cache_not_the_users(built):
    step, _ = built
    (aot_step,) = step.fast._aot.values()
    cache = Path(os.environ["DEFORM_CACHE"])
    assert cache.name.startswith("deform-cache")  # the session's directory (tests/conftest.py)
    assert aot_step.path.parent == aot.cache_dir() == cache / "aot"
    assert aot_step.path.is_file()
    assert Path.home() / ".cache" / "deform" not in aot_step.path.parents


def test_a_second_step_loads_the_package_without_compiling(model, start, built, monkeypatch):
    def no_build(*args, **kwargs):
        raise AssertionError("compiled again although the package is on disk")

    monkeypatch.setattr(aot, "_build", no_build)
    state, grips = start
    again = RolloutStep(model, branch_free=BRANCH_FREE, ahead_of_time=True)
    assert torch.equal(rollout(again, state, grips), built[1])
    assert again.fast.ahead_of_time


def test_changed_parameters_are_never_run_with_the_old_package(start, built, monkeypatch):
    model = load_model("DLO1")  # a model of its own: its parameters are changed below
    state, grips = start
    step = aot.AheadOfTimeStep(model, BRANCH_FREE, batch=4)  # loads the package built above
    key = aot.package_key(model, BRANCH_FREE, 4, torch.float64)
    loads = []
    monkeypatch.setattr(aot.AheadOfTimeStep, "load", lambda self: loads.append(self.model))
    pad = lambda t: torch.cat([t, t[:1]])  # noqa: E731 - 3 rods to the package's 4
    padded = type(state)(*(pad(t) for t in (state.x, state.v, state.d1, state.theta, state.rest)))
    step(padded, pad(grips[:, 0]))
    assert loads == []
    with torch.no_grad():
        next(model.parameters()).mul_(1.5)
    assert aot.package_key(model, BRANCH_FREE, 4, torch.float64) != key
    step(padded, pad(grips[:, 0]))  # would build a package for the new values (load stubbed out)
    assert loads == [model]


def test_the_thread_count_is_part_of_the_package(model):
    """Inductor writes the thread count into the kernels: a package built on one thread would run
    on one thread in a process that has two."""
    before = torch.get_num_threads()
    try:
        keys = set()
        for threads in (1, 2):
            torch.set_num_threads(threads)
            keys.add(aot.package_key(model, BRANCH_FREE, 4, torch.float64))
    finally:
        torch.set_num_threads(before)
    assert len(keys) == 2


@pytest.mark.parametrize(
    "broken_part, warning",
    [
        ("__init__", "ahead-of-time step unavailable"),  # cannot be built here
        ("__call__", "ahead-of-time step failed"),  # built, but fails when called: not eager either
    ],
)
def test_package_that_cannot_run_falls_back_to_torch_compile(
    model, start, built, monkeypatch, caplog, broken_part, warning
):
    def broken(*args, **kwargs):
        raise RuntimeError("no AOTInductor")

    monkeypatch.setattr(aot.AheadOfTimeStep, broken_part, broken)
    state, grips = start
    step = RolloutStep(model, branch_free=BRANCH_FREE, ahead_of_time=True)
    with caplog.at_level("WARNING", logger="deform.compiled"):
        out = rollout(step, state, grips)
    assert not step.fast.ahead_of_time and step.active  # still compiled, only without the package
    assert warning in caplog.text
    assert torch.equal(out, built[1])  # the torch.compile one-graph step's values, not the eager ones


def test_a_package_is_built_once_when_two_ask_for_it_at_once(model, tmp_path, monkeypatch):
    """Two predict processes meeting a new batch size together: one builds, the other waits and
    loads (threads here: each opens the lock file itself, as a process would)."""
    import threading
    import time

    monkeypatch.setenv("DEFORM_CACHE", str(tmp_path))
    builds = []

    def slow_build(model, branch_free, batch, dtype, path, network_dtype=None):
        builds.append(batch)
        time.sleep(0.3)
        path.write_bytes(b"package")

    monkeypatch.setattr(aot, "_build", slow_build)
    results = []
    threads = [
        threading.Thread(
            target=lambda: results.append(aot.ensure_package(model, BRANCH_FREE, 8, torch.float32))
        )
        for _ in range(2)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert builds == [8]
    assert sorted(built for _, built in results) == [False, True]
    assert results[0][0] == results[1][0] and results[0][0].read_bytes() == b"package"


def test_the_network_precision_is_part_of_the_package(model):
    """A bfloat16 network is other kernels: never loaded for a float32 one, nor the reverse."""
    keys = {aot.package_key(model, BRANCH_FREE, 4, torch.float32, net) for net in (None, torch.bfloat16)}
    assert len(keys) == 2


def test_unconverged_rods_are_redone_by_the_rescue_package(model, start, monkeypatch):
    """A grip jumping 5 cm needs more sweeps than predict's one graph holds: that rod goes through
    the rescue package (the checked solvers' limits as one graph), not the eager loops, and comes
    out within the projection's tolerance; the other rods keep the one graph's result."""
    from deform.rod.inextensibility import max_relative_error
    from deform.rod.layout import vertex_major

    state, grips = start
    state, grips = model.step(state, grips[:, 0]), grips[:, 1:]
    jump = grips.clone()
    jump[0, 3:, 2:] += torch.tensor([0.05, 0.0, 0.0], dtype=jump.dtype)
    step = RolloutStep(model, branch_free=BRANCH_FREE, ahead_of_time=True)
    assert step.rescue.active
    eager_calls = []
    real_eager = step.checked.eager
    monkeypatch.setattr(
        step.checked, "eager", lambda s, g: eager_calls.append(s.x.shape[0]) or real_eager(s, g)
    )
    out = rollout(step, state, jump)
    assert step.redone >= 1 and step.rescue.ahead_of_time
    assert eager_calls == [], "no rod went through the checked step's eager loops"
    assert step.rescue.redone == 0, "the rescue package converged the jerked rod (no eager redo)"
    for k in range(out.shape[1]):
        assert (
            max_relative_error(vertex_major(out[:, k], 2), vertex_major(state.rest, 1))
            < model.options.pbd_tol
        )
    for r in (1, 2):  # untouched by the redo: what the one graph gives them
        assert torch.equal(out[r], rollout(RolloutStep(model, branch_free=BRANCH_FREE), state, jump)[r])
    ref = rollout(model, state, jump)  # the checked step throughout (eager: its compiled form is
    # the same to 1e-6, tests/deform/test_compiled.py, and compiling it here took 15-70 s)
    assert (out - ref).abs().max() < 5e-4


def test_a_deferred_rescue_graph_leaves_unconverged_rods_to_the_eager_loops(model, start, monkeypatch):
    """Until ``warmup_rescue``, a rollout never builds or calls the rescue package (a cold start
    lets another process build it): the jerked rod goes through the checked eager loops; after it,
    through the rescue package."""
    state, grips = start
    state, grips = model.step(state, grips[:, 0]), grips[:, 1:]
    jump = grips.clone()
    jump[0, 3:, 2:] += torch.tensor([0.05, 0.0, 0.0], dtype=jump.dtype)
    step = RolloutStep(model, branch_free=BRANCH_FREE, ahead_of_time=True)
    step.warmup((), state.x.dtype, rescue=False)
    rescued = []

    class Spy:  # the rescue step, its calls counted
        def __init__(self, inner):
            self.inner = inner

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def __call__(self, s, g):
            rescued.append(s.x.shape[0])
            return self.inner(s, g)

    step.rescue = Spy(step.rescue)
    eager_calls = []
    real_eager = step.checked.eager
    monkeypatch.setattr(
        step.checked, "eager", lambda s, g: eager_calls.append(s.x.shape[0]) or real_eager(s, g)
    )
    rollout(step, state, jump)
    assert not step.rescue_ready and step.redone >= 1
    assert rescued == [] and step.rescue._aot == {} and eager_calls, "the eager loops redid the rod"
    step.warmup_rescue(state.x.dtype)
    eager_calls.clear()
    rollout(step, state, jump)
    assert step.rescue_ready and rescued and eager_calls == []


def test_the_package_is_keyed_on_the_source_the_step_runs_only(tmp_path, monkeypatch):
    """An edit to the discrepancy tool or the command line keeps the prebuilt packages; an edit to
    the rod's physics, a module the step imports inside a function, or a package ``__init__`` does not."""
    import shutil

    copy = tmp_path / "deform"
    shutil.copytree(Path(aot.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__", "*.pt"))
    names = {p.relative_to(copy).as_posix() for p in aot.step_sources(copy)}
    assert {"model.py", "step_graph.py", "rod/forces.py", "rod/twist_theseus.py", "__init__.py"} <= names
    assert not names & {"cli.py", "train.py", "diagnose/selection.py", "evaluate.py"}
    monkeypatch.setattr(aot, "_PACKAGE_SOURCE", copy)
    model = load_model("DLO1")
    key = aot.package_key(model, BRANCH_FREE, 4, torch.float64)
    for unrelated in ("diagnose/selection.py", "cli.py"):
        (copy / unrelated).write_text((copy / unrelated).read_text() + "\n# edited\n")
    assert aot.package_key(model, BRANCH_FREE, 4, torch.float64) == key
    for related in ("rod/forces.py", "rod/twist_theseus.py", "rod/__init__.py"):
        (copy / related).write_text((copy / related).read_text() + "\n# edited\n")
        assert aot.package_key(model, BRANCH_FREE, 4, torch.float64) != key
        key = aot.package_key(model, BRANCH_FREE, 4, torch.float64)
