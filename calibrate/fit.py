r"""Identification and residual training from camera tracks, tracking again with the better model.

Round 0 tracks every clip with a plain discrete elastic rod known by the given length and mass
(:func:`deform.generic_rod`), then each round trains a copy of the best model so far on the tracks
of the training clips (:func:`deform.train.train`: coarse identification of the stiffness and
damping in the first round, then the physical parameters and the residual network jointly), sets
the damping on the training clips' 3 s predictions (:mod:`calibrate.damping`: the 1 s training windows
barely see a light rope's damping), tracks every clip again with it, and keeps it while the fit on
the held-out clips improves.

The held-out fit is scored against the clouds, not against tracks: tracks change with the model
that made them, the camera's points do not. From the track at step :math:`s` (two frames, as the
paper's metric starts) the model predicts open loop with the recorded grippers for :math:`H` steps
(0.5 s); at each cloud :math:`c` in that window the error is the mean over its rope points
:math:`p` of :math:`\min(d(p, \hat{x}_{k_c}), 5\,\mathrm{cm})`, with :math:`d` the distance to the
predicted rod's polyline. One-sided (cloud to model), so occlusion hides points without adding
error; capped, so that stray rope-coloured points cost no more than a missed rope. The points lie
on the rope's near surface, so a perfect model scores about the rope's radius, not zero.

Training scores a prediction only where and when a cloud corrected the track, against the track
as corrected (:meth:`Track.recording`, :meth:`Track.at_clouds`): between clouds and behind an
occluder the track is the tracker's model's guess, and a loss on it would teach the model its own
prediction. The coarse identification grid of the first round and the validation that picks each
round's best iterate score alike (:func:`deform.train.validation_l1`). The windows start from the
whole tracked shape, smoothed; the coverage in the report says how much of the rope the camera saw.
"""

from __future__ import annotations

import copy
import math
import tempfile
import time
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import torch

from calibrate.bags import Clip
from calibrate.checks import check_length, check_rope_seen, motion_problem
from calibrate.damping import MAX_FITS, settle_damping
from calibrate.errors import CalibrationError
from calibrate.identifiability import FITS as RANGE_FITS
from calibrate.identifiability import parameter_ranges
from calibrate.points import polyline_distances
from calibrate.tracks import Track, cut, track_clip
from calibrate.workers import Workers
from deform import DeformModel, ModelOptions, generic_rod
from deform.train import TrainConfig, train
from service.config import Grippers

CAP_M = 0.05  # a point's error is capped here (a stray point costs no more than a missed rope)
RESERVE_S = 30.0  # kept from the time limit for the parameter ranges and the report after the rounds, at
# least (more when the held-out fits they repeat take longer: end_reserve_s)
DAMPING_TRACKS = 12  # the damping search rolls out at most this many training tracks (60 s of 5 s clips),
# spread over them. On 280 s of clips it rolled out all 44: round 1's work besides training took 873 s
# (round 0's tracking pass: 244 s) and, reserved for, left round 1 one of its 500 training iterations
# (calibrate_rods.300s.implicit, DLO3)
# the rest of a round (after training) is reserved as an earlier round's with this much to spare: the
# same work took 0.82-1.19x as long from round 1 to round 2 on a shared machine (DLO1-4's clips, two
# calibrations side by side); DLO3's second round ran 23 s past its estimate, the calibration 12 s past
# its 20 minutes
SPARE = 1.2
RANGE_TRACKS = 2  # the parameter ranges use at least this many held-out tracks (50 s of clips hold out 2)
REPORT_S = 10.0  # kept from the time limit after the parameter ranges, for the report and the model file
MIN_GAIN = 0.01  # a round is kept when it improves the held-out fit by at least this share
EDGE_M = 0.09  # the default vertex count keeps the rope's edges at most about this long ...
VERTICES = (12, 14)  # ... within these counts (default_vertices)


