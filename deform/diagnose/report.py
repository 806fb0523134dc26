"""report.json (the issue's schema) and report.md with PNG plots."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from deform.diagnose.localize import plot_localization
from deform.diagnose.scoring import PER_PARAM
from deform.diagnose.selection import Diagnosis
from deform.io.recordings import Recording
from deform.terms.library import LIBRARY


def _significance(c: dict) -> str:
    """The candidate table's verdict: significant, and if so whether beyond the material level; or
    nameable on its fitted size (rule v8, :func:`deform.diagnose.scoring.nameable`)."""
    if not c["significant"]:
        return (
            "no; beyond a rope's material level, helping on the check: nameable"
            if c.get("nameable")
            else "no"
        )
    return "yes" if c.get("beyond_material_level", True) else "yes, within a rope's material level: not named"


def _named_on_size(c: dict) -> list[str]:
    """report.md's lines for a selected candidate named under its threshold (rule v8), else none."""
    if c["significant"]:
        return []
    return [
        f"{c['name']} (round {c['round']}) is named on its fitted size: its gain "
        f"({c['improvement'] * 100:+.1f} %) is under the threshold ({c['threshold'] * 100:.1f} %), but it "
        "is fitted beyond a rope's material level and helps across the check recordings "
        f"(90 % interval {c['improvement_ci90'][0] * 100:+.1f} to "
        f"{c['improvement_ci90'][1] * 100:+.1f} %).",
        "",
    ]


def _held_by_material_level(c: dict) -> list[str]:
    """report.md's lines for a round's pick left unnamed because a term within its material level
    explained the check recordings as well (rule v9), else none."""
    w = c.get("held_by_material_level")
    if not w:
        return []
    return [
        f"Round {c['round']} names nothing: {w['term']}, fitted within a rope's own material level, explains "
        f"the check recordings as well as {c['name']} ({w['term_penalised'] * 100:+.1f} % against "
        f"{w['pick_penalised'] * 100:+.1f} %, each less {PER_PARAM * 100:.0f} % per parameter). The rope's "
        "ordinary material physics accounts for the misfit as well as the new term would.",
        "",
    ]


def _unconfirmed(rep: dict) -> list[str]:
    """report.md's lines for the last round's best candidate left unnamed when some check recordings
    confirm it and others do not: physics that acts only where a recording reaches it (a table
    touched in few of them) needs check recordings that exercise it. None otherwise."""
    rows = [c for c in rep["candidates"] if c.get("improvement_by_check_recording")]
    if not rows:
        return []
    last = max(c["round"] for c in rows)
    named = set(rep["selected"])
    unnamed = [
        c
        for c in rows
        if c["round"] == last and c["name"] not in named and c.get("beyond_material_level", True)
    ]
    if not unnamed:
        return []
    c = max(unnamed, key=lambda c: c["improvement"])
    by = c["improvement_by_check_recording"]
    if c["improvement"] <= 0 or max(by) <= c["threshold"]:
        return []
    names = list(rep["nominal"].get("check_l1_by_recording_m", {})) or [f"#{i}" for i in range(len(by))]
    per = ", ".join(f"{n} {v * 100:+.1f} %" for n, v in zip(names, by))
    return [
        f"Not confirmed: {c['name']} (round {c['round']}) improves some check recordings beyond its "
        f"threshold ({c['threshold'] * 100:.1f} %) but not on average ({c['improvement'] * 100:+.1f} %): "
        f"{per}. Physics that acts only where a recording reaches it (a table the rope touches in few "
        "of them) is decided by check recordings that exercise it; add such recordings to check/ to "
        "decide.",
        "",
    ]


