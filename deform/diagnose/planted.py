"""Recordings with one planted effect, from a simulator configured unlike the tool's model.

The truth is a finer rod (``refine`` sub-edges per marker interval, so 3-5x more vertices) stepped
with a smaller time step, gripper motions replayed from real recordings (interpolated between
frames), markers a subset of the simulated nodes, and 0.3 mm motion-capture noise. One effect from
the candidate library (or none, for controls) is added to the truth with known parameters.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from deform.diagnose.simulator import Nominal, Simulator, between_markers, marker_nodes
from deform.diagnose.spec import RodSpec
from deform.io.recordings import Recording
from deform.model import gripped_indices
from deform.terms.library import make_term

EFFECTS = (
    "aerodynamic_drag",
    "internal_damping",
    "ground_contact",
    "point_mass",
    "stiffness_variation",
    "external_force",
    "mass_scale",
    "actuation_delay",
    "rest_curvature",
)


class MarkerMass(nn.Module):
    """Point masses on the marker nodes only (the truth of ``mass_scale``)."""

    def __init__(self, n: int, nodes: list[int], kg: float):
        super().__init__()
        w = torch.zeros(n, dtype=torch.float64)
        w[nodes] = kg
        self.register_buffer("w", w)

    def mass(self, mass):
        return mass + self.w


def _layout(markers0: np.ndarray, refine: int) -> tuple[np.ndarray, list[int]]:
    """Sim node positions (N, 3) interpolated from one frame of markers, and the marker node ids."""
    return between_markers(markers0, refine - 1), marker_nodes(len(markers0), refine - 1)


def planted_truth(effect: str | None, spec: RodSpec, lowest_z: float) -> dict:
    """Physical parameters of the planted effect, in the tool's conventions (for parameter error).

    Args:
        effect: a library term name, or None (a control).
        spec: the rod.
        lowest_z: lowest marker height of the source motions [m] (places a contact plane).

    Returns:
        Parameter name -> value.
    """
    return {
        None: {},
        # quadratic air drag only (a linear part is indistinguishable from the nominal damping); 3 /m
        # is ~5-30x the bare-air value of these rods (0.5 rho Cd d / mass per length ~ 0.1-0.7 /m):
        # a light, bulky rod (foam tube, rope with tags), chosen so the effect is visible above noise
        "aerodynamic_drag": {"linear_1_per_s": 0.0, "quadratic_1_per_m": 3.0},
        # Kelvin-Voigt bending-rate damping nu = eta_c / rho = 5e-5 m^4/s (0.6 /s in units of the 9.5 cm
        # marker spacing, nu / l^4; a relaxation time nu rho / EI of about 1 ms at the truth's EI)
        "internal_damping": {"bending_rate_damping_m4_per_s": 5e-5},
        "ground_contact": {"height_m": lowest_z, "stiffness_1_per_s2": 10000.0, "friction": 0.5},
        "point_mass": {"mass_kg": 0.25 * spec.mass_kg, "position_s": 0.35},
        "stiffness_variation": {"stiffness_ratio": 5.0, "start_s": 0.3, "end_s": 0.55},
        "external_force": {"ax_m_per_s2": 0.8, "ay_m_per_s2": 0.5},
        "mass_scale": {"marker_mass_kg": 0.004},
        "actuation_delay": {"delay_frames": 2.0},
        "rest_curvature": {"kappa1_per_m": 2.0, "kappa2_per_m": 0.0},  # radius 0.5 m (a coiled cable)
    }[effect]


def _truth_terms(effect, truth, n_sim, s_sim, marker_ids, refine, mean_marker_edge):
    if effect is None or effect == "actuation_delay":
        return []
    if effect == "mass_scale":
        return [MarkerMass(n_sim, marker_ids, truth["marker_mass_kg"])]
    # planted in the "up" convention's roll (the truth has no roll to read)
    term = make_term(effect, n_sim, s_sim, read_roll=False)
    with torch.no_grad():
        if effect == "aerodynamic_drag":
            term.log_lin.fill_(math.log(max(truth["linear_1_per_s"], 1e-7)))
            term.log_quad.fill_(math.log(truth["quadratic_1_per_m"]))
        elif effect == "internal_damping":  # the term is discretisation-independent (divided differences)
            term.log_nu.fill_(math.log(truth["bending_rate_damping_m4_per_s"] / term.scale))
        elif effect == "ground_contact":
            term.h0.fill_(truth["height_m"])
            term.raw_h.fill_(0.0)
            term.log_k.fill_(math.log(truth["stiffness_1_per_s2"]))
            term.raw_mu.fill_(math.log(truth["friction"] / (1 - truth["friction"])))
        elif effect == "point_mass":
            term.raw_pos.fill_(math.log(0.35 / 0.65))
            term.log_mass.fill_(math.log(truth["mass_kg"]))
            term.sigma = 0.25 / (n_sim - 1)
        elif effect == "stiffness_variation":
            c, w = 0.425, 0.25
            term.raw_c.fill_(math.log(c / (1 - c)))
            term.raw_w.fill_(math.log((w - 0.05) / 0.9 / (1 - (w - 0.05) / 0.9)))
            term.log_ratio.fill_(0.5 * math.log(truth["stiffness_ratio"]))
        elif effect == "external_force":
            term.set_field(truth["ax_m_per_s2"], truth["ay_m_per_s2"])
        elif effect == "rest_curvature":  # per-vertex turning = curvature x edge length
            edge = mean_marker_edge / refine
            term.raw.copy_(torch.tensor([truth["kappa1_per_m"] * edge, truth["kappa2_per_m"] * edge]) / 0.05)
    return [term]


def oracle_term(effect: str | None, truth: dict, n: int, arclength: np.ndarray, mean_marker_edge: float):
    """The tool's own term (marker resolution) set to the planted truth: the best the tool's model
    class can do with the right physics, used as the 'truth' end of the gap in the benchmark.

    Args:
        effect: a library term name, or None.
        truth: from :func:`planted_truth`.
        n: markers.
        arclength: (n,) normalised marker arc length.
        mean_marker_edge: mean marker spacing [m].

    Returns:
        The term, or None for a control.
    """
    if effect is None:
        return None
    if effect == "mass_scale":
        term = make_term("mass_scale", n, arclength)
        with torch.no_grad():
            term.raw_g.fill_(math.log(math.expm1(truth["marker_mass_kg"] / 1e-3)))
        return term
    if effect == "actuation_delay":
        term = make_term("actuation_delay", n, arclength)
        with torch.no_grad():
            d = truth["delay_frames"]
            term.raw.fill_(term.max_frames / term.scale * math.atanh(d / term.max_frames))
        return term
    (term,) = _truth_terms(effect, truth, n, arclength, list(range(n)), 1, mean_marker_edge)
    if effect == "point_mass":
        term.sigma = 0.5 / (n - 1)
    return term


def generate_planted(
    effect: str | None,
    sources: list[Recording],
    spec: RodSpec,
    n_frames: int = 300,
    refine: int = 3,
    substeps: int = 5,
    noise_m: float = 3e-4,
    seed: int = 0,
    ei: float = 3e-3,
    gj: float = 2e-3,
    damping: float = 1.0,
    settle_s: float = 1.0,
    truth_override: dict | None = None,
    nodes_out: list | None = None,
):
    """-> (recordings, truth params). Each source recording gives the gripper motion of one output.
    ``truth_override``: planted parameter values replacing :func:`planted_truth`'s (a size study).

    Args:
        effect: a library term name, or None (a control).
        sources: recordings whose gripper motions are replayed.
        spec: the rod.
        n_frames: frames per recording.
        refine: simulated nodes per marker interval.
        substeps: simulator steps per frame.
        noise_m: marker noise [m].
        seed: noise and choices.
        ei: bending stiffness [N m^2].
        gj: twisting stiffness [N m^2].
        damping: linear velocity damping [1/s] (in every dataset).
        settle_s: settling time before the first frame [s].
        truth_override: planted values to use instead.
        nodes_out: when given, receives the simulated rod's node positions (B, T, N, 3) [m] (noise-free)
            and the node ids of the markers: the state between the markers that recordings do not show.

    Returns:
        ``(recordings, truth)``.
    """
    rng = np.random.default_rng(seed)
    n = spec.n_vertices
    # a table just above the lowest points most recordings reach: the rod touches it in most of them
    lowest = float(np.percentile([r.positions[:n_frames, 2:-2, 2].min() for r in sources], 80))
    truth = {**planted_truth(effect, spec, lowest), **(truth_override or {})}
    starts = [int(rng.integers(0, r.n_frames - n_frames + 1)) for r in sources]
    grips_rec = np.stack(
        [r.positions[s : s + n_frames][:, gripped_indices(n)] for r, s in zip(sources, starts)]
    )
    x0_markers = np.stack([r.positions[s] for r, s in zip(sources, starts)])
    nodes, ids = zip(*[_layout(x, refine) for x in x0_markers])
    X0 = np.stack(nodes)
    n_sim = X0.shape[1]
    rest = np.linalg.norm(np.diff(X0, axis=1), axis=-1)
    s_sim = np.concatenate([[0.0], np.cumsum(rest.mean(0))])
    s_sim /= s_sim[-1]
    sim_spec = RodSpec(length_m=spec.length_m, mass_kg=spec.mass_kg, n_vertices=n_sim, dt=spec.dt / substeps)
    terms = _truth_terms(
        effect, truth, n_sim, s_sim, list(ids[0]), refine, float(rest[:, 1:-1].mean() * refine)
    )
    sim = Simulator(sim_spec, Nominal(ei, gj, damping), [t for t in terms if not isinstance(t, MarkerMass)])
    for t in terms:
        if isinstance(t, MarkerMass):
            sim.model.extensions.append(t)
    sim.sync()
    model = sim.model
    delay = truth.get("delay_frames", 0.0)
    # gripper input of the simulated rod at fractional frame f: the recorded grips at f - delay
    T = n_frames

    def grip_at(f: float) -> torch.Tensor:
        f = min(max(f - delay, 0.0), T - 1.0)
        i = min(math.floor(f), T - 2)
        a = f - i
        return torch.tensor((1 - a) * grips_rec[:, i] + a * grips_rec[:, i + 1])

    state = model.static_state(torch.tensor(X0), rest=torch.tensor(rest))
    g0 = grip_at(0.0)
    out = np.empty((len(sources), T, n, 3))
    every = np.empty((len(sources), T, n_sim, 3)) if nodes_out is not None else None
    with torch.no_grad():
        for _ in range(int(settle_s / sim_spec.dt)):
            state = model.step(state, g0)
        for k in range(T):
            for j in range(1, substeps + 1) if k else ():
                state = model.step(state, grip_at(k - 1 + j / substeps))
            out[:, k] = state.x.numpy()[:, list(ids[0])]
            if every is not None:
                every[:, k] = state.x.numpy()
    if nodes_out is not None:
        nodes_out.extend([every, list(ids[0])])
    out[:, :, gripped_indices(n)] = grips_rec  # the recorded inputs (the sim's ends lag them by `delay`)
    out = out + rng.normal(0, noise_m, out.shape)
    if not np.all(np.isfinite(out)):
        raise RuntimeError(f"planted {effect}: the truth simulation diverged")
    recs = [
        Recording(name=f"{effect or 'control'}_{seed}_{i}", positions=out[i], dt=spec.dt)
        for i in range(len(sources))
    ]
    return recs, truth
