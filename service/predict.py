"""`{ns}/predict`: candidate gripper plans -> predicted shapes, batched, from a copy of the estimate.

Requests are validated before any work so a malformed or huge request costs microseconds; the
rollout never touches the live tracker.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import orjson
import torch

from deform import overstretched
from service import plan_cost, predict_codec
from service.estimator import NS, Estimator
from service.geometry import grips_from_poses
from service.messages import InputError
from service.tracking import rod_state


@dataclass(frozen=True)
class Request:
    """A validated predict request. ``steps``: 0-based indices of the steps to return (all, the
    last, or every k-th and the last); ``binary``: reply in :mod:`service.predict_codec`'s format."""

    plans: np.ndarray  # (P, S, 2, 7), unit quaternions
    steps: np.ndarray
    id: str | int | float | None = None
    binary: bool = False
    cost: dict | None = None  # the request's "cost" object (service.plan_cost.parse_cost checks it)


def returned_steps(spec, S: int) -> np.ndarray:
    """``"all"``, ``"final"``, ``"every:K"`` or ``"none"`` (costs only) -> 0-based step indices
    (every K-th and the last)."""
    if spec in (None, "all"):
        return np.arange(S)
    if spec == "none":
        return np.arange(0)
    if spec == "final":
        return np.array([S - 1])
    if isinstance(spec, str) and spec.startswith("every:"):
        try:
            k = int(spec[6:])
        except ValueError:
            k = 0
        if k >= 1:
            return np.unique(np.append(np.arange(k - 1, S, k), S - 1))
    raise InputError(
        "bad_request", f'"return" must be "all", "final", "every:K" (K >= 1) or "none", not {spec!r}'
    )


def parse_request(body: bytes, limits, dt: float) -> Request:
    """Validate a predict request (JSON; see docs/predict.schema.json). Raises InputError."""
    if len(body) > limits.max_request_bytes:
        raise InputError("too_large", f"{len(body)} bytes > {limits.max_request_bytes}")
    if predict_codec.is_binary_request(body):  # plans as little-endian floats (service/predict_codec.py)
        try:
            req, binary_plans = predict_codec.decode_request(body)
        except predict_codec.CodecError as exc:
            raise InputError("bad_request", str(exc)) from None
        if not isinstance(req, dict) or "plans" in req:
            raise InputError("bad_request", "the header holds the other fields, the plans follow it")
        req["plans"] = binary_plans
    else:
        try:
            req = orjson.loads(body)  # 4x faster than json on a 64-plan request
        except orjson.JSONDecodeError:
            try:
                req = json.loads(body)  # accepts NaN literals, so a NaN pose gets its own reason below
            except (ValueError, UnicodeDecodeError):
                raise InputError("bad_json") from None
    if not isinstance(req, dict) or "plans" not in req:
        raise InputError("bad_request", 'expected {"plans": [...], "dt": ...}')
    unknown = set(req) - {"plans", "dt", "id", "return", "encoding", "cost"}
    if unknown:
        raise InputError("bad_request", f"unknown fields {sorted(unknown)}")
    if req.get("encoding", "json") not in ("json", "binary"):
        raise InputError("bad_request", '"encoding" must be "json" or "binary"')
    if not isinstance(req.get("id"), (str, int, float, type(None))) or isinstance(req.get("id"), bool):
        raise InputError("bad_request", '"id" must be a string or a number')
    if "dt" in req and (not isinstance(req["dt"], (int, float)) or abs(float(req["dt"]) - dt) > 1e-9):
        raise InputError("bad_dt", f"the model steps dt = {dt}")
    try:
        plans = np.asarray(req["plans"], dtype=np.float64)
    except (ValueError, TypeError):
        raise InputError("bad_shape", "plans must be a regular numeric array") from None
    if plans.ndim != 4 or plans.shape[2:] != (2, 7) or plans.shape[0] < 1 or plans.shape[1] < 1:
        raise InputError("bad_shape", f"plans shape {plans.shape}, expected (plans, steps, 2, 7)")
    check_size(plans.shape[0], plans.shape[1], limits)
    if not np.all(np.isfinite(plans)):
        raise InputError("nan_pose")
    qn = np.linalg.norm(plans[..., 3:], axis=-1)
    if np.any(np.abs(qn - 1.0) > 0.1):
        raise InputError("bad_quaternion")
    plans[..., 3:] /= qn[..., None]
    if req.get("return") == "none" and req.get("cost") is None:
        raise InputError("bad_request", '"return": "none" needs a "cost"')
    return Request(
        plans=plans,
        steps=returned_steps(req.get("return"), plans.shape[1]),
        id=req.get("id"),
        binary=req.get("encoding") == "binary",
        cost=req.get("cost"),
    )


def check_size(plans: int, steps: int, limits) -> None:
    """Refuse a request of more plans, steps or plan-steps than ``limits`` allow (InputError)."""
    if plans > limits.max_plans or steps > limits.max_steps or plans * steps > limits.max_plan_steps_total:
        raise InputError("too_large", f"{plans} plans x {steps} steps")


def snapshot(est: Estimator) -> tuple[tuple, int]:
    """The state behind the current estimate as numpy arrays (x, v, d1, theta, rest) and its stamp."""
    with est.lock:
        if est.estimate is None:
            raise InputError("no_estimate", "no gripper poses received yet")
        base = rod_state(est.tracker, est.model, est.prev_x, est.estimate.x)
        stamp = est.estimate.stamp_ns
        return tuple(
            t[:1].detach().numpy().copy() for t in (base.x, base.v, base.d1, base.theta, base.rest)
        ), stamp


