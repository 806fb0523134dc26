"""Ablations (paper's Tables 2 and 6) on DLO1..DLO3 eval, every variant with the same training budget.

Variants: DER with the initial parameters (no training); no residual learning (system
identification only); no system identification (residual network only, initial physics);
original (unweighted) inextensibility; single-step training (horizon 1); the full model.

`python benchmarks/ablations.py [--rods DLO1 DLO2 DLO3] [--iterations 150] [--variants ...]`
-> runs/ablations/<variant>/<rod>/ and benchmarks/results/ablations.{json,md}. Resumable: a
finished variant is not trained again.
"""

import argparse
import json
import sys
from pathlib import Path

import torch

if not __package__:  # run as `python benchmarks/ablations.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from deform.config import load_rod_config
from deform.evaluate import evaluate
from deform.io.recordings import find_data_root, load_recordings
from deform.model import DeformModel, ModelOptions
from deform.train import TrainConfig, split_validation, train

VARIANTS = {
    "der_initial": None,
    "no_residual": dict(options=dict(residual=False), train=dict(residual=False)),
    "no_sysid": dict(options=dict(), train=dict(sysid=False)),
    "original_inextensibility": dict(options=dict(weighted_pbd=False), train=dict()),
    "single_step": dict(options=dict(), train=dict(horizon=1, curriculum=())),
    "full": dict(options=dict(), train=dict()),
}
PAPER = {  # paper's Table 1 (DEFORM, DER) in cm; ablation rows are compared against these two
    "DLO1": {"deform": 1.01, "der": 1.96},
    "DLO2": {"deform": 0.97, "der": 1.91},
    "DLO3": {"deform": 0.77, "der": 1.86},
}


def run_variant(name: str, rod: str, root: Path, iterations: int, out_root: Path, batch: int = 32) -> dict:
    cfg = load_rod_config(rod)
    spec = VARIANTS[name]
    out = out_root / name / rod
    result_file = out / "result.json"
    if result_file.is_file():
        return json.loads(result_file.read_text())
    if spec is None:
        model = DeformModel(cfg, ModelOptions(residual=False))
    else:
        model = DeformModel(cfg, ModelOptions(**spec["options"]))
        recs = load_recordings(root / rod / "train", cfg.n_vertices)
        tr, val = split_validation(recs)
        tcfg = TrainConfig(iterations=iterations, batch=batch, **spec["train"])
        train(model, tr, val, tcfg, out)
        model = DeformModel.load(out / "best.pt")
        model.options = ModelOptions(**spec["options"])
    res = evaluate(model, load_recordings(root / rod / "eval", cfg.n_vertices))
    out.mkdir(parents=True, exist_ok=True)
    row = {
        "variant": name,
        "rod": rod,
        "iterations": 0 if spec is None else iterations,
        "batch": batch,
        "l1_m": res["l1_m"],
        "step_ms_p50": res["step_ms_p50"],
    }
    result_file.write_text(json.dumps(row))
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rods", nargs="*", default=["DLO1", "DLO2", "DLO3"])
    ap.add_argument("--variants", nargs="*", default=list(VARIANTS))
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--out", default="runs/ablations")
    args = ap.parse_args()
    torch.set_num_threads(1)
    root = find_data_root()
    if root is None:
        raise SystemExit("no dataset: set DEFORM_DATA")
    rows = []
    for name in args.variants:
        for rod in args.rods:
            row = run_variant(name, rod, root, args.iterations, Path(args.out), args.batch)
            print(f"{name:26s} {rod}: {row['l1_m'] * 100:.3f} cm", flush=True)
            rows.append(row)
    results = Path(__file__).parent / "results"
    results.mkdir(exist_ok=True)
    from benchmarks.provenance import provenance

    payload = {**provenance(threads=1), "rows": rows}
    (results / "ablations.json").write_text(json.dumps(payload, indent=2) + "\n")
    table = {}
    for r in rows:
        table.setdefault(r["variant"], {})[r["rod"]] = r["l1_m"] * 100
    lines = [
        f"Each trained variant: {args.iterations} iterations, batch {args.batch}, seed 0, same curriculum.",
        "",
        "| variant | " + " | ".join(args.rods) + " |",
        "|---|" + "---:|" * len(args.rods),
    ]
    for name, vals in table.items():
        lines.append(
            f"| {name} | " + " | ".join(f"{vals.get(rod, float('nan')):.3f}" for rod in args.rods) + " |"
        )
    lines.append("| paper DER | " + " | ".join(f"{PAPER[r]['der']:.2f}" for r in args.rods) + " |")
    lines.append("| paper DEFORM | " + " | ".join(f"{PAPER[r]['deform']:.2f}" for r in args.rods) + " |")
    (results / "ablations.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
