"""How far a planted effect moves the markers from its paired control (:func:`detectability`), and
the command line of the independent simulators' generators that prints it per effect
(``python benchmarks/elastica_planted.py``, ``python benchmarks/mujoco_planted.py``)."""

from __future__ import annotations

import time as _time

import numpy as np

from deform.diagnose.spec import RodSpec
from deform.io.recordings import Recording
from deform.model import gripped_indices


def detectability(effect_recs: list[Recording], control_recs: list[Recording]) -> float:
    """Marker L1 [m] between a case and its paired control (same seed, motions and noise): mean
    |a - b| over frames, non-gripped markers and xyz."""
    diffs = []
    for a, b in zip(effect_recs, control_recs, strict=True):
        n = a.positions.shape[1]
        inner = [k for k in range(n) if k not in gripped_indices(n)]
        diffs.append(np.abs(a.positions[:, inner] - b.positions[:, inner]).ravel())
    return float(np.concatenate(diffs).mean())


def print_detectability_table(
    generate, describe_numerics, description: str, kinds: tuple | list, effects: tuple | list
) -> None:
    """The command line of a planted-effect generator: per rod kind, a control (its time, what
    ``describe_numerics(truth)`` says of its numerics, its L1 from the real recordings it replays),
    then each effect's marker L1 from that control (:func:`detectability`).

    Args:
        generate: ``generate_elastica`` or another generator with its signature.
        describe_numerics: ``truth -> str``, the simulator's own checks of a control.
        description: the command's help text.
        kinds: the simulator's rod kinds (``--kinds``' default).
        effects: the effects it plants (``--effects``' default).
    """
    import argparse

    from deform.io.recordings import find_data_root, load_recordings

    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--sources", type=int, default=8)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--kinds", nargs="*", default=list(kinds))
    ap.add_argument("--effects", nargs="*", default=list(effects))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--strength", type=float, default=1.0)
    args = ap.parse_args()
    from benchmarks.rods import RODS, SOURCE_ROD  # the benchmark's rods, one table

    root = find_data_root()
    for kind in args.kinds:
        name = SOURCE_ROD[kind]
        length, mass, nv = RODS[name]
        sources = load_recordings(root / name / "train")[: args.sources]
        spec = RodSpec(length_m=length, mass_kg=mass, n_vertices=nv, dt=0.01, name=name)
        t0 = _time.perf_counter()
        control, truth = generate(None, sources, spec, kind, args.frames, args.seed)
        tc = _time.perf_counter() - t0
        real = np.mean(
            [
                np.abs(c.positions[:, 2:-2] - r.positions[s : s + args.frames, 2:-2]).mean()
                for c, r, s in zip(control, sources, truth["numerics"]["starts"])
            ]
        )
        print(
            f"{kind} ({name}): control {tc:.1f} s, {describe_numerics(truth)}, L1 vs real {real * 100:.2f} cm",
            flush=True,
        )
        for effect in args.effects:
            t0 = _time.perf_counter()
            recs, _ = generate(effect, sources, spec, kind, args.frames, args.seed, strength=args.strength)
            print(
                f"  {effect:20s} {detectability(recs, control) * 100:5.2f} cm  "
                f"({_time.perf_counter() - t0:.1f} s)",
                flush=True,
            )
