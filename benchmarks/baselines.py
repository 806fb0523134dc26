"""Baselines beside DEFORM on the real recordings (issue 6), all in one run.

Trains what is missing in ``deform/baselines/weights/`` (plain-DER identification, XPBD tuning,
Bi-LSTM training, each on the rod's train recordings minus the held-out fifth, which selects the
best checkpoint exactly as ``deform train`` does), then evaluates every method and DEFORM
(``load_model(rod)``) with ``deform.evaluate.evaluate``: paper's metric (``l1_m``, 500-step open
loop from frames 0 and 1) on DLO1..DLO3 eval and on the held-out fifth of DLO4/DLO5 train, and
time per step (median over ``--timing-runs`` runs of the per-step p50, batch of one, one thread).

    .venv/bin/python benchmarks/baselines.py                 # train missing + evaluate all
    .venv/bin/python benchmarks/baselines.py --retrain bilstm --rods DLO1
    .venv/bin/python benchmarks/baselines.py --no-train      # evaluate the shipped weights only

-> benchmarks/results/baselines.{json,md} and docs/baselines.md
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from deform.baselines import BASELINES, load_baseline  # noqa: E402
from deform.baselines import bilstm as B  # noqa: E402
from deform.baselines import der as D  # noqa: E402
from deform.baselines import xpbd as X  # noqa: E402
from deform.config import load_rod_config  # noqa: E402
from deform.evaluate import evaluate, predict_recordings  # noqa: E402
from deform.io.recordings import find_data_root, load_recordings  # noqa: E402
from deform.model import MODEL_DIR, load_model  # noqa: E402
from deform.train import split_validation  # noqa: E402

RODS = ("DLO1", "DLO2", "DLO3", "DLO4", "DLO5")
PAPER_CM = {
    "deform": {"DLO1": 1.01, "DLO2": 0.97, "DLO3": 0.77, "DLO4": 0.85, "DLO5": 0.99},
    "der": {"DLO1": 1.96, "DLO2": 1.91, "DLO3": 1.86, "DLO4": 1.50, "DLO5": 1.65},
    "bilstm": {"DLO1": 1.98, "DLO2": 1.75, "DLO3": 1.10, "DLO4": 1.75, "DLO5": 1.88},
}
PAPER_STEP_MS = {"deform": 9.5, "bilstm": 0.3}
PAPER_KEY = {"deform": "deform", "der_initial": "der", "der_identified": "der", "bilstm": "bilstm"}
METHODS = ("deform",) + BASELINES
TRAINABLE = ("der_identified", "xpbd", "bilstm")


def splits(root: Path, rod: str, n: int):
    train_all = load_recordings(root / rod / "train", n)
    train, held_out = split_validation(train_all)
    if (root / rod / "eval").is_dir():
        return train, held_out, load_recordings(root / rod / "eval", n), "eval"
    return train, held_out, held_out, "held-out fifth of train"


def weight_file(method: str, rod: str) -> Path:
    return {"der_identified": D.weight_path, "xpbd": X.weight_path, "bilstm": B.weight_path}[method](rod)


def train_missing(rod: str, train, val, retrain: set[str], args) -> dict:
    info = {}
    n = load_rod_config(rod).n_vertices
    for method in TRAINABLE:
        if weight_file(method, rod).is_file() and method not in retrain:
            continue
        t0 = time.perf_counter()
        print(f"{rod}: training {method}", flush=True)
        if method == "der_identified":
            r = D.identify(
                rod,
                train,
                val,
                ROOT / "runs" / "baselines" / f"der_{rod}",
                iterations=args.der_iterations,
                progress=False,
            )
            info[method] = {"best_val_l1_m": r["best_val_l1_m"], "coarse": r["coarse_identification"]}
        elif method == "xpbd":
            r = X.tune(rod, train)
            info[method] = {
                "train_l1_m": r["train_l1_m"],
                "params": r["params"],
                "configs_tried": r["configs_tried"],
            }
        else:
            _, r = B.train_bilstm(
                train,
                val,
                n,
                iterations=args.bilstm_iterations,
                time_limit_s=args.bilstm_seconds,
                out=B.weight_path(rod),
                progress=True,
            )
            info[method] = {k: v for k, v in r.items() if k != "log"}
        info[method]["seconds"] = time.perf_counter() - t0
        print(f"{rod}: {method} trained in {info[method]['seconds']:.0f} s", flush=True)
    return info


def weights_info(method: str, rod: str) -> dict | None:
    """What the shipped weight file says of its training (held-out L1, iterations, parameters)."""
    if method not in TRAINABLE or not weight_file(method, rod).is_file():
        return None
    path = weight_file(method, rod)
    if method == "xpbd":
        data = json.loads(path.read_text())
        return {
            "file": str(path.relative_to(ROOT)),
            "params": data["params"],
            "train_l1_m": data["train_l1_m"],
        }
    payload = torch.load(path, map_location="cpu", weights_only=True)
    keys = ("val_l1_m", "best_val_l1_m", "iterations")
    return {"file": str(path.relative_to(ROOT)), **{k: payload[k] for k in keys if k in payload}}


def timing_ms(model, recs, runs: int, first_p50: float) -> list[float]:
    out = [first_p50]
    with torch.no_grad():
        for _ in range(runs - 1):
            t = predict_recordings(model, recs[:1], 200, batched=False)[0].step_seconds
            out.append(float(np.median(t) * 1e3))
    return out


def load_method(method: str, rod: str):
    if method == "deform":
        return load_model(rod)
    return load_baseline(method, rod)


def table(results: dict, rods) -> list[str]:
    head = "| method | " + " | ".join(f"{r} L1 [cm] (paper)" for r in rods) + " | step p50 [ms] (paper) |"
    lines = [head, "|---|" + "---:|" * (len(rods) + 1)]
    for m in METHODS:
        cells = []
        steps = []
        for rod in rods:
            r = results.get(rod, {}).get(m)
            if r is None:
                cells.append("–")
                continue
            paper = PAPER_CM.get(PAPER_KEY.get(m, ""), {}).get(rod)
            star = "*" if m == "deform" and "no shipped model" in str(r.get("model_file")) else ""
            cells.append(f"{r['l1_m'] * 100:.2f}{star}" + (f" ({paper:.2f})" if paper else ""))
            steps.append(r["step_ms"])
        p = PAPER_STEP_MS.get(m)
        step = f"{np.median(steps):.2f}" if steps else "–"
        lines.append(f"| {m} | " + " | ".join(cells) + f" | {step}" + (f" ({p})" if p else "") + " |")
    return lines


def step_table(results: dict, rods) -> list[str]:
    lines = [
        "| method | " + " | ".join(f"{r} step p50 [ms]" for r in rods) + " |",
        "|---|" + "---:|" * len(rods),
    ]
    for m in METHODS:
        cells = [f"{results[r][m]['step_ms']:.3f}" if m in results.get(r, {}) else "–" for r in rods]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rods", nargs="*", default=list(RODS))
    ap.add_argument("--methods", nargs="*", default=list(METHODS), choices=METHODS)
    ap.add_argument("--retrain", nargs="*", default=[], choices=TRAINABLE)
    ap.add_argument(
        "--no-train", action="store_true", help="only evaluate; methods without weights are skipped"
    )
    ap.add_argument("--bilstm-iterations", type=int, default=1500)
    ap.add_argument("--bilstm-seconds", type=float, default=240.0, help="time limit per rod")
    ap.add_argument("--der-iterations", type=int, default=100)
    ap.add_argument("--timing-runs", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    ap.add_argument("--docs", default=str(ROOT / "docs" / "baselines.md"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    root = find_data_root()
    if root is None:
        raise SystemExit("no dataset: set DEFORM_DATA")
    t_start = time.perf_counter()
    results, training = {}, {}
    for rod in args.rods:
        n = load_rod_config(rod).n_vertices
        train, val, test, split = splits(root, rod, n)
        if not args.no_train:
            training[rod] = train_missing(rod, train, val, set(args.retrain), args)
        results[rod] = {}
        for m in args.methods:
            if m == "deform":
                continue  # after every baseline (the shipped models may be replaced meanwhile)
            try:
                model = load_method(m, rod)
            except FileNotFoundError as exc:
                print(f"{rod}: {m} skipped ({exc})", flush=True)
                continue
            results[rod][m] = run_one(model, m, rod, test, split, args.timing_runs)
            results[rod][m]["weights"] = weights_info(m, rod)
    if "deform" in args.methods:
        for rod in args.rods:
            n = load_rod_config(rod).n_vertices
            _, _, test, split = splits(root, rod, n)
            results[rod]["deform"] = run_one(load_model(rod), "deform", rod, test, split, args.timing_runs)
            results[rod]["deform"]["model_file"] = (
                str(MODEL_DIR / f"{rod}.pt")
                if (MODEL_DIR / f"{rod}.pt").is_file()
                else "config initial parameters (no shipped model)"
            )
    for rod in args.rods:
        r = results[rod]
        if "deform" in r and "bilstm" in r:
            r["deform"]["step_ratio_to_bilstm"] = r["deform"]["step_ms"] / r["bilstm"]["step_ms"]
            # interleaved runs, so that both see the same load of the shared machine
            _, _, test, _ = splits(root, rod, load_rod_config(rod).n_vertices)
            pair = {"deform": load_model(rod), "bilstm": load_baseline("bilstm", rod)}
            runs = {k: [] for k in pair}
            for _ in range(args.timing_runs):
                for k, model in pair.items():
                    runs[k] += timing_ms(model, test, 2, 0.0)[1:]
            r["deform"]["paired_timing_ms"] = {k: float(np.median(v)) for k, v in runs.items()}
            r["deform"]["paired_step_ratio_to_bilstm"] = float(
                np.median(runs["deform"]) / np.median(runs["bilstm"])
            )
    from benchmarks.provenance import provenance

    payload = {
        **provenance(
            argv,
            script="benchmarks/baselines.py",
            threads=1,
            cpu_count=os.cpu_count(),
            load_average_1_min_at_end=round(os.getloadavg()[0], 2),  # what else ran beside the timing
            timing_runs=args.timing_runs,
            batch=1,
        ),
        "seconds": time.perf_counter() - t_start,
        "training": training,
        "results": results,
        "paper_cm": PAPER_CM,
        "paper_step_ms": PAPER_STEP_MS,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "baselines.json").write_text(json.dumps(payload, indent=2) + "\n")
    lines = (
        table(results, args.rods)
        + ["", "Time per step by rod (batch of one, one thread):", ""]
        + step_table(results, args.rods)
    )
    ratio = [
        f"{rod} {d['step_ratio_to_bilstm']:.1f}x ({d['paired_timing_ms']['deform']:.2f} / "
        f"{d['paired_timing_ms']['bilstm']:.2f} ms interleaved: {d['paired_step_ratio_to_bilstm']:.1f}x)"
        for rod in args.rods
        if "step_ratio_to_bilstm" in (d := results[rod].get("deform", {}))
    ]
    extra = []
    if any("no shipped model" in str(results[r].get("deform", {}).get("model_file")) for r in args.rods):
        extra.append(
            "\\* no trained model shipped for this rod at the time of the run: the untrained model "
            "(config's initial parameters, untrained residual network)."
        )
    if ratio:
        extra.append(
            f"DEFORM step time / Bi-LSTM step time, same run: {', '.join(ratio)}; paper: about 9.5 / 0.3 ms "
            "= 32x."
        )
    (out / "baselines.md").write_text("\n".join(lines + [""] + extra) + "\n")
    print("\n".join(lines + [""] + extra))
    write_docs(Path(args.docs), lines, extra, payload, args)


def run_one(model, method: str, rod: str, test, split: str, timing_runs: int) -> dict:
    torch.set_num_threads(1)
    res = evaluate(model, test)
    runs = timing_ms(model, test, timing_runs, res["step_ms_p50"])
    res.pop("per_recording_l1_m", None)
    res.update(
        {
            "split": split,
            "step_ms": float(np.median(runs)),
            "step_ms_runs": runs,
            "source": getattr(model, "baseline_source", None),
        }
    )
    print(
        f"{rod}: {method:15s} L1 {res['l1_m'] * 100:.3f} cm on {res['recordings']} {split} recordings; "
        f"step p50 {res['step_ms']:.3f} ms",
        flush=True,
    )
    return res


def write_docs(path: Path, lines, extra, payload, args) -> None:
    m = payload["machine"]
    der_src = {
        rod: str(payload["results"][rod].get("der_identified", {}).get("source")).replace(str(ROOT) + "/", "")
        for rod in payload["results"]
    }
    text = f"""# Baselines beside DEFORM

