"""Does a circular arc explain how the chord from a gripper to the first free marker varies?

The chord between a gripper's inner marker and the first free marker varies by millimetres within a
recording (README, known limits). If the cable left the gripper along the axis of its two markers
and bent along a circular arc of fixed length L, the chord would be ``L sin(a) / a`` with ``a`` the
angle between that axis and the chord. This compares, over a rod's train recordings, the mean
|chord - prediction| of that model (L from each recording's first frame, or its median: an oracle)
with a constant chord (the first frame's).

    python benchmarks/gripper_chords.py [--rods DLO1 DLO2 DLO3]
"""

import argparse

import numpy as np

from deform.io.recordings import find_data_root, load_recordings


def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c = (a * b).sum(-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return np.arccos(np.clip(c, -1.0, 1.0))


def sinc(a: np.ndarray) -> np.ndarray:
    return np.where(a < 1e-6, 1.0, np.sin(a) / np.maximum(a, 1e-9))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rods", nargs="*", default=["DLO1", "DLO2", "DLO3"])
    args = ap.parse_args()
    root = find_data_root()
    if root is None:
        raise SystemExit("no DEFORM data (set DEFORM_DATA)")
    for rod in args.rods:
        recs = load_recordings(root / rod / "train")
        for side in ("first", "last"):
            const, arc0, arc_med = [], [], []
            for r in recs:
                P = r.positions
                axis, chord = (
                    (P[:, 1] - P[:, 0], P[:, 2] - P[:, 1])
                    if side == "first"
                    else (P[:, -2] - P[:, -1], P[:, -3] - P[:, -2])
                )
                c, a = np.linalg.norm(chord, axis=-1), angle(axis, chord)
                const.append(c - c[0])
                arc0.append(c - c[0] / sinc(a[0]) * sinc(a))
                arc_med.append(c - np.median(c / sinc(a)) * sinc(a))
            mm = [1e3 * np.abs(np.concatenate(x)).mean() for x in (const, arc0, arc_med)]
            print(
                f"{rod} {side} gripper: mean |chord error| constant {mm[0]:.2f} mm, arc (L from frame 0) "
                f"{mm[1]:.2f} mm, arc (median L, oracle) {mm[2]:.2f} mm"
            )


if __name__ == "__main__":
    main()
