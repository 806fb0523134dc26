"""Renderers of the results page (scripts/make_results.py) for perception, tracking, calibration and
the discrepancy tool: one function per results file, the file's dict in, markdown lines out."""

from __future__ import annotations

from results_common import fmt, get, render_generic, table


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


def render_diagnose(d: dict) -> list[str]:
    out = []
    if d.get("simulator"):
        out += [f"Planted by: {d['simulator']} simulator.", ""]
    if d.get("budget"):
        out += [f"Budget: {d['budget']}.", ""]
    if d.get("run_wall_s") is not None:
        w = d.get("workers")
        how = ", ".join(f"{k} {v}" for k, v in w.items()) if isinstance(w, dict) else str(w or "-")
        out += [f"Wall time: {d['run_wall_s']:.0f} s for {d.get('datasets_run')} datasets ({how}).", ""]
    against = d.get("names_against")
    if against:
        line = (
            f"Against `{against['stem']}` ({against.get('commit')}), the same datasets: the first name the "
            f"same on {against.get('same_first', '-')}/{against['datasets']}, every name on "
            f"{against['same']}/{against['datasets']}"
        )
        if against.get("differ"):
            line += " (differ: " + ", ".join(f"`{x['key']}`" for x in against["differ"]) + ")"
        theirs = against.get("their_seconds_total_runs")
        if theirs and d.get("run_wall_s") and against["datasets"] == d.get("datasets_run"):
            line += (
                f"; wall time {d['run_wall_s']:.0f} s against {theirs / 2:.0f} s for theirs fitted two at a "
                f"time ({d['run_wall_s'] / (theirs / 2):.2f}x)"
            )
        out += [line + ".", ""]
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


def _pair(markers, rope, nd: int, unit: str) -> str:
    """``markers / rope`` (the rope part only where the stored run measured it)."""
    out = f"{fmt(markers, nd)}{unit}"
    return out if rope is None else f"{out} / {fmt(rope, nd)}{unit}"


def render_tracking_peers(d: dict) -> list[str]:
    methods = d.get("methods", [])
    args = d.get("args", {})
    summ = d.get("summary", {})
    label = d.get("labels", {})  # older stored runs lack them: the variant's key is shown
    out = [
        "Mean two-way distance between tracked nodes and the true rope [mm] (TrackDLO's metric), per camera "
        f"frame, mean over frames and recordings ({args.get('per_rod', '-')} per rod of "
        f"{', '.join(args.get('rods', [])) or '-'}); every method on the same rendered clouds (30 fps unless "
        "said), started from the true nodes; rows named after DLO3 on its recordings only. Each cell: against the "
        "marker polyline / against the rope as rendered (the curve through the markers the clouds show; against "
        "the markers, a model whose vertices are the markers scores 0 for the true shape, no other node layout "
        "can). Ratios: against the same motion with the right model and no contact (target for ours: at most 1.5x).",
        "",
    ]
    rows = []
    for v, cells in summ.items():
        n = max((c.get("n_recordings", 0) for c in cells.values()), default=0)
        rows.append(
            [label.get(v, v), n]
            + [
                _pair(get(cells, m, "mean_error_mm"), get(cells, m, "mean_rope_error_mm"), 1, "")
                for m in methods
            ]
        )
    for v, cells in d.get("ratios", {}).items():
        rows.append(
            [f"{label.get(v, v)}: ratio", "-"]
            + [
                _pair(get(cells, m, "ratio"), get(cells, m, "ratio_rope"), 2, "x") if m in cells else "-"
                for m in methods
            ]
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
    floor = get(summ, "wrong_model", "ours", "camera_floor_mm")
    if floor is not None:
        out += [
            f"The wrong model's floor: its vertices laid exactly on the rope the camera sees score {fmt(floor, 1)} mm "
            f"(on the marker polyline {fmt(get(summ, 'wrong_model', 'ours', 'floor_mm'), 1)} mm).",
            "",
        ]
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
                three(cell, "tracking_rope_mm", 1)
                if get(cell, "tracking_rope_mm", "calibrated") is not None
                else "-",
                three(cell, "tracking_hidden_mm", 1)
                if get(cell, "tracking_hidden_mm", "calibrated") is not None
                else "-",
                three(cell, "prediction_1s_mm", 1),
                fmt(get(cell, "calibrate_s"), 1, 1 / 60),
                f"{len(targets) - len(missed)}/{len(targets)}"
                + (f" (missed: {'; '.join(missed)})" if missed else ""),
            ]
        )
    setup = get(d, "args", "setup") or "session"
    lab = (
        []
        if setup == "session"
        else [
            f"Filmed as the lab `{setup}` films (`benchmarks/calibration/setups.py`: camera place and rate, "
            "rope colour given by its range, noise, occluders), the held-out motions too.",
            "",
        ]
    )
    return (
        lab
        + [
            "Calibrated from rendered camera clips of the rod's training motions alone (one camera for the "
            f"session, depth noise, dropouts, an occluder in {'every other clip' if setup == 'session' else 'some clips'}), "
            "`deform calibrate` with its "
            "defaults; scored on the held-out motions (eval; DLO4, DLO5: the held-out fifth of train) beside "
            "the shipped mocap-trained model and the generic DER of the same length and mass. Each cell: "
            "calibrated / shipped / generic. Open loop: the paper's 500-step metric [cm]; tracking: two-way "
            f"distance through a quarter-rope occlusion [mm] ({get(d, 'args', 'tracked')} motions per rod), "
            "against the marker polyline and (rope) against the rope as rendered, on which the tracking targets "
            "are judged (against the markers only the shipped model, whose vertices are the markers, can score 0); "
            "hidden: the markers the occluder hides, their distance to the curve through the estimate [mm]; "
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
                "tracking, rope [mm]",
                "hidden part [mm]",
                "1 s prediction [mm]",
                "calibrate [min]",
                "targets met",
            ],
            rows,
        )
        + [f"Wall time {fmt(d.get('wall_s'), 0)} s; detail: `calibrate_rods.md`.", ""]
        + (
            [
                f"Scored again (not calibrated again): the stored calibrations of code {', '.join(rescored)}.",
                "",
            ]
            if (rescored := sorted({r["rescored_from"] for r in d.get("rows", []) if r.get("rescored_from")}))
            else []
        )
    )


def render_diagnose_ab(d: dict) -> list[str]:
    s = d.get("summary", {})
    rows = [
        [
            name,
            fmt(r.get("base_s"), 0),
            fmt(r.get("head_s"), 0),
            f"{fmt(r.get('speedup'))}x",
            ", ".join(r.get("selected") or []) or "none",
            "yes" if r.get("same_names") else "no",
            "-" if r.get("max_improvement_difference") is None else f"{r['max_improvement_difference']:.1e}",
        ]
        for name, r in s.get("datasets", {}).items()
    ]
    return [
        f"One PyElastica planted dataset per row (`{d.get('planted')}`), simulated once and diagnosed by "
        f"both checkouts, one thread each, processes alternated. Base: {d.get('base')}. Speed-up over all "
        f"rows (base time / today's): {fmt(s.get('speedup'))}x.",
        "",
    ] + table(
        ["dataset", "base [s]", "today [s]", "speed-up", "named", "same names", "largest score difference"],
        rows,
    )
