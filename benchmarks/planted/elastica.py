"""Recordings with one planted effect, made by an independent rod simulator (PyElastica).

Why: ``deform.diagnose.planted`` plants effects into data made by *our own* discrete-elastic-rod
code, so the discrepancy tool is tested against its own discretisation, its own contact model and
its own damping law. Here the truth comes from PyElastica (Gazzola et al. 2018), a Cosserat-rod code
written by others, and nothing of ours is inside the simulation:

* discretisation: a shearable, extensible Cosserat rod (positions + element director frames,
  bending/twist couples on Voronoi regions, explicit position-Verlet with a sub-millisecond step)
  instead of our inextensible Kirchhoff DER with an implicit step at the frame rate; the rod is the
  rope's real length with free tails beyond the outer markers, and the markers are points of the
  centreline at fixed material arc length, interpolated between nodes (not nodes);
* gripping: the two gripped end portions (outer marker to second marker, snapped outwards to the
  node grid) are held rigidly, position and director frame, by a kinematic PyElastica constraint
  that follows the recorded gripper poses (interpolated between frames, the frame's roll carried
  by parallel transport);
* damping: every case has a small material (Kelvin-Voigt-like) damping, a 4th-difference filter of
  the nodal velocities and element angular velocities (PyElastica's Laplace dissipation filter of
  order 2, with a tunable weight); ``internal_damping`` makes it strong (and shortens the time step
  if needed to keep the filter weight at most 1). There is no linear velocity (air) damping at all,
  unlike our nominal model;
* contact: PyElastica's rod-plane contact (a spring-dashpot on the rod's surface, radius included)
  with its Coulomb friction (static and kinetic, axial and rolling), not our penalty plane;
* air drag: a quadratic normal-velocity drag forcing; wind: a horizontal acceleration (the law of
  PyElastica's GravityForces); rest curvature: PyElastica's rest_kappa; a clip: extra nodal mass;
  a stiff segment: the bend matrix scaled over a stretch.

All rods (one per source) are simulated together in one PyElastica collection; each feature (grips,
forces, damping) is added once and acts on every rod, which steps them fast (see ``_features``).

Each source recording gives the gripper motion of one output recording, over a window of
``n_frames`` frames at a seeded offset. The grippers that drive the rod move as the recorded ones
with mocap spikes and jitter filtered out (real grippers move smoothly), and a 0.2 s lead-in in
which they accelerate from rest to their first velocity (no velocity jump). The rod starts as a
spline through the first frame's markers with its material length, settles under gravity for
``SETTLE_S`` with the grips held (and extra settling damping), then the grips move and the markers
are read at 100 Hz. The gripped markers are then set to the recorded (raw) inputs and 0.3 mm of
Gaussian motion-capture noise is added to every marker.

Rope beyond the markers: the rod has the rope's real length; the part beyond the marker span is
split into two equal free tails past the outer markers (5.7 cm for DLO1, 1.3 cm for DLO3), which
hang from the grippers. The markers' material positions are the median marker spacings.

    python benchmarks/elastica_planted.py [--sources 8] [--frames 300]   # detectability table

The rope's geometry (markers, grips, starting curve) is shared with MuJoCo's: benchmarks/planted/geometry.py.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from benchmarks.planted.detectability import detectability
from benchmarks.planted.geometry import (
    LEAD_FRAMES,
    _frames,
    _unit,
    driving_grips,
    held_nodes,
    initial_curve,
    marker_layout,
    transport,
)
from deform.diagnose.spec import RodSpec
from deform.io.recordings import Recording
from deform.model import gripped_indices

__all__ = [
    "DEFAULTS",
    "EFFECTS",
    "LEAD_FRAMES",
    "ROD_KINDS",
    "detectability",
    "driving_grips",
    "generate_elastica",
    "held_nodes",
    "initial_curve",
    "marker_layout",
    "planted_truth",
    "transport",
]

EFFECTS = (
    "aerodynamic_drag",
    "ground_contact",
    "point_mass",
    "stiffness_variation",
    "external_force",
    "internal_damping",
    "rest_curvature",
    "actuation_delay",
)

# Material of the two reference rods. The rod simulated takes its length and mass from the RodSpec
# passed in (these lengths / masses are the references the values were chosen for); radius, bending
# stiffness and damping come from here. Young's modulus is EI / (pi r^4 / 4) (a solid round section);
# the shear modulus is E / 3 (incompressible). The radius sets the stretch stiffness EA = 4 EI / r^2:
# it is a compromise of near-inextensibility and the explicit time step (the rotational shear mode
# limits dt to about 1.5x the step used). Measured largest element strain per frame (8 sources, 300
# frames): 99th percentile 0.6 % (light) / 0.3 % (stiff), brief local peaks at a gripper 1.4 / 0.6 %.
ROD_KINDS = {
    # like DLO1 (1.152 m, 34.5 g), a soft cable: 8 mm thick, E 5.0 MPa, EA 250 N, 600 kg/m^3
    "light": {
        "length_m": 1.152,
        "mass_kg": 0.0345,
        "radius_m": 0.004,
        "bend_stiffness_Nm2": 1.0e-3,
        "material_damping_m4_per_s": 2e-6,
        "n_elements": 48,
        "dt_s": 5e-5,
    },
    # like DLO3 (0.998 m, 96.8 g), the stiffest of the five: 12 mm thick, E 11.8 MPa, EA 1330 N, 860 kg/m^3
    "stiff": {
        "length_m": 0.998,
        "mass_kg": 0.0968,
        "radius_m": 0.006,
        "bend_stiffness_Nm2": 1.2e-2,
        "material_damping_m4_per_s": 2e-6,
        "n_elements": 42,
        "dt_s": 5e-5,
    },
    # a third rod, added after the two above were benchmarked and never tuned on: DLO2's length,
    # mass and gripper motions (0.996 m, 65.2 g), 10 mm thick, EI between the light and stiff rods
    "medium": {
        "length_m": 0.996,
        "mass_kg": 0.0652,
        "radius_m": 0.005,
        "bend_stiffness_Nm2": 4.0e-3,
        "material_damping_m4_per_s": 2e-6,
        "n_elements": 42,
        "dt_s": 5e-5,
    },
}
SETTLE_S = 1.0  # settling time before the first recorded frame [s]
SETTLE_DAMPING = 10.0  # extra velocity damping while settling [1/s]
GRAVITY = 9.81

# Planted parameters at strength 1 per rod kind, and what ``strength`` scales. The sizes are tuned
# (seed 0, 8 DLO1 / DLO3 train sources, 300 frames: see the module's __main__) so that each effect
# moves the markers by about 0.5-2 cm (L1) from its paired control; the stiff, heavy rod needs a
# stronger wind and a stronger internal damping than the light one to show them as much.
# Measured L1 vs the paired control [cm], light / stiff: drag 1.35 / 0.83, ground 1.40 / 1.41,
# clip 1.35 / 1.72, stiff segment 1.30 / 1.48, wind 0.83 / 0.77, internal damping 0.63 / 0.65,
# rest curvature 0.78 / 1.28, delay 0.84 / 0.70. Internal damping above dx^4 / (16 dt) shortens dt.
_COMMON = {
    "aerodynamic_drag": {"quadratic_1_per_m": 3.0},  # x strength
    "ground_contact": {"stiffness_1_per_s2": 1.0e4, "friction": 0.5},  # friction x strength (<= 1.5)
    "point_mass": {"mass_fraction": 0.20, "position_s": 0.35},  # mass x strength
    "stiffness_variation": {"stiffness_ratio": 5.0, "start_s": 0.30, "end_s": 0.55},  # (ratio - 1) x strength
    "rest_curvature": {"kappa1_per_m": 2.0, "kappa2_per_m": 0.0},  # x strength (radius 0.5 m)
    "actuation_delay": {"delay_frames": 2.0},  # x strength
}
DEFAULTS = {
    "light": {
        **_COMMON,
        "external_force": {"ax_m_per_s2": 1.2, "ay_m_per_s2": 0.75},  # x strength
        "internal_damping": {"bending_rate_damping_m4_per_s": 2e-4},  # x strength
        "rest_curvature": {"kappa1_per_m": 3.0, "kappa2_per_m": 0.0},  # radius 0.33 m
        "actuation_delay": {"delay_frames": 3.0},
    },
    "stiff": {
        **_COMMON,
        "external_force": {"ax_m_per_s2": 3.2, "ay_m_per_s2": 2.0},
        "internal_damping": {"bending_rate_damping_m4_per_s": 1e-3},
    },
    "medium": {  # between the light and stiff rods' sizes (not measured before the benchmark ran)
        **_COMMON,
        "external_force": {"ax_m_per_s2": 2.0, "ay_m_per_s2": 1.25},
        "internal_damping": {"bending_rate_damping_m4_per_s": 5e-4},
        "rest_curvature": {"kappa1_per_m": 2.5, "kappa2_per_m": 0.0},
    },
}


def _elastica():
    import elastica as ea  # imported lazily: an optional dependency (the `bench` extra)

    return ea


def _grip_tracks(
    grips: np.ndarray,
    s_markers: np.ndarray,
    s_nodes: np.ndarray,
    held_a: np.ndarray,
    held_b: np.ndarray,
    d1_a: np.ndarray,
    d1_b: np.ndarray,
    frame_dt: float,
):
    """Per-frame targets of the held nodes and elements, from the recorded grips (T, 4, 3).

    -> P (T, 3, nh) positions, V (T, 3, nh) velocities to the next frame, Q (T, 3, 3, ne) directors,
    W (T, 3, ne) material-frame angular velocities to the next frame, node ids, element ids."""
    T = len(grips)
    p_a, t_a = grips[:, 0], _unit(grips[:, 1] - grips[:, 0])  # outer marker, inward edge
    p_b, u_b = grips[:, 3], _unit(grips[:, 2] - grips[:, 3])
    pos_a = p_a[:, None] + t_a[:, None] * (s_nodes[held_a] - s_markers[0])[None, :, None]
    pos_b = p_b[:, None] + u_b[:, None] * (s_markers[-1] - s_nodes[held_b])[None, :, None]
    tang = {"a": t_a, "b": -u_b}  # element tangents point along increasing material s
    d1 = {"a": [d1_a], "b": [d1_b]}
    for k in range(1, T):
        for e in "ab":
            d1[e].append(transport(d1[e][-1], tang[e][k]))
    Q_a, Q_b = _frames(t_a, np.array(d1["a"])), _frames(-u_b, np.array(d1["b"]))
    omega = {}
    for e, Q in (("a", Q_a), ("b", Q_b)):
        t = tang[e]
        w = np.zeros((T, 3))
        w[:-1] = np.cross(t[:-1], t[1:] - t[:-1]) / frame_dt  # minimal rotation: no spin about t
        omega[e] = np.einsum("tij,tj->ti", Q, w)
    el_a, el_b = held_a[:-1], held_b[:-1]
    P = np.concatenate([pos_a, pos_b], axis=1).transpose(0, 2, 1)
    V = np.zeros_like(P)
    V[:-1] = np.diff(P, axis=0) / frame_dt
    Q = np.concatenate(
        [np.repeat(Q_a[..., None], len(el_a), -1), np.repeat(Q_b[..., None], len(el_b), -1)], -1
    )
    W = np.concatenate(
        [np.repeat(omega["a"][..., None], len(el_a), -1), np.repeat(omega["b"][..., None], len(el_b), -1)], -1
    )
    return (
        np.ascontiguousarray(P),
        np.ascontiguousarray(V),
        np.ascontiguousarray(Q),
        np.ascontiguousarray(W),
        np.concatenate([held_a, held_b]).astype(np.int64),
        np.concatenate([el_a, el_b]).astype(np.int64),
    )


# ----------------------------------------------------------------------------------------------
# numba kernels (numba comes with PyElastica)
# ----------------------------------------------------------------------------------------------


@functools.cache  # compiled once per process (cache=False: no on-disk cache, see below)
def _kernels():
    """The per-rod kernels, and their ``*_all`` loops over the rods' column ranges of the memory
    block (``n0:n1`` nodes, ``e0:e1`` elements of rod r), which call the per-rod kernels on the rods'
    slices: one Python call per step acts on every rod, with each rod's arithmetic unchanged."""
    from elastica._contact_functions import (
        _calculate_contact_forces_rod_plane_with_anisotropic_friction as rod_plane_contact,
    )
    from numba import njit

    jit = njit(cache=False)  # no on-disk cache: it records the importing module path (benchmarks.x vs x)

    @jit
    def grip_values(tau, P, Q, nodes, elems, pos, dirs):
        T = P.shape[0]
        f = min(max(tau, 0.0), T - 1.0)
        i = min(int(f), T - 2)
        a = f - i
        for c in range(3):
            for j in range(nodes.shape[0]):
                pos[c, nodes[j]] = (1 - a) * P[i, c, j] + a * P[i + 1, c, j]
            for r in range(3):
                for j in range(elems.shape[0]):
                    dirs[r, c, elems[j]] = (1 - a) * Q[i, r, c, j] + a * Q[i + 1, r, c, j]

    @jit
    def grip_rates(tau, V, W, nodes, elems, vel, omega):
        T = V.shape[0]
        inside = 0.0 <= tau < T - 1.0
        i = min(max(int(tau), 0), T - 2)
        for c in range(3):
            for j in range(nodes.shape[0]):
                vel[c, nodes[j]] = V[i, c, j] if inside else 0.0
            for j in range(elems.shape[0]):
                omega[c, elems[j]] = W[i, c, j] if inside else 0.0

    @jit
    def fourth_difference_damp(rate, weight):
        # rate -= weight * (D4 rate) / 16: PyElastica's order-2 Laplace filter with a weight; the
        # two end values are left untouched (and the filter term at them is zero), as in PyElastica
        n = rate.shape[1]
        lap = np.zeros_like(rate)
        for c in range(3):
            for k in range(1, n - 1):
                lap[c, k] = 0.25 * (2.0 * rate[c, k] - rate[c, k - 1] - rate[c, k + 1])
        for c in range(3):
            for k in range(1, n - 1):
                rate[c, k] -= weight * 0.25 * (2.0 * lap[c, k] - lap[c, k - 1] - lap[c, k + 1])

    @jit
    def add_acceleration(acc, mass, forces):  # PyElastica's GravityForces: forces += acc (x) mass
        for c in range(3):
            for k in range(mass.shape[0]):
                forces[c, k] += acc[c] * mass[k]

    @jit
    def quadratic_drag(coef, mass, vel, tangents, forces):
        n = vel.shape[1]
        for k in range(n):  # node tangent: mean of the adjacent element tangents
            a, b = max(k - 1, 0), min(k, n - 2)
            t0 = tangents[0, a] + tangents[0, b]
            t1 = tangents[1, a] + tangents[1, b]
            t2 = tangents[2, a] + tangents[2, b]
            norm = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
            t0, t1, t2 = t0 / norm, t1 / norm, t2 / norm
            vt = vel[0, k] * t0 + vel[1, k] * t1 + vel[2, k] * t2
            n0, n1, n2 = vel[0, k] - vt * t0, vel[1, k] - vt * t1, vel[2, k] - vt * t2
            c = coef * mass[k] * math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            forces[0, k] -= c * n0
            forces[1, k] -= c * n1
            forces[2, k] -= c * n2

    @jit
    def grip_values_all(tau, P, Q, nodes, elems, n0, n1, e0, e1, pos, dirs):
        for r in range(n0.shape[0]):
            grip_values(tau, P[r], Q[r], nodes, elems, pos[:, n0[r] : n1[r]], dirs[:, :, e0[r] : e1[r]])

    @jit
    def grip_rates_all(tau, V, W, nodes, elems, n0, n1, e0, e1, vel, omega):
        for r in range(n0.shape[0]):
            grip_rates(tau, V[r], W[r], nodes, elems, vel[:, n0[r] : n1[r]], omega[:, e0[r] : e1[r]])

    @jit
    def damp_all(weight, settling, factor, n0, n1, e0, e1, vel, omega):
        for r in range(n0.shape[0]):
            v, w = vel[:, n0[r] : n1[r]], omega[:, e0[r] : e1[r]]
            fourth_difference_damp(v, weight)
            fourth_difference_damp(w, weight)
            if settling:  # then the settling damping of the same rod
                for c in range(3):
                    for k in range(v.shape[1]):
                        v[c, k] *= factor
                    for k in range(w.shape[1]):
                        w[c, k] *= factor

    @jit
    def forces_all(gravity, wind, drag, n0, n1, e0, e1, mass, vel, tangents, forces):
        # per rod, in the order the per-rod forcings were added: gravity, wind (an acceleration), drag
        for r in range(n0.shape[0]):
            m, f = mass[n0[r] : n1[r]], forces[:, n0[r] : n1[r]]
            add_acceleration(gravity, m, f)
            if wind.shape[0] == 3:
                add_acceleration(wind, m, f)
            if drag > 0.0:
                quadratic_drag(drag, m, vel[:, n0[r] : n1[r]], tangents[:, e0[r] : e1[r]], f)

    @jit
    def contact_all(
        origin, normal, c, n0, n1, e0, e1, radius, mass, tangents, pos, dirs, vel, omega, fi, fe, ti, te
    ):
        # PyElastica's RodPlaneContactWithAnisotropicFriction.apply_contact on each rod's slices;
        # c: surface_tol, slip_velocity_tol, k, nu, kinetic mu (3), static mu (3)
        for r in range(n0.shape[0]):
            nr, er = slice(n0[r], n1[r]), slice(e0[r], e1[r])
            rod_plane_contact(
                origin, normal, c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8], c[9],
                radius[er], mass[nr], tangents[:, er], pos[:, nr], dirs[:, :, er], vel[:, nr],
                omega[:, er], fi[:, nr], fe[:, nr], ti[:, er], te[:, er],
            )  # fmt: skip

    return grip_values_all, grip_rates_all, damp_all, forces_all, contact_all


