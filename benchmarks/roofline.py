"""A roofline of the batched model step: operations and memory traffic per rod-step, by phase, against
what the 2 cores can do.

    python benchmarks/roofline.py [--batch 1024] [--json benchmarks/results/roofline.json]

Counting: one branch-free step (the graph the compiled and ahead-of-time steps run, deform.step_graph)
is executed eagerly under a ``TorchDispatchMode`` that sees every aten operation. Matrix products
count 2 m n k (torch.utils.flop_counter's formulas); every other arithmetic or comparison operation
counts one operation per output element, a reduction one per input element (a sine or a division
counts one, like an add: the figure is "operations", the usual convention of a roofline); pure data
movement (views, copies, concatenation, indexing, fills) counts none. Traffic is the bytes each
non-view operation reads and writes: what the eager step moves, an upper bound for compiled code,
which fuses operations; the lower bound is the state read and written once.

Phases, by the function running when the operation is dispatched: ``theta`` (the twist solve),
``forces`` (bending and twisting forces from the solved angles), ``geometry`` (tangents, frames,
curvatures), ``residual`` (the graph network), ``projection`` (inextensibility), ``other``
(integration, drag, bookkeeping).

Peaks, measured in the same run: a float64 and a float32 matrix product of 2048 x 2048 on 2 threads
(what BLAS reaches: the attainable compute peak) and a large float64 copy (the attainable
bandwidth). The step's own rate comes from a timed eager step here, from
``benchmarks/results/speed.json`` for the convergence-checked compiled step
(``throughput_compiled_rod_steps_per_s_2_threads``; benchmarks/speed.py), and from
``benchmarks/results/batched_throughput.json`` for predict's float32 step (benchmarks/batched_throughput.py).

Where the time goes: predict's one-graph float32 step under torch.compile with inductor's kernel
profiling on (the same graph as its ahead-of-time package), ``--profile-steps`` steps of the batch
profiled, self time per kernel and per library call.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import flop_registry

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

MOVEMENT = (
    "view", "expand", "permute", "transpose", "select", "slice", "unsqueeze", "squeeze", "clone",
    "copy", "cat", "stack", "index", "gather", "scatter", "zeros", "empty", "full", "ones", "detach",
    "alias", "split", "unbind", "narrow", "repeat", "flip", "roll", "as_strided", "new_", "fill",
    "lift_fresh", "t.default", "_to_copy", "scalar_tensor", "arange", "masked_fill", "where",
)  # fmt: skip
VIEWS = ("view", "expand", "permute", "transpose", "select", "slice", "unsqueeze", "squeeze", "alias",
         "as_strided", "split", "unbind", "narrow", "t.default", "detach", "lift_fresh")  # fmt: skip
REDUCTIONS = (
    "sum",
    "mean",
    "amax",
    "amin",
    "norm",
    "prod",
    "any",
    "all",
    "max",
    "min",
    "cumsum",
    "logsumexp",
)


def _tensors(obj):
    if isinstance(obj, torch.Tensor):
        yield obj
    elif isinstance(obj, (list, tuple)):
        for o in obj:
            yield from _tensors(o)
    elif isinstance(obj, dict):
        for o in obj.values():
            yield from _tensors(o)


class Counter(TorchDispatchMode):
    """Operations and bytes of every aten call, attributed to the phase on top of ``self.phase``."""

    def __init__(self):
        super().__init__()
        self.phase = ["other"]
        self.ops = defaultdict(float)
        self.bytes = defaultdict(float)
        self.calls = defaultdict(int)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = str(func.overloadpacket.__name__) + "." + func._overloadname
        phase = self.phase[-1]
        self.calls[phase] += 1
        packet = func.overloadpacket
        ins, outs = list(_tensors((args, kwargs))), list(_tensors(out))
        if packet in flop_registry:
            self.ops[phase] += flop_registry[packet](*args, out_val=out, **kwargs)
        elif any(m in name for m in MOVEMENT):
            pass
        elif any(name.startswith(r) or name.startswith("linalg_" + r) for r in REDUCTIONS):
            self.ops[phase] += sum(t.numel() for t in ins[:1])
        else:
            self.ops[phase] += sum(t.numel() for t in outs)
        if not any(v in name for v in VIEWS):
            self.bytes[phase] += sum(t.numel() * t.element_size() for t in ins + outs)
        return out

    @contextmanager
    def within(self, phase: str):
        self.phase.append(phase)
        try:
            yield
        finally:
            self.phase.pop()


def _wrap(counter: Counter, fn, phase: str):
    def wrapped(*a, **k):
        with counter.within(phase):
            return fn(*a, **k)

    return wrapped


def count_step(model, batch: int) -> tuple[dict, dict, dict]:
    """(ops, bytes, calls) per phase for one branch-free step of ``batch`` rods (float64)."""
    import deform.model as dm
    from deform.compiled import LOOP_BRANCH_FREE
    from deform.step_graph import branch_free_step, rod_at_rest_vertex_major

    state, grip = rod_at_rest_vertex_major(model, batch, torch.float64)
    state = branch_free_step(model, state, grip + 0.01, LOOP_BRANCH_FREE)[0]  # not at rest: a real step
    counter = Counter()
    patched = {
        "rod_forces": "forces",
        "rod_geometry": "geometry",
        "curvature_projections": "geometry",
        "enforce_inextensibility": "projection",
    }
    saved = {k: getattr(dm, k) for k in patched}
    saved_solve, saved_res = model._solve_theta, model.residual.forward
    try:
        for k, phase in patched.items():
            setattr(dm, k, _wrap(counter, saved[k], phase))
        model._solve_theta = _wrap(counter, saved_solve, "theta")
        model.residual.forward = _wrap(counter, saved_res, "residual")
        with torch.no_grad(), counter:
            branch_free_step(model, state, grip + 0.02, LOOP_BRANCH_FREE)
    finally:
        for k, fn in saved.items():
            setattr(dm, k, fn)
        del model._solve_theta, model.residual.forward
    return dict(counter.ops), dict(counter.bytes), dict(counter.calls)


def measured_peaks(threads: int) -> dict:
    """What this machine reaches: float64 GEMM (compute) and a large copy (bandwidth), best of 5."""
    torch.set_num_threads(threads)
    gemm = {}
    for dtype in (torch.float64, torch.float32):
        a, b = torch.randn(2048, 2048, dtype=dtype), torch.randn(2048, 2048, dtype=dtype)
        a @ b
        gemm[dtype] = min(_timed(lambda a=a, b=b: a @ b) for _ in range(5))
    src = torch.randn(64 * 2**20 // 8, dtype=torch.float64)
    dst = torch.empty_like(src)
    dst.copy_(src)
    copy = min(_timed(lambda: dst.copy_(src)) for _ in range(5))
    return {
        "gemm_gflops": round(2 * 2048**3 / gemm[torch.float64] / 1e9, 1),
        "gemm_gflops_float32": round(2 * 2048**3 / gemm[torch.float32] / 1e9, 1),
        "copy_gb_per_s": round(2 * src.numel() * 8 / copy / 1e9, 1),  # read + write
    }


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def kernel_profile(model, batch: int, steps: int) -> dict:
    """Milliseconds per step by compiled kernel and library call, predict's one-graph float32 step."""
    import torch._inductor.config as inductor_config

    from deform.compiled import PREDICT_BRANCH_FREE
    from deform.step_graph import branch_free_step, rod_at_rest_vertex_major

    inductor_config.cpp.enable_kernel_profile = True  # each generated kernel a profiler record
    state, grip = rod_at_rest_vertex_major(model, batch, torch.float32)
    grip = grip.clone()
    grip[2:, 2] += 0.002  # moving grippers: a real step, not a rod at rest
    fn = torch.compile(lambda s, g: branch_free_step(model, s, g, PREDICT_BRANCH_FREE), dynamic=False)
    with torch.no_grad():
        for _ in range(3):
            state = fn(state, grip)[0]
        t = time.perf_counter()
        for _ in range(steps):
            state = fn(state, grip)[0]
        rate = batch * steps / (time.perf_counter() - t)
        with torch.profiler.profile() as prof:
            for _ in range(steps):
                state = fn(state, grip)[0]
    inductor_config.cpp.enable_kernel_profile = False
    rows = {}
    for e in prof.key_averages():
        name = e.key
        if "cpp_fused" in name:
            kind = "compiled kernel"
        elif name in ("aten::mm", "aten::addmm", "aten::bmm"):
            kind = "matrix product (library)"
        else:
            continue
        rows[name] = {
            "kind": kind,
            "ms_per_step": e.self_cpu_time_total / 1e3 / steps,
            "calls": e.count // steps,
        }
    total = sum(r["ms_per_step"] for r in rows.values())
    top = sorted(rows.items(), key=lambda kv: -kv[1]["ms_per_step"])
    by_kind = defaultdict(float)
    for r in rows.values():
        by_kind[r["kind"]] += r["ms_per_step"]
    return {
        "rod_steps_per_s_torch_compile": round(rate),
        "ms_per_step_in_kernels_and_products": round(total, 3),
        "by_kind_ms": {k: round(v, 3) for k, v in by_kind.items()},
        "top": [
            {"name": name[:90], **{k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()}}
            for name, r in top[:8]
        ],
    }


