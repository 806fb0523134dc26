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

A request may come the same way (magic ``b"DFPQ"``): the header holds the JSON request's fields
other than ``plans`` (``dt``, ``id``, ``return``, ``encoding``, ``cost``) plus ``shape`` [P, S, 2, 7]
and ``dtype`` (``"<f8"`` or ``"<f4"``), then the plans' poses follow as little-endian floats in C
order. 1024 plans x 100 steps are 11.5 MB this way in float64 (5.7 MB in float32) against about
28 MB of JSON.
"""

from __future__ import annotations

import json
import struct

import numpy as np

MAGIC = b"DFPR"
REQUEST_MAGIC = b"DFPQ"
_REQUEST_DTYPES = ("<f8", "<f4")
VERSION = 1
_FIXED = struct.Struct("<4sHHI")


class CodecError(ValueError):
    """Bytes that are not a binary predict reply of a version this code reads."""


def encode(vertices: np.ndarray, header: dict) -> bytes:
    """Vertices (P, K, n, 3) and the header fields (``id``, ``stamp``, ``steps``,
    ``overstretched``) -> the binary reply."""
    data = np.ascontiguousarray(vertices, dtype="<f4")
    return encode_parts(list(data.shape), header, [data.tobytes()])


def encode_parts(shape: list[int], header: dict, parts: list[bytes]) -> bytes:
    """The binary reply from its vertices in consecutive blocks of plans, each already as
    little-endian float32 bytes (the predict processes' shares of one request, joined in order).

    Args:
        shape: [P, K, n, 3] of all the parts together.
        header: the other header fields.
        parts: the blocks' bytes, in plan order.

    Returns:
        The reply, the same bytes as :func:`encode` of the whole array.
    """
    head = json.dumps({**header, "shape": list(shape), "dtype": "<f4"}).encode()
    return b"".join([_FIXED.pack(MAGIC, VERSION, 0, len(head)), head, *parts])


def is_binary(payload: bytes) -> bool:
    return payload[:4] == MAGIC


def encode_request(plans: np.ndarray, fields: dict, dtype: str = "<f8") -> bytes:
    """Plans (P, S, 2, 7) and the other request fields -> a binary predict request."""
    if dtype not in _REQUEST_DTYPES:
        raise ValueError(f"dtype must be one of {_REQUEST_DTYPES}")
    data = np.ascontiguousarray(plans, dtype=dtype)
    head = json.dumps({**fields, "shape": list(data.shape), "dtype": dtype}).encode()
    return _FIXED.pack(REQUEST_MAGIC, VERSION, 0, len(head)) + head + data.tobytes()


def is_binary_request(payload: bytes) -> bool:
    return payload[:4] == REQUEST_MAGIC


def request_shape(payload: bytes) -> tuple[int, ...] | None:
    """The plans' shape a binary request's header states (its data unread), or None (JSON, or a
    header that does not parse: the full parse then reports the error)."""
    if not is_binary_request(payload) or len(payload) < _FIXED.size:
        return None
    _, _, _, size = _FIXED.unpack_from(payload)
    try:
        return tuple(int(k) for k in json.loads(payload[_FIXED.size : _FIXED.size + size])["shape"])
    except (ValueError, KeyError, TypeError):
        return None


def request_plans(payload: bytes) -> int | None:
    """The plan count a binary request's header states, or None (see :func:`request_shape`)."""
    shape = request_shape(payload)
    return shape[0] if shape else None


def split_request(payload: bytes, bounds: list[tuple[int, int]]) -> list[bytes] | None:
    """A binary request cut into requests of consecutive blocks of its plans, ``[lo, hi)`` for each
    of ``bounds``, with the same other fields: what each predict process is sent, so that the
    processes together receive and parse the request once rather than once each (1024 plans x 100
    steps are 11.5 MB).

    Returns:
        The blocks' requests, or None when the request does not decode to (plans, steps, 2, 7)
        (the whole request then goes to one process, whose parse reports the error).
    """
    try:
        fields, data = _split(payload, REQUEST_MAGIC, _REQUEST_DTYPES)
    except CodecError:
        return None
    if data.ndim != 4 or data.shape[2:] != (2, 7):
        return None
    return [encode_request(data[lo:hi], fields, data.dtype.str) for lo, hi in bounds]


def decode_request(payload: bytes) -> tuple[dict, np.ndarray]:
    """A binary predict request -> (its other fields, plans as float64)."""
    fields, data = _split(payload, REQUEST_MAGIC, _REQUEST_DTYPES)
    return fields, data.astype(np.float64)


def _split(payload: bytes, magic: bytes, dtypes: tuple[str, ...]) -> tuple[dict, np.ndarray]:
    if len(payload) < _FIXED.size:
        raise CodecError("too short for a predict message")
    got, version, _, size = _FIXED.unpack_from(payload)
    if got != magic:
        raise CodecError(f"not a binary predict message ({magic!r})")
    if version != VERSION:
        raise CodecError(f"predict message version {version}; this code reads {VERSION}")
    try:
        header = json.loads(payload[_FIXED.size : _FIXED.size + size])
        shape, dtype = tuple(int(k) for k in header.pop("shape")), header.pop("dtype")
    except (ValueError, KeyError, TypeError, AttributeError):
        raise CodecError("bad header") from None
    if dtype not in dtypes:
        raise CodecError(f"dtype {dtype!r}, expected one of {dtypes}")
    data = np.frombuffer(payload, dtype=dtype, offset=_FIXED.size + size)
    if data.size != int(np.prod(shape)) or any(k < 0 for k in shape):
        raise CodecError(f"{data.size} values for shape {shape}")
    return header, data.reshape(shape)


def decode(payload: bytes) -> tuple[dict, np.ndarray]:
    """The binary reply -> (header dict, vertices (P, K, n, 3) float32)."""
    header, data = _split(payload, MAGIC, ("<f4",))
    return {**header, "shape": list(data.shape), "dtype": "<f4"}, data