@dataclass(frozen=True)
class Budget:
    """How much work calibration does: iteration counts, so that the same clips give the same model
    on a fast machine and on a busy one. On 50 s of clips on one core (one worker): tracking about 30 s
    a pass, the first round about 7 min, later rounds about 4 min each; ``rounds`` caps the
    train-and-track-again rounds.

    ``time_limit_s`` keeps the promise of a model within 20 minutes on a slow or crowded machine:
    a later round is not started when its projected time (:func:`projected_round_s`) would pass it,
    and training stops early where the rest of the round (the previous round's time besides
    training; round 1: :func:`first_round_rest_s`; each with :data:`SPARE`) would otherwise pass it
    (the report says which). The third round was kept in 12 of the 29 stored benchmark calibrations
    that ran it, gaining 1.4-3.5 % of held-out fit: what a slow machine mostly loses. Where the limit
    binds, results depend on the machine's speed."""

    iterations: int = 500  # first round: coarse identification, then these training iterations
    refine_iterations: int = 200  # each later round, from the previous round's model
    batch: int = 16
    horizon: int = 100
    curriculum: tuple[int, ...] = (10, 25, 50)
    curriculum_iters: int = 40
    rounds: int = 3
    time_limit_s: float | None = 1200.0  # the whole calibration at most this long (None: no limit)
    score_horizon: int = 50  # steps of the held-out prediction fit (0.5 s)
    score_every: int = 25  # steps between its starts
    damping_horizon: int = 300  # steps of the training clips' predictions that set the damping (3 s; 0: off)
    held_out_every: int = 5  # every k-th clip (by name) is held out; fewer clips: their last 30 % (split)
    seed: int = 0


@dataclass
class Round:
    """One tracking pass: the model's held-out prediction fit and the tracks' fit to the clouds [m]."""

    index: int
    held_out_fit_m: float
    tracking_fit_m: float
    kept: bool
    seconds: float
    train: dict | None = None
    # the time limit cut this round's training short (Budget.time_limit_s)
    cut_by_time_limit: bool = False
    # of ``seconds``, those spent training (round 0: none)
    train_s: float = 0.0
    # one held-out prediction fit of the round's model (round 0: the start model with its network on,
    # as the later models run), what each of the parameter ranges' fits costs
    held_fit_s: float = 0.0

    @property
    def after_training_s(self) -> float:
        """The round's time besides training: the damping search, tracking again and scoring (round
        0: its tracking pass), which the next round needs whole besides its own training."""
        return max(self.seconds - self.train_s, 0.0)


@dataclass
class Calibration:
    """What :func:`calibrate` found. ``model`` is None when the clips cannot identify anything
    (``problem`` says why)."""

    model: DeformModel | None
    start: DeformModel
    tracks: list[Track]
    train_names: list[str]
    held_out_names: list[str]
    rounds: list[Round] = field(default_factory=list)
    checks: dict = field(default_factory=dict)
    problem: str | None = None
    seconds: float = 0.0
    # how well the held-out clips pin down each parameter (calibrate.identifiability)
    parameter_ranges: dict = field(default_factory=dict)
    # what Budget.time_limit_s left undone (empty: nothing)
    time_limit_notes: list[str] = field(default_factory=list)


def default_vertices(length_m: float) -> int:
    r"""The model's vertex count when the user gives none: :math:`n = \lceil L / h \rceil + 1` for
    edges of at most :math:`h` = 9 cm on average, within 12..14.

    Why: a fixed count coarsens a long rope (a 12-vertex model of DLO1's 1.03 m between the grippers
    scores 0.13 cm against its 13 markers even when its shape is exact); the motion-capture ropes,
    markers about 10 cm apart, are modelled at about that spacing. Why no more than 14: a training
    iteration costs 1.8x at 16 vertices what it costs at 12, and at 16 the first round of a
    calibration no longer fits its time limit (``calibrate_rods.v16``). Why at least 12: a short rope
    still needs the shape resolution (and 12 is what the tool was measured at on the 0.92-0.97 m
    ropes)."""
    if not length_m > 0:
        raise CalibrationError(f"the rope's length must be positive, not {length_m:g} m")
    low, high = VERTICES
    return int(min(high, max(low, math.ceil(length_m / EDGE_M - 1e-9) + 1)))


