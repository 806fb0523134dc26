r"""A model scored on held-out motions the three ways issue 49 asks, against the motion-capture truth.

* **open loop**: the paper's metric (:func:`deform.evaluate.predict_recordings`: 500 steps from the
  first two frames, gripped vertices given; a model of another vertex count is compared at the
  markers by arc length);
* **tracking**: our tracker (perception's :class:`Tracker`, default settings, started from the first
  two true frames) on rendered clouds with an occluder hiding a quarter of the rope for half of the
  recording; per cloud TrackDLO's two-way distance between the estimate and the true polyline, mean
  over clouds: against the marker polyline (``tracking_mm``) and against the rope as rendered
  (``tracking_rope_mm``, :func:`benchmarks.tracking.metric.rope_error`). The shipped model's
  vertices are the markers, the calibrated model's are spread evenly along the rope: against the
  markers only the first can score 0, against the rendered rope neither; and where the occluder
  hides the rope (``tracking_hidden_mm``): per cloud that hides some free marker, the mean distance
  of the hidden markers to the smooth curve through the estimate (the renderer's centreline,
  whatever the vertex count), mean over those clouds. There the camera corrects nothing and the
  estimate is the model's; over the whole rope the camera's correction of the visible part dominates;
* **1 s prediction**: every 0.5 s from 1 s on, the tracked state is rolled out 100 steps with the
  recorded gripper motion (the service's ``predict`` with the recording as plan 0); the error is the
  mean distance between the prediction and the truth 1 s ahead, at the markers (arc length).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
import torch

from benchmarks.tracking.metric import point_to_polyline, rope_error, two_way_error
from deform import Recording, gripped_indices
from deform.evaluate import CURVE, as_model_vertices, metrics, predict_recordings
from deform.io.arc_length import edge_lengths, resample_vertices

OCCLUSION = 0.25
AHEAD_STEPS = 100  # 1 s at 10 ms
PREDICT_EVERY = 50
PREDICT_FROM = 100


def open_loop(model, held_out: list[Recording]) -> dict:
    """The paper's 500-step metric: ``l1_cm`` (mean over recordings) and per recording."""
    m = metrics(predict_recordings(model, held_out, 500))
    return dict(
        l1_cm=round(100 * m["l1_m"], 4),
        per_recording_cm={k: round(100 * v, 4) for k, v in m["per_recording_l1_m"].items()},
    )


def hidden_error(estimate: np.ndarray, truth: np.ndarray, visible) -> float | None:
    """The mean distance [m] of the free true markers a cloud does not show (``visible`` False) to the
    smooth curve through ``estimate`` (k, 3); None when the cloud shows every free marker or says
    nothing of visibility (``visible`` None). The two gripped markers at each end are left out: the
    grippers place them."""
    from perception import rope_centreline

    if visible is None:
        return None
    hidden = ~np.asarray(visible, dtype=bool)
    hidden[list(gripped_indices(len(truth)))] = False
    if not hidden.any():
        return None
    return float(point_to_polyline(truth[hidden], rope_centreline(np.asarray(estimate, np.float64))).mean())


def track_and_predict(model, truth: np.ndarray, frames, perception) -> dict:
    """Track ``frames`` (rendered from ``truth`` (T, m, 3)) with ``model``; the tracking errors per
    cloud [m] (``tracking_hidden``: per cloud that hides some of the rope, :func:`hidden_error`) and
    the 1 s prediction errors [m]."""
    from perception import Tracker

    own = as_model_vertices(Recording("truth", truth), model).positions  # its start and grippers
    gi = gripped_indices(model.n)
    markers = edge_lengths(truth[0])
    tracker = Tracker(model, config=perception)
    tracker.initialize_from_frames(own[0], own[1])
    by_step = {f.step: f for f in frames}
    tracking, tracking_rope, tracking_hidden, ahead = [], [], [], []
    for k in range(2, len(truth)):
        x, _ = tracker.step(own[k, gi])
        f = by_step.get(k)
        if f is not None:
            x, _ = tracker.correct(f.xyz, f.rgb, f.camera)
            tracking.append(two_way_error(x, truth[k]))
            tracking_rope.append(rope_error(x, truth[k]))
            hidden = hidden_error(x, truth[k], getattr(f, "visible", None))
            if hidden is not None:
                tracking_hidden.append(hidden)
        if k >= PREDICT_FROM and (k - PREDICT_FROM) % PREDICT_EVERY == 0 and k + AHEAD_STEPS < len(truth):
            state = tracker.state
            with torch.no_grad():
                for j in range(k + 1, k + AHEAD_STEPS + 1):
                    state = model.step(state, torch.as_tensor(own[j, gi], dtype=state.x.dtype).unsqueeze(0))
            pred = resample_vertices(state.x[0].double().numpy(), truth.shape[1], markers, curve=CURVE)
            ahead.append(float(np.linalg.norm(pred - truth[k + AHEAD_STEPS], axis=-1).mean()))
    return dict(tracking=tracking, tracking_rope=tracking_rope, tracking_hidden=tracking_hidden, ahead=ahead)


