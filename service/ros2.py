"""rmw_zenoh's wire conventions, so that a robot running ROS 2 on Zenoh sees the service with no bridge.

A ROS 2 node on ``rmw_zenoh_cpp`` (Jazzy and later; after ros2/rmw_zenoh ``docs/design.md``) finds and
exchanges data through three conventions, which this module writes down and nothing else:

- **data keys** ``<domain>/<topic>/<DDS type>/<type hash>``: the topic without its leading slash,
  the type as DDS names it (``geometry_msgs::msg::dds_::PoseArray_``) and its RIHS01 hash (computed
  by rosbags from the message definition). The payload is the CDR message, the same bytes
  zenoh-bridge-ros2dds carries.
- **an attachment on every sample**: sequence number (int64), source timestamp in ns (int64), then
  the publisher's GID as a length byte (16) and 16 bytes, all little-endian.
- **liveliness tokens** under ``@ros2_lv``, one for the node and one per publisher or subscription,
  from which ``ros2 topic list`` and ``ros2 node list`` build the graph::

    @ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>
    @ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP|MS/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>

  where ``/`` inside a name is written ``%`` and an empty name is ``%``.

Subscriptions accept any hash (``*``): a Humble node sends ``TypeHashNotSupported`` there. Written
by hand: rosbags gives the CDR and the hash, but no Python library offers these conventions for
a server process (zenoh-ros2-sdk, used as the independent reference in the tests, keeps one global
session per process and no way to serve an existing one).
"""

from __future__ import annotations

import os
import re
import struct
import threading
import time
from dataclasses import dataclass

import zenoh

from service import messages as M

ADMIN_SPACE = "@ros2_lv"
GID_BYTES = 16
_ROS_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