def rest_lengths(length_m: float, n_vertices: int, grippers: Grippers) -> np.ndarray:
    """(n-1,) rest lengths: the gripped end edges as the grippers hold them (``|d1 - d0|``), the
    rest of the length spread evenly over the free edges.

    Raises:
        CalibrationError: the grippers' end edges leave no rope between them.
    """
    e0 = abs(grippers.first.d1 - grippers.first.d0)
    e1 = abs(grippers.last.d1 - grippers.last.d0)
    free = length_m - e0 - e1
    if free <= 0:
        raise CalibrationError(
            f"--length {length_m:g} m leaves no rope between the gripped end edges ({e0:g} + {e1:g} m, "
            "grippers d0/d1 in the config)"
        )
    return np.concatenate([[e0], np.full(n_vertices - 3, free / (n_vertices - 3)), [e1]])


def start_model(
    length_m: float, mass_kg: float, rest: np.ndarray, name: str, prior: float | None = None
) -> DeformModel:
    """The plain DER known by length and mass (:func:`deform.generic_rod`, stiffness from ``prior``),
    residual off, with ``rest`` as its typical edge lengths (``nominal_rest``, what a tracker starts a
    rope seen by a camera with; training sets it from the tracks, which keep these lengths)."""
    model = DeformModel(
        generic_rod(length_m, mass_kg, len(rest) + 1, name=name, prior=prior), ModelOptions(residual=False)
    )
    with torch.no_grad():
        model.nominal_rest.copy_(torch.as_tensor(rest, dtype=model.nominal_rest.dtype))
    model.choose_bending_scheme()  # a short or stiff rope's bending stepped implicitly (deform.rod.implicit)
    return model.eval()


def split(tracks: list[Track], every: int, min_frames: int = 0) -> tuple[list[Track], list[Track]]:
    """(train, held out). With ``every`` tracks or more, every ``every``-th track by name, whole.
    With fewer, each track is cut in two and its last 30 % held out, when every such piece keeps
    ``min_frames`` (the held-out fit's window); else the first track is held out whole. A single
    track is always cut.

    Why cut: a lab that records two or three bags would otherwise train on a half or two thirds of
    its motion; the cut keeps 70 % of each for training and still holds out motion training never saw.
    """
    tracks = sorted(tracks, key=lambda t: t.name)
    if len(tracks) < every:
        stops = [int(0.7 * t.n_frames) for t in tracks]
        if len(tracks) == 1 or all(t.n_frames - k >= min_frames for t, k in zip(tracks, stops)):
            train = [cut(t, 0, k, f"{t.name}[train]") for t, k in zip(tracks, stops)]
            return train, [cut(t, k, t.n_frames, f"{t.name}[held out]") for t, k in zip(tracks, stops)]
    held = tracks[::every]
    return [t for t in tracks if t not in held], held


def tracking_fit(tracks: list[Track]) -> float:
    """Mean capped distance of the clouds' rope points to the track at their step [m]."""
    errs = [
        float(np.minimum(polyline_distances(p, t.positions[k]), CAP_M).mean())
        for t in tracks
        for k, p in zip(t.cloud_steps, t.cloud_points)
        if len(p)
    ]
    return float(np.mean(errs)) if errs else math.nan


def prediction_fit(
    model: DeformModel, tracks: list[Track], horizon: int, every: int, workers: Workers | None = None
) -> float:
    """Open-loop prediction from the tracks scored against the clouds [m] (module docstring).

    Args:
        model: the model.
        tracks: tracks to start from (their clouds are the reference).
        horizon: steps predicted from each start.
        every: steps between starts.
        workers: the tracks rolled out side by side (None: one after another; the same number).

    Returns:
        The mean capped point error over every (start, cloud) pair, or NaN when there is none.
    """
    per_track = (workers or Workers()).map(prediction_errors, tracks, model, horizon, every)
    errs = [e for errors in per_track for e in errors]
    return float(np.mean(errs)) if errs else math.nan


