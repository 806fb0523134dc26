"""Fitting through the simulator: Adam on open-loop multi-step L1 windows of the fit recordings.

Windows are short (tens of steps) and batched so that one candidate costs seconds; every candidate
sees the same window sequence (same seed) so that their fits are comparable. Optionally
(``FitBudget.final_horizon``) they grow during a descent to the one-second windows the check error
is scored on.
"""

from __future__ import annotations

import copy
import math
import random
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from deform.diagnose.simulator import ROLL_FRAMES, Simulator
from deform.diagnose.stack import window_losses
from deform.io.recordings import Recording


@dataclass
class FitBudget:
    iterations: int = 40
    batch: int = 16
    horizon: int = 30
    lr_terms: float = 0.08
    lr_nominal: float = 0.03
    margin: int = 3  # frames kept around a window for the delay term
    starts: int = 2  # descents from the best points of a new term's grid; the best end is kept (fit)
    seed: int = 0
    progress: bool = True
    transported: bool = True  # windows start with the reference frames a full rollout carries (make_windows)
    # None: every window `horizon` steps (the tool's fits). A number (e.g. 100, the one-second
    # windows the check error is scored on): the descent's windows grow from `horizon` to it over the
    # first `grow` share of iterations, fewer per batch (rod-steps per iteration kept, at least
    # `min_batch`), and starts are ranked and chosen on windows of that length. A study option
    # (diagnose_planted.py --growing-windows): as the default for every term it lost a stiff stretch
    # and tied a table with a mass scale on PyElastica (results/diagnose.growing_windows.runs.jsonl)
    final_horizon: int | None = None
    grow: float = 0.6
    min_batch: int = 4
    # the model's longest step [s] in this fit (None: simulator.MAX_STEP_S): see
    # DiagnoseBudget.slow_step_s
    max_step_s: float | None = None
    anneal: bool = (
        True  # second half: cosine decay of the learning rates to 0: the last iterate settles instead of
    )
    # jittering by one Adam step, which would make two fits of the same model differ by noise


