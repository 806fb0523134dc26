"""Shared fixtures: the model, a free loopback endpoint, a short simulated recording and its stream."""

from __future__ import annotations

import time

import pytest
import torch


@pytest.fixture(scope="session")
def model():
    from deform import load_model

    torch.set_num_threads(1)
    return load_model("DLO1")


@pytest.fixture
def endpoint():
    from service.demo import free_port

    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture(scope="session")
def sim_positions(model):
    from deform import generate_recording

    return generate_recording(model, n_frames=60, seed=3, warmup_s=1.0).positions


@pytest.fixture(scope="session")
def sim_stream(sim_positions):
    from service import scenario

    grippers = scenario.offsets_for(sim_positions)
    return grippers, scenario.build_stream(sim_positions, grippers, fps=30.0)


def wait_for(cond, timeout=20.0):
    """Poll ``cond`` (a query: nothing to be notified by) until true or ``timeout``."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return False


def make_config(endpoint=None, connect=None, **over):
    from service.config import load_config

    z = {
        "mode": "peer",
        "multicast_scouting": False,
        "listen": [endpoint] if endpoint else [],
        "connect": [connect] if connect else [],
    }
    # compiling the predict rollout costs ~30 s per batch size: tests/deform/test_compiled.py covers it;
    # one predict process (the split across two: test_predict.py inline, test_workers.py processes)
    over.setdefault("workers", {"compile_predict": False, "predict_processes": 1})
    over.setdefault("compile_step", False)
    return load_config(zenoh=z, **over)


class FakeClock:
    """Stands in for ``time.monotonic`` (call it) and ``time.sleep`` (``sleep`` advances it): time
    moves only when a test says so, so rate limits and timeouts are checked exactly."""

    def __init__(self, t: float = 1000.0):
        self.t, self.sleeps, self._due = t, 0, []

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += dt
        for item in [d for d in self._due if d[0] <= self.t]:
            self._due.remove(item)
            item[1]()

    def sleep(self, dt: float) -> None:
        self.sleeps += 1
        self.advance(dt)

    def call_at(self, t: float, fn) -> None:
        """Run ``fn`` once the clock reaches ``t`` (as another thread would, during a sleep)."""
        self._due.append((t, fn))


def package_paths(cfg) -> dict:
    """``{label: path}``: where the packages a start with ``cfg`` loads (``service.cli.prebuild_jobs``,
    for ``cfg.rod``) are in the cache ``$DEFORM_CACHE`` names now, each keyed as built: on its threads."""
    from deform import load_model
    from deform.aot import package_path
    from service.cli import prebuild_jobs

    model, before, out = load_model(cfg.rod), torch.get_num_threads(), {}
    try:
        for label, branch_free, batch, dtype, network, threads in prebuild_jobs(cfg):
            torch.set_num_threads(threads)  # part of the package's key
            out[label] = package_path(model, branch_free, batch, dtype, network)
    finally:
        torch.set_num_threads(before)
    return out