def _plots(diag: Diagnosis, check: list[Recording], out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    plot_localization(diag.report["localization"], out / "localization.png")
    files.append("localization.png")
    nom = diag.nominal_sim.predict(check)
    fin = diag.final_sim.predict(check)
    fig, ax = plt.subplots(figsize=(6, 4))
    for preds, label in ((nom, "nominal"), (fin, "final")):
        err = np.mean(
            [np.abs(p - r.positions[2 : 2 + len(p)]).mean(axis=(1, 2)) for p, r in zip(preds, check)], 0
        )
        ax.plot(np.arange(1, len(err) + 1), err * 100, label=label)
    ax.set_xlabel("horizon [steps]")
    ax.set_ylabel("check L1 [cm]")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "horizon.png", dpi=80)
    plt.close(fig)
    files.append("horizon.png")
    r, p0, p1 = check[0], nom[0], fin[0]
    mid = r.n_vertices // 2
    t = np.arange(2, 2 + len(p0)) * r.dt
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.5))
    for k, ax in enumerate(axes):
        ax.plot(t, r.positions[2 : 2 + len(p0), mid, k], "k", label="recorded")
        ax.plot(t, p0[:, mid, k], "--", label="nominal")
        ax.plot(t, p1[:, mid, k], label="final")
        ax.set_title(f"{r.name}: vertex {mid}, {'xyz'[k]} [m]")
        ax.set_xlabel("t [s]")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out / "overlay.png", dpi=80)
    plt.close(fig)
    files.append("overlay.png")
    cands = [c for c in diag.report["candidates"] if c["round"] == 1]
    if cands:
        fig, ax = plt.subplots(figsize=(7, 3.5))
        y = np.array([c["improvement"] for c in cands]) * 100
        lo = np.array([c["improvement_ci90"][0] for c in cands]) * 100
        hi = np.array([c["improvement_ci90"][1] for c in cands]) * 100
        ax.bar(
            range(len(cands)),
            y,
            yerr=[y - lo, hi - y],
            color=["tab:green" if c["significant"] else "tab:gray" for c in cands],
        )
        ax.plot(
            [-0.5, len(cands) - 0.5], [cands[0]["threshold"] * 100] * 2, "r:", label="threshold (1-param)"
        )
        ax.set_xticks(range(len(cands)), [c["name"] for c in cands], rotation=40, ha="right", fontsize=8)
        ax.set_ylabel("1 s check improvement [%] (90% CI)")
        fig.tight_layout()
        fig.savefig(out / "candidates.png", dpi=80)
        plt.close(fig)
        files.append("candidates.png")
    return files


def _fmt(d: dict, std: dict | None = None) -> str:
    parts = []
    for k, v in d.items():
        s = f"{k}={v:.4g}"
        if std and k in std:
            s += " (± not determined)" if std[k] is None else f" ± {std[k]:.2g}"
        parts.append(s)
    return ", ".join(parts)


def _fine_nominal(nom: dict) -> list[str]:
    """The nominal fit at the finer step that slow terms start from in round 1, if one was made."""
    fine = nom.get("fine")
    if not fine:
        return []
    return [
        f"Slow terms (internal damping) are fitted with the model stepped at "
        f"{fine['model_step_s'] * 1e3:g} ms, in round 1 from a nominal fit of their own at that step: "
        f"{_fmt(fine['params'])}; one-second check predictions {fine['check_window_l1_m'] * 100:.3f} cm. "
        "The model's usual step dissipates on its own about as much as a light rope's material damping.",
        "",
    ]