def eager_rate(model, batch: int, steps: int = 10) -> float:
    """Rod-steps per second of the eager branch-free step (2 threads)."""
    from deform.compiled import LOOP_BRANCH_FREE
    from deform.step_graph import branch_free_step, rod_at_rest_vertex_major

    state, grip = rod_at_rest_vertex_major(model, batch, torch.float64)
    with torch.no_grad():
        state = branch_free_step(model, state, grip, LOOP_BRANCH_FREE)[0]
        t = time.perf_counter()
        for _ in range(steps):
            state = branch_free_step(model, state, grip, LOOP_BRANCH_FREE)[0]
    return batch * steps / (time.perf_counter() - t)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--rod", default="DLO1")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/roofline.json"))
    ap.add_argument("--profile-steps", type=int, default=20)
    args = ap.parse_args()
    from deform import load_model

    torch.set_num_threads(2)
    model = load_model(args.rod)
    ops, traffic, calls = count_step(model, args.batch)
    B = args.batch
    per_rod = {p: ops[p] / B for p in ops}
    total_ops, total_bytes = sum(ops.values()) / B, sum(traffic.values()) / B
    state_bytes = (model.n * 3 * 3 + (model.n - 1) * 3 + (model.n - 1) * 2) * 8  # x, v, d1; theta, rest
    peaks = measured_peaks(2)
    eager = eager_rate(model, B)
    speed = json.loads((ROOT / "benchmarks/results/speed.json").read_text())
    compiled = float(speed["throughput_compiled_rod_steps_per_s_2_threads"].get(str(B), "nan"))
    batched = json.loads((ROOT / "benchmarks/results/batched_throughput.json").read_text())
    predict32 = float("nan")
    if batched.get("batch") == B:
        predict32 = float(batched["rod_steps_per_s"]["predict_aot_2_2_float32"]["median"])
    profile = kernel_profile(model, B, args.profile_steps)
    from benchmarks.provenance import provenance

    result = {
        **provenance(),
        "rod": args.rod,
        "n_vertices": model.n,
        "batch": B,
        "ops_per_rod_step": round(total_ops),
        "ops_per_rod_step_by_phase": {p: round(v) for p, v in sorted(per_rod.items(), key=lambda kv: -kv[1])},
        "aten_calls_per_step_by_phase": calls,
        "eager_bytes_per_rod_step": round(total_bytes),
        "eager_bytes_by_phase": {p: round(v / B) for p, v in traffic.items()},
        "state_bytes_per_rod_step": 2 * state_bytes,
        "intensity_ops_per_byte": {
            "eager": round(total_ops / total_bytes, 3),
            "fused_bound": round(total_ops / (2 * state_bytes), 2),
        },
        "peaks_2_threads": peaks,
        "rates_rod_steps_per_s": {
            "eager_here": round(eager),
            "compiled_speed_json": None if compiled != compiled else round(compiled),
            "predict_float32_batched_throughput_json": None if predict32 != predict32 else round(predict32),
        },
        "profile_predict_float32": profile,
    }
    for label, rate, peak in (
        ("eager", eager, peaks["gemm_gflops"]),
        ("compiled", compiled, peaks["gemm_gflops"]),
        ("predict_float32", predict32, peaks["gemm_gflops_float32"]),
    ):
        if rate != rate:  # no rate stored for this batch size
            continue
        gops = total_ops * rate / 1e9
        result[f"achieved_{label}"] = {
            "gops": round(gops, 2),
            "fraction_of_gemm_peak": round(gops / peak, 4),
            "gb_per_s_if_eager_traffic": round(total_bytes * rate / 1e9, 2),
        }
    ridge = peaks["gemm_gflops"] / peaks["copy_gb_per_s"]
    result["ridge_ops_per_byte"] = round(ridge, 2)
    print(json.dumps(result, indent=1))
    Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