def prediction_errors(track: Track, model: DeformModel, horizon: int, every: int) -> list[float]:
    """:func:`prediction_fit`'s capped point errors of one track, one per (start, cloud) pair."""
    starts = list(range(1, track.n_frames - horizon, every))
    if not starts:
        return []
    x = torch.as_tensor(track.positions, dtype=torch.float64)
    g = torch.as_tensor(track.grips, dtype=torch.float64)
    s = torch.as_tensor(starts)
    steps = s[:, None] + 1 + torch.arange(horizon)[None]
    with torch.no_grad():
        state = model.initial_state(x[s - 1], x[s])
        pred, _ = model.rollout(state, g[steps])
    pred = pred.numpy()
    errs = []
    for k, p in zip(track.cloud_steps, track.cloud_points):
        if not len(p):
            continue
        for b, s0 in enumerate(starts):
            if s0 < k <= s0 + horizon:
                xk = pred[b, k - s0 - 1]
                ok = np.all(np.isfinite(xk))
                errs.append(float(np.minimum(polyline_distances(p, xk), CAP_M).mean()) if ok else CAP_M)
    return errs


def _track_all(clips, model, grippers, perception, rest, progress, label, workers: Workers) -> list[Track]:
    found = workers.map(
        track_clip, clips, model, grippers, perception, rest, desc=label if progress else None, unit="clip"
    )
    tracks = [t for t in found if t is not None]
    if not tracks:
        raise CalibrationError("no clip has a cloud within the time span of its gripper poses")
    return tracks


def _train(
    model, train_tracks, held_tracks, budget: Budget, first: bool, progress: bool, time_limit_s: float | None
) -> tuple:
    cfg = TrainConfig(
        iterations=budget.iterations if first else budget.refine_iterations,
        batch=budget.batch,
        horizon=budget.horizon,
        curriculum=budget.curriculum if first else (),
        curriculum_iters=budget.curriculum_iters,
        seed=budget.seed,
        time_limit_s=time_limit_s,
        coarse_sysid=first,
        residual=True,
        sysid=True,
    )
    model.options.residual = True
    with tempfile.TemporaryDirectory(prefix="deform-calibrate-") as tmp:
        result = train(
            model,
            [t.recording() for t in train_tracks],
            [t.recording() for t in held_tracks],
            cfg,
            tmp,
            resume=False,
            progress=progress,
        )
        best = DeformModel.load(f"{tmp}/best.pt").eval()
    return best, result


def calibrate(
    clips: list[Clip],
    length_m: float,
    mass_kg: float,
    grippers: Grippers,
    perception,
    n_vertices: int | None = None,
    budget: Budget | None = None,
    name: str = "calibrated",
    progress: bool = True,
    prior: float | None = None,
    workers: int = 1,
) -> Calibration:
    """A model of the rope in ``clips`` from the camera and the grippers alone.

    Args:
        clips: the bags (:func:`calibrate.bags.read_clip`).
        length_m: the rope's length [m].
        mass_kg: its mass [kg].
        grippers: the gripper convention (service config).
        perception: perception settings (:class:`perception.PerceptionConfig`).
        n_vertices: vertices of the model (None: :func:`default_vertices` of ``length_m``).
        budget: how much work (default :class:`Budget`).
        name: the model's name.
        progress: progress bars.
        prior: bending stiffness per linear density of the start [N m^3/kg] (None: the shipped
            rods' median, :func:`deform.bend_per_linear_density`).
        workers: processes for the work that splits by clip (tracking passes, held-out fits;
            :mod:`calibrate.workers`); the same model with any number.

    Returns:
        A :class:`Calibration`; ``model`` None with ``problem`` set when the clips are too short or
        too still.

    Raises:
        CalibrationError: the colour range finds no rope, the length disagrees with the camera, no
            clip has clouds within its poses' time span.
    """
    with Workers(workers) as pool:
        return _calibrate(
            clips, length_m, mass_kg, grippers, perception, n_vertices, budget, name, progress, prior, pool
        )


