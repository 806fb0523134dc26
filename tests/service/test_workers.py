"""Worker processes: the tracker crosses the process boundary intact, a job gives the same answer in
a child process as inline, errors come back as errors, and a hung job restarts the child."""

import json

import numpy as np
import pytest

from service import messages as M
from service import predict_pool
from service.estimator import Estimator
from service.workers import InlineWorker, WorkerError, WorkerProcess, pack_tracker, unpack_tracker
from tests.service.conftest import make_config
from tests.service.open_loop_tracker import OpenLoopTracker

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


@pytest.mark.slow
def test_predict_in_child_process_equals_inline(est, child, model):
    plans = np.tile(GOOD, (2, 4, 1, 1))
    plans[1, :, :, 2] -= 0.01
    body = json.dumps({"plans": plans.tolist()}).encode()
    ok_c, reply_c = predict_pool.handle(est, body, child)
    ok_i, reply_i = predict_pool.handle(est, body, InlineWorker(model, est.cfg))
    assert ok_c and ok_i
    assert json.loads(reply_c) == json.loads(reply_i)
    assert np.array(json.loads(reply_c)["vertices"]).shape == (2, 4, 13, 3)


def test_a_cloud_fused_in_the_child_process_equals_inline(child, model, sim_stream):
    """perception's tracker, taken back to a kept tick's moment and corrected with a rendered cloud:
    the child returns the tracker the inline worker returns, bit for bit (state, velocities, the
    recovery counts)."""
    from service.estimator import Estimator as Est
    from service.workers import pack_moment
    from tests.service.conftest import FakeClock

    _, stream = sim_stream
    e = Est(make_config(pose_delay_s=0), model, clock=FakeClock())
    inline, fused = InlineWorker(model, e.cfg), 0
    for m in stream:
        if m.name == "camera_info":
            e.on_camera_info(m.data)
        elif m.name == "camera_pose":
            e.on_camera_pose(m.data)
        elif m.name == "ee_poses":
            assert e.on_poses(m.data)
            e.tick(m.log_time)
        elif m.name == "points" and e.tick_index > 2:
            cloud = e.decode_cloud(m.data)
            blob, moment = pack_tracker(e.tracker, model), pack_moment(e.fusion_tick(cloud.stamp_ns).moment)
            a = unpack_tracker(child.call("fuse", blob, cloud, moment, timeout=120)[0], model)
            b = unpack_tracker(inline.call("fuse", blob, cloud, moment)[0], model)
            for f in ("x", "v", "theta"):
                assert np.array_equal(getattr(a.state, f).numpy(), getattr(b.state, f).numpy())
            assert a.health.as_dict(0.01) == b.health.as_dict(0.01) and a.observed.any()
            e.tracker, fused = b, fused + 1
            if fused == 3:
                break
    assert fused == 3


def test_errors_come_back_and_the_child_keeps_serving(est, child):
    ok, reply = predict_pool.handle(est, b"{not json", child)
    assert not ok and json.loads(reply)["error"] == "bad_json"
    with pytest.raises(WorkerError, match=r"Error"):
        child.call("fuse", b"not a tracker", None)
    assert child.call("ping") is True


@pytest.mark.slow
def test_hung_job_times_out_and_restarts_the_child(child):
    with pytest.raises(WorkerError, match="longer than"):
        child.call("ping", 30.0, timeout=0.2)
    assert child.call("ping", timeout=60) is True


@pytest.mark.slow
def test_a_jobs_timeout_does_not_count_the_childs_start_up(model):
    """A fresh child imports torch and perception and loads the model (seconds; tens of seconds for
    a niced child on a busy machine) before it serves: a job's timeout starts once it is ready.
    Timed from the send, the first 1 s ping of a new or restarted child would time out."""
    w = WorkerProcess(model, make_config(), "test-cold", nice=5)
    try:
        assert w.call("ping", timeout=1.0) is True
        before = w.pid
        w.restart()
        assert w.call("ping", timeout=1.0) is True and w.pid != before
    finally:
        w.close()


