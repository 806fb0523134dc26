"""Heavy work off the loop's interpreter: cloud fusion and batched prediction in child processes.

Why processes: the loop, the Zenoh callbacks and the Rerun logger share one GIL. Perception's
fusion (segmentation, DBSCAN, GMM) and a 64-plan rollout are mostly Python-level work, and run in
threads they made a 1 ms model step take 3 ms inside the service. A child process per job kind has
its own interpreter and its own copy of the model; only small things cross the pipe (the tracker's
state, a decoded cloud, a request body and its reply bytes).

:class:`WorkerProcess` and :class:`InlineWorker` have the same ``call(op, *args)``; the inline one
runs the job in the caller's thread (tests, or ``workers.processes: false``).
"""

from __future__ import annotations

import atexit
import gc
import io
import logging
import os
import pickle
import socket
import subprocess
import sys
import tempfile
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path

log = logging.getLogger("deform.service")


_PROJECT_ROOT = str(Path(__file__).resolve().parent.parent)


def _child_env() -> dict:
    """The parent's environment, with this checkout importable even when not installed."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (_PROJECT_ROOT, env.get("PYTHONPATH")) if p)
    return env


class WorkerError(RuntimeError):
    """The job raised in the worker (the message names the exception)."""


# ----- tracker state across processes ------------------------------------------------------------
class _TrackerPickler(pickle.Pickler):
    def __init__(self, file, model):
        from deform.compiled import CompiledStep

        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self._model, self._step_type = model, CompiledStep

    def persistent_id(self, obj):
        if obj is self._model:
            return "model"
        return "step" if isinstance(obj, self._step_type) else None


class _TrackerUnpickler(pickle.Unpickler):
    def __init__(self, file, model, step):
        super().__init__(file)
        self._model, self._step = model, step

    def persistent_load(self, pid):
        if pid == "model":
            return self._model
        if pid == "step":
            return self._step
        raise pickle.UnpicklingError(f"unknown persistent id {pid!r}")


def pack_tracker(tracker, model) -> bytes:
    """The tracker's state without its model or compiled step (each process has its own).
    Only ever exchanged between this service's own processes: never used on network input."""
    buf = io.BytesIO()
    _TrackerPickler(buf, model).dump(tracker)
    return buf.getvalue()


def unpack_tracker(blob: bytes, model, step=None):
    """The tracker on this side, with this process's ``model`` and compiled ``step`` (None: the
    model's own step)."""
    return _TrackerUnpickler(io.BytesIO(blob), model, step).load()


# ----- jobs --------------------------------------------------------------------------------------
class JobContext:
    """What a worker holds: the model, the service config and the (lazily) compiled predict step."""

    def __init__(self, model, cfg):
        self.model, self.cfg = model, cfg
        self._step = None

    @property
    def dtype(self):
        """The predict rollout's state dtype (``workers.predict_dtype``)."""
        import torch

        return getattr(torch, self.cfg.workers.predict_dtype)

    @property
    def step(self):
        if self._step is None:
            self._step = self._rollout_step(self.cfg.workers.compile_predict)
        return self._step

    def _rollout_step(self, compiled: bool):
        from deform.compiled import RolloutStep
        from deform.nn.precision import network_dtype

        return RolloutStep(
            self.model,
            enabled=compiled,
            ahead_of_time=self.cfg.workers.predict_ahead_of_time,
            compile_checked=self.cfg.workers.compile_checked_step,
            network_dtype=network_dtype(self.cfg.workers.predict_network_dtype),
        )

    def use_eager(self) -> None:
        """From now on the rollout is the model's eager step (what a failed warm-up falls back to)."""
        self._step = self._rollout_step(False)

    def check_step(self) -> None:
        """Two eager steps of one rod at rest in predict's dtype: what every rollout falls back on
        for the rods its compiled step leaves unconverged, and all it runs when not compiled.
        Raises what the model raises (a physics term of another dtype, ...), or a RuntimeError when
        the step does not keep the dtype or gives no finite shape: a warm-up that passes this
        check serves, and one that fails it says why at once (a few ms), before any compiling."""
        import torch

        from deform.step_graph import rod_at_rest

        state, grip = rod_at_rest(self.model, 1, self.dtype)
        with torch.no_grad():
            for _ in range(2):
                state = self.model.step(state, grip)
        kept = {name: getattr(state, name).dtype for name in ("x", "v", "d1", "theta")}
        if any(dtype != self.dtype for dtype in kept.values()):
            raise RuntimeError(f"the model's {self.dtype} step returned {kept}")
        if not torch.isfinite(state.x).all():
            raise RuntimeError(f"the model's {self.dtype} step of a rod at rest is not finite")