# ----------------------------------------------------------------------------------------------
# the PyElastica system
# ----------------------------------------------------------------------------------------------


def _features(ea, kernels):
    """PyElastica feature classes (defined here so that importing this module needs no PyElastica).

    Each feature is added once, on the first rod, and acts on every rod: PyElastica keeps all rods
    of a collection in one memory block (each rod's arrays are views of its columns) and steps the
    block as one system, so per-rod features would cost a Python call per rod and step for a few
    microseconds of work each. A feature's operator runs when every rod is at the same point of the
    step (constraints after the block's kinematic / dynamic update, forcings after its internal
    forces, dampers after all constraints' rates), touches only rod r's columns for rod r, and
    does each rod's work in the order the per-rod features did: the same numbers, bit for bit."""
    grip_values_all, grip_rates_all, damp_all, forces_all, contact_all = kernels

    class Sim(ea.BaseSystemCollection, ea.Constraints, ea.Forcing, ea.Damping):
        pass

    class RodBlock:
        """The memory block of ``rods`` (found at the first call, after ``sim.finalize`` built it)
        and each rod's node and element column ranges in it."""

        def __init__(self, sim, rods):
            self.sim, self.rods, self.block = sim, rods, None

        def __call__(self):
            if self.block is None:
                (block,) = [b for b in self.sim.final_systems() if hasattr(b, "start_idx_in_rod_nodes")]
                R = len(self.rods)
                ranges = [block.start_idx_in_rod_nodes[:R], block.end_idx_in_rod_nodes[:R]]
                ranges += [block.start_idx_in_rod_elems[:R], block.end_idx_in_rod_elems[:R]]
                self.ranges = tuple(np.ascontiguousarray(x, dtype=np.int64) for x in ranges)
                n0, _, e0, _ = self.ranges
                for r, rod in enumerate(self.rods):  # the rods' arrays are these columns of the block
                    for name, start in (("position_collection", n0), ("director_collection", e0)):
                        column = getattr(block, name)[..., start[r]]
                        assert getattr(rod, name).ctypes.data == column.ctypes.data, (name, r)
                self.block = block
            return self.block

    class GripTracks(ea.ConstraintBase):
        """Every rod's two gripped end portions follow its recorded gripper poses (fractional frame
        ``(t - settle) / frame_dt - delay``; the first frame's pose before that). ``tracks``: the
        rods' :func:`_grip_tracks` stacked (P, V, Q, W with a leading rod axis; shared node ids)."""

        def __init__(self, block, tracks, settle_s, frame_dt, delay_frames, **kwargs):
            super().__init__(**kwargs)
            self.rod_block = block
            self.P, self.V, self.Q, self.W, self.nodes, self.elems = tracks
            self.settle_s, self.frame_dt, self.delay = settle_s, frame_dt, delay_frames

        def _tau(self, time):
            return (float(time) - self.settle_s) / self.frame_dt - self.delay

        def constrain_values(self, system, time):
            b = self.rod_block()
            args = (self.P, self.Q, self.nodes, self.elems, *self.rod_block.ranges)
            grip_values_all(self._tau(time), *args, b.position_collection, b.director_collection)

        def constrain_rates(self, system, time):
            b = self.rod_block()
            args = (self.V, self.W, self.nodes, self.elems, *self.rod_block.ranges)
            grip_rates_all(self._tau(time), *args, b.velocity_collection, b.omega_collection)

    class MaterialDamping(ea.DamperBase):
        """Kelvin-Voigt-like damping of every rod: a weighted 4th-difference (order-2 Laplace) filter
        of the nodal velocities and the element angular velocities, every step. Continuum
        equivalent: a bending rate damping dv/dt = -nu d4v/ds4 with nu = weight dx^4 / (16 dt)
        [m^4/s]. Then, while the rods settle (``time < until_s``), a uniform velocity damping
        ``settle_rate`` [1/s]."""

        def __init__(self, block, weight, settle_rate, until_s, time_step, **kwargs):
            super().__init__(**kwargs)
            self.rod_block, self.weight = block, float(weight)
            self.factor, self.until = math.exp(-settle_rate * time_step), until_s

        def dampen_rates(self, system, time):
            b = self.rod_block()
            args = (self.weight, bool(time < self.until), self.factor, *self.rod_block.ranges)
            damp_all(*args, b.velocity_collection, b.omega_collection)

    class RodForces(ea.NoForces):
        """On every rod: gravity, then ``wind`` (a uniform acceleration, PyElastica's GravityForces
        law) if given, then air drag quadratic in the normal velocity (f = -c m |v_n| v_n at every
        node, c = ``drag``) if ``drag`` > 0, then the rod-plane ``contact`` (PyElastica's
        RodPlaneContactWithAnisotropicFriction with a Plane) if given."""

        def __init__(self, block, gravity, wind=None, drag=0.0, contact=None):
            super().__init__()
            self.rod_block, self.gravity, self.drag = block, np.asarray(gravity, float), float(drag)
            self.wind = np.zeros(0) if wind is None else np.asarray(wind, float)
            self.law, self.plane = (None, None) if contact is None else contact
            if self.law is not None:  # its coefficients, in the order of its numba kernel's arguments
                c = self.law
                mu = [c.kinetic_mu_forward, c.kinetic_mu_backward, c.kinetic_mu_sideways]
                mu += [c.static_mu_forward, c.static_mu_backward, c.static_mu_sideways]
                self.coefs = np.array([c.surface_tol, c.slip_velocity_tol, c.k, c.nu, *mu], float)

        def apply_forces(self, system, time=0.0):
            b = self.rod_block()
            ranges = self.rod_block.ranges
            args = (b.mass, b.velocity_collection, b.tangents, b.external_forces)
            forces_all(self.gravity, self.wind, self.drag, *ranges, *args)
            if self.law is not None:
                contact_all(
                    self.plane.origin, self.plane.normal, self.coefs, *ranges, b.radius, b.mass, b.tangents,
                    b.position_collection, b.director_collection, b.velocity_collection, b.omega_collection,
                    b.internal_forces, b.external_forces, b.internal_torques, b.external_torques,
                )  # fmt: skip

    return Sim, RodBlock, GripTracks, MaterialDamping, RodForces