def rollout(step, base: tuple, grips: np.ndarray, dtype: torch.dtype = torch.float64) -> np.ndarray:
    """Every plan from the same state: grips (P, S, 4, 3) -> vertices (P, S, n, 3) of ``dtype``.
    ``step`` is a :class:`deform.compiled.RolloutStep` (or a ``CompiledStep``, or the model)."""
    from deform import RodState
    from deform.compiled import rollout as batched_rollout

    P = grips.shape[0]
    state = RodState(*(torch.from_numpy(a).to(dtype).expand(P, *a.shape[1:]).clone() for a in base))
    return batched_rollout(step, state, torch.from_numpy(grips).to(dtype)).numpy()


@dataclass
class Part:
    """One predict process's share of a request (a block of its plans, :func:`share`, sent as a
    request of its own, ``predict_codec.split_request``): the reply's fields for those plans, or
    the error their parse found.

    ``vertices``: the returned steps of those plans as little-endian float32 bytes (binary replies)
    or as the JSON text of their list (JSON replies), ready to be joined with the other shares."""

    ok: bool
    error: bytes = b""
    reason: str | None = None
    detail: str | None = None
    header: dict | None = None  # id, stamp and (when not every step) steps: the same in every share
    shape: tuple = ()  # (hi - lo, K, n, 3)
    overstretched: list | None = None
    costs: dict | None = None  # plan_cost.plan_costs of these plans
    binary: bool = False
    vertices: bytes = b""


def share(plans: int, shard: int, shards: int) -> tuple[int, int]:
    """Plans ``[lo, hi)`` of ``shards`` consecutive, near-equal blocks that process ``shard`` rolls out.

    Args:
        plans: plans in the request.
        shard: this process, 0-based.
        shards: processes the request is split across.

    Returns:
        ``(lo, hi)``.
    """
    return shard * plans // shards, (shard + 1) * plans // shards


def answer_part(ctx, body: bytes, base: tuple, stamp_ns: int) -> Part:
    """Validate, roll out and encode a request (or one share of it, see :class:`Part`). Pure of
    service state, so it runs the same in a worker process. ``ctx`` has ``model``, ``cfg``,
    ``step`` and ``dtype``."""
    try:
        req = parse_request(body, ctx.cfg.limits, ctx.model.dt)
        cost = None if req.cost is None else plan_cost.parse_cost(req.cost, ctx.model.n)
    except InputError as exc:
        error = json.dumps({"error": exc.reason, "detail": str(exc)}).encode()
        return Part(False, error, exc.reason, str(exc))
    grips = grips_from_poses(req.plans, ctx.cfg.grippers)
    verts = rollout(ctx.step, base, grips, ctx.dtype)
    # plans that at some step hold the rod farther apart than it is long: no real rope follows them
    # intact (the model stretches the rod evenly to reach; a planner should discard them)
    taut = overstretched(torch.from_numpy(grips), torch.from_numpy(base[4])).any(-1).tolist()
    costs = None if cost is None else plan_cost.plan_costs(verts, base[4][0], cost)
    header = {"id": req.id, "stamp": stamp_ns / NS}
    verts = verts[:, req.steps]
    if len(req.steps) != req.plans.shape[1]:
        header["steps"] = (req.steps + 1).tolist()  # 1-based step numbers returned
    if req.binary:
        data = np.ascontiguousarray(verts, dtype="<f4").tobytes()
    else:  # 0.01 mm resolution: the estimate is not better than that, and the reply is a third shorter
        data = orjson.dumps(np.round(verts, 5), option=orjson.OPT_SERIALIZE_NUMPY)
    return Part(
        True,
        header=header,
        shape=verts.shape,
        overstretched=taut,
        costs=costs,
        binary=req.binary,
        vertices=data,
    )


def assemble(parts: list[Part]) -> tuple[bool, bytes, str | None, str | None]:
    """The reply to a request from its shares, in plan order: -> (ok, reply, error reason, detail).
    The same bytes as one process answering the whole request; an error, that of the first share
    (in plan order) that found one."""
    for part in parts:
        if not part.ok:
            return False, part.error, part.reason, part.detail
    first = parts[0]
    header = {
        "id": first.header["id"],
        "stamp": first.header["stamp"],
        "overstretched": [t for p in parts for t in p.overstretched],
    }
    if first.costs is not None:
        header["costs"] = [c for p in parts for c in p.costs["costs"]]
        header["cost_terms"] = {
            k: [c for p in parts for c in p.costs["cost_terms"][k]] for k in first.costs["cost_terms"]
        }
    if "steps" in first.header:
        header["steps"] = first.header["steps"]
    shape = [sum(p.shape[0] for p in parts), *first.shape[1:]]
    if first.binary:
        return True, predict_codec.encode_parts(shape, header, [p.vertices for p in parts]), None, None
    plans = b",".join(p.vertices[1:-1] for p in parts if p.shape[0])  # each share's list, brackets off
    return True, orjson.dumps(header)[:-1] + b',"vertices":[' + plans + b"]}", None, None


def answer(ctx, body: bytes, base: tuple, stamp_ns: int) -> tuple[bool, bytes, str | None, str | None]:
    """Validate, roll out, encode the whole request in this process: -> (ok, reply, error reason,
    detail). ``ctx`` has ``model``, ``cfg``, ``step`` and ``dtype``."""
    return assemble([answer_part(ctx, body, base, stamp_ns)])
