"""Today's step against an earlier commit's, in the same run: processes of both checkouts alternated.

Why: this VM's speed drifts by tens of percent within minutes, so a speed-up is only measured
against its baseline in one run. Each measurement is a fresh process importing ``deform`` from one
checkout (the earlier commit checked out as a git worktree in a temporary directory), the two
checkouts taking turns ``--rounds`` times. Measured, on one thread (what each predict process runs):

* ``predict_step``: predict's one-graph step (2 twist iterations, 2 sweeps, ahead of time, float32
  state) called step after step on 1024 rods, rod-steps per second (median of 7 timings of 50 steps);
* ``rollout_512``: ``benchmarks/predict_rollout.py --plans 512 --settings 2,2:aot`` of that
  checkout, the median rollout time [ms] over its start states;
* ``loop_step``: the 100 Hz loop's step (one rod, float64, ahead of time) over a DLO1 recording,
  p50 and p99 [ms];
* ``reposition``: a correction of the one-rod eager model (:meth:`DeformModel.reposition`, a 2 mm
  shift of every vertex) after every third step, median [ms] of the correction and of the step;
* ``tracker``: our tracker's camera update and model step as ``benchmarks/tracking_peers.py --quick
  --methods ours --scenarios occlusion`` of that checkout times them (DLO1 and DLO3, 0-50 %
  occluded), p50 and p99 [ms].

    python benchmarks/ab_commits.py [--base 233b390] [--rounds 2] [--measure tracker ...]
        -> benchmarks/results/ab_commits[.<measures>].json
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# run inside the checkout under test (its own deform): prints one JSON line
_STEP = """
import json, statistics, sys, torch
sys.path.insert(0, {root!r})
torch.set_num_threads(1)
from deform import load_model
from deform.bench import _trajectory, throughput
from deform.compiled import PREDICT_BRANCH_FREE, CompiledStep
model = load_model("DLO1")
pos = _trajectory(model)
step = CompiledStep(model, branch_free=PREDICT_BRANCH_FREE, ahead_of_time=True)
throughput(model, pos, 1024, 3, step, torch.float32)  # build or load the package
rates = [throughput(model, pos, 1024, 50, step, torch.float32) for _ in range(7)]
print(json.dumps({{"rod_steps_per_s": statistics.median(rates)}}))
"""

_LOOP = """
import json, sys, time, torch
sys.path.insert(0, {root!r})
torch.set_num_threads(1)
from deform import load_model
from deform.bench import _percentiles, _trajectory
from deform.compiled import LOOP_BRANCH_FREE, CompiledStep
from deform.model import gripped_indices
model = load_model("DLO1")
pos = torch.tensor(_trajectory(model))
step = CompiledStep(model, branch_free=LOOP_BRANCH_FREE, ahead_of_time=True)
idx = gripped_indices(model.n)
seconds = []
with torch.no_grad():
    for rep in range(3):
        s = model.initial_state(pos[0:1], pos[1:2])
        for k in range(len(pos) - 2):
            t = time.perf_counter()
            s = step(s, pos[2 + k : 3 + k, idx])
            if k >= 20:
                seconds.append(time.perf_counter() - t)
print(json.dumps(_percentiles(seconds)))
"""

_REPOSITION = """
import json, statistics, sys, time, torch
sys.path.insert(0, {root!r})
torch.set_num_threads(1)
from deform import load_model
from deform.bench import _trajectory
from deform.model import gripped_indices
model = load_model("DLO1")
pos = torch.tensor(_trajectory(model))
idx = gripped_indices(model.n)
noise = torch.Generator().manual_seed(0)
correct, step = [], []
with torch.no_grad():
    for rep in range(3):
        s = model.initial_state(pos[0:1], pos[1:2])
        for k in range(len(pos) - 2):
            t0 = time.perf_counter()
            s = model.step(s, pos[2 + k : 3 + k, idx])
            t1 = time.perf_counter()
            step.append(t1 - t0)
            if k % 3 == 0:
                x = s.x + 0.002 * torch.randn(s.x.shape, generator=noise, dtype=s.x.dtype)
                s = model.reposition(s, x, s.v)
                correct.append(time.perf_counter() - t1)
