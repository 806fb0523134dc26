"""Fits of several models stepped as one batch (:mod:`deform.diagnose.stack`): what
:mod:`deform.diagnose.fitting` does for one model, for a selection round's reference and candidates
at once. Each model keeps its own loss, optimiser, schedule, clipping and skipped steps, and its
start chosen as :func:`~deform.diagnose.fitting.fit` chooses it, so that it ends where it would
alone (to rounding: 1e-15 of a step, grown by the optimiser to about 1e-9 of a parameter)."""

from __future__ import annotations

import copy
import dataclasses
import random

import torch
from tqdm import tqdm

from deform.diagnose.fitting import (
    FitBudget,
    apply_point,
    fit,
    fit_nominals,
    forward_loss,
    held_out_windows,
    make_windows,
    optimiser,
    rank_starts,
    update,
    window_schedule,
)
from deform.diagnose.simulator import Simulator
from deform.diagnose.stack import Stack
from deform.io.recordings import Recording


def descend_together(
    sims: list[Simulator],
    recordings: list[Recording],
    budget: FitBudget,
    desc: str,
    fit_nominal: bool = True,
    seeds: list[int] | None = None,
) -> list[dict]:
    """:func:`deform.diagnose.fitting._descend` of every simulator, stepped as one batch: the same
    windows (or each simulator those of its own seed), each simulator its own loss, Adam,
    learning-rate schedule, gradient clipping and skipped steps (a diverged model does not stop the
    others).

    Args:
        sims: the simulators (see :class:`Stack`).
        recordings: fit recordings.
        budget: iterations, windows, learning rates.
        desc: progress bar label.
        fit_nominal: also fit the nominal parameters.
        seeds: per simulator the seed of its windows (None: ``budget.seed`` for all).

    Returns:
        Per simulator ``{"loss_history_m", "skipped"}``.
    """
    stack = Stack(sims)
    seeds = seeds or [budget.seed] * len(sims)
    rngs = {seed: random.Random(seed) for seed in seeds}
    opts, scheds = zip(*(optimiser(s, budget, fit_nominal) for s in sims))
    history: list[list[float]] = [[] for _ in sims]
    skipped = [0] * len(sims)
    bar = tqdm(
        range(budget.iterations), desc=desc, disable=None if budget.progress else True, leave=False, unit="it"
    )
    for i in bar:
        horizon, batch = window_schedule(budget, recordings, i)
        drawn = {
            seed: make_windows(recordings, batch, horizon, budget.margin, rng, budget.transported)
            for seed, rng in rngs.items()
        }
        X, d1, origin = (list(w) for w in zip(*(drawn[seed] for seed in seeds)))
        for opt in opts:
            opt.zero_grad(set_to_none=True)
        preds, stacked = stack.rollout(X, horizon, budget.margin, create_graph=True, d1=d1, origin=origin)
        end = budget.margin + 2 + horizon
        losses = [(p - x[:, budget.margin + 2 : end]).abs().mean() for p, x in zip(preds, X)]
        finite = [bool(torch.isfinite(loss)) for loss in losses]
        if any(finite):
            stack.backward(sum(loss for loss, ok in zip(losses, finite) if ok), stacked)
        for k, s in enumerate(sims):
            skipped[k] += not update(s, opts[k], scheds[k], finite[k])
            history[k].append(float(losses[k].detach()))
        bar.set_postfix(best=f"{min(h[-1] for h in history) * 100:.3f}cm")
    return [{"loss_history_m": h, "skipped": n} for h, n in zip(history, skipped)]


def fit_together(
    members: list[tuple[Simulator, object | None]],
    recordings: list[Recording],
    budget: FitBudget,
    desc: str,
    seeds: list[int] | None = None,
) -> list[tuple[Simulator, dict]]:
    """:func:`deform.diagnose.fitting.fit` of several simulators, their descents stepped as one batch.

    A member ``(simulator, new term or None)`` with a new term is started from the best
    ``budget.starts`` points of its grid, each a copy of the simulator descended beside the others;
    the end point with the lowest loss on held-out windows of the fit recordings is kept (first on a
    tie), as :func:`~deform.diagnose.fitting.fit` keeps it.

    Args:
        members: simulators and the term each just added.
        recordings: fit recordings.
        budget: the fit's budget (one for all: they are stepped together).
        desc: progress bar label.
        seeds: per member the seed of its windows, as ``budget.seed`` (None: the budget's for all).

    Returns:
        Per member the fitted simulator (a copy when it had several starts; its new term is at the
        same index in ``terms``) and ``{"loss_history_m", "skipped"}``, with several starts also
        ``"starts"``: each start's point and held-out loss.
    """
    budgets = [
        budget if seeds is None else dataclasses.replace(budget, seed=seed) for seed in seeds or members
    ]
    runs: list[tuple[int, bool, dict | None, Simulator]] = []  # (member, one of several starts, point, sim)
    for i, (sim, term) in enumerate(members):
        ranked = rank_starts(sim, term, recordings, budgets[i]) if term is not None else []
        if len(ranked) <= 1 or budget.starts <= 1:
            if ranked:
                apply_point(sim, term, ranked[0][1])
            runs.append((i, False, None, sim))
            continue
        index = sim.terms.index(term)
        for _, point in ranked[: budget.starts]:  # a point None: the term's current values
            start = copy.deepcopy(sim)
            apply_point(start, start.terms[index], point)
            runs.append((i, True, point, start))
    outs = descend_together(
        [r[3] for r in runs], recordings, budget, desc, seeds=[budgets[r[0]].seed for r in runs]
    )
    held_out: dict[int, tuple] = {}  # per seed
    best: dict[int, tuple] = {}
    starts: dict[int, list] = {}
    for (i, several, point, sim), out in zip(runs, outs):
        if not several:
            best[i] = (0.0, sim, out)
            continue
        b = budgets[i]
        if b.seed not in held_out:
            held_out[b.seed] = held_out_windows(recordings, b)
        sim.sync()
        loss = forward_loss(sim, held_out[b.seed], b)
        starts.setdefault(i, []).append({"point": point, "loss_m": loss})
        if i not in best or loss < best[i][0]:
            best[i] = (loss, sim, out)
    return [
        (best[i][1], {**best[i][2], **({"starts": starts[i]} if i in starts else {})})
        for i in range(len(members))
    ]


def descend_nominals(
    sims: list[Simulator], recordings: list[Recording], budget: FitBudget, desc: str
) -> None:
    """A descent of simulators with no new term, stepped as one batch; of one alone,
    :func:`~deform.diagnose.fitting.fit` (its numbers to the bit)."""
    if len(sims) == 1:
        fit(sims[0], recordings, budget, desc=desc)
    else:
        descend_together(sims, recordings, budget, desc)


def fit_nominals_together(
    sims: list[Simulator], recordings: list[Recording], budget: FitBudget, clamp_restart_m: float | None
) -> list[dict]:
    """:func:`deform.diagnose.fitting.fit_nominal` of several simulators of one rod (at other model
    steps: the tool's fits at the candidates' step and at the slow terms' finer one), their descents
    stepped as one batch (:func:`descend_nominals`)."""
    return fit_nominals(
        sims,
        recordings,
        budget,
        clamp_restart_m,
        lambda group, desc: descend_nominals(group, recordings, budget, desc),
    )