Accuracy on the paper's metric (mean absolute coordinate error over 500 open-loop steps from frames
0 and 1, all vertices, in cm; the paper's Table 1 in brackets) and time per step (median over
{m["timing_runs"]} runs of the per-step p50 of a 200-step rollout, batch of one, one thread; the
median over rods is shown). Test data: DLO1..DLO3 eval recordings; DLO4 and DLO5 have no eval
split, so the held-out fifth of their train recordings (`deform.train.split_validation`), which
the baselines (like `deform train`) also use to pick their best checkpoint.

{chr(10).join(lines)}

{chr(10).join(extra)}

Methods (`deform eval --rod ROD --method NAME`, code in `deform/baselines/`):

- `deform`: the shipped model `deform/models/ROD.pt` (`load_model(rod)`), evaluated last in the run.
- `der_initial`: DEFORM's rod without the residual network, config's initial parameters.
- `der_identified`: the same with physical parameters identified on the train recordings
  (`deform.train.train`, `residual=False`, {args.der_iterations} iterations after the coarse grid),
  from `deform/baselines/weights/der_ROD.pt`.
- `xpbd`: XPBD rope (distance + bending constraints, gravity, damping, 10 substeps), compliances
  and damping tuned by a coarse-to-fine grid on train recordings (`weights/xpbd_ROD.json`).
- `bilstm`: bidirectional LSTM over the vertices (Yan et al. 2020 style), trained with open-loop
  rollouts (horizon 5 -> 50) for at most {args.bilstm_seconds:.0f} s / {args.bilstm_iterations}
  iterations per rod on one core (`weights/bilstm_ROD.pt`).
- `hold_shape`: frame 1's interior held still, gripped vertices following the inputs.

Command: `.venv/bin/python {payload["command"].split(" ", 1)[1]}` (total {payload["seconds"] / 60:.1f} min,
training included only for weights that were missing). Machine: {m["cpu_count"]} CPU cores ({m["processor"]}),
shared with other jobs (model training running), torch {m["torch"]}, one thread, one run for
accuracy (deterministic), {m["timing_runs"]} timing runs. Raw numbers:
`benchmarks/results/baselines.json`. DER-identified parameter source per rod: {json.dumps(der_src)}.
"""
    # hand-written notes below the marker survive a re-run
    marker = "<!-- notes: kept when benchmarks/baselines.py rewrites this file -->"
    old = path.read_text() if path.is_file() else ""
    notes = old[old.index(marker) :] if marker in old else marker + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text + "\n" + notes)


if __name__ == "__main__":
    main()
