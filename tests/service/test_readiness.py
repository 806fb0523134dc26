"""Predict's readiness is told truthfully: ``not_ready`` (NotReady) only while its warm-up runs; a
failed warm-up is in status (``predict_failed``, the reason) within a second and in every predict
reply (``predict_failed``: ServiceFailed naming it); it is retried once on the eager step, which
status and the log say.

Why (issue 52): DLO4's float32 step failed predict's warm-up; the service logged it once and went on
answering "predict is being prepared (compiling)" to every request, which never became true.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
import torch

from deform.terms.library import ExternalForce
from service import messages as M
from service.client import NotReady, ServiceFailed, ShapeClient, error_from_reply
from service.geometry import poses_from_vertices
from service.node import PredictReadiness, Service
from service.workers import InlineWorker, JobContext, WorkerError
from tests.service.conftest import make_config, wait_for
from tests.service.test_every_model import Feeder


def _wind_in_float64(self, x, v, mass, rest):
    """ExternalForce.acceleration before the fix of issue 52: a float64 field whatever the state."""
    return torch.cat([self.field(), self.log_strength.new_zeros(1)]).expand_as(x)


def _plans(rope, cfg, plans=2, steps=5):
    _, x, _ = rope.vertices()
    return np.tile(poses_from_vertices(x.astype(float), cfg.grippers), (plans, steps, 1, 1))


class _Query:
    """A stand-in for a Zenoh query: keeps what it is answered."""

    attachment = None
    key_expr = "deform/rod1/predict"

    def __init__(self):
        self.errors, self.replies = [], []

    def reply_err(self, payload):
        self.errors.append(payload)

    def reply(self, key, payload, **kwargs):
        self.replies.append(payload)


# ----- protocol ---------------------------------------------------------------------------------
def test_each_readiness_is_its_own_reply_and_error_type():
    """A not started service (predict preparing), then as if its warm-up had failed: the JSON reply
    and the ROS 2 response say which, the client raises NotReady, then ServiceFailed."""
    from service.ros2_predict import PREDICT_SRV

    svc = Service(make_config(clock="message", workers={"processes": False, "compile_predict": False}))
    try:
        q = _Query()
        svc._on_predict_query(q)
        err = error_from_reply(q.errors[-1])
        assert isinstance(err, NotReady) and err.reason == "not_ready" and "being prepared" in err.detail
        svc.predict = PredictReadiness("retrying_eager", failed="RuntimeError: no compiler")
        svc._on_predict_query(q)
        err = error_from_reply(q.errors[-1])
        assert isinstance(err, ServiceFailed) and err.reason == "predict_failed"
        assert "RuntimeError: no compiler" in err.detail and "retrying in eager mode" in err.detail
        svc.predict = PredictReadiness(
            "failed", failed="RuntimeError: no compiler; the eager retry failed too"
        )
        svc._on_predict_query(q)
        err = error_from_reply(q.errors[-1])
        assert isinstance(err, ServiceFailed) and "eager retry failed too" in str(err)
        svc._on_ros_predict_query(q)
        text = M.decode(q.replies[-1], f"{PREDICT_SRV}_Response").error
        assert text.startswith("predict_failed: predict warm-up failed: RuntimeError: no compiler")
        rejected = svc.est.status()["rejected"]
        assert rejected["predict:not_ready"] == 1 and rejected["predict:predict_failed"] == 3
    finally:
        svc.stop()


# ----- a failed warm-up ---------------------------------------------------------------------------
@pytest.mark.zenoh
@pytest.mark.slow
def test_a_failed_warm_up_is_in_status_within_a_second_and_in_every_predict_reply(
    endpoint, monkeypatch, caplog
):
    """DLO4 with the dtype bug of issue 52 put back: the loop tracks (float64), predict's float32
    step fails its warm-up and the eager retry; status says so within 1 s, every predict names it."""
    monkeypatch.setattr(ExternalForce, "acceleration", _wind_in_float64)
    failed_at = []
    check = JobContext.check_step

    def timed_check(ctx):
        try:
            check(ctx)
        except Exception:
            failed_at.append(time.monotonic())
            raise

    monkeypatch.setattr(JobContext, "check_step", timed_check)
    cfg = make_config(endpoint, rod="DLO4", workers={"processes": False, "compile_predict": False})
    with caplog.at_level(logging.INFO, "deform.service"), Service(cfg):
        with ShapeClient(cfg.namespace, connect=[endpoint], timeout_s=5.0) as rope:
            seen = None
            deadline = time.monotonic() + 60
            while seen is None and time.monotonic() < deadline:
                status = rope.status()
                if status["predict_failed"] is not None:
                    seen = time.monotonic()
                else:
                    time.sleep(0.01)
            assert seen is not None and failed_at, "no failure in status"
            assert seen - failed_at[0] < 1.0
            assert "expected scalar type Float but found Double" in status["predict_failed"]
            assert status["predict_ready"] is False and "predict" in status["not_ready"]
            assert wait_for(lambda: rope.status()["predict_state"] == "failed")
            status = rope.status()
            assert status["failed"] == ["predict"] and "eager retry failed too" in status["predict_failed"]
            with Feeder(rope):
                assert wait_for(lambda: rope.status()["ticks"] > 3)  # the loop serves regardless
                plans = _plans(rope, cfg)
                for _ in range(3):
                    with pytest.raises(ServiceFailed) as err:
                        rope.predict(plans)
                    assert err.value.reason == "predict_failed"
                    assert "expected scalar type Float but found Double" in err.value.detail
    log = caplog.text
    assert "predict warm-up failed" in log and "retrying in eager mode" in log
    assert "predict unavailable" in log and "being prepared" not in log


@pytest.mark.zenoh
@pytest.mark.slow
def test_a_warm_up_that_cannot_compile_is_retried_in_eager_mode(endpoint, monkeypatch, caplog):
    """The compiled warm-up fails (as a compiler that crashes would); the eager step works: predict
    answers in eager mode, and status and the log say why."""
    from deform.compiled import RolloutStep

    def no_compiler(self, *args, **kwargs):
        raise RuntimeError("the C++ compiler crashed")

    monkeypatch.setattr(RolloutStep, "warmup", no_compiler)
    cfg = make_config(endpoint, workers={"processes": False, "compile_predict": True, "predict_warmup": [4]})
    with caplog.at_level(logging.INFO, "deform.service"), Service(cfg):
        with ShapeClient(cfg.namespace, connect=[endpoint], timeout_s=5.0) as rope:
            assert wait_for(lambda: rope.status()["predict_ready"], 60)
            status = rope.status()
            assert status["predict_state"] == "ready" and status["predict_mode"] == "eager"
            assert "the C++ compiler crashed" in status["predict_failed"] and status["failed"] == []
            with Feeder(rope):
                assert wait_for(lambda: rope.status()["ticks"] > 3)
                assert rope.predict(_plans(rope, cfg)).shape[:2] == (2, 5)
    assert "retrying in eager mode" in caplog.text
    assert "predict ready in eager mode, after its warm-up failed (WorkerError" not in caplog.text
    assert (
        "predict ready in eager mode, after its warm-up failed (RuntimeError: the C++ compiler crashed)"
        in (caplog.text)
    )


def test_the_eager_retry_warms_every_predict_process(model, monkeypatch):
    """A pool whose first process failed its warm-up keeps the others for the retry, which starts
    them on the eager step too."""
    from deform.compiled import RolloutStep
    from service.predict_pool import PredictPool

    def no_compiler(self, *args, **kwargs):
        raise RuntimeError("the C++ compiler crashed")

    monkeypatch.setattr(RolloutStep, "warmup", no_compiler)
    cfg = make_config(workers={"processes": False, "compile_predict": True, "predict_processes": 2})
    first, second = InlineWorker(model, cfg), InlineWorker(model, cfg)
    pool = PredictPool([first], split_min_plans=2, more=[lambda: second])
    with pytest.raises(WorkerError, match="compiler crashed"):
        pool.call("warmup", [4])
    assert not pool.started.is_set() and len(pool.workers) == 1
    assert pool.call("warmup_eager") is False
    assert pool.started.wait(30) and pool.workers == [first, second]
    assert not first.ctx.step.fast.enabled and not second.ctx.step.fast.enabled