def _calibrate(
    clips, length_m, mass_kg, grippers, perception, n_vertices, budget, name, progress, prior, pool
):
    budget = budget or Budget()
    n_vertices = n_vertices or default_vertices(length_m)
    t_start = time.perf_counter()
    torch.manual_seed(budget.seed)
    rest = rest_lengths(length_m, n_vertices, grippers)
    model = start_model(length_m, mass_kg, rest, name, prior)
    t0 = time.perf_counter()
    tracks = _track_all(
        clips, model, grippers, perception, rest, progress, "track (length and mass only)", pool
    )
    check_rope_seen(tracks, perception.segmentation)
    checks = {"length": check_length(tracks, length_m, float(rest[1:-1].sum()))}
    train_t, held_t = split(tracks, budget.held_out_every, budget.score_horizon + 2)
    out = Calibration(
        model=None,
        start=model,
        tracks=tracks,
        train_names=[t.name for t in train_t],
        held_out_names=[t.name for t in held_t],
        checks=checks,
    )
    out.problem = motion_problem(tracks, budget.horizon + 2)
    if out.problem is None and not any(t.n_frames >= budget.score_horizon + 2 for t in held_t):
        out.problem = f"the held-out clips are shorter than the {budget.score_horizon * model.dt:g} s the fit is scored over"
    if out.problem is not None:
        out.seconds = time.perf_counter() - t_start
        return out
    best_fit = prediction_fit(model, held_t, budget.score_horizon, budget.score_every, workers=pool)
    out.rounds.append(Round(0, best_fit, tracking_fit(held_t), True, time.perf_counter() - t0))
    first_rest_s = 0.0
    if budget.time_limit_s is not None:
        first_rest_s = first_round_rest_s(out.rounds[0], model, train_t, budget, pool)
        out.rounds[0].held_fit_s = _timed_fit(
            model, held_t, budget.score_horizon, budget.score_every, True, pool
        )
    best, best_fit_s = model, out.rounds[0].held_fit_s  # best_fit_s: how long a held-out fit of best takes
    for r in range(1, budget.rounds + 1):
        t0 = time.perf_counter()
        left = _time_left(budget, t_start)
        need = projected_round_s(out.rounds[-1], budget.refine_iterations) if r > 1 else 0.0
        reserve_s = end_reserve_s(out.rounds[-1])
        if left is not None and r > 1 and left < need + reserve_s:
            skipped = f"round {r}" if r == budget.rounds else f"rounds {r}..{budget.rounds}"
            out.time_limit_notes.append(
                f"{skipped} not started: {left:.0f} s of the time limit ({budget.time_limit_s:.0f} s) "
                f"were left, round {r} would take about {need:.0f} s"
            )
            break
        # leave the round's work after training the time the last round's took (round 1: an estimate)
        after_training_s = SPARE * (first_rest_s if r == 1 else out.rounds[-1].after_training_s)
        train_limit = None if left is None else max(left - after_training_s - reserve_s, 1e-3)  # 0: no limit
        usable = _trainable(train_t, budget)
        t_train = time.perf_counter()
        candidate, result = _train(copy.deepcopy(best), usable, held_t, budget, r == 1, progress, train_limit)
        train_s = time.perf_counter() - t_train
        damping = None
        if budget.damping_horizon > 0:
            candidate, damping = settle_damping(
                candidate,
                partial(
                    prediction_fit,
                    tracks=damping_tracks(usable),
                    horizon=budget.damping_horizon,
                    every=budget.score_every,
                    workers=pool,
                ),
                tolerance=MIN_GAIN,
            )
            damping["horizon_s"] = budget.damping_horizon * candidate.dt
        new_tracks = _track_all(
            clips, candidate, grippers, perception, rest, progress, f"track (round {r})", pool
        )
        new_train, new_held = split(new_tracks, budget.held_out_every, budget.score_horizon + 2)
        t_fit = time.perf_counter()
        fit = prediction_fit(candidate, new_held, budget.score_horizon, budget.score_every, workers=pool)
        held_fit_s = time.perf_counter() - t_fit
        kept = bool(fit < best_fit * (1 - MIN_GAIN))
        summary = {
            k: result.get(k) for k in ("best_val_l1_m", "coarse_identification", "seconds_per_iteration_p50")
        }
        summary["iterations"] = result.get("last", {}).get("iteration")
        summary["damping"] = damping
        wanted = budget.iterations if r == 1 else budget.refine_iterations
        cut_short = (summary["iterations"] or 0) < wanted
        if cut_short:
            out.time_limit_notes.append(
                f"round {r} trained {summary['iterations']} of {wanted} iterations: the time limit "
                f"({budget.time_limit_s:.0f} s) was near"
            )
        out.rounds.append(
            Round(
                r,
                fit,
                tracking_fit(new_held),
                kept,
                time.perf_counter() - t0,
                summary,
                cut_short,
                train_s,
                held_fit_s,
            )
        )
        if not kept:
            break
        best, best_fit, train_t, held_t, out.tracks = candidate, fit, new_train, new_held, new_tracks
        best_fit_s = held_fit_s
    out.model = best
    left = _time_left(budget, t_start)
    ranges_t = ranges_tracks(held_t, best_fit_s, left)
    if len(ranges_t) < len(held_t):
        out.time_limit_notes.append(
            f"the parameter ranges were measured on {len(ranges_t)} of the {len(held_t)} held-out clips: "
            f"{left:.0f} s of the time limit ({budget.time_limit_s:.0f} s) were left"
        )
    out.parameter_ranges = parameter_ranges(
        best,
        lambda m: prediction_fit(m, ranges_t, budget.score_horizon, budget.score_every, workers=pool),
        MIN_GAIN,
    )
    out.parameter_ranges["held_out_clips"] = [t.name for t in ranges_t]
    out.seconds = time.perf_counter() - t_start
    return out


