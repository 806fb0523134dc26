"""Datasets planted by this project's own simulator (deform.diagnose.planted: a finer rod, a smaller
step, markers a subset of its nodes, 0.3 mm noise, gripper motions replayed from real DLO2
recordings), and the real recordings DLO1..DLO5 against plain DER. The tool is not told the effect.

A planted dataset is ``EFFECT:SEED`` (``none`` a control), a real rod ``real:ROD``.
"""

from __future__ import annotations

import time

from benchmarks.planted.config import run_config, tool_budget
from benchmarks.planted.inputs import as_user_inputs, equivalence_of, marker_edge, oracle_check, param_error
from benchmarks.planted.splice import run_spliced
from benchmarks.rods import data_root, own_pick, own_rod, own_sources, rod_spec
from deform.diagnose.planted import generate_planted
from deform.diagnose.selection import diagnose
from deform.diagnose.spec import Inputs
from deform.io.recordings import load_recordings


def planted_key(effect: str | None, seed: int) -> str:
    return f"{effect or 'none'}:{seed}"


def planted_jobs(args, effects: list[str]) -> list[tuple]:
    """Controls first (they calibrate the rule), then each seed through all effects."""
    return [(None, s) for s in range(args.control_seeds)] + [
        (e, s) for s in range(args.seeds) for e in effects
    ]


def planted_dataset(effect: str | None, seed: int, args, old: dict | None = None) -> dict:
    """The row of the own simulator's dataset (``effect``, ``seed``); with ``old``, a ``--refit`` of it."""
    key = planted_key(effect, seed)
    spec = own_rod()
    src = own_pick(own_sources(), seed, args.fit + args.check)
    t0 = time.perf_counter()
    recs, truth = generate_planted(effect, src, spec, n_frames=args.frames, seed=seed)
    inputs = Inputs(spec=spec, fit=recs[: args.fit], check=recs[args.fit :])
    if old is not None:
        row = run_spliced(old, inputs, args, t0)
        if effect in row["spliced"]["refitted"]:
            row["param_rel_error"] = param_error(row["found_round1"], truth, marker_edge(inputs.fit))
        return row
    rep = diagnose(inputs, tool_budget(args)).report
    t_diag = time.perf_counter() - t0
    found = next((c["params"] for c in rep["candidates"] if c["name"] == effect and c["round"] == 1), {})
    fitted = {k: v for k, v in rep["nominal"]["final_params"].items() if k == effect}
    row = {
        "key": key,
        "config": run_config(args),
        "kind": "planted",
        "effect": effect or "none",
        "seed": seed,
        "selected": rep["selected"],
        "truth": truth,
        "found_round1": found,
        "found_selected": fitted.get(effect, {}),
        "param_rel_error": param_error(fitted.get(effect) or found, truth, marker_edge(inputs.fit)),
        "nominal_params": rep["nominal"]["params"],
        "clamp_restart": rep["nominal"].get("clamp_restart"),
        "nominal_check_l1_m": rep["nominal"]["check_l1_m"],
        "final_check_l1_m": rep["final_check_l1_m"],
        "candidates": rep["candidates"],
        "findings": rep["localization"]["findings"],
        "seconds_diagnose": t_diag,
    }
    row["oracle_check_l1_m"] = oracle_check(spec, rep["nominal"]["params"], effect, truth, inputs, args.quick)
    row["seconds"] = time.perf_counter() - t0
    return row


def real_key(rod: str) -> str:
    return f"real:{rod}"


def real_dataset(rod: str, args, old: dict | None = None) -> dict:
    """The row of the real rod ``rod``: fit on its train recordings, check on eval where the rod has
    eval recordings (DLO1-DLO3), else on later train recordings; through the user path (ROD.json
    with the rope's real length)."""
    data = data_root()
    recs = load_recordings(data / rod / "train")
    spec = rod_spec(rod)
    held = load_recordings(data / rod / "eval")[: args.check] if (data / rod / "eval").is_dir() else []
    inputs = as_user_inputs(spec, recs[: args.fit], held or recs[args.fit : args.fit + args.check])
    t0 = time.perf_counter()
    if old is not None:
        return run_spliced(old, inputs, args, t0)
    rep = diagnose(inputs, tool_budget(args)).report
    return {
        "key": real_key(rod),
        "config": run_config(args),
        "kind": "real",
        "rod": rod,
        "selected": rep["selected"],
        "check_split": "eval" if held else "train",
        "equivalence_class": equivalence_of(rep),
        "warnings": rep["nominal"]["warnings"],
        "n_frames": [r.n_frames for r in inputs.fit + inputs.check],
        "nominal_check_l1_m": rep["nominal"]["check_l1_m"],
        "final_check_l1_m": rep["final_check_l1_m"],
        "findings": rep["localization"]["findings"],
        "nominal_params": rep["nominal"]["params"],
        "clamp_restart": rep["nominal"].get("clamp_restart"),
        "final_params": rep["nominal"]["final_params"],
        "candidates": rep["candidates"],
        "seconds": time.perf_counter() - t0,
    }
