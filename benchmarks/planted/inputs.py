"""What the tool is given and what a row measures: the user path for recordings (ROD.json and files,
:func:`as_user_inputs`), a camera's frame rate (:func:`at_frame_step`), the independent simulators
(:func:`independent_simulator`), a planted truth's parameter error and the oracle's check error."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from benchmarks.planted.config import budget
from deform.diagnose.planted import oracle_term
from deform.diagnose.spec import Inputs, RodSpec
from deform.io.recordings import Recording


def param_error(found: dict, truth: dict, edge_m: float) -> dict:
    """Relative error of each planted parameter the term reports. Rest curvature: the tool reports a
    turning per vertex (curvature x marker spacing ``edge_m``) in a material frame whose orientation
    depends on the unobserved twist, so the magnitude |kappa| is compared."""
    if "kappa1_per_vertex" in found:
        k_found = float(np.hypot(found["kappa1_per_vertex"], found["kappa2_per_vertex"])) / edge_m
        k_true = float(np.hypot(truth["kappa1_per_m"], truth["kappa2_per_m"]))
        return {"kappa_per_m": abs(k_found - k_true) / k_true}
    out = {}
    for k, v in truth.items():
        if k in found and v != 0:
            out[k] = abs(found[k] - v) / abs(v)
    return out


def at_frame_step(spec: RodSpec, recs: list, step: int) -> tuple[RodSpec, list]:
    """Every ``step``-th frame of the simulated recordings, as a camera or motion-capture system at
    ``100 / step`` Hz records them, and ROD.json's frame period to match (the tool resamples them to
    its 100 Hz, ``deform.diagnose.resample``)."""
    if step == 1:
        return spec, recs
    sub = [Recording(name=r.name, positions=r.positions[::step], dt=r.dt * step) for r in recs]
    return spec.model_copy(update={"dt": spec.dt * step}), sub


def marker_edge(recs) -> float:
    return float(
        np.median(
            np.concatenate(
                [np.linalg.norm(np.diff(r.positions[::25, 1:-1], axis=1), axis=-1).ravel() for r in recs]
            )
        )
    )


def oracle_check(spec, nominal_params: dict, effect, truth, inputs, quick: bool) -> float | None:
    """Check error of the tool's model class with the right term started at the planted truth
    (nominal refitted with the candidate budget): the 'truth' end of the gap."""
    from deform.diagnose.fitting import fit
    from deform.diagnose.simulator import Nominal, Simulator, arclength_of, per_recording_l1

    s = arclength_of(inputs.fit)
    edge = marker_edge(inputs.fit)
    term = oracle_term(effect, truth, spec.n_vertices, s, edge)
    if term is None:
        return None
    nom = Nominal(
        nominal_params["bend_stiffness_Nm2"],
        nominal_params["twist_stiffness_Nm2"],
        nominal_params["damping_1_per_s"],
        clamp_m=nominal_params.get("clamp_m", 0.0),
    )
    nom.clamp_dm.requires_grad_("clamp_m" in nominal_params)  # fits before v9 freed the rope at the markers
    sim = Simulator(spec, nom, [term])
    fit(sim, inputs.fit, dataclasses.replace(budget(quick).candidate, progress=False), desc="oracle")
    return float(per_recording_l1(sim.predict(inputs.check), inputs.check).mean())


def as_user_inputs(spec: RodSpec, fit: list, check: list, smooth_noise: bool = True) -> Inputs:
    """The recordings written to files and read back with ROD.json as a user gives them
    (`deform diagnose --rod --fit --check [--denoise off]`): the tool's own input checks and
    conventions apply (a rope longer than its marker span is simulated over the span, with a
    warning; recordings far noisier than the calibrated 0.3 mm are smoothed)."""
    import tempfile

    from deform.diagnose.spec import load_inputs
    from deform.io import save_recording

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name, recs in (("fit", fit), ("check", check)):
            (tmp / name).mkdir()
            for i, r in enumerate(recs):
                save_recording(tmp / name / f"{i:02d}.pkl", r.positions)
        (tmp / "rod.json").write_text(json.dumps(spec.model_dump()))
        return load_inputs(tmp / "rod.json", tmp / "fit", tmp / "check", smooth_noise=smooth_noise)


def equivalence_of(rep: dict) -> list[str]:
    """The equivalence class of the first selected term (itself alone when the data tell it apart)."""
    if not rep["selected"]:
        return []
    first = next((c for c in rep["candidates"] if c["name"] == rep["selected"][0] and c["round"] == 1), {})
    return first.get("equivalence_class", rep["selected"][:1])


# the independent simulators: the module that plants the effects and its generator function
INDEPENDENT = {
    "elastica": ("benchmarks.planted.elastica", "generate_elastica"),  # PyElastica, Cosserat rods
    "mujoco": ("benchmarks.planted.mujoco", "generate_mujoco"),  # MuJoCo, a chain of rigid capsules
}


def independent_simulator(simulator: str):
    """-> (EFFECTS, generate, detectability) of an independent simulator's planted-effect module
    (``benchmarks/planted/<simulator>.py``; imported when asked: PyElastica and MuJoCo are optional)."""
    import importlib

    module, generate = INDEPENDENT[simulator]
    mod = importlib.import_module(module)
    return mod.EFFECTS, getattr(mod, generate), mod.detectability
