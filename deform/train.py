"""Training: system identification of the physical parameters jointly with the residual network.

Loss: open-loop L1 over a horizon (100 steps by default) of windows cut from the train recordings,
each started from two observed frames with the gripped vertices given at every step, exactly as
evaluation does. Gradients flow through the whole rollout (the closed-form forces of
:mod:`deform.rod.forces` differentiated by autograd with ``create_graph``, twist angles by the implicit function theorem, PBD by plain autograd).
Checkpoints hold the model, the optimiser, the step and the RNG state, so a run resumes exactly.
"""

from __future__ import annotations

import json
import math
import random
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from deform.errors import UsageError
from deform.io.recordings import Recording
from deform.model import DeformModel, gripped_indices
from deform.terms import attach, tie, without


@dataclass
class TrainConfig:
    iterations: int = 300
    batch: int = 32
    horizon: int = 100
    curriculum: tuple[int, ...] = (10, 25, 50)  # shorter horizons first, each for `curriculum_iters`
    curriculum_iters: int = 20
    lr_physics: float = 2e-2
    lr_network: float = 1e-3
    residual: bool = True
    sysid: bool = True
    seed: int = 0
    time_limit_s: float | None = None
    log_every: int = 10
    rest_curvature_penalty: float = 1e-3  # L2 on the rest curvature [m per unit curvature^2]
    lr_final_fraction: float = 0.1  # cosine decay of the learning rates
    rest_curvature_lr_scale: float = 0.05
    coarse_sysid: bool = True
    # the bending scheme (deform.rod.implicit): "auto" lets the coarse identification choose it by the
    # step ratio (without one, the starting model's stays); "explicit" / "implicit" fix it
    bending: str = "auto"
    drag: bool = True  # False: no quadratic air drag (fixed at its floor), linear damping only
    transported_frames: bool = (
        True  # windows start in the reference frames evaluation carries (sample_windows)
    )
    terms: tuple[str, ...] = ()  # physics added to the model (deform.terms.ADDED); built-in ones are on
    without: tuple[str, ...] = ()  # built-in physics removed, for an ablation (deform.terms.BUILT_IN)
    extra: dict = field(default_factory=dict)


def nominal_rest_lengths(recordings: list[Recording]) -> torch.Tensor:
    """(m,) median over recordings of the first frame's edge lengths (the markers' spacing).

    Args:
        recordings: each ``positions`` (T, n, 3).

    Returns:
        (n-1,) float64 [m].
    """
    first = np.stack([np.linalg.norm(np.diff(r.positions[0], axis=0), axis=-1) for r in recordings])
    return torch.tensor(np.median(first, axis=0), dtype=torch.float64)


def split_validation(recordings: list[Recording], every: int = 5) -> tuple[list[Recording], list[Recording]]:
    """Every ``every``-th recording (by sorted name) is held out for validation.

    Args:
        recordings: all training recordings, sorted by name.
        every: hold out one in ``every``.

    Returns:
        ``(train, validation)``.
    """
    val = recordings[::every]
    train = [r for r in recordings if r not in val]
    return train, val


def long_enough(recordings: list[Recording], horizon: int) -> list[Recording]:
    """The recordings a ``horizon``-step window (``horizon + 2`` frames) can be cut from; a
    UsageError naming the longest when there is none.

    Args:
        recordings: candidates.
        horizon: steps per window.

    Returns:
        The usable recordings.
    """
    usable = [r for r in recordings if r.n_frames >= horizon + 2]
    if not usable:
        longest = max((r.n_frames for r in recordings), default=0)
        raise UsageError(
            f"a {horizon}-step window needs recordings of at least {horizon + 2} frames; "
            f"the longest has {longest}"
        )
    return usable


