r"""What the tracks say about the input, before any fitting: is the rope seen at all, does its
length agree with ``--length``, is there motion to identify anything from.

Length: with :math:`g_1, g_2` the inner gripped vertices and :math:`L_{free}` the rope between
them (the given length less the two gripped end edges), every rope point satisfies
:math:`|p - g_1| + |p - g_2| \le L_{free}` (:func:`calibrate.points.reach_bound`), and the grippers
can never hold :math:`g_1, g_2` farther apart than :math:`L_{free}`. A rope longer than stated
shows points beyond the bound (or grippers beyond reach); a rope shorter than stated never comes
near it. The bound's 90th percentile over the clouds (the rope spread out, not hanging in a tight
U) is compared with :math:`L_{free}`: beyond 1.25, or below 0.7, the two disagree. For a rope
of the stated length the ratio lies near 0.9-1.0 in any pose a robot holds it in (a catenary of
span 0.75 L reaches 0.92 L at its lowest point), and a little above 1 from the depth noise and
the surface offset.
"""

from __future__ import annotations

import numpy as np

from calibrate.errors import CalibrationError
from calibrate.points import reach_bound
from calibrate.tracks import Track

MIN_ROPE_POINTS = 10  # rope voxels a cloud needs to count as showing the rope
LONGER, SHORTER = 1.25, 0.7  # ratio of the reach bound to the stated free length
MIN_SECONDS = 2.0  # of tracks in all
MIN_MOTION_M = 0.02  # gripper travel below which nothing can be identified


def check_rope_seen(tracks: list[Track], segmentation) -> None:
    """Raise when the colour range finds the rope in fewer than a tenth of the clouds.

    Args:
        tracks: all tracked clips.
        segmentation: perception's segmentation settings (named in the message).

    Raises:
        CalibrationError: the colour range finds no rope.
    """
    counts = np.array([len(p) for t in tracks for p in t.cloud_points])
    if len(counts) == 0 or np.mean(counts >= MIN_ROPE_POINTS) < 0.1:
        raise CalibrationError(
            f"the colour range HSV {tuple(segmentation.hsv_low)}..{tuple(segmentation.hsv_high)} finds no "
            f"rope in {int(np.sum(counts < MIN_ROPE_POINTS))} of {len(counts)} clouds: set segmentation "
            "hsv_low/hsv_high in a perception settings file (--perception)"
        )


def seen_length(tracks: list[Track]) -> tuple[float, float]:
    """(reach bound, gripper span) [m]: the 90th percentile over clouds of
    :func:`calibrate.points.reach_bound`, and the 99th percentile over steps of the inner gripped
    vertices' distance."""
    bounds = [
        reach_bound(p, t.grips[k])
        for t in tracks
        for k, p in zip(t.cloud_steps, t.cloud_points)
        if len(p) >= 2 * MIN_ROPE_POINTS
    ]
    spans = np.concatenate([np.linalg.norm(t.grips[:, 1] - t.grips[:, 2], axis=-1) for t in tracks])
    return (float(np.quantile(bounds, 0.9)) if bounds else float("nan")), float(np.quantile(spans, 0.99))


def check_length(tracks: list[Track], length_m: float, free_length_m: float) -> dict:
    """Raise when the rope the camera sees is clearly longer or shorter than ``--length``.

    Args:
        tracks: all tracked clips.
        length_m: the stated length [m].
        free_length_m: the stated length between the inner gripped vertices [m].

    Returns:
        ``{"reach_bound_m", "gripper_span_m", "ratio"}`` for the report.

    Raises:
        CalibrationError: the two disagree (see the module docstring).
    """
    bound, span = seen_length(tracks)
    ratio = bound / free_length_m
    found = {"reach_bound_m": bound, "gripper_span_m": span, "ratio": ratio}
    if span > 1.1 * free_length_m or ratio > LONGER:
        seen = max(bound, span)
        raise CalibrationError(
            f"the camera sees at least {seen:.2f} m of rope between the grippers, more than --length "
            f"{length_m:g} m allows ({free_length_m:.2f} m between them): is the length right?"
        )
    if ratio < SHORTER:
        raise CalibrationError(
            f"the rope the camera sees between the grippers never reaches more than {bound:.2f} m, "
            f"{ratio:.0%} of what --length {length_m:g} m gives ({free_length_m:.2f} m): is the length right?"
        )
    return found


def motion_problem(tracks: list[Track], needed_frames: int) -> str | None:
    """Why the tracks cannot identify anything (too short, too still), or None.

    Args:
        tracks: the usable tracks.
        needed_frames: frames a training window needs.

    Returns:
        A sentence for the report, or None.
    """
    total = sum(t.duration_s for t in tracks)
    if total < MIN_SECONDS or max((t.n_frames for t in tracks), default=0) < needed_frames:
        return (
            f"the clips are too short: {total:.1f} s tracked in all, the longest "
            f"{max((t.duration_s for t in tracks), default=0):.2f} s; calibration needs at least "
            f"{MIN_SECONDS:g} s and one clip of {needed_frames * tracks[0].dt if tracks else 0:.2f} s"
        )
    travel = max(float(np.linalg.norm(t.grips - t.grips[:1], axis=-1).max()) for t in tracks)
    if travel < MIN_MOTION_M:
        return (
            f"the clips are too still: the grippers move at most {travel * 100:.1f} cm; the rope's "
            f"stiffness and damping show only in motion (move the grippers by {MIN_MOTION_M * 100:g} cm or more)"
        )
    return None
