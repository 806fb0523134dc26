"""A benchmark's independent datasets as Ray tasks: on this machine with no set-up, or on a cluster.

    with Workers.from_args(args) as workers:
        control = workers.shared(simulate, kind, None, seed)           # computed once, given to tasks
        failures = workers.run({key: call(run_dataset, control, ...), ...}, on_result)

* this machine (the default): a local Ray is started for the run with one CPU per core
  (``--num-cpus N`` / ``--workers N`` for fewer) and shut down after it;
* a cluster: ``--address ray://HOST:10001`` (Ray client, from anywhere), ``--address HOST:6379`` or
  ``--address auto`` (on one of its nodes), or ``$RAY_ADDRESS``. The repository's code is shipped
  to the workers (Ray's ``working_dir``, without ``.venv``, ``.git``, ``runs`` and the stored
  results); the nodes need the project's dependencies installed (``pip install -e ".[bench]"``) and
  the recordings at ``$DEFORM_DATA`` (passed on to the workers when it is set here) or
  ``../shared/data/deform`` beside the code. ``--num-cpus N`` caps the tasks in flight. A cluster
  with Ray's token authentication (``ray start`` sets it up) takes a Ray client only with
  ``RAY_AUTH_MODE=token`` and its token (``~/.ray/auth_token`` or ``$RAY_AUTH_TOKEN``) here;
* ``--inline``: no Ray, the tasks one after another in this process (for a debugger).

Every task runs with one torch thread (a task per core). Tasks return their results to this
process, which stores each one as it arrives (:mod:`benchmarks.store`); a progress bar counts them.
A task that raises is reported and the others go on; :meth:`Workers.run` returns the failures.
"""

from __future__ import annotations

import argparse
import os
import sys
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
# not shipped to a cluster's workers: environments, history, outputs and the stored results
EXCLUDES = [
    ".venv/",
    ".git/",
    "runs/",
    "out/",
    "demo_out/",
    "build/",
    "benchmarks/results/",
    "*.rrd",
    "*.egg-info/",
]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The workers' options: ``--address``, ``--num-cpus`` (``--workers``), ``--inline``."""
    g = p.add_argument_group("workers (Ray)")
    g.add_argument(
        "--address",
        default=None,
        help="a Ray cluster: ray://HOST:PORT (Ray client), HOST:PORT or auto (on one of its nodes); "
        "default $RAY_ADDRESS, else a local Ray started for this run",
    )
    g.add_argument(
        "--num-cpus",
        "--workers",
        dest="num_cpus",
        type=int,
        default=None,
        help="tasks at once: the local Ray's CPUs (default: this machine's cores); on a cluster, a cap",
    )
    g.add_argument(
        "--inline", action="store_true", help="no Ray: the tasks one after another in this process"
    )


@dataclass
class Call:
    """A function and its arguments, run as one task (arguments may be :meth:`Workers.shared` handles)."""

    fn: Callable
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)


def call(fn: Callable, *args, **kwargs) -> Call:
    return Call(fn, args, kwargs)


def run_call(fn: Callable, *args, **kwargs):
    """A task's body, in its worker: one torch thread, then ``fn``."""
    import torch

    torch.set_num_threads(1)
    return fn(*args, **kwargs)


class _Deferred:
    """``--inline``'s stand-in for a shared task: computed when a task first needs it."""

    _unset = object()

    def __init__(self, c: Call):
        self.c, self.value = c, self._unset

    def get(self):
        if self.value is self._unset:
            self.value = run_call(self.c.fn, *self.c.args, **self.c.kwargs)
        return self.value


def _resolved(x):
    return x.get() if isinstance(x, _Deferred) else x


