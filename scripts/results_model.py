"""Renderers of the results page (scripts/make_results.py) for the model, its speed and the service:
one function per results file, the file's dict in, markdown lines out."""

from __future__ import annotations

import statistics

from results_common import fmt, get, machine_text, table


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


def render_service_timing(d: dict) -> list[str]:
    """The service's tracking error with late clouds and bursty poses, per mode and camera latency
    (``service_timing.py``: simulated clock; ``service_latency.py``: the live service)."""
    modes = d.get("modes") or {}
    out = [
        f"Recording {d.get('recording', '-')}, played back and forth at 100 Hz, clouds at 30 Hz. Tracking "
        "error: two-way distance of the estimate to the rope as rendered at the time of the poses it "
        "stepped to [mm], mean / p90. Camera latency: from a cloud's stamp to its arrival; transport "
        "and decoding come on top. Ratio: the default over the service before, means. In brackets, "
        "where recorded: the rope's redetections from the cloud alone over the run, start included.",
        "",
    ]
    latencies = list(next(iter(modes.values()), {}))

    def cell(m: dict, key: str) -> str:
        text = f"{fmt(get(m, key, 'error_mm'), 2)} / {fmt(get(m, key, 'error_p90_mm'), 2)}"
        redetected = (get(m, key, "rope") or {}).get("redetected")
        return text if redetected is None else f"{text} ({redetected})"

    rows = [
        [f"{key} ms"]
        + [cell(m, key) for m in modes.values()]
        + [fmt(get(d, "ratio_default_over_before", key), 2)]
        for key in latencies
    ]
    return out + table(["camera latency", *modes, "ratio"], rows)


def render_service_latency(d: dict) -> list[str]:
    """The live service (``service_latency.py``): per mode and camera latency, the tracking error of
    each service start and the rope's redetections, which the episodes of docs/service.md showed."""
    out = [
        f"Recording {d.get('recording', '-')}, played back and forth by a feeder process over Zenoh on "
        f"loopback, clouds at {fmt(d.get('fps'), 0)} Hz; {d.get('repeats', '-')} service starts per mode, "
        f"{fmt(d.get('run_s'), 0)} s per camera latency (the latencies one after another in each start). "
        "Tracking error: two-way distance of each published estimate to the rope as rendered at the "
        "time of its poses [mm], after the first 3 s. Redetections: the rope found again from the "
        "cloud alone, counted from the start (the status after each latency's run).",
        "",
    ]
    rows = []
    for mode, by_latency in (d.get("modes") or {}).items():
        for key, row in by_latency.items():
            runs = row.get("runs") or []
            errors = [r.get("error_mm") for r in runs if r.get("error_mm") is not None]
            redetected = [(r.get("rope") or {}).get("redetected") for r in runs]
            rows.append(
                [
                    mode,
                    f"{key} ms",
                    f"{fmt(row.get('error_mm'), 2)} / {fmt(row.get('error_p90_mm'), 2)}",
                    f"{fmt(min(errors), 2)}-{fmt(max(errors), 2)}" if errors else "-",
                    ", ".join("-" if n is None else str(n) for n in redetected) or "-",
                ]
            )
    return out + table(
        ["mode", "camera latency", "error mean / p90", "per start, range", "redetections per start"], rows
    )


