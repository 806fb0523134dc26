"""The calibration report: ``report.json`` (every number), ``report.md`` (the same for a person) and
two plots (``coverage.png``: how much of the rope the camera saw, per vertex; ``fit.png``: the
held-out fit per round). A calibration that could not identify anything gets a report that says
why, and no model.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from calibrate.bags import Clip
from calibrate.fit import Calibration, Round, identified


def build(cal: Calibration, clips: list[Clip], inputs: dict) -> dict:
    """Everything the report holds, as plain data.

    Args:
        cal: the calibration.
        clips: the bags it read.
        inputs: the command's arguments worth recording (length, mass, files, model path).

    Returns:
        The ``report.json`` content.
    """
    by_name = {c.name: c for c in clips}
    tracks = [
        {
            "clip": t.name,
            "seconds": round(t.duration_s, 3),
            "clouds": len(t.cloud_steps),
            "camera_pose_from": by_name[t.name].camera_source if t.name in by_name else None,
            "gripper_poses_frame": by_name[t.name].poses_from if t.name in by_name else None,
            "intrinsics_from": by_name[t.name].intrinsics_from if t.name in by_name else None,
            "coverage_per_vertex": [round(float(c), 3) for c in t.coverage],
            "tracker": t.status,
            "held_out": t.name in cal.held_out_names,
        }
        for t in cal.tracks
    ]
    coverage = np.mean([t.coverage for t in cal.tracks], axis=0) if cal.tracks else np.zeros(0)
    return {
        "inputs": inputs,
        "model_written": cal.model is not None,
        "problem": cal.problem,
        "seconds": round(cal.seconds, 1),
        "checks": cal.checks,
        "held_out_clips": cal.held_out_names,
        "train_clips": cal.train_names,
        "coverage_per_vertex": [round(float(c), 3) for c in coverage],
        "rounds": [
            {
                "round": r.index,
                "held_out_prediction_fit_m": r.held_out_fit_m,
                "held_out_tracking_fit_m": r.tracking_fit_m,
                "kept": r.kept,
                "seconds": round(r.seconds, 1),
                "train_seconds": round(r.train_s, 1),
                "train": r.train,
                "cut_by_time_limit": r.cut_by_time_limit,
            }
            for r in cal.rounds
        ],
        "time_limit_notes": list(cal.time_limit_notes),
        "identified": _identified(cal),
        "tracks": tracks,
    }


def _identified(cal: Calibration) -> dict | None:
    """What was identified (:func:`calibrate.fit.identified`), each parameter's range told by the
    held-out clips (:mod:`calibrate.identifiability`), and every parameter they do not tell."""
    if cal.model is None:
        return None
    out = identified(cal.model, cal.start)
    ranges = cal.parameter_ranges
    params = ranges.get("parameters", {})
    out["told_within"] = {k: v["told_within"] for k, v in params.items()}
    out["held_out_fit_by_factor"] = {k: v["fit_by_factor"] for k, v in params.items()}
    out["told_by_clips"] = ranges.get("held_out_clips", cal.held_out_names)
    for k, v in params.items():
        if not v["told"]:
            out["not_identifiable"].append(
                f"{k}: the held-out fit stays within {100 * ranges['tolerance']:g} % of the best "
                f"{_span(v['told_within'], v['unit'])}"
            )
    out["damping_set"] = damping_set(cal.rounds)
    return out


def damping_set(rounds: list[Round]) -> dict | None:
    """Where the last kept round's damping search (:func:`calibrate.damping.settle_damping`) put the
    damping and the range its fit on the training clips' longer predictions tells it within, in 1/s
    (None: open on that side), and those predictions' horizon. None when no kept round searched."""
    searched = [r for r in rounds if r.kept and r.train and (r.train.get("damping") or {}).get("fits")]
    if not searched:
        return None
    search = searched[-1].train["damping"]
    return {
        "trained_per_s": search["damping_per_s"][0],
        "set_per_s": search["damping_per_s"][1],
        "told_within_per_s": search["told_within_per_s"],
        "horizon_s": search["horizon_s"],
    }


def _span(told: list, unit: str) -> str:
    lo, hi = told
    if lo is None and hi is None:
        return "from 1/8 to 8 times the value found"
    if lo is None:
        return f"down to 1/8 of the value found (values above {hi:.3g} {unit} fit worse)"
    return f"up to 8 times the value found (values below {lo:.3g} {unit} fit worse)"


