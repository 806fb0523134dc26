"""The gripper poses sampled at the loop's steady step, by their stamps (wall clock and message clock).

Why: the model steps ``dt`` per tick, so the grip it steps to must advance ``dt`` of the robot's time
per tick. Taking the newest pose at each tick does not: poses arrive with jitter, in bursts when
their sender is busy, or at another rate (125 Hz, 500 Hz), so some ticks repeat a pose and the next
jumps two; the model then sees the gripper stop and lurch, and the rope whips. Measured on the live
service fed at 100 Hz over loopback: a fifth to two fifths of the ticks repeated a pose.

Here each tick samples the poses at a time ``tau`` that advances ``dt`` per tick and follows, slowly,
the newest stamp less a ``delay`` (1.5 times the poses' median interval unless set), so that the
poses around ``tau`` have almost always arrived; between two poses the positions are interpolated
linearly and the orientations along the shorter arc (normalised linear interpolation, exact enough
over one pose interval).

When the samples fall far behind (the first tick settles the rope for half a second, the loop
stalls), the next tick steps through the poses missed, one sample a period, up to ``CATCH_UP_S``:
jumped to in one step, the grippers would move that far in 10 ms and whip the model's rope (measured
on the live service: 2 m/s after the first cloud, then repeated redetections). A longer gap (a paused
sender) or samples ahead of their target (a sender whose clock went back) are jumped (``jumped``: the
estimator then stops the rope, which the jump's step threw).

On the message clock (a replay, the demo) nothing arrives late, so :class:`PoseGrid` ticks on a
fixed grid of the poses' own time: every ``dt`` from the first pose, each tick's poses interpolated
between the two messages around it. A bag with poses at 125 Hz (or 500, or 30) then plays at the
rate it was recorded; one tick per message ran it 1.25x (5x, 0.3x) slow in the model's time.
"""

from __future__ import annotations

from bisect import bisect_right
from collections import deque
from itertools import islice

import numpy as np

from service.geometry import interpolate_poses

NS = 1_000_000_000
FOLLOW = 0.1  # of the gap between tau and its target closed per tick (a 10-tick time constant)
RESET_S = 0.1  # a gap wider than this (a start, a pause, a new sender) is not followed slowly ...
CATCH_UP_S = 1.0  # ... but stepped through when the samples are at most this far behind; else jumped
KEEP_S = CATCH_UP_S + 0.2  # poses kept this long: those a catch-up steps through, at any rate
AUTO_PERIODS = 1.5  # the automatic delay in median pose intervals ...
DELAY_POSES = 65  # ... of the last this many poses
GRID_GAP_S = 1.0  # message clock: poses farther apart than this start the grid again at the later one


