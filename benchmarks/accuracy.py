"""Accuracy of the shipped models (issue 2): paper's metric on DLO1..DLO3 eval and on the held-out
fifth of the train recordings of DLO4 and DLO5 (which have no eval split).

`python benchmarks/accuracy.py [--rods DLO1 DLO2] [--model-dir DIR]` -> benchmarks/results/accuracy.{json,md}
"""

import argparse
import json
import sys
from pathlib import Path

import torch

if not __package__:  # run as `python benchmarks/accuracy.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from benchmarks.provenance import provenance
from deform.evaluate import evaluate
from deform.io.recordings import find_data_root, load_recordings
from deform.model import DeformModel, load_model
from deform.train import split_validation

PAPER_DEFORM_CM = {"DLO1": 1.01, "DLO2": 0.97, "DLO3": 0.77, "DLO4": 0.85, "DLO5": 0.99}
PAPER_DER_CM = {"DLO1": 1.96, "DLO2": 1.91, "DLO3": 1.86, "DLO4": 1.50, "DLO5": 1.65}


def test_recordings(root: Path, rod: str, n: int):
    if (root / rod / "eval").is_dir():
        return load_recordings(root / rod / "eval", n), "eval"
    _, held_out = split_validation(load_recordings(root / rod / "train", n))
    return held_out, "train (held-out fifth, never trained on)"


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rods", nargs="*", default=list(PAPER_DEFORM_CM))
    ap.add_argument("--model-dir", help="directory of ROD.pt (default: the shipped models)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    root = find_data_root()
    if root is None:
        raise SystemExit("no dataset: set DEFORM_DATA")
    rows = {}
    for rod in args.rods:
        model = DeformModel.load(Path(args.model_dir) / f"{rod}.pt") if args.model_dir else load_model(rod)
        recs, split = test_recordings(root, rod, model.n)
        res = evaluate(model, recs)
        rows[rod] = {
            "split": split,
            **res,
            "paper_deform_cm": PAPER_DEFORM_CM[rod],
            "paper_der_cm": PAPER_DER_CM[rod],
        }
        print(
            f"{rod}: {res['l1_m'] * 100:.3f} cm (paper DEFORM {PAPER_DEFORM_CM[rod]}) on {len(recs)} {split} recordings",
            flush=True,
        )
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    meta = provenance()
    (out / "accuracy.json").write_text(json.dumps({**meta, **rows}, indent=2))
    lines = [
        "| rod | recordings | L1 [cm] | paper DEFORM [cm] | ratio | interior vertex dist [cm] | L1 at 1/10/100/500 steps [cm] |",
        "|---|---|---:|---:|---:|---:|---|",
    ]
    for rod, r in rows.items():
        h = r["l1_by_horizon_m"]
        lines.append(
            f"| {rod} | {r['recordings']} {r['split'].split(' ')[0]} | {r['l1_m'] * 100:.3f} | {r['paper_deform_cm']:.2f} | "
            f"{r['l1_m'] * 100 / r['paper_deform_cm']:.2f} | {r['mean_vertex_dist_m'] * 100:.3f} | "
            + " / ".join(f"{h[k] * 100:.2f}" for k in ("1", "10", "100", "500"))
            + " |"
        )
    (out / "accuracy.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
