"""Model-only demo: predict a recording open-loop and print the error (used when the service is absent)."""

from __future__ import annotations

import time

import numpy as np
import torch

from deform.evaluate import metrics, predict_recordings
from deform.io.recordings import find_data_root, load_recordings
from deform.model import load_model
from deform.synthetic import generate_recording


def main(rod: str = "DLO1") -> int:
    """The model alone: open-loop prediction of three recordings (eval, or simulated without the
    dataset), accuracy and step time printed.

    Args:
        rod: a shipped rod.

    Returns:
        The exit code (0).
    """
    torch.set_num_threads(1)
    model = load_model(rod)
    root = find_data_root()
    if root is not None and (root / rod / "eval").is_dir():
        recs = load_recordings(root / rod / "eval", model.n)[:3]
        source = f"{root / rod / 'eval'} (first 3 recordings)"
    else:
        recs = [generate_recording(model, n_frames=500, seed=s) for s in range(3)]
        source = "synthetic recordings from the model itself"
    t0 = time.perf_counter()
    res = predict_recordings(model, recs, batched=False)
    m = metrics(res)
    step = np.concatenate([r.step_seconds for r in res])
    print(f"{rod}: open-loop prediction of {source}")
    print(
        f"  L1 (paper's metric) {m['l1_m'] * 100:.3f} cm, mean interior vertex distance {m['mean_vertex_dist_m'] * 100:.3f} cm"
    )
    print(
        f"  step p50 {np.median(step) * 1e3:.3f} ms, p99 {np.percentile(step, 99) * 1e3:.3f} ms, "
        f"total {time.perf_counter() - t0:.1f} s"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
