"""The work of a calibration that splits by clip, spread over the machine's cores.

A tracking pass tracks every clip alone, and a held-out fit rolls out every track alone: both are a
list of independent jobs. Training is not split: it is one optimisation. ``deform calibrate`` runs
torch with one thread (small tensors, one rod: a second thread gains little), so without workers a
2-core machine left one core idle through every tracking pass, the damping search, the held-out fits
and the parameter ranges, on 280 s of clips about 60 % of a calibration.

Every job runs with one torch thread, as the calibration does by default, and its result is put back
in the order of the jobs: the numbers do not depend on the number of workers. Processes are spawned,
not forked (a fork after torch has started its thread pool can deadlock).

Why a process pool of the standard library rather than Ray: one machine's cores for one command a
user runs with no set-up (as :mod:`deform.diagnose.pool`).
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, TypeVar

from tqdm import tqdm

T = TypeVar("T")


def _start() -> None:
    import torch

    torch.set_num_threads(1)


class Workers:
    """``workers`` processes (started on first use), or inline with one: ``map`` gives the same
    results either way. A context manager: the processes end with it."""

    def __init__(self, workers: int = 1):
        if workers < 1:
            raise ValueError(f"workers must be at least 1, not {workers}")
        self.workers = workers
        self._pool: ProcessPoolExecutor | None = None

    def map(
        self,
        fn: Callable[..., T],
        items: Sequence[Any],
        *shared: Any,
        desc: str | None = None,
        unit: str = "item",
    ) -> list[T]:
        """``[fn(item, *shared) for item in items]``, the jobs side by side; ``desc``: a progress bar
        over them. ``fn`` must be a module-level function (it is sent to the workers by name)."""
        bar = tqdm(total=len(items), desc=desc, unit=unit, disable=True if desc is None else None)
        with bar:
            if self.workers == 1 or len(items) <= 1:
                out = []
                for item in items:
                    out.append(fn(item, *shared))
                    bar.update()
                return out
            pool = self._start_pool()
            futures = {pool.submit(fn, item, *shared): i for i, item in enumerate(items)}
            results: list = [None] * len(items)
            try:
                for f in as_completed(futures):
                    results[futures[f]] = f.result()
                    bar.update()
            except BaseException:
                for f in futures:
                    f.cancel()
                raise
            return results

    def _start_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                self.workers, mp_context=multiprocessing.get_context("spawn"), initializer=_start
            )
        return self._pool

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> Workers:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
