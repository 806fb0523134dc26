"""Cloud fusion off the loop thread, latest-only: the tick never waits for a cloud.

A cloud is fused into a private copy of the tracker as it was at tick k, the tick of the cloud's
stamp (``camera.fuse_at: stamp``, the default: the tracker after each tick is kept for 5 s) or the
tick its fusion starts (``arrival``). The copy is then brought forward through the grips of the
ticks since and swapped in. The result equals fusing at tick k in the loop (same operations, same
order), without the loop paying for it. Why at the stamp: a camera delivers a cloud tens of
milliseconds after it was taken and decoding adds more; a cloud fused where it arrives pulls the
rope back to where it was then. The fusion itself runs in a worker (:mod:`service.workers`: a child
process by default, so perception's Python-level work never holds the loop's interpreter); only the
catch-up steps run here.
"""

from __future__ import annotations

import logging
import threading
import time

from service import messages as M
from service.estimator import Estimator
from service.workers import InlineWorker, WorkerError, pack_moment, pack_tracker, unpack_tracker

log = logging.getLogger("deform.service")

AHEAD_WAIT_PERIODS = 3  # a cloud newer than every tick waits at most the pose delay and this many periods


class LatestSlot:
    """Holds one item; a new put replaces the unread one (which is reported as superseded)."""

    def __init__(self):
        self._item = None
        self._cond = threading.Condition()

    def put(self, item) -> bool:
        with self._cond:
            replaced = self._item is not None
            self._item = item
            self._cond.notify()
        return replaced

    def take(self, timeout: float):
        with self._cond:
            if self._item is None:
                self._cond.wait(timeout)
            item, self._item = self._item, None
        return item