def dds_type(typename: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_`` (the type part of keys and tokens).

    Args:
        typename: a ROS 2 type, e.g. ``sensor_msgs/msg/PointCloud2``.

    Returns:
        The DDS type name.
    """
    pkg, kind, name = typename.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def type_hash(typename: str) -> str:
    """The RIHS01 hash of a message type (``RIHS01_<64 hex>``), from its definition (rosbags).

    Args:
        typename: a ROS 2 type known to the typestore of :mod:`service.messages`.

    Returns:
        The hash string as it appears in keys and tokens.
    """
    return M.TYPESTORE.hash_rihs01(typename)


def mangle(name: str) -> str:
    """A ROS name as one key chunk: ``/`` -> ``%``, the empty or root name -> ``%``.

    Args:
        name: a namespace, node or topic name.

    Returns:
        The mangled chunk.
    """
    return "%" if name in ("", "/") else name.replace("/", "%")


def topic_key(domain_id: int, topic: str, typename: str, hash_: str | None = None) -> str:
    """The data key of a topic; ``hash_=None``: its type's RIHS01 hash, ``"*"``: any hash.

    Args:
        domain_id: the ROS domain.
        topic: the absolute topic name, e.g. ``/deform/rod1/vertices``.
        typename: its message type.
        hash_: the hash chunk (see above).

    Returns:
        ``<domain>/<topic>/<DDS type>/<hash>``.
    """
    return f"{domain_id}/{topic.strip('/')}/{dds_type(typename)}/{hash_ or type_hash(typename)}"


def qos_token(depth: int = 10, reliable: bool = True) -> str:
    """The QoS part of an endpoint token: reliability, durability, history, deadline, lifespan,
    liveliness; empty fields mean the default (reliable, volatile, no deadline or lifespan,
    automatic liveliness), as rmw_zenoh writes them.

    Args:
        depth: KEEP_LAST history depth.
        reliable: False declares BEST_EFFORT.

    Returns:
        E.g. ``::,10:,:,:,,`` for the default profile.
    """
    return f"{'' if reliable else '2'}::,{int(depth)}:,:,:,,"


def encode_attachment(sequence: int, stamp_ns: int, gid: bytes) -> bytes:
    """The per-sample attachment: int64 sequence, int64 source time [ns], GID with its length.

    Args:
        sequence: the publisher's sample counter (from 1).
        stamp_ns: when the sample was published [ns since the epoch].
        gid: the publisher's 16-byte id.

    Returns:
        33 bytes, little-endian.
    """
    if len(gid) != GID_BYTES:
        raise ValueError(f"a GID has {GID_BYTES} bytes, got {len(gid)}")
    return struct.pack("<qqB", sequence, stamp_ns, GID_BYTES) + bytes(gid)


def decode_attachment(raw: bytes) -> tuple[int, int, bytes]:
    """Inverse of :func:`encode_attachment`.

    Args:
        raw: the attachment bytes.

    Returns:
        ``(sequence, stamp_ns, gid)``.
    """
    if len(raw) < 17:
        raise ValueError(f"attachment of {len(raw)} bytes: at least 17 expected")
    sequence, stamp, n = struct.unpack_from("<qqB", raw)
    if len(raw) < 17 + n:
        raise ValueError("attachment shorter than its GID length says")
    return sequence, stamp, bytes(raw[17 : 17 + n])


def check_names(namespace: str, node: str) -> None:
    """Refuse names a ROS 2 graph cannot hold (letters, digits and ``_``; no leading digit).

    Args:
        namespace: the service namespace without leading slash (``deform/rod1``).
        node: the node name.
    """
    if not _ROS_NAME.match("/" + namespace.strip("/")):
        raise ValueError(
            f"namespace {namespace!r} is not a ROS 2 name (letters, digits, _ per part, no leading digit)"
        )
    if not _ROS_NAME.match("/" + node) or "/" in node:
        raise ValueError(f"node name {node!r} is not a ROS 2 name")


@dataclass
class _Endpoint:
    token: object
    inner: object

    def undeclare(self) -> None:
        for d in (self.inner, self.token):
            try:
                d.undeclare()
            except Exception:
                pass


class Publisher:
    """A Zenoh publisher on a topic's data key that attaches sequence, time and GID to each sample."""

    def __init__(self, publisher, gid: bytes):
        self._pub, self.gid, self._seq = publisher, gid, 0
        self._lock = threading.Lock()

    def put(self, payload: bytes) -> None:
        with self._lock:
            self._seq += 1
            seq = self._seq
        self._pub.put(payload, attachment=encode_attachment(seq, time.time_ns(), self.gid))

    def undeclare(self) -> None:
        self._pub.undeclare()


class Node:
    """One ROS 2 node on an open Zenoh session: its liveliness token, and publishers and subscriptions
    that announce themselves the way rmw_zenoh does (``ros2 topic list`` shows them with their types).

    Args:
        session: the Zenoh session (the service's own).
        name: node name.
        namespace: node namespace, e.g. ``/deform/rod1``.
        domain_id: ROS domain (``ROS_DOMAIN_ID``).
    """

    def __init__(self, session: zenoh.Session, name: str, namespace: str, domain_id: int = 0):
        self.session, self.name, self.namespace, self.domain_id = session, name, namespace, domain_id
        self.zid = str(session.info.zid())
        self.node_id = 0
        self._next_entity = 1
        self._declared: list = []
        self._declared.append(session.liveliness().declare_token(self._prefix(self.node_id, "NN")))

    def _prefix(self, entity_id: int, kind: str) -> str:
        return (
            f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{entity_id}/{kind}/%/"
            f"{mangle(self.namespace)}/{mangle(self.name)}"
        )

    def _token(self, kind: str, topic: str, typename: str) -> object:
        entity, self._next_entity = self._next_entity, self._next_entity + 1
        key = (
            f"{self._prefix(entity, kind)}/{mangle(topic)}/{dds_type(typename)}/{type_hash(typename)}/"
            f"{qos_token()}"
        )
        return self.session.liveliness().declare_token(key)

    def publisher(self, topic: str, typename: str, **options) -> Publisher:
        """Declare a publisher (token ``MP``) on ``topic`` of ``typename``; ``options`` go to Zenoh."""
        token = self._token("MP", topic, typename)
        pub = Publisher(
            self.session.declare_publisher(topic_key(self.domain_id, topic, typename), **options),
            os.urandom(GID_BYTES),
        )
        self._declared.append(_Endpoint(token, pub))
        return pub

    def subscription(self, topic: str, typename: str, callback) -> None:
        """Subscribe (token ``MS``) to ``topic`` of ``typename`` from any publisher, with any hash."""
        token = self._token("MS", topic, typename)
        sub = self.session.declare_subscriber(topic_key(self.domain_id, topic, typename, "*"), callback)
        self._declared.append(_Endpoint(token, sub))

    def service(self, name: str, typename: str, callback) -> str:
        """Serve ``name`` of service type ``typename`` (token ``SS``): ``callback(query)`` gets each
        request (CDR payload, the client's attachment) and answers it with :func:`reply`.

        Returns:
            The key the queryable is declared on.
        """
        token = self._token("SS", name, typename)
        key = topic_key(self.domain_id, name, typename)
        queryable = self.session.declare_queryable(key, callback, complete=True)
        self._declared.append(_Endpoint(token, queryable))
        return key

    def close(self) -> None:
        """Undeclare everything (the tokens' disappearance tells the graph the node left)."""
        for d in reversed(self._declared):
            try:
                d.undeclare()
            except Exception:
                pass
        self._declared.clear()


def reply(query, payload: bytes) -> None:
    """Answer a service request as rmw_zenoh does: the response's CDR, and an attachment with the
    request's sequence number and client GID (how the client pairs them) and the time of reply."""
    att = query.attachment
    sequence, _, gid = decode_attachment(att.to_bytes()) if att is not None else (0, 0, bytes(GID_BYTES))
    if len(gid) != GID_BYTES:
        gid = bytes(GID_BYTES)
    query.reply(query.key_expr, payload, attachment=encode_attachment(sequence, time.time_ns(), gid))
