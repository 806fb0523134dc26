"""The loop from `deform diagnose` back into DEFORM, on the real rods (issue 18, part 5).

For every rod, the terms the discrepancy tool named (benchmarks/results/diagnose.real.json, or
--terms ROD=NAME) are trained into DEFORM and compared on the paper's metric:

* ``shipped``: the shipped model (deform/models/ROD.pt);
* ``with``: the shipped model fine-tuned with the term (an added term is attached; a built-in one,
  see deform.terms.BUILT_IN, stays free);
* ``without``: the same fine-tuning without the term (an added term left out; a built-in one removed:
  uniform stiffness, no quadratic drag...). Same budget and seed as ``with``, so the difference is
  the term and not the extra training.

Validation (the held-out fifth of the train recordings: the shipped models chose their best\ncheckpoint on it but never took a gradient from it)
picks among the three; `--install` ships the ``with`` model only when validation picks it. Eval
(DLO1-DLO3) reports the paper's metric over 500 steps, as benchmarks/accuracy.py does.

    python benchmarks/real_terms.py [--rods DLO2 DLO3] [--iterations 120] [--install]
        -> benchmarks/results/real_terms.{json,md}, runs in runs/real_terms/
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

if not __package__:  # run as `python benchmarks/real_terms.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from benchmarks.accuracy import test_recordings
from benchmarks.provenance import machine_text, provenance
from deform.evaluate import evaluate
from deform.io.recordings import find_data_root, load_recordings
from deform.model import MODEL_DIR, DeformModel, load_model
from deform.terms import ADDED, BUILT_IN, attached_names, describe
from deform.train import TrainConfig, split_validation, train, validation_l1

ROOT = Path(__file__).resolve().parents[1]

RESULTS = ROOT / "benchmarks" / "results"


def named_terms(rods: list[str], explicit: list[str]) -> dict[str, list[str]]:
    """ROD -> the terms the stored diagnosis selected (or the ones given as ROD=NAME)."""
    if explicit:
        out = {rod: [] for rod in rods}
        for item in explicit:
            rod, name = item.split("=", 1)
            out.setdefault(rod, []).append(name)
        return out
    stored = json.loads((RESULTS / "diagnose.real.json").read_text())
    by_rod = {row["rod"]: row.get("selected", []) for row in stored["real"]}
    return {rod: list(by_rod.get(rod, [])) for rod in rods}


def scores(model: DeformModel, val_recs, test_recs, val_steps: int) -> dict:
    return {
        "val_l1_m": validation_l1(model, val_recs, val_steps),
        "eval_l1_m": evaluate(model, test_recs)["l1_m"],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rods", nargs="*", default=["DLO1", "DLO2", "DLO3", "DLO4", "DLO5"])
    ap.add_argument("--terms", nargs="*", default=[], help="ROD=NAME instead of the stored diagnosis")
    ap.add_argument("--iterations", type=int, default=120)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--horizon", type=int, default=100)
    ap.add_argument("--lr-scale", type=float, default=0.25, help="of the training learning rates")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--install", action="store_true", help="ship a with-term model validation picks")
    ap.add_argument("--runs", default=str(ROOT / "runs" / "real_terms"))
    ap.add_argument("--stem", default="real_terms", help="result files benchmarks/results/<stem>.{json,md}")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    root = find_data_root()
    if root is None:
        raise SystemExit("no dataset: set DEFORM_DATA")
    named = named_terms(args.rods, args.terms)
    rows = []
    t_all = time.perf_counter()

    def write(complete: bool) -> dict:
        """The rows so far (after every term: an interrupted run keeps what it measured)."""
        result = {
            **provenance(threads=args.threads),
            "threads": args.threads,
            "budget": {
                "iterations": args.iterations,
                "batch": args.batch,
                "horizon": args.horizon,
                "lr_scale": args.lr_scale,
            },
            "seconds_total": time.perf_counter() - t_all,
            "complete": complete,
            "rows": rows,
        }
        RESULTS.mkdir(exist_ok=True)
        (RESULTS / f"{args.stem}.json").write_text(json.dumps(result, indent=2))
        (RESULTS / f"{args.stem}.md").write_text(markdown(result))
        return result

    for rod in args.rods:
        shipped = load_model(rod)
        train_recs, val_recs = split_validation(load_recordings(root / rod / "train", shipped.n))
        test_recs, split = test_recordings(root, rod, shipped.n)
        val_steps = min(args.horizon * 5, min(r.n_frames for r in val_recs) - 2)
        base = scores(shipped, val_recs, test_recs, val_steps)
        print(f"{rod} shipped: val {base['val_l1_m'] * 100:.3f} cm, {split} {base['eval_l1_m'] * 100:.3f} cm")
        if not named[rod]:
            rows.append({"rod": rod, "term": None, "split": split, "shipped": base})
            continue
        for name in named[rod]:
            arms = {}
            for arm in ("with", "without"):
                model = load_model(rod)
                terms = (name,) if (arm == "with" and name in ADDED) else ()
                # a built-in term, or an added one the shipped model already carries (trained with it)
                removable = name in BUILT_IN or name in attached_names(model)
                removed = (name,) if (arm == "without" and removable) else ()
                cfg = TrainConfig(
                    iterations=args.iterations,
                    batch=args.batch,
                    horizon=args.horizon,
                    curriculum=(),
                    lr_physics=2e-2 * args.lr_scale,
                    lr_network=1e-3 * args.lr_scale,
                    coarse_sysid=False,  # fine-tuning an identified model
                    terms=terms,
                    without=removed,
                )
                out = Path(args.runs) / rod / f"{name}.{arm}"
                t0 = time.perf_counter()
                result = train(model, train_recs, val_recs, cfg, out, resume=False)
                best = DeformModel.load(out / "best.pt")
                arms[arm] = {
                    **scores(best, val_recs, test_recs, val_steps),
                    "seconds": time.perf_counter() - t0,
                    "terms": list(terms),
                    "without": list(removed),
                    "term_starts": result.get("term_starts"),
                    "path": str(out / "best.pt"),
                }
                print(
                    f"{rod} {name} {arm}: val {arms[arm]['val_l1_m'] * 100:.3f} cm, "
                    f"{split} {arms[arm]['eval_l1_m'] * 100:.3f} cm ({arms[arm]['seconds']:.0f} s)",
                    flush=True,
                )
            picked = min([("shipped", base), *arms.items()], key=lambda kv: kv[1]["val_l1_m"])[0]
            installed = False
            if args.install and picked == "with":
                DeformModel.load(arms["with"]["path"]).save(MODEL_DIR / f"{rod}.pt")
                installed = True
            rows.append(
                {
                    "rod": rod,
                    "term": name,
                    "kind": "built in" if name in BUILT_IN else "added",
                    "meaning": describe(name),
                    "split": split,
                    "shipped": base,
                    **arms,
                    "validation_picks": picked,
                    "installed": installed,
                }
            )
            write(complete=False)
    print(markdown(write(complete=True)))
    return 0


def markdown(result: dict) -> str:
    def cm(row, arm, key):
        return f"{row[arm][key] * 100:.3f}" if arm in row else "-"

    b = result["budget"]
    machine = machine_text(result["machine"])
    lines = [
        "# Named physics trained into DEFORM, real rods",
        "",
        f"Run: `{result['command']}` at commit {result['commit']} on "
        f"{machine}; "
        f"{result['seconds_total']:.0f} s. Fine-tuning from the shipped model: {b['iterations']} "
        f"iterations of {b['batch']} windows x {b['horizon']} steps, learning rates x {b['lr_scale']}, "
        "the same seed for both arms.",
        "",
        "| rod | term named | in DEFORM | val shipped [cm] | val with [cm] | val without [cm] "
        "| test shipped [cm] | test with [cm] | test without [cm] | test split | validation picks |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['rod']} | {r['term'] or 'none'} | {r.get('kind', '-')} | {cm(r, 'shipped', 'val_l1_m')} "
            f"| {cm(r, 'with', 'val_l1_m')} | {cm(r, 'without', 'val_l1_m')} "
            f"| {cm(r, 'shipped', 'eval_l1_m')} | {cm(r, 'with', 'eval_l1_m')} | {cm(r, 'without', 'eval_l1_m')} "
            f"| {r['split'].split(' ')[0]} | {r.get('validation_picks', 'shipped')}"
            f"{' (installed)' if r.get('installed') else ''} |"
        )
    lines += [
        "",
        "Test: the paper's metric (500-step open-loop L1, gripped vertices given) on eval (DLO1-DLO3) "
        "or on the held-out fifth of train (DLO4, DLO5, which is then also the validation set).",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