def pack_moment(moment) -> bytes:
    """A tracker's moment as bytes: tensors sent as they are would go through torch's shared-memory
    reducers, which a worker's connection cannot pass. Only ever between this service's processes."""
    return pickle.dumps(moment, protocol=pickle.HIGHEST_PROTOCOL)


def job_fuse(
    ctx: JobContext, tracker_blob: bytes, cloud, moment_blob: bytes | None = None
) -> tuple[bytes, float]:
    """Correct a tracker copy with one cloud, first taken back to a moment (:func:`pack_moment`: the
    tick of the cloud's stamp; None: as it is). -> (corrected tracker, seconds spent correcting)."""
    import torch

    tracker = unpack_tracker(tracker_blob, ctx.model)
    if moment_blob is not None:
        tracker.restore(pickle.loads(moment_blob))  # our own process's bytes, never network input
    t0 = time.perf_counter()
    with torch.no_grad():
        tracker.correct(cloud.xyz, cloud.rgb, cloud.camera)
    return pack_tracker(tracker, ctx.model), time.perf_counter() - t0


def job_predict(ctx: JobContext, body: bytes, base, stamp_ns: int):
    """-> the answer to a request or to this process's share of one (``predict.answer_part``), the
    seconds it took in here, and the rollout steps its one-graph step left unconverged (redone with
    the checked step; they double a step's cost, so status counts them)."""
    from service import predict

    t0 = time.perf_counter()
    redone0 = getattr(ctx.step, "redone", 0)
    part = predict.answer_part(ctx, body, base, stamp_ns)
    return part, time.perf_counter() - t0, getattr(ctx.step, "redone", 0) - redone0


def job_warmup(ctx: JobContext, batch_sizes, rescue: bool = True) -> bool:
    """Check the model's eager step in predict's dtype (:meth:`JobContext.check_step`), then compile
    or load predict's steps for these plan counts (``rescue=False``: all but the rescue graph, see
    ``service.predict_pool.PredictPool._warmup``). -> whether the compiled step is in use. Raises
    when predict cannot answer (the service then reports ``predict_failed``)."""
    ctx.check_step()
    active = ctx.step.warmup(tuple(batch_sizes), ctx.dtype, rescue=rescue) if batch_sizes else ctx.step.active
    gc.freeze()  # the compiled code's objects too (see _serve)
    return active


def job_warmup_eager(ctx: JobContext) -> bool:
    """After a failed warm-up: the rollout on the model's eager step from now on, checked
    (:meth:`JobContext.check_step`; raises when that fails too). -> False (not compiled)."""
    ctx.use_eager()
    ctx.check_step()
    gc.freeze()
    return False


def job_warmup_rescue(ctx: JobContext) -> bool:
    """Load (or build) the rescue graph a ``warmup(rescue=False)`` deferred. -> True."""
    ctx.step.warmup_rescue(ctx.dtype)
    gc.freeze()
    return True


def job_build_step(ctx: JobContext, branch_free, batch: int) -> tuple[str, bool]:
    """Build (or find) the ahead-of-time package of the one-graph step for ``batch`` rods in the
    on-disk cache (deform.aot), here rather than in the service process: compiling holds the
    interpreter lock for long stretches, which the 100 Hz loop would feel. The service then loads
    the package, keyed on the same model values. -> (its path, whether it was compiled now)."""
    import torch

    from deform.aot import ensure_package

    path, built = ensure_package(ctx.model, tuple(branch_free), int(batch), torch.float64)
    return str(path), built


def job_ping(ctx: JobContext, delay_s: float = 0.0) -> bool:
    """Health check (the delay stands in for a hung job in tests)."""
    time.sleep(delay_s)
    return True


def job_threads(ctx: JobContext) -> int:
    """The worker's torch threads (what its compiled packages are built for)."""
    import torch

    return torch.get_num_threads()


JOBS = {
    "fuse": job_fuse,
    "predict": job_predict,
    "warmup": job_warmup,
    "warmup_eager": job_warmup_eager,
    "warmup_rescue": job_warmup_rescue,
    "build_step": job_build_step,
    "ping": job_ping,
    "threads": job_threads,
}