def first_round_rest_s(
    tracked: Round, model: DeformModel, tracks: list[Track], budget: Budget, workers: Workers | None = None
) -> float:
    """About how long round 1 takes besides training [s], before any round has trained: round 0's
    tracking pass (``tracked``) slowed as the residual network slows a rollout, and the damping search
    (:func:`calibrate.damping.settle_damping`, at most ``MAX_FITS`` rollouts over the damping horizon).
    Both from one rollout of ``model`` over ``tracks`` timed with the network off and one with it on.

    Why: the time limit reserves this for round 1. Reserving round 0's pass alone, a round 1 cut by
    a 9-minute limit on DLO1's clips ended the calibration 65 s past the limit (its rest took 116 s
    against round 0's 41); estimated so, 9 s within it, with the same model."""
    horizon = budget.damping_horizon or budget.score_horizon
    usable = damping_tracks(_trainable(tracks, budget))
    plain_s, learnt_s = (
        _timed_fit(model, usable, horizon, budget.score_every, residual, workers)
        for residual in (False, True)
    )
    search_s = MAX_FITS * learnt_s if budget.damping_horizon > 0 else 0.0
    return tracked.after_training_s * learnt_s / max(plain_s, 1e-9) + search_s


def spread(tracks: list[Track], k: int) -> list[Track]:
    """At most ``k`` of ``tracks``, spread evenly from the first to the last (all when fewer)."""
    if len(tracks) <= k:
        return tracks
    return [tracks[i] for i in np.unique(np.linspace(0, len(tracks) - 1, k).round().astype(int))]


def damping_tracks(tracks: list[Track]) -> list[Track]:
    """At most :data:`DAMPING_TRACKS` of ``tracks``, spread evenly over them (all when fewer): what the
    damping search rolls out. One value's 3 s fit needs a few clips, not every clip a long recording
    gives."""
    return spread(tracks, DAMPING_TRACKS)


def ranges_tracks(tracks: list[Track], fit_s: float, left_s: float | None) -> list[Track]:
    """The held-out ``tracks`` the parameter ranges can afford in the ``left_s`` seconds left of the
    time limit, when a fit of all of them takes ``fit_s``: the most, spread over them, whose
    :data:`calibrate.identifiability.FITS` fits (with :data:`SPARE`, by their frames) leave
    :data:`REPORT_S`; at least :data:`RANGE_TRACKS`. All of them with no limit or no timing.

    Why: the ranges come last, when every estimate made before the rounds has been spent. On 280 s of
    clips round 1's rest took longer than estimated and the ranges over all 12 held-out clips
    (86 s) ended the calibration 39-60 s past its limit (calibrate_rods.300s.damping_tracks)."""
    if left_s is None or fit_s <= 0 or len(tracks) <= RANGE_TRACKS:
        return tracks
    per_frame_s = SPARE * RANGE_FITS * fit_s / sum(t.n_frames for t in tracks)
    for k in range(len(tracks), RANGE_TRACKS, -1):
        picked = spread(tracks, k)
        if per_frame_s * sum(t.n_frames for t in picked) <= left_s - REPORT_S:
            return picked
    return spread(tracks, RANGE_TRACKS)


