"""Train several rods at once: `deform train` for each of DLO1..DLO5 (or ``--rods``), every rod a Ray
task with one torch thread (benchmarks/cluster.py: a local Ray with one task per core, or a cluster).

    python benchmarks/train_rods.py [--rods DLO1 DLO2 ...] [--install] [--num-cpus N]
        [--address ray://HOST:PORT | auto] [-- DEFORM TRAIN OPTIONS, e.g. --iterations 400 --time-limit 1080]

Options after ``--`` (or not known here) go to `deform train` as they are (``--rod``, ``--out``,
``--threads`` and ``--install`` are this script's). Each rod trains in ``runs/train_rods/ROD/`` (as
`deform train --out`; on a cluster, on its worker's disk, resumed there); its result (the JSON line
`deform train` prints) is stored as it finishes in ``benchmarks/results/train_rods.runs/``, one
file per rod, and its best model written to ``runs/train_rods/ROD/best.pt`` on this machine
(``--install``: also to deform/models/ROD.pt). A rerun with the same options skips the rods stored.
Summary: ``benchmarks/results/train_rods.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from pathlib import Path

if not __package__:  # run as `python benchmarks/train_rods.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from benchmarks.cluster import Workers, add_arguments, call, repo_path
from benchmarks.provenance import provenance
from benchmarks.store import RunStore, write_result

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
RODS = ("DLO1", "DLO2", "DLO3", "DLO4", "DLO5")
OWN = ("--rod", "--out", "--threads", "--install")  # set by this script, not passed through


def train_rod(rod: str, train_args: list[str], out: str) -> dict:
    """A task: `deform train --rod ROD --out OUT --threads 1 TRAIN_ARGS` in this worker; -> the JSON
    it prints and its best model's bytes (``best_pt``)."""
    from deform.cli import main

    path = repo_path(out)
    printed = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(printed):
        code = main(["train", "--rod", rod, "--out", str(path), "--threads", "1", *train_args])
    if code != 0:
        raise RuntimeError(f"deform train --rod {rod} exited with {code}")
    result = json.loads(printed.getvalue().strip().splitlines()[-1])
    result["out"] = out
    return {"result": result, "seconds": time.perf_counter() - t0, "best_pt": (path / "best.pt").read_bytes()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rods", nargs="*", default=list(RODS))
    ap.add_argument("--install", action="store_true", help="copy each best model to deform/models/ROD.pt")
    ap.add_argument("--runs", default="runs/train_rods", help="training runs (relative to the repository)")
    ap.add_argument("--stem", default="train_rods", help="results benchmarks/results/<stem>.json")
    add_arguments(ap)
    args, train_args = ap.parse_known_args(argv)
    train_args = [a for a in train_args if a != "--"]
    if any(a.split("=")[0] in OWN for a in train_args):
        ap.error(f"{', '.join(OWN)} are set by this script")
    config = {"train_args": train_args}
    store = RunStore.for_runs(RESULTS / f"{args.stem}.runs")
    done = store.load(config)
    tasks = {
        rod: call(train_rod, rod, train_args, f"{args.runs}/{rod}") for rod in args.rods if rod not in done
    }

    def stored(rod: str, value: dict) -> None:
        best = ROOT / value["result"]["out"] / "best.pt"
        best.parent.mkdir(parents=True, exist_ok=True)
        best.write_bytes(value.pop("best_pt"))  # on this machine's disk (a cluster's worker has its own)
        row = {"key": rod, "config": config, "rod": rod, **value}
        store.save(row)
        done[rod] = row
        workers.log(json.dumps({"rod": rod, **value["result"]}))

    with Workers.from_args(args) as workers:
        failures = workers.run(tasks, stored, desc=args.stem)
    rows = [done[rod] for rod in args.rods if rod in done]
    if args.install:
        from deform.model import MODEL_DIR, DeformModel

        for row in rows:
            DeformModel.load(ROOT / row["result"]["out"] / "best.pt").save(MODEL_DIR / f"{row['rod']}.pt")
    result = {
        **provenance(argv, threads=1),
        "workers": workers.describe(),
        "train_args": train_args,
        "installed": bool(args.install),
        "complete": not failures,
        "rows": rows,
    }
    return write_result(RESULTS / args.stem, result, failures, "rod(s)", indent=2)


if __name__ == "__main__":
    raise SystemExit(main())
