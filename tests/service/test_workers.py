"""Worker processes: the tracker crosses the process boundary intact, a job gives the same answer in
a child process as inline, errors come back as errors, and a hung job restarts the child."""
import json

import numpy as np
import pytest

from service import messages as M
from service import predict
from service.estimator import Estimator
from service.tracking import OpenLoopTracker
from service.workers import InlineWorker, WorkerError, WorkerProcess, pack_tracker, unpack_tracker
from tests.service.conftest import make_config

GOOD = np.array([[-0.4, 0, 0.5, 0, 0, 0, 1], [0.4, 0, 0.5, 0, 0, 1, 0]], dtype=float)
T0 = 1_700_000_000 * 10**9


@pytest.fixture(scope="module")
def est(model):
    e = Estimator(make_config(), model, OpenLoopTracker(model, settle_steps=30))
    e.on_poses(M.pose_array(T0, GOOD))
    e.tick(T0)
    return e


@pytest.fixture(scope="module")
def child(model):
    w = WorkerProcess(model, make_config(), "test-worker")
    yield w
    w.close()


def test_tracker_round_trip_keeps_state_and_shares_model(est, model):
    copy = unpack_tracker(pack_tracker(est.tracker, model), model)
    assert copy.model is model
    assert np.array_equal(copy.state.x.numpy(), est.tracker.state.x.numpy())
    copy.step(est.estimate.grip)  # the copy moves, the original does not
    assert not np.array_equal(copy.state.x.numpy(), est.tracker.state.x.numpy())


def test_predict_in_child_process_equals_inline(est, child, model):
    plans = np.tile(GOOD, (2, 4, 1, 1))
    plans[1, :, :, 2] -= 0.01
    body = json.dumps({"plans": plans.tolist()}).encode()
    ok_c, reply_c = predict.handle(est, body, child)
    ok_i, reply_i = predict.handle(est, body, InlineWorker(model, est.cfg))
    assert ok_c and ok_i
    assert json.loads(reply_c) == json.loads(reply_i)
    assert np.array(json.loads(reply_c)["vertices"]).shape == (2, 4, 13, 3)


def test_errors_come_back_and_the_child_keeps_serving(est, child):
    ok, reply = predict.handle(est, b"{not json", child)
    assert not ok and json.loads(reply)["error"] == "bad_json"
    with pytest.raises(WorkerError, match="UnpicklingError|Error"):
        child.call("fuse", b"not a tracker", None)
    assert child.call("ping") is True


def test_hung_job_times_out_and_restarts_the_child(child):
    with pytest.raises(WorkerError, match="longer than"):
        child.call("ping", 30.0, timeout=0.2)
    assert child.call("ping", timeout=60) is True
