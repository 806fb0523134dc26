"""A rope known by its length and mass alone: open-loop accuracy of the generic DER
(``deform.generic_model``) beside the shipped model of the same rod, in the same run.

Paper's metric (500-step open loop from frames 0 and 1, gripped vertices given) on DLO1..DLO3 eval
and the held-out fifth of DLO4/DLO5 train; the generic rod has the rod's length, mass and vertex
count and nothing else (no markers, no identification, no residual network).

    python benchmarks/generic_model.py [--rods DLO1 DLO3]   -> benchmarks/results/generic_model.{json,md}
"""

import argparse
import json
import sys
from pathlib import Path

import torch

if not __package__:  # run as `python benchmarks/generic_model.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from benchmarks.accuracy import test_recordings
from benchmarks.provenance import provenance
from deform import find_data_root, generic_model, load_model
from deform.evaluate import evaluate

OUT = Path(__file__).resolve().parent / "results"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rods", nargs="*", default=["DLO1", "DLO2", "DLO3", "DLO4", "DLO5"])
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    root = find_data_root()
    if root is None:
        raise SystemExit("no dataset: set DEFORM_DATA")
    rows = {}
    for rod in args.rods:
        shipped = load_model(rod)
        cfg = shipped.cfg
        generic = generic_model(cfg.length_m, cfg.mass_kg, cfg.n_vertices)
        recs, split = test_recordings(root, rod, shipped.n)
        g, s = evaluate(generic, recs)["l1_m"], evaluate(shipped, recs)["l1_m"]
        rows[rod] = {
            "split": split,
            "recordings": len(recs),
            "length_m": cfg.length_m,
            "mass_kg": cfg.mass_kg,
            "generic_l1_m": g,
            "shipped_l1_m": s,
            "ratio": g / s,
        }
        print(f"{rod}: generic {g * 100:.2f} cm, shipped {s * 100:.2f} cm ({g / s:.2f}x)", flush=True)
    OUT.mkdir(exist_ok=True)
    (OUT / "generic_model.json").write_text(json.dumps({**provenance(), "rods": rows}, indent=2) + "\n")
    lines = [
        "| rod | recordings | length [m] | mass [g] | generic DER L1 [cm] | shipped model L1 [cm] | ratio |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for rod, r in rows.items():
        lines.append(
            f"| {rod} | {r['recordings']} {r['split'].split(' ')[0]} | {r['length_m']:.3f} | "
            f"{r['mass_kg'] * 1e3:.1f} | {r['generic_l1_m'] * 100:.2f} | {r['shipped_l1_m'] * 100:.2f} | "
            f"{r['ratio']:.2f} |"
        )
    (OUT / "generic_model.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
