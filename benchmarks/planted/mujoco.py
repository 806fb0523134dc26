"""Recordings with one planted effect, made by a third rod simulator (MuJoCo).

Why: the discrepancy tool is scored on recordings from simulators we do not have. PyElastica
(``benchmarks/planted/elastica.py``) is one independent simulator; this is a second one, built on
a different mechanics altogether, so that a result that only holds for Cosserat rods (or only for
our own discrete elastic rods) shows up. Nothing of ours is inside the simulation:

* discretisation: an articulated chain of rigid capsules (about 3 cm long) joined by ball joints,
  simulated in generalised (joint) coordinates by MuJoCo's rigid-body dynamics (a kinematic tree
  rooted at the middle link), stepped by MuJoCo 4's ``discrete`` integrator at 0.5 ms (implicit in
  the joint springs, the joint damping and the constraints, all in one effective metric). The chain
  is exactly inextensible and unshearable (rigid links), has the rotary inertia of whole links, and
  bends and twists only at the joints; our DER and PyElastica's Cosserat rod are continua
  discretised at nodes. The rope has its real length with free tails beyond the outer markers; the
  markers are material points on the links' axes at fixed arc length (not joints);
* elasticity: a linear spring on each ball joint towards the reference (stress-free) configuration
  in which the chain was defined, stiffness EI / h (h the distance between the two links'
  midpoints), the same for both bending axes and for twist (GJ = EI);
* gripping: the two gripped end portions (outer marker to second marker) are single capsules, each
  welded by a soft equality constraint (MuJoCo's constraint solver, 0.5 ms time constant) to a
  mocap body that follows the recorded gripper pose (interpolated between frames, the roll carried
  by parallel transport); MuJoCo treats mocap bodies as fixed, so a weld trails a moving target:
  the targets are set ahead by that lag (the gripped links then follow within 0.15-0.35 mm);
* damping: every case has a small material damping, a joint damping on every ball joint (a torque
  proportional to the relative angular velocity of the two links: Kelvin-Voigt in bending and
  twist, discretised per joint); ``internal_damping`` makes it strong. There is no air damping;
* contact: MuJoCo's soft contact (a constraint with 10 ms time constant, critically damped,
  about 1e4 1/s^2 per unit mass) between the capsules (surface, radius included) and a plane, with
  MuJoCo's regularised pyramidal Coulomb friction, solved with the other constraints; not a penalty
  spring;
* air drag: the drag law of MuJoCo's ellipsoid fluid model (blunt drag on the area the capsule's
  ellipsoid projects along the velocity plus slender drag on the rest, default coefficients), on
  the whole velocity of each link's centre (along the link it is half of what it is across),
  applied as an external force (``EllipsoidDrag``: MuJoCo's own fluid model, which would add added
  mass, lift and angular drag, makes a discrete step 10x slower); the medium's density is set so
  that the drag across a link per unit mass equals the planted quadratic coefficient;
* wind: a uniform horizontal force per unit mass, as a tilted gravity vector (MuJoCo's ``wind``
  only acts through the fluid model, where it would be a drag, not a uniform field);
* a clip: a small sphere of extra mass on the link at its material position; a stiff segment: the
  joint stiffness scaled over a stretch; rest curvature: the chain is defined curved (each child
  link rotated about its material d1 axis), so the joint springs rest in the arc; actuation delay:
  the mocap targets lag the recorded poses.

Why a chain of capsules: MuJoCo 4.0 removed ``<composite type="cable">`` and the
``mujoco.elasticity.cable`` plugin; their successor, a 1D ``flexcomp`` with ``<elasticity>``, is a
discrete elastic rod (like ours), so it would test the tool against its own discretisation again.
The implicit step also damps the chain's fastest modes numerically (link twist at thousands of
rad/s); what moves the markers is far slower and keeps its physical (joint) damping.

Like the PyElastica benchmark, each source recording gives the gripper motion of one output
recording, over a window of ``n_frames`` at a seeded offset. The grippers that drive the rope move
as the recorded ones with spikes and jitter filtered out and a 0.2 s lead-in from rest
(``driving_grips``). The rope starts as a curve through the first frame's markers with its
material length (``initial_curve``), settles under gravity for ``SETTLE_S`` with the grips held
(and extra uniform velocity damping), then the grips move and the markers are read at 100 Hz. The
gripped markers are then set to the recorded (raw) inputs and 0.3 mm of Gaussian motion-capture
noise is added to every marker.

    python benchmarks/mujoco_planted.py [--sources 8] [--frames 300]   # detectability table
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from benchmarks.planted import elastica
from deform.diagnose.spec import RodSpec
from deform.io.recordings import Recording
from deform.model import gripped_indices

# the same effects, lead-in, planted parameters and detectability as the PyElastica benchmark
EFFECTS, LEAD_FRAMES = elastica.EFFECTS, elastica.LEAD_FRAMES
detectability, planted_truth = elastica.detectability, elastica.planted_truth

__all__ = ["DEFAULTS", "EFFECTS", "ROD_KINDS", "detectability", "generate_mujoco", "planted_truth"]

# Material of the reference rods: PyElastica's (``elastica.ROD_KINDS``; length and mass come from the
# RodSpec), discretised here as links about ``link_m`` long (the gripped portions are one link each,
# whatever their length): 39 (light) / 34 (stiff) links. The fastest modes of the chain are twists
# of single links (small axial inertia), at about 4900 (light) / 6000 rad/s (stiff), twice that with
# the stiff segment: an explicit step would need 0.1 ms; the discrete (implicit) integrator is stable
# at 0.5 ms, where it damps those modes numerically and leaves the bending modes that move the
# markers (below 100 rad/s) alone.
MATERIAL = ("length_m", "mass_kg", "radius_m", "bend_stiffness_Nm2", "material_damping_m4_per_s")
ROD_KINDS = {
    kind: {**{k: rod[k] for k in MATERIAL}, "link_m": 0.03, "dt_s": 5e-4}
    for kind, rod in elastica.ROD_KINDS.items()
}
INTEGRATOR = "discrete"  # MuJoCo 4's implicit step: joint springs, damping and constraints in its metric
SETTLE_S = 1.0  # settling time before the first recorded frame [s]
SETTLE_DAMPING = 10.0  # extra uniform velocity damping while settling [1/s]
GRAVITY = 9.81
GRIP_TIMECONST_S = 5e-4  # weld constraint time constant (the discrete integrator takes one step)
GRIP_IMPEDANCE = 0.99  # weld impedance: the rope's bending moment tilts the grip by (1 - d) / d of it
# A critically damped weld to a mocap body (which has zero velocity to MuJoCo) trails a moving target
# by (2 timeconst + one step, the spring being evaluated at the end of the step) x velocity: the
# mocap targets are set that far ahead (measured grip error then 0.15 mm max instead of 1.2 mm).
CONTACT_TIMECONST_S = 0.01  # contact: critically damped, stiffness ~ 1 / timeconst^2 = 1e4 1/s^2

# Planted parameters at strength 1 per rod kind, in the tool's conventions (``planted_truth``
# scales them by ``strength``). The PyElastica benchmark's sizes, kept: measured here (seed 0, 8 DLO1
# / DLO3 train sources, 300 frames: the module's __main__) they move the markers by 0.5-2 cm (L1)
# from the paired control. Measured L1 vs the paired control [cm], light / stiff: drag 1.40 / 1.11,
# ground 1.49 / 1.73, clip 1.44 / 1.98, stiff segment 1.41 / 1.59, wind 1.00 / 0.92, internal
# damping 0.63 / 0.58, rest curvature 0.88 / 1.42, delay 0.86 / 0.70. Controls vs the real
# recordings they replay: 1.97 / 1.77 cm.
DEFAULTS = elastica.DEFAULTS


def _mujoco():
    import mujoco  # imported lazily: an optional dependency (the `bench` extra)

    return mujoco


# ----------------------------------------------------------------------------------------------
# geometry: links, frames, poses
# ----------------------------------------------------------------------------------------------


def link_bounds(s_markers: np.ndarray, length_m: float, link_m: float) -> tuple[np.ndarray, int, int]:
    """Material arc length [m] of the link ends (0 .. length_m), and the ids of the two gripped
    links: each gripped portion (outer marker to second marker) is one link; the tails and the free
    span between the grips are cut into equal links of about ``link_m``."""
    cuts = [0.0, s_markers[0], s_markers[1], s_markers[-2], s_markers[-1], length_m]
    bounds, grip = [0.0], {}
    for j, (a, b) in enumerate(itertools.pairwise(cuts)):
        if b - a < 1e-6:  # no tail
            continue
        if j in (1, 3):
            grip[j] = len(bounds) - 1
            bounds.append(b)
            continue
        k = max(1, round((b - a) / link_m))
        bounds.extend(a + (b - a) * np.arange(1, k + 1) / k)
    return np.array(bounds), grip[1], grip[3]


def chain_root(ga: int, gb: int) -> int:
    """The link that roots the kinematic tree: the middle one between the grips."""
    return (ga + gb) // 2


def frame_origins(bounds: np.ndarray, ga: int, gb: int) -> np.ndarray:
    """Material arc length of each link's body-frame origin: the joint to its parent, i.e. its
    lower end for the root and the links after it, its upper end for the links before the root."""
    root = chain_root(ga, gb)
    s = bounds[:-1].copy()
    s[:root] = bounds[1 : root + 1]
    return s


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _frame(t: np.ndarray, d1: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) with columns d1, t x d1, t: a link's body frame (its axis is z)."""
    return np.stack([d1, np.cross(t, d1), t], axis=-1)


