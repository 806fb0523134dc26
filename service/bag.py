"""MCAP record and replay with ROS 2 schemas (ros2msg + CDR), readable by ros2 bag, Foxglove and Rerun.

Topics are ROS names (``/deform/rod1/ee_poses``); Zenoh keys are the same without the leading slash,
which is how zenoh-bridge-ros2dds maps them. Replay can remap to another namespace.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.writer import Writer

from service import messages as M
from service.ordering import encode_order, new_stream_id

log = logging.getLogger(__name__)

TYPES = {
    "ee_poses": M.POSE_ARRAY,
    "points": M.POINT_CLOUD2,
    "camera_info": M.CAMERA_INFO,
    "camera_pose": M.POSE_STAMPED,
    "vertices": M.POINT_CLOUD2,
}


# what rosbag2 stores per channel: the QoS the publisher offered (here reliable, volatile, keep
# last 10, no deadline or lifespan), so `ros2 bag play` republishes with the same QoS
OFFERED_QOS = """- history: 1
  depth: 10
  reliability: 1
  durability: 2
  deadline:
    sec: 9223372036
    nsec: 854775807
  lifespan:
    sec: 9223372036
    nsec: 854775807
  liveliness: 1
  liveliness_lease_duration:
    sec: 9223372036
    nsec: 854775807
  avoid_ros_namespace_conventions: false
"""


@dataclass
class Message:
    name: str  # input name: ee_poses, points, ...
    log_time: int  # ns; replay paces by it
    data: bytes  # CDR


class McapWriter:
    """Appends messages of the known inputs under a namespace; schemas are registered once."""

    def __init__(self, path: str | Path, namespace: str):
        self._f = open(path, "wb")
        self._w = Writer(self._f)
        self._w.start(profile="ros2", library="deform-service")
        self.namespace = namespace
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._seq = 0
        self._lock = threading.Lock()

    def _channel(self, name: str) -> int:
        if name not in self._channels:
            typename = TYPES[name]
            if typename not in self._schemas:
                self._schemas[typename] = self._w.register_schema(
                    name=typename, encoding="ros2msg", data=M.definition(typename).encode()
                )
            self._channels[name] = self._w.register_channel(
                topic=f"/{self.namespace}/{name}",
                message_encoding="cdr",
                schema_id=self._schemas[typename],
                metadata={"offered_qos_profiles": OFFERED_QOS},
            )
        return self._channels[name]

    def write(self, name: str, log_time: int, data: bytes) -> None:
        with self._lock:
            self._seq += 1
            self._w.add_message(
                channel_id=self._channel(name),
                log_time=int(log_time),
                publish_time=int(log_time),
                data=data,
                sequence=self._seq,
            )

    def close(self) -> None:
        with self._lock:
            self._w.finish()
            self._f.close()


def write_messages(path: str | Path, namespace: str, messages) -> None:
    w = McapWriter(path, namespace)
    for m in messages:
        w.write(m.name, m.log_time, m.data)
    w.close()


class BagError(ValueError):
    """A file that is not a readable MCAP recording; the message names it."""


def read_messages(path: str | Path) -> list[Message]:
    """All messages of known input names, in log-time order (stable for equal times).

    Raises:
        BagError: not an MCAP file, or one cut short.
    """
    out = []
    try:
        with open(path, "rb") as f:
            for _, channel, msg in make_reader(f).iter_messages(log_time_order=True):
                name = channel.topic.rstrip("/").rsplit("/", 1)[-1]
                if name in TYPES and name != "vertices":
                    out.append(Message(name, msg.log_time, bytes(msg.data)))
    except (McapError, EOFError, struct.error) as exc:
        raise BagError(f"{path}: not a readable MCAP recording ({exc})") from None
    return out


def record(
    session: zenoh.Session,
    namespace: str,
    path: str | Path,
    stop: threading.Event,
    names=("ee_poses", "points", "camera_info", "camera_pose", "vertices"),
    key=None,
) -> int:
    """Write what arrives on the input keys and the service's vertices until ``stop`` is set (replay
    reads back the inputs only); returns the message count. ``key(name)``: the key expression of a
    topic (default ``{namespace}/{name}``; a ROS 2 graph on rmw_zenoh: see service/cli.py)."""
    w = McapWriter(path, namespace)
    count = [0]

    def on(name):
        def cb(sample):
            w.write(name, time.time_ns(), sample.payload.to_bytes())
            count[0] += 1

        return cb

    subs = [session.declare_subscriber(key(n) if key else f"{namespace}/{n}", on(n)) for n in names]
    stop.wait()
    for s in subs:
        s.undeclare()
    w.close()
    return count[0]


def wait_for_subscribers(publishers, timeout_s: float) -> list:
    """Wait until every publisher has a matching subscriber, or ``timeout_s``; returns those that
    have none. Why: a sample published before the receiver's subscription has reached this session
    goes nowhere, and a replay's first samples would then be missing for the service (it waits
    ``gap_s`` for them, then counts a sequence gap)."""
    end = time.monotonic() + timeout_s
    while True:
        unmatched = [p for p in publishers if not p.matching_status.matching]
        if not unmatched or time.monotonic() >= end:
            return unmatched
        time.sleep(0.005)


def replay(
    session: zenoh.Session,
    namespace: str,
    messages: list[Message],
    fast: bool = True,
    speed: float = 1.0,
    wait_s: float = 10.0,
) -> int:
    """Publish on ``{namespace}/<name>``: as fast as possible (reliable, blocking: nothing dropped) or
    paced by the recorded log times. Every sample carries its place in the send order (see
    :mod:`service.ordering`), so a message-clock service handles them in this order whatever order
    the transport delivers them in. Sending starts once every topic has a subscriber, or after
    ``wait_s`` (then with a warning: what nobody subscribes to is lost). Returns the number of
    messages sent."""
    pubs = {
        n: session.declare_publisher(
            f"{namespace}/{n}",
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        for n in {m.name for m in messages}
    }
    unmatched = wait_for_subscribers(list(pubs.values()), wait_s)
    if unmatched:
        log.warning(
            "replay: no subscriber on %s after %.0f s: sending anyway",
            ", ".join(str(p.key_expr) for p in unmatched),
            wait_s,
        )
    t0_log, t0_wall = (messages[0].log_time if messages else 0), time.perf_counter()
    stream = new_stream_id()
    for seq, m in enumerate(messages):
        if not fast:
            delay = (m.log_time - t0_log) / 1e9 / speed - (time.perf_counter() - t0_wall)
            if delay > 0:
                time.sleep(delay)
        pubs[m.name].put(m.data, attachment=encode_order(stream, seq, last=seq == len(messages) - 1))
    for p in pubs.values():
        p.undeclare()
    return len(messages)
