"""The planted-effect benchmark's tables: decisions re-derived from the stored candidate scores under
the tool's rule and a rule calibrated on the controls (:func:`apply_rules`), a summary per planted
effect (:func:`summarise`), and the result files ``benchmarks/results/STEM.{json,md}`` (:func:`write`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from benchmarks.planted.config import RULE, TOOL_VERSION, budget, tool_min_gain
from benchmarks.planted.inputs import equivalence_of
from benchmarks.provenance import machine_text
from benchmarks.store import write_atomic
from deform.diagnose.scoring import MIN_GAIN, PER_PARAM, calibrate_min_gain, reselect
from deform.terms.library import LIBRARY

RESULTS = Path(__file__).resolve().parents[1] / "results"


def apply_rules(planted: list[dict], real: list[dict], alpha: float) -> dict:
    """Decisions under (a) the rule the tool ran with and (b) the rule calibrated on the controls.
    Controls are judged with a leave-one-control-out calibration (their own scores never set their
    threshold); planted datasets and real rods with the calibration on all controls."""
    controls = [r for r in planted if r["effect"] == "none"]
    n_cand = len(LIBRARY)

    def nulls(rows):
        c = [c for r in rows for c in r["candidates"] if c["round"] == 1]
        return [x["improvement"] for x in c], [x["n_params"] for x in c]

    cal = None
    if len(controls) >= 2:
        imp, k = nulls(controls)
        cal = calibrate_min_gain(imp, n_cand, alpha=alpha, per_param=PER_PARAM, n_params=k)
    for r in planted + real:
        r["as_run"] = {"selected": r["selected"], "final_check_l1_m": r["final_check_l1_m"]}
        tool = reselect(r["candidates"], r["nominal_check_l1_m"], tool_min_gain(r), PER_PARAM)
        same_first = tool["selected"][:1] == r["selected"][:1]
        r["tool"] = {
            "min_gain": tool_min_gain(r),
            **tool,
            "equivalence_class": equivalence_of(r) if same_first else tool["selected"][:1],
        }
        if cal is None:
            continue
        if r.get("effect") == "none":
            others = [c for c in controls if c is not r]
            if len(others) < 2:
                continue
            imp, k = nulls(others)
            mg = calibrate_min_gain(imp, n_cand, alpha=alpha, per_param=PER_PARAM, n_params=k)["min_gain"]
        else:
            mg = cal["min_gain"]
        r["calibrated"] = {
            "min_gain": mg,
            **reselect(r["candidates"], r["nominal_check_l1_m"], mg, PER_PARAM),
        }
    # the rule the rows were run with, read back from the stored thresholds (not today's default)
    ran = sorted(
        {
            round(c["threshold"] - PER_PARAM * c["n_params"], 6)
            for r in planted + real
            for c in r["candidates"]
        }
    )
    return {
        "calibration": cal,
        "tool_rule": {
            "min_gain": ran[0] if len(ran) == 1 else MIN_GAIN,
            "per_param": PER_PARAM,
            "min_gain_values_in_rows": ran,
        },
    }


def _pair(r: dict):
    """The control a dataset is paired with: same seed (same motions), same rod kind."""
    return (r.get("rod_kind"), r["seed"])


def _gaps(r: dict, floor: dict, final: float) -> dict:
    out = {}
    if r["effect"] == "none":
        return out
    o = r.get("oracle_check_l1_m")
    if o is not None:
        gap = r["nominal_check_l1_m"] - o
        out["gap_oracle_m"] = gap
        out["gap_closed_oracle"] = (r["nominal_check_l1_m"] - final) / gap if gap > 1e-5 else None
    if _pair(r) in floor:
        gap = r["nominal_check_l1_m"] - floor[_pair(r)]
        out["gap_control_m"] = gap
        out["gap_closed_control"] = (r["nominal_check_l1_m"] - final) / gap if gap > 1e-5 else None
    return out


def summarise(rows: list[dict], rule: str) -> dict:
    floor = {_pair(r): r["nominal_check_l1_m"] for r in rows if r["effect"] == "none"}
    out = {}
    for eff in sorted({r["effect"] for r in rows}, key=lambda e: (e != "none", e)):
        rs = [r for r in rows if r["effect"] == eff and rule in r]
        if not rs:
            continue
        sel = [r[rule]["selected"] for r in rs]
        right = [(s[:1] == [eff]) if eff != "none" else (s == []) for s in sel]
        finals = [r[rule]["final_check_l1_m"] for r in rs]
        g = [_gaps(r, floor, f) for r, f in zip(rs, finals)]
        go = [x["gap_closed_oracle"] for x in g if x.get("gap_closed_oracle") is not None]
        gc = [x["gap_closed_control"] for x in g if x.get("gap_closed_control") is not None]
        perr = [float(np.mean(list(r["param_rel_error"].values()))) for r in rs if r["param_rel_error"]]
        if eff == "none":
            in_class = right
        elif rule == "tool":
            in_class = [eff in r["tool"]["equivalence_class"] for r in rs]
        else:
            in_class = [eff in r.get("equivalence_class", equivalence_of(r)) for r in rs]
        detect = [r["detectability_l1_m"] for r in rs if r.get("detectability_l1_m") is not None]
        out[eff] = {
            "runs": len(rs),
            "named_correctly": int(sum(right)),
            "rate": float(np.mean(right)),
            "named_in_class": int(sum(in_class)) if rule in ("as_run", "tool") else None,
            "detectability_cm": (float(np.median(detect)) * 100) if detect and eff != "none" else None,
            "selected": [s or ["none"] for s in sel],
            "nominal_check_cm": float(np.mean([r["nominal_check_l1_m"] for r in rs]) * 100),
            "final_check_cm": float(np.mean(finals) * 100),
            "oracle_check_cm": (
                float(np.mean([r["oracle_check_l1_m"] for r in rs]) * 100)
                if all(r.get("oracle_check_l1_m") is not None for r in rs)
                else None
            ),
            "gap_closed_oracle_median": float(np.median(go)) if go else None,
            "gap_closed_control_median": float(np.median(gc)) if gc else None,
            "gap_closed_oracle_values": go,
            "gap_closed_control_values": gc,
            "param_rel_error_median": float(np.median(perr)) if perr else None,
        }
    return out


def _fmt(x, pct=True):
    return "-" if x is None else (f"{x * 100:.0f} %" if pct else f"{x:.3f}")


def _pooled_gap(summ: dict) -> str:
    """The median gap closed over every planted dataset that has one (all effects pooled)."""
    out = ""
    for key, label in (("oracle", "the truth-started oracle"), ("control", "the paired control")):
        vals = [v for k, s in summ.items() if k != "none" for v in s.get(f"gap_closed_{key}_values") or []]
        if vals:
            out += (
                f" Median gap closed between the nominal model and {label}, all planted datasets with a"
                f" gap: {np.median(vals) * 100:.0f} % ({len(vals)} datasets)."
            )
    return out


def write(result: dict, stem: str = "diagnose", results: Path = RESULTS) -> None:
    """``results/STEM.json`` (the result) and ``results/STEM.md`` (its tables)."""
    results.mkdir(exist_ok=True)
    write_atomic(results / f"{stem}.json", json.dumps(result, indent=2))
    title = {
        "elastica": "planted-effect benchmark, recordings from PyElastica (an independent simulator)",
        "mujoco": "planted-effect benchmark, recordings from MuJoCo (an independent simulator)",
    }.get(result.get("simulator"), "planted-effect benchmark")
    lines = [
        f"# deform diagnose: {title}",
        "",
        f"Run: `{result['command']}` on {machine_text(result['machine'])}; {result['seconds_total_runs']:.0f} s of "
        f"dataset runs (sum over the rows in `{result.get('runs_file', stem + '.runs.jsonl')}`).",
        "",
        f"Budget: {result['budget']}",
        "",
    ]
    for r in result.get("diverged", []):
        lines += [f"No dataset for `{r['key']}`: {r['reason']} (the simulator's own step).", ""]
    cal = result["rules"]["calibration"]
    if cal:
        lines += [
            f"Calibrated rule (from {cal['n_null']} round-1 control improvements, parameter penalty "
            f"{cal['per_param'] * 100:.0f} %/param removed): mean {cal['mu'] * 100:.2f} %, sd {cal['sd'] * 100:.2f} %, "
            f"z = {cal['z']:.2f} (alpha {cal['alpha']} over {len(LIBRARY)} candidates) -> "
            f"min gain {cal['min_gain'] * 100:.2f} % + {cal['per_param'] * 100:.0f} %/param. Controls are "
            f"judged leave-one-control-out.",
            "",
        ]
    lines += [
        f"Decisions are re-derived from the stored candidate scores (exact: the fits are those of tool "
        f"v{result['fits_of_tool_version']}; after a first pick the rows were run with no longer matters for the first name). "
        f"Tool rule {RULE}: {MIN_GAIN * 100:.1f} % + {PER_PARAM * 100:.0f} %/param.",
        "",
    ]
    for rule, title in (
        ("tool", f"Rule of the tool ({RULE})"),
        ("calibrated", "Calibrated rule (same form, threshold from this benchmark's controls)"),
        (
            "as_run",
            "Decisions as the rows were run "
            f"({result['rules']['tool_rule']['min_gain'] * 100:.1f} % + "
            f"{result['rules']['tool_rule']['per_param'] * 100:.0f} %/param, with the rest of the rule "
            "of their day)",
        ),
    ):
        summ = result["summary"].get(rule)
        if not summ:
            continue
        tot = sum(s["runs"] for k, s in summ.items() if k != "none")
        ok = sum(s["named_correctly"] for k, s in summ.items() if k != "none")
        in_class = sum(s["named_in_class"] or 0 for k, s in summ.items() if k != "none")
        lines += [
            f"## {title}",
            "",
            f"Planted effects named first: {ok}/{tot}"
            + (
                f" (the truth in the named equivalence class: {in_class}/{tot})"
                if rule in ("as_run", "tool")
                else ""
            )
            + f"; controls `none`: {summ.get('none', {}).get('named_correctly', 0)}/{summ.get('none', {}).get('runs', 0)}."
            + _pooled_gap(summ),
            "",
            "| planted effect | runs | named correctly | in class | marker L1 vs control [cm] | check nominal [cm] | after [cm] | oracle [cm] | gap closed vs oracle (median) | vs control (median) | param rel. error (median) |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for eff, s in summ.items():
            lines.append(
                f"| {eff} | {s['runs']} | {s['named_correctly']}/{s['runs']} | "
                f"{'-' if s.get('named_in_class') is None else str(s['named_in_class']) + '/' + str(s['runs'])} | "
                f"{'-' if s.get('detectability_cm') is None else format(s['detectability_cm'], '.2f')} | {s['nominal_check_cm']:.3f} | "
                f"{s['final_check_cm']:.3f} | {_fmt(s['oracle_check_cm'] and s['oracle_check_cm'] / 100 * 100, False) if s['oracle_check_cm'] is not None else '-'} | "
                f"{_fmt(s['gap_closed_oracle_median'])} | {_fmt(s['gap_closed_control_median'])} | "
                f"{_fmt(s['param_rel_error_median'])} |"
            )
        lines.append("")
    lines += ["## Per run", ""]
    for r in result["planted"]:
        cal_sel = r.get("calibrated", {}).get("selected")
        lines.append(
            f"- {r.get('rod_kind', '') + ' ' if r.get('rod_kind') else ''}{r['effect']} seed {r['seed']}: "
            f"tool {r['tool']['selected'] or ['none']}, as run {r['selected'] or ['none']}"
            + (f" (class {r['equivalence_class']})" if len(r.get("equivalence_class", [])) > 1 else "")
            + (
                f", marker L1 vs control {r['detectability_l1_m'] * 100:.2f} cm"
                if r.get("detectability_l1_m")
                else ""
            )
            + ", calibrated "
            f"{(cal_sel or ['none']) if cal_sel is not None else '-'}; {r['nominal_check_l1_m'] * 100:.3f} -> "
            f"{r['final_check_l1_m'] * 100:.3f} cm (oracle {_fmt(r.get('oracle_check_l1_m') and r['oracle_check_l1_m'] * 100, False)}); "
            f"params {json.dumps({k: round(v, 4) for k, v in (r['found_selected'] or r['found_round1']).items()})} "
            f"truth {json.dumps(r['truth'])}; {r['seconds']:.0f} s"
        )
    if result["real"]:
        lines += [
            "",
            "## Real recordings against plain DER",
            "",
            "| rod | selected (tool) | selected (as run) | selected (calibrated) | check before [cm] | after (tool) [cm] | best round-1 candidates (improvement) | s |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in result["real"]:
            top = sorted((c for c in r["candidates"] if c["round"] == 1), key=lambda c: -c["improvement"])[:3]
            cs = r.get("calibrated", {}).get("selected")
            lines.append(
                f"| {r['rod']} | {', '.join(r['tool']['selected']) or 'none'} | {', '.join(r['selected']) or 'none'} | "
                f"{(', '.join(cs) or 'none') if cs is not None else '-'} | {r['nominal_check_l1_m'] * 100:.3f} | "
                f"{r['tool']['final_check_l1_m'] * 100:.3f} | "
                + ", ".join(f"{c['name']} {c['improvement'] * 100:+.1f} %" for c in top)
                + f" | {r['seconds']:.0f} |"
            )
    write_atomic(results / f"{stem}.md", "\n".join(lines) + "\n")


def result_of(rows: dict[str, dict], args, provenance: dict, runs_name: str, results: Path = RESULTS) -> dict:
    """The result file's content from every stored row of the run's configuration (``rows``):
    ``provenance`` (command, commit, machine, workers) and ``runs_name`` (where the rows are) as
    given; ``results``: where another run's file named by ``--names-against`` is."""
    planted = [r for r in rows.values() if r["kind"] == "planted"]
    planted.sort(key=lambda r: (r["effect"] != "none", r["effect"], r["seed"]))
    real = sorted((r for r in rows.values() if r["kind"] == "real"), key=lambda r: r["rod"])
    rules = apply_rules(planted, real, args.alpha)
    b = budget(args.quick)
    return {
        **provenance,
        "simulator": args.simulator,
        "budget": (
            f"nominal {b.nominal_iterations} Adam iterations, candidates {b.candidate.iterations} iterations "
            f"of {b.candidate.batch} windows x {b.candidate.horizon} steps, {b.max_rounds} rounds; "
            f"{args.fit} fit + {args.check} check recordings of {args.frames} frames per planted dataset "
            f"(real rods: the first {args.fit} + next {args.check} train recordings, full length)"
        ),
        "seconds_total_runs": float(sum(r["seconds"] for r in rows.values())),
        "runs_file": runs_name,
        "rules": rules,
        "rule": RULE,
        "fits_of_tool_version": args.fits_version or TOOL_VERSION,
        "summary": {
            "tool": summarise(planted, "tool"),
            "as_run": summarise(planted, "as_run"),
            "calibrated": summarise(planted, "calibrated"),
        },
        "planted": planted,
        "real": real,
        "diverged": sorted((r for r in rows.values() if r["kind"] == "diverged"), key=lambda r: r["key"]),
        **(
            {"names_against": names_against(planted, args.names_against, results)}
            if args.names_against
            else {}
        ),
    }


