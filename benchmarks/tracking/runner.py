"""Every method on the same rendered clouds: our tracker (the DEFORM model predicting every 10 ms step,
each cloud correcting it) and the peer trackers (one update per cloud), all started from the true
nodes of frame 1 (ours also from frame 0, for the velocity).

The peers see what ours sees: the rope points of our segmentation (``perception.segment.segment_rope``
with the default settings) in the world frame, the depth image of the cloud, the camera and the
grippers' nodes (0, 1, n-2, n-1) of the frame. Their update time includes that segmentation, as
``Tracker.correct``'s time includes ours.
"""

from __future__ import annotations

import logging
import time
import zlib
from dataclasses import replace

import numpy as np

from benchmarks.tracking.metric import recovery_time, rope_error, two_way_error
from benchmarks.tracking.scenarios import (
    Clouds,
    Unit,
    clouds_of,
    model_of,
    on_rendered_rope,
    render_config,
    resample_to,
    rest_scale_of,
)
from deform import gripped_indices
from perception import Tracker, camera_steps, load_config, render_recording
from perception.cloud import depth_image
from perception.segment import segment_rope

log = logging.getLogger(__name__)
OURS = "ours"


def available_peers() -> dict:
    """``{name: factory}`` of the peer trackers in :mod:`perception.baselines` ({} when not there)."""
    try:
        from perception.baselines import PEERS, make_peer
    except ImportError as exc:
        log.warning("no peer trackers (%s): ours only", exc)
        return {}
    return {name: (lambda name=name: make_peer(name)) for name in PEERS}


def _ms(values) -> dict:
    v = np.asarray(values, dtype=np.float64)
    if not len(v):
        return dict(p50=None, p99=None, n=0)
    return dict(
        p50=round(float(np.percentile(v, 50)), 3), p99=round(float(np.percentile(v, 99)), 3), n=len(v)
    )


def run_ours(model, truth: np.ndarray, frames, config, rest_scale: float = 1.0) -> dict:
    """Our tracker on ``frames``; errors against ``truth`` (T, n, 3) after each cloud's correction.
    ``rest_scale``: a factor on the free rest lengths the tracker starts with (a length given wrong)."""
    track = truth if model.n == truth.shape[1] else resample_to(truth, model)
    gi = gripped_indices(model.n)
    tracker = Tracker(model, config=config)
    tracker.initialize_from_frames(track[0], track[1])
    if rest_scale != 1.0:
        rest = tracker.state.rest.clone()
        rest[:, 1:-1] *= rest_scale
        tracker.state = replace(tracker.state, rest=rest)
        tracker.rest = rest[0].double().numpy().copy()
    by_step = {f.step: f for f in frames}
    errors, rope_errors, correct_ms, step_ms, floor, camera_floor = [], [], [], [], [], []
    for k in range(2, len(truth)):
        t0 = time.perf_counter()
        x, _ = tracker.step(track[k, gi])
        step_ms.append(1e3 * (time.perf_counter() - t0))
        f = by_step.get(k)
        if f is not None:
            t0 = time.perf_counter()
            x, _ = tracker.correct(f.xyz, f.rgb, f.camera)
            correct_ms.append(1e3 * (time.perf_counter() - t0))
            errors.append(two_way_error(x, truth[k]))
            rope_errors.append(rope_error(x, truth[k]))
            if track is not truth:  # what the vertex count alone costs: the truth at the model's count
                floor.append(two_way_error(track[k], truth[k]))
                camera_floor.append(two_way_error(on_rendered_rope(truth[k], model), truth[k]))
    out = dict(errors=errors, rope_errors=rope_errors, update_ms=correct_ms, step_ms=step_ms, failures=0)
    out["length_scale"] = tracker.status()[
        "length_scale"
    ]  # 1: the camera never disagreed with the rest length
    if floor:
        out["floor_mm"] = 1e3 * float(np.mean(floor))
        out["camera_floor_mm"] = 1e3 * float(np.mean(camera_floor))
    return out


def segmented(frames, config) -> list[tuple]:
    """Per frame ``(world points, depth, seconds it took)``: what the peers are given."""
    out = []
    for f in frames:
        t0 = time.perf_counter()
        pts = f.camera.to_world(segment_rope(f.xyz, f.rgb, config.segmentation))
        depth = depth_image(f.xyz, f.camera)
        out.append((pts, depth, time.perf_counter() - t0))
    return out


