"""A simulator fitted on the fit recordings and its errors on the check recordings: the unit of
work of a diagnosis, run inline or in a worker process (:mod:`deform.diagnose.pool`), alone or
with others stepped as one batch (:mod:`deform.diagnose.stack`)."""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from deform.diagnose.fitting import FitBudget, fit
from deform.diagnose.joint_fit import descend_nominals, fit_nominals_together, fit_together
from deform.diagnose.simulator import (
    MAX_STEP_S,
    Nominal,
    Simulator,
    clamp_bound,
    per_recording_l1,
    per_recording_window_l1,
)
from deform.diagnose.spec import Inputs
from deform.diagnose.stack import check_errors


@dataclass
class CheckErrors:
    """Held-out errors of one fitted model, per check recording [m]: ``window``, the mean L1 of
    one-second predictions restarted along each recording, decides (scoring); ``rollout``, the
    paper's full open loop, is what the report states as the check error."""

    rollout: np.ndarray
    window: np.ndarray

    @classmethod
    def of(cls, sim: Simulator, recordings) -> CheckErrors:
        return cls(
            per_recording_l1(sim.predict(recordings), recordings), per_recording_window_l1(sim, recordings)
        )

    @classmethod
    def of_all(cls, sims: list[Simulator], recordings) -> list[CheckErrors]:
        """:meth:`of` every simulator, stepped as one batch (:func:`deform.diagnose.stack.check_errors`)."""
        return [cls(rollout, window) for rollout, window in check_errors(sims, recordings)]


def fit_and_check(
    spec, nominal, terms, inputs: Inputs, budget: FitBudget, desc: str, new_term=None, hidden: int = 0
):
    """A simulator from a copy of ``nominal`` and ``terms``, fitted on ``inputs.fit``, and its
    per-recording check errors.

    Args:
        spec: the rod.
        nominal: the nominal parameters (copied).
        terms: the terms to attach.
        inputs: fit and check recordings.
        budget: the fit's budget.
        desc: progress label.
        new_term: the term just added, started from its coarse grid, or None.
        hidden: simulated nodes between markers.

    Returns:
        ``(simulator, CheckErrors)``.
    """
    sim = Simulator(
        spec, copy.deepcopy(nominal), terms, hidden=hidden, max_step_s=budget.max_step_s or MAX_STEP_S
    )
    fit(sim, inputs.fit, budget, desc=desc, new_term=new_term)
    return sim, CheckErrors.of(sim, inputs.check)


class Member(NamedTuple):
    """One model of :func:`fit_and_check_together`: its terms, the index of its new term in them
    (None: none new), and where it differs from the group: its start (None: the group's nominal)
    and the seed of its windows (None: the budget's)."""

    terms: list
    index: int | None
    nominal: Nominal | None = None
    seed: int | None = None


def fit_and_check_together(
    spec, nominal, members: list[tuple], inputs: Inputs, budget: FitBudget, desc: str
) -> list[tuple[Simulator, CheckErrors]]:
    """:func:`fit_and_check` of several models that share a budget, their descents stepped as one
    batch (:func:`deform.diagnose.joint_fit.fit_together`).

    Args:
        spec: the rod.
        nominal: the nominal parameters the models start from (copied for each).
        members: per model a :class:`Member` (or its fields as a tuple).
        inputs: fit and check recordings.
        budget: the fits' budget.
        desc: progress label.

    Returns:
        Per member ``(simulator, CheckErrors)``; its fitted new term is ``simulator.terms[index]``.
    """
    members = [Member(*m) for m in members]
    max_step = budget.max_step_s or MAX_STEP_S
    sims = [
        Simulator(spec, copy.deepcopy(m.nominal or nominal), m.terms, max_step_s=max_step) for m in members
    ]
    own_seeds = any(m.seed is not None for m in members)
    fitted = fit_together(
        [(sim, None if m.index is None else sim.terms[m.index]) for sim, m in zip(sims, members)],
        inputs.fit,
        budget,
        desc,
        seeds=[budget.seed if m.seed is None else m.seed for m in members] if own_seeds else None,
    )
    fitted_sims = [sim for sim, _ in fitted]
    return list(zip(fitted_sims, CheckErrors.of_all(fitted_sims, inputs.check), strict=True))


def fit_nominals_at(
    spec, start, recordings, budget: FitBudget, steps: list[float], desc: str, from_model: bool
) -> list[tuple]:
    """The nominal parameters fitted from ``start`` with the model stepped at most each of ``steps``
    [s], stepped as one batch: per step ``(simulator, coarse grid's best point, clamp restart)``;
    from a given model (``from_model``), a plain descent with no grid and no restart (a held clamp
    is not restarted either)."""
    sims = [Simulator(spec, copy.deepcopy(start), max_step_s=step) for step in steps]
    if from_model:
        descend_nominals(sims, recordings, budget, desc)
        return [(sim, None, None) for sim in sims]
    started = fit_nominals_together(sims, recordings, budget, 0.5 * clamp_bound(spec))
    return [(sim, out["coarse"], out.get("clamp_restart")) for sim, out in zip(sims, started)]
