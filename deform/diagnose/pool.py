"""Fits of a selection round run in parallel processes: they are independent of each other.

Every fit draws its windows from a ``random.Random`` seeded by its own budget, and torch runs one
thread in every process, so a fit gives the same numbers in a worker as inline: the names do not
depend on ``workers``. Processes are spawned (not forked): a fork after torch has started its
thread pool can deadlock. Each worker receives the recordings once, at its start.

Why a process pool of the standard library rather than Ray: this is one machine's cores, for one
command a user runs with no set-up; the benchmarks that spread many diagnoses over machines use
Ray around whole ``deform diagnose`` runs.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from typing import Any

from tqdm import tqdm

from deform.diagnose.checked_fit import CheckErrors, fit_and_check_together, fit_nominals_at
from deform.diagnose.spec import Inputs

_INPUTS: Inputs | None = None  # a worker's recordings, set once by _start


def _start(inputs: Inputs) -> None:
    import torch

    global _INPUTS
    _INPUTS = inputs
    torch.set_num_threads(1)


def fit_together_job(spec, nominal, members, budget, desc: str, inputs=None):
    """:func:`deform.diagnose.checked_fit.fit_and_check_together` -> per member ``(simulator,
    CheckErrors)``."""
    return fit_and_check_together(spec, nominal, members, inputs or _INPUTS, budget, desc)


def nominal_fits_job(spec, start, budget, steps: list[float], desc: str, from_model: bool, inputs=None):
    """:func:`deform.diagnose.checked_fit.fit_nominals_at` -> per model step ``(simulator, coarse,
    clamp restart, CheckErrors on the check recordings)``."""
    inputs = inputs or _INPUTS
    fitted = fit_nominals_at(spec, start, inputs.fit, budget, steps, desc, from_model)
    checked = CheckErrors.of_all([sim for sim, _, _ in fitted], inputs.check)
    return [(*f, c) for f, c in zip(fitted, checked, strict=True)]


@dataclass
class Job:
    """One fit of a batch: ``make()`` -> ``(job function, args)``, called when the job is sent (so
    it may read what earlier jobs gave); ``cost`` ranks jobs, the costliest first."""

    key: Any
    cost: float
    make: Callable[[], tuple]


class FitPool:
    """``submit(job, *args)`` -> a Future; ``workers`` 1 runs each job at once, in this process,
    with the progress bars of the fits; more runs them in that many spawned processes, whose fits
    show no bars of their own (the caller counts finished jobs)."""

    def __init__(self, inputs: Inputs, workers: int = 1):
        self.inputs = inputs
        self.workers = max(1, int(workers))
        self._executor: ProcessPoolExecutor | None = None
        if self.workers > 1:
            self._executor = ProcessPoolExecutor(
                self.workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_start,
                initargs=(inputs,),
            )

    @property
    def parallel(self) -> bool:
        return self._executor is not None

    def submit(self, job, *args) -> Future:
        if self._executor is not None:
            return self._executor.submit(job, *args)
        out: Future = Future()
        try:
            out.set_result(job(*args, inputs=self.inputs))
        except Exception as exc:  # the caller's .result() raises it, as from a process
            out.set_exception(exc)
        return out

    def run(self, jobs: list[Job], desc: str) -> dict:
        """Every job's result, by key. Whenever a process is free, the costliest job left is sent
        (longest first: the round does not end on one long fit started last).

        Args:
            jobs: the batch.
            desc: the bar's label (worker processes only; inline fits show their own bars).
        """
        pending = sorted(jobs, key=lambda j: -j.cost)
        running: dict[Future, Any] = {}
        results: dict = {}
        bar = tqdm(
            total=len(jobs), desc=desc, unit="fit", leave=False, disable=True if not self.parallel else None
        )
        while pending or running:
            while pending and len(running) < self.workers:
                job = pending.pop(0)
                fn, args = job.make()
                running[self.submit(fn, *args)] = job.key
            done, _ = wait(list(running), return_when=FIRST_COMPLETED)
            for f in done:
                results[running.pop(f)] = f.result()
                bar.update()
        bar.close()
        return results

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    def __enter__(self) -> FitPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
