"""Does a float32 rollout keep the accuracy? The paper's metric on the eval recordings, float64 against
float32 in the same run (the same model, the eager step), and how far the two predictions are apart.

    python benchmarks/float32_accuracy.py [--rods DLO1 DLO2 DLO3] [--json benchmarks/results/float32_accuracy.json]

Issue 21's bound: the float32 rollout within 0.1 mm of float64 on the paper's metric.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rods", nargs="*", default=["DLO1", "DLO2", "DLO3"])
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/float32_accuracy.json"))
    args = ap.parse_args()
    from deform import load_model
    from deform.evaluate import metrics, predict_recordings
    from deform.io.recordings import find_data_root, load_recordings

    torch.set_num_threads(1)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    out = {
        "command": "python benchmarks/float32_accuracy.py " + " ".join(sys.argv[1:]),
        "commit": commit.stdout.strip(),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "torch": torch.__version__},
        "rods": {},
    }
    root = find_data_root()
    if root is None:
        raise SystemExit("no DEFORM data: set DEFORM_DATA")
    for rod in args.rods:
        model = load_model(rod)
        recs = load_recordings(root / rod / "eval", model.n)
        row = {"recordings": len(recs)}
        preds = {}
        for name, dtype in (("float64", torch.float64), ("float32", torch.float32)):
            t = time.perf_counter()
            res = predict_recordings(model, recs, args.steps, dtype=dtype)
            row[f"{name}_l1_m"] = metrics(res)["l1_m"]
            row[f"{name}_l1_cm"] = round(100 * row[f"{name}_l1_m"], 4)
            row[f"{name}_seconds"] = round(time.perf_counter() - t, 1)
            preds[name] = res
        diff = [
            np.abs(a.prediction - b.prediction).mean() for a, b in zip(preds["float64"], preds["float32"])
        ]
        row["l1_difference_mm"] = abs(row["float64_l1_m"] - row["float32_l1_m"]) * 1e3
        row["mean_abs_prediction_gap_mm"] = round(1e3 * float(np.mean(diff)), 5)
        row["within_0.1_mm"] = row["l1_difference_mm"] <= 0.1
        print(rod, json.dumps(row), flush=True)
        out["rods"][rod] = row
    Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