def make_windows(
    recordings: list[Recording],
    batch: int,
    horizon: int,
    margin: int,
    rng: random.Random,
    transported: bool = True,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """(B, horizon + 2 + 2 margin, n, 3) windows cut at random from the recordings, the reference
    directors (B, m, 3) a full rollout would carry at each window's start frame (``margin + 1``),
    and the first frames (B, 2 + ROLL_FRAMES, n, 3) of each window's recording (where a
    material-frame roll is read: :meth:`Simulator.initial_roll`); both None when not
    ``transported`` (fresh frames, the behaviour before they were carried).

    Args:
        recordings: each ``positions`` (T, n, 3).
        batch: windows.
        horizon: steps scored per window.
        margin: extra frames on each side (for a delay term's shifted inputs).
        rng: chooses recordings and start frames.
        transported: start in the directors a full rollout carries.

    Returns:
        ``(windows, d1, origin)``.
    """
    out, frames, origins = [], [], []
    length = horizon + 2 + 2 * margin
    first = min(2 + ROLL_FRAMES, min(r.n_frames for r in recordings))
    for _ in range(batch):
        r = rng.choice(recordings)
        s = rng.randrange(0, r.n_frames - length + 1)
        out.append(r.positions[s : s + length])
        origins.append(r.positions[:first])
        if transported:
            frames.append(r.reference_frames[s + margin + 1])
    X = torch.tensor(np.stack(out), dtype=torch.float64)
    if not transported:
        return X, None, None
    return (
        X,
        torch.tensor(np.stack(frames), dtype=torch.float64),
        torch.tensor(np.stack(origins), dtype=torch.float64),
    )


def window_loss(sim: Simulator, windows, horizon: int, margin: int, create_graph: bool) -> torch.Tensor:
    """Open-loop L1 of the simulator over windows, from their frames ``margin`` and ``margin + 1``.

    Args:
        sim: the simulator.
        windows: ``(X, d1, origin)`` from :func:`make_windows`.
        horizon: steps scored.
        margin: frames before the start.
        create_graph: differentiable (fitting) or not (scoring).

    Returns:
        A scalar [m].
    """
    X, d1, origin = windows
    pred = sim.rollout(X, horizon, margin, create_graph=create_graph, d1=d1, origin=origin)
    return (pred - X[:, margin + 2 : margin + 2 + horizon]).abs().mean()


def _grid_handles(sim: Simulator, term) -> dict:
    named = {k: p for k, p in term.named_parameters()}
    named.update({f"nominal:{k}": p for k, p in sim.nominal.named_parameters()})
    return named


@torch.no_grad()
def apply_point(sim: Simulator, term, point: dict | None) -> None:
    """Set a grid point (see :func:`rank_starts`) on top of the simulator's current values.

    Args:
        sim: the simulator with ``term`` attached.
        term: the term the point belongs to.
        point: ``{raw parameter: value}``, or None (the current values).
    """
    named = _grid_handles(sim, term)
    for k, v in (point or {}).items():
        if k.startswith("nominal:"):
            named[k].add_(v)
        elif isinstance(v, (list, tuple)):
            named[k].copy_(torch.tensor(v, dtype=named[k].dtype))
        else:
            named[k].fill_(v)
    sim.sync()


@torch.no_grad()
def rank_starts(sim: Simulator, term, recordings: list[Recording], budget: FitBudget) -> list[tuple]:
    """The term's current raw values and each point of ``term.grid()``, scored on one fixed batch
    of windows (forward rollouts only), best first. A grid key ``"nominal:NAME"`` adds its value to
    the nominal parameter NAME (a log): a term that takes over part of
    what the nominal model did (drag vs linear damping) is tried together with the nominal share it
    replaces. The simulator is left as it was.

    Args:
        sim: the simulator with ``term`` attached.
        term: the :class:`deform.terms.library.Term` to start.
        recordings: fit recordings.
        budget: batch, horizon and seed of the scoring windows.

    Returns:
        ``[(window loss [m], point or None), ...]``, best first; empty when the term has no grid.
    """
    points = term.grid()
    if not points:
        return []
    windows = make_windows(
        recordings,
        budget.batch,
        longest_horizon(budget, recordings),
        budget.margin,
        random.Random(budget.seed + 1),
        budget.transported,
    )
    index = sim.terms.index(term)
    copies = []
    for point in [None] + points:
        c = copy.deepcopy(sim)
        apply_point(c, c.terms[index], point)
        copies.append(c)
    losses = window_losses(copies, windows, budget.margin)  # every point in one batch
    sim.sync()
    return sorted(zip(losses, [None] + points), key=lambda lp: rank_key(lp[0]))


def rank_key(loss: float) -> float:
    """A loss rounded to 10 significant digits, to rank by: points that tie (a plane that touches
    nothing at two heights) keep their order, whichever batch they were stepped in (a batch moves a
    loss by about 1e-15 of itself: deform.diagnose.stack)."""
    return float(f"{loss:.9e}")


def coarse_start(sim: Simulator, term, recordings: list[Recording], budget: FitBudget) -> dict | None:
    """Set the best point of :func:`rank_starts` on the simulator.
    -> {"grid_loss_m": ..., "chosen": ...} or None (no grid).

    Args:
        sim: the simulator with ``term`` attached.
        term: the term to start.
        recordings: fit recordings.
        budget: batch, horizon and seed of the scoring windows.
    """
    ranked = rank_starts(sim, term, recordings, budget)
    if not ranked:
        return None
    apply_point(sim, term, ranked[0][1])
    return {"grid_loss_m": ranked[0][0], "chosen": ranked[0][1]}


@torch.no_grad()
def forward_loss(sim: Simulator, windows, budget: FitBudget) -> float:
    """Window loss without gradients; a diverged rollout scores infinity."""
    horizon = windows[0].shape[1] - 2 - 2 * budget.margin  # the windows' own length
    return float(torch.nan_to_num(window_loss(sim, windows, horizon, budget.margin, False), nan=math.inf))


def _snapshot(sim: Simulator) -> list[torch.Tensor]:
    return [p.detach().clone() for p in sim.parameters()]


@torch.no_grad()
def _restore(sim: Simulator, saved: list[torch.Tensor]) -> None:
    for p, v in zip(sim.parameters(), saved, strict=True):
        p.copy_(v)
    sim.sync()


def fit(
    sim: Simulator,
    recordings: list[Recording],
    budget: FitBudget,
    desc: str = "fit",
    fit_nominal: bool = True,
    new_term=None,
) -> dict:
    """Fit the simulator's term parameters (and the nominal ones, more slowly) in place.

    ``new_term`` (a term just added) is started from its coarse grid: from each of the
    ``budget.starts`` best points a whole descent is run, and the end point with the lowest loss
    on a fixed batch of other windows of the fit recordings is kept (check recordings are never
    looked at). Why several: a term's loss landscape has basins the grid's forward ranking cannot
    tell apart, because the other parameters have not yet adapted to the term (a table under a
    stiff rope: from the planted truth the descent closed a third of the error, from the grid's
    first choice it stayed worse than no table).

    Args:
        sim: the simulator (nominal model and terms).
        recordings: fit recordings.
        budget: iterations, windows, learning rates, starts.
        desc: progress bar label.
        fit_nominal: also fit the nominal parameters.
        new_term: the term just added, or None.

    Returns:
        ``{"loss_history_m", "skipped"}``, and with several starts ``"starts"``: each start's point
        and end loss.
    """
    ranked = rank_starts(sim, new_term, recordings, budget) if new_term is not None else []
    if len(ranked) <= 1 or budget.starts <= 1:
        if ranked:
            apply_point(sim, new_term, ranked[0][1])
        return _descend(sim, recordings, budget, desc, fit_nominal)
    held_out = held_out_windows(recordings, budget)
    origin, best, starts = _snapshot(sim), None, []
    for k, (_, point) in enumerate(ranked[: budget.starts]):
        _restore(sim, origin)
        apply_point(sim, new_term, point)
        out = _descend(sim, recordings, budget, f"{desc} (start {k + 1})", fit_nominal)
        sim.sync()
        loss = forward_loss(sim, held_out, budget)
        starts.append({"point": point, "loss_m": loss})
        if best is None or loss < best[0]:
            best = (loss, _snapshot(sim), out)
    _restore(sim, best[1])
    return {**best[2], "starts": starts}


def held_out_windows(recordings: list[Recording], budget: FitBudget):
    """A fixed batch of windows of the fit recordings, other than the descent's (its own seed), on
    which the end points of several starts are compared: at least 16 windows of
    :func:`longest_horizon` steps.

    Args:
        recordings: fit recordings.
        budget: the fit's budget.

    Returns:
        Windows as :func:`make_windows` gives them.
    """
    return make_windows(
        recordings,
        max(budget.batch, 16),
        longest_horizon(budget, recordings),
        budget.margin,
        random.Random(budget.seed + 2),
        budget.transported,
    )


def longest_horizon(budget: FitBudget, recordings: list[Recording]) -> int:
    """The window length starts are ranked and chosen on: ``final_horizon`` (else ``horizon``),
    shortened to what the shortest recording holds."""
    want = budget.final_horizon or budget.horizon
    room = min(r.n_frames for r in recordings) - 2 - 2 * budget.margin
    return max(1, min(want, room))


def window_schedule(budget: FitBudget, recordings: list[Recording], iteration: int) -> tuple[int, int]:
    """(horizon, batch) of a descent's ``iteration``: the horizon grows linearly from
    ``budget.horizon`` to :func:`longest_horizon` over the first ``grow`` share of the iterations,
    the batch shrinks so that rod-steps per iteration stay those of the first.

    Why: the decision scores one-second predictions, and a fit on 25-step windows may not tell slow
    dissipation from stiffness or from the nominal damping's share. Short windows first keep the
    early, far-from-optimal steps out of long chaotic rollouts."""
    if budget.final_horizon is None:
        return budget.horizon, budget.batch
    h1 = longest_horizon(budget, recordings)
    h0 = min(budget.horizon, h1)
    ramp = max(1.0, budget.grow * budget.iterations)
    h = round(h0 + (h1 - h0) * min(1.0, iteration / ramp))
    return h, max(budget.min_batch, round(budget.batch * h0 / h))


def optimiser(sim: Simulator, budget: FitBudget, fit_nominal: bool):
    """A descent's Adam over the simulator's term parameters (and, when ``fit_nominal``, its nominal
    ones at their own rate) and its learning-rate schedule (None without ``budget.anneal``): full
    rate for the first half, then cosine decay to 0. -> ``(optimiser, schedule)``."""
    groups = []
    if sim.term_parameters():
        groups.append({"params": sim.term_parameters(), "lr": budget.lr_terms})
    if fit_nominal:
        groups.append({"params": list(sim.nominal.parameters()), "lr": budget.lr_nominal})
    opt = torch.optim.Adam(groups)
    half = budget.iterations / 2
    sched = (
        torch.optim.lr_scheduler.LambdaLR(
            opt, lambda i: 1.0 if i < half else 0.5 * (1 + math.cos(math.pi * (i - half) / half))
        )
        if budget.anneal
        else None
    )
    return opt, sched


def update(sim: Simulator, opt, sched, finite: bool) -> bool:
    """One descent step after the backward pass: clipped, taken and clamped when the loss
    (``finite``) and every gradient are finite, else skipped; the schedule advances either way.
    -> whether the step was taken."""
    params = sim.parameters()
    taken = finite and all(p.grad is None or torch.isfinite(p.grad).all() for p in params)
    if taken:
        torch.nn.utils.clip_grad_norm_(params, 5.0)
        opt.step()
        sim.clamp_()
    if sched is not None:
        sched.step()
    return taken


def _descend(
    sim: Simulator, recordings: list[Recording], budget: FitBudget, desc: str, fit_nominal: bool
) -> dict:
    """Adam on open-loop window losses (the same window sequence for every call with one seed)."""
    rng = random.Random(budget.seed)
    opt, sched = optimiser(sim, budget, fit_nominal)
    history, skipped = [], 0
    bar = tqdm(
        range(budget.iterations), desc=desc, disable=None if budget.progress else True, leave=False, unit="it"
    )
    for i in bar:
        horizon, batch = window_schedule(budget, recordings, i)
        windows = make_windows(recordings, batch, horizon, budget.margin, rng, budget.transported)
        opt.zero_grad(set_to_none=True)
        exprs = sim.sync()
        loss = window_loss(sim, windows, horizon, budget.margin, create_graph=True)
        finite = bool(torch.isfinite(loss))
        if finite:
            sim.backward(loss, exprs)
        skipped += not update(sim, opt, sched, finite)
        history.append(float(loss.detach()))
        bar.set_postfix(loss=f"{float(loss.detach()) * 100:.3f}cm")
    return {"loss_history_m": history, "skipped": skipped}


def coarse_nominal(
    sim: Simulator, recordings: list[Recording], steps: int = 150, max_recordings: int = 4
) -> dict:
    """Log-grid search of EI (GJ tied at 0.7 EI) and damping: puts Adam in the right basin.

    Args:
        sim: the simulator; its nominal parameters are set in place.
        recordings: fit recordings (a few are used).
        steps: open-loop steps scored.
        max_recordings: recordings used at most.

    Returns:
        ``{"l1_m", "bend_stiffness", "damping"}`` of the best point.
    """
    recs = recordings[:: max(1, len(recordings) // max_recordings)][:max_recordings]
    steps = min(steps, min(r.n_frames for r in recs) - 2)
    X = torch.tensor(np.stack([r.positions[: steps + 2] for r in recs]), dtype=torch.float64)
    best = (math.inf, None)
    nom = sim.nominal
    points = [
        (ei, c)
        for ei in (1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2)
        for c in sorted({min(c, nom.damping_max) for c in (0.3, 1.0, 3.0)})
    ]
    copies = []
    for ei, c in points:
        s = copy.deepcopy(sim)
        with torch.no_grad():
            s.nominal.log_ei.fill_(math.log(ei))
            s.nominal.log_gj.fill_(math.log(0.7 * ei))
            s.nominal.log_damping.fill_(math.log(c))
        copies.append(s)
    # every point in one batch: the full rollouts from the first frames (no margin, fresh frames)
    losses = window_losses(copies, (X, None, None), 0)
    for err, point in zip(losses, points):
        err = 1.0 if math.isinf(err) else err  # a diverged rollout scores 1 m, as before
        if err < best[0]:
            best = (err, point)
    ei, c = best[1]
    with torch.no_grad():
        nom.log_ei.fill_(math.log(ei))
        nom.log_gj.fill_(math.log(0.7 * ei))
        nom.log_damping.fill_(math.log(c))
    return {"l1_m": best[0], "bend_stiffness": ei, "damping": c}


CLAMP_RESTART_M = 1e-3  # a fitted clamp shorter than this ended at its lower bound, 0
# the second start replaces the first only when it is this much lower on held-out windows: two ends
# within it are one basin as far as the data tell (on 16 such benchmark fits the second was 0.02-1.4 %
# lower or 0.03-3.6 % higher; the basin that hid a stiff stretch was 14 % worse), and a flip
# between them would be noise
RESTART_MIN_GAIN = 0.02


def fit_nominal(
    sim: Simulator, recordings: list[Recording], budget: FitBudget, clamp_restart_m: float | None
) -> dict:
    """The nominal fit: the coarse grid (:func:`coarse_nominal`), then a descent. When the clamp is
    fitted and ends under :data:`CLAMP_RESTART_M`, both are repeated from a clamp of
    ``clamp_restart_m``, and the second end point is kept when its loss on held-out windows of the
    fit recordings is lower by more than :data:`RESTART_MIN_GAIN` (check recordings are never
    looked at).

    Why: the clamp starts at 0, and there a stiff stretch of rope pulls the coarse grid to a
    uniformly stiffer rope held right at its markers, a basin the descent does not leave. On
    PyElastica's noise-free light rope with a stiff stretch that fit ended at EI 1.9e-3 and a clamp
    of 0.06 mm, with every candidate worse than it; from a clamp of half its bound it ended at EI
    1.0e-3 and 2.5 cm, 14 % lower on held-out fit windows (docs/diagnose.md). A fit that ends with
    a clamp is where the clamp was wanted, so only an end at the bound is tried again.

    Args:
        sim: the simulator; its nominal parameters are set in place.
        recordings: fit recordings.
        budget: the nominal fit's budget.
        clamp_restart_m: the clamp [m] of the second start, or None for no second start.

    Returns:
        ``{"coarse"}`` (the grid's best point) and, when a second start was run, ``"clamp_restart"``:
        its clamp, both ends' held-out losses and which was kept.
    """
    return fit_nominals([sim], recordings, budget, clamp_restart_m)[0]


def fit_nominals(
    sims: list[Simulator],
    recordings: list[Recording],
    budget: FitBudget,
    clamp_restart_m: float | None,
    descend: Callable[[list[Simulator], str], object] | None = None,
) -> list[dict]:
    """:func:`fit_nominal` of several simulators (the same rod at other model steps), their descents
    run by ``descend(simulators, label)``: one after another by default, or stepped as one batch
    (deform.diagnose.joint_fit.fit_nominals_together)."""

    def one_by_one(group: list[Simulator], desc: str) -> None:
        for sim in group:
            fit(sim, recordings, budget, desc=desc)

    descend = descend or one_by_one
    out = [{"coarse": coarse_nominal(sim, recordings)} for sim in sims]
    descend(sims, "nominal fit")
    again = [
        k
        for k, sim in enumerate(sims)
        if clamp_restart_m is not None
        and sim.nominal.clamp_dm.requires_grad
        and float(sim.nominal.clamp_length().detach()) < CLAMP_RESTART_M
    ]
    if not again:
        return out
    held_out = held_out_windows(recordings, budget)
    first = {}
    for k in again:
        sims[k].sync()
        first[k] = (forward_loss(sims[k], held_out, budget), _snapshot(sims[k]))
        sims[k].nominal.set_clamp(clamp_restart_m, fitted=True)
        out[k]["clamp_restart"] = {
            "clamp_start_m": clamp_restart_m,
            "coarse": coarse_nominal(sims[k], recordings),
        }
    descend([sims[k] for k in again], "nominal fit (clamp restart)")
    for k in again:
        sims[k].sync()
        second_loss = forward_loss(sims[k], held_out, budget)
        kept = second_loss < (1.0 - RESTART_MIN_GAIN) * first[k][0]
        if not kept:
            _restore(sims[k], first[k][1])
        out[k]["clamp_restart"].update(
            {
                "held_out_loss_m": {"clamp_0": first[k][0], "clamp_restart": second_loss},
                "kept": "clamp_restart" if kept else "clamp_0",
            }
        )
    return out


def laplace_uncertainty(
    sim: Simulator, recordings: list[Recording], budget: FitBudget, term
) -> dict[str, float]:
    """Approximate 1-sigma of the term's physical parameters: diagonal curvature of the window
    loss by finite differences, residual windows treated as independent Laplace samples.

    Args:
        sim: the fitted simulator.
        recordings: fit recordings.
        budget: the windows to evaluate the loss on.
        term: the term whose parameters are assessed.

    Returns:
        Physical parameter name -> standard deviation; None where the loss has no positive
        curvature there (flat or rough at the fit: the windows do not determine it).
    """
    rng = random.Random(budget.seed + 777)
    horizon = longest_horizon(budget, recordings)
    windows = make_windows(recordings, max(budget.batch, 16), horizon, budget.margin, rng, budget.transported)

    def loss() -> float:
        sim.sync()
        with torch.no_grad():
            return float(window_loss(sim, windows, horizon, budget.margin, False))

    base = loss()
    n_eff = windows[0].shape[0]
    center = term.params()
    spread: dict[str, float | None] = {k: 0.0 for k in center}
    for p in term.parameters():
        flat = p.data.view(-1)
        for i in range(flat.numel()):
            orig = float(flat[i])
            d = 0.05
            flat[i] = orig + d
            up = loss()
            flat[i] = orig - d
            down = loss()
            curv = (up + down - 2 * base) / d**2
            sigma_raw = math.sqrt(base / (n_eff * curv)) if curv > 0 else math.inf
            undetermined = sigma_raw > 10.0  # (raw parameters are logs and the like: e^10 is no estimate)
            flat[i] = orig + (1.0 if undetermined else sigma_raw)
            hi = term.params()
            flat[i] = orig
            if undetermined:  # the physical parameters this raw one moves
                spread.update({k: None for k in center if hi[k] != center[k]})
                continue
            for k in center:
                if spread[k] is not None:
                    spread[k] = math.hypot(spread[k], hi[k] - center[k]) if math.isfinite(hi[k]) else None
    sim.sync()
    return spread