class Workers:
    """Where a benchmark's tasks run (see the module's docstring)."""

    def __init__(self, address: str | None = None, num_cpus: int | None = None, inline: bool = False):
        self.address = address or os.environ.get("RAY_ADDRESS") or None
        self.num_cpus = num_cpus
        self.inline = inline
        self._ray = None
        self._started = False  # this object started Ray (and shuts it down)
        self._remote = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Workers:
        return cls(
            getattr(args, "address", None), getattr(args, "num_cpus", None), getattr(args, "inline", False)
        )

    def describe(self) -> dict:
        """Where the tasks ran, for a result's provenance."""
        if self.inline:
            return {"ray": None, "tasks_at_once": 1}
        if self.address:
            return {"ray": self.address, "tasks_at_once": self.num_cpus or "cluster"}
        return {"ray": "local", "tasks_at_once": self.num_cpus or os.cpu_count()}

    def __enter__(self) -> Workers:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._started:
            self._ray.shutdown()
            self._started = False

    def _start(self):
        if self._ray is not None:
            return self._ray
        import ray

        if not ray.is_initialized():
            if self.address:
                runtime_env: dict[str, Any] = {"working_dir": str(ROOT), "excludes": EXCLUDES}
                if os.environ.get("DEFORM_DATA"):
                    runtime_env["env_vars"] = {"DEFORM_DATA": os.environ["DEFORM_DATA"]}
                ray.init(address=self.address, runtime_env=runtime_env, log_to_driver=True)
            else:
                # the local workers import this repository's packages as this process does
                path = os.environ.get("PYTHONPATH")
                os.environ["PYTHONPATH"] = str(ROOT) + (os.pathsep + path if path else "")
                # "local": a new instance even where another Ray runs (or a stopped one left its address)
                ray.init(address="local", num_cpus=self.num_cpus or os.cpu_count(), include_dashboard=False)
            self._started = True
        self._ray = ray
        self._remote = ray.remote(num_cpus=1)(run_call)
        return ray

    def shared(self, fn: Callable, *args, **kwargs):
        """Start ``fn(*args, **kwargs)`` as a task whose result several tasks take as an argument
        (computed once); -> its handle, to pass in :func:`call`'s arguments."""
        if self.inline:
            return _Deferred(Call(fn, args, kwargs))
        self._start()
        return self._remote.remote(fn, *args, **kwargs)

    def run(
        self,
        tasks: dict[str, Call],
        on_result: Callable[[str, Any], None],
        desc: str = "datasets",
    ) -> dict[str, str]:
        """Run ``tasks`` (key -> call), ``on_result(key, value)`` in this process as each finishes;
        -> ``{key: error}`` of the tasks that raised (the others ran to the end)."""
        from tqdm import tqdm

        failures: dict[str, str] = {}
        if not tasks:
            return failures
        bar = tqdm(total=len(tasks), desc=desc, unit="task", smoothing=0, file=sys.stderr)
        try:
            if self.inline:
                for key, c in tasks.items():
                    try:
                        value = run_call(
                            c.fn, *map(_resolved, c.args), **{k: _resolved(v) for k, v in c.kwargs.items()}
                        )
                    except Exception:
                        failures[key] = traceback.format_exc()
                        bar.write(f"{key}: failed\n{failures[key]}")
                    else:
                        on_result(key, value)
                    bar.update()
                return failures
            ray = self._start()
            queue = list(tasks.items())
            cap = self.num_cpus if (self.address and self.num_cpus) else len(queue)
            pending: dict = {}
            try:
                while queue or pending:
                    while queue and len(pending) < cap:
                        key, c = queue.pop(0)
                        pending[self._remote.remote(c.fn, *c.args, **c.kwargs)] = key
                    # with a timeout: Ctrl-C reaches this process between waits (not while blocked)
                    ready, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
                    if not ready:
                        continue
                    key = pending.pop(ready[0])
                    ref = ready[0]
                    try:
                        value = ray.get(ref)
                    except ray.exceptions.RayError as exc:
                        failures[key] = str(exc)
                        bar.write(f"{key}: failed\n{exc}")
                    else:
                        on_result(key, value)
                    bar.update()
            except BaseException:
                for ref in pending:  # stopped: nothing left running on a cluster's workers
                    try:
                        ray.cancel(ref, force=True)
                    except Exception:  # already finished, or the connection is gone
                        pass
                raise
        finally:
            bar.close()
        return failures

    def log(self, message: str) -> None:
        """A line beside the progress bar."""
        from tqdm import tqdm

        tqdm.write(message)


def repo_path(relative: str | Path) -> Path:
    """A path of the repository in the worker that runs a task (the shipped copy on a cluster)."""
    return ROOT / relative