def _wxyz(rot) -> np.ndarray:
    """MuJoCo's quaternion order (w, x, y, z) of scipy rotation(s)."""
    q = rot.as_quat()
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def _rest_rotations(bounds: np.ndarray, kappa: tuple[float, float]):
    """Rotation of each link relative to its parent in the reference (stress-free) shape: a turn of
    (kappa1 d1 + kappa2 d2) times the distance between the two links' midpoints."""
    from scipy.spatial.transform import Rotation

    lengths = np.diff(bounds)
    h = 0.5 * (lengths[:-1] + lengths[1:])
    rotvec = np.zeros((len(h), 3))
    rotvec[:, 0], rotvec[:, 1] = kappa[0] * h, kappa[1] * h
    return Rotation.from_rotvec(rotvec)


def _chain_pose(curve: np.ndarray, s_curve: np.ndarray, bounds: np.ndarray, ga: int, origin_a: np.ndarray):
    """Link frames (K, 3, 3) and starts (K, 3: the points at material ``bounds``) of a chain laid
    along ``curve`` (sampled at material ``s_curve``): each link points along the chord of the curve
    over its material interval, d1 is carried by parallel transport from the vertical; the gripped
    link ``ga`` starts at ``origin_a`` and the others are chained from it in both directions (links
    keep their lengths)."""
    ends = np.stack([np.interp(bounds, s_curve, curve[:, c]) for c in range(3)], axis=1)
    t = _unit(np.diff(ends, axis=0))
    up = np.array([0.0, 0.0, 1.0]) if abs(t[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    d1 = [elastica.transport(up, t[0])]
    for k in range(1, len(t)):
        d1.append(elastica.transport(d1[-1], t[k]))
    R = _frame(t, np.array(d1))
    steps = np.diff(bounds)[:, None] * t
    start = np.empty_like(t)
    start[ga] = origin_a
    for k in range(ga + 1, len(t)):
        start[k] = start[k - 1] + steps[k - 1]
    for k in range(ga - 1, -1, -1):
        start[k] = start[k + 1] - steps[k]
    return R, start


def _grip_poses(drive: np.ndarray, s_markers: np.ndarray, s_a: float, s_b: float, d1_a, d1_b):
    """Per-frame poses of the two gripped links' frames (origins at material ``s_a``, ``s_b``) from
    the gripper trajectory (T, 4, 3): origins (T, 2, 3) and rotations (T, 2, 3, 3). Each link lies on
    its grip line, anchored at the outer marker; its d1 is carried from the first frame by parallel
    transport (no spin about the axis)."""
    t_a = _unit(drive[:, 1] - drive[:, 0])
    t_b = _unit(drive[:, 3] - drive[:, 2])  # along increasing material s
    pos = np.stack(
        [
            drive[:, 0] + t_a * (s_a - s_markers[0]),
            drive[:, 3] + t_b * (s_b - s_markers[-1]),
        ],
        axis=1,
    )
    d1 = {"a": [elastica.transport(d1_a, t_a[0])], "b": [elastica.transport(d1_b, t_b[0])]}
    for k in range(1, len(drive)):
        d1["a"].append(elastica.transport(d1["a"][-1], t_a[k]))
        d1["b"].append(elastica.transport(d1["b"][-1], t_b[k]))
    rot = np.stack([_frame(t_a, np.array(d1["a"])), _frame(t_b, np.array(d1["b"]))], axis=1)
    return pos, rot


# ----------------------------------------------------------------------------------------------
# the MuJoCo model
# ----------------------------------------------------------------------------------------------


def _fmt(v) -> str:
    return " ".join(f"{float(x):.10g}" for x in np.atleast_1d(v))


def chain_xml(
    bounds: np.ndarray,
    ga: int,
    gb: int,
    kind: dict,
    spec: RodSpec,
    effect: str | None,
    truth: dict,
    s_markers: np.ndarray,
    damping_m4_per_s: float,
) -> str:
    """MJCF of one rope: a chain of capsules (body ``l{k}``, axis z, its frame origin at material
    ``frame_origins(...)[k]``), rooted by a free joint at the middle link (two branches: the mass
    matrix of a serial chain is dense, a tree of two halves factors about 4x faster), ball joints with
    springs and damping, two mocap grippers welded to the gripped links, and the planted effect."""
    L, r0, ei = spec.length_m, kind["radius_m"], kind["bend_stiffness_Nm2"]
    mu = spec.mass_kg / L  # mass per length [kg/m]
    lengths = np.diff(bounds)
    span = s_markers[-1] - s_markers[0]
    dt = kind["dt_s"]
    gravity = [0.0, 0.0, -GRAVITY]
    geom_extra = ""
    contype = 0
    world = ""
    if effect == "external_force":  # uniform horizontal force per unit mass: a tilted gravity
        gravity[:2] = truth["ax_m_per_s2"], truth["ay_m_per_s2"]
    elif effect == "ground_contact":
        contype = 1
        mu_f = truth["friction"]
        geom_extra = f' friction="{mu_f:.6g} 0.005 0.0001"'
        world = (
            f'<geom name="table" type="plane" size="5 5 0.1" pos="0 0 {truth["height_m"] - r0:.10g}" '
            f'contype="0" conaffinity="1" friction="{mu_f:.6g} 0.005 0.0001" '
            f'solref="{CONTACT_TIMECONST_S} 1"/>'
        )
    kappa = (truth.get("kappa1_per_m", 0.0), truth.get("kappa2_per_m", 0.0))
    rest = _rest_rotations(bounds, kappa)  # entry k - 1: link k relative to link k - 1
    rest_fwd, rest_bwd = _wxyz(rest), _wxyz(rest.inv())
    s_origin = frame_origins(bounds, ga, gb)
    clip = None
    if effect == "point_mass":
        s_clip = s_markers[0] + truth["position_s"] * span
        clip = (int(np.searchsorted(bounds, s_clip, side="right") - 1), s_clip)

    def link(k: int, parent: int | None) -> str:
        """The opening tag of link k's body, its joint to ``parent`` and its geoms."""
        lo, hi = bounds[k] - s_origin[k], bounds[k + 1] - s_origin[k]  # the axis, in the body frame
        if parent is None:
            head = f'<body name="l{k}"><freejoint name="root"/>'
        else:
            j = max(k, parent)  # the joint sits at material bounds[j], between links j - 1 and j
            h = 0.5 * (lengths[j - 1] + lengths[j])
            u = (bounds[j] - s_markers[0]) / span  # the joint's place along the marker span
            stiff = ei / h
            if effect == "stiffness_variation" and truth["start_s"] <= u <= truth["end_s"]:
                stiff *= truth["stiffness_ratio"]
            pos = bounds[j] - s_origin[parent]  # the joint (= this frame's origin) in the parent's frame
            quat = rest_fwd[j - 1] if k > parent else rest_bwd[j - 1]
            head = (
                f'<body name="l{k}" pos="0 0 {pos:.10g}" quat="{_fmt(quat)}">'
                f'<joint name="j{k}" type="ball" stiffness="{stiff:.10g}" '
                f'damping="{damping_m4_per_s * mu / h:.10g}"/>'
            )
        geom = (
            f'<geom type="capsule" fromto="0 0 {lo:.10g} 0 0 {hi:.10g}" size="{r0}" '
            f'mass="{mu * lengths[k]:.10g}" contype="{contype}" conaffinity="0"{geom_extra}/>'
        )
        if clip is not None and clip[0] == k:
            geom += (
                f'<geom type="sphere" pos="0 0 {clip[1] - s_origin[k]:.10g}" size="{r0:.10g}" '
                f'mass="{truth["mass_kg"]:.10g}" contype="0" conaffinity="0"/>'
            )
        return head + geom

    root, K = chain_root(ga, gb), len(lengths)
    forward = "".join(link(k, k - 1) for k in range(root + 1, K)) + "</body>" * (K - 1 - root)
    backward = "".join(link(k, k + 1) for k in range(root - 1, -1, -1)) + "</body>" * root
    chain = link(root, None) + forward + backward + "</body>"
    return f"""<mujoco model="rope">
  <option timestep="{dt}" integrator="{INTEGRATOR}" gravity="{_fmt(gravity)}"/>
  <default>
    <equality solref="{GRIP_TIMECONST_S} 1" solimp="{GRIP_IMPEDANCE} {GRIP_IMPEDANCE} 0.001"/>
  </default>
  <worldbody>
    {world}
    {chain}
    <body name="grip_a" mocap="true"/>
    <body name="grip_b" mocap="true"/>
  </worldbody>
  <equality>
    <weld body1="l{ga}" body2="grip_a" relpose="0 0 0 1 0 0 0"/>
    <weld body1="l{gb}" body2="grip_b" relpose="0 0 0 1 0 0 0"/>
  </equality>
</mujoco>"""


def _initial_qpos(model, R: np.ndarray, start: np.ndarray, bounds: np.ndarray, ga: int, gb: int, kappa):
    """qpos of the chain with link frames ``R`` (K, 3, 3) and material starts ``start`` (K, 3): the
    root's free joint (the world pose of its frame), then each ball joint's rotation relative to the
    reference shape (R_k = R_parent R_rest R_joint)."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_matrix(R)
    rest = _rest_rotations(bounds, kappa)
    root = chain_root(ga, gb)
    qpos = np.array(model.qpos0)
    adr = model.joint("root").qposadr[0]
    qpos[adr : adr + 3] = start[root]
    qpos[adr + 3 : adr + 7] = _wxyz(rot[root])
    for k in range(len(R)):
        if k == root:
            continue
        if k > root:  # parent k - 1: R_k = R_{k-1} rest_k J
            joint = rest[k - 1].inv() * rot[k - 1].inv() * rot[k]
        else:  # parent k + 1: R_k = R_{k+1} rest_{k+1}^-1 J
            joint = rest[k] * rot[k + 1].inv() * rot[k]
        adr = model.joint(f"j{k}").qposadr[0]
        qpos[adr : adr + 4] = _wxyz(joint)
    return qpos


def _mocap_steps(pos: np.ndarray, rot: np.ndarray, tau: np.ndarray):
    """Gripper poses at fractional frames ``tau`` (clamped to the track): linear in position,
    spherical-linear in orientation. -> (S, 2, 3) positions, (S, 2, 4) quaternions (w, x, y, z)."""
    from scipy.spatial.transform import Rotation, Slerp

    T = len(pos)
    f = np.clip(tau, 0.0, T - 1.0)
    i = np.minimum(f.astype(int), T - 2)
    a = (f - i)[:, None, None]
    p = (1 - a) * pos[i] + a * pos[i + 1]
    q = np.stack([_wxyz(Slerp(np.arange(T), Rotation.from_matrix(rot[:, g]))(f)) for g in range(2)], axis=1)
    return p, q


def _marker_reader(bounds: np.ndarray, s_origin: np.ndarray, s_markers: np.ndarray, body_of_link: np.ndarray):
    """Marker positions from the body poses: the point of its link's axis at its material s."""
    k = np.clip(np.searchsorted(bounds, s_markers, side="right") - 1, 0, len(bounds) - 2)
    bodies, offset = body_of_link[k], (s_markers - s_origin[k])[:, None]

    def read(data) -> np.ndarray:
        axis = data.xmat[bodies].reshape(-1, 3, 3)[:, :, 2]
        return data.xpos[bodies] + offset * axis

    return read


DRAG_COEFS = (0.5, 0.25)  # MuJoCo's default blunt and slender drag coefficients (geom fluidcoef)


class EllipsoidDrag:
    """Quadratic air drag of MuJoCo's ellipsoid fluid model (its blunt and slender drag terms) on
    every link, applied as an external force at the link's centre of mass:
    f = -rho [C_blunt A(v) + C_slender (A_max - A(v))] |v| v, with A(v) the area the link's ellipsoid
    (semi-axes r, r, l/2 + r, as MuJoCo fits a capsule) projects along v and A_max = pi r (l/2 + r).
    The drag is along the whole velocity: across the link it is twice what it is along it.

    MuJoCo's own fluid model (``density`` with ``fluidshape="ellipsoid"``) would add added mass,
    lift and angular drag, but under the discrete integrator its velocity derivatives make a step
    about 10x slower, so the drag force is evaluated here, explicitly, from the previous step's
    velocities. ``rho`` is chosen so that the blunt drag across a link of median length is the
    planted quadratic coefficient [1/m] times its mass."""

    def __init__(self, model, bodies: np.ndarray, bounds: np.ndarray, radius: float, mu: float, coef: float):
        lengths = np.diff(bounds)
        self.bodies, self.root = bodies, model.body_rootid[bodies]
        self.r, self.c = radius, 0.5 * lengths + radius
        link = float(np.median(lengths))
        self.rho = coef * mu * link / (DRAG_COEFS[0] * math.pi * radius * (0.5 * link + radius))

    def __call__(self, data) -> None:
        cv = data.cvel[self.bodies]  # [rot, lin] about the subtree centre of mass of the root
        v = cv[:, 3:] + np.cross(cv[:, :3], data.xipos[self.bodies] - data.subtree_com[self.root])
        speed = np.linalg.norm(v, axis=1)
        axis = data.xmat[self.bodies].reshape(-1, 3, 3)[:, :, 2]
        cos2 = np.sum(v * axis, axis=1) ** 2 / np.maximum(speed, 1e-12) ** 2
        area = math.pi * self.r * np.sqrt(self.c**2 * (1.0 - cos2) + self.r**2 * cos2)
        a_max = math.pi * self.r * self.c
        k = self.rho * (DRAG_COEFS[0] * area + DRAG_COEFS[1] * (a_max - area)) * speed
        data.xfrc_applied[self.bodies, :3] = -k[:, None] * v


def generate_mujoco(
    effect: str | None,
    sources: list[Recording],
    spec: RodSpec,
    rod_kind: str = "light",
    n_frames: int = 300,
    seed: int = 0,
    noise_m: float = 3e-4,
    strength: float = 1.0,
) -> tuple[list[Recording], dict]:
    """-> (recordings, truth). One output recording per source: the source's gripper motion over a
    window of ``n_frames`` at a seeded offset, replayed on a MuJoCo chain of capsules with one planted
    ``effect`` (None: a control) of size ``strength`` (1 = ``DEFAULTS``). ``truth`` holds the planted
    parameters (tool conventions) plus "effect", "rod_kind", "strength", the rope's material and the
    numerics."""
    if effect is not None and effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; expected one of {EFFECTS}")
    if rod_kind not in ROD_KINDS:
        raise ValueError(f"unknown rod kind {rod_kind!r}; expected one of {tuple(ROD_KINDS)}")
    mujoco = _mujoco()
    kind = ROD_KINDS[rod_kind]
    rng = np.random.default_rng(seed)
    n = spec.n_vertices
    if any(r.n_vertices != n for r in sources):
        raise ValueError(f"sources must have {n} markers")
    frame_dt, L, dt = spec.dt, spec.length_m, float(kind["dt_s"])
    per_frame = round(frame_dt / dt)
    if abs(per_frame * dt - frame_dt) > 1e-9:
        raise ValueError(f"the frame period {frame_dt} s is not a whole number of {dt} s steps")
    s_markers, tail = elastica.marker_layout(sources, L)
    bounds, ga, gb = link_bounds(s_markers, L, kind["link_m"])
    s_fine = np.linspace(0.0, L, 8 * (len(bounds) - 1) + 1)  # the initial curve's grid
    fine_a = elastica.held_nodes(s_fine, s_markers[0], s_markers[1])
    fine_b = elastica.held_nodes(s_fine, s_markers[-2], s_markers[-1])

    starts = [int(rng.integers(0, r.n_frames - n_frames + 1)) for r in sources]
    # a table just above the lowest points most recordings reach: the rope touches it in most of them
    lowest = float(
        np.percentile([r.positions[s : s + n_frames, 2:-2, 2].min() for r, s in zip(sources, starts)], 80)
    )
    truth = planted_truth(effect, rod_kind, strength, lowest, spec, defaults=DEFAULTS)
    nu = kind["material_damping_m4_per_s"] + truth.get("bending_rate_damping_m4_per_s", 0.0)
    delay = truth.get("delay_frames", 0.0)
    kappa = (truth.get("kappa1_per_m", 0.0), truth.get("kappa2_per_m", 0.0))
    xml = chain_xml(bounds, ga, gb, kind, spec, effect, truth, s_markers, nu)
    model = mujoco.MjModel.from_xml_string(xml)
    body_of_link = np.array([model.body(f"l{k}").id for k in range(len(bounds) - 1)])
    s_origin = frame_origins(bounds, ga, gb)
    read = _marker_reader(bounds, s_origin, s_markers, body_of_link)
    drag = None
    if effect == "aerodynamic_drag":
        drag = EllipsoidDrag(
            model, body_of_link, bounds, kind["radius_m"], spec.mass_kg / L, truth["quadratic_1_per_m"]
        )
    settle_steps = round(SETTLE_S / dt)
    n_move = (LEAD_FRAMES + n_frames - 1) * per_frame
    # fractional frame of the gripper track at the end of each step after settling (lagged by `delay`)
    lead_s = 2 * GRIP_TIMECONST_S + dt
    tau = (np.arange(1, n_move + 1) * dt + lead_s) / frame_dt - delay
    settle_factor = math.exp(-SETTLE_DAMPING * dt)
    W = mujoco.mjtWarning
    unstable = [int(w) for w in (W.mjWARN_BADQACC, W.mjWARN_BADQVEL, W.mjWARN_BADQPOS, W.mjWARN_INERTIA)]

    grips_rec = np.stack(
        [r.positions[s : s + n_frames][:, gripped_indices(n)] for r, s in zip(sources, starts)]
    )
    out = np.empty((len(sources), n_frames, n, 3))
    grip_err = []  # per frame and rope: distance of the gripped links' frames from their targets
    for i, (r, st) in enumerate(zip(sources, starts)):
        drive = elastica.driving_grips(grips_rec[i])
        markers0 = r.positions[st].copy()
        markers0[gripped_indices(n)] = drive[0]  # the grips where settling starts
        curve = elastica.initial_curve(markers0, s_markers, s_fine, fine_a, fine_b)
        R, start = _chain_pose(curve, s_fine, bounds, ga, drive[0, 0])  # link ga starts at marker 0
        gpos, grot = _grip_poses(drive, s_markers, s_origin[ga], s_origin[gb], R[ga][:, 0], R[gb][:, 0])
        mp, mq = _mocap_steps(gpos, grot, tau)
        want, _ = _mocap_steps(gpos, grot, LEAD_FRAMES + np.arange(n_frames) - delay)  # no lead
        data = mujoco.MjData(model)
        data.qpos[:] = _initial_qpos(model, R, start, bounds, ga, gb, kappa)
        data.mocap_pos[:] = gpos[0]
        data.mocap_quat[:] = _wxyz_from_matrix(grot[0])
        for _ in range(settle_steps):
            if drag is not None:
                drag(data)
            mujoco.mj_step(model, data)
            data.qvel[:] *= settle_factor
        if sum(data.warning[w].number for w in unstable):
            raise RuntimeError(f"mujoco {effect}: the simulation diverged while settling (rope {i})")
        j = 0
        for k in range(-LEAD_FRAMES, n_frames):
            if k > -LEAD_FRAMES:
                for _ in range(per_frame):
                    data.mocap_pos[:] = mp[j]
                    data.mocap_quat[:] = mq[j]
                    if drag is not None:
                        drag(data)
                    mujoco.mj_step(model, data)
                    j += 1
            if k >= 0:
                x = read(data)
                bad = sum(data.warning[w].number for w in unstable)  # MuJoCo resets a diverged state
                if bad or not np.all(np.isfinite(x)) or np.abs(x).max() > 100.0:
                    raise RuntimeError(f"mujoco {effect}: the simulation diverged (rope {i}, frame {k})")
                out[i, k] = x
                grip_err.append(
                    float(np.linalg.norm(data.xpos[body_of_link[[ga, gb]]] - want[k], axis=-1).max())
                )
    out[:, :, gripped_indices(n)] = grips_rec  # the recorded inputs (the rope's ends lag them by `delay`)
    out = out + rng.normal(0.0, noise_m, out.shape)
    recs = [
        Recording(name=f"mujoco_{rod_kind}_{effect or 'control'}_{seed}_{i}", positions=out[i], dt=frame_dt)
        for i in range(len(sources))
    ]
    lengths = np.diff(bounds)
    truth.update(
        {
            "effect": effect,
            "rod_kind": rod_kind,
            "strength": float(strength),
            "rod": {
                "length_m": L,
                "mass_kg": spec.mass_kg,
                "radius_m": kind["radius_m"],
                "bend_stiffness_Nm2": kind["bend_stiffness_Nm2"],
                "twist_stiffness_Nm2": kind["bend_stiffness_Nm2"],
                "material_damping_m4_per_s": kind["material_damping_m4_per_s"],
                "tail_m": tail,
                "marker_s_m": s_markers.tolist(),
                "link_s_m": bounds.tolist(),
            },
            "numerics": {
                "n_links": len(lengths),
                "link_m": float(np.median(lengths)),
                "dt_s": dt,
                "integrator": INTEGRATOR,
                "settle_s": SETTLE_S,
                "grip_timeconst_s": GRIP_TIMECONST_S,
                "max_grip_error_m": max(grip_err),
                "p99_grip_error_m": float(np.percentile(grip_err, 99)),
                "drag_density_kg_per_m3": drag.rho if drag is not None else 0.0,
                "mujoco_version": mujoco.__version__,
                "starts": starts,
            },
        }
    )
    return recs, truth


def _wxyz_from_matrix(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return _wxyz(Rotation.from_matrix(R))


def grip_error(truth: dict) -> str:
    """The control's numerics for the detectability table."""
    n = truth["numerics"]
    return (
        f"{n['n_links']} links, grip error max {n['max_grip_error_m'] * 1e3:.2f} mm "
        f"p99 {n['p99_grip_error_m'] * 1e3:.2f} mm"
    )
