"""The Zenoh side: subscribers, the 100 Hz loop thread, the vertices publisher and the queryables.

Two clocks. ``wall``: a fixed-rate timer ticks with the gripper poses sampled by their stamps, clouds
are fused by a worker. ``message``: the gripper messages tick every ``dt`` of their own stamps
(:class:`service.pose_timeline.PoseGrid`) and everything is handled on one thread in send order
(:mod:`service.ordering`), so a replay gives the same output bit for bit.
"""

from __future__ import annotations

import gc
import json
import logging
import os
import queue
import sys
import threading
import time
from dataclasses import dataclass

import torch
import zenoh

from service import messages as M
from service import predict_codec, predict_pool
from service.config import ServiceConfig, ZenohSettings
from service.estimator import Estimator
from service.fusion import FusionWorker
from service.ordering import SequenceBuffer, decode_order
from service.stats import Stats
from service.workers import WorkerError, fusion_worker_spec, make_worker

log = logging.getLogger("deform.service")
INPUT_TYPES = {
    "ee_poses": M.POSE_ARRAY,
    "points": M.POINT_CLOUD2,
    "camera_info": M.CAMERA_INFO,
    "camera_pose": M.POSE_STAMPED,
}
INPUTS = tuple(INPUT_TYPES)


def zenoh_config(z: ZenohSettings) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(z.mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(z.multicast_scouting))
    if z.connect:
        conf.insert_json5("connect/endpoints", json.dumps(z.connect))
        # keep retrying forever so the service reconnects when the router restarts
        conf.insert_json5("connect/timeout_ms", json.dumps({"router": -1, "peer": -1, "client": -1}))
    if z.listen:
        conf.insert_json5("listen/endpoints", json.dumps(z.listen))
    return conf


def open_session(z: ZenohSettings) -> zenoh.Session:
    return zenoh.open(zenoh_config(z))


def set_realtime_priority(priority: int | None) -> bool:
    """Run the calling thread under SCHED_FIFO at ``priority`` (Linux) so that worker processes and
    other programs cannot preempt a tick; usual practice for robot control loops. Needs root or
    CAP_SYS_NICE (or an rtprio limit): without it the loop runs at normal priority, with a warning."""
    if not priority:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (AttributeError, PermissionError, OSError) as exc:
        log.warning(
            "real-time priority %s not available (%s): the loop runs at normal priority", priority, exc
        )
        return False


@dataclass(frozen=True)
class PredictReadiness:
    """Where predict stands; replaced whole, so that a status or a query reads one consistent value.

    ``state``: ``preparing`` (the warm-up runs: checking the model's step, compiling or loading the
    compiled steps), ``ready`` (answers), ``retrying_eager`` (the warm-up failed; the eager step is
    being checked) or ``failed`` (the eager retry failed too: predict cannot answer). ``mode``: how
    a ready predict runs (``compiled``, ``eager``, ``compiles on first use``). ``failed``: the
    reason of a failed warm-up (kept once ready in eager mode, to say why it is eager)."""

    state: str = "preparing"
    mode: str | None = None
    failed: str | None = None
    since: float = 0.0  # time.monotonic() of the last change

    @property
    def ready(self) -> bool:
        return self.state == "ready"

    def detail(self) -> str:
        """What a refused predict is told (NotReady while preparing, ServiceFailed after a failure)."""
        if self.state == "preparing":
            return (
                f"predict is being prepared (warm-up running for {time.monotonic() - self.since:.0f} s: "
                "checking the model's step, compiling or loading the compiled steps); "
                "status.predict_state says when it is ready or has failed"
            )
        if self.state == "retrying_eager":
            return f"predict warm-up failed ({self.failed}); retrying in eager mode"
        return f"predict warm-up failed: {self.failed}"


def _failure(exc: Exception) -> str:
    """A warm-up's exception as one line (a worker's error already names the remote exception)."""
    text = str(exc) if isinstance(exc, WorkerError) else f"{type(exc).__name__}: {exc}"
    return text.splitlines()[0] if text else type(exc).__name__


