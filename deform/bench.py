"""Speed benchmark of the model: latency, batched throughput, cost against vertex count, training.

Every figure is a median (and p99 for latencies) over many steps, measured in one process; the
Theseus twist solver runs in the same process as the baseline the fast solver is compared to.
"""

from __future__ import annotations

import os
import platform
import random
import time

import numpy as np
import torch

from deform.config import load_rod_config
from deform.io.recordings import find_data_root, load_recordings
from deform.model import DeformModel, ThetaSolver, gripped_indices, load_model
from deform.synthetic import generate_recording


def _trajectory(model: DeformModel, frames: int = 500) -> np.ndarray:
    root = find_data_root()
    if root is not None and (root / model.cfg.name / "train").is_dir():
        return load_recordings(root / model.cfg.name / "train", model.n)[0].positions
    return generate_recording(model, n_frames=frames, seed=1).positions


def _percentiles(seconds: list[float]) -> dict:
    ms = np.asarray(seconds) * 1e3
    return {"p50_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)), "steps": len(ms)}


def step_latency(model: DeformModel, positions: np.ndarray, steps: int, step_fn=None) -> dict:
    """Single rollout (B = 1): the whole step, replaying the recording's grippers in a loop.
    ``step_fn``: the step to time (default ``model.step``; e.g. a :class:`~deform.compiled.CompiledStep`).

    Args:
        model: the model.
        positions: (T, n, 3) a recording to replay.
        steps: steps timed.
        step_fn: the step, or None.

    Returns:
        ``{"p50_ms", "p99_ms", "steps"}``.
    """
    step_fn = step_fn or model.step
    X = torch.tensor(positions, dtype=torch.float64).unsqueeze(0)
    idx = gripped_indices(model.n)
    times = []
    with torch.no_grad():
        state = model.initial_state(X[:, 0], X[:, 1])
        for k in range(steps + 20):
            f = 2 + k % (X.shape[1] - 2)
            if f == 2:
                state = model.initial_state(X[:, 0], X[:, 1])
            t0 = time.perf_counter()
            state = step_fn(state, X[:, f, idx])
            times.append(time.perf_counter() - t0)
    return _percentiles(times[20:])


def throughput(
    model: DeformModel,
    positions: np.ndarray,
    batch: int,
    steps: int,
    step_fn=None,
    dtype: torch.dtype = torch.float64,
) -> float:
    """Batched stepping speed.

    Args:
        model: the model.
        positions: (T, n, 3) a recording (its grippers drive every rod).
        batch: rods stepped together.
        steps: steps timed.
        step_fn: the step, or None (``model.step``).
        dtype: of the rods' state (the step follows it).

    Returns:
        Rod-steps per second.
    """
    step_fn = step_fn or model.step
    X = torch.tensor(positions[: steps + 2], dtype=dtype).unsqueeze(0).expand(batch, -1, -1, -1)
    X = X + 1e-4 * torch.randn_like(X)
    idx = gripped_indices(model.n)
    with torch.no_grad():
        state = model.initial_state(X[:, 0], X[:, 1])
        state = step_fn(state, X[:, 2, idx])
        t0 = time.perf_counter()
        for k in range(steps):
            state = step_fn(state, X[:, 2 + k, idx])
        dt = time.perf_counter() - t0
    return batch * steps / dt


def vertex_scaling(counts=(13, 25, 50, 100), steps: int = 300) -> dict:
    """Step latency against the number of vertices (an untrained DLO1-like rod).

    Args:
        counts: vertex counts.
        steps: steps timed per count.

    Returns:
        ``{str(n): step_latency result}``.
    """
    out = {}
    base = load_rod_config("DLO1")
    for n in counts:
        model = DeformModel(base.model_copy(update={"n_vertices": n}))
        rec = generate_recording(model, n_frames=200, seed=2)
        out[str(n)] = step_latency(model, rec.positions, steps)
    return out


def training_iteration(
    model: DeformModel, positions: np.ndarray, batch: int = 32, horizon: int = 100, iters: int = 3
) -> dict:
    """Seconds of one training update (forward rollout with graph, backward, no optimizer step).

    Args:
        model: the model.
        positions: (T, n, 3) a recording windows are cut from.
        batch: windows.
        horizon: steps per window.
        iters: updates timed.

    Returns:
        ``{"seconds_p50", "iterations", "batch", "horizon"}``.
    """
    from deform.io.recordings import Recording
    from deform.train import rollout_loss, sample_windows

    rec = Recording("bench", positions)
    rng = random.Random(0)
    times = []
    for _ in range(iters):
        w, d1 = sample_windows([rec], batch, horizon, rng)
        t0 = time.perf_counter()
        loss = rollout_loss(model, w, d1)
        loss.backward()
        times.append(time.perf_counter() - t0)
        model.zero_grad(set_to_none=True)
    return {"seconds_p50": float(np.median(times)), "iterations": iters, "batch": batch, "horizon": horizon}


def theta_solver_training_ratio(rod: str, positions: np.ndarray, batch: int = 4, horizon: int = 10) -> dict:
    """Forward + backward of a small training window with each twist solver, same weights and data.

    Args:
        rod: a shipped rod.
        positions: (T, n, 3) a recording.
        batch: windows.
        horizon: steps per window.

    Returns:
        Seconds per iteration with each solver and their ratio.
    """
    out = {}
    for solver in (ThetaSolver.NEWTON, ThetaSolver.THESEUS):
        model = load_model(rod)
        model.options.theta_solver = solver
        out[solver] = training_iteration(model, positions, batch=batch, horizon=horizon, iters=2)[
            "seconds_p50"
        ]
    return {
        "batch": batch,
        "horizon": horizon,
        "seconds_newton": out["newton"],
        "seconds_theseus": out["theseus"],
        "theseus_over_newton": out["theseus"] / out["newton"],
    }


def run_benchmarks(quick: bool = False, rod: str = "DLO1") -> dict:
    """All of ``deform bench``: latency eager and compiled, throughput, vertex scaling, training.

    Args:
        quick: fewer steps (a smoke run).
        rod: the shipped rod to time.

    Returns:
        The results (``deform bench --json`` prints them).
    """
    steps = 300 if quick else 2000
    model = load_model(rod)
    positions = _trajectory(model)
    torch.set_num_threads(1)
    result = {
        "machine": {
            "cpu_count": os.cpu_count(),
            "processor": platform.processor() or platform.machine(),
            "torch": torch.__version__,
            "python": platform.python_version(),
        },
        "rod": rod,
        "n_vertices": model.n,
    }
    result["single_rollout_1_thread"] = step_latency(model, positions, steps)
    theseus_model = load_model(rod)
    theseus_model.options.theta_solver = ThetaSolver.THESEUS
    result["single_rollout_theseus_theta_1_thread"] = step_latency(
        theseus_model, positions, 20 if quick else 60
    )
    result["speedup_vs_theseus_theta"] = (
        result["single_rollout_theseus_theta_1_thread"]["p50_ms"]
        / result["single_rollout_1_thread"]["p50_ms"]
    )
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    result["throughput_rod_steps_per_s_2_threads"] = {
        str(b): throughput(model, positions, b, 20 if quick else (200 if b <= 32 else 50))
        for b in ((1, 32, 256) if quick else (1, 32, 256, 1024))
    }
    # the compiled inference steps (deform.compiled), same data and threads: one graph per step for
    # a single rollout (the service loop's), convergence-checked loops for batches (predict's)
    from deform.compiled import LOOP_BRANCH_FREE, CompiledStep

    torch.set_num_threads(1)
    single = CompiledStep(model, branch_free=LOOP_BRANCH_FREE)
    single.warmup((1,))
    result["single_rollout_compiled_1_thread"] = step_latency(model, positions, steps, single)
    result["single_rollout_compiled_redone"] = single.redone
    compiled = CompiledStep(model)
    compiled.warmup((1,))
    result["compiled_active"] = compiled.active and single.active
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    sizes = (1, 32, 256) if quick else (1, 32, 256, 1024)
    compiled.warmup(sizes)
    result["throughput_compiled_rod_steps_per_s_2_threads"] = {
        str(b): throughput(model, positions, b, 20 if quick else (200 if b <= 32 else 50), compiled)
        for b in sizes
    }
    torch.set_num_threads(1)
    result["vertex_scaling_1_thread"] = vertex_scaling(steps=100 if quick else 300)
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    result["training_iteration_2_threads"] = training_iteration(
        load_model(rod), positions, iters=2 if quick else 5
    )
    result["training_theta_solver_2_threads"] = theta_solver_training_ratio(rod, positions)
    return result