def render_held_out(recording: Recording, camera, render_cfg, seed: int, fps: float = 30.0):
    """The clouds of a held-out motion: the session's camera at its rate, an occluder over a quarter
    of the rope."""
    from perception import render_recording

    cfg = replace(render_cfg, occlusion=OCCLUSION)
    return render_recording(
        recording.positions, dt=recording.dt, fps=fps, config=cfg, camera=camera, seed=seed
    )


def score(
    models: dict,
    held_out: list[Recording],
    tracked: int,
    camera,
    perception,
    fps: float = 30.0,
    film: Callable[[Recording, int], list] | None = None,
) -> dict:
    """Every model on the held-out motions: open loop on all of them, tracking and 1 s prediction on
    the first ``tracked`` (the same clouds for every model, ``fps`` clouds a second). ``film(recording,
    i)``: the clouds of held-out motion ``i`` as frames (``step``, ``xyz``, ``rgb``, ``camera``) when
    another lab films them (default: perception's renderer with ``camera``).

    Returns:
        ``{name: {open_loop: {...}, tracking_mm, tracking_rope_mm, tracking_hidden_mm, prediction_1s_mm,
        per_recording: {...}}}``.
    """
    out = {name: dict(open_loop=open_loop(m, held_out), per_recording={}) for name, m in models.items()}
    for i, rec in enumerate(held_out[:tracked]):
        if film is None:
            frames = render_held_out(rec, camera, perception.render, seed=2000 + i, fps=fps)
        else:
            frames = film(rec, i)
        for name, m in models.items():
            r = track_and_predict(m, rec.positions, frames, perception)
            out[name]["per_recording"][rec.name] = dict(
                tracking_mm=round(1e3 * float(np.mean(r["tracking"])), 3),
                tracking_rope_mm=round(1e3 * float(np.mean(r["tracking_rope"])), 3),
                tracking_hidden_mm=_mean_mm(r["tracking_hidden"]),
                hidden_clouds=len(r["tracking_hidden"]),
                prediction_1s_mm=round(1e3 * float(np.mean(r["ahead"])), 3) if r["ahead"] else None,
            )
    for name in models:
        rows = out[name]["per_recording"].values()
        track = [r["tracking_mm"] for r in rows]
        rope = [r["tracking_rope_mm"] for r in rows]
        ahead = [r["prediction_1s_mm"] for r in rows if r["prediction_1s_mm"] is not None]
        # over every cloud that hides some rope, as the motions' clouds weigh (not per motion)
        hidden = [(r["tracking_hidden_mm"], r["hidden_clouds"]) for r in rows if r["hidden_clouds"]]
        out[name]["tracking_mm"] = round(float(np.mean(track)), 3) if track else None
        out[name]["tracking_rope_mm"] = round(float(np.mean(rope)), 3) if rope else None
        out[name]["prediction_1s_mm"] = round(float(np.mean(ahead)), 3) if ahead else None
        out[name]["tracking_hidden_mm"] = (
            round(sum(e * n for e, n in hidden) / sum(n for _, n in hidden), 3) if hidden else None
        )
    return out


def _mean_mm(errors: list[float]) -> float | None:
    return round(1e3 * float(np.mean(errors)), 3) if errors else None