class PoseTimeline:
    """Poses in, one sample per tick out (:meth:`next`).

    Args:
        dt_s: the loop's period [s].
        delay_s: how far behind the newest stamp the samples follow [s]; None: ``AUTO_PERIODS``
            times the median interval of the last ``DELAY_POSES`` poses.
        max_poses: at most this many poses kept; otherwise those of the last ``KEEP_S`` (a
            catch-up steps through them, at any pose rate) and at least three.
    """

    def __init__(self, dt_s: float, delay_s: float | None = None, max_poses: int = 4096):
        self.dt_ns = round(dt_s * NS)
        self.delay_s = delay_s
        self.stamps: deque[int] = deque(maxlen=max_poses)
        self.values: deque[np.ndarray] = deque(maxlen=max_poses)
        self.tau: int | None = None
        self.jumped = False  # the last :meth:`next` jumped (a gap beyond CATCH_UP_S, or back in time)
        self._auto_ns: int | None = None  # the automatic delay of the poses kept (None: to compute)

    def add(self, stamp_ns: int, poses: np.ndarray) -> None:
        """A pose message (stamps increasing: the estimator refuses others)."""
        self.stamps.append(int(stamp_ns))
        self.values.append(np.asarray(poses, dtype=float))
        oldest = int(stamp_ns) - round(KEEP_S * NS)
        while len(self.stamps) > 3 and self.stamps[0] < oldest:
            self.stamps.popleft()
            self.values.popleft()
        self._auto_ns = None

    def delay_ns(self) -> int:
        if self.delay_s is not None:
            return round(self.delay_s * NS)
        if len(self.stamps) < 3:
            return 0
        if self._auto_ns is None:  # once per pose, not once per tick
            recent = np.fromiter(islice(reversed(self.stamps), DELAY_POSES), dtype=np.int64)
            self._auto_ns = round(AUTO_PERIODS * float(np.median(-np.diff(recent))))
        return self._auto_ns

    def next(self) -> list[tuple[int, np.ndarray]]:
        """The samples ``(tau, poses (k, 7) at tau)`` the next tick steps through: one, or when the
        samples lag their target by more than ``RESET_S`` and at most ``CATCH_UP_S``, one a period
        up to the target (see the module docstring); empty before any pose."""
        self.jumped = False
        if not self.stamps:
            return []
        target = self.stamps[-1] - self.delay_ns()
        if self.tau is None:
            self.tau = target
            return [(target, self.at(target))]
        ahead = self.tau + self.dt_ns
        gap = target - ahead
        if RESET_S * NS < gap <= CATCH_UP_S * NS:
            count = round((target - self.tau) / self.dt_ns)  # at least 1: the gap exceeds RESET_S
            taus = [self.tau + round(j * (target - self.tau) / count) for j in range(1, count + 1)]
        elif abs(gap) > RESET_S * NS:
            taus, self.jumped = [target], True
        else:
            taus = [round(ahead + FOLLOW * gap)]
        self.tau = taus[-1]
        return [(t, self.at(t)) for t in taus]

    def at(self, t: int) -> np.ndarray:
        """The poses at ``t``: interpolated between the two kept around it, else the nearest end."""
        i = bisect_right(self.stamps, t)
        around = range(max(i - 1, 0), min(i + 1, len(self.stamps)))  # the two around t, or the end
        return interpolate_poses(
            np.array([self.stamps[j] for j in around]),
            np.stack([self.values[j] for j in around]),
            np.array([t]),
        )[0]


class PoseGrid:
    """Message clock: ticks every ``dt_s`` of the poses' own time from the first pose's stamp.

    :meth:`add` takes the pose messages in stamp order and returns the ticks each one completes,
    ``(time, poses (k, 7) at time)`` for every grid time after the previous message up to its stamp.
    A grid time on a stamp takes that message's poses as they are (poses exactly on the grid tick as
    one tick per message did, bit for bit); one between two messages interpolates them. A gap wider
    than ``gap_s`` (a paused sender) is not filled in: the grid starts again at the later message.
    """

    def __init__(self, dt_s: float, gap_s: float = GRID_GAP_S):
        self.dt_ns = round(dt_s * NS)
        self.gap_ns = round(gap_s * NS)
        self.last: tuple[int, np.ndarray] | None = None
        self.next_ns: int | None = None
        self.restarted = False  # the last :meth:`add` started the grid again after a gap

    def add(self, stamp_ns: int, poses: np.ndarray) -> list[tuple[int, np.ndarray]]:
        stamp_ns, poses = int(stamp_ns), np.asarray(poses, dtype=float)
        last, self.last = self.last, (stamp_ns, poses)
        self.restarted = last is not None and stamp_ns - last[0] > self.gap_ns
        if last is None or self.restarted:
            self.next_ns = stamp_ns + self.dt_ns
            return [(stamp_ns, poses)]
        ticks = []
        while self.next_ns <= stamp_ns:
            t = self.next_ns
            if t == stamp_ns:
                ticks.append((t, poses))
            else:
                ticks.append(
                    (
                        t,
                        interpolate_poses(
                            np.array([last[0], stamp_ns]), np.stack([last[1], poses]), np.array([t])
                        )[0],
                    )
                )
            self.next_ns += self.dt_ns
        return ticks
