"""A client for controllers: the rope's current shape, its stream, predictions and the service status.

Made for a robot's Python process: it imports zenoh, numpy and the CDR decoder of
:mod:`service.messages`, never torch. ::

    from service.client import ShapeClient

    with ShapeClient("deform/rod1", connect=["tcp/192.168.1.10:7447"]) as rope:
        stamp_ns, x, observed = rope.vertices()          # x (n, 3) metres, world frame
        sub = rope.subscribe(lambda stamp_ns, x, observed: ...)   # every tick (100 Hz)
        shapes = rope.predict(plans)                     # plans (P, S, 2, 7) -> (P, S, n, 3)
        rope.status()["mode"]

A plan step is the two gripper poses ``[x y z qx qy qz qw]`` in the world frame, one step per
``dt`` (default the model's 10 ms). The service's error replies come back as typed exceptions
(:class:`BadRequest`, :class:`NotReady`, :class:`Busy`, :class:`ServiceFailed`), a missing reply as
:class:`NoReply`.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import orjson
import zenoh

from service import predict_codec
from service.messages import parse_vertices


class ServiceError(Exception):
    """An error reply of the service: ``reason`` (a short code such as ``bad_shape``) and ``detail``."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason, self.detail = reason, detail


class BadRequest(ServiceError):
    """The request was refused as it stands (bad JSON, shapes, quaternions, dt, size)."""


class NotReady(ServiceError):
    """No estimate yet (``no_estimate``: no gripper poses received), or predict is still being
    prepared at start-up (``not_ready``: its warm-up runs; ``status()["not_ready"]`` lists what is
    pending, ``status()["predict_state"]`` says ``preparing``). Worth asking again."""


class Busy(ServiceError):
    """Too many predictions queued; ask again."""


class ServiceFailed(ServiceError):
    """The service failed on a valid request (``internal``: its log has the trace), or predict
    cannot answer because its warm-up failed (``predict_failed``; ``detail`` names why, and says
    when it is being retried in eager mode; ``status()["predict_failed"]`` too)."""


class NoReply(ServiceError):
    """Nothing answered within the timeout: no service under this namespace, or it is not reachable."""


_BY_REASON = {
    "no_estimate": NotReady,
    "not_ready": NotReady,
    "busy": Busy,
    "internal": ServiceFailed,
    "predict_failed": ServiceFailed,
}
_PLAN_DTYPES = {"float32": "<f4", "float64": "<f8"}  # predict_full's binary plans


def error_from_reply(payload: bytes) -> ServiceError:
    """The typed exception for an error reply's JSON body (``{"error": reason, "detail": ...}``)."""
    try:
        body = json.loads(payload)
        reason, detail = str(body.get("error", "unknown")), str(body.get("detail", ""))
    except (ValueError, AttributeError):
        reason, detail = "unknown", payload[:200].decode("utf-8", "replace")
    return _BY_REASON.get(reason, BadRequest)(reason, detail)


@dataclass(frozen=True)
class Prediction:
    """A predict reply: ``vertices`` (P, K, n, 3) metres at the 1-based plan ``steps`` (K,);
    ``overstretched`` (P,) plans that hold the rope farther apart than it is long at some step
    (discard them); ``stamp_s`` of the estimate the rollouts started from; the request's ``id``."""

    vertices: np.ndarray
    overstretched: np.ndarray
    stamp_s: float
    steps: np.ndarray
    id: str | int | float | None = None
    costs: np.ndarray | None = None  # (P,) with a cost request (service/plan_cost.py)
    cost_terms: dict | None = None