def run_peer(factory, truth: np.ndarray, frames, inputs) -> dict:
    """A peer tracker on ``frames`` (``inputs`` from :func:`segmented`); errors against ``truth``. An
    update that raises or returns something unusable keeps the last estimate (counted in ``failures``)."""
    gi = gripped_indices(truth.shape[1])
    peer = factory()
    x = np.asarray(truth[1], dtype=np.float64).copy()
    peer.initialize(x.copy(), truth[1, gi].copy())
    errors, rope_errors, update_ms, failures = [], [], [], 0
    for f, (pts, depth, seg_s) in zip(frames, inputs):
        t0 = time.perf_counter()
        try:
            out = np.asarray(peer.update(pts, truth[f.step, gi].copy(), depth, f.camera), dtype=np.float64)
            ok = out.ndim == 2 and out.shape[1] == 3 and len(out) >= 2 and np.isfinite(out).all()
        except Exception as exc:  # a peer's failure is a result, not the end of the run
            log.warning("peer update failed: %s", exc)
            ok = False
        update_ms.append(1e3 * (time.perf_counter() - t0 + seg_s))
        if ok:
            x = out
        else:
            failures += 1
        errors.append(two_way_error(x, truth[f.step]))
        rope_errors.append(rope_error(x, truth[f.step]))
    return dict(errors=errors, rope_errors=rope_errors, update_ms=update_ms, failures=failures)


def summarize(result: dict, times: np.ndarray, info: dict) -> dict:
    """Rounded series and statistics of one method's run on one case."""
    e = 1e3 * np.asarray(result["errors"], dtype=np.float64)
    rope = 1e3 * np.asarray(result.get("rope_errors", []), dtype=np.float64)
    out = dict(
        mean_error_mm=round(float(e.mean()), 3) if len(e) else None,
        mean_rope_error_mm=round(float(rope.mean()), 3) if len(rope) else None,
        errors_mm=[round(float(v), 2) for v in e],
        update_ms=_ms(result["update_ms"]),
        update_ms_all=[round(float(v), 2) for v in result["update_ms"]],
        failures=result["failures"],
    )
    for key in ("floor_mm", "camera_floor_mm", "length_scale"):
        if key in result:
            out[key] = round(result[key], 3)
    if "step_ms" in result:
        out["step_ms"] = _ms(result["step_ms"])
        out["step_ms_all"] = [round(float(v), 3) for v in result["step_ms"]]
    if "blackout_s" in info:
        start = info["blackout_start_s"]
        rec, ref = recovery_time(times, e, start, start + info["blackout_s"])
        out["recovery_s"] = None if rec is None else round(rec, 3)
        out["error_before_blackout_mm"] = None if ref is None else round(ref, 3)
    return out


def seed_of(unit: Unit, clouds: Clouds) -> int:
    """A render seed fixed by the recording and the clouds (not Python's salted ``hash``)."""
    return zlib.crc32(f"{unit.key}.{clouds.name}".encode()) % 100_000


def run_unit(
    unit: Unit, methods: list[str], peers: dict, config=None, models: dict | None = None, progress=None
) -> dict:
    """Every variant of ``unit`` for every method: the rendered clouds made once per set and reused.

    Args:
        unit: the recording and its variants.
        methods: method names (``"ours"`` and peer names).
        peers: ``{name: factory}`` of the peers (a factory makes a fresh tracker).
        config: the perception config (None: the defaults).
        models: a cache ``{rod: DeformModel}``.
        progress: called with a short text after each run (e.g. a progress bar's postfix).

    Returns:
        ``{"key", "rod", "recording", "cases": [{variant, fps, model, times_s, info, methods: {...}}]}``.
    """
    config = load_config(config)
    models = {} if models is None else models
    cases = []
    for clouds in clouds_of(unit):
        t0 = time.perf_counter()
        frames = render_recording(
            clouds.truth,
            dt=unit.dt,
            fps=30.0,
            config=render_config(config.render, clouds),
            seed=seed_of(unit, clouds),
            obstacles=clouds.obstacles,
        )
        render_s = time.perf_counter() - t0
        frames = [f for f in frames if f.step >= 2]
        done_ours, done_peers = {}, {}
        for variant, fps, rod in clouds.cases:
            sub = set(camera_steps(len(clouds.truth), unit.dt, fps))
            fr = [f for f in frames if f.step in sub]
            times = np.array([f.step * unit.dt for f in fr])
            inputs = None
            out = {}
            for name in methods:
                if name == OURS:
                    if (fps, rod) not in done_ours:
                        model = models.setdefault(rod, model_of(rod))
                        done_ours[(fps, rod)] = run_ours(model, clouds.truth, fr, config, rest_scale_of(rod))
                    res = done_ours[(fps, rod)]
                elif name in peers:
                    if fps not in done_peers.setdefault(name, {}):
                        inputs = inputs if inputs is not None else segmented(fr, config)
                        done_peers[name][fps] = run_peer(peers[name], clouds.truth, fr, inputs)
                    res = done_peers[name][fps]
                else:
                    continue
                out[name] = summarize(res, times, clouds.info)
                if progress:
                    progress(f"{unit.key} {variant} {name} {out[name]['mean_error_mm']} mm")
            cases.append(
                dict(
                    variant=variant,
                    fps=fps,
                    model=rod,
                    clouds=clouds.name,
                    times_s=[round(float(t), 3) for t in times],
                    render_s=round(render_s, 2),
                    hidden_free_fraction=round(float(np.mean([1 - f.visible[2:-2].mean() for f in fr])), 3),
                    info=clouds.info,
                    methods=out,
                )
            )
    return dict(key=unit.key, rod=unit.rod, recording=unit.name, variants=list(unit.variants), cases=cases)
