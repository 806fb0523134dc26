"""Counters, rolling timing percentiles and rate-limited log lines: what `{ns}/status` reports.

Rejections are counted per reason and logged at most once a second per reason, so a flood of bad
messages cannot turn into a flood of log lines that slows the loop.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque

import numpy as np

log = logging.getLogger("deform.service")


class Rolling:
    """The last ``size`` samples of a duration, for p50/p99 without unbounded memory."""

    def __init__(self, size: int = 2000):
        self._buf = deque(maxlen=size)

    def add(self, value: float) -> None:
        self._buf.append(value)

    def values(self, last: int | None = None) -> list[float]:
        """The buffered samples, oldest first (all, or the ``last`` ones)."""
        values = list(self._buf)
        return values[-last:] if last else values

    def latest(self) -> float | None:
        """The newest sample, or None before the first."""
        return self._buf[-1] if self._buf else None

    def summary(self, scale: float = 1e3, last: int | None = None) -> dict:
        """p50, p99 and max (times ``scale``: ms by default) over the buffer or its ``last`` samples."""
        values = self.values(last)
        if not values:
            return {"p50": None, "p99": None, "max": None, "n": 0}
        a = np.fromiter(values, dtype=float) * scale
        return {
            "p50": round(float(np.percentile(a, 50)), 4),
            "p99": round(float(np.percentile(a, 99)), 4),
            "max": round(float(a.max()), 4),
            "n": len(a),
        }


class Stats:
    def __init__(self, namespace: str = ""):
        self.namespace = namespace
        self.rejected: Counter = Counter()
        self.dropped: Counter = Counter()
        self.counts: Counter = Counter()
        self.step_s = Rolling()
        self.publish_s = Rolling()  # tick start -> vertices handed to Zenoh
        self.fusion_s = Rolling(500)
        self.cloud_age_s = Rolling(500)  # wall clock: a cloud's stamp -> its correction in the estimate
        self.predict_s = Rolling(200)  # a predict job handed to the worker -> its reply back (IPC included)
        self.predict_compute_s = Rolling(200)  # the same job inside the worker: parse, rollout, encode
        self.tick_starts = deque(maxlen=500)
        self._last_log: dict[str, float] = {}
        self._lock = threading.Lock()

    def _log(self, key: str, level: int, msg: str) -> None:
        now = time.monotonic()
        with self._lock:
            if now - self._last_log.get(key, -1e9) < 1.0:
                return
            self._last_log[key] = now
        log.log(level, "[%s] %s", self.namespace, msg)

    def reject(self, topic: str, reason: str, detail: str = "") -> None:
        key = f"{topic}:{reason}"
        with self._lock:
            self.rejected[key] += 1
            total = self.rejected[key]
        self._log(
            key,
            logging.WARNING,
            f"rejected {topic} ({reason}{': ' + detail if detail else ''}); {total} so far",
        )

    def drop(self, what: str, detail: str = "") -> None:
        with self._lock:
            self.dropped[what] += 1
            total = self.dropped[what]
        self._log(
            "drop:" + what,
            logging.INFO,
            f"dropped {what}{' (' + detail + ')' if detail else ''}; {total} so far",
        )

    def count(self, what: str, k: int = 1) -> None:
        with self._lock:
            self.counts[what] += k

    def rate_hz(self) -> float | None:
        ts = list(self.tick_starts)
        if len(ts) < 2 or ts[-1] <= ts[0]:
            return None
        return round((len(ts) - 1) / (ts[-1] - ts[0]), 2)

    def snapshot(self) -> dict:
        with self._lock:
            return {
                "rejected": dict(self.rejected),
                "dropped": dict(self.dropped),
                "counts": dict(self.counts),
            }
