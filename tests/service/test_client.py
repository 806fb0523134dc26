"""service.client against a running service on loopback: vertices, the stream, predict, status and
typed errors round-trip; the client imports no torch."""

import subprocess
import sys
import threading

import numpy as np
import pytest

from service import messages as M
from service.client import BadRequest, NoReply, NotReady, ServiceError, ShapeClient, error_from_reply
from service.geometry import poses_from_vertices
from service.node import Service
from tests.service.conftest import make_config
from tests.service.test_zenoh import GOOD, wait_matched

pytestmark = pytest.mark.zenoh


def test_error_replies_map_to_typed_exceptions():
    assert isinstance(error_from_reply(b'{"error": "no_estimate"}'), NotReady)
    err = error_from_reply(b'{"error": "bad_shape", "detail": "plans must be (P, S, 2, 7)"}')
    assert isinstance(err, BadRequest) and err.reason == "bad_shape" and "(P, S, 2, 7)" in str(err)
    assert error_from_reply(b"not json").reason == "unknown"


def test_client_module_imports_no_torch():
    code = "import sys, service.client; assert 'torch' not in sys.modules, 'torch imported'"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True).returncode == 0


def test_round_trip_vertices_stream_predict_status(model, endpoint):
    cfg = make_config(
        endpoint, namespace="deform/client", workers={"processes": False, "compile_predict": False}
    )
    with Service(cfg, model=model), ShapeClient("deform/client", connect=[endpoint], timeout_s=5.0) as rope:
        assert rope.status()["mode"] == "waiting"
        for _ in range(200):  # predict answers "not ready" at once until its warm-up is done
            if rope.status()["predict_ready"]:
                break
            threading.Event().wait(0.05)
        assert rope.status()["not_ready"] in ([], ["step"])
        with pytest.raises(NotReady):
            rope.vertices()
        poses = rope.session.declare_publisher("deform/client/ee_poses")
        assert wait_matched(rope.session, ["deform/client/ee_poses"])
        got = threading.Event()
        seen = []
        rope.subscribe(lambda stamp, x, observed: (seen.append((stamp, x.shape, observed.shape)), got.set()))
        stop = threading.Event()

        def feed():
            k = 0
            while not stop.is_set():
                poses.put(M.pose_array(10**9 + k * 10**7, GOOD))
                k += 1
                stop.wait(0.01)

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:
            assert got.wait(20.0)
            stamp, x, observed = rope.vertices()
            assert x.shape == (model.n, 3) and observed.shape == (model.n,) and stamp > 0
            assert seen[0][1] == (model.n, 3)
            base = poses_from_vertices(x.astype(float), cfg.grippers)
            plans = np.tile(base, (3, 20, 1, 1))
            plans[:, :, :, 2] += (
                np.linspace(0.0, 0.05, 20)[None, :, None] * np.array([0, 1, 2])[:, None, None]
            )
            full = rope.predict_full(plans)
            assert full.vertices.shape == (3, 20, model.n, 3) and full.overstretched.shape == (3,)
            # plan 0 holds still, plan 2 lifts twice as far as plan 1: the rope follows in that order
            lift = full.vertices[:, -1, :, 2].mean(-1) - full.vertices[0, -1, :, 2].mean()
            assert 0 < lift[1] < lift[2]
            assert rope.predict(plans).shape == full.vertices.shape  # from a later estimate: not equal
            final = rope.predict_full(plans, steps="final", binary=False, request_id="p1")
            assert final.vertices.shape == (3, 1, model.n, 3) and final.steps.tolist() == [20]
            assert final.id == "p1" and full.steps.tolist() == list(range(1, 21))
            with pytest.raises(ValueError):  # refused before anything is sent
                rope.predict_full(plans, plan_dtype="float16")
            wide = rope.predict_full(plans, plan_dtype="float64")
            assert wide.vertices.shape == full.vertices.shape
            costs = rope.costs(plans, {"goal": full.vertices[2, -1]})
            assert costs.shape == (3,) and int(np.argmin(costs)) == 2
            with pytest.raises(BadRequest) as bad:
                rope._get("predict", b"{not json", 10.0)
            assert bad.value.reason == "bad_json"
            status = rope.status()
            assert status["mode"] != "waiting" and status["counts"]["predictions"] >= 2
        finally:
            stop.set()
            feeder.join()


def test_no_service_is_a_typed_no_reply(endpoint):
    with ShapeClient("deform/nobody", connect=[endpoint], timeout_s=0.5) as rope:
        with pytest.raises(NoReply) as err:
            rope.status()
        assert isinstance(err.value, ServiceError)


def test_predict_during_warm_up_is_refused_at_once(model):
    """Until the predict worker is ready the query is answered "not ready" at once, not after the
    compile; the client raises NotReady."""
    cfg = make_config(clock="message", workers={"processes": False, "compile_predict": False})
    svc = Service(cfg, model=model)  # not started: predict is not ready
    replies = []
    query = type("Query", (), {"reply_err": lambda self, payload: replies.append(payload)})()
    assert not svc.predict_ready
    svc._on_predict_query(query)
    err = error_from_reply(replies[0])
    assert isinstance(err, NotReady) and err.reason == "not_ready"
    assert svc.predict_queue.empty()
    status = svc.est.status()
    assert status["rejected"]["predict:not_ready"] == 1
    svc.stop()
