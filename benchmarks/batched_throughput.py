"""Batched step throughput at planning scale, today's steps side by side in one run (issue 21).

    python benchmarks/batched_throughput.py [--batch 1024] [--steps 100] [--json benchmarks/results/batched_throughput.json]

Rod-steps per second on 2 threads (``deform.bench.throughput``: B copies of a DLO1 recording's
grippers, slightly perturbed), for: the eager step; the convergence-checked step under
torch.compile (``speed.json``'s "compiled"); and predict's step, the one-graph step with 2 twist
iterations and 2 projection sweeps as an AOTInductor package, unconverged rods redone eagerly
(``CompiledStep(branch_free=(2, 2), ahead_of_time=True)``), and the same one-graph step under
torch.compile; and predict's step with a float32 state (``predict_aot_2_2_float32``), also on one
thread (``..._1_thread``: what the service's predict worker runs, ``workers.predict_threads``);
and those with the residual network in bfloat16 (``..._bf16_network``: ``deform.nn.precision``,
what the service picks where the CPU has native bfloat16, ``machine.native_bfloat16``).
Ratios are to the checked compiled step.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/batched_throughput.json"))
    args = ap.parse_args()
    from deform import load_model
    from deform.bench import _trajectory, throughput
    from deform.compiled import PREDICT_BRANCH_FREE, CompiledStep
    from deform.nn.precision import native_bfloat16

    torch.set_num_threads(2)
    model = load_model("DLO1")
    positions = _trajectory(model)
    predict_step = CompiledStep(model, branch_free=PREDICT_BRANCH_FREE, ahead_of_time=True)
    f64, f32 = torch.float64, torch.float32
    one_thread_step = CompiledStep(model, branch_free=PREDICT_BRANCH_FREE, ahead_of_time=True)
    bf16 = {"branch_free": PREDICT_BRANCH_FREE, "ahead_of_time": True, "network_dtype": torch.bfloat16}
    variants = {  # name: (step, state dtype, threads)
        "eager": (model.step, f64, 2),
        "compiled_checked": (CompiledStep(model), f64, 2),
        "predict_aot_2_2": (predict_step, f64, 2),
        "predict_aot_2_2_float32": (predict_step, f32, 2),
        "predict_aot_2_2_float32_1_thread": (one_thread_step, f32, 1),
        "predict_aot_2_2_float32_bf16_network": (CompiledStep(model, **bf16), f32, 2),
        "predict_aot_2_2_float32_bf16_network_1_thread": (CompiledStep(model, **bf16), f32, 1),
        "one_graph_2_2_torch_compile": (CompiledStep(model, branch_free=PREDICT_BRANCH_FREE), f64, 2),
    }
    from benchmarks.provenance import provenance

    out = {
        **provenance(native_bfloat16=native_bfloat16()),
        "batch": args.batch,
        "steps": args.steps,
        "rod_steps_per_s": {},
    }
    for name, (fn, dtype, threads) in variants.items():  # compile / build / load first
        torch.set_num_threads(threads)  # a package is built for, and keyed on, its thread count
        t0 = time.perf_counter()
        throughput(model, positions, args.batch, 2, fn, dtype)
        out.setdefault("warmup_s", {})[name] = round(time.perf_counter() - t0, 1)
    rates = {name: [] for name in variants}
    for _ in range(args.repeats):  # interleaved: the VM's speed drifts by tens of percent in minutes
        for name, (fn, dtype, threads) in variants.items():
            torch.set_num_threads(threads)
            rates[name].append(throughput(model, positions, args.batch, args.steps, fn, dtype))
    for name, r in rates.items():
        out["rod_steps_per_s"][name] = {"median": round(sorted(r)[len(r) // 2]), "all": [round(x) for x in r]}
        print(name, out["rod_steps_per_s"][name], flush=True)
    base = out["rod_steps_per_s"]["compiled_checked"]["median"]
    out["ratio_to_compiled_checked"] = {
        k: round(v["median"] / base, 2) for k, v in out["rod_steps_per_s"].items()
    }
    print(json.dumps(out["ratio_to_compiled_checked"]))
    Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