def write_report(diag: Diagnosis, check: list[Recording], out: Path) -> Path:
    """Write report.json, the plots and report.md into ``out`` (created).

    Args:
        diag: the :class:`Diagnosis`.
        check: the check recordings (overlay plot).
        out: the output directory.

    Returns:
        The path of report.md.
    """
    out.mkdir(parents=True, exist_ok=True)
    rep = diag.report
    (out / "report.json").write_text(json.dumps(rep, indent=2))
    files = _plots(diag, check, out)
    nom = rep["nominal"]
    lines = ["# Discrepancy diagnosis", ""]
    for w in nom["warnings"]:
        lines.append(f"> **Warning:** {w}")
    lines += [
        "",
        "## Nominal model (plain DER, identified on fit/)",
        "",
        f"Parameters: {_fmt(nom['params'])}",
        "",
        "`clamp_m` is how far past the gripped markers (vertices 1 and n-2) the grippers hold the rope, "
        + (
            "fitted with the rest: where the free rope starts."
            if nom.get("clamp_fitted", True)
            else "given (`--clamp`) and held: where the free rope starts."
        ),
        "",
        f"Check error (the whole recording open loop, paper's metric): **{nom['check_l1_m'] * 100:.3f} cm**; "
        f"one-second predictions along the recordings: {nom['check_window_l1_m'] * 100:.3f} cm",
        "",
        *_fine_nominal(nom),
        "## Where the nominal model is wrong",
        "",
    ]
    lines += [f"- {f}" for f in rep["localization"]["findings"]]
    lines += [
        "",
        "![localization](localization.png)",
        "",
        "## Candidate terms",
        "",
        "| round | term | params | check L1 [cm] | improvement (1 s) | 90% CI | open loop | threshold | significant |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for c in rep["candidates"]:
        lines.append(
            f"| {c['round']} | {c['name']} | {_fmt(c['params'], c.get('params_std'))} | {c['check_l1_m'] * 100:.3f} | "
            f"{c['improvement'] * 100:+.1f} % | [{c['improvement_ci90'][0] * 100:+.1f}, {c['improvement_ci90'][1] * 100:+.1f}] | "
            f"{c.get('improvement_rollout', float('nan')) * 100:+.1f} % | "
            f"{c['threshold'] * 100:.1f} % | {_significance(c)} |"
        )
    lines += [
        "",
        "Improvement (1 s): mean over check recordings of the relative reduction of the error of one-second "
        "predictions restarted every 0.2 s along each recording, against a reference refitted with the same "
        "budget; significant when the mean exceeds the parameter-penalised threshold (calibrated on control "
        "datasets); the 90 % bootstrap interval over recordings shows how evenly the recordings share it. "
        "Open loop: the same for whole-recording predictions (reported, not deciding: they drift, and "
        "spread twice as wide on controls). ± : approximate 1-sigma (Laplace). A term fitted within a "
        "rope's own material level (internal damping up to the level every rope's material has) is "
        "significant but not named; one fitted beyond that level whose 90 % interval lies above 0 may be "
        "named below the threshold (its gain is diluted by the nominal model's own numerical dissipation). "
        "A round picks the nameable candidate with the largest improvement less its parameter penalty. "
        "Nothing is named in a round where a term within its material level does as well as the best "
        "candidate, both less their parameter penalty.",
        "",
        "![candidates](candidates.png)" if "candidates.png" in files else "",
        "",
        "## Result",
        "",
        f"Selected: **{', '.join(rep['selected']) or 'none'}**",
        "",
    ]
    for c in rep["candidates"]:
        lines += _held_by_material_level(c)
    lines += _unconfirmed(rep)
    for c in rep["candidates"]:
        if "fit_noise" in c:
            lines += _named_on_size(c)
            lines += [
                f"{c['name']} (round {c['round']}) fitted again on other windows: improvement "
                f"{c['fit_noise']['improvement_refit'] * 100:+.1f} % (first fit {c['improvement'] * 100:+.1f} %; "
                f"the fit's own noise about {c['fit_noise']['noise'] * 100:.1f} %).",
                "",
            ]
        if len(c.get("equivalence_class", [])) > 1:
            lines += [
                f"Marker motion cannot tell **{c['name']}** apart from "
                f"{', '.join(n for n in c['equivalence_class'] if n != c['name'])} (round {c['round']}): "
                "either explains the held-out recordings as well; " + "; ".join(c["equivalence_why"]) + ".",
                "",
            ]
    known = [(name, cls.cannot_tell_from) for name, cls in LIBRARY.items() if cls.cannot_tell_from]
    if known:
        lines += ["### What marker motion cannot tell apart", ""]
        lines += [f"- **{name}** from {why}." for name, why in known]
        lines += [""]
    lines += [
        f"Check error: {nom['check_l1_m'] * 100:.3f} cm (nominal) -> **{rep['final_check_l1_m'] * 100:.3f} cm**",
        "",
        "Final parameters: " + "; ".join(f"{k}: {_fmt(v)}" for k, v in nom["final_params"].items()),
        "",
        "![horizon](horizon.png)",
        "",
        "![overlay](overlay.png)",
        "",
        f"Run time: {nom['seconds']:.0f} s",
    ]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    return out / "report.json"