def names_against(planted: list[dict], stem: str, results: Path = RESULTS) -> dict:
    """The names of each dataset of this run against another run's of the same datasets
    (``results/STEM.json``): the tool's names re-derived by today's rule and the names as run, and
    that run's time per dataset, summed (``seconds_total_runs``: two at a time, half of it is the
    wall time of a by-hand run on two cores)."""
    other = json.loads((results / f"{stem}.json").read_text())
    theirs = {r["key"]: r for r in other.get("planted", [])}
    common = [r for r in planted if r["key"] in theirs]
    differ = [
        {
            "key": r["key"],
            "tool": [r["tool"]["selected"], theirs[r["key"]]["tool"]["selected"]],
            "as_run": [r["selected"], theirs[r["key"]]["selected"]],
        }
        for r in common
        if r["tool"]["selected"] != theirs[r["key"]]["tool"]["selected"]
        or r["selected"] != theirs[r["key"]]["selected"]
    ]
    first = sum(r["tool"]["selected"][:1] == theirs[r["key"]]["tool"]["selected"][:1] for r in common)
    return {
        "stem": stem,
        "commit": other.get("commit"),
        "datasets": len(common),
        "same": len(common) - len(differ),
        "same_first": first,
        "differ": differ,
        "their_seconds_total_runs": other.get("seconds_total_runs"),
    }
