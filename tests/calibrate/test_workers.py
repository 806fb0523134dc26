"""The work that splits by clip runs side by side in worker processes and gives what it gives
inline: the jobs' results in their order, a job's error raised in the caller, and the same
calibration to the last bit (calibrate.workers, calibrate.fit)."""

import operator

import pytest
import torch

from calibrate.bags import read_clip
from calibrate.fit import Budget, calibrate
from calibrate.workers import Workers
from perception import PerceptionConfig
from service.config import ServiceConfig

from .conftest import LENGTH, MASS, N


@pytest.mark.slow
def test_jobs_come_back_in_their_order_and_a_jobs_error_is_raised_in_the_caller():
    items = [8.0, 4.0, 2.0, 1.0, 0.5]
    with Workers(2) as pool:
        assert pool.map(operator.truediv, items, 2.0) == [4.0, 2.0, 1.0, 0.5, 0.25]
        with pytest.raises(ZeroDivisionError):
            pool.map(operator.truediv, items, 0.0)
        assert pool.map(operator.truediv, [], 2.0) == []
    assert Workers(1).map(operator.truediv, items, 2.0) == [4.0, 2.0, 1.0, 0.5, 0.25]
    with pytest.raises(ValueError, match="at least 1"):
        Workers(0)


@pytest.mark.slow  # a whole calibration: tens of seconds
def test_a_calibration_with_two_workers_is_the_calibration_without(clips):
    """Two rounds (tracking passes, the damping search, held-out fits, the parameter ranges all
    through the workers): the same tracks, fits and model, exactly."""
    cfg = ServiceConfig(grippers=clips.grippers)
    clip_list = [read_clip(b, cfg) for b in clips.bags]
    budget = Budget(
        iterations=3, refine_iterations=2, rounds=2, horizon=20, batch=2, curriculum=(), damping_horizon=40
    )

    def run(workers):
        return calibrate(
            clip_list,
            LENGTH,
            MASS,
            cfg.grippers,
            PerceptionConfig(),
            n_vertices=N,
            budget=budget,
            progress=False,
            workers=workers,
        )

    alone, pooled = run(1), run(2)
    assert [r.held_out_fit_m for r in pooled.rounds] == [r.held_out_fit_m for r in alone.rounds]
    assert len(alone.rounds) >= 2 and alone.rounds[1].train["damping"] is not None
    assert [t.name for t in pooled.tracks] == [t.name for t in alone.tracks]
    for a, b in zip(alone.tracks, pooled.tracks, strict=True):
        assert (a.positions == b.positions).all()
    assert pooled.parameter_ranges == alone.parameter_ranges
    for (name, a), (_, b) in zip(
        alone.model.state_dict().items(), pooled.model.state_dict().items(), strict=True
    ):
        assert torch.equal(a, b), name