class ShapeClient:
    """One rope's service under ``namespace``.

    Args:
        namespace: the service's key prefix (``namespace`` in its config).
        connect: Zenoh endpoints to connect to (e.g. ``["tcp/192.168.1.10:7447"]``), and no
            multicast scouting; None: peer mode with multicast scouting, as the service's default.
        session: an open Zenoh session to use instead (not closed by :meth:`close`).
        timeout_s: default time to wait for a reply to ``vertices`` and ``status``.
        interface: the service's ``interface``: ``zenoh`` (plain keys) or ``ros2`` (the stream on
            rmw_zenoh's keys in ROS domain ``domain_id``); queries use plain keys in both.
    """

    def __init__(
        self,
        namespace: str = "deform/rod1",
        connect: list[str] | None = None,
        session: zenoh.Session | None = None,
        timeout_s: float = 2.0,
        interface: str = "zenoh",
        domain_id: int = 0,
    ):
        if interface not in ("zenoh", "ros2"):
            raise ValueError(f"interface must be zenoh or ros2, not {interface!r}")
        self.interface, self.domain_id = interface, domain_id
        self.namespace = namespace.strip("/")
        self.timeout_s = timeout_s
        self._own = session is None
        if session is None:
            conf = zenoh.Config()
            if connect:  # explicit endpoints: no multicast scouting of other peers
                conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
                conf.insert_json5("scouting/multicast/enabled", "false")
                # a client started before the service (a controller on the robot) retries every
                # 0.1-0.5 s, so it sees the service soon after it listens; Zenoh's default back-off
                # (1 s doubling to 4 s) could add up to 4 s
                conf.insert_json5(
                    "connect/retry",
                    json.dumps({"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2}),
                )
            session = zenoh.open(conf)
        self.session = session
        self._subscribers: list = []

    def key(self, name: str) -> str:
        return f"{self.namespace}/{name}"

    def _get(self, name: str, payload: bytes | None, timeout_s: float) -> bytes:
        kwargs = {"timeout": timeout_s} if payload is None else {"payload": payload, "timeout": timeout_s}
        for reply in self.session.get(self.key(name), **kwargs):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
            raise error_from_reply(reply.err.payload.to_bytes())
        raise NoReply("no_reply", f"nothing answered on {self.key(name)} within {timeout_s} s")

    def vertices(self, timeout_s: float | None = None) -> tuple[int, np.ndarray, np.ndarray]:
        """The current estimate.

        Returns:
            ``(stamp_ns, x, observed)``: x (n, 3) float32 metres in the world frame, observed (n,)
            bool (the vertex was corrected from the camera recently).
        """
        return parse_vertices(self._get("vertices", None, timeout_s or self.timeout_s))

    def subscribe(self, callback: Callable[[int, np.ndarray, np.ndarray], None]):
        """Call ``callback(stamp_ns, x, observed)`` for every published estimate (each tick).

        Returns:
            The Zenoh subscriber (``.undeclare()`` stops it; :meth:`close` stops all).
        """

        def on_sample(sample) -> None:
            callback(*parse_vertices(sample.payload.to_bytes()))

        key = self.key("vertices")
        if self.interface == "ros2":
            from service.ros2 import topic_key

            key = topic_key(self.domain_id, f"/{self.namespace}/vertices", "sensor_msgs/msg/PointCloud2", "*")
        sub = self.session.declare_subscriber(key, on_sample)
        self._subscribers.append(sub)
        return sub

    def predict_full(
        self,
        plans: np.ndarray,
        dt: float | None = None,
        steps: str = "all",
        binary: bool = True,
        request_id: str | int | None = None,
        cost: dict | None = None,
        timeout_s: float = 30.0,
        plan_dtype: str = "float32",
    ) -> Prediction:
        """Roll every plan out from the current estimate.

        Args:
            plans: (P, S, 2, 7) gripper poses ``[x y z qx qy qz qw]``, world frame, one per step.
            dt: seconds per step (None: the model's step, 10 ms).
            steps: which steps come back: ``"all"``, ``"final"`` or ``"every:K"`` (and the last).
            binary: request and reply in :mod:`service.predict_codec`'s binary format (plans as
                ``plan_dtype``, float32 vertices: smaller, faster) or JSON both ways.
            request_id: echoed in the reply (``Prediction.id``).
            cost: score each plan in the service (``{"goal": (n, 3), "plane_z": z, "weights": {...}}``,
                see service/plan_cost.py); with ``steps="none"`` only the costs come back.
            timeout_s: time to wait (a first request may include compilation).
            plan_dtype: the binary request's plans, ``"float32"`` (positions to 0.06 um at a metre
                from the origin; half the bytes: 5.7 MB for 1024 x 100, which the service's float32
                rollout does not resolve anyway) or ``"float64"``.

        Returns:
            A :class:`Prediction` with vertices (P, K, n, 3), K the number of steps returned.
        """
        if plan_dtype not in _PLAN_DTYPES:
            raise ValueError(f"plan_dtype must be one of {sorted(_PLAN_DTYPES)}, not {plan_dtype!r}")
        plans = np.ascontiguousarray(plans, dtype=float)
        if plans.ndim != 4 or plans.shape[2:] != (2, 7):
            raise BadRequest("bad_shape", f"plans must be (P, S, 2, 7), got {plans.shape}")
        fields = {"return": steps, "encoding": "binary" if binary else "json"}  # all but the plans
        if dt is not None:
            fields["dt"] = float(dt)
        if request_id is not None:
            fields["id"] = request_id
        if cost is not None:
            fields["cost"] = {
                k: (np.asarray(v, dtype=float).tolist() if k == "goal" else v) for k, v in cost.items()
            }
        if binary:  # the plans as floats behind a header (service/predict_codec.py): no text at all
            body = predict_codec.encode_request(plans, fields, _PLAN_DTYPES[plan_dtype])
        else:  # orjson writes the numpy array directly: 5 ms for 64 x 100 plans against 60 ms via lists
            body = orjson.dumps({"plans": plans, **fields}, option=orjson.OPT_SERIALIZE_NUMPY)
        payload = self._get("predict", body, timeout_s)
        if predict_codec.is_binary(payload):
            out, vertices = predict_codec.decode(payload)
        else:
            out = json.loads(payload)
            vertices = np.asarray(out["vertices"])
        n_steps = plans.shape[1]
        return Prediction(
            vertices=np.asarray(vertices, dtype=np.float64),
            overstretched=np.asarray(out.get("overstretched", [False] * len(plans)), dtype=bool),
            stamp_s=float(out.get("stamp", float("nan"))),
            steps=np.asarray(out.get("steps", range(1, n_steps + 1)), dtype=int),
            id=out.get("id"),
            costs=None if "costs" not in out else np.asarray(out["costs"]),
            cost_terms=out.get("cost_terms"),
        )

    def predict(
        self, plans: np.ndarray, dt: float | None = None, steps: str = "all", timeout_s: float = 30.0
    ) -> np.ndarray:
        """:meth:`predict_full`'s vertices (P, K, n, 3) alone."""
        return self.predict_full(plans, dt, steps=steps, timeout_s=timeout_s).vertices

    def costs(self, plans: np.ndarray, cost: dict, timeout_s: float = 30.0) -> np.ndarray:
        """(P,) costs of the plans, computed by the service (no vertices are sent back)."""
        return self.predict_full(plans, steps="none", cost=cost, timeout_s=timeout_s).costs

    def status(self, timeout_s: float | None = None) -> dict:
        """The service status (mode, rates, latencies, readiness; see docs/service.md)."""
        return json.loads(self._get("status", None, timeout_s or self.timeout_s))

    def close(self) -> None:
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers.clear()
        if self._own:
            self.session.close()

    def __enter__(self) -> ShapeClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
