"""The binary predict reply (numpy only: the service and :mod:`service.client` share it).

A JSON reply of 1024 plans x 100 steps is tens of megabytes of decimal text; this is the same
content as little-endian float32 behind a small self-describing header (version 1)::

    offset  size  field
    0       4     magic b"DFPR"
    4       2     uint16 version (1)
    6       2     uint16 reserved (0)
    8       4     uint32 H, length of the header
    12      H     UTF-8 JSON header: {"id", "stamp", "shape": [P, K, n, 3], "dtype": "<f4",
                  "steps": [k, ...] (1-based step numbers returned), "overstretched": [bool] * P}
    12 + H  ...   P * K * n * 3 float32, little-endian, C order: the vertices [m]

The Zenoh reply carries encoding ``application/octet-stream`` (JSON replies ``application/json``).
"""

from __future__ import annotations

import json
import struct

import numpy as np

MAGIC = b"DFPR"
VERSION = 1
_FIXED = struct.Struct("<4sHHI")


class CodecError(ValueError):
    """Bytes that are not a binary predict reply of a version this code reads."""


def encode(vertices: np.ndarray, header: dict) -> bytes:
    """Vertices (P, K, n, 3) and the header fields (``id``, ``stamp``, ``steps``,
    ``overstretched``) -> the binary reply."""
    data = np.ascontiguousarray(vertices, dtype="<f4")
    head = json.dumps({**header, "shape": list(data.shape), "dtype": "<f4"}).encode()
    return _FIXED.pack(MAGIC, VERSION, 0, len(head)) + head + data.tobytes()


def is_binary(payload: bytes) -> bool:
    return payload[:4] == MAGIC


def decode(payload: bytes) -> tuple[dict, np.ndarray]:
    """The binary reply -> (header dict, vertices (P, K, n, 3) float32)."""
    if len(payload) < _FIXED.size:
        raise CodecError("too short for a predict reply")
    magic, version, _, size = _FIXED.unpack_from(payload)
    if magic != MAGIC:
        raise CodecError("not a binary predict reply (magic)")
    if version != VERSION:
        raise CodecError(f"predict reply version {version}; this client reads {VERSION}")
    header = json.loads(payload[_FIXED.size : _FIXED.size + size])
    shape = tuple(header["shape"])
    data = np.frombuffer(payload, dtype=header["dtype"], offset=_FIXED.size + size)
    if data.size != int(np.prod(shape)):
        raise CodecError(f"{data.size} values for shape {shape}")
    return header, data.reshape(shape)
