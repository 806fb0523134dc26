"""Running the planted-effect benchmark: every dataset not yet stored for the run's configuration
becomes a task (:mod:`benchmarks.cluster`: a local Ray, a cluster, or ``--inline``), each row is
stored as it arrives (:mod:`benchmarks.store`: one file per dataset, so a stopped run resumes by
skipping those), then the tables are written from every stored row (:mod:`benchmarks.planted.tables`).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from benchmarks.cluster import Workers, call
from benchmarks.planted.config import previous_config, run_config, stem_of
from benchmarks.planted.independent import dataset_key, independent_jobs, independent_tasks
from benchmarks.planted.inputs import INDEPENDENT, independent_simulator
from benchmarks.planted.own import planted_dataset, planted_jobs, planted_key, real_dataset, real_key
from benchmarks.planted.tables import RESULTS, result_of, write
from benchmarks.provenance import provenance
from benchmarks.store import RunStore
from deform.diagnose.planted import EFFECTS

SCRIPT = "benchmarks/diagnose_planted.py"
_SUMMARY = {  # the fields printed as a row arrives
    "spliced": ("key", "selected", "spliced"),
    "diverged": ("key", "reason"),
    "independent": (
        "key",
        "selected",
        "equivalence_class",
        "detectability_l1_m",
        "nominal_check_l1_m",
        "final_check_l1_m",
        "seconds",
    ),
    "planted": ("key", "selected", "nominal_check_l1_m", "final_check_l1_m", "oracle_check_l1_m", "seconds"),
    "real": ("key", "selected", "nominal_check_l1_m", "final_check_l1_m", "seconds"),
}


def summary_of(row: dict) -> dict:
    """The fields of ``row`` printed when it arrives."""
    if "spliced" in row:
        kind = "spliced"
    elif row["kind"] == "planted" and "simulator" in row:
        kind = "independent"
    else:
        kind = row["kind"]
    return {k: row.get(k) for k in _SUMMARY[kind]}


def store_of(args) -> RunStore:
    """``--runs``, else ``benchmarks/results/STEM.runs/`` (and the rows of ``STEM.runs.jsonl``)."""
    return RunStore.for_runs(args.runs or RESULTS / f"{stem_of(args)}.runs")


def tasks_of(workers: Workers, args, store: RunStore) -> dict:
    """The tasks of the datasets of ``args`` not yet stored (key -> call), in the benchmark's order:
    controls first (they calibrate the rule and pair the effects), then the effects, then real rods."""
    config = run_config(args)
    done = store.load(config)
    old_rows = store.load(previous_config(args)) if getattr(args, "refit", None) else {}
    if args.simulator in INDEPENDENT:
        effects, _, _ = independent_simulator(args.simulator)
        effects = [e for e in (args.effects or effects) if e != "none"]
        pending = [
            job for job in independent_jobs(args, effects) if dataset_key(args.simulator, *job) not in done
        ]
        return independent_tasks(workers, args, pending, old_rows)
    effects = [e for e in (args.effects or EFFECTS) if e != "none"]
    tasks = {}
    for effect, seed in planted_jobs(args, effects):
        key = planted_key(effect, seed)
        if key not in done:
            tasks[key] = call(planted_dataset, effect, seed, args, old_rows.get(key))
    for rod in args.real:
        key = real_key(rod)
        if key not in done:
            tasks[key] = call(real_dataset, rod, args, old_rows.get(key))
    return tasks


def run_benchmark(args, results: Path = RESULTS, argv: list[str] | None = None) -> int:
    """Run the datasets of ``args`` not yet stored (none with ``--summary-only``), then write
    ``results/STEM.{json,md}`` from every stored row of the configuration; -> the exit code (1 when
    a dataset failed: the others are stored, and a rerun runs only the failed ones)."""
    stem = stem_of(args)
    store = store_of(args)
    config = run_config(args)
    workers = Workers.from_args(args)
    failures: dict[str, str] = {}
    ran: dict = {}
    if not args.summary_only:

        def stored(key: str, row: dict) -> None:
            store.save(row)
            workers.log(json.dumps(summary_of(row)))

        with workers:
            tasks = tasks_of(workers, args, store)
            start = time.perf_counter()
            failures = workers.run(tasks, stored, desc=stem)
            # the wall time of this invocation's datasets (the resumed ones not counted)
            ran = {"datasets_run": len(tasks), "run_wall_s": round(time.perf_counter() - start, 1)}
    if args.summary_only:  # the wall time of the run that stored the rows, when it was this file's
        old = results / f"{stem}.json"
        if old.is_file():
            before = json.loads(old.read_text())
            ran = {k: before[k] for k in ("datasets_run", "run_wall_s") if k in before}
    prov = {
        **provenance(
            [a for a in (sys.argv[1:] if argv is None else argv) if a != "--summary-only"],
            script=SCRIPT,
            threads=1,
        ),
        "workers": workers.describe(),
        **ran,
    }
    write(result_of(store.load(config), args, prov, store.where(config), results), stem, results)
    if failures:
        print(f"{len(failures)} dataset(s) failed, not stored: {', '.join(failures)}", file=sys.stderr)
        return 1
    return 0
