"""`{ns}/predict`: candidate gripper plans -> predicted shapes, batched, from a copy of the estimate.

Requests are validated before any work so a malformed or huge request costs microseconds; the
rollout never touches the live tracker.
"""
from __future__ import annotations

import json

import numpy as np
import torch

from service.estimator import NS, Estimator
from service.geometry import grips_from_poses
from service.messages import InputError
from service.tracking import rod_state


def parse_request(body: bytes, limits, dt: float) -> np.ndarray:
    """-> plans (P, S, 2, 7) float64 with unit quaternions; raises InputError."""
    if len(body) > limits.max_request_bytes:
        raise InputError("too_large", f"{len(body)} bytes > {limits.max_request_bytes}")
    try:
        req = json.loads(body)
    except (ValueError, UnicodeDecodeError):
        raise InputError("bad_json") from None
    if not isinstance(req, dict) or "plans" not in req:
        raise InputError("bad_request", 'expected {"plans": [...], "dt": ...}')
    if "dt" in req and (not isinstance(req["dt"], (int, float)) or abs(float(req["dt"]) - dt) > 1e-9):
        raise InputError("bad_dt", f"the model steps dt = {dt}")
    try:
        plans = np.asarray(req["plans"], dtype=np.float64)
    except (ValueError, TypeError):
        raise InputError("bad_shape", "plans must be a regular numeric array") from None
    if plans.ndim != 4 or plans.shape[2:] != (2, 7) or plans.shape[0] < 1 or plans.shape[1] < 1:
        raise InputError("bad_shape", f"plans shape {plans.shape}, expected (plans, steps, 2, 7)")
    P, S = plans.shape[:2]
    if P > limits.max_plans or S > limits.max_steps or P * S > limits.max_plan_steps_total:
        raise InputError("too_large", f"{P} plans x {S} steps")
    if not np.all(np.isfinite(plans)):
        raise InputError("nan_pose")
    qn = np.linalg.norm(plans[..., 3:], axis=-1)
    if np.any(np.abs(qn - 1.0) > 0.1):
        raise InputError("bad_quaternion")
    plans[..., 3:] /= qn[..., None]
    return plans


def rollout(est: Estimator, plans: np.ndarray) -> tuple[int, np.ndarray]:
    """-> stamp of the estimate used, vertices (P, S, n, 3)."""
    with est.lock:
        if est.estimate is None:
            raise InputError("no_estimate", "no gripper poses received yet")
        base = rod_state(est.tracker, est.model, est.prev_x, est.estimate.x)
        stamp = est.estimate.stamp_ns
    P, S = plans.shape[:2]
    grips = torch.from_numpy(grips_from_poses(plans, est.cfg.grippers))
    out = np.empty((P, S, est.model.n, 3))
    with torch.no_grad():
        fields = [t[:1].expand(P, *t.shape[1:]).clone() for t in (base.x, base.v, base.d1, base.theta, base.rest)]
        state = type(base)(*fields)
        for s in range(S):
            state = est.model.step(state, grips[:, s])
            out[:, s] = state.x.numpy()
    return stamp, out


def handle(est: Estimator, body: bytes) -> tuple[bool, bytes]:
    """-> (ok, JSON reply). Errors are counted under ``predict:<reason>``."""
    try:
        plans = parse_request(body, est.cfg.limits, est.model.dt)
        stamp, verts = rollout(est, plans)
    except InputError as exc:
        est.stats.reject("predict", exc.reason, str(exc))
        return False, json.dumps({"error": exc.reason, "detail": str(exc)}).encode()
    est.stats.count("predictions")
    body = '{"stamp": %.9f, "vertices": %s}' % (stamp / NS, _json_array(verts))
    return True, body.encode()


_TEMPLATES: dict = {}


def _json_array(a: np.ndarray) -> str:
    """JSON for a large float array at 0.01 mm resolution: one %-format over a cached nested template
    (json.dumps of nested lists is several times slower)."""
    template = _TEMPLATES.get(a.shape)
    if template is None:
        t = "%.5f"
        for size in reversed(a.shape):
            t = "[" + ",".join([t] * size) + "]"
        template = _TEMPLATES[a.shape] = t
        if len(_TEMPLATES) > 16:
            _TEMPLATES.pop(next(iter(_TEMPLATES)))
    return template % tuple(a.ravel().tolist())
