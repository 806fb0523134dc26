"""Where calibration's training loss puts the damping, scored three ways on the same windows.

    python benchmarks/calibration_loss_bias.py [--rod DLO2] [--setups session other_lab]

A camera track is the tracking model's prediction between clouds and the camera's correction at
them. `deform calibrate` used to score its training windows against the track smoothed in time;
it now scores them only at the clouds, against the track as corrected (calibrate/tracks.py). This
study shows why: the rod's training motions are filmed as a lab films them
(benchmarks/calibration/setups.py), written as bags, read and tracked as `deform calibrate` tracks
them, with the shipped model standing in for a calibrated one. Then the shipped model's damping is
scaled by 2^k and its 1 s open-loop L1 scored on one fixed set of windows (the same starts, from the
smoothed track) against

* the motion-capture truth (where the damping should be),
* the smoothed track (the loss before),
* the track at the clouds, as corrected, weighted by what each cloud showed (the loss now).

Each loss's optimum (a parabola through the best scale and its neighbours) is reported as a
factor of the truth's: 1 is unbiased. Results: ``benchmarks/results/calibration_loss_bias.{json,md}``.
"""

from __future__ import annotations

import argparse
import random
import sys
import tempfile
from pathlib import Path

if not __package__:  # run as `python benchmarks/calibration_loss_bias.py`
    sys.path[0] = str(Path(__file__).resolve().parents[1])

import numpy as np

from benchmarks.provenance import provenance
from benchmarks.store import write_result

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SCALES = np.arange(-1.0, 1.25, 0.125)  # log2 of the damping's factor
WINDOWS, HORIZON = 48, 100


def tracked(rod: str, setup: str, model) -> list:
    """The rod's 50 s of training clips filmed by ``setup``, tracked as `deform calibrate` tracks."""
    from benchmarks.calibrate_rods import _session
    from benchmarks.calibration.clips import write_session
    from calibrate.bags import read_clip
    from calibrate.tracks import track_clip
    from deform.evaluate import as_model_vertices
    from service.config import load_config

    clips, _, lab, camera = _session(rod, 50.0, quick=False, setup=setup)
    with tempfile.TemporaryDirectory(prefix="loss-bias-") as tmp:
        session = write_session(rod, clips, Path(tmp), lab, camera)
        cfg = load_config(session.config)
        tracks = [track_clip(read_clip(b, cfg), model, cfg.grippers, lab.perception()) for b in session.bags]
    truths = [as_model_vertices(c, model).positions for c in clips]
    return list(zip(tracks, truths))


def optimum(scales: np.ndarray, losses: np.ndarray) -> float:
    """log2 of the best factor: the vertex of a parabola through the grid's best point and two on
    each side; the grid's best when it lies on the grid's edge (no minimum inside)."""
    j = int(np.argmin(losses))
    if j in (0, len(scales) - 1):
        return float(scales[j])
    lo, hi = max(j - 2, 0), min(j + 3, len(scales))
    a, b, _ = np.polyfit(scales[lo:hi], losses[lo:hi], 2)
    return float(np.clip(-b / (2 * a), scales[j - 1], scales[j + 1])) if a > 0 else float(scales[j])


def scan(model, pairs: list, seed: int = 0) -> dict:
    """The three losses at every damping factor on one set of windows: ``{loss: [L1 m per scale]}``."""
    import copy

    import torch

    from deform import gripped_indices

    gi = np.asarray(gripped_indices(model.n))
    clips = []
    for track, true in pairs:
        # the track starts at the first cloud, the truth at the clip's first pose: aligned by the grips
        offsets = range(max(len(true) - track.n_frames, 0) + 1)
        offset = min(offsets, key=lambda k: float(np.abs(true[k, gi] - track.grips[0]).sum()))
        clips.append((track.recording(), true, offset, min(track.n_frames, len(true) - offset)))
    rng = random.Random(seed)
    start, smooth, truth, corrected, weight = [], [], [], [], []
    for _ in range(WINDOWS):
        rec, true, offset, n = clips[rng.randrange(len(clips))]
        s = rng.randrange(0, n - HORIZON - 2)
        cut = slice(s + 2, s + 2 + HORIZON)
        start.append(rec.positions[s : s + 2])
        smooth.append(rec.positions[cut])
        truth.append(true[offset + s + 2 : offset + s + 2 + HORIZON])
        corrected.append(rec.targets[cut])
        weight.append(rec.weights[cut])
    S, X, Y = (torch.tensor(np.stack(a)) for a in (start, smooth, truth))
    C, W = torch.tensor(np.stack(corrected)), torch.tensor(np.stack(weight)).unsqueeze(-1)
    grips = X[:, :, gi]
    out = {"truth": [], "smoothed track": [], "at the clouds": []}
    for k in SCALES:
        m = copy.deepcopy(model)
        with torch.no_grad():
            m.log_damping += float(k * np.log(2))
            pred, _ = m.rollout(m.initial_state(S[:, 0], S[:, 1]), grips, create_graph=False)
        out["truth"].append(float((pred - Y).abs().mean()))
        out["smoothed track"].append(float((pred - X).abs().mean()))
        out["at the clouds"].append(float((W * (pred - C).abs()).sum() / (3 * W.sum())))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rod", default="DLO2")
    ap.add_argument("--setups", nargs="*", default=["session", "other_lab"])
    ap.add_argument("--stem", default="calibration_loss_bias")
    args = ap.parse_args(argv)

    import torch

    from deform import load_model

    torch.set_num_threads(1)
    model = load_model(args.rod).eval()
    result = {
        **provenance(),
        "rod": args.rod,
        "damping_per_s": float(model.log_damping.detach().exp()),
        "setups": {},
    }
    lines = [
        f"# Calibration's training loss: the damping it prefers ({args.rod}, shipped model)",
        "",
        "Optimum of each loss as a factor of the motion-capture truth's (1: unbiased).",
        "",
        "| lab | smoothed track (before) | at the clouds (now) |",
        "|---|---:|---:|",
    ]
    for setup in args.setups:
        losses = scan(model, tracked(args.rod, setup, model))
        best = {name: optimum(SCALES, np.array(v)) for name, v in losses.items()}
        factor = {name: round(2 ** (b - best["truth"]), 3) for name, b in best.items() if name != "truth"}
        result["setups"][setup] = {"losses_m": losses, "log2_scales": SCALES.tolist(), "optimum_log2": best}
        for name, f in factor.items():
            result[f"{setup}: {name}, damping optimum x truth's"] = f
        lines.append(f"| {setup} | {factor['smoothed track']:.2f}x | {factor['at the clouds']:.2f}x |")
        print(setup, factor, flush=True)
    return write_result(RESULTS / args.stem, result, [], "setups", "\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