def render_bending_stability(d: dict) -> list[str]:
    """Ropes bent and held (``bending_stability.py``): at rest or ringing, explicit and implicit
    bending and the scheme the model gets, and the step's cost beside the explicit one's in the
    same run."""
    out = [
        "Each rope (12 vertices, straight at first) has its grippers brought 30 % of its length closer "
        "over 0.5 s and held for 2.5 s: top vertex speed over the last 0.5 s [m/s] (a soft rope still "
        "swings slowly, up to 0.2 m/s; a ringing one keeps metres a second). Step ratio: the held rope's "
        "stiffest bending mode's turn per 10 ms frame (`omega_max dt`). Explicit and implicit: one step a "
        "frame. As stepped: the scheme in the model file (shipped models) or the one a model whose "
        "stiffness is chosen gets (implicit above a ratio of 1, in substeps above `IMPLICIT_RATIO_MAX`).",
        "",
    ]

    def scheme(r: dict) -> str:
        if not r.get("chosen_implicit"):
            return "explicit"
        n = r.get("chosen_substeps", 1)
        return "implicit" + (f", {n} substeps" if n > 1 else "")

    rows = [
        [
            r.get("rope"),
            fmt(r.get("step_ratio"), 2),
            fmt(r.get("explicit_m_per_s"), 3),
            fmt(r.get("implicit_m_per_s"), 3),
            fmt(r.get("chosen_m_per_s"), 3),
            scheme(r),
        ]
        for r in d.get("rows") or []
    ]
    out += table(
        ["rope", "step ratio", "explicit [m/s]", "implicit [m/s]", "as stepped [m/s]", "scheme"], rows
    )
    cost = d.get("step_cost") or {}

    def ms(key: str) -> str:
        return f"{fmt(get(cost, key, 'p50_ms'), 3)} / {fmt(get(cost, key, 'p99_ms'), 3)}"

    if cost:
        out += [
            "One frame of a 1 m, 50 g rope with the residual network, median / p99 [ms]: eager "
            f"{ms('eager_explicit')} explicit, {ms('eager_implicit')} implicit "
            f"({fmt(cost.get('eager_ratio_p50'), 2)}x), {ms('eager_substeps2')} in two implicit substeps "
            f"({fmt(cost.get('eager_substeps2_ratio_p50'), 2)}x); compiled as the service runs it "
            f"{ms('compiled_explicit')}, {ms('compiled_implicit')} ({fmt(cost.get('compiled_ratio_p50'), 2)}x) "
            f"and {ms('compiled_substeps2')} ({fmt(cost.get('compiled_substeps2_ratio_p50'), 2)}x).",
            "",
        ]
    return out


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
    measured = rounds.get("head", [{}])[0] if rounds.get("head") else {}

    def med(name, *keys):
        vals = []
        for r in rounds.get(name, []):
            for k in keys:
                r = r[k]
            vals.append(r)
        return statistics.median(vals) if vals else None

    rows = [
        ["predict's step, 1024 rods, float32, 1 thread [rod-steps/s]", ("predict_step_rod_steps_per_s",)],
        ["predict's rollout, 512 plans x 100 steps, 1 thread, median [ms]", ("rollout_512_median_ms",)],
        ["the 100 Hz loop's step, one rod, p50 [ms]", ("loop_step", "p50_ms")],
        ["the 100 Hz loop's step, one rod, p99 [ms]", ("loop_step", "p99_ms")],
        ["a correction (reposition) of the eager one-rod model, p50 [ms]", ("reposition", "correct_p50_ms")],
        ["the eager one-rod model's step among corrections, p50 [ms]", ("reposition", "step_p50_ms")],
        ["the tracker's camera update, p50 [ms]", ("tracker", "update", "p50")],
        ["the tracker's camera update, p99 [ms]", ("tracker", "update", "p99")],
        ["the tracker's model step, p50 [ms]", ("tracker", "step", "p50")],
        ["the tracker's model step, p99 [ms]", ("tracker", "step", "p99")],
    ]
    body = [
        [label, fmt(med("base", *keys), 3), fmt(med("head", *keys), 3)]
        for label, keys in rows
        if keys[0] in measured
    ]
    speed = d.get("speedup", {})
    ratios = ", ".join(f"{key.removesuffix('_ratio')} {fmt(value)}x" for key, value in speed.items())
    return [
        f"Processes of both checkouts alternated, {len(rounds.get('head', []))} rounds; medians over rounds. "
        f"Base: {d.get('base')}. Speed-up (base time / today's): {ratios}.",
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
