"""Stand-ins for the planted benchmark's tasks (tests/benchmarks/test_planted_run.py): they return the
rows of a stored run instead of simulating and diagnosing. A module of their own, so that Ray's
workers import them by name, and a light one (no deform.diagnose) so that they start fast."""

import json
from pathlib import Path

import torch

STEM = "diagnose.mujoco.noise1mm.light"
RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"
ROWS = RESULTS / f"{STEM}.runs.jsonl"
# the command that stored them (its json's "command")
ARGS = (
    "--simulator mujoco --quick --rod-kinds light --seeds 1 --control-seeds 1 --fit 8 --check 4 "
    "--frames 300 --noise-mm 1.0 --fits-version 10"
).split()


def stored_rows() -> dict[str, dict]:
    return {row["key"]: row for row in map(json.loads, ROWS.read_text().splitlines())}


def simulate(simulator, kind, effect, seed, args) -> dict:
    return {"recs": [], "truth": {}, "seconds": 0.0, "threads": torch.get_num_threads()}


def independent_dataset(simulator, kind, effect, seed, args, control=None, old=None) -> dict:
    assert control is not None and control["threads"] == 1  # the shared control, resolved
    rows = getattr(args, "fake_rows", None) or stored_rows()  # given where the results are not shipped
    row = dict(rows[f"{simulator}:{kind}:{effect or 'none'}:{seed}"])
    row["task_threads"] = torch.get_num_threads()
    return row


def failing_dataset(simulator, kind, effect, seed, args, control=None, old=None) -> dict:
    if effect == "point_mass":
        raise RuntimeError("a bug in one dataset")
    return independent_dataset(simulator, kind, effect, seed, args, control, old)
