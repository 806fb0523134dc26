"""Predict's rollout alone: 64 random plans of 100 steps from recorded states, for several one-graph
iteration counts of :class:`deform.compiled.RolloutStep`, interleaved in one process.

Why: the service's predict time mixes the rollout with IPC, JSON and whatever else the machine runs.
This isolates the rollout and how often its one-graph step misses (a step it leaves unconverged is
stepped again, that rod alone, by the convergence-checked loops). The plans are drawn as
in ``benchmarks/service_bench.py``: each gripper moves linearly to a random offset of up to 10 cm per
axis over the 100 steps, from the state of a recording at frames 50, 200 and 350.

    python benchmarks/predict_rollout.py [--rod DLO1] [--recordings 5] [--settings 2,1 2,2 3,2] [--repeats 3]
    python benchmarks/predict_rollout.py --settings 2,2 2,2:aot    # torch.compile vs ahead of time

A setting ``T,S:aot`` runs the one-graph step as an AOTInductor package (``deform.aot``), ``T,S:aot:bf16``
also with the residual network in bfloat16 (``deform.nn.precision``; from 512 plans on, below that
the float32 network runs either way), ``...:norescue`` redoes unconverged rods with the checked eager
loops instead of the rescue graph. ``--start sagging`` starts every plan from one sagging rod that
many plans pull nearly taut (where the one graph misses):

    python benchmarks/predict_rollout.py --start sagging --plans 512 --repeats 3 --settings 2,2:aot:norescue 2,2:aot

Prints one JSON line per setting: median, p90 and max rollout time (best of ``repeats`` per start
state), the starts where the one graph missed, rod-steps redone, and pauses.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def start_states(model, rod: str, n_recordings: int):
    """(name, state of one rod, grips now (4, 3)) at frames 50, 200, 350 of the first eval recordings
    (or of simulated ones without the dataset)."""
    from deform import find_data_root, generate_recording, gripped_indices, load_recording

    root = find_data_root()
    files = sorted((root / rod / "eval").glob("*.pkl"))[:n_recordings] if root else []
    recs = [load_recording(f) for f in files] or [
        generate_recording(model, n_frames=400, seed=s) for s in range(n_recordings)
    ]
    gi = gripped_indices(model.n)
    for r in recs:
        X = torch.as_tensor(r.positions, dtype=torch.float64)
        d1 = torch.as_tensor(r.reference_frames)
        for k in (50, 200, 350):
            if k + 2 > len(X):
                continue
            s = model.initial_state(X[k - 1 : k], X[k : k + 1], d1=d1[k : k + 1])
            s = model.step(s, X[k + 1 : k + 2, gi])  # the material angles solved, as in a running service
            yield f"{r.name}@{k}", s, X[k + 1, gi]


def sagging_start(model):
    """One rod hanging between grippers 0.8 m apart with 15 cm of sag, at rest in that shape (its
    rest lengths are this shape's): random plans of up to 10 cm per axis then pull many of the
    rods nearly taut, where the one-graph step misses (planning-scale sampling meets this)."""
    from deform import gripped_indices

    s = torch.linspace(0, 1, model.n, dtype=torch.float64)
    x = torch.stack([0.8 * s, 0 * s, 0.4 - 0.15 * torch.sin(torch.pi * s)], -1)[None]
    state = model.initial_state(x, x)
    grip = x[0, gripped_indices(model.n)]
    yield "sagging", model.step(state, grip[None]), grip


def main() -> None:
    from deform import RodState, load_model
    from deform.compiled import RolloutStep, rollout

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rod", default="DLO1")
    ap.add_argument("--recordings", type=int, default=5)
    ap.add_argument(
        "--settings", nargs="+", default=["2,1", "2,2", "3,2"], help="twist iterations,projection sweeps"
    )
    ap.add_argument("--plans", type=int, default=64)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--start",
        default="recorded",
        choices=["recorded", "sagging"],
        help="recorded states, or sagging_start",
    )
    ap.add_argument(
        "--dtype",
        default="float32",
        choices=["float32", "float64"],
        help="of the rollout (the service's predict: float32)",
    )
    args = ap.parse_args()
    dtype = getattr(torch, args.dtype)
    torch.set_num_threads(1)  # as in the service's predict worker
    model = load_model(args.rod)
    steps = {
        s: RolloutStep(
            model,
            branch_free=tuple(int(v) for v in s.split(":")[0].split(",")),
            ahead_of_time="aot" in s.split(":")[1:],
            network_dtype=torch.bfloat16 if "bf16" in s.split(":")[1:] else None,
        )
        for s in args.settings
    }
    for s, st in steps.items():
        if "norescue" in s.split(":")[1:]:  # unconverged rods through the checked eager loops only
            st.rescue.enabled = False
    for st in steps.values():
        st.warmup((args.plans,), dtype)
    rng = np.random.default_rng(args.seed)
    results = {s: {"ms": [], "missed_at": [], "redone": 0, "paused": 0} for s in args.settings}
    lin = torch.linspace(0, 1, args.steps, dtype=torch.float64)[None, :, None, None]
    starts = (
        sagging_start(model) if args.start == "sagging" else start_states(model, args.rod, args.recordings)
    )
    for name, state, grip in starts:
        batch = RodState(
            *(
                t.expand(args.plans, *t.shape[1:]).to(dtype)
                for t in (state.x, state.v, state.d1, state.theta, state.rest)
            )
        )
        offsets = torch.as_tensor(rng.uniform(-0.1, 0.1, (args.plans, 1, 2, 3)))
        grips = (grip[None, None] + lin * offsets[:, :, [0, 0, 1, 1]]).to(dtype)
        for s, st in steps.items():  # interleaved: the same machine state for every setting
            r0, p0 = st.redone, st.paused
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                rollout(st, batch, grips)
                times.append(time.perf_counter() - t0)
            res = results[s]
            res["ms"].append(1e3 * min(times))
            redone = (st.redone - r0) // args.repeats
            res["redone"] += redone
            res["paused"] += (st.paused - p0) // args.repeats
            if redone:
                res["missed_at"].append(name)
    for s, res in results.items():
        ms = np.array(res["ms"])
        print(
            json.dumps(
                {
                    "branch_free": s,
                    "starts": len(ms),
                    "plans": args.plans,
                    "steps": args.steps,
                    "dtype": args.dtype,
                    "median_ms": round(float(np.median(ms)), 1),
                    "p90_ms": round(float(np.percentile(ms, 90)), 1),
                    "max_ms": round(float(ms.max()), 1),
                    "starts_missed": len(res["missed_at"]),
                    "rod_steps_redone": res["redone"],
                    "pauses": res["paused"],
                    "missed_at": res["missed_at"],
                }
            )
        )


if __name__ == "__main__":
    main()
