"""Predict as a ROS 2 service, ``deform_msgs/srv/PredictShapes`` (``interface: ros2``).

The service's own type, declared here rather than in a ROS package so nothing needs building: a ROS 2
node calls it with the definition below (save it as ``deform_msgs/srv/PredictShapes.srv``; for the
type hash only the fields count). It carries what the JSON predict carries, minus the cost mode::

    # request: P plans of S steps, each step the two gripper poses x y z qx qy qz qw (world frame),
    # row-major (P, S, 2, 7)
    uint32 plans
    uint32 steps
    float64[] poses
    float64 dt             # seconds per step; 0: the model's step
    string return_steps    # "all" (also when empty), "final" or "every:K"
    ---
    string error           # empty on success; else the reason, e.g. "not_ready: ..." (no positions then)
    uint32 plans
    uint32 vertices
    uint32[] steps         # the 1-based plan steps returned
    float32[] positions    # (plans, len(steps), vertices, 3) row-major [m], frame frame_id
    bool[] overstretched   # per plan: the grippers farther apart than the rod is long at some step

Type hashes of services (REP 2011) are computed by rosbags over the request, the response and the
event message (``service_msgs/ServiceEventInfo`` plus at most one request and one response), the
same description rosidl builds; ``tests/service/test_ros2.py`` checks the construction against the
published hash of ``example_interfaces/srv/AddTwoInts``.
"""

from __future__ import annotations

import json

import numpy as np
from rosbags.typesys import get_types_from_msg

from service import messages as M
from service import predict_codec

PREDICT_SRV = "deform_msgs/srv/PredictShapes"
REQUEST = """uint32 plans
uint32 steps
float64[] poses
float64 dt
string return_steps
"""
RESPONSE = """string error
uint32 plans
uint32 vertices
uint32[] steps
float32[] positions
bool[] overstretched
"""
# Jazzy's service_msgs/ServiceEventInfo; its char[16] is uint8[16] in the type description
_EVENT_INFO = "uint8 event_type\nbuiltin_interfaces/Time stamp\nuint8[16] client_gid\nint64 sequence_number\n"


def _renamed(obj, old: str, new: str):
    if isinstance(obj, str):
        return obj.replace(old, new)
    if isinstance(obj, (tuple, list)):
        return type(obj)(_renamed(o, old, new) for o in obj)
    return obj


def register_service(typename: str, request: str, response: str, typestore=None) -> str:
    """Register a service type (request, response, event and the service itself) in a rosbags
    typestore so that it serialises ``<typename>_Request`` / ``_Response`` and hashes the service.

    Args:
        typename: ``pkg/srv/Name``.
        request: the request's field definitions (.msg syntax).
        response: the response's.
        typestore: default the one of :mod:`service.messages`.

    Returns:
        The service's RIHS01 type hash.
    """
    store = typestore or M.TYPESTORE
    if "service_msgs/msg/ServiceEventInfo" not in store.fielddefs:
        store.register(get_types_from_msg(_EVENT_INFO, "service_msgs/msg/ServiceEventInfo"))
    pkg, _, name = typename.split("/")
    tmp = f"{pkg}/msg/{name}"  # rosbags parses .msg text only under a msg/ name
    types = {}
    types.update(get_types_from_msg(request, f"{tmp}_Request"))
    types.update(get_types_from_msg(response, f"{tmp}_Response"))
    event = f"service_msgs/ServiceEventInfo info\n{tmp}_Request[<=1] request\n{tmp}_Response[<=1] response\n"
    types.update(get_types_from_msg(event, f"{tmp}_Event"))
    wrapper = f"{tmp}_Request request_message\n{tmp}_Response response_message\n{tmp}_Event event_message\n"
    types.update(get_types_from_msg(wrapper, tmp))
    store.register({_renamed(k, tmp, typename): _renamed(v, tmp, typename) for k, v in types.items()})
    return store.hash_rihs01(typename)


def request_body(cdr: bytes) -> bytes:
    """A ``PredictShapes`` request -> the binary predict request (binary reply) that
    :func:`service.predict_pool.handle` takes: no text to write or parse, and a large request is split
    across the predict processes (their pool reads the plan count from the header). Raises
    :class:`service.messages.InputError`."""
    msg = M.decode(cdr, f"{PREDICT_SRV}_Request")
    poses = np.asarray(msg.poses, dtype=float)
    if msg.plans == 0 or msg.steps == 0 or poses.size != msg.plans * msg.steps * 14:
        raise M.InputError(
            "bad_shape", f"{poses.size} pose values for {msg.plans} plans x {msg.steps} steps x 2 x 7"
        )
    fields = {"return": msg.return_steps or "all", "encoding": "binary"}
    if msg.dt > 0:
        fields["dt"] = float(msg.dt)
    # float32 plans, as ShapeClient sends them: half the bytes to hand to the predict processes,
    # positions still to 0.06 um at a metre (the rollout's own precision is float32)
    return predict_codec.encode_request(poses.reshape(msg.plans, msg.steps, 2, 7), fields, "<f4")


def response(ok: bool, reply: bytes) -> bytes:
    """What :func:`service.predict_pool.handle` answered -> a ``PredictShapes`` response (CDR)."""
    Res = M.T[f"{PREDICT_SRV}_Response"]
    if not ok:
        err = json.loads(reply)
        text = err.get("error", "error") + (f": {err['detail']}" if err.get("detail") else "")
        return error_response(text)
    header, vertices = predict_codec.decode(reply)
    P, K, n, _ = vertices.shape
    steps = header.get("steps") or list(range(1, K + 1))  # all steps: the reply lists none
    msg = Res(
        error="",
        plans=P,
        vertices=n,
        steps=np.asarray(steps, dtype=np.uint32),
        positions=np.ascontiguousarray(vertices, dtype=np.float32).ravel(),
        overstretched=np.asarray(header.get("overstretched", [False] * P), dtype=bool),
    )
    return M.encode(msg, f"{PREDICT_SRV}_Response")


def error_response(text: str) -> bytes:
    """A response that carries only the reason it has no shapes."""
    Res = M.T[f"{PREDICT_SRV}_Response"]
    msg = Res(
        error=text,
        plans=0,
        vertices=0,
        steps=np.zeros(0, np.uint32),
        positions=np.zeros(0, np.float32),
        overstretched=np.zeros(0, bool),
    )
    return M.encode(msg, f"{PREDICT_SRV}_Response")


PREDICT_HASH = register_service(PREDICT_SRV, REQUEST, RESPONSE)
