"""`{ns}/predict` served by processes: the pool that shards a request over the predict worker
processes, and the front door :func:`handle` that checks a request, snapshots the estimate and
hands it to the pool.

Its own module so that imports go one way: :mod:`service.predict` is the request and the compute
of one process (parsing, :func:`~service.predict.answer_part`, :func:`~service.predict.share`,
:func:`~service.predict.assemble`), :mod:`service.workers` the process mechanism that runs it
(its predict job calls ``answer_part``), and this module uses both.
"""

from __future__ import annotations

import json
import logging
import threading
import time

from service import predict_codec
from service.estimator import Estimator
from service.messages import InputError
from service.predict import assemble, check_size, share, snapshot
from service.workers import make_worker, predict_worker_specs

log = logging.getLogger("deform.service")


def shares_for(plans: int | None, processes: int, split_min_plans: int) -> int:
    """How many predict processes a request of ``plans`` plans is split across: every process from
    ``split_min_plans`` plans on, else the first one alone (also when the plan count is not known
    without parsing the request). The one rule for serving (:meth:`PredictPool.predict`) and for
    what warm-up compiles (:func:`share_sizes`).

    Args:
        plans: plans in the request, or None.
        processes: predict processes serving.
        split_min_plans: smaller requests go to the first process whole.

    Returns:
        The number of shares, 1 or ``processes``.
    """
    if plans is None or plans < split_min_plans:
        return 1
    return min(processes, plans)  # no process without a plan


def share_sizes(plan_counts, processes: int, split_min_plans: int) -> list[list[int]]:
    """The batch sizes each predict process rolls out for requests of these plan counts: what it
    compiles at warm-up, and what ``deform-service prebuild`` builds.

    Args:
        plan_counts: plans per request (``workers.predict_warmup``).
        processes: predict processes.
        split_min_plans: smaller requests go to the first process whole.

    Returns:
        Per process, the sorted distinct sizes (empty for a process no such request reaches).
    """
    out: list[set] = [set() for _ in range(processes)]
    for plans in plan_counts:
        k = shares_for(plans, processes, split_min_plans)
        for i in range(k):
            lo, hi = share(plans, i, k)
            if hi > lo:
                out[i].add(hi - lo)
    return [sorted(s) for s in out]