class FusionWorker(threading.Thread):
    def __init__(
        self,
        est: Estimator,
        worker=None,
        max_lag_ticks: int = 200,
        yield_to: threading.Event | None = None,
        max_yield_s: float = 0.0,
    ):
        super().__init__(name=f"fusion[{est.cfg.namespace}]", daemon=True)
        self.est = est
        self.worker = worker if worker is not None else InlineWorker(est.model, est.cfg)
        self.slot = LatestSlot()
        self.max_lag = max_lag_ticks
        self._stop_event = threading.Event()
        self._can_clone = True
        self.yield_to = yield_to  # set while a predict runs: the next fusion waits (see _yield)
        self.max_yield_s = max_yield_s
        self.clock, self.sleep = time.monotonic, time.sleep  # _yield's wall time; tests swap in fakes

    def _yield(self) -> None:
        """Wait (at most ``max_yield_s``) while ``yield_to`` is set. On 2 cores a fusion (decode,
        perception, catch-up steps: about half a core at 30 Hz) running beside a predict more than
        doubles the planner's wait; deferred, the cloud waits in the latest-only slot (a newer one
        supersedes it) and the estimate runs open-loop for those ticks."""
        if self.yield_to is None or self.max_yield_s <= 0 or not self.yield_to.is_set():
            return
        deadline = self.clock() + self.max_yield_s
        self.est.stats.count("fusion_deferred")
        while self.yield_to.is_set() and self.clock() < deadline and not self._stop_event.is_set():
            self.sleep(0.002)

    def due(self, cloud) -> bool:
        """Has the loop reached ``cloud``'s tick? On the wall clock, fused at the stamp, the ticks
        step to poses ``pose_delay_s`` behind the newest, so a camera faster than that (a simulator's,
        a fast driver on loopback: 8 ms from stamp to decoded, against ticks 16-24 ms behind the wall
        clock) delivers clouds newer than every tick. Fused at once, each would correct a state
        older than itself toward where the rope is later (on the live service fed over loopback,
        every cloud was 16 ms ahead); it waits for the first tick within half a period of its stamp
        instead. Always due elsewhere."""
        est = self.est
        if not est.rewinds:
            return True
        with est.lock:
            newest = est.history[-1].pose_ns if est.history else None
        return newest is None or newest >= cloud.stamp_ns - est.cfg.dt * 1e9 / 2

    def ahead_wait_s(self) -> float:
        """How long a cloud may wait for its tick: the ticks lag the newest pose by the pose delay
        and up to a period or two more (the tick's phase, the pose interval), so a cloud still
        ahead after ``AHEAD_WAIT_PERIODS`` periods beyond it has a stamp no tick will reach soon
        (its camera's clock ahead of the robot's: ``camera.stamp_delay_s`` corrects that)."""
        with self.est.lock:  # the pose subscriber adds to the timeline under it
            timeline = self.est.timeline
            delay = timeline.delay_ns() / 1e9 if timeline is not None else 0.0
        return delay + AHEAD_WAIT_PERIODS * self.est.cfg.dt

    def _await_tick(self, cloud) -> None:
        """Wait (at most :meth:`ahead_wait_s`) until ``cloud`` is :meth:`due`; a cloud still ahead
        then is fused at the newest tick and counted (``clouds_ahead_of_poses``)."""
        deadline = self.clock() + self.ahead_wait_s()
        while not self.due(cloud) and not self._stop_event.is_set():
            if self.clock() >= deadline:
                self.est.stats.count("clouds_ahead_of_poses")
                return
            self.sleep(0.001)

    def submit(self, raw: bytes) -> None:
        if not self.est.admit_cloud(raw):
            return
        if self.slot.put(raw):
            self.est.stats.drop("cloud_superseded", "a newer cloud arrived before fusion")

    def stop(self) -> None:
        self._stop_event.set()

    def run(self) -> None:
        import torch

        torch.set_num_threads(self.est.cfg.torch_threads)
        while not self._stop_event.is_set():
            self._yield()
            raw = self.slot.take(0.1)
            if raw is None:
                continue
            try:
                cloud = self.est.decode_cloud(raw)
            except M.InputError as exc:
                self.est.stats.reject("points", exc.reason, str(exc))
                continue
            self._await_tick(cloud)
            try:
                with torch.no_grad():
                    self.fuse(cloud)
            except Exception:  # a fusion failure must never take the service down
                log.exception("cloud fusion failed")
                self.est.stats.count("fusion_errors")

    def fuse(self, cloud) -> None:
        est = self.est
        with est.lock:
            if not est.initialized:
                est.stats.drop("cloud_before_init")
                return
            if self._can_clone:
                try:
                    blob, k = pack_tracker(est.tracker, est.model), est.tick_index
                except Exception as exc:
                    log.warning("tracker cannot be copied (%s): fusing in the loop thread", exc)
                    self._can_clone = False
            if not self._can_clone:
                est._correct(est.tracker, cloud)
                est.fused_at = est.now()
                est.stats.cloud_age_s.add((est.wall_ns() - cloud.stamp_ns) / 1e9)
                return
            start = est.fusion_tick(cloud.stamp_ns)
            if start is not None:
                k = start.index
        moment = None if start is None else pack_moment(start.moment)
        try:
            fused, seconds = self.worker.call(
                "fuse", blob, cloud, moment, timeout=est.cfg.workers.fusion_timeout_s
            )
        except WorkerError as exc:
            log.warning("cloud fusion failed in the worker: %s", exc)
            est.stats.count("fusion_errors")
            return
        copy = unpack_tracker(fused, est.model)
        if hasattr(copy, "step_fn"):  # the worker stepped eagerly: this side's compiled step again
            copy.step_fn = est.step_fn
        est.record_fusion(cloud, seconds)
        replayed = {k: copy.moment()} if start is not None else {}  # the history's ticks, rewritten

        def catch_up(todo) -> None:
            for t in todo:
                copy.step(t.grip)
                if start is not None:
                    replayed[t.index] = copy.moment()

        while True:
            with est.lock:
                todo = [t for t in est.history if t.index > k]
                if (todo and todo[0].index != k + 1) or len(todo) > self.max_lag:
                    est.stats.drop("cloud_too_late", f"{len(todo)} ticks behind")
                    return
                if len(todo) <= 1:  # one step left: finish under the lock and swap
                    if hasattr(copy, "step_fn"):  # (compiled meanwhile?)
                        copy.step_fn = est.step_fn
                    catch_up(todo)
                    est.tracker = copy
                    est.rewrite_history(replayed)
                    est.fused_at = est.now()
                    est.stats.cloud_age_s.add((est.wall_ns() - cloud.stamp_ns) / 1e9)
                    est.stats.count("fusion_catchup_steps", len(todo))
                    return
            catch_up(todo)
            k = todo[-1].index
            est.stats.count("fusion_catchup_steps", len(todo))
            time.sleep(0)
