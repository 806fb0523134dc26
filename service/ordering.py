"""Send order across keys, for bit-exact replays on the message clock.

Zenoh keeps the order of one publisher's samples, not the order between keys: a small camera_info or
pose sample can overtake a fragmented point cloud published before it, and a replay's outcome then
depends on transport timing (a cloud that overtakes its camera_info is rejected; one that arrives
after its tick is fused a tick late). A replay therefore stamps every sample with one counter shared
by all its publishers (a Zenoh attachment); the message clock releases samples in that counter's
order, whatever order they arrive in. Samples without the attachment (any other publisher) are
released as they arrive.

Attachment layout (18 bytes): ``b"DFSQ"``, version ``1`` (one byte), flags (one byte; bit 0: the
stream's last sample), stream id (8 bytes, random per replay), sequence number (uint64
little-endian, 0 for a stream's first sample). The last-sample flag lets the service tick the final
poses at once instead of waiting for the input to go idle (which would make the result depend on
how long the sender paused).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field
from typing import NamedTuple

MAGIC = b"DFSQ"
VERSION = 1
_LAYOUT = struct.Struct("<4sBB8sQ")
LAST = 1


class Order(NamedTuple):
    stream: bytes
    seq: int
    last: bool = False


def new_stream_id() -> bytes:
    """A random id for one replay: two replays into one service are ordered separately."""
    return os.urandom(8)


def encode_order(stream: bytes, seq: int, last: bool = False) -> bytes:
    """The attachment of the ``seq``-th sample (from 0) of replay ``stream``."""
    return _LAYOUT.pack(MAGIC, VERSION, LAST if last else 0, stream, seq)


def decode_order(attachment: bytes | None) -> Order | None:
    """The :class:`Order` of an attachment written by :func:`encode_order`, else None (unordered)."""
    if attachment is None or len(attachment) != _LAYOUT.size:
        return None
    magic, version, flags, stream, seq = _LAYOUT.unpack(attachment)
    if magic != MAGIC or version != VERSION:
        return None
    return Order(stream, seq, bool(flags & LAST))


@dataclass
class _Stream:
    expected: int = 0
    held: dict[int, object] = field(default_factory=dict)
    gap_since: float | None = None  # when a sample was first held waiting for ``expected``


class SequenceBuffer:
    """Reorders samples of each stream into send order.

    :meth:`push` returns the samples that can be processed now, in order. A sample whose predecessor
    has not arrived is held; if the gap is still open ``patience_s`` later (the predecessor was lost,
    or the stream started before the service), :meth:`expire` gives up on it and releases what is held.
    """

    def __init__(self, patience_s: float):
        self.patience_s = patience_s
        self._streams: dict[bytes, _Stream] = {}
        self.gaps = 0  # sequence numbers given up on

    def push(self, item, order: Order | tuple[bytes, int] | None, now: float) -> list:
        if order is None:
            return [item]
        stream_id, seq = order[0], order[1]
        st = self._streams.setdefault(stream_id, _Stream())
        if seq < st.expected:  # a duplicate or one already given up on: too late to keep the order
            return [item]
        st.held[seq] = item
        out = self._drain(st)
        if not st.held:
            st.gap_since = None
        elif out or st.gap_since is None:  # a new gap opens now
            st.gap_since = now
        return out

    def expire(self, now: float) -> list:
        """Release what waits behind gaps older than ``patience_s``."""
        out = []
        for st in self._streams.values():
            if st.held and st.gap_since is not None and now - st.gap_since >= self.patience_s:
                first = min(st.held)
                self.gaps += first - st.expected
                st.expected = first
                out += self._drain(st)
                st.gap_since = now if st.held else None
        return out

    def holding(self) -> bool:
        return any(st.held for st in self._streams.values())

    @staticmethod
    def _drain(st: _Stream) -> list:
        out = []
        while st.expected in st.held:
            out.append(st.held.pop(st.expected))
            st.expected += 1
        return out