def _serve(conn, cfg, nice: int = 0, threads: int | None = None) -> None:
    """Child process main: lower its priority by ``nice``, set its torch threads (``threads``,
    default ``cfg.torch_threads``), import what the jobs need, then wait
    for the model (a ``("model", path)`` message: the child may be started before the parent has
    loaded it, so that both import at once), load it, say ready and answer jobs in order until the
    pipe closes."""
    if nice:
        os.nice(nice)
    import torch

    torch.set_num_threads(threads or cfg.torch_threads)
    import deform.compiled  # noqa: F401  (the predict step's code)
    import service.predict  # the predict job's code
    import service.tracking  # noqa: F401  (perception, for fuse: imported once here, not in a timed job)
    from deform import DeformModel
    from deform.errors import CheckpointError

    try:
        op, args = conn.recv()
    except (EOFError, OSError, KeyboardInterrupt):
        return
    if op != "model":  # "stop" before any model, or a protocol error
        return
    try:
        model = DeformModel.load(args[0])
    except CheckpointError:
        # the parent closed before this worker had started (a pool's late joiner at exit) and its
        # temporary model file went with it; a parent still waiting sees the socket close
        return
    ctx = JobContext(model, cfg)
    # Long-lived objects (torch, the model, later the compiled code: ~600k objects) out of the
    # collector's reach: a full collection of them took 0.4 s, and JSON parsing triggers one every
    # few predict requests (measured: 3 of 20 requests took 0.4 s instead of 0.13 s).
    gc.freeze()
    try:
        conn.send(("ready", os.getpid()))  # start-up done: the parent times jobs from here on
    except (BrokenPipeError, OSError):
        return
    while True:
        try:
            op, args = conn.recv()
        except (EOFError, OSError, KeyboardInterrupt):
            return
        if op == "stop":
            return
        try:
            reply = ("ok", JOBS[op](ctx, *args))
        except Exception as exc:
            reply = ("error", f"{type(exc).__name__}: {exc}")
        try:
            conn.send(reply)
        except (BrokenPipeError, OSError):
            return


def main(argv: list[str] | None = None) -> None:
    """``python -m service.workers FD CONFIG_JSON [NICE [THREADS]]``: a worker on an inherited socket."""
    from service.config import ServiceConfig

    fd, cfg_json, *rest = argv or sys.argv[1:]
    nice, threads = (int(a) for a in (rest + ["0", "0"])[:2])
    _serve(Connection(int(fd)), ServiceConfig.model_validate_json(cfg_json), nice, threads or None)


class InlineWorker:
    """Same interface, in the caller's process and thread."""

    def __init__(self, model, cfg):
        self.ctx = JobContext(model, cfg)
        self._lock = threading.Lock()

    def call(self, op: str, *args, timeout: float | None = None):
        with self._lock:
            try:
                return JOBS[op](self.ctx, *args)
            except Exception as exc:
                raise WorkerError(f"{type(exc).__name__}: {exc}") from exc

    def restart(self) -> None:
        pass

    def close(self) -> None:
        pass


