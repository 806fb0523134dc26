r"""How late the clouds are stamped against the gripper poses, from where the rope leaves the grippers.

A camera driver may stamp a cloud when it arrives rather than when it was taken, or run on a clock of
its own: the stamps then lag (or lead) the poses by a delay :math:`\tau`, and a tracker that corrects
the state at a cloud's stamp sees the rope where it was :math:`\tau` earlier. Read as physics, that
lag is damping and softness the rope does not have.

The rope leaves each gripper at a point the poses give exactly: the end edge's inner vertex (vertex 1
and :math:`n-2`, ``d1`` along the gripper's axis). Each cloud shows the rope there at the moment it
was taken. For every candidate delay, the cost is the distance from those two points, placed with the
poses at :math:`t_{stamp} - \tau`, to the nearest rope point of the cloud (capped at 3 cm, so a
hidden end counts as a constant), averaged over clouds; the delay is the minimum over a 5 ms grid.
No model enters: the estimate is the same before and after calibration. Grippers that hardly move
do not tell the delay; the curve is then flat, and the estimate is taken only when its minimum lies
clearly below the cost at zero delay.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from calibrate.bags import Clip
from service.config import Grippers
from service.geometry import grips_from_poses, interpolate_poses

DELAYS_S = np.round(np.arange(-0.1, 0.2 + 1e-9, 0.005), 3)  # the candidates: 100 ms early to 200 ms late
CAP_M = 0.03  # a distance above this is a hidden or unsegmented end: it counts as this
CLOUDS_PER_CLIP = 60  # clouds read per clip (spread over it)
MIN_POINTS = 20  # rope points a cloud needs to count
GAIN = 0.9  # the best delay's cost must be below this share of the cost at zero to be taken


@dataclass(frozen=True)
class CloudDelay:
    """``delay_s``: the delay taken (0 when the clips do not tell it); ``best_s``: the curve's
    minimum; the costs [m] there and at zero; ``clouds`` read."""

    delay_s: float
    best_s: float
    cost_at_best_m: float
    cost_at_zero_m: float
    clouds: int

    @property
    def told(self) -> bool:
        return self.delay_s != 0.0

    def as_dict(self) -> dict:
        return dict(
            delay_s=self.delay_s,
            best_s=self.best_s,
            cost_at_best_m=round(self.cost_at_best_m, 5),
            cost_at_zero_m=round(self.cost_at_zero_m, 5),
            clouds=self.clouds,
        )


def delay_costs(clip: Clip, grippers: Grippers, segmentation, delays: np.ndarray = DELAYS_S) -> tuple:
    """``(summed costs per delay [m], terms)`` of one clip (see the module)."""
    from perception import segment_rope

    total, terms = np.zeros(len(delays)), 0
    shifts = np.round(np.asarray(delays) * 1e9).astype(np.int64)
    first, last = int(clip.pose_stamps_ns[0]), int(clip.pose_stamps_ns[-1])
    every = max(1, int(np.ceil(clip.n_clouds / CLOUDS_PER_CLIP)))
    for k, (stamp, xyz, rgb) in enumerate(clip.clouds()):
        times = stamp - shifts
        if k % every or times.min() < first or times.max() > last:
            continue
        points = segment_rope(xyz, rgb, segmentation)
        if len(points) < MIN_POINTS:
            continue
        tree = cKDTree(clip.camera.to_world(points))
        grips = grips_from_poses(interpolate_poses(clip.pose_stamps_ns, clip.poses, times), grippers)
        d, _ = tree.query(grips[:, 1:3].reshape(-1, 3), distance_upper_bound=CAP_M)
        total += np.minimum(d, CAP_M).reshape(len(delays), 2).sum(1)
        terms += 2
    return total, terms


def cloud_delay(clips: list[Clip], grippers: Grippers, segmentation) -> CloudDelay:
    """The delay of the clouds' stamps behind the poses, over all ``clips`` (one camera, one clock).

    Args:
        clips: the bags (:func:`calibrate.bags.read_clip`).
        grippers: the gripper convention (service config).
        segmentation: perception's segmentation settings (the rope's colour range).

    Returns:
        A :class:`CloudDelay`; ``delay_s`` 0 when no cloud shows the rope at the grippers or the
        curve's minimum is not clearly below its value at zero delay.
    """
    total, terms = np.zeros(len(DELAYS_S)), 0
    for clip in clips:
        t, n = delay_costs(clip, grippers, segmentation)
        total, terms = total + t, terms + n
    if terms == 0:
        return CloudDelay(0.0, 0.0, float("nan"), float("nan"), 0)
    cost = total / terms
    best = int(np.argmin(cost))
    zero = int(np.argmin(np.abs(DELAYS_S)))
    taken = float(DELAYS_S[best]) if cost[best] < GAIN * cost[zero] else 0.0
    return CloudDelay(taken, float(DELAYS_S[best]), float(cost[best]), float(cost[zero]), terms // 2)
