"""Marker label swaps: two neighbouring markers that trade names for a while.

Markers on a rope look alike, and a motion-capture system that loses one for a moment can give it
back under its neighbour's label. The two then jump by a marker spacing in one frame (10 m/s at
10 cm and 100 Hz, below any speed check a moving rope would pass), and every fit sees a rope folded
back on itself. Within a frame period a marker moves far less than the spacing to its neighbour, so
a swap shows as the crossed assignment to the previous frame being much shorter than the labelled
one; labels are restored frame by frame from the first frame on.
"""

from __future__ import annotations

import numpy as np

from deform.io.recordings import Recording

# a frame's neighbours are swapped back when the crossed assignment is shorter than this share of the
# labelled one: a real swap of markers 3-10 cm apart moving at most 2 cm a frame gives at most 0.2-0.5
# of it; the rope's own motion never favours the crossed one by that much
CROSSED_SHARE = 0.25


def fix_label_swaps(positions: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Swap neighbouring markers back wherever their labels crossed.

    Args:
        positions: (T, n, 3) [m], no NaN.

    Returns:
        ``(positions, swaps)``: the corrected copy (the input when nothing crossed) and each
        ``(frame, i)`` where markers i and i+1 were swapped back (every frame of a crossed
        stretch: each frame is compared with the corrected one before it).
    """
    swaps: list[tuple[int, int]] = []
    x = positions.copy()
    for t in range(1, x.shape[0]):
        prev, cur = x[t - 1], x[t]  # cur is a view: swaps are made in x
        straight = np.linalg.norm(cur[:-1] - prev[:-1], axis=-1) + np.linalg.norm(cur[1:] - prev[1:], axis=-1)
        crossed = np.linalg.norm(cur[:-1] - prev[1:], axis=-1) + np.linalg.norm(cur[1:] - prev[:-1], axis=-1)
        last = -2
        for i in np.flatnonzero(crossed < CROSSED_SHARE * straight):
            if i == last + 1:  # overlapping pairs: the first one decided
                continue
            cur[[i, i + 1]] = cur[[i + 1, i]]
            swaps.append((t, int(i)))
            last = i
    return (x if swaps else positions), swaps


def fix_recordings_labels(recordings: list[Recording]) -> tuple[list[Recording], str | None]:
    """:func:`fix_label_swaps` on each recording, and one line saying what was restored (None when
    no labels crossed).

    Args:
        recordings: without NaN.

    Returns:
        ``(recordings, note)``.
    """
    out, done = [], []
    for r in recordings:
        x, swaps = fix_label_swaps(r.positions)
        out.append(Recording(name=r.name, positions=x, dt=r.dt) if swaps else r)
        if swaps:
            pairs = sorted({i for _, i in swaps})
            done.append(
                f"{r.name} (markers {', '.join(f'{i}-{i + 1}' for i in pairs)}: {len(swaps)} frame(s))"
            )
    if not done:
        return out, None
    return out, "marker labels swapped between neighbours and restored in " + "; ".join(done)