@pytest.mark.slow
def test_restart_gives_a_fresh_child_that_serves(child):
    before = child.pid
    child.restart()
    assert child.pid != before and child.call("ping", timeout=60) is True


def test_compiled_step_is_not_pickled_but_resolved_on_each_side(model):
    """A tracker running on a compiled step crosses to a worker without it (each process compiles
    its own) and comes back with the receiving side's step."""
    from deform.compiled import CompiledStep
    from perception import Tracker

    x0 = np.stack([np.linspace(-0.4, 0.4, model.n), np.zeros(model.n), np.full(model.n, 0.5)], axis=1)
    ours, theirs = CompiledStep(model, enabled=False), CompiledStep(model, enabled=False)
    tracker = Tracker(model, step_fn=ours)
    tracker.initialize_from_frames(x0, x0)
    blob = pack_tracker(tracker, model)
    assert len(blob) < 20_000  # state only: no model, no compiled code
    assert unpack_tracker(blob, model).step_fn is None  # a worker without a compiled step: model.step
    back = unpack_tracker(blob, model, theirs)
    assert back.step_fn is theirs and back.model is model
    calls = []
    back.step_fn = lambda state, grip: calls.append(1) or model.step(state, grip)
    back.step(x0[[0, 1, -2, -1]])
    assert calls == [1]


def test_use_step_switches_the_tracker_and_status(model):
    e = Estimator(make_config(), model, OpenLoopTracker(model, settle_steps=30))
    assert e.status()["step"] == "eager"
    e.on_poses(M.pose_array(T0, GOOD))
    e.tick(T0)  # initialisation: no step
    calls = []
    e.use_step(lambda state, grip: calls.append(1) or model.step(state, grip))
    assert e.status()["step"] == "compiled"
    e.tick(T0 + 10_000_000)
    assert calls == [1]


@pytest.mark.slow
def test_a_worker_can_run_at_lower_cpu_priority(model):
    """The fusion worker runs ``workers.fusion_nice`` below the service so that predict gets the
    core first on a busy machine; a worker started without it keeps the service's priority."""
    import os

    low = WorkerProcess(model, make_config(), "test-low", nice=5)
    try:
        assert low.call("ping") is True  # the child is up and has applied its nice value
        assert os.getpriority(os.PRIO_PROCESS, low.pid) == os.getpriority(os.PRIO_PROCESS, 0) + 5
    finally:
        low.close()


@pytest.mark.slow
def test_the_service_lowers_its_fusion_worker_not_predict(model):
    import os

    from service.node import Service

    svc = Service(make_config(workers={"processes": True, "compile_predict": False}), model=model)
    try:
        assert svc.fusion_worker.call("ping") and svc.predict_worker.call("ping")
        base = os.getpriority(os.PRIO_PROCESS, 0)
        assert (
            os.getpriority(os.PRIO_PROCESS, svc.fusion_worker.pid)
            == base + svc.cfg.workers.fusion_nice
            > base
        )
        # the other predict processes start at predict's warm-up (after the service's start-up)
        assert len(svc.predict_worker.workers) == 1
        svc.predict_worker.call("warmup", [])  # not compiled here: says False
        assert svc.predict_worker.started.wait(60)  # the second process, in the background
        assert len(svc.predict_worker.workers) == svc.cfg.workers.predict_processes == 2
        for w in svc.predict_worker.workers:
            assert os.getpriority(os.PRIO_PROCESS, w.pid) == base
    finally:
        svc.fusion_worker.close()
        svc.predict_worker.close()