def _timed_fit(
    model: DeformModel, tracks: list[Track], horizon: int, every: int, residual: bool, workers: Workers | None
) -> float:
    """How long one :func:`prediction_fit` of a copy of ``model`` takes with its residual network on or
    off [s] (the fit itself is not needed: a probe of what later rollouts will cost)."""
    probe = copy.deepcopy(model)
    probe.options.residual = residual
    t0 = time.perf_counter()
    prediction_fit(probe, tracks, horizon, every, workers=workers)
    return time.perf_counter() - t0


def end_reserve_s(last: Round) -> float:
    """What the time limit keeps for the work after the rounds [s]: the parameter ranges'
    held-out fits (:data:`calibrate.identifiability.FITS`, each as long as the ``last`` round's, with
    :data:`SPARE`) and the report, at least :data:`RESERVE_S`. On 280 s of clips (12 held-out clips)
    the work outside the rounds (the ranges, round 1's time probe) took 155 s against the 30 s kept,
    and the calibration ended 140 s past its limit."""
    return max(RESERVE_S, SPARE * RANGE_FITS * last.held_fit_s)


def _trainable(tracks: list[Track], budget: Budget) -> list[Track]:
    """The tracks long enough for a training window (all of them when none is)."""
    return [t for t in tracks if t.n_frames >= budget.horizon + 2] or tracks


def projected_round_s(previous: Round, iterations: int) -> float:
    """About how long a round of ``iterations`` training iterations takes [s]: the ``previous``
    round's training time per iteration, with 20 % to spare (later rounds train on longer windows
    from the start), plus what that round did besides training (the damping search, a tracking pass
    and the held-out fit: as long again, whatever the iterations). Counting that part per iteration
    too had a later round of DLO1's foreign-lab clips projected at 373 s; it took 482 and ended the
    calibration 67 s past the 20 minutes.

    Whether a round starts, not when it ends: a started round's training stops early enough for the
    rest of it with :data:`SPARE`. With that spare here too, DLO3's second round (451 s left, 442
    projected) was not started, and its open loop was 0.47 cm against 0.44 with it."""
    done = max((previous.train or {}).get("iterations") or 1, 1)
    return 1.2 * previous.train_s * iterations / done + previous.after_training_s


def _time_left(budget: Budget, t_start: float) -> float | None:
    """Seconds left of ``budget.time_limit_s`` since ``t_start`` (None: no limit)."""
    if budget.time_limit_s is None:
        return None
    return budget.time_limit_s - (time.perf_counter() - t_start)


def identified(model: DeformModel, start: DeformModel) -> dict:
    """The physical parameters found, beside where they started, and what the data cannot tell.

    Bending stiffness is per vertex: its spread (min..max) is reported as the range the data left
    it in. Twist shows in no camera (a rope's material frame is invisible); its stiffness is
    reported with that caveat.
    """

    def summary(m: DeformModel) -> dict:
        beta = m.log_beta.detach().exp().double().numpy()
        gamma = m.log_gamma.detach().exp().double().numpy()
        extra = torch.nn.functional.softplus(m.extra_mass_raw.detach()).double().numpy() * 1e-3
        return {
            "bend_stiffness_Nm2": float(np.median(beta)),
            "bend_stiffness_range_Nm2": [float(beta.min()), float(beta.max())],
            "twist_stiffness_Nm2": float(np.median(gamma)),
            "damping_per_s": float(m.damping.detach()),
            "drag_per_m": float(m.drag.detach()),
            "extra_mass_kg": float(extra.sum()),
            "residual_network": bool(m.options.residual),
            # the stiffest bending mode's turn per step and whether the bending is stepped implicitly
            "bending_step_ratio": round(m.bending_step_ratio(), 3),
            "implicit_bending": bool(m.cfg.implicit_bending),
            "substeps": int(m.cfg.substeps),
        }

    return {
        "found": summary(model),
        "start": summary(start),
        "not_identifiable": [
            "twist_stiffness_Nm2: a camera does not see the material frame; the value is what made the "
            "bending fit best, not a measurement"
        ],
    }