def sample_windows(
    recordings: list[Recording], batch: int, horizon: int, rng: random.Random, transported: bool = True
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The windows and start directors of :func:`sample_weighted_windows` (the same draws)."""
    windows, d1, _ = sample_weighted_windows(recordings, batch, horizon, rng, transported)
    return windows, d1


def sample_weighted_windows(
    recordings: list[Recording], batch: int, horizon: int, rng: random.Random, transported: bool = True
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """(B, horizon + 2, n, 3) windows (two frames to start from, ``horizon`` frames to predict) and
    the reference directors (B, n-1, 3) to start them in. Recordings shorter than ``horizon + 2``
    frames are skipped; a UsageError when all are. The predicted frames are a recording's
    :attr:`~deform.Recording.scored` positions, the two start frames its ``positions``.

    ``transported``: the directors a rollout from the recording's first frame carries at the window's
    start (``Recording.reference_frames``), so that training states have the twist and material frame
    that evaluation's states have; otherwise None (fresh space-parallel frames for every window).

    Args:
        recordings: each ``positions`` (T, n, 3).
        batch: windows.
        horizon: steps to predict per window.
        rng: chooses recordings and start frames.
        transported: start in the directors evaluation carries.

    Returns:
        ``(windows, d1, weights)``: (B, horizon + 2, n, 3) float64, (B, n-1, 3) or None, and the
        predicted frames' weights (B, horizon, n) when any recording has ``weights``, else None.
    """
    usable = long_enough(recordings, horizon)  # too short for a window: not sampled
    weighted = any(r.weights is not None for r in usable)
    out, frames, weights = [], [], []
    for _ in range(batch):
        r = rng.choice(usable)
        s = rng.randrange(0, r.n_frames - horizon - 2 + 1)
        out.append(np.concatenate([r.positions[s : s + 2], r.scored[s + 2 : s + horizon + 2]]))
        if transported:
            frames.append(r.reference_frames[s + 1])
        if weighted:
            w = np.ones(r.positions.shape[:2]) if r.weights is None else r.weights
            weights.append(w[s + 2 : s + horizon + 2])
    X = torch.tensor(np.stack(out), dtype=torch.float64)
    return (
        X,
        torch.tensor(np.stack(frames), dtype=torch.float64) if transported else None,
        torch.tensor(np.stack(weights), dtype=torch.float64) if weighted else None,
    )


def rollout_loss(
    model: DeformModel,
    windows: torch.Tensor,
    d1: torch.Tensor | None = None,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    r"""Open-loop L1 of the model over windows, from their first two frames with the gripped vertices
    given (the paper's protocol), differentiable. With ``weights`` :math:`w_{bkv}` the mean is
    weighted: :math:`\sum w \, |\hat{x} - x| / (3 \sum w)`, so positions nobody saw (weight 0)
    teach nothing.

    Args:
        model: the model.
        windows: (B, h + 2, n, 3).
        d1: (B, n-1, 3) start directors or None.
        weights: (B, h, n) per predicted position, or None (all 1).

    Returns:
        A scalar [m].
    """
    idx = gripped_indices(model.n)
    state = model.initial_state(windows[:, 0], windows[:, 1], d1=d1)
    pred, _ = model.rollout(state, windows[:, 2:, idx], create_graph=True)
    err = (pred - windows[:, 2:]).abs()
    if weights is None:
        return err.mean()
    w = weights.to(err.dtype).unsqueeze(-1)
    return (w * err).sum() / (3 * w.sum()).clamp_min(1e-12)


COARSE_STIFFNESS = (1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2)  # bending stiffness grid [N m^2]
COARSE_SOFTER = (3e-5, 1e-5, 3e-6)  # tried in turn while the softest so far is the best
COARSE_STIFFER = (1e-1, 3e-1)  # tried in turn while the stiffest so far is the best (a cable)
COARSE_DAMPING = (0.3, 1.0, 3.0)  # [1/s]


def coarse_identification(
    model: DeformModel,
    recordings: list[Recording],
    steps: int = 200,
    max_recordings: int = 8,
    progress: bool = True,
    choose_scheme: bool = True,
) -> dict:
    """Grid search of one stiffness scale and the damping before gradient descent.

    Stiffness of real cables spans orders of magnitude and the open-loop loss is far from convex in
    it; a coarse log-grid on a few recordings puts gradient descent in the right basin (seconds).
    When the softest grid point is the best, the grid goes on below it half a decade at a time (down
    to 3e-6 N m^2) while the softest stays the best; likewise above the stiffest (up to 0.3 N m^2).
    Each point is scored with the bending scheme it would be stepped with
    (:meth:`deform.model.DeformModel.choose_bending_scheme`); the best point's is kept
    (``choose_scheme=False``: the model's own scheme throughout).

    Args:
        model: the model, changed in place (stiffness scale and damping).
        recordings: training recordings (a few are used).
        steps: open-loop steps scored per recording.
        max_recordings: recordings used at most.
        progress: progress bar.
        choose_scheme: choose the bending scheme per point by the step ratio.

    Returns:
        ``{"l1_m", "bend_stiffness", "damping", "implicit_bending", "substeps"}`` of the best grid point.
    """
    recs = recordings[:: max(1, len(recordings) // max_recordings)][:max_recordings]
    base_beta, base_gamma = model.log_beta.detach().clone(), model.log_gamma.detach().clone()
    shift0 = float(base_beta.mean())
    options = model.options.residual
    model.options.residual = False
    best = (math.inf, 0.0, float(model.log_damping.detach()))

    def scored(stiffnesses) -> None:
        nonlocal best
        grid = [(math.log(ei), math.log(c)) for ei in stiffnesses for c in COARSE_DAMPING]
        for log_ei, log_c in tqdm(
            grid, desc="coarse identification", disable=None if progress else True, leave=False
        ):
            with torch.no_grad():
                model.log_beta.copy_(base_beta - shift0 + log_ei)
                model.log_gamma.copy_(base_gamma - shift0 + log_ei)
                model.log_damping.fill_(log_c)
            if choose_scheme:
                model.choose_bending_scheme()  # a stiff point is scored as the model will step it
            err = validation_l1(model, recs, steps)
            if err < best[0]:
                best = (err, log_ei, log_c)

    scored(COARSE_STIFFNESS)
    # a rope softer than the grid (a string, a yarn) or stiffer (a cable): while the grid's edge is
    # the best, the next half decade beyond it. The shipped ropes span 1e-4..1.3e-2 N m^2; stiff
    # points are stepped implicitly (choose_bending_scheme), without which the 10 ms step of a
    # 20-100 g rope at 12 vertices rang from 0.003-0.01 N m^2 on.
    for edge, beyond in ((COARSE_STIFFNESS[0], COARSE_SOFTER), (COARSE_STIFFNESS[-1], COARSE_STIFFER)):
        for ei in beyond:
            if not math.isclose(math.exp(best[1]), edge, rel_tol=1e-9):
                break
            scored([ei])
            edge = ei
    with torch.no_grad():
        model.log_beta.copy_(base_beta - shift0 + best[1])
        model.log_gamma.copy_(base_gamma - shift0 + best[1])
        model.log_damping.fill_(best[2])
    model.options.residual = options
    if choose_scheme:
        model.choose_bending_scheme()  # kept through the descent that follows (one scheme per model)
    return {
        "l1_m": best[0],
        "bend_stiffness": math.exp(best[1]),
        "damping": math.exp(best[2]),
        "implicit_bending": model.cfg.implicit_bending,
        "substeps": model.cfg.substeps,
    }


def parameter_groups(model: DeformModel, cfg: TrainConfig) -> list[dict]:
    """Adam's parameter groups: the physics (and extension terms), the rest curvature (slower), the
    residual network; what ``cfg`` leaves out is frozen.

    Args:
        model: the model.
        cfg: ``sysid``, ``residual``, ``drag``, ``without`` and the learning rates.

    Returns:
        The groups.
    """
    physics = [model.log_beta, model.log_gamma, model.extra_mass_raw, model.log_damping]
    physics += list(model.extensions.parameters())  # physics terms attached by deform.terms
    physics = [p for p in physics if p.requires_grad]  # frozen by an ablation (deform.terms.without)
    if cfg.drag and "aerodynamic_drag" not in cfg.without:
        physics.append(model.log_drag)
    else:
        with torch.no_grad():
            model.log_drag.fill_(math.log(1e-4))
        model.log_drag.requires_grad_(False)
    groups = []
    if cfg.sysid:
        groups.append({"params": physics, "lr": cfg.lr_physics})
        # the rest curvature is poorly identifiable (its effect depends on the unobserved twist):
        # it moves slowly so that it only captures what is consistent across recordings
        if model.wbar.requires_grad:
            groups.append({"params": [model.wbar], "lr": cfg.lr_physics * cfg.rest_curvature_lr_scale})
    else:
        for p in physics + [model.wbar]:
            p.requires_grad_(False)
    if cfg.residual:
        groups.append({"params": list(model.residual.parameters()), "lr": cfg.lr_network})
    else:
        for p in model.residual.parameters():
            p.requires_grad_(False)
    return groups


def clamp_physical(model: DeformModel) -> None:
    """Keep identified parameters in physically plausible ranges (explicit integration stays stable).

    Args:
        model: changed in place.
    """
    with torch.no_grad():
        model.log_beta.clamp_(math.log(1e-6), math.log(0.3))
        model.log_gamma.clamp_(math.log(1e-6), math.log(0.3))
        model.wbar.clamp_(-1.0, 1.0)
        model.log_damping.clamp_(math.log(1e-3), math.log(20.0))
        model.log_drag.clamp_(math.log(1e-4), math.log(20.0))
        model.extra_mass_raw.clamp_(-10.0, 10.0)


def horizon_at(it: int, cfg: TrainConfig) -> int:
    """The curriculum's horizon at an iteration.

    Args:
        it: iteration (0-based).
        cfg: ``curriculum``, ``curriculum_iters``, ``horizon``.

    Returns:
        Steps per window.
    """
    stage = it // max(cfg.curriculum_iters, 1)
    return cfg.curriculum[stage] if stage < len(cfg.curriculum) else cfg.horizon


def validation_l1(model: DeformModel, recordings: list[Recording], steps: int) -> float:
    r"""Mean over recordings of the open-loop L1 from each one's first two frames: the paper's metric
    for a recording without ``weights``; with them, as training scores a window
    (:func:`rollout_loss`), :math:`\sum w \, |\hat{x} - y| / (3 \sum w)` against its
    :attr:`~deform.Recording.scored` positions. A recording whose steps carry no weight counts as
    nothing (none counting: infinity).

    Args:
        model: the model.
        recordings: each ``positions`` (T, n, 3).
        steps: steps predicted per recording.

    Returns:
        L1 [m].
    """
    from deform.evaluate import paper_l1, predict_recordings

    fits = []
    for r, res in zip(recordings, predict_recordings(model, recordings, steps)):
        if r.weights is None:
            fits.append(paper_l1(res.prediction, res.truth))
            continue
        s = len(res.prediction)
        w = r.weights[2 : s + 2, :, None]
        if w.sum() > 0:
            fits.append(float((w * np.abs(res.prediction - r.scored[2 : s + 2])).sum() / (3 * w.sum())))
    return float(np.mean(fits)) if fits else math.inf


@dataclass
class Progress:
    """Where a run stands: what a checkpoint restores besides the model and the optimiser."""

    iteration: int = 0
    best_val_l1_m: float = math.inf
    skipped: int = 0


def make_optimizer(
    model: DeformModel, cfg: TrainConfig
) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LambdaLR]:
    """Adam over the parameter groups, with a cosine decay to ``lr_final_fraction`` of the rates.

    Args:
        model: the model (with any extension terms attached).
        cfg: learning rates and iterations.

    Returns:
        ``(optimizer, scheduler)``.
    """
    opt = torch.optim.Adam(parameter_groups(model, cfg))
    floor = cfg.lr_final_fraction

    def rate(it: int) -> float:
        return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * min(it / max(cfg.iterations, 1), 1.0)))

    return opt, torch.optim.lr_scheduler.LambdaLR(opt, rate)


def save_checkpoint(
    path: Path, model: DeformModel, opt, scheduler, progress: Progress, rng: random.Random
) -> None:
    """Everything :func:`resume_from` needs to continue exactly: model, optimiser, schedule, RNG states.

    Args:
        path: ``checkpoint.pt``.
        model: the model.
        opt: the optimizer.
        scheduler: the learning-rate schedule.
        progress: iteration, best validation error, skipped updates.
        rng: the window sampler's random state.
    """
    torch.save(
        {
            "model": model.state_dict(),
            "optimizer": opt.state_dict(),
            "iteration": progress.iteration,
            "scheduler": scheduler.state_dict(),
            "best": progress.best_val_l1_m,
            "rng": rng.getstate(),
            "torch_rng": torch.get_rng_state(),
        },
        path,
    )


def resume_from(path: Path, model: DeformModel, opt, scheduler, rng: random.Random) -> Progress:
    """Restore a checkpoint written by :func:`save_checkpoint` (a fresh Progress when there is none).

    Args:
        path: ``checkpoint.pt``.
        model: loaded in place.
        opt: loaded in place.
        scheduler: loaded in place.
        rng: loaded in place.

    Returns:
        The :class:`Progress` to continue from.
    """
    if not path.is_file():
        return Progress()
    ck = torch.load(path, map_location="cpu", weights_only=False)
    model.load_state_dict(ck["model"])
    opt.load_state_dict(ck["optimizer"])
    scheduler.load_state_dict(ck["scheduler"])
    rng.setstate(ck["rng"])
    torch.set_rng_state(ck["torch_rng"])
    return Progress(iteration=ck["iteration"], best_val_l1_m=ck["best"])


def train_step(
    model: DeformModel,
    opt: torch.optim.Optimizer,
    windows: torch.Tensor,
    d1: torch.Tensor | None,
    cfg: TrainConfig,
    weights: torch.Tensor | None = None,
) -> tuple[float, bool]:
    """One update on a batch of windows (B, h + 2, n, 3). Returns the fit loss [m] and whether the
    update was applied: a non-finite loss or gradient (an unstable window) skips it rather than
    poison the parameters.

    Args:
        model: the model.
        opt: the optimizer.
        windows: (B, h + 2, n, 3) from :func:`sample_windows`.
        d1: (B, n-1, 3) start directors or None.
        cfg: the training settings (penalty, tied parameters).
        weights: (B, h, n) per predicted position (:func:`rollout_loss`), or None.

    Returns:
        ``(loss_m, applied)``.
    """
    opt.zero_grad(set_to_none=True)
    fit = rollout_loss(model, windows, d1, weights)
    loss = fit + cfg.rest_curvature_penalty * model.wbar.pow(2).mean()
    params = [p for g in opt.param_groups for p in g["params"]]
    if torch.isfinite(loss):
        loss.backward()
    ok = bool(torch.isfinite(loss)) and all(p.grad is None or torch.isfinite(p.grad).all() for p in params)
    if ok:
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        clamp_physical(model)
        tie(model, cfg.without)
    return fit.item(), ok


def validate(
    model: DeformModel, val_recs: list[Recording], steps: int, progress: Progress, out_dir: Path
) -> float:
    """Validation L1 [m]; a new best is saved to ``out_dir/best.pt``.

    Args:
        model: the model.
        val_recs: validation recordings.
        steps: open-loop steps per recording.
        progress: holds the best error so far (updated).
        out_dir: the run directory.

    Returns:
        The validation L1 [m].
    """
    val = validation_l1(model, val_recs, steps)
    if val < progress.best_val_l1_m:
        progress.best_val_l1_m = val
        model.save(out_dir / "best.pt", {"val_l1_m": val, "iteration": progress.iteration})
    return val


def train(
    model: DeformModel,
    train_recs: list[Recording],
    val_recs: list[Recording],
    cfg: TrainConfig,
    out_dir: str | Path,
    resume: bool = True,
    progress: bool = True,
) -> dict:
    """Train in place; writes ``out_dir/checkpoint.pt`` (resumable), ``best.pt`` and ``log.jsonl``.

    ``cfg.terms`` are attached to the model first and ``cfg.without`` removed (:mod:`deform.terms`).

    Args:
        model: trained in place.
        train_recs: recordings windows are cut from.
        val_recs: recordings that choose ``best.pt`` (none, or none ever scored finite, e.g. a camera
            track no cloud corrected: the last weights are saved).
        cfg: :class:`TrainConfig`.
        out_dir: the run directory.
        resume: continue from ``checkpoint.pt`` when there is one.
        progress: progress bar.

    Returns:
        ``best_val_l1_m``, the ``last`` log entry, the ``coarse_identification`` result, the median
        seconds per iteration, ``terms``, ``without`` and ``term_starts``.
    """
    long_enough(train_recs, cfg.horizon)  # before any work: the first training batch could not be cut
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():  # before attaching: terms are fixed on these typical rest lengths
        model.nominal_rest.copy_(nominal_rest_lengths(train_recs))
    attach(model, cfg.terms, train_recs)
    without(model, cfg.without)
    model.options.residual = cfg.residual
    if cfg.bending not in ("auto", "explicit", "implicit"):
        raise ValueError(f"bending={cfg.bending!r}: choose one of auto, explicit, implicit")
    if cfg.bending != "auto":
        model.cfg.implicit_bending = cfg.bending == "implicit"
    torch.manual_seed(cfg.seed)
    rng = random.Random(cfg.seed)
    opt, scheduler = make_optimizer(model, cfg)
    ckpt_path = out_dir / "checkpoint.pt"
    state = resume_from(ckpt_path, model, opt, scheduler, rng) if resume else Progress()
    start = state.iteration
    coarse = None
    if start == 0 and cfg.sysid and cfg.coarse_sysid:
        coarse = coarse_identification(
            model, train_recs, progress=progress, choose_scheme=cfg.bending == "auto"
        )
        tie(model, cfg.without)
    term_starts = coarse_start(model, cfg.terms, train_recs) if start == 0 and cfg.terms else None
    val_steps = min(cfg.horizon * 5, min(r.n_frames for r in val_recs) - 2) if val_recs else 0
    t_start = time.perf_counter()
    iter_times = []
    bar = tqdm(
        range(start, cfg.iterations),
        initial=start,
        total=cfg.iterations,
        disable=None if progress else True,  # None: tqdm shows bars on a terminal only
        desc=f"train {model.cfg.name}",
        unit="it",
    )
    last = {}
    # resumed, the log goes on; started afresh (--fresh), a discarded run's lines would read as this one's
    with (out_dir / "log.jsonl").open("a" if start else "w") as log:
        for it in bar:
            t0 = time.perf_counter()
            horizon = horizon_at(it, cfg)
            windows, d1, weights = sample_weighted_windows(
                train_recs, cfg.batch, horizon, rng, cfg.transported_frames
            )
            fit, ok = train_step(model, opt, windows, d1, cfg, weights)
            state.skipped += not ok
            state.iteration = it + 1
            iter_times.append(time.perf_counter() - t0)
            scheduler.step()
            bar.set_postfix(loss=f"{fit * 100:.3f}cm", h=horizon)
            last = {
                "iteration": it + 1,
                "loss_m": fit,
                "horizon": horizon,
                "seconds": iter_times[-1],
                "skipped": state.skipped,
            }
            done = it + 1 == cfg.iterations or (
                cfg.time_limit_s and time.perf_counter() - t_start > cfg.time_limit_s
            )
            if val_recs and ((it + 1) % cfg.log_every == 0 or done):
                last["val_l1_m"] = validate(model, val_recs, val_steps, state, out_dir)
            log.write(json.dumps(last) + "\n")
            log.flush()
            if (it + 1) % cfg.log_every == 0 or done:
                save_checkpoint(ckpt_path, model, opt, scheduler, state, rng)
            if done:
                break
    if not val_recs or not (out_dir / "best.pt").exists():  # none, or never a finite fit
        model.save(out_dir / "best.pt", {"iteration": last.get("iteration", start)})
    return {
        "best_val_l1_m": state.best_val_l1_m,
        "last": last,
        "coarse_identification": coarse,
        "seconds_per_iteration_p50": float(np.median(iter_times)) if iter_times else None,
        "terms": list(cfg.terms),
        "term_starts": term_starts,
        "without": list(cfg.without),
    }


def coarse_start(model, names, recordings, steps: int = 100, max_recordings: int = 4) -> dict[str, dict]:
    """Start each attached term of ``names`` at the best point of its coarse grid.

    A term's effect can be decades away from its default start (a drag coefficient, a plane's
    height), further than Adam moves in a fine-tuning budget. Each term's grid (``Term.grid``, the
    discrepancy tool's multi-start) is scored by open-loop L1 over ``steps`` steps of a few
    recordings, and the best point kept. Entries that move the tool's own nominal model are skipped:
    here the model's parameters are already identified.

    Returns:
        Per term, the chosen raw values and their L1 [m].
    """
    from deform.evaluate import metrics, predict_recordings

    recs = recordings[:: max(1, len(recordings) // max_recordings)][:max_recordings]
    chosen = {}
    for term in model.extensions:
        if getattr(term, "name", None) not in names or not hasattr(term, "grid"):
            continue
        raw = dict(term.named_parameters())
        points, seen = [], set()
        for point in term.grid():
            point = {k: v for k, v in point.items() if k in raw}
            key = repr(sorted(point.items()))
            if point and key not in seen:
                seen.add(key)
                points.append(point)
        initial = {k: p.detach().clone() for k, p in raw.items()}
        best = (math.inf, {})
        for point in [{}, *points]:
            with torch.no_grad():
                for k, p in raw.items():
                    p.copy_(torch.as_tensor(point.get(k, initial[k]), dtype=p.dtype))
                err = metrics(predict_recordings(model, recs, steps))["l1_m"]
            if err < best[0]:
                best = (err, point)
        with torch.no_grad():
            for k, p in raw.items():
                p.copy_(torch.as_tensor(best[1].get(k, initial[k]), dtype=p.dtype))
        chosen[term.name] = {
            "l1_m": best[0],
            "start": {k: float(torch.as_tensor(v).sum()) for k, v in best[1].items()},
        }
    return chosen