def planted_truth(
    effect: str | None,
    rod_kind: str = "light",
    strength: float = 1.0,
    lowest_z: float = 0.0,
    spec: RodSpec | None = None,
    defaults: dict | None = None,
) -> dict:
    """Planted parameters (``defaults[rod_kind]``, by default this module's ``DEFAULTS``, scaled by
    ``strength``) in the tool's conventions."""
    if effect is None:
        return {}
    d = dict((DEFAULTS if defaults is None else defaults)[rod_kind][effect])
    s = float(strength)
    if effect == "aerodynamic_drag":
        d = {"linear_1_per_s": 0.0, "quadratic_1_per_m": d["quadratic_1_per_m"] * s}
    elif effect == "ground_contact":
        d = {
            "height_m": lowest_z,
            "stiffness_1_per_s2": d["stiffness_1_per_s2"],
            "friction": min(d["friction"] * s, 1.5),
        }
    elif effect == "point_mass":
        d = {
            "mass_kg": d["mass_fraction"] * s * (spec.mass_kg if spec else 1.0),
            "position_s": d["position_s"],
        }
    elif effect == "stiffness_variation":
        d["stiffness_ratio"] = 1.0 + (d["stiffness_ratio"] - 1.0) * s
    elif effect == "external_force":
        d = {"ax_m_per_s2": d["ax_m_per_s2"] * s, "ay_m_per_s2": d["ay_m_per_s2"] * s}
    elif effect == "internal_damping":
        d["bending_rate_damping_m4_per_s"] *= s
    elif effect == "rest_curvature":
        d = {"kappa1_per_m": d["kappa1_per_m"] * s, "kappa2_per_m": d["kappa2_per_m"] * s}
    elif effect == "actuation_delay":
        d["delay_frames"] *= s
    return d


