"""The summary of the stored per-recording rows: the JSON's fields, the markdown table and the plots."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.tracking.scenarios import REFERENCE, VARIANTS

ORDER = [v for vs in VARIANTS.values() for v in vs]
LABEL = {
    "occ0": "no occlusion",
    "occ25": "25 % occluded",
    "occ50": "50 % occluded",
    "blackout": "rope hidden 1 s",
    "fastest": "fastest motions",
    "fps10": "clouds at 10 Hz",
    "sensor": "colour 2 px off the depth, mixed edge pixels",
    "far": "camera 1.6 m away, 35 degrees off square, noisier, 15 Hz",
    "table": "on a table (unmodelled)",
    "post": "caught on a post (unmodelled)",
    "nocontact": "same motion, no contact",
    "wrong_model": "DLO3 with DLO1's model",
    "right_model": "DLO3 with DLO3's model",
    "long_model": "DLO3, its model's rest length 6 % long",
    "short_model": "DLO3, its model's rest length 6 % short",
    "generic_model": "generic DER (length and mass only)",
    "shipped_model": "the rod's shipped model",
}
RECOVERY_TARGET_S = 0.5
RATIO_TARGET = 1.5
TARGETED = ("table", "post", "wrong_model")  # the ratios the target applies to (generic: measured only)


def _pct(values) -> dict:
    v = np.asarray(values, dtype=np.float64)
    if not len(v):
        return dict(p50=None, p99=None, n=0)
    return dict(
        p50=round(float(np.percentile(v, 50)), 3), p99=round(float(np.percentile(v, 99)), 3), n=len(v)
    )


def cases_by_variant(rows: list[dict]) -> dict:
    """``{variant: [(row, case)]}`` over the stored rows."""
    out: dict = {}
    for row in rows:
        for case in row["cases"]:
            out.setdefault(case["variant"], []).append((row, case))
    return out


def summarize(rows: list[dict], methods: list[str]) -> dict:
    """The summary fields of the JSON: per variant and method the mean error, update times, failures
    and (blackout) recovery; ratios to the references; error series averaged over recordings."""
    by = cases_by_variant(rows)
    variants = [v for v in ORDER if v in by] + [v for v in by if v not in ORDER]
    summary, series = {}, {}
    for v in variants:
        cs = by[v]
        summary[v] = {}
        series[v] = {}
        for m in methods:
            got = [(r, c["methods"][m], c) for r, c in cs if m in c["methods"]]
            if not got:
                continue
            means = [g["mean_error_mm"] for _, g, _ in got if g["mean_error_mm"] is not None]
            rope = [g.get("mean_rope_error_mm") for _, g, _ in got if g.get("mean_rope_error_mm") is not None]
            entry = dict(
                mean_error_mm=round(float(np.mean(means)), 3) if means else None,
                mean_rope_error_mm=round(float(np.mean(rope)), 3) if rope else None,
                n_recordings=len(got),
                per_recording_mm={f"{r['rod']}.{r['recording']}": g["mean_error_mm"] for r, g, _ in got},
                per_recording_rope_mm={
                    f"{r['rod']}.{r['recording']}": g.get("mean_rope_error_mm") for r, g, _ in got
                },
                update_ms=_pct([t for _, g, _ in got for t in g["update_ms_all"]]),
                failures=int(sum(g["failures"] for _, g, _ in got)),
            )
            for key in ("floor_mm", "camera_floor_mm"):
                floors = [g[key] for _, g, _ in got if key in g]
                if floors:
                    entry[key] = round(float(np.mean(floors)), 3)
            steps = [t for _, g, _ in got for t in g.get("step_ms_all", [])]
            if steps:
                entry["step_ms"] = _pct(steps)
            if v == "blackout":
                rec = [g.get("recovery_s") for _, g, _ in got]
                done = [x for x in rec if x is not None]
                entry["recovery_s"] = dict(
                    mean=round(float(np.mean(done)), 3) if done else None,
                    max=round(float(np.max(done)), 3) if done else None,
                    within_target=sum(x <= RECOVERY_TARGET_S for x in done),
                    never=len(rec) - len(done),
                    n=len(rec),
                    target_s=RECOVERY_TARGET_S,
                )
            summary[v][m] = entry
            length = min(len(g["errors_mm"]) for _, g, _ in got)
            if length:
                errs = np.array([g["errors_mm"][:length] for _, g, _ in got])
                series[v][m] = [round(float(x), 2) for x in errs.mean(0)]
        series[v]["times_s"] = cs[0][1]["times_s"][: min(len(c["times_s"]) for _, c in cs)]
    ratios = {}
    for v, ref in REFERENCE.items():
        if v not in summary or ref not in summary:
            continue
        ratios[v] = {}
        for m in methods:
            a, b = summary[v].get(m), summary[ref].get(m)
            if not a or not b:
                continue
            common = [k for k in a["per_recording_mm"] if k in b["per_recording_mm"]]
            if common:
                ratios[v][m] = dict(
                    ratio=_ratio_over(a["per_recording_mm"], b["per_recording_mm"], common),
                    ratio_rope=_ratio_over(
                        a.get("per_recording_rope_mm", {}), b.get("per_recording_rope_mm", {}), common
                    ),
                    reference=ref,
                    n=len(common),
                    target=RATIO_TARGET if v in TARGETED else None,
                )
    return dict(summary=summary, ratios=ratios, series=series)


def _ratio_over(a: dict, b: dict, keys: list) -> float | None:
    """mean of ``a`` over mean of ``b`` on the recordings ``keys`` (None where a value is missing)."""
    num, den = [a.get(k) for k in keys], [b.get(k) for k in keys]
    if None in num or None in den or not np.mean(den) > 0:
        return None
    return round(float(np.mean(num) / np.mean(den)), 3)


def _ratio_cell(cell: dict) -> str:
    """markers / rendered rope."""
    out = "-" if cell.get("ratio") is None else f"{cell['ratio']:.2f}x"
    return out + ("" if cell.get("ratio_rope") is None else f" / {cell['ratio_rope']:.2f}x")


def markdown(result: dict) -> str:
    """The tables of ``benchmarks/results/tracking_peers.md`` (and docs/results.md)."""
    return "\n".join(tables(result)) + "\n"


def _f(x, nd=1) -> str:
    return "-" if x is None else f"{x:.{nd}f}"


def tables(d: dict) -> list[str]:
    methods = d.get("methods", [])
    summ = d.get("summary", {})
    args = d.get("args", {})
    out = [
        "Mean two-way distance between the tracked nodes and the true rope [mm] (TrackDLO's metric: half "
        "the mean distance of the tracked nodes to the true polyline plus half the mean distance of the "
        "true polyline, 10 points an edge, to the tracked one), per camera frame, averaged over frames and "
        f"recordings ({args.get('per_rod', '-')} per rod of {', '.join(args.get('rods', []))}); "
        "every method on the same rendered clouds (30 fps unless said), started from the true nodes. "
        "The rows named after DLO3 run on its recordings only. Each cell: against the marker polyline / "
        "against the rope as rendered (the smooth curve through the markers the clouds were drawn from; "
        "against the markers a model whose vertices are the markers scores 0 for the true shape, any "
        "other node layout cannot).",
        "",
        "| scenario | n | " + " | ".join(methods) + " |",
        "|---|---:|" + "---:|" * len(methods),
    ]
    for v, cells in summ.items():
        n = max((c["n_recordings"] for c in cells.values()), default=0)
        out.append(
            f"| {LABEL.get(v, v)} | {n} | "
            + " | ".join(
                _f(cells[m]["mean_error_mm"])
                + (
                    f" / {_f(cells[m]['mean_rope_error_mm'])}"
                    if cells[m].get("mean_rope_error_mm") is not None
                    else ""
                )
                + (f" ({cells[m]['failures']} failed)" if cells[m]["failures"] else "")
                if m in cells
                else "-"
                for m in methods
            )
            + " |"
        )
    out.append("")
    if d.get("ratios"):
        out += [
            "Error against the same motion with the right model and no contact (target for ours: at most "
            f"{RATIO_TARGET}x for contact and the wrong model; the generic DER's ratio is measured, not a target):",
            "",
            "| scenario | against | " + " | ".join(methods) + " |",
            "|---|---|" + "---:|" * len(methods),
        ]
        for v, cells in d["ratios"].items():
            ref = next(iter(cells.values()))["reference"] if cells else "-"
            out.append(
                f"| {LABEL.get(v, v)} | {LABEL.get(ref, ref)} | "
                + " | ".join(_ratio_cell(cells[m]) if m in cells else "-" for m in methods)
                + " |"
            )
        out.append("")
        ours = summ.get("wrong_model", {}).get("ours", {})
        right = summ.get("right_model", {}).get("ours", {}).get("mean_error_mm")
        if ours.get("floor_mm") is not None:
            seen = ours.get("camera_floor_mm")
            out += [
                "DLO1's model has 13 vertices, DLO3's markers are 12: the true shape resampled to 13 "
                f"vertices is itself {ours['floor_mm']:.1f} mm from the true polyline by this metric"
                + (
                    f"; laid on the rope the camera sees (the smooth curve through the markers), "
                    f"{seen:.1f} mm"
                    + (f" = {seen / right:.2f}x the right model's error" if right else "")
                    + ": what a tracker that followed the camera exactly would score with that model"
                    if seen is not None
                    else ""
                )
                + ".",
                "",
            ]
    if "blackout" in summ:
        out += [
            f"Recovery after the rope was hidden for 1 s: time from its reappearance until the error is within 2x "
            f"the mean of the second before (target: {RECOVERY_TARGET_S} s).",
            "",
            "| method | mean [s] | max [s] | within target | never |",
            "|---|---:|---:|---:|---:|",
        ]
        for m in methods:
            r = summ["blackout"].get(m, {}).get("recovery_s")
            if r:
                out.append(
                    f"| {m} | {_f(r['mean'], 2)} | {_f(r['max'], 2)} | {r['within_target']}/{r['n']} | {r['never']} |"
                )
        out.append("")
    out += [
        "Update time per cloud [ms], p50 / p99 over every cloud of every scenario (ours: `Tracker.correct`; "
        "peers: our segmentation to world points and depth image plus their `update`), one thread:",
        "",
        "| method | update p50 | update p99 | clouds | model step p50 | model step p99 |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for m, t in d.get("timing_ms", {}).items():
        s = t.get("step") or {}
        out.append(
            f"| {m} | {_f(t['update']['p50'])} | {_f(t['update']['p99'])} | {t['update']['n']} | "
            f"{_f(s.get('p50'), 2)} | {_f(s.get('p99'), 2)} |"
        )
    out += ["", f"Wall time {d.get('wall_s', '-')} s; plots: `{d.get('plot', '-')}`.", ""]
    return out


def timing(rows: list[dict], methods: list[str]) -> dict:
    """Pooled update (and, ours, step) times over every case."""
    out = {}
    for m in methods:
        up, st = [], []
        for row in rows:
            for case in row["cases"]:
                g = case["methods"].get(m)
                if g:
                    up += g["update_ms_all"]
                    st += g.get("step_ms_all", [])
        if up:
            out[m] = dict(update=_pct(up), step=_pct(st) if st else None)
    return out


def plot(result: dict, path: Path) -> Path:
    """One figure, a panel per scenario: the error over time of each method, mean over recordings."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series = result["series"]
    names = list(series)
    cols = 3
    rows = max(1, -(-len(names) // cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 2.8 * rows), squeeze=False, sharey=False)
    for ax, v in zip(axes.flat, names):
        t = series[v]["times_s"]
        for m in result["methods"]:
            if m in series[v]:
                ax.plot(t[: len(series[v][m])], series[v][m], label=m, lw=1.0)
        if v == "blackout":
            info = result.get("blackout", {})
            s0 = info.get("start_s", 1.5)
            ax.axvspan(s0, s0 + info.get("duration_s", 1.0), color="0.85", zorder=0)
        ax.set_title(LABEL.get(v, v), fontsize=9)
        ax.set_xlabel("time [s]", fontsize=8)
        ax.set_ylabel("error [mm]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_yscale("log")
    for ax in list(axes.flat)[len(names) :]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=len(labels), fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
