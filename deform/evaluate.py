"""Open-loop evaluation with the DEFORM paper's metric.

For a recording ``X`` (T, n, 3): start from frames 0 and 1, feed the gripped vertices of every later
frame, and predict the rest. ``l1_m`` is the mean of ``|prediction - truth|`` over predicted steps, all
vertices (gripped ones included, as in the paper) and x, y, z.

A model whose vertex count differs from the recording's markers (a calibrated model) is started
from the markers resampled to its vertices by arc length along a smooth curve through them
(:mod:`deform.io.arc_length`, ``curve="cubic"``), and its prediction is resampled back to the
markers the same way, where the error is taken.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from deform.io.arc_length import edge_lengths, resample_vertices
from deform.io.recordings import Recording
from deform.model import gripped_indices

HORIZONS = (1, 10, 100, 500)
CURVE = "cubic"  # how shapes of different vertex counts are compared (deform.io.arc_length)


@dataclass
class RolloutResult:
    name: str
    prediction: np.ndarray  # (S, n, 3) predicted frames 2 .. 2+S-1
    truth: np.ndarray
    step_seconds: np.ndarray  # (S,) wall time per step (batch of one)


def batches_by_horizon(recordings: list[Recording], steps: int | None = 500) -> dict[int, list[int]]:
    """Indices of the recordings grouped by how many steps each is predicted over (``steps``, or all
    its frames after the first two when None or shorter): one batched rollout per group.

    Args:
        recordings: each ``positions`` (T, n, 3).
        steps: steps per recording, or None for all.

    Returns:
        ``{steps: [recording indices]}``.
    """
    groups: dict[int, list[int]] = {}
    for i, r in enumerate(recordings):
        groups.setdefault(r.n_frames - 2 if steps is None else min(steps, r.n_frames - 2), []).append(i)
    return groups


def paper_l1(prediction: np.ndarray, truth: np.ndarray, nan_as: float | None = None) -> float:
    """The paper's metric for one recording: mean |prediction - truth| over steps, vertices and axes.

    Args:
        prediction: (S, n, 3) predicted positions [m].
        truth: (S, n, 3) recorded positions of the same steps [m].
        nan_as: the error counted for a coordinate of a diverged (NaN) prediction, instead of NaN.

    Returns:
        The L1 error [m].
    """
    err = np.abs(prediction - truth)
    return float((err if nan_as is None else np.nan_to_num(err, nan=nan_as)).mean())


def predict_recordings(
    model,
    recordings: list[Recording],
    steps: int = 500,
    batched: bool = True,
    dtype: torch.dtype = torch.float64,
    step=None,
) -> list[RolloutResult]:
    """Roll out every recording open-loop, in input order, from its first two frames with the gripped
    vertices given at every step (the paper's protocol).

    Args:
        model: anything with ``n``, ``initial_state`` and ``step`` (the baselines too).
        recordings: each ``positions`` (T, n, 3).
        steps: steps predicted per recording (at most T - 2).
        batched: recordings predicted over the same number of steps share one batch; otherwise one
            rollout each (the timing of a single rollout).
        dtype: of the rollout's state (float32: the planner's trade of accuracy for speed).
        step: ``(state, grip_next) -> state``, or None for ``model.step`` (a compiled step, such as
            the one predict rolls out with, to score what the service answers).

    Returns:
        One :class:`RolloutResult` per recording: ``prediction`` and ``truth`` (S, n, 3) and the
        seconds of each step.
    """
    idx = gripped_indices(model.n)
    step = step or model.step
    markers = recordings
    recordings = [as_model_vertices(r, model) for r in recordings]
    horizon = [min(steps, r.n_frames - 2) for r in recordings]
    groups = (
        list(batches_by_horizon(recordings, steps).values())
        if batched
        else [[i] for i in range(len(recordings))]
    )
    results: list[RolloutResult | None] = [None] * len(recordings)
    with torch.no_grad():
        for members in groups:
            s = horizon[members[0]]
            X = torch.tensor(np.stack([recordings[i].positions[: s + 2] for i in members]), dtype=dtype)
            state = model.initial_state(X[:, 0], X[:, 1])
            preds, times = [], []
            for k in range(s):
                t0 = time.perf_counter()
                state = step(state, X[:, k + 2, idx])
                times.append(time.perf_counter() - t0)
                preds.append(state.x)
            P = torch.stack(preds, 1).double().numpy()
            for j, i in enumerate(members):
                r, pred = markers[i], P[j]
                if r.n_vertices != model.n:
                    pred = resample_vertices(pred, r.n_vertices, edge_lengths(r.positions[0]), curve=CURVE)
                results[i] = RolloutResult(r.name, pred, r.positions[2 : s + 2], np.asarray(times))
    return results


def as_model_vertices(recording: Recording, model) -> Recording:
    """The recording itself when its marker count is the model's; else its markers resampled by
    arc length (along :data:`CURVE`) to the model's vertices, placed as the model's typical rest
    lengths (``nominal_rest``, when it has them) place them."""
    if recording.n_vertices == model.n:
        return recording
    rest = getattr(model, "nominal_rest", None)
    rest = None if rest is None else rest.detach().double().numpy()
    return Recording(
        recording.name, resample_vertices(recording.positions, model.n, rest, curve=CURVE), recording.dt
    )


def metrics(results: list[RolloutResult]) -> dict:
    """The JSON fields of ``deform eval``.

    Args:
        results: from :func:`predict_recordings`.

    Returns:
        ``l1_m`` (mean over recordings of :func:`paper_l1`), ``per_recording_l1_m``, errors at the
        horizons 1/10/100/500 steps, the interior vertices' mean distance, counts.
    """
    per_rec = []
    by_h = {h: [] for h in HORIZONS}
    vdist = []
    for r in results:
        err = np.abs(r.prediction - r.truth)  # (S, n, 3)
        per_rec.append(paper_l1(r.prediction, r.truth))
        interior = np.linalg.norm(r.prediction[:, 2:-2] - r.truth[:, 2:-2], axis=-1)
        vdist.append(float(interior.mean()))
        for h in HORIZONS:
            k = min(h, len(err)) - 1
            by_h[h].append(float(err[k].mean()))
    return {
        "recordings": len(results),
        "steps": int(max(len(r.prediction) for r in results)),
        "l1_m": float(np.mean(per_rec)),
        "mean_vertex_dist_m": float(np.mean(vdist)),
        "l1_by_horizon_m": {str(h): float(np.mean(v)) for h, v in by_h.items()},
        "per_recording_l1_m": {r.name: v for r, v in zip(results, per_rec)},
    }


def evaluate(model, recordings: list[Recording], steps: int = 500) -> dict:
    """Accuracy (batched over recordings) plus single-rollout step latency on the first recording.

    Args:
        model: as for :func:`predict_recordings`.
        recordings: the test recordings.
        steps: steps predicted per recording.

    Returns:
        :func:`metrics` plus ``step_ms_p50`` and ``step_ms_p99`` of one rollout's steps.
    """
    out = metrics(predict_recordings(model, recordings, steps))
    timing = predict_recordings(model, recordings[:1], min(steps, 200), batched=False)[0].step_seconds
    out["step_ms_p50"] = float(np.median(timing) * 1e3)
    out["step_ms_p99"] = float(np.percentile(timing, 99) * 1e3)
    return out