class PredictPool:
    """The predict worker processes: a large request is split across them in consecutive blocks of
    plans, each rolled out on one thread, and the shares are joined in order into one reply.

    Why processes rather than threads: the compiled step's parallel loops meet at about 120
    barriers per step, so two threads wait for each other whenever the loop, fusion or a camera
    takes a core (a 1024-rod step beside one busy process: 53-122k rod-steps/s on two threads,
    201-209k on one); processes do not wait for each other, and Python threads cannot share the
    work (the ahead-of-time step holds the interpreter lock). Only binary requests of at least
    ``split_min_plans`` plans are split (their plan count is in the header; a JSON request would
    have to be parsed here, in the loop's process).

    ``more``: makers of the other processes, started in the background by the first ``warmup`` once
    the first process is warm (predict is ready then), so that their imports do not slow the
    service's start-up (a third process importing torch beside the service and two workers put
    warm start-up at 11 s instead of 6.5), and they load the packages the first one built. Until
    they are warm, every request goes to the first process (``started`` tells when they are).
    """

    def __init__(self, workers: list, split_min_plans: int = 128, more=()):
        self.workers, self.split_min_plans = list(workers), split_min_plans
        self._more = list(more)
        self._lock = threading.Lock()  # the pool's membership against close()
        self._closed = False
        self.started = threading.Event()  # every process is warm and takes its share
        if not self._more:
            self.started.set()

    @property
    def pid(self) -> int:
        return self.workers[0].pid

    def call(self, op: str, *args, timeout: float | None = None):
        """A job on the first process (``warmup``: on every process, for the share sizes a split
        request gives it, the first process before the others so that they load its packages;
        ``warmup_eager``, after a failed warm-up: every process on the eager step)."""
        if op == "warmup":
            return self._warmup(args[0], timeout)
        if op == "warmup_eager":
            return self._warmup([], timeout, eager=True)
        return self.workers[0].call(op, *args, timeout=timeout)

    def _warmup(self, sizes, timeout, eager: bool = False) -> bool:
        """The first process now (-> whether its step is compiled), the others in the background.

        With other processes to start, the first defers the rescue graph (``RolloutStep.warmup``):
        on a cold start the second process builds it while the first already serves (its redo on
        the eager loops meanwhile), and the first loads it once the others are warm; predict is
        ready one package build (about 25 s) sooner. When the first process's warm-up fails, the
        others are kept for the next warm-up (``eager``: the retry on the eager step)."""
        per = share_sizes(sizes, len(self.workers) + len(self._more), self.split_min_plans)
        more, self._more = self._more, []
        try:
            if eager:
                active = self.workers[0].call("warmup_eager", timeout=timeout)
            else:
                active = self.workers[0].call("warmup", per[0], not more, timeout=timeout)
        except Exception:
            self._more = more
            raise
        if more:
            threading.Thread(
                target=self._start_more, args=(more, per[1:], timeout, eager), daemon=True
            ).start()
        return bool(active)

    def _start_more(self, makers, sizes, timeout, eager: bool = False) -> None:
        try:
            self._add_processes(makers, sizes, timeout, eager)
        finally:  # the first process's deferred rescue graph, built by now (or built by it here)
            try:
                if not self._closed:
                    self.workers[0].call("warmup_rescue", timeout=timeout)
            except Exception as exc:
                log.warning("predict: the rescue graph is not loaded (%s); unconverged rods go eager", exc)

    def _add_processes(self, makers, sizes, timeout, eager: bool = False) -> None:
        new = []
        try:
            for make in makers:
                with self._lock:
                    if self._closed:
                        return
                    new.append(make())
            warm = [(w, ("warmup_eager",) if eager else ("warmup", p)) for w, p in zip(new, sizes)]
            self._each(warm, timeout)
            self._each([(w, ("warmup_rescue",)) for w in new], timeout)  # builds it on a cold start
            with self._lock:
                if not self._closed:
                    self.workers = [*self.workers, *new]  # split requests from here on
                    new = []
                    self.started.set()
        except Exception as exc:  # predict goes on with the first process alone
            log.warning("predict: the other predict processes did not start (%s); one process serves", exc)
        finally:
            for w in new:  # not taken into the pool (closed meanwhile, or failed)
                w.close()

    @staticmethod
    def _each(calls, timeout) -> list:
        """``worker.call(*args)`` for each ``(worker, args)`` at once (each waits on its own socket);
        a single call in this thread."""
        if len(calls) == 1:
            worker, args = calls[0]
            return [worker.call(*args, timeout=timeout)]
        out: list = [None] * len(calls)
        errors: list = []

        def run(i, worker, args):
            try:
                out[i] = worker.call(*args, timeout=timeout)
            except Exception as exc:
                errors.append(exc)

        threads = [threading.Thread(target=run, args=(i, w, a)) for i, (w, a) in enumerate(calls)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        if errors:
            raise errors[0]
        return out

    def predict(self, body: bytes, base, stamp_ns: int, timeout: float | None = None):
        """-> (ok, reply, reason, detail, compute seconds (the slowest share), steps redone)."""
        workers = list(self.workers)  # the second process may join meanwhile
        plans = predict_codec.request_plans(body) if len(workers) > 1 else None
        k = shares_for(plans, len(workers), self.split_min_plans)
        bodies = None
        if k > 1:  # each process is sent its block of plans alone (handle checked the size)
            bodies = predict_codec.split_request(body, [share(plans, i, k) for i in range(k)])
        calls = [(w, ("predict", b, base, stamp_ns)) for w, b in zip(workers, bodies or [body])]
        results = self._each(calls, timeout)
        reply = assemble([part for part, _, _ in results])
        return (*reply, max(r[1] for r in results), sum(r[2] for r in results))

    def restart(self) -> None:
        for w in self.workers:
            w.restart()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            workers = list(self.workers)
        for w in workers:
            w.close()


def make_predict_pool(model, cfg) -> PredictPool:
    """The service's :class:`PredictPool`: its first process now, the others at its warm-up (one
    inline worker when ``workers.processes`` is off)."""
    specs = predict_worker_specs(cfg) if cfg.workers.processes else predict_worker_specs(cfg)[:1]
    more = [lambda s=s: make_worker(model, cfg, *s) for s in specs[1:]]
    return PredictPool([make_worker(model, cfg, *specs[0])], cfg.workers.predict_split_min_plans, more)


def handle(est: Estimator, body: bytes, worker) -> tuple[bool, bytes]:
    """-> (ok, JSON reply). Errors are counted under ``predict:<reason>``. The rollout runs in
    ``worker``: a :class:`PredictPool` of processes, or one worker of :mod:`service.workers` (a
    child process, or an ``InlineWorker`` for this thread)."""
    try:
        if len(body) > est.cfg.limits.max_request_bytes:  # before copying it anywhere
            raise InputError("too_large", f"{len(body)} bytes > {est.cfg.limits.max_request_bytes}")
        shape = predict_codec.request_shape(body)
        if shape is not None and len(shape) == 4:  # here: the processes each see only their share
            check_size(shape[0], shape[1], est.cfg.limits)
        base, stamp = snapshot(est)
    except InputError as exc:
        est.stats.reject("predict", exc.reason, str(exc))
        return False, json.dumps({"error": exc.reason, "detail": str(exc)}).encode()
    t0 = time.perf_counter()
    pool = worker if isinstance(worker, PredictPool) else PredictPool([worker])
    ok, reply, reason, detail, compute_s, redone = pool.predict(
        body, base, stamp, timeout=est.cfg.workers.predict_timeout_s
    )
    if ok:
        est.stats.count("predictions")
        est.stats.count("predict_steps_redone", redone)
        est.stats.predict_s.add(time.perf_counter() - t0)
        est.stats.predict_compute_s.add(compute_s)
    else:
        est.stats.reject("predict", reason, detail)
    return ok, reply