@pytest.mark.slow
def test_prestarted_workers_serve_the_service_with_its_model_and_are_used_once(model):
    """`deform-service run` starts its workers before importing torch (so the imports overlap):
    the service then takes them, sends its model, and they answer as any worker; a second service
    gets new ones, and a restart hands the model to the new child again."""
    import os

    from service.node import Service
    from service.workers import _PRESTARTED, prestart

    cfg = make_config(workers={"processes": True, "compile_predict": False, "predict_threads": 2})
    prestart(cfg)
    early = {w.name: w.pid for w in _PRESTARTED.values()}
    svc = Service(cfg, model=model)
    try:
        # fusion and the first predict process were started early; the second starts at warm-up
        pids = {svc.fusion_worker.pid, *(w.pid for w in svc.predict_worker.workers)}
        assert pids == set(early.values()) and len(pids) == 2
        svc.predict_worker.call("warmup", [])
        assert svc.predict_worker.started.wait(60) and len(svc.predict_worker.workers) == 2
        assert not _PRESTARTED  # handed out once
        assert svc.fusion_worker.call("ping") and svc.predict_worker.call("ping")
        assert os.getpriority(os.PRIO_PROCESS, svc.fusion_worker.pid) > os.getpriority(os.PRIO_PROCESS, 0)
        # each worker on its own thread count (what its compiled packages are built for)
        assert [w.call("threads") for w in svc.predict_worker.workers] == [cfg.workers.predict_threads] * 2
        assert svc.fusion_worker.call("threads") == cfg.torch_threads
        svc.predict_worker.restart()
        assert not {w.pid for w in svc.predict_worker.workers} & set(early.values())
        assert svc.predict_worker.call("ping")
        assert svc.predict_worker.call("threads") == cfg.workers.predict_threads  # kept on a restart
    finally:
        svc.fusion_worker.close()
        svc.predict_worker.close()


def test_share_sizes_are_what_each_predict_process_rolls_out():
    """Small requests go whole to the first process; a split one gives each its block."""
    from service.predict_pool import share_sizes

    assert share_sizes([64, 256, 1001], 2, 128) == [[64, 128, 500], [128, 501]]
    assert share_sizes([64, 256], 1, 128) == [[64, 256]]
    assert share_sizes([], 2, 128) == [[], []]


def test_the_first_predict_process_defers_the_rescue_graph_to_the_second():
    """With a second process to start, the first warms up without the rescue graph (predict is
    ready a package build sooner on a cold start); the second builds it at its own warm-up, and the
    first loads it after that. Alone, the first warms it up itself."""
    import time

    from service.predict_pool import PredictPool

    class Fake:
        pid = 0

        def __init__(self, log):
            self.log = log

        def call(self, op, *args, timeout=None):
            self.log.append((self, op, *args))
            return True

        def close(self):
            pass

    log = []
    first, second = Fake(log), Fake(log)
    pool = PredictPool([first], split_min_plans=128, more=[lambda: second])
    assert pool.call("warmup", [64, 1024]) is True
    assert log[0] == (first, "warmup", [64, 512], False)  # predict is ready here
    assert pool.started.wait(5)
    deadline = time.monotonic() + 5
    while (first, "warmup_rescue") not in log and time.monotonic() < deadline:
        time.sleep(0.01)
    assert log[1:] == [(second, "warmup", [512]), (second, "warmup_rescue"), (first, "warmup_rescue")]
    log.clear()
    alone = PredictPool([first], split_min_plans=128)
    alone.call("warmup", [64])
    assert log == [(first, "warmup", [64], True)]


def test_a_worker_whose_model_file_is_gone_exits_quietly(tmp_path):
    """A pool's late-starting worker can be sent the path of a model its parent has removed at exit
    (``make demo`` printed that worker's traceback): it returns, and its end of the socket closes."""
    import socket
    import threading
    from multiprocessing.connection import Connection

    from service.workers import _serve

    ours, theirs = socket.socketpair()
    parent, child = Connection(ours.detach()), Connection(theirs.detach())
    parent.send(("model", (str(tmp_path / "gone" / "model.pt"),)))
    errors = []

    def run():
        try:
            _serve(child, make_config(), 0, 1)
        except Exception as exc:  # the behaviour under test: nothing escapes
            errors.append(exc)
        finally:
            child.close()

    import torch

    threads = torch.get_num_threads()  # _serve sets this process's (it is the child's own elsewhere)
    worker = threading.Thread(target=run)
    worker.start()
    worker.join(timeout=120)
    torch.set_num_threads(threads)
    assert not worker.is_alive() and errors == []
    with pytest.raises(EOFError):  # the parent sees the worker gone, as when a child exits
        parent.recv()