print(json.dumps({{"correct_p50_ms": 1e3 * statistics.median(correct), "step_p50_ms": 1e3 * statistics.median(step)}}))
"""


def _run(code: str, cwd: Path) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, check=True
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def _rollout(root: Path) -> float:
    out = subprocess.run(
        [
            sys.executable,
            "benchmarks/predict_rollout.py",
            "--plans",
            "512",
            "--settings",
            "2,2:aot",
            "--recordings",
            "3",
            "--repeats",
            "2",
        ],
        cwd=root,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return json.loads([line for line in out.splitlines() if line.startswith("{")][-1])["median_ms"]


def _tracker(root: Path) -> dict:
    with tempfile.TemporaryDirectory() as out:
        subprocess.run(
            [
                sys.executable,
                "benchmarks/tracking_peers.py",
                "--quick",
                "--methods",
                "ours",
                "--scenarios",
                "occlusion",
                "--out",
                out,
            ],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        )
        timing = json.loads((Path(out) / "tracking_peers.json").read_text())["timing_ms"]["ours"]
    return {"update": timing["update"], "step": timing["step"]}


# name on the command line -> (key of its value in a round, the measurement)
MEASURES = {
    "predict_step": (
        "predict_step_rod_steps_per_s",
        lambda root: _run(_STEP.format(root=str(root)), root)["rod_steps_per_s"],
    ),
    "rollout_512": ("rollout_512_median_ms", _rollout),
    "loop_step": ("loop_step", lambda root: _run(_LOOP.format(root=str(root)), root)),
    "reposition": ("reposition", lambda root: _run(_REPOSITION.format(root=str(root)), root)),
    "tracker": ("tracker", _tracker),
}


def measure(root: Path, names: list[str]) -> dict:
    """One round of the named measurements in the checkout at ``root``."""
    return {MEASURES[name][0]: MEASURES[name][1](root) for name in names}


def speedups(rows: dict[str, list]) -> dict:
    """Base over head (a time) or head over base (a rate), medians over the rounds, for what was
    measured: above 1 where the head is faster."""

    def med(name, *keys):
        vals = []
        for r in rows[name]:
            for k in keys:
                r = r[k]
            vals.append(r)
        return statistics.median(vals)

    measured = rows["head"][0]
    out = {}
    if "predict_step_rod_steps_per_s" in measured:
        out["predict_step_ratio"] = med("head", "predict_step_rod_steps_per_s") / med(
            "base", "predict_step_rod_steps_per_s"
        )
    if "rollout_512_median_ms" in measured:
        out["rollout_512_ratio"] = med("base", "rollout_512_median_ms") / med("head", "rollout_512_median_ms")
    if "loop_step" in measured:
        out["loop_step_p50_ratio"] = med("base", "loop_step", "p50_ms") / med("head", "loop_step", "p50_ms")
    if "reposition" in measured:
        for part in ("correct", "step"):
            out[f"reposition_{part}_p50_ratio"] = med("base", "reposition", f"{part}_p50_ms") / med(
                "head", "reposition", f"{part}_p50_ms"
            )
    if "tracker" in measured:
        for part in ("update", "step"):
            for q in ("p50", "p99"):
                out[f"tracker_{part}_{q}_ratio"] = med("base", "tracker", part, q) / med(
                    "head", "tracker", part, q
                )
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--base", default="233b390", help="the earlier commit (default: before the vertex-major layout)"
    )
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--measure", nargs="+", choices=list(MEASURES), default=list(MEASURES))
    ap.add_argument("--json", default=None, help="default benchmarks/results/ab_commits[.<measures>].json")
    args = ap.parse_args()
    every = args.measure == list(MEASURES)
    stem = "ab_commits" if every else "ab_commits." + "_".join(args.measure)
    path = Path(args.json) if args.json else ROOT / "benchmarks/results" / f"{stem}.json"
    from benchmarks.provenance import provenance

    rows: dict[str, list] = {"base": [], "head": []}
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "base"
        subprocess.run(
            ["git", "worktree", "add", "-q", "--detach", str(base), args.base], cwd=ROOT, check=True
        )
        try:
            for r in range(args.rounds):
                for name, root in (("base", base), ("head", ROOT)):
                    rows[name].append(measure(root, args.measure))
                    print(name, r, json.dumps(rows[name][-1]), flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base)], cwd=ROOT, check=False)

    summary = speedups(rows)
    result = {**provenance(), "base": args.base, "rounds": rows, "speedup": summary}
    path.write_text(json.dumps(result, indent=2))
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