def _marker_weights(s_markers: np.ndarray, dx: float, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Node index and weight of the linear interpolation of each marker between two nodes."""
    f = s_markers / dx
    j = np.clip(np.floor(f).astype(int), 0, n_nodes - 2)
    return j, f - j


def generate_elastica(
    effect: str | None,
    sources: list[Recording],
    spec: RodSpec,
    rod_kind: str = "light",
    n_frames: int = 300,
    seed: int = 0,
    noise_m: float = 3e-4,
    strength: float = 1.0,
    grip_snap: str = "outward",
) -> tuple[list[Recording], dict]:
    """-> (recordings, truth). One output recording per source: the source's gripper motion over a
    window of ``n_frames`` at a seeded offset, replayed on a PyElastica rod with one planted
    ``effect`` (None: a control) of size ``strength`` (1 = ``DEFAULTS``). ``truth`` holds the
    planted parameters plus "effect", "rod_kind", the rod's material and the numerics.
    ``grip_snap``: how the clamps meet the node grid (:func:`held_nodes`; the benchmark's rows are
    "outward")."""
    if effect is not None and effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; expected one of {EFFECTS}")
    if rod_kind not in ROD_KINDS:
        raise ValueError(f"unknown rod kind {rod_kind!r}; expected one of {tuple(ROD_KINDS)}")
    ea = _elastica()
    Sim, RodBlock, GripTracks, MaterialDamping, RodForces = _features(ea, _kernels())
    kind = ROD_KINDS[rod_kind]
    rng = np.random.default_rng(seed)
    n = spec.n_vertices
    if any(r.n_vertices != n for r in sources):
        raise ValueError(f"sources must have {n} markers")
    frame_dt = spec.dt
    L, n_el, dt = spec.length_m, int(kind["n_elements"]), float(kind["dt_s"])
    r0, ei = kind["radius_m"], kind["bend_stiffness_Nm2"]
    area = math.pi * r0**2
    youngs = ei / (math.pi * r0**4 / 4)
    density = spec.mass_kg / (L * area)
    dx = L / n_el
    s_nodes = np.arange(n_el + 1) * dx
    s_markers, tail = marker_layout(sources, L)
    span = s_markers[-1] - s_markers[0]
    held_a = held_nodes(s_nodes, s_markers[0], s_markers[1], inner="b", snap=grip_snap)
    held_b = held_nodes(s_nodes, s_markers[-2], s_markers[-1], inner="a", snap=grip_snap)

    starts = [int(rng.integers(0, r.n_frames - n_frames + 1)) for r in sources]
    # a table just above the lowest points most recordings reach: the rope touches it in most of them
    lowest = float(
        np.percentile([r.positions[s : s + n_frames, 2:-2, 2].min() for r, s in zip(sources, starts)], 80)
    )
    truth = planted_truth(effect, rod_kind, strength, lowest, spec)
    nu = kind["material_damping_m4_per_s"] + truth.get("bending_rate_damping_m4_per_s", 0.0)
    dt = min(
        dt, frame_dt / math.ceil(frame_dt / (dx**4 / (16 * nu)))
    )  # filter weight <= 1, whole steps per frame
    delay = truth.get("delay_frames", 0.0)

    grips_rec = np.stack(
        [r.positions[s : s + n_frames][:, gripped_indices(n)] for r, s in zip(sources, starts)]
    )
    sim = Sim()
    rods, tracks = [], []
    for i, (r, st) in enumerate(zip(sources, starts)):
        drive = driving_grips(grips_rec[i])
        markers0 = r.positions[st].copy()
        markers0[gripped_indices(n)] = drive[0]  # the grips where settling starts
        x0 = initial_curve(markers0, s_markers, s_nodes, held_a, held_b)
        t = _unit(np.diff(x0, axis=0))
        up = np.array([0.0, 0.0, 1.0]) if abs(t[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        d1 = [transport(up, t[0])]
        for k in range(1, len(t)):
            d1.append(transport(d1[-1], t[k]))
        directors = _frames(t, np.array(d1)).transpose(1, 2, 0).copy()
        rod = ea.CosseratRod.straight_rod(
            n_el,
            np.zeros(3),
            np.array([1.0, 0, 0]),
            np.array([0, 0, 1.0]),
            L,
            r0,
            density,
            youngs_modulus=youngs,
            shear_modulus=youngs / 3.0,
        )
        rod.position_collection[:] = x0.T
        rod.director_collection[:] = directors
        s_vor = s_nodes[1:-1]  # Voronoi regions (between elements) sit on the interior nodes
        u_vor = (s_vor - s_markers[0]) / span  # normalised position along the marker span
        if effect == "point_mass":  # a clip: extra mass shared by the two nodes around it
            s_clip = s_markers[0] + truth["position_s"] * span
            j = int(s_clip // dx)
            a = s_clip / dx - j
            rod.mass[j] += (1 - a) * truth["mass_kg"]
            rod.mass[j + 1] += a * truth["mass_kg"]
        elif effect == "stiffness_variation":
            inside = (u_vor >= truth["start_s"]) & (u_vor <= truth["end_s"])
            rod.bend_matrix[0, 0, inside] *= truth["stiffness_ratio"]
            rod.bend_matrix[1, 1, inside] *= truth["stiffness_ratio"]
        elif effect == "rest_curvature":
            rod.rest_kappa[0, :] = truth["kappa1_per_m"]
            rod.rest_kappa[1, :] = truth["kappa2_per_m"]
        sim.append(rod)
        rods.append(rod)
        tracks.append(
            _grip_tracks(
                drive,
                s_markers,
                s_nodes,
                held_a,
                held_b,
                directors[0, :, held_a[0]],
                directors[0, :, held_b[-1] - 1],
                frame_dt,
            )
        )
    # each feature is added once and acts on every rod (see _features)
    block = RodBlock(sim, rods)
    stacked = tuple(np.ascontiguousarray(np.stack([tr[k] for tr in tracks])) for k in range(4))
    sim.constrain(rods[0]).using(
        GripTracks,
        block=block,
        tracks=(*stacked, *tracks[0][4:]),
        settle_s=SETTLE_S,
        frame_dt=frame_dt,
        delay_frames=delay,
    )
    forcing = {}
    if effect == "external_force":
        forcing["wind"] = np.array([truth["ax_m_per_s2"], truth["ay_m_per_s2"], 0.0])
    elif effect == "aerodynamic_drag":
        forcing["drag"] = truth["quadratic_1_per_m"]
    elif effect == "ground_contact":
        plane = ea.Plane(plane_origin=np.array([0.0, 0.0, lowest - r0]), plane_normal=np.array([0.0, 0, 1]))
        m_el = spec.mass_kg / n_el
        k_c = truth["stiffness_1_per_s2"] * m_el
        law = ea.RodPlaneContactWithAnisotropicFriction(
            k=k_c,
            nu=2.0 * math.sqrt(k_c * m_el),
            slip_velocity_tol=1e-4,
            static_mu_array=np.full(3, truth["friction"]),
            kinetic_mu_array=np.full(3, truth["friction"]),
        )
        forcing["contact"] = (law, plane)
    sim.add_forcing_to(rods[0]).using(
        RodForces, block=block, gravity=np.array([0.0, 0.0, -GRAVITY]), **forcing
    )
    sim.dampen(rods[0]).using(
        MaterialDamping,
        block=block,
        weight=16.0 * nu * dt / dx**4,
        settle_rate=SETTLE_DAMPING,
        until_s=SETTLE_S,
        time_step=dt,
    )
    sim.finalize()
    stepper = ea.PositionVerlet()
    jm, am = _marker_weights(s_markers, dx, n_el + 1)
    out = np.empty((len(sources), n_frames, n, 3))
    strain = []  # per frame and rod: the largest element strain |dilatation - 1|

    def read(k):
        for i, rod in enumerate(rods):
            x = rod.position_collection
            if not np.all(np.isfinite(x)) or np.abs(x).max() > 100.0:
                raise RuntimeError(f"elastica {effect}: the simulation diverged (rod {i}, frame {k})")
            out[i, k] = ((1 - am) * x[:, jm] + am * x[:, jm + 1]).T
            strain.append(float(np.abs(rod.dilatation - 1).max()))

    t_sim = 0.0
    settle_steps = round(SETTLE_S / dt)
    per_frame = round(frame_dt / dt)
    for _ in range(settle_steps):
        t_sim = stepper.step(sim, t_sim, dt)
    t_sim = SETTLE_S  # exact frame times (PyElastica accumulates float time)
    for k in range(-LEAD_FRAMES, n_frames):
        if k > -LEAD_FRAMES:
            for _ in range(per_frame):
                t_sim = stepper.step(sim, t_sim, dt)
            t_sim = SETTLE_S + (k + LEAD_FRAMES) * frame_dt
        if k >= 0:
            read(k)
    out[:, :, gripped_indices(n)] = grips_rec  # the recorded inputs (the rod's ends lag them by `delay`)
    out = out + rng.normal(0.0, noise_m, out.shape)
    if not np.all(np.isfinite(out)):
        raise RuntimeError(f"elastica {effect}: the simulation diverged")
    recs = [
        Recording(name=f"elastica_{rod_kind}_{effect or 'control'}_{seed}_{i}", positions=out[i], dt=frame_dt)
        for i in range(len(sources))
    ]
    truth.update(
        {
            "effect": effect,
            "rod_kind": rod_kind,
            "strength": float(strength),
            "rod": {
                "length_m": L,
                "mass_kg": spec.mass_kg,
                "radius_m": r0,
                "youngs_modulus_Pa": youngs,
                "shear_modulus_Pa": youngs / 3.0,
                "bend_stiffness_Nm2": ei,
                "stretch_stiffness_N": youngs * area,
                "material_damping_m4_per_s": kind["material_damping_m4_per_s"],
                "tail_m": tail,
                "marker_s_m": s_markers.tolist(),
            },
            "numerics": {
                "n_elements": n_el,
                "dt_s": dt,
                "settle_s": SETTLE_S,
                "max_stretch": max(strain),
                "p99_stretch": float(np.percentile(strain, 99)),
                "starts": starts,
                # the clamps' material extent [m]: the benchmark's rows hold past the gripped markers
                "held_s_m": [
                    [float(s_nodes[held_a[0]]), float(s_nodes[held_a[-1]])],
                    [float(s_nodes[held_b[0]]), float(s_nodes[held_b[-1]])],
                ],
            },
        }
    )
    return recs, truth


def element_strain(truth: dict) -> str:
    """The control's numerics for the detectability table."""
    n = truth["numerics"]
    return f"element strain max {n['max_stretch'] * 100:.2f} % p99 {n['p99_stretch'] * 100:.2f} %"