def _plots(data: dict, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    cov = data["coverage_per_vertex"]
    if cov:
        fig, ax = plt.subplots(figsize=(6, 3))
        ax.bar(range(len(cov)), [c * 100 for c in cov], color="tab:orange")
        ax.set_xlabel("vertex (0, 1, n-2, n-1: held by the grippers)")
        ax.set_ylabel("clouds that corrected it [%]")
        ax.set_ylim(0, 100)
        ax.set_title("camera coverage per vertex")
        fig.tight_layout()
        fig.savefig(out / "coverage.png", dpi=100)
        plt.close(fig)
        names.append("coverage.png")
    if data["rounds"]:
        fig, ax = plt.subplots(figsize=(6, 3))
        idx = [r["round"] for r in data["rounds"]]
        ax.plot(
            idx,
            [r["held_out_prediction_fit_m"] * 1000 for r in data["rounds"]],
            "o-",
            label="0.5 s prediction",
        )
        ax.plot(idx, [r["held_out_tracking_fit_m"] * 1000 for r in data["rounds"]], "s--", label="tracking")
        ax.set_xlabel("round (0: length and mass only)")
        ax.set_ylabel("held-out fit to the clouds [mm]")
        ax.set_xticks(idx)
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "fit.png", dpi=100)
        plt.close(fig)
        names.append("fit.png")
    return names