class Service:
    """One rod under one namespace. ``start()`` declares everything and starts the threads."""

    def __init__(
        self,
        cfg: ServiceConfig,
        model=None,
        tracker=None,
        session: zenoh.Session | None = None,
        rerun_logger=None,
    ):
        torch.set_num_threads(cfg.torch_threads)
        # the loop shares the GIL with fusion and Zenoh callbacks: hand it over every 0.5 ms, not 5 ms,
        # so a tick waits at most that long for the interpreter
        sys.setswitchinterval(min(sys.getswitchinterval(), 0.0005))
        if model is None:
            from deform import load_model

            model = load_model(cfg.rod)
        self.cfg = cfg
        self.stats = Stats(cfg.namespace)
        self.est = Estimator(cfg, model, tracker, self.stats)
        self.session = session
        self._own_session = session is None
        self.rerun = rerun_logger
        if self.rerun is None and cfg.rerun.mode != "off":
            from service.rerun_log import RerunLogger

            self.rerun = RerunLogger(cfg.rerun, cfg.namespace, self.stats)
        # child processes (or inline workers) for cloud fusion (wall clock only: the message clock
        # fuses in order, in the loop, for bit-exact replays) and for predict
        fusion_spec = fusion_worker_spec(cfg)
        self.fusion_worker = None if fusion_spec is None else make_worker(model, cfg, *fusion_spec)
        self.predict_running = threading.Event()  # fusion defers to it (workers.fusion_yields_to_predict_s)
        self.fusion = (
            None
            if self.est.message_clock
            else FusionWorker(
                self.est,
                self.fusion_worker,
                yield_to=self.predict_running,
                max_yield_s=cfg.workers.fusion_yields_to_predict_s,
            )
        )
        self.predict_worker = predict_pool.make_predict_pool(model, cfg)
        self.inbox: queue.Queue = queue.Queue(maxsize=4096)
        self.predict_queue: queue.Queue = queue.Queue(maxsize=4)
        self.latest_payload: bytes | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._decl: list = []
        self.ros_node = None  # interface ros2: the node whose tokens announce the topics
        self.shape_pub = None  # {ns}/shape, declared by start()
        self._last_logged_cloud = None
        self._idle = True
        self.predict = PredictReadiness(since=time.monotonic())
        self.step_ready = (
            not cfg.compile_step or self.est.message_clock
        )  # the loop's step compiled (or not wanted)

    # ----- lifecycle ---------------------------------------------------------------------------
    def start(self) -> Service:
        if self.session is None:
            self.session = open_session(self.cfg.zenoh)
        s, key = self.session, self.cfg.key
        cc = zenoh.CongestionControl.BLOCK if self.est.message_clock else zenoh.CongestionControl.DROP
        if self.cfg.interface == "ros2":  # rmw_zenoh's keys and tokens (service/ros2.py)
            from service.ros2 import Node

            self.ros_node = Node(s, self.cfg.ros2.node, "/" + self.cfg.namespace, self.cfg.ros2.domain_id)
            topic = self.cfg.topic
            self.pub = self.ros_node.publisher(topic("vertices"), M.POINT_CLOUD2, congestion_control=cc)
            self.shape_pub = self.ros_node.publisher(topic("shape"), M.MARKER, congestion_control=cc)
            for name, typename in INPUT_TYPES.items():
                self.ros_node.subscription(topic(name), typename, self._on_input(name))
            from service.ros2_predict import PREDICT_SRV

            self.ros_node.service(topic("predict"), PREDICT_SRV, self._on_ros_predict_query)
        else:
            self.pub = s.declare_publisher(key("vertices"), congestion_control=cc)
            self.shape_pub = s.declare_publisher(key("shape"), congestion_control=cc)
            self._decl += [self.pub, self.shape_pub]
            for name in INPUTS:
                self._decl.append(s.declare_subscriber(key(name), self._on_input(name)))
        # queries stay on plain keys in both interfaces (ShapeClient, service/client.py)
        self._decl.append(s.declare_queryable(key("vertices"), self._on_vertices_query))
        self._decl.append(s.declare_queryable(key("status"), self._on_status_query))
        self._decl.append(s.declare_queryable(key("predict"), self._on_predict_query))
        if self.rerun is not None:
            self.rerun.start()
        if self.fusion is not None:
            self.fusion.start()
        self._warm = threading.Thread(target=self._warmup, name=f"warmup[{self.cfg.namespace}]", daemon=True)
        self._warm.start()
        if self.cfg.compile_step and not self.est.message_clock:
            # importing the compiler's runtime takes the interpreter lock for a second or two: done
            # here, before the loop runs, rather than in the compile thread beside it
            import torch._inductor  # noqa: F401

            import deform.compiled  # noqa: F401

            # not on the message clock: a replay must not depend on when compilation finished
            threading.Thread(
                target=self._compile_step, name=f"compile[{self.cfg.namespace}]", daemon=True
            ).start()
        gc.freeze()  # torch and the model out of the collector's reach (see _compile_step)
        loop = self._message_loop if self.est.message_clock else self._wall_loop
        for target, name in ((loop, "loop"), (self._predict_loop, "predict")):
            t = threading.Thread(target=target, name=f"{name}[{self.cfg.namespace}]", daemon=True)
            t.start()
            self._threads.append(t)
        log.info(
            "[%s] service up (%s clock, %.0f Hz, tracker %s)",
            self.cfg.namespace,
            self.cfg.clock,
            self.cfg.rate_hz,
            type(self.est.tracker).__name__,
        )
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5)
        if self.fusion is not None:
            self.fusion.stop()
            self.fusion.join(timeout=5)
        for d in self._decl:
            try:
                d.undeclare()
            except Exception:
                pass
        if self.ros_node is not None:
            self.ros_node.close()
        for w in (self.fusion_worker, self.predict_worker):
            if w is not None:
                w.close()
        if self.rerun is not None:
            self.rerun.close()
        if self._own_session and self.session is not None:
            self.session.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    def drain(self, timeout: float = 30.0) -> bool:
        """Message clock: wait until every received message has been processed (tests, replay)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.inbox.unfinished_tasks == 0 and self._idle:
                return True
            time.sleep(0.005)
        return False

    @property
    def predict_ready(self) -> bool:
        """Whether predict answers now (:class:`PredictReadiness`)."""
        return self.predict.ready

    def _set_predict(self, state: str, mode: str | None = None, failed: str | None = None) -> None:
        self.predict = PredictReadiness(state, mode, failed, time.monotonic())

    def _warmup(self) -> None:
        """Check the model's step in predict's dtype, then compile the predict rollout for the
        configured plan counts (in the worker; queries are refused meanwhile). A failed warm-up is
        in status (``predict_failed``) and in every predict reply at once, and is retried once on
        the eager step."""
        ns = self.cfg.namespace
        sizes = self.cfg.workers.predict_warmup if self.cfg.workers.compile_predict else []
        t0 = time.perf_counter()
        try:
            active = self.predict_worker.call("warmup", list(sizes))
        except Exception as exc:
            reason = _failure(exc)
            self._set_predict("retrying_eager", failed=reason)
            log.error(
                "[%s] predict warm-up failed after %.1f s: %s; retrying in eager mode",
                ns,
                time.perf_counter() - t0,
                reason,
            )
            self._retry_eager(reason)
            return
        mode = "compiled" if active and sizes else "eager" if not active else "compiles on first use"
        self._set_predict("ready", mode)
        log.info("[%s] predict ready in %.1f s (%s)", ns, time.perf_counter() - t0, mode)

    def _retry_eager(self, reason: str) -> None:
        """After a failed warm-up: every predict process on the model's eager step, if that works."""
        ns = self.cfg.namespace
        try:
            self.predict_worker.call("warmup_eager")
        except Exception as exc:
            failed = f"{reason}; the eager retry failed too: {_failure(exc)}"
            self._set_predict("failed", failed=failed)
            log.error("[%s] predict unavailable: %s", ns, failed)
            return
        self._set_predict("ready", "eager", failed=reason)
        log.warning("[%s] predict ready in eager mode, after its warm-up failed (%s)", ns, reason)

    def _compile_step(self) -> None:
        """Compile the loop's step (B = 1) off the loop thread, then switch the tracker to it."""
        from deform.compiled import LOOP_BRANCH_FREE, CompiledStep

        t0 = time.perf_counter()
        if self.cfg.step_ahead_of_time:
            # built in a worker process (the fusion worker: idle until clouds come; else predict's),
            # loaded here from the cache: the loop never waits for the compiler's hold on the GIL
            from deform.aot import package_path

            # a warm cache is loaded below at once, without waiting for a worker to start
            if not package_path(self.est.model, LOOP_BRANCH_FREE, 1, torch.float64).exists():
                builder = self.fusion_worker or self.predict_worker
                try:
                    _, built = builder.call("build_step", list(LOOP_BRANCH_FREE), 1, timeout=900.0)
                    if built and builder is self.fusion_worker:
                        builder.restart()  # the compiler's memory goes with the old child
                except Exception as exc:
                    log.warning(
                        "[%s] loop step not built in a worker (%s): building here", self.cfg.namespace, exc
                    )
        with torch.no_grad():
            step = CompiledStep(
                self.est.model, branch_free=LOOP_BRANCH_FREE, ahead_of_time=self.cfg.step_ahead_of_time
            )
            if step.warmup((1,)) and not self._stop.is_set():
                self.est.use_step(step)
                log.info("[%s] loop step compiled in %.1f s", self.cfg.namespace, time.perf_counter() - t0)
            else:
                log.warning("[%s] loop step not compiled: running eagerly", self.cfg.namespace)
        # the compiled code's objects (hundreds of thousands) out of the collector's reach: a full
        # collection holds the interpreter lock, and the loop thread with it, for about 0.4 s
        gc.freeze()
        self.step_ready = True

    # ----- inputs ------------------------------------------------------------------------------
    def _on_input(self, name: str):
        if self.est.message_clock:

            def enqueue(sample):
                self._idle = False
                att = sample.attachment
                # a replay numbers its samples in the attachment; rmw_zenoh's attachment numbers
                # each publisher's samples alone, which says nothing about the order between topics
                ros2 = self.cfg.interface == "ros2"
                order = decode_order(att.to_bytes() if att is not None and not ros2 else None)
                self.inbox.put((name, sample.payload.to_bytes(), order))  # blocks: back-pressure, never loss

            return enqueue
        handlers = {
            "ee_poses": self.est.on_poses,
            "points": self.fusion.submit,
            "camera_info": self.est.on_camera_info,
            "camera_pose": self.est.on_camera_pose,
        }
        handler = handlers[name]

        def direct(sample):
            try:
                handler(sample.payload.to_bytes())
            except Exception:
                log.exception("input handler %s failed", name)

        return direct

    # ----- loops -------------------------------------------------------------------------------
    def _publish(self, estimate, t_start: float, initial: bool) -> None:
        payload = M.vertices_cloud(estimate.stamp_ns, estimate.x, estimate.observed, self.cfg.frame_id)
        self.latest_payload = payload  # first: a client that queries on receiving the sample finds it
        self.pub.put(payload)
        publish_s = time.perf_counter() - t_start  # tick start -> vertices handed over (the shape follows)
        if self.shape_pub is not None:
            self.shape_pub.put(
                M.shape_marker(estimate.stamp_ns, estimate.x, self.cfg.frame_id, self.cfg.namespace)
            )
        if not initial:
            self.stats.publish_s.add(publish_s)
        if self.rerun is not None:
            last = self.stats.step_s.latest()
            step = last * 1e3 if last is not None and not initial else None
            self.rerun.submit(
                "estimate", estimate, step, publish_s * 1e3, self.est.mode(), self.est.rope_status()
            )
            cloud = getattr(self.est, "last_cloud", None)
            if cloud is not None and cloud is not self._last_logged_cloud:
                self._last_logged_cloud = cloud
                self.rerun.submit("cloud", cloud)

    def _tick(self, stamp_ns: int) -> bool:
        t0 = time.perf_counter()
        self.stats.tick_starts.append(t0)
        initial = not self.est.initialized
        estimate = self.est.tick(stamp_ns)
        if estimate is None:
            return initial
        self._publish(estimate, t0, initial)
        return initial

    def _wall_loop(self) -> None:
        torch.set_num_threads(self.cfg.torch_threads)
        set_realtime_priority(self.cfg.realtime_priority)
        period = self.cfg.dt
        next_t = time.perf_counter()
        while not self._stop.is_set():
            delay = next_t - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            try:
                initial = self._tick(time.time_ns())
            except Exception:
                log.exception("tick failed")
                self.stats.count("tick_errors")
                initial = True
            end = time.perf_counter()
            self.stats.count("ticks")
            if end > next_t + period and not initial:
                self.stats.count("deadline_misses")
            next_t += period
            if end > next_t + period:  # more than a period behind: resynchronise rather than burst
                skipped = int((end - next_t) / period)
                next_t += skipped * period
                # the first estimate's static solve (a few hundred ms, once, before anything is
                # published) is counted apart: those ticks had nothing to publish late
                self.stats.count("ticks_skipped_initializing" if initial else "ticks_skipped", skipped)

    def _message_loop(self) -> None:
        """Message clock. Zenoh does not keep the order between keys (large clouds are fragmented and
        overtaken by small messages), so samples are first put back into send order when the sender
        numbered them (a replay does: :mod:`service.ordering`), and poses wait in a queue until the
        tick at their stamp can no longer be changed by a message still in transit (see _advance)."""
        torch.set_num_threads(self.cfg.torch_threads)
        est = self.est
        handlers = {
            "camera_info": est.on_camera_info,
            "camera_pose": est.on_camera_pose,
            "points": est.on_cloud_sync,
        }
        window = int(self.cfg.timeouts.reorder_s * 1e9)
        order = SequenceBuffer(self.cfg.timeouts.gap_s)
        poses: list = []
        last_pose = None
        last_message = time.perf_counter()
        while not self._stop.is_set():
            try:
                name, raw, seq = self.inbox.get(timeout=0.05)
                last_message = time.perf_counter()
                ready, taken = (
                    order.push((name, raw, seq is not None, bool(seq and seq.last)), seq, last_message),
                    True,
                )
                ready += order.expire(last_message)
            except queue.Empty:
                taken = False
                ready = order.expire(time.perf_counter())
                # idle for as long as a cloud may lag the poses: nothing is in transit any more
                # (a shorter wait made replays on a loaded machine depend on scheduling); a replay in
                # send order marks its last sample, so its poses wait as long as a missing sample
                # (gap_s: a sender that died) and a pause of the sender does not tick a pose before
                # its cloud
                ordered = poses and poses[-1][2]
                patience = self.cfg.timeouts.gap_s if ordered else self.cfg.timeouts.reorder_s
                if not ready and not order.holding() and time.perf_counter() - last_message >= patience:
                    self._advance(poses, flush=True)
            for name, raw, ordered, last in ready:
                try:
                    if name == "ee_poses":
                        parsed = est.parse_poses(raw, last_pose)
                        if parsed is not None:
                            poses.append((parsed, time.perf_counter(), ordered))
                            last_pose = parsed[0]
                    else:
                        handlers[name](raw)
                    self._advance(poses, window=window, flush=last)  # the replay's last sample: tick all
                except Exception:
                    log.exception("message %s failed", name)
                    self.stats.count("tick_errors")
            if order.gaps:  # samples lost in transit (or sent before the service started)
                self.stats.count("sequence_gaps", order.gaps)
                order.gaps = 0
            if taken:  # idle = nothing left to tick (drain: after the last task_done, nothing in flight)
                self._idle = not poses and not order.holding()
                self.inbox.task_done()

    def _advance(self, poses: list, window: int = 0, flush: bool = False) -> None:
        """Tick through the queued poses ``(parsed, arrival, ordered)`` whose clouds are settled.

        A pose in send order (``ordered``) ticks once the next pose has been released: everything
        sent between the two (its cloud, a camera_info) has then been handled, so the outcome
        depends only on the send order. Other poses tick once a cloud stamped at or after t has
        arrived, or once later poses are ``window`` ahead in message time *and* the pose has waited
        ``reorder_s`` of wall time (a fast replay sends a second of poses in milliseconds, so message
        time alone made the result depend on how long a cloud took in transit). ``flush`` (the input
        has been idle for ``reorder_s``) ticks them all."""
        est = self.est
        patience = self.cfg.timeouts.reorder_s
        now = time.perf_counter()
        while poses:
            (t, *_), arrived, ordered = poses[0]
            if ordered:
                ready = len(poses) > 1
            else:
                cloud_seen = est.last_cloud_ns is not None and est.last_cloud_ns >= t
                ready = cloud_seen or (poses[-1][0][0] - t >= window and now - arrived >= patience)
            if not (flush or ready):
                return
            for tick_ns in est.set_poses(poses.pop(0)[0]):  # every dt of message time up to t
                self.stats.count("ticks")
                self._tick(tick_ns)
        self._idle = True

    # ----- queries -----------------------------------------------------------------------------
    def _on_vertices_query(self, query) -> None:
        payload = self.latest_payload
        if payload is None:
            query.reply_err(json.dumps({"error": "no_estimate"}).encode())
        else:
            query.reply(self.cfg.key("vertices"), payload)

    def _on_status_query(self, query) -> None:
        status = self.est.status()
        predict = self.predict
        status["predict_ready"] = predict.ready
        status["predict_state"] = predict.state  # preparing, ready, retrying_eager or failed
        status["predict_mode"] = predict.mode  # compiled, eager, compiles on first use (when ready)
        status["predict_failed"] = predict.failed  # why a warm-up failed (None: it did not)
        # processes taking a share of a large request (the others start after predict is ready)
        status["predict_processes"] = len(self.predict_worker.workers)
        status["step_ready"] = self.step_ready
        status["not_ready"] = [
            k for k, ok in (("predict", predict.ready), ("step", self.step_ready)) if not ok
        ]
        status["failed"] = ["predict"] if predict.state in ("retrying_eager", "failed") else []
        query.reply(self.cfg.key("status"), json.dumps(status).encode())

    def _on_predict_query(self, query) -> None:
        def refuse(reason: str, detail: str) -> None:
            query.reply_err(json.dumps({"error": reason, "detail": detail}).encode())

        self._admit_predict("json", query, refuse)

    def _on_ros_predict_query(self, query) -> None:
        """``interface: ros2``: the ROS 2 service ``deform_msgs/srv/PredictShapes`` (service/ros2_predict.py)."""
        from service.ros2 import reply
        from service.ros2_predict import error_response

        self._admit_predict(
            "ros2", query, lambda reason, detail: reply(query, error_response(f"{reason}: {detail}"))
        )

    def _admit_predict(self, kind: str, query, refuse) -> None:
        """Queue a predict query for the predict thread, or ``refuse(reason, detail)`` it at once:
        warming up (``not_ready``: said now instead of answering after the compile), its warm-up
        failed (``predict_failed``, naming why; the client raises ServiceFailed) or too many queued
        (``busy``)."""
        predict = self.predict
        if not predict.ready:
            reason = "not_ready" if predict.state == "preparing" else "predict_failed"
            detail = predict.detail()
            self.stats.reject("predict", reason, detail)
            refuse(reason, detail)
            return
        try:
            self.predict_queue.put_nowait((kind, query))
        except queue.Full:
            self.stats.reject("predict", "busy", "too many predictions queued")
            refuse("busy", "too many predictions queued; ask again")

    def _predict_loop(self) -> None:
        from service import ros2, ros2_predict

        torch.set_num_threads(self.cfg.torch_threads)
        while not self._stop.is_set():
            try:
                kind, query = self.predict_queue.get(timeout=0.1)  # kind: "json" or "ros2"
            except queue.Empty:
                continue
            try:
                raw = query.payload.to_bytes() if query.payload is not None else b""
                if kind == "ros2":
                    try:
                        body = ros2_predict.request_body(raw)
                    except M.InputError as exc:
                        self.stats.reject("predict", exc.reason, str(exc))
                        ros2.reply(query, ros2_predict.error_response(str(exc)))
                        continue
                else:
                    body = raw
                self.predict_running.set()
                try:
                    ok, reply = predict_pool.handle(self.est, body, self.predict_worker)
                finally:
                    self.predict_running.clear()
                if kind == "ros2":
                    ros2.reply(query, ros2_predict.response(ok, reply))
                elif ok:
                    binary = predict_codec.is_binary(reply)
                    encoding = (
                        zenoh.Encoding.APPLICATION_OCTET_STREAM if binary else zenoh.Encoding.APPLICATION_JSON
                    )
                    query.reply(self.cfg.key("predict"), reply, encoding=encoding)
                else:
                    query.reply_err(reply)
            except Exception:
                log.exception("predict failed")
                if kind == "ros2":
                    ros2.reply(query, ros2_predict.error_response("internal"))
                else:
                    query.reply_err(b'{"error": "internal"}')
            finally:
                query.drop()
