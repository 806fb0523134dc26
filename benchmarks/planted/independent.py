"""Datasets planted by a simulator we did not write (``INDEPENDENT``: PyElastica,
benchmarks/planted/elastica.py, or MuJoCo, benchmarks/planted/mujoco.py) on a light and a stiff
rod (a medium one when asked), each driven by real gripper motions; the tool is given them through
the user path (files and ROD.json).

A dataset is ``SIMULATOR:KIND:EFFECT:SEED``; its paired control (``EFFECT`` none, same seed: same
motions and noise) is simulated once (:func:`simulate`, a shared task) and given to the control's
own task and to each effect's, which measures how far the effect moved the markers from it.
"""

from __future__ import annotations

import time

from benchmarks.planted.config import run_config, tool_budget
from benchmarks.planted.inputs import as_user_inputs, at_frame_step, equivalence_of, independent_simulator
from benchmarks.planted.splice import run_spliced
from benchmarks.rods import SOURCE_ROD, independent_rod, rod_spec, seeded_sources
from deform.diagnose.selection import diagnose


def dataset_key(simulator: str, kind: str, effect: str | None, seed: int) -> str:
    return f"{simulator}:{kind}:{effect or 'none'}:{seed}"


def simulate(simulator: str, kind: str, effect: str | None, seed: int, args) -> dict:
    """The recordings of one dataset (``args.fit + args.check`` of ``args.frames`` frames):
    ``{"recs", "truth", "seconds"}``, or ``{"diverged": reason, "seconds"}`` when the simulator's own
    step diverged (no dataset, stated as such)."""
    _, generate, _ = independent_simulator(simulator)
    spec, sources = independent_rod(kind, simulator=simulator)
    src = seeded_sources(sources, seed, args.fit + args.check)
    noise = {"noise_m": args.noise_mm * 1e-3} if args.noise_mm is not None else {}
    t0 = time.perf_counter()
    try:
        recs, truth = generate(effect, src, spec, rod_kind=kind, n_frames=args.frames, seed=seed, **noise)
    except RuntimeError as exc:
        if "diverged" not in str(exc):
            raise
        return {"diverged": str(exc), "seconds": time.perf_counter() - t0}
    return {"recs": recs, "truth": truth, "seconds": time.perf_counter() - t0}


def independent_dataset(
    simulator: str,
    kind: str,
    effect: str | None,
    seed: int,
    args,
    control: dict | None = None,
    old: dict | None = None,
) -> dict:
    """The row of one dataset. ``control``: :func:`simulate`'s result for the paired control (the
    control's own recordings when ``effect`` is None; not needed for a ``--refit`` of ``old``)."""
    key = dataset_key(simulator, kind, effect, seed)
    _, _, detectability = independent_simulator(simulator)
    t0 = time.perf_counter()
    sim = control if effect is None else simulate(simulator, kind, effect, seed, args)
    shared = sim["seconds"] if effect is None else 0.0  # simulated in another task
    reason = sim.get("diverged")
    if reason is None and effect is not None and old is None:
        reason = control.get("diverged")
    if reason is not None:
        row = {
            "key": key,
            "config": run_config(args),
            "kind": "diverged",
            "simulator": simulator,
            "rod_kind": kind,
            "effect": effect or "none",
            "seed": seed,
            "reason": reason,
            "seconds": time.perf_counter() - t0 + shared,
        }
        return row
    recs, truth, t_sim = sim["recs"], sim["truth"], sim["seconds"]
    spec = rod_spec(SOURCE_ROD[kind], f"{kind}-{simulator}")
    user_spec, user_recs = at_frame_step(spec, recs, args.frame_step)
    inputs = as_user_inputs(
        user_spec, user_recs[: args.fit], user_recs[args.fit :], smooth_noise=args.denoise != "off"
    )
    if old is not None:
        return run_spliced(old, inputs, args, t0 - shared)
    rep = diagnose(inputs, tool_budget(args)).report
    found = next((c["params"] for c in rep["candidates"] if c["name"] == effect and c["round"] == 1), {})
    return {
        "key": key,
        "config": run_config(args),
        "kind": "planted",
        "simulator": simulator,
        "rod_kind": kind,
        "effect": effect or "none",
        "seed": seed,
        "selected": rep["selected"],
        "equivalence_class": equivalence_of(rep),
        "truth": truth,
        "found_round1": found,
        "found_selected": rep["nominal"]["final_params"].get(effect, {}) if effect else {},
        "param_rel_error": {},
        "warnings": rep["nominal"]["warnings"],
        "detectability_l1_m": detectability(recs, control["recs"]) if effect is not None else 0.0,
        "nominal_params": rep["nominal"]["params"],
        "clamp_restart": rep["nominal"].get("clamp_restart"),
        "nominal_check_l1_m": rep["nominal"]["check_l1_m"],
        "final_check_l1_m": rep["final_check_l1_m"],
        "candidates": rep["candidates"],
        "findings": rep["localization"]["findings"],
        "seconds_simulate": t_sim,
        "seconds": time.perf_counter() - t0 + shared,
        "oracle_check_l1_m": None,
    }


def independent_jobs(args, effects: list[str]) -> list[tuple]:
    """(kind, effect, seed) per rod kind and seed: the control first (it is also the effects' pair),
    then the effects."""
    return [
        (k, e, s)
        for k in args.rod_kinds
        for s in range(args.first_seed, max(args.seeds, args.control_seeds))
        for e in ([None] if s < args.control_seeds else []) + (effects if s < args.seeds else [])
    ]


def independent_tasks(workers, args, pending: list[tuple], old_rows: dict) -> dict:
    """The tasks of the ``pending`` datasets (kind, effect, seed), -> {key: call}: one shared
    simulation per paired control that a pending dataset needs."""
    from benchmarks.cluster import call

    simulator = args.simulator
    controls: dict = {}
    tasks = {}
    for kind, effect, seed in pending:
        key = dataset_key(simulator, kind, effect, seed)
        old = old_rows.get(key)
        control = None
        if effect is None or old is None:
            if (kind, seed) not in controls:
                controls[(kind, seed)] = workers.shared(simulate, simulator, kind, None, seed, args)
            control = controls[(kind, seed)]
        tasks[key] = call(independent_dataset, simulator, kind, effect, seed, args, control, old)
    return tasks