def _markdown(data: dict, plots: list[str]) -> str:
    inp = data["inputs"]
    lines = [
        "# Calibration report",
        "",
        f"Rope: length {inp['length_m']:g} m, mass {inp['mass_kg']:g} kg, {inp['vertices']} vertices; "
        f"{len(data['tracks'])} clip(s), {sum(t['seconds'] for t in data['tracks']):.1f} s tracked; "
        f"{data['seconds']:.0f} s of work.",
        "",
    ]
    if data["problem"]:
        lines += ["**No model was written**: " + data["problem"] + ".", ""]
    else:
        lines += [
            f"Model: `{inp['out']}` (load with `deform.load_model`, run with `deform-service run --rod "
            f"{inp['out']}`; `deform-service prebuild --rod {inp['out']}` builds its compiled steps "
            "beforehand, 1-2.5 min once, so that the first run starts warm).",
            "",
        ]
    if data["rounds"]:
        lines += [
            "## Fit on held-out clips",
            "",
            "Mean distance of the held-out clouds' rope points to the model's 0.5 s open-loop prediction "
            "from the track (capped at 5 cm; the points lie on the rope's near surface, so a perfect model "
            "scores about its radius), and to the track itself.",
            "",
            "Damping: as training left it, and as the training clips' longer predictions set it "
            "(the training windows barely see a light rope's damping).",
            "",
            "| round | prediction [mm] | tracking [mm] | damping [1/s]: trained -> set | kept | seconds |",
            "|---:|---:|---:|---|:--|---:|",
        ]
        for r in data["rounds"]:
            damping = ((r.get("train") or {}).get("damping") or {}).get("damping_per_s")
            cell = "-" if not damping else f"{damping[0]:.3g} -> {damping[1]:.3g}"
            lines.append(
                f"| {r['round']} | {r['held_out_prediction_fit_m'] * 1000:.2f} | "
                f"{r['held_out_tracking_fit_m'] * 1000:.2f} | {cell} | {'yes' if r['kept'] else 'no'} | "
                f"{r['seconds']:.0f} |"
            )
        lines += ["", f"Held out: {', '.join(data['held_out_clips'])}.", ""]
        for note in data["time_limit_notes"]:
            lines += [
                f"**Time limit**: {note} (a faster or quieter machine gives the full budget's model).",
                "",
            ]
    if data["identified"]:
        f, s = data["identified"]["found"], data["identified"]["start"]
        told = data["identified"].get("told_within", {})
        lines += [
            "## Identified",
            "",
            "Told within: each parameter scaled alone (1/8 to 8 times the value found, steps of 2^0.25), "
            "the nearest values on either side whose held-out prediction fit is over 1 % worse; every "
            "value the clips cannot tell from the one found lies between them (open: not bounded on "
            "that side). Told by the held-out clips " + ", ".join(data["identified"]["told_by_clips"]) + ".",
            "",
            "| parameter | found | start (length and mass) | told within |",
            "|---|---:|---:|---|",
        ]
        for k in (
            "bend_stiffness_Nm2",
            "twist_stiffness_Nm2",
            "damping_per_s",
            "drag_per_m",
            "extra_mass_kg",
        ):
            span = told.get(k)
            cell = "-" if span is None else " .. ".join("open" if v is None else f"{v:.3g}" for v in span)
            lines.append(f"| {k} | {f[k]:.4g} | {s[k]:.4g} | {cell} |")
        lo, hi = f["bend_stiffness_range_Nm2"]
        prior = data["inputs"].get("stiffness_prior") or {}
        if prior.get("from"):  # reports written before the prior's ropes were listed lack them
            lines += [
                "",
                f"The start's bending stiffness: {prior['bend_per_linear_density']:.3g} N m^3/kg times the "
                "mass per length, the median over the shipped ropes " + ", ".join(prior["from"]) + ".",
            ]
        lines += [
            "",
            f"Bending stiffness varies along the rope within {lo:.3g}..{hi:.3g} N m². Not identifiable: "
            + "; ".join(data["identified"]["not_identifiable"])
            + ".",
            "",
        ]
        if "implicit_bending" in f:  # reports written before the scheme was chosen lack it
            lines += [
                f"Bending stepped {'implicitly' if f['implicit_bending'] else 'explicitly'}: the stiffest "
                f"bending mode turns {f['bending_step_ratio']:.2f} rad per frame (implicit above 1)"
                + (f", stepped in {f['substeps']} substeps a frame." if f.get("substeps", 1) > 1 else "."),
                "",
            ]
        damping = data["identified"].get("damping_set")
        if damping:
            span = " .. ".join("open" if v is None else f"{v:.3g}" for v in damping["told_within_per_s"])
            lines += [
                f"Damping after training {damping['trained_per_s']:.3g} /s, set to {damping['set_per_s']:.3g} /s "
                f"by the training clips' {damping['horizon_s']:g} s predictions (the training windows barely see it), which "
                f"tell it within {span} /s.",
                "",
            ]
    lines += [
        "## Coverage",
        "",
        "Share of the clouds that corrected each vertex (the gripped ones are inputs):",
        "",
    ]
    lines.append("| clip | seconds | clouds | coverage per vertex [%] |")
    lines.append("|---|---:|---:|---|")
    for t in data["tracks"]:
        cov = " ".join(f"{c * 100:.0f}" for c in t["coverage_per_vertex"])
        lines.append(
            f"| {t['clip']}{' (held out)' if t['held_out'] else ''} | {t['seconds']:.1f} | {t['clouds']} | {cov} |"
        )
    for key, what in (
        ("gripper_poses_frame", "Gripper poses in"),
        ("camera_pose_from", "Camera pose from"),
        ("intrinsics_from", "Camera intrinsics from"),
    ):
        seen = sorted({str(t.get(key)) for t in data["tracks"] if t.get(key)})
        if seen:
            lines += ["", f"{what}: {'; '.join(seen)}."]
    delay = data["inputs"].get("cloud_delay")
    if delay and delay["clouds"]:
        if delay["delay_s"]:
            lines += [
                "",
                f"Cloud stamps: {1e3 * delay['delay_s']:+.0f} ms against the gripper poses (where the rope "
                f"leaves the grippers: {1e3 * delay['cost_at_best_m']:.1f} mm from the rope there against "
                f"{1e3 * delay['cost_at_zero_m']:.1f} at the stamps, {delay['clouds']} clouds); the clouds were "
                f"tracked at their stamps less that. Serve the rope with `camera.stamp_delay_s: "
                f"{delay['delay_s']:g}` in the service config.",
            ]
        else:
            lines += [
                "",
                f"Cloud stamps: on the gripper poses' clock ({delay['clouds']} clouds tell no delay).",
            ]
    length = data["checks"].get("length")
    if length:
        lines += [
            "",
            f"Length check: the camera sees at least {length['reach_bound_m']:.3f} m of rope between the "
            f"grippers ({length['ratio']:.0%} of the stated free length).",
        ]
    lines += [""] + [f"![{p}]({p})" for p in plots]
    return "\n".join(lines) + "\n"


def write(cal: Calibration, clips: list[Clip], inputs: dict, out_dir: str | Path) -> Path:
    """Write ``report.json``, ``report.md`` and the plots into ``out_dir``.

    Returns:
        The directory.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = build(cal, clips, inputs)
    plots = _plots(data, out)
    (out / "report.json").write_text(json.dumps(data, indent=2, default=float) + "\n")
    (out / "report.md").write_text(_markdown(data, plots))
    return out