class WorkerProcess:
    """A spawned child holding its own model; ``call`` sends one job and waits for its reply.
    Calls from several threads are serialised. A call that times out restarts the child (the
    reply would otherwise arrive to the next caller). A job's timeout counts the job only: the
    first call after a (re)start first waits up to ``start_timeout_s`` for the child to say it is
    ready (importing torch and perception and loading the model take seconds, tens of seconds for
    a niced child on a busy machine, which a 5 s fusion timeout must not be charged with)."""

    def __init__(
        self,
        model,
        cfg,
        name: str,
        nice: int = 0,
        threads: int | None = None,
        start_timeout_s: float = 300.0,
    ):
        self.cfg, self.name, self.nice, self.threads = cfg, name, nice, threads
        self.start_timeout_s = start_timeout_s
        self._dir = tempfile.TemporaryDirectory(prefix="deform-worker-")
        self._model_path: str | None = None
        self._lock = threading.Lock()
        self._start()
        if model is not None:
            self.set_model(model)

    def set_model(self, model) -> None:
        """The model the child holds (a copy through a file): sent once; a restart sends it again.

        Args:
            model: a :class:`deform.model.DeformModel`.
        """
        self._model_path = str(Path(self._dir.name) / "model.pt")
        model.save(self._model_path)
        self._send_model()

    def _send_model(self) -> None:
        try:
            self._conn.send(("model", (self._model_path,)))
        except (BrokenPipeError, OSError) as exc:
            log.warning("%s: could not send the model (%s)", self.name, exc)

    def _start(self) -> None:
        # a fresh interpreter (`python -m service.workers`) on one end of a socket pair: fork would
        # copy the parent's threads' locks mid-use, and multiprocessing's spawn re-runs the parent's
        # main script (which then needs an `if __name__ == "__main__"` guard)
        ours, theirs = socket.socketpair()
        self._proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "service.workers",
                str(theirs.fileno()),
                self.cfg.model_dump_json(),
                str(self.nice),
                str(self.threads or 0),
            ],
            pass_fds=[theirs.fileno()],
            cwd=_PROJECT_ROOT,
            env=_child_env(),
        )
        theirs.close()
        self._conn = Connection(ours.detach())
        self._ready = False
        if self._model_path is not None:  # a restart
            self._send_model()

    def _wait_ready(self) -> None:
        """Block until the child has started (its "ready" message), at most ``start_timeout_s``."""
        if self._ready:
            return
        if not self._conn.poll(self.start_timeout_s):
            raise TimeoutError(f"{self.name}: not started within {self.start_timeout_s} s")
        status, _ = self._conn.recv()
        if status != "ready":
            raise EOFError(f"{self.name}: unexpected first message {status!r}")
        self._ready = True

    @property
    def pid(self) -> int:
        return self._proc.pid

    def call(self, op: str, *args, timeout: float | None = None):
        with self._lock:
            try:
                self._wait_ready()
                self._conn.send((op, args))
                if timeout is not None and not self._conn.poll(timeout):
                    raise TimeoutError(f"{self.name}: {op} took longer than {timeout} s")
                status, value = self._conn.recv()
            except (TimeoutError, EOFError, OSError) as exc:
                log.warning("%s: %s; restarting the worker", self.name, exc)
                self._restart()
                raise WorkerError(str(exc)) from exc
        if status == "error":
            raise WorkerError(value)
        return value

    def restart(self) -> None:
        """A fresh child (e.g. to hand back the memory a compilation left behind, about 0.6 GB)."""
        with self._lock:
            self._restart()

    def _restart(self) -> None:
        self._proc.kill()
        self._proc.wait(timeout=5)
        self._conn.close()
        self._start()

    def close(self) -> None:
        with self._lock:
            try:
                self._conn.send(("stop", ()))
            except (BrokenPipeError, OSError):
                pass
            try:
                self._proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(timeout=5)
            self._conn.close()
        self._dir.cleanup()


def fusion_worker_spec(cfg) -> tuple[str, int, int] | None:
    """(name, nice, threads) of the service's fusion worker; None on the message clock (it fuses
    in the loop)."""
    if cfg.clock == "message":
        return None
    return f"fusion[{cfg.namespace}]", cfg.workers.fusion_nice, cfg.torch_threads


def predict_worker_specs(cfg) -> list[tuple[str, int, int]]:
    """(name, nice, threads) of each of the service's predict worker processes."""
    from service.config import predict_threads

    threads = predict_threads(cfg.workers)
    return [
        (f"predict[{cfg.namespace}]" + (f"#{i}" if i else ""), 0, threads)
        for i in range(cfg.workers.predict_processes)
    ]


_PRESTARTED: dict[tuple[str, int, int, str], WorkerProcess] = {}


def prestart(cfg) -> None:
    """Start worker processes before the caller has imported torch or loaded its model: the
    children's imports (3-4 s each) then overlap the parent's instead of following them.
    :func:`make_worker` hands them out; a started worker nobody asks for is stopped at exit.

    Args:
        cfg: the service config the workers will serve (must be the one ``make_worker`` gets).
    """
    if not cfg.workers.processes:
        return
    # the first predict process only: the others start at predict's warm-up (see service.predict_pool.PredictPool)
    for name, nice, threads in filter(None, (fusion_worker_spec(cfg), predict_worker_specs(cfg)[0])):
        key = (name, nice, threads, cfg.model_dump_json())
        if key not in _PRESTARTED:
            worker = WorkerProcess(None, cfg, name, nice, threads)
            _PRESTARTED[key] = worker
            atexit.register(_close_unused, key)


def _close_unused(key) -> None:
    worker = _PRESTARTED.pop(key, None)
    if worker is not None:
        worker.close()


def make_worker(model, cfg, name: str, nice: int = 0, threads: int | None = None):
    """A worker process (``nice``: its CPU priority below the service's; ``threads``: its torch
    threads, default ``cfg.torch_threads``), or inline when ``workers.processes`` is off (in the
    caller's thread, with its threads). A worker :func:`prestart` started for the same name, nice,
    threads and config is used when there is one."""
    if not cfg.workers.processes:
        return InlineWorker(model, cfg)
    worker = _PRESTARTED.pop((name, nice, threads, cfg.model_dump_json()), None)
    if worker is None:
        return WorkerProcess(model, cfg, name, nice, threads)
    worker.set_model(model)
    return worker


if __name__ == "__main__":
    main()
