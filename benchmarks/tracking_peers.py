"""Tracking side by side with the published trackers (issue 50): our tracker (the DEFORM model predicting
every 10 ms step, each cloud correcting it) against the peers of :mod:`perception.baselines` (CPD,
CDCPD, TrackDLO, UPETrack, one update per cloud), on the same rendered clouds of the DEFORM recordings,
started from the same true nodes; TrackDLO's metric (mean two-way distance to the true rope).

Scenarios (``--scenarios``): ``occlusion`` (0, 25, 50 %), ``blackout`` (the whole rope hidden 1 s, and
the recovery after it), ``fastest`` (the recordings with the fastest grippers), ``fps10`` (clouds at
10 Hz), ``sensor`` (a camera whose colour is 2 px off its depth, mixed edge pixels; reference: the
clean clouds), ``far_camera`` (another lab's camera: 1.6 m away, 35 degrees off square, noisier, at 15 Hz;
reference: the clean clouds), ``contact`` (a table or a post the model does not know; reference: the same motion without),
``wrong_model`` (DLO3 tracked with DLO1's model; reference: DLO3's). See :mod:`benchmarks.tracking`.

    python benchmarks/tracking_peers.py                 # 2 recordings per rod, DLO1..DLO5
    python benchmarks/tracking_peers.py --quick         # smoke run: DLO1 and DLO3, 1 each, a subset
    python benchmarks/tracking_peers.py --per-rod 1 --methods ours trackdlo --scenarios occlusion blackout

Each recording's results are stored as they finish (``benchmarks/results/tracking_peers.runs/``): a
stopped run resumes. Writes ``tracking_peers.json``, ``tracking_peers.md`` and ``tracking_peers.png``
in ``benchmarks/results/``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core, as the latency budget says
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import sys
import time
from pathlib import Path

if not __package__:  # run as `python benchmarks/tracking_peers.py`: import the repository's packages
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OUT = Path(__file__).resolve().parent / "results"
STEM = "tracking_peers"


def parse(argv=None):
    from benchmarks.tracking.scenarios import RODS, SCENARIOS

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--quick", action="store_true", help="DLO1 and DLO3, one recording each, a subset of variants"
    )
    ap.add_argument("--per-rod", type=int, default=2, help="recordings per rod (0 = all held-out ones)")
    ap.add_argument("--rods", nargs="+", default=None, help=f"default {' '.join(RODS)}")
    ap.add_argument("--methods", nargs="+", default=None, help="ours and peer names (default: all)")
    ap.add_argument("--scenarios", nargs="+", default=None, choices=SCENARIOS)
    ap.add_argument(
        "--perception",
        type=Path,
        default=None,
        help="our tracker's settings (YAML; default: the shipped ones)",
    )
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--stem", default=STEM)
    return ap.parse_args(argv)


def main(argv=None) -> dict:
    import torch
    from tqdm import tqdm

    from benchmarks.provenance import provenance
    from benchmarks.store import RunStore, source_digest, write_atomic
    from benchmarks.tracking import report
    from benchmarks.tracking.runner import OURS, available_peers, run_unit
    from benchmarks.tracking.scenarios import (
        BLACKOUT_S,
        BLACKOUT_START_S,
        QUICK_RODS,
        QUICK_VARIANTS,
        RODS,
        SCENARIOS,
        VARIANTS,
        select_units,
    )

    args = parse(argv)
    torch.set_num_threads(1)
    per_rod = 1 if args.quick else args.per_rod
    rods = args.rods or list(QUICK_RODS if args.quick else RODS)
    scenarios = args.scenarios or list(SCENARIOS)
    variants = [v for s in scenarios for v in VARIANTS[s]]
    if args.quick:
        variants = [v for v in variants if v in QUICK_VARIANTS]
    peers = available_peers()
    methods = args.methods or [OURS, *peers]
    unknown = [m for m in methods if m != OURS and m not in peers]
    if unknown:
        raise SystemExit(f"unknown methods {unknown}; have {[OURS, *peers]}")
    t_start = time.time()
    units, ranking = select_units(rods, per_rod, variants)
    store = RunStore(args.out / f"{args.stem}.runs")
    code = source_digest("deform", "perception", "benchmarks/tracking")  # older code's rows: not reused
    config = dict(per_rod=per_rod, quick=args.quick, variants=variants, methods=methods, code=code)
    if args.perception is not None:  # results of other settings are stored apart
        config["perception"] = str(args.perception)
    done = store.load(config)
    rows = [done[u.key] for u in units if u.key in done]
    todo = [u for u in units if u.key not in done]
    if rows:
        print(f"resuming: {len(rows)} recordings stored in {store.where(config)}, {len(todo)} to run")
    models: dict = {}
    with tqdm(todo, desc="recordings", unit="rec") as bar:
        for unit in bar:
            row = run_unit(
                unit,
                methods,
                peers,
                config=args.perception,
                models=models,
                progress=lambda s: bar.set_postfix_str(s[-60:]),
            )
            row.update(config=config, seconds=round(time.time() - t_start, 1))
            store.save(row)
            rows.append(row)
    rows.sort(key=lambda r: (r["rod"], r["recording"]))
    result = dict(
        **provenance(argv, script="benchmarks/tracking_peers.py"),
        args=dict(
            per_rod=per_rod,
            quick=args.quick,
            rods=rods,
            scenarios=scenarios,
            variants=variants,
            perception=None if args.perception is None else str(args.perception),
        ),
        methods=methods,
        labels=report.LABEL,
        wall_s=round(time.time() - t_start, 1),
        blackout=dict(start_s=BLACKOUT_START_S, duration_s=BLACKOUT_S),
        fastest_ranking=ranking,
        **report.summarize(rows, methods),
        timing_ms=report.timing(rows, methods),
        recordings=[
            dict(
                key=r["key"],
                variants=r["variants"],
                cases={
                    c["variant"]: dict(
                        info=c["info"],
                        hidden_free_fraction=c["hidden_free_fraction"],
                        mean_error_mm={m: g["mean_error_mm"] for m, g in c["methods"].items()},
                        recovery_s={m: g["recovery_s"] for m, g in c["methods"].items() if "recovery_s" in g},
                    )
                    for c in r["cases"]
                },
            )
            for r in rows
        ],
        store=store.where(config),
    )
    png = args.out / f"{args.stem}.png"
    try:
        report.plot(result, png)
        result["plot"] = (
            str(png.relative_to(Path(__file__).resolve().parents[1]))
            if png.is_relative_to(Path(__file__).resolve().parents[1])
            else str(png)
        )
    except Exception as exc:  # a plot is a convenience; the numbers are stored regardless
        print(f"no plot: {exc}")
    write_atomic(args.out / f"{args.stem}.json", json.dumps(result, indent=1, default=float) + "\n")
    write_atomic(args.out / f"{args.stem}.md", report.markdown(result))
    print(report.markdown(result))
    return result


if __name__ == "__main__":
    main()
