#!/usr/bin/env python3
"""Regenerate docs/results.md from the stored benchmark results in benchmarks/results/*.json.

    python scripts/make_results.py [--results DIR] [--out FILE]      (or `make results`)

One section per results file, in a fixed order for the files this script knows (accuracy, speed,
perception, service, service_soak, baselines, ablations, diagnose and any diagnose.*.json), then a
short section for any other .json it finds. Each section states where its numbers came from: the
file's own `command`, `commit` and `machine` fields ("not recorded" when the file has none), the
script that writes it, and the git commit that last changed the file. A missing file is listed
as missing; a file whose layout this script does not understand is listed with its top-level fields.

Standard library and numpy only; nothing is measured here, every number is copied from a file.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
OUT = ROOT / "docs" / "results.md"

# file -> (title, the script that writes it)
KNOWN = {
    "accuracy.json": ("Accuracy: 500-step open-loop prediction", "python benchmarks/accuracy.py"),
    "speed.json": ("Speed of the model step", "python benchmarks/speed.py"),
    "perception.json": (
        "Perception: tracking from rendered RGB-D clouds",
        "python benchmarks/perception_tracking.py",
    ),
    "service.json": (
        "Service: loop, predict, memory soak",
        "python benchmarks/service_bench.py --json benchmarks/results/service.json",
    ),
    "service_soak.json": (
        "Service: 30-minute soak",
        "python benchmarks/service_bench.py --loop-s 30 --soak-s 1800 --predict-n 20 --json benchmarks/results/service_soak.json",
    ),
    "baselines.json": ("Baselines beside DEFORM", "python benchmarks/baselines.py"),
    "ablations.json": ("Ablations", "python benchmarks/ablations.py"),
    "diagnose.json": ("deform diagnose: planted-effect benchmark", "python benchmarks/diagnose_planted.py"),
    "real_terms.json": ("Named physics trained into DEFORM, real rods", "python benchmarks/real_terms.py"),
    "real_terms.v6.json": (
        "Named physics trained into DEFORM, real rods: the terms tool v6 newly named",
        "python benchmarks/real_terms.py --rods DLO1 DLO2 DLO4 DLO5 --terms DLO1=internal_damping "
        "DLO2=external_force DLO4=external_force DLO5=external_force --stem real_terms.v6",
    ),
    "real_terms.dlo1.json": (
        "DLO1 with internal damping trained into DEFORM and installed (the shipped model since)",
        "python benchmarks/real_terms.py --rods DLO1 --terms DLO1=internal_damping --stem real_terms.dlo1 --install",
    ),
    "service_startup.json": ("Service start-up, cold and warm", "python benchmarks/service_startup.py"),
    "roofline.json": ("Roofline of the batched model step", "python benchmarks/roofline.py"),
    "float32_accuracy.json": ("float32 rollout against float64", "python benchmarks/float32_accuracy.py"),
    "batched_throughput.json": (
        "Batched step throughput at 1024 rods",
        "python benchmarks/batched_throughput.py",
    ),
    "predict_planning.json": (
        "Planning-scale predict in the service",
        "python benchmarks/predict_planning.py --n 30 --rounds 3 --compare predict_network_dtype=auto",
    ),
    "ab_commits.json": (
        "Today's step against an earlier commit's, same run",
        "python benchmarks/ab_commits.py",
    ),
    "tracking_peers.json": (
        "Tracking side by side with the published trackers (CPD, CDCPD, TrackDLO, UPETrack)",
        "python benchmarks/tracking_peers.py",
    ),
    "calibrate_rods.json": (
        "deform calibrate: models from camera clips alone, DLO1..DLO5",
        "python benchmarks/calibrate_rods.py",
    ),
}


# ----- helpers --------------------------------------------------------------------------------------
def fmt(x, nd: int = 2, scale: float = 1.0) -> str:
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, (int, float)):
        if isinstance(x, int) and scale == 1.0:
            return f"{x:,}".replace(",", " ")
        return f"{x * scale:.{nd}f}"
    return str(x)


def table(header: list[str], rows: list[list]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return out + [""]


def get(d, *path, default=None):
    for p in path:
        if isinstance(d, dict) and p in d:
            d = d[p]
        else:
            return default
    return d


def git_last_commit(path: Path) -> str | None:
    """`<hash> (<date>)` of the last commit that changed ``path``, with a note when the working
    tree differs from it; None without git or when the file was never committed."""
    try:
        rel = str(path.resolve().relative_to(ROOT))
        log = subprocess.run(
            ["git", "log", "-1", "--format=%h (%cs)", "--", rel],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        if not log:
            return None
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", rel], cwd=ROOT, capture_output=True, text=True, timeout=10
        ).stdout.strip()
        return log + ("; the working tree's copy differs from it" if dirty else "")
    except (OSError, ValueError, subprocess.SubprocessError):
        return None


def machine_text(m) -> str:
    if m is None:
        return "not recorded"
    if isinstance(m, dict):
        return ", ".join(f"{k} {v}" for k, v in m.items() if v not in ("", None))
    return str(m)


def provenance(name: str, data, path: Path) -> list[str]:
    meta = data if isinstance(data, dict) else {}
    command = meta.get("command")
    lines = [
        f"- file: `benchmarks/results/{name}`",
        f"- command: `{command.strip()}`"
        if command
        else "- command: not recorded" + (f" (written by `{KNOWN[name][1]}`)" if name in KNOWN else ""),
        f"- commit: `{meta['commit']}`"
        if meta.get("commit")
        else "- commit: not recorded"
        + (f" (file last changed in git commit {c})" if (c := git_last_commit(path)) else ""),
        f"- machine: {machine_text(meta.get('machine'))}",
    ]
    return lines + [""]


# ----- one renderer per known file --------------------------------------------------------------------
def render_accuracy(d: dict) -> list[str]:
    rows = []
    for rod, r in d.items():
        if not isinstance(r, dict) or "l1_m" not in r:
            continue
        paper = r.get("paper_deform_cm")
        l1 = r["l1_m"] * 100
        hz = r.get("l1_by_horizon_m", {})
        rows.append(
            [
                rod,
                f"{r.get('recordings', '-')} {str(r.get('split', '')).split(' ')[0]}",
                f"{l1:.3f}",
                fmt(paper),
                f"{l1 / paper:.2f}" if paper else "-",
                fmt(r.get("paper_der_cm")),
                fmt(r.get("mean_vertex_dist_m"), 3, 100),
                " / ".join(fmt(hz.get(h), 2, 100) for h in ("1", "10", "100", "500")),
                f"{fmt(r.get('step_ms_p50'))} / {fmt(r.get('step_ms_p99'))}",
            ]
        )
    out = [
        "L1 = mean |prediction - truth| over the predicted steps, all vertices and x, y, z (the paper's metric). "
        "Split `train` = the held-out fifth of the train recordings (DLO4 and DLO5 have no eval split).",
        "",
    ]
    return out + table(
        [
            "rod",
            "recordings",
            "L1 [cm]",
            "paper DEFORM [cm]",
            "ratio",
            "paper DER [cm]",
            "interior vertex dist [cm]",
            "L1 at 1/10/100/500 steps [cm]",
            "step p50 / p99 [ms]",
        ],
        rows,
    )


def render_speed(d: dict) -> list[str]:
    rows = []
    for key, label in (
        ("single_rollout_1_thread", "single rollout, eager step, 1 thread"),
        ("single_rollout_compiled_1_thread", "single rollout, compiled step, 1 thread"),
        ("single_rollout_theseus_theta_1_thread", "single rollout, Theseus twist solver, 1 thread"),
    ):
        r = d.get(key)
        if isinstance(r, dict):
            rows.append(
                [
                    label,
                    f"p50 {fmt(r.get('p50_ms'))} ms, p99 {fmt(r.get('p99_ms'))} ms ({r.get('steps', '-')} steps)",
                ]
            )
    for key, label in (
        ("throughput_rod_steps_per_s_2_threads", "batched throughput, eager, 2 threads [rod-steps/s]"),
        (
            "throughput_compiled_rod_steps_per_s_2_threads",
            "batched throughput, compiled, 2 threads [rod-steps/s]",
        ),
    ):
        r = d.get(key)
        if isinstance(r, dict):
            rows.append([label, ", ".join(f"B={b}: {v:,.0f}" for b, v in r.items())])
    vs = d.get("vertex_scaling_1_thread")
    if isinstance(vs, dict):
        rows.append(
            [
                "step against vertex count, eager, 1 thread (p50 / p99 ms)",
                ", ".join(f"n={n}: {fmt(r.get('p50_ms'))} / {fmt(r.get('p99_ms'))}" for n, r in vs.items()),
            ]
        )
    tr = d.get("training_iteration_2_threads")
    if isinstance(tr, dict):
        rows.append(
            [
                f"training iteration (batch {tr.get('batch')}, horizon {tr.get('horizon')}, forward + backward), 2 threads",
                f"{fmt(tr.get('seconds_p50'))} s (median of {tr.get('iterations')})",
            ]
        )
    th = d.get("training_theta_solver_2_threads")
    if isinstance(th, dict):
        rows.append(
            [
                f"training, Theseus over Newton twist solver (batch {th.get('batch')}, horizon {th.get('horizon')})",
                f"{fmt(th.get('theseus_over_newton'), 1)}x",
            ]
        )
    out = [
        f"Rod {d.get('rod', '-')} ({d.get('n_vertices', '-')} vertices); compiled step active: "
        f"{fmt(d.get('compiled_active'))}; compiled steps redone eagerly: {fmt(d.get('single_rollout_compiled_redone'))}.",
        "",
    ]
    return out + table(["measure", "result"], rows)


def render_perception(d: dict) -> list[str]:
    cells: dict[tuple, dict] = {}
    fps_all: set = set()
    for r in d.get("mean_l1_cm", []):
        cells.setdefault((r["occlusion"], r["tracker"]), {})[r["fps"]] = r["l1_cm"]
        fps_all.add(r["fps"])
    fps = sorted(fps_all)
    n = {r.get("n") for r in d.get("mean_l1_cm", [])}
    args = d.get("args", {})
    out = [
        f"L1 over 5 s [cm], mean of {'/'.join(str(x) for x in sorted(n - {None})) or '-'} recordings "
        f"({args.get('per_rod', '-')} per rod of {', '.join(args.get('rods', [])) or '-'}); columns: camera updates "
        "per second (0 = open loop). `baseline` = the same tracker with a non-physical prediction.",
        "",
    ]
    rows = [
        [f"{occ * 100:.0f} %", tr] + [fmt(c.get(f)) for f in fps]
        for (occ, tr), c in sorted(cells.items(), key=lambda kv: (kv[0][0], kv[0][1] != "deform"))
    ]
    out += table(["occlusion", "tracker"] + [f"{f} fps" for f in fps], rows)
    hid = d.get("hidden_fraction_of_free_vertices")
    if isinstance(hid, dict):
        out += [
            "Free vertices actually hidden while the occluder is present: "
            + ", ".join(f"{float(k) * 100:.0f} % setting: {v * 100:.0f} %" for k, v in hid.items())
            + ".",
            "",
        ]
    lat = d.get("latency_ms", {})
    parts = []
    for key, label in (
        ("bench_resolution", "benchmark clouds (320x288)"),
        ("full_resolution", "full-resolution clouds"),
    ):
        r = lat.get(key)
        if isinstance(r, dict):
            shape = (
                f" {r['shape'][1]}x{r['shape'][0]}"
                if isinstance(r.get("shape"), list) and len(r["shape"]) == 2
                else ""
            )
            parts.append(
                f"{label}{shape}: p50 {fmt(r.get('p50'), 1)} ms, p99 {fmt(r.get('p99'), 1)} ms ({r.get('n')} updates)"
            )
    if parts:
        out += [
            "`Tracker.correct` latency: " + "; ".join(parts) + f". Wall time {fmt(d.get('wall_s'), 1)} s.",
            "",
        ]
    return out


def _predict_row(label: str, p: dict | None) -> list:
    if not isinstance(p, dict):
        return [label] + ["-"] * 6
    return [
        label,
        fmt(p.get("p50_ms"), 1),
        fmt(p.get("p90_ms"), 1),
        fmt(p.get("max_ms"), 1),
        fmt(get(p, "worker_ms", "p50"), 1),
        fmt(p.get("steps_redone")),
        fmt(p.get("loop_deadline_misses")),
    ]


def render_service(d: dict) -> list[str]:
    out = [
        f"Tracker {d.get('tracker', '-')}, feeder {d.get('feeder', 'not recorded')}, loop step "
        f"{d.get('loop_step', '-')}, predict plans start at: {d.get('plans_start', 'not recorded')}; "
        f"predict worker warm-up {fmt(d.get('predict_warmup_s'), 1)} s. Workers: {machine_text(d.get('workers'))}.",
        "",
    ]
    lp = d.get("loop")
    if isinstance(lp, dict):
        rows = [
            ["seconds / ticks", f"{fmt(lp.get('seconds'), 0)} s / {fmt(lp.get('ticks'))}"],
            ["rate", f"{fmt(lp.get('rate_hz'), 1)} Hz"],
            ["deadline misses", f"{fmt(lp.get('deadline_misses'))} ({fmt(lp.get('deadline_miss_pct'))} %)"],
            [
                "tick-to-publish p50 / p99 / max [ms]",
                " / ".join(fmt(get(lp, "tick_to_publish_ms", k)) for k in ("p50", "p99", "max")),
            ],
            [
                "model step p50 / p99 / max [ms]",
                " / ".join(fmt(get(lp, "step_ms", k)) for k in ("p50", "p99", "max")),
            ],
            [
                "cloud fusion p50 / p99 [ms]",
                " / ".join(fmt(get(lp, "fusion_ms", k), 1) for k in ("p50", "p99")),
            ],
            ["clouds fused (per s)", f"{fmt(lp.get('clouds_fused'))} ({fmt(lp.get('clouds_per_s'), 1)})"],
            ["compiled steps redone", fmt(lp.get("compiled_steps_redone"))],
            ["dropped / rejected", f"{lp.get('dropped', {})} / {lp.get('rejected', {})}"],
        ]
        out += ["Loop (100 Hz, clouds at 30 Hz):", ""] + table(["measure", "result"], rows)
    out += ["Predict, 64 plans x 100 steps, timed at a client process from request to reply [ms]:", ""]
    out += table(
        ["condition", "p50", "p90", "max", "worker p50", "steps redone", "loop misses meanwhile"],
        [
            _predict_row("service idle", d.get("predict_64x100")),
            _predict_row("while the loop runs", d.get("predict_64x100_live")),
        ],
    )
    sk = d.get("soak")
    if isinstance(sk, dict):
        out += [
            f"Soak: {fmt(sk.get('seconds'), 0)} s, RSS of the service and its workers {fmt(sk.get('rss_start_mb'), 1)} -> "
            f"{fmt(sk.get('rss_end_mb'), 1)} MB ({fmt(sk.get('growth_pct'))} %), {fmt(sk.get('ticks'))} ticks, "
            f"{fmt(sk.get('deadline_misses_total'))} deadline misses.",
            "",
        ]
    return out


def render_baselines(d: dict) -> list[str]:
    res = d.get("results", {})
    rods = list(res)
    methods: list[str] = []
    for r in res.values():
        methods += [m for m in r if m not in methods]
    paper = d.get("paper_cm", {})
    paper_step = d.get("paper_step_ms", {})
    alias = {"der_initial": "der", "der_identified": "der"}
    rows = []
    for m in methods:
        cells = []
        for rod in rods:
            r = res[rod].get(m)
            p = get(paper, alias.get(m, m), rod)
            cells.append(
                "-" if not r else f"{r['l1_m'] * 100:.2f}" + (f" ({fmt(p)})" if p is not None else "")
            )
        steps = sorted(
            res[rod][m].get("step_ms", res[rod][m].get("step_ms_p50")) for rod in rods if m in res[rod]
        )
        med = steps[len(steps) // 2] if steps else None
        ps = paper_step.get(m)
        rows.append([m] + cells + [fmt(med) + (f" ({fmt(ps, 1)})" if ps is not None else "")])
    out = [
        "L1 [cm] on the same splits as the accuracy table (paper's Table 1 in brackets); step p50 = median over "
        "rods, batch of one, one thread.",
        "",
    ]
    return out + table(["method"] + [f"{r} L1 [cm]" for r in rods] + ["step p50 [ms]"], rows)


def render_ablations(d: dict) -> list[str]:
    rods, variants, cells, budget = [], [], {}, {}
    for r in d["rows"]:
        rods += [r["rod"]] if r["rod"] not in rods else []
        variants += [r["variant"]] if r["variant"] not in variants else []
        cells[(r["variant"], r["rod"])] = r["l1_m"] * 100
        budget.setdefault(r["variant"], set()).add((r.get("iterations"), r.get("batch")))
    rows = [
        [v]
        + [fmt(cells.get((v, rod)), 3) for rod in rods]
        + [", ".join(f"{i} x {b}" for i, b in sorted(budget[v], key=str))]
        for v in variants
    ]
    return [
        "L1 [cm] on the eval recordings; every trained variant with the same budget (iterations x batch), "
        "so the rows compare with each other, not with the accuracy table.",
        "",
    ] + table(["variant"] + rods + ["iterations x batch"], rows)


def render_diagnose(d: dict) -> list[str]:
    out = []
    if d.get("simulator"):
        out += [f"Planted by: {d['simulator']} simulator.", ""]
    if d.get("budget"):
        out += [f"Budget: {d['budget']}.", ""]
    summary = d.get("summary", {})
    for rule, title in (
        ("tool", "rule of the tool"),
        ("calibrated", "calibrated rule"),
        ("as_run", "rule the rows were run with"),
    ):
        s = summary.get(rule)
        if not isinstance(s, dict):
            continue
        planted = {k: v for k, v in s.items() if k != "none"}
        ok = sum(v.get("named_correctly", 0) for v in planted.values())
        tot = sum(v.get("runs", 0) for v in planted.values())
        ctl = s.get("none", {})
        out += [
            f"**{title.capitalize()}**: planted effects named first {ok}/{tot}"
            + (f" ({100 * ok / tot:.0f} %)" if tot else "")
            + f"; controls named `none` {ctl.get('named_correctly', '-')}/{ctl.get('runs', '-')}.",
            "",
        ]
        rows = [
            [
                k,
                v.get("runs"),
                f"{v.get('named_correctly')}/{v.get('runs')}",
                fmt(v.get("nominal_check_cm"), 3),
                fmt(v.get("final_check_cm"), 3),
                fmt(v.get("oracle_check_cm"), 3),
                fmt(v.get("gap_closed_oracle_median"), 0, 100),
            ]
            for k, v in s.items()
        ]
        out += table(
            [
                "planted effect",
                "runs",
                "named first",
                "check L1 nominal [cm]",
                "after [cm]",
                "oracle [cm]",
                "gap closed vs oracle, median [%]",
            ],
            rows,
        )
    real = d.get("real")
    if isinstance(real, list) and real:
        rows = [
            [
                r.get("rod", r.get("key")),
                ", ".join(get(r, "as_run", "selected", default=r.get("selected")) or []) or "none",
                fmt(r.get("nominal_check_l1_m"), 3, 100),
                fmt(r.get("final_check_l1_m"), 3, 100),
                fmt(r.get("seconds"), 0),
            ]
            for r in real
        ]
        out += ["Real recordings against plain DER:", ""]
        out += table(["rod", "selected", "check L1 before [cm]", "after [cm]", "seconds"], rows)
    if not out:
        out = render_generic(d)
    return out


def render_generic(d) -> list[str]:
    if isinstance(d, list):
        return [
            f"A list of {len(d)} rows"
            + (f" with fields {', '.join(d[0])}." if d and isinstance(d[0], dict) else "."),
            "",
        ]
    if not isinstance(d, dict):
        return [f"Value: {d}", ""]
    rows = [
        [k, fmt(v, 4) if not isinstance(v, (dict, list)) else f"({type(v).__name__} of {len(v)})"]
        for k, v in d.items()
        if k not in ("command", "commit", "machine")
    ]
    return ["Top-level fields (this script has no table for this file):", ""] + table(
        ["field", "value"], rows
    )


def render_real_terms(d: dict) -> list[str]:
    b = d.get("budget", {})
    out = [
        f"Fine-tuning from the shipped model, {b.get('iterations')} iterations of {b.get('batch')} windows x "
        f"{b.get('horizon')} steps, with and without each term the discrepancy tool named; L1 [cm], "
        "the paper's metric (500 steps).",
        "",
    ]
    rows = []
    for r in d.get("rows", []):

        def cm(arm, key, r=r):
            return fmt(get(r, arm, key), 3, 100.0)

        rows.append(
            [
                r.get("rod"),
                r.get("term") or "none",
                r.get("kind", "-"),
                cm("shipped", "val_l1_m"),
                cm("with", "val_l1_m"),
                cm("without", "val_l1_m"),
                cm("shipped", "eval_l1_m"),
                cm("with", "eval_l1_m"),
                cm("without", "eval_l1_m"),
                r.get("validation_picks", "shipped"),
            ]
        )
    header = ["rod", "term", "in DEFORM", "val shipped", "val with", "val without", "test shipped"]
    header += ["test with", "test without", "validation picks"]
    return out + table(header, rows)


def render_startup(d: dict) -> list[str]:
    out = [
        "`deform-service run` in a fresh process, a feeder at 100 Hz (poses) and 30 Hz (clouds); ready ="
        " status says predict_ready and step_ready. Cold: empty compile caches; warm: the same caches again."
        " Medians over the runs.",
        "",
    ]
    rows = []
    for kind, v in d.get("summary", {}).items():
        rows.append(
            [
                kind,
                fmt(v.get("ready_s"), 1),
                fmt(v.get("predict_ready_s"), 1),
                fmt(v.get("step_ready_s"), 1),
                fmt(v.get("warmup_miss_pct"), 2),
                fmt(v.get("warmup_vertex_gap_max_ms"), 1),
                fmt(v.get("first_predict_64x100_ms"), 1),
            ]
        )
    header = ["start", "ready [s]", "predict ready [s]", "step ready [s]", "loop misses while warming [%]"]
    header += ["longest vertex gap [ms]", "first predict 64x100 [ms]"]
    return out + table(header, rows)


def render_roofline(d: dict) -> list[str]:
    phases = d.get("ops_per_rod_step_by_phase", {})
    total = d.get("ops_per_rod_step") or 1
    out = [
        f"One branch-free step of {d.get('batch')} rods ({d.get('rod')}, {d.get('n_vertices')} vertices),"
        f" counted op by op: {d.get('ops_per_rod_step')} operations per rod-step;"
        f" eager traffic {d.get('eager_bytes_per_rod_step')} B per rod-step (state alone:"
        f" {d.get('state_bytes_per_rod_step')} B). Peaks measured in the same run (2 threads):"
        f" {get(d, 'peaks_2_threads', 'gemm_gflops')} GFLOP/s float64 GEMM,"
        f" {get(d, 'peaks_2_threads', 'copy_gb_per_s')} GB/s copy.",
        "",
    ]
    out += table(
        ["phase", "operations per rod-step", "share"],
        [[p, v, f"{100 * v / total:.1f} %"] for p, v in phases.items()],
    )
    rows = []
    rates = {
        "eager": ("eager_here", "float64"),
        "compiled": ("compiled_speed_json", "float64"),
        "predict_float32": ("predict_float32_batched_throughput_json", "float32"),
    }
    for label, (key, dtype) in rates.items():
        a = d.get(f"achieved_{label}")
        if a:
            rate = get(d, "rates_rod_steps_per_s", key)
            frac = f"{100 * a.get('fraction_of_gemm_peak', 0):.1f} %"
            rows.append([label, rate, a.get("gops"), f"{frac} ({dtype})"])
    out += [""] + table(["step", "rod-steps/s", "achieved Gop/s", "of the GEMM peak"], rows)
    prof = d.get("profile_predict_float32")
    if prof:
        out += [
            "",
            f"Where predict's float32 step spends its time (torch.compile, inductor kernel profiling;"
            f" {prof.get('rod_steps_per_s_torch_compile')} rod-steps/s while profiled,"
            f" {prof.get('ms_per_step_in_kernels_and_products')} ms per step in kernels and library calls):",
            "",
        ]
        out += table(
            ["kernel or call", "kind", "ms per step", "calls per step"],
            [[f"`{t['name']}`", t["kind"], t["ms_per_step"], t["calls"]] for t in prof.get("top", [])],
        )
    return out


def render_batched_throughput(d: dict) -> list[str]:
    rates, ratios = d.get("rod_steps_per_s", {}), d.get("ratio_to_compiled_checked", {})
    rows = [
        [name, r.get("median"), ratios.get(name), min(r.get("all", [0])), max(r.get("all", [0]))]
        for name, r in rates.items()
    ]
    return [
        f"B = {d.get('batch')} rods, {d.get('steps')} steps per timing, repeats interleaved; medians.",
        "",
    ] + table(["step", "rod-steps/s", "ratio to compiled_checked", "min", "max"], rows)


def render_ab_commits(d: dict) -> list[str]:
    rounds = d.get("rounds", {})

    def med(name, key, sub=None):
        vals = [r[key][sub] if sub else r[key] for r in rounds.get(name, [])]
        return statistics.median(vals) if vals else None

    rows = [
        ["predict's step, 1024 rods, float32, 1 thread [rod-steps/s]", "predict_step_rod_steps_per_s", None],
        ["predict's rollout, 512 plans x 100 steps, 1 thread, median [ms]", "rollout_512_median_ms", None],
        ["the 100 Hz loop's step, one rod, p50 [ms]", "loop_step", "p50_ms"],
        ["the 100 Hz loop's step, one rod, p99 [ms]", "loop_step", "p99_ms"],
    ]
    body = [[label, fmt(med("base", key, sub), 3), fmt(med("head", key, sub), 3)] for label, key, sub in rows]
    speed = d.get("speedup", {})
    return [
        f"Processes of both checkouts alternated, {len(rounds.get('head', []))} rounds; medians over rounds. "
        f"Base: {d.get('base')}. Speed-up (base time / today's): step {fmt(speed.get('predict_step_ratio'))}x, "
        f"rollout {fmt(speed.get('rollout_512_ratio'))}x, loop step {fmt(speed.get('loop_step_p50_ratio'))}x.",
        "",
    ] + table(["measure", "base", "today"], body)


def render_predict_planning(d: dict) -> list[str]:
    targets = d.get("targets_p50_ms", {})
    compared = d.get("compared", {})
    header = ["request", "p50 [ms]", "p90 [ms]", "max [ms]", "target p50 [ms]"]
    header += [f"p50 with {name} [ms] (ratio)" for name in compared]
    rows = []
    for label, r in d.get("requests", {}).items():
        row = [label, r.get("p50_ms"), r.get("p90_ms"), r.get("max_ms"), targets.get(label)]
        for c in compared.values():
            other = c.get("requests", {}).get(label, {})
            row.append(f"{other.get('p50_ms')} ({c.get('p50_ratio_to_headline', {}).get(label)})")
        rows.append(row)
    loop = d.get("loop", {})
    out = [
        f"Default configuration ({d.get('rounds')} services, interleaved with each variant);"
        f" loop meanwhile: {loop.get('miss_pct')} % of {loop.get('ticks')} ticks missed,"
        f" tick-to-publish p99 {get(d, 'loop', 'tick_to_publish_ms', 'p99')} ms."
        + (
            f" Rod-steps the one-graph step left unconverged: {d['redone_pct_of_rod_steps']} %."
            if "redone_pct_of_rod_steps" in d
            else ""
        ),
        "",
    ]
    return out + table(header, rows)


def render_float32(d: dict) -> list[str]:
    names = [
        ("float32", "eager float32"),
        ("predict_float64", "predict's step"),
        ("predict_float32", "predict's step, float32"),
        ("predict_float32_bf16_network", "predict's step, float32, bfloat16 network"),
    ]
    names = [(k, label) for k, label in names if any(f"{k}_l1_cm" in r for r in d.get("rods", {}).values())]
    rows = []
    for rod, r in d.get("rods", {}).items():
        row = [rod, r.get("recordings"), fmt(r.get("float64_l1_cm"), 4)]
        for k, _ in names:
            gap = r.get(f"{k}_l1_difference_mm", r.get("l1_difference_mm") if k == "float32" else None)
            row += [fmt(r.get(f"{k}_l1_cm"), 4), "" if gap is None else f"{gap:.1e}"]
        rows.append(row)
    header = ["rod", "eval recordings", "eager float64 L1 [cm]"]
    for _, label in names:
        header += [f"{label} L1 [cm]", "|difference| [mm]"]
    return [
        "The paper's metric, 500 steps, same model; differences to the eager float64 step; bound 0.1 mm.",
        "",
    ] + table(header, rows)


def render_tracking_peers(d: dict) -> list[str]:
    methods = d.get("methods", [])
    args = d.get("args", {})
    summ = d.get("summary", {})
    label = d.get("labels", {})  # older stored runs lack them: the variant's key is shown
    out = [
        "Mean two-way distance between tracked nodes and the true rope [mm] (TrackDLO's metric), per camera "
        f"frame, mean over frames and recordings ({args.get('per_rod', '-')} per rod of "
        f"{', '.join(args.get('rods', [])) or '-'}); every method on the same rendered clouds (30 fps unless "
        "said), started from the true nodes. Ratios: against the same motion with the right model and no "
        "contact (target for ours: at most 1.5x).",
        "",
    ]
    rows = []
    for v, cells in summ.items():
        n = max((c.get("n_recordings", 0) for c in cells.values()), default=0)
        rows.append([label.get(v, v), n] + [fmt(get(cells, m, "mean_error_mm"), 1) for m in methods])
    for v, cells in d.get("ratios", {}).items():
        rows.append(
            [f"{label.get(v, v)}: ratio", "-"]
            + [f"{fmt(get(cells, m, 'ratio'), 2)}x" if m in cells else "-" for m in methods]
        )
    black = summ.get("blackout", {})
    if black:
        rows.append(
            ["recovery after the blackout: mean s (within 0.5 s)", "-"]
            + [
                f"{fmt(get(black, m, 'recovery_s', 'mean'), 2)} ({get(black, m, 'recovery_s', 'within_target')}/"
                f"{get(black, m, 'recovery_s', 'n')})"
                if m in black
                else "-"
                for m in methods
            ]
        )
    out += table(["scenario", "n"] + methods, rows)
    timing = d.get("timing_ms", {})
    if timing:
        out += table(
            ["method", "update p50 [ms]", "update p99 [ms]", "clouds", "model step p50 [ms]"],
            [
                [
                    m,
                    fmt(get(t, "update", "p50"), 1),
                    fmt(get(t, "update", "p99"), 1),
                    get(t, "update", "n"),
                    fmt(get(t, "step", "p50"), 2),
                ]
                for m, t in timing.items()
            ],
        )
    out += [
        "Update: `Tracker.correct` for ours; for the peers our segmentation plus their `update`. "
        f"Wall time {fmt(d.get('wall_s'), 0)} s. Plot: `{d.get('plot', '-')}`; detail: `tracking_peers.md`.",
        "",
    ]
    return out


def render_calibrate_rods(d: dict) -> list[str]:
    models = ("calibrated", "shipped", "generic")

    def three(cell, name, nd, scale=1.0):
        return " / ".join(fmt(get(cell, name, m), nd, scale) for m in models)

    rows = []
    for cell in d.get("summary", {}).values():
        targets = cell.get("targets", {})
        missed = [k for k, v in targets.items() if not v]
        rows.append(
            [
                cell.get("rod"),
                fmt(cell.get("seconds"), 0),
                three(cell, "open_loop", 2),
                fmt(cell.get("paper_deform_cm"), 2),
                three(cell, "tracking_mm", 1),
                three(cell, "prediction_1s_mm", 1),
                fmt(get(cell, "calibrate_s"), 1, 1 / 60),
                f"{len(targets) - len(missed)}/{len(targets)}"
                + (f" (missed: {'; '.join(missed)})" if missed else ""),
            ]
        )
    return (
        [
            "Calibrated from rendered camera clips of the rod's training motions alone (one camera for the "
            "session, depth noise, dropouts, an occluder in every other clip), `deform calibrate` with its "
            "defaults; scored on the held-out motions (eval; DLO4, DLO5: the held-out fifth of train) beside "
            "the shipped mocap-trained model and the generic DER of the same length and mass. Each cell: "
            "calibrated / shipped / generic. Open loop: the paper's 500-step metric [cm]; tracking: two-way "
            f"distance through a quarter-rope occlusion [mm] ({get(d, 'args', 'tracked')} motions per rod); "
            "1 s: mean marker distance of the prediction from the tracked state, 1 s ahead [mm].",
            "",
        ]
        + table(
            [
                "rod",
                "clips [s]",
                "open loop [cm]",
                "paper DEFORM [cm]",
                "tracking [mm]",
                "1 s prediction [mm]",
                "calibrate [min]",
                "targets met",
            ],
            rows,
        )
        + [f"Wall time {fmt(d.get('wall_s'), 0)} s; detail: `calibrate_rods.md`.", ""]
    )


RENDER = {
    "calibrate_rods.json": render_calibrate_rods,
    "service_startup.json": render_startup,
    "roofline.json": render_roofline,
    "float32_accuracy.json": render_float32,
    "batched_throughput.json": render_batched_throughput,
    "predict_planning.json": render_predict_planning,
    "ab_commits.json": render_ab_commits,
    "tracking_peers.json": render_tracking_peers,
    "accuracy.json": render_accuracy,
    "speed.json": render_speed,
    "perception.json": render_perception,
    "service.json": render_service,
    "service_soak.json": render_service,
    "baselines.json": render_baselines,
    "ablations.json": render_ablations,
    "diagnose.json": render_diagnose,
    "real_terms.json": render_real_terms,
    "real_terms.v6.json": render_real_terms,
    "real_terms.dlo1.json": render_real_terms,
}


def renderer(name: str):
    if name in RENDER:
        return RENDER[name]
    if name.startswith("diagnose.") and name.endswith(".json"):
        return render_diagnose
    for stem, render in (
        ("tracking_peers.", render_tracking_peers),
        ("calibrate_rods.", render_calibrate_rods),
    ):
        if name.startswith(stem):
            return render
    return render_generic


# ----- page ------------------------------------------------------------------------------------------
def build(results: Path) -> str:
    present = sorted(p.name for p in results.glob("*.json")) if results.is_dir() else []
    extra_diag = [n for n in present if n.startswith("diagnose.") and n not in KNOWN]
    others = [n for n in present if n not in KNOWN and n not in extra_diag]
    order = list(KNOWN) + extra_diag + others
    lines = [
        "# Results",
        "",
        "<!-- generated by scripts/make_results.py from benchmarks/results/*.json; edit those or the script, not this page -->",
        "",
        "Every number on this page is copied from a results file in `benchmarks/results/`, written by the "
        "benchmark script named in its section; regenerate the page with `make results`. Timings come from "
        "a 2-core x86_64 VM without GPU (torch CPU build) whose speed varies with the host's load; each "
        'section names the machine as the file records it. "Commit: not recorded" means the file does '
        "not say which code produced it; the git commit that last changed the file is given instead "
        "(the results were stored with, or after, the code they measure). The `.md` files beside the JSON "
        "(e.g. `diagnose.md`, per-run detail) and `docs/*.md` have more.",
        "",
    ]
    lines += ["Files: " + ", ".join(f"[{n}](#{anchor(n)})" for n in order) + ".", ""]
    for name in order:
        title = KNOWN.get(name, (f"Other results: {name}",))[0]
        if name.startswith("diagnose.") and name not in KNOWN:
            title = f"deform diagnose: {name}"
        lines += [f"## {name}", "", f"*{title}*", ""]
        path = results / name
        if not path.is_file():
            lines += [
                "Missing: no such file in `benchmarks/results/`"
                + (f" (run `{KNOWN[name][1]}`)." if name in KNOWN else "."),
                "",
            ]
            continue
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            lines += [f"Could not be read: {exc}", ""]
            continue
        lines += provenance(name, data, path)
        try:
            lines += renderer(name)(data)
        except Exception as exc:  # a results layout this script does not know yet: say so, keep going
            lines += [
                f"(The layout of this file was not understood by scripts/make_results.py: "
                f"{type(exc).__name__}: {exc}.)",
                "",
            ] + render_generic(data)
    return "\n".join(lines).rstrip() + "\n"


def anchor(name: str) -> str:
    return "".join(c for c in name.lower() if c.isalnum() or c in "-_ ").replace(" ", "-")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    text = build(args.results)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out} ({text.count(chr(10))} lines)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
