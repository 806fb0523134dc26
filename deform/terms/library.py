"""Library of candidate physics terms the plain DER model may be missing.

Each term is a small ``nn.Module`` with a few physical parameters in a raw, well-scaled form (so one
Adam learning rate suits all). A term acts on the simulator in one or more of three ways:

* ``acceleration(x, v, mass, rest)`` / ``mass(mass)``: DeformModel extension hooks;
* ``bind(exprs)``: rewrite the model's identified parameters (``log_beta``, ``wbar``...) as
  differentiable expressions of the term's parameters (see :mod:`deform.diagnose.simulator`, the discrepancy tool);
* ``delay_frames``: a fractional shift of the gripper input sequence.

Every hook follows the dtype of what it is given: the parameters and buffers are float64, the state
is float64 in the loop and in training but float32 in the service's predict rollout, so a hook casts
its own tensors to the state's dtype (``x.dtype``, ``mass.dtype``, the expression's) and returns that
dtype. Left to type promotion, a (3,) float64 field added to a float32 state made the whole step
float64 and it failed further on (``expected scalar type Float but found Double``, issue 52).

``params()`` gives the physical values for the report; ``init_from_data`` sets data-driven starts;
``grid()`` lists coarse starting values (raw parameter values, log-spaced over decades) that the fit
tries before gradient descent, so that a term whose effect is orders of magnitude away from its
default start (drag, damping, a delay of frames) is not limited by Adam's step size x iterations.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn.functional import softplus

from deform.rod.geometry import normal_velocity
from deform.rod.layout import batch_major, vertex_major
from deform.rod.positive import inv_softplus

# The least internal (bending-rate) damping the tool names [m^4/s]: a fit at or below it is what a
# rope's own material damping gives, as every real rope has, not an effect left out of the model.
# Why: on a stiff MuJoCo control (a chain whose joints carry a small material damping and whose
# implicit step damps its fastest modes) internal damping improved the check by 4.0 %, just over its
# threshold, with nu = 4.9e-7. 2x the largest fit on the controls of the two benchmarks it is
# calibrated on (tool v8 rows: 2.9e-7 to 1.2e-6 on PyElastica's six, 3.4e-7 to 1.85e-5 on this
# project's five), never on the cases scored; far below what is named where damping is planted
# (2.2e-4 to 4.1e-4) or found on real ropes (1.4e-4 to 3.6e-3).
INTERNAL_DAMPING_LEVEL = 3.7e-5

# How much of the nominal linear damping a dissipative candidate (drag, contact friction, internal
# damping) is tried with: all of it, half, or a fifth. A fifth: a fit held at the bound (1.03 /s)
# keeps 0.2 /s, what the controls' nominal fits took (0.13-0.16 /s light, 0.3-0.5 /s stiff), so that
# the candidate may take over all the external dissipation. (Tools v3-v5 tried "at most the material
# level" instead, which is the bound itself: the same point as keeping it all.)
_DAMPING_SHARES = (
    {},
    {"nominal:log_damping": math.log(0.5)},
    {"nominal:log_damping": math.log(0.2)},
)


def _logit(p: float) -> float:
    return math.log(p / (1 - p))


class Term(nn.Module):
    """Base class: ``name``, a one-line physical ``description``, raw parameters."""

    name = "term"
    description = ""
    # what marker motion cannot tell this term apart from, and why (None: nothing known); the report
    # names these classes instead of pretending to a choice
    cannot_tell_from: str | None = None
    # True: the effect builds up over many steps (a dissipation of deformation rates), so a fit on
    # short windows cannot tell it from the nominal damping's share; with
    # ``DiagnoseBudget.grow_slow_terms`` such a term and its reference are fitted on windows growing
    # to the one-second scoring windows
    slow = False
    # (parameter, level): a fit at or below the level is a rope's own material property, which every
    # rope has, so the term is not named for it however much it improves the check (None: no level)
    material_level: tuple[str, float] | None = None

    def __init__(self, n: int, arclength: np.ndarray):
        super().__init__()
        self.n = n
        self.register_buffer("s", torch.as_tensor(arclength, dtype=torch.float64))  # (n,) in [0, 1]

    @property
    def n_params(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def init_from_data(self, context: dict) -> None:
        """Data-driven starting values (``context``: lowest z, localisation peak...)."""

    def bind(self, exprs: dict[str, Tensor]) -> dict[str, Tensor]:
        return exprs

    def grid(self) -> list[dict[str, float]]:
        """Coarse starting points ``{raw parameter name: value}`` tried before Adam (default: none)."""
        return []

    def params(self) -> dict[str, float]:
        raise NotImplementedError


class AerodynamicDrag(Term):
    name = "aerodynamic_drag"
    description = "air drag on the velocity across the rod, linear and quadratic in speed"
    cannot_tell_from = (
        "the nominal linear damping, for its linear part: both take a force proportional to "
        "the velocity; only the quadratic part, or more than a rope's material damping, is "
        "drag by itself"
    )

    def __init__(self, n, arclength):
        super().__init__(n, arclength)
        self.log_lin = nn.Parameter(torch.tensor(math.log(0.02), dtype=torch.float64))
        self.log_quad = nn.Parameter(torch.tensor(math.log(0.02), dtype=torch.float64))

    def acceleration(self, x, v, mass, rest):
        vn = batch_major(normal_velocity(vertex_major(x, 2), vertex_major(v, 2)), x.shape[:-2])
        lin, quad = self.log_lin.exp().to(x.dtype), self.log_quad.exp().to(x.dtype)
        return -(lin + quad * vn.norm(dim=-1, keepdim=True)) * vn

    def grid(self):
        # quadratic coefficient over 3 decades, each with a linear part of none, 1 or 4 /s (the nominal
        # damping is bounded at a material level, so an external linear drag must be this term's) and
        # with the nominal linear damping kept or halved: drag and damping are the same dissipation, so
        # a drag term is only seen as better if it may take over part of what the nominal fit gave to
        # its damping
        return [
            {"log_quad": math.log(q), "log_lin": math.log(lin), **nominal}
            for q in (0.03, 0.3, 1.0, 3.0, 10.0)
            for lin in (0.02, 1.0, 4.0)
            for nominal in _DAMPING_SHARES
        ]

    @torch.no_grad()
    def params(self):
        return {"linear_1_per_s": float(self.log_lin.exp()), "quadratic_1_per_m": float(self.log_quad.exp())}


def damping_modes(rest: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Modes of the bending-rate damping operator ``M^-1 K`` for rest lengths ``rest`` (B, m).

    ``K = D^T diag(1/lbar) D`` with ``D`` the divided second differences in arc length and ``M`` the
    Voronoi lengths ``lbar`` (the vertex masses up to the density). With ``si = lbar^(-1/2)``,
    ``si K si = U diag(lam) U^T`` is symmetric, so ``M^-1 K = diag(si) U diag(lam) U^T diag(1/si)``.

    Returns:
        ``lam`` (B, n) (clamped at 0), ``U`` (B, n, n), ``si`` (B, n), all float64.
    """
    l = rest.to(torch.float64)  # (B, m)
    lbar = torch.cat([l[..., :1] / 2, (l[..., :-1] + l[..., 1:]) / 2, l[..., -1:] / 2], -1)  # (B, n)
    n = lbar.shape[-1]
    D = l.new_zeros(*l.shape[:-1], n - 2, n)
    i = torch.arange(n - 2)
    D[..., i, i] = 1.0 / l[..., :-1]
    D[..., i, i + 1] = -(1.0 / l[..., :-1] + 1.0 / l[..., 1:])
    D[..., i, i + 2] = 1.0 / l[..., 1:]
    K = D.transpose(-1, -2) @ (D / lbar[..., 1:-1, None])
    si = lbar.rsqrt()
    lam, U = torch.linalg.eigh(si[..., :, None] * K * si[..., None, :])
    return lam.clamp_min(0.0), U, si


class InternalDamping(Term):
    """Bending-rate damping (Kelvin-Voigt-like internal friction), independent of the discretisation.

    Rayleigh dissipation of the continuum ``R = 1/2 eta_c int |v''(s)|^2 ds`` discretised with divided
    differences in arc length: ``g_i = (v_{i+1} - v_i)/l_i - (v_i - v_{i-1})/l_{i-1}`` and
    ``R = 1/2 eta_c sum_i |g_i|^2 / lbar_i`` (``lbar_i`` the Voronoi length), divided by the vertex mass
    ``rho lbar_i``. The parameter ``nu = eta_c / rho`` [m^4/s] is the same on a coarse or a fine
    discretisation of the same rod, and a straight rod moving rigidly (velocity linear in arc length)
    is not damped even where the vertex spacing changes (the short gripped end edges): plain second
    differences of vertex velocities damped the turning of the grippers there and changed meaning with
    the spacing (``nu / l^4`` on a uniform grid of spacing ``l``)."""

    name = "internal_damping"
    slow = True
    description = "damping of the bending rate (Kelvin-Voigt internal friction of the rod's curvature)"
    cannot_tell_from = (
        "the nominal linear damping, where the motion is mostly one slow bending mode: "
        "damping that mode's rate and damping the velocity look the same at the markers"
    )
    scale = 1e-5  # m^4/s per exp(raw): about 0.1 /s in units of a 10 cm marker spacing
    material_level = ("bending_rate_damping_m4_per_s", INTERNAL_DAMPING_LEVEL)

    def __init__(self, n, arclength):
        super().__init__(n, arclength)
        self.log_nu = nn.Parameter(torch.tensor(math.log(0.5), dtype=torch.float64))
        self.dt = 0.01
        self._cache = None

    def set_dt(self, dt: float) -> None:
        self.dt = dt

    @property
    def nu(self) -> Tensor:
        return self.scale * self.log_nu.exp()

    @torch.no_grad()
    def _modes(self, rest: Tensor):
        """Eigen-decomposition of the mass-normalised operator for these rest lengths (cached).

        The cache holds the tensor itself and checks identity and version: a key made of its address
        alone went stale when a freed tensor's memory was reused for other rest lengths, and a
        rollout then ran with another recording's operator, depending on the allocator. A view (the
        model hands terms a fresh batch-first view of its vertex-major rest lengths every step) is
        keyed on the tensor it views and its layout in it: keyed on the view object itself, the
        cache missed on every step and the decomposition ran once per step."""
        base = rest if rest._base is None else rest._base
        layout = (rest.shape, rest.stride(), rest.storage_offset())
        cached = self._cache
        if cached is not None and cached[0] is base and cached[1] == rest._version and cached[2] == layout:
            return cached[3]
        out = damping_modes(rest)
        self._cache = (base, rest._version, layout, out)
        return out

    @torch.no_grad()
    def fix_rest(self, rest: Tensor) -> None:
        """Freeze the operator at one set of rest lengths ``rest`` (m,), e.g. a trained model's typical
        ones (``DeformModel.nominal_rest``). Why: the per-call cache above is keyed on a tensor's
        address, which ``torch.export`` cannot trace, and an eigendecomposition per step inside the
        graph halves a batched step's rate; with the modes fixed the term is one (n, n) product per
        step. A recording's own edge lengths then enter the damping only through this typical set
        (they differ by a few per cent; the damping is a smooth function of them)."""
        lam, U, si = damping_modes(rest.reshape(1, -1))
        self.register_buffer("fixed_lam", lam[0], persistent=False)
        self.register_buffer("fixed_U", U[0], persistent=False)
        self.register_buffer("fixed_si", si[0], persistent=False)

    def acceleration(self, x, v, mass, rest):
        # integrated exactly over the (explicit) step: each mode decays by exp(-dt nu lambda) in one
        # step; -nu M^-1 K v for small dt, but never overshoots for stiff damping of short modes.
        # M^-1 K = S^(1/2) U diag(lam) U^T S^(-1/2) with S = diag(si^2) = M^-1 up to the density.
        if getattr(self, "fixed_lam", None) is not None:
            rate = -torch.expm1(-self.dt * self.nu * self.fixed_lam) / self.dt  # (n,)
            U, si = self.fixed_U, self.fixed_si
            op = si[:, None] * ((U * rate) @ U.T) / si[None, :]  # (n, n)
            # one matrix product over every rod and axis (a step hands the term a view of
            # vertex-major velocities, on which a batched product made a copy per rod)
            return -torch.tensordot(v, op.to(v.dtype), dims=([-2], [1])).movedim(-1, -2)
        lam, U, si = self._modes(rest)
        rate = -torch.expm1(-self.dt * self.nu * lam) / self.dt  # (B, n)
        U, si = U.to(v.dtype), si.to(v.dtype)
        modal = U.transpose(-1, -2) @ (v / si.unsqueeze(-1))
        return -si.unsqueeze(-1) * (U @ (rate.to(v.dtype).unsqueeze(-1) * modal))

    def grid(self):  # nu over 4 decades, with the nominal damping kept or halved (both are dissipation)
        return [
            {"log_nu": math.log(e), **nominal}
            for e in (0.1, 0.5, 2.0, 5.0, 20.0, 100.0)
            for nominal in _DAMPING_SHARES
        ]

    @torch.no_grad()
    def params(self):
        return {"bending_rate_damping_m4_per_s": float(self.nu)}


class GroundContact(Term):
    name = "ground_contact"
    description = "a horizontal plane with height, contact stiffness and Coulomb friction"
    width = 0.002  # softplus width of the penalty [m]

    def __init__(self, n, arclength):
        super().__init__(n, arclength)
        self.register_buffer("h0", torch.tensor(0.0, dtype=torch.float64))
        self.raw_h = nn.Parameter(torch.tensor(0.0, dtype=torch.float64))
        self.log_k = nn.Parameter(torch.tensor(math.log(2000.0), dtype=torch.float64))
        self.raw_mu = nn.Parameter(torch.tensor(_logit(0.3), dtype=torch.float64))

    def init_from_data(self, context):
        self.h0.fill_(float(context.get("lowest_z", 0.0)) + 0.002)
        self.contact_z = context.get("contact_z")  # localisation: the height below which errors grow

    def grid(self):
        """Plane heights from the lowest point reached (-0.5 to +2 cm) and, when localisation found
        errors growing below some height, that height; each with a soft and a stiff contact. Started
        at one height only, a contact fit can stay where the plane touches nothing (no gradient)."""
        offsets = [-0.005, 0.0, 0.005, 0.01, 0.02]
        if getattr(self, "contact_z", None) is not None:
            offsets.append(float(self.contact_z) - float(self.h0))
        # a table carries weight the nominal fit had to give to stiffness (a rope lying on it held
        # up by its own EI): each plane also with the nominal EI and GJ halved
        softer = ({}, {"nominal:log_ei": math.log(0.5), "nominal:log_gj": math.log(0.5)})
        return [
            {"raw_h": dz / 0.02, "log_k": math.log(k), **nominal, **stiffness}
            for dz in offsets
            if abs(dz) <= 0.1
            for k in (2000.0, 10000.0)
            for nominal in _DAMPING_SHARES
            for stiffness in softer
        ]

    @property
    def height(self) -> Tensor:
        return self.h0 + 0.02 * self.raw_h

    def set_dt(self, dt: float) -> None:
        self.dt = dt

    def acceleration(self, x, v, mass, rest):
        """Penalty normal force and Coulomb friction that at most stops the sliding in one step:
        ``|a_f| = min(mu a_n, |v_xy| / dt)``. A friction force regularised only by a small speed
        scale is a damping of rate ``mu a_n / v_eps`` near rest (about 500 /s for a rope lying on
        a table), far beyond what an explicit step of 10 ms can integrate: the resting part of
        the rope chattered and the candidate predicted worse than no table at all."""
        pen = softplus((self.height.to(x.dtype) - x[..., 2]) / self.width) * self.width
        normal = self.log_k.exp().to(x.dtype) * pen  # (B, n) [m/s^2]
        vxy = v[..., :2]
        speed = (vxy.pow(2).sum(-1) + 1e-12).sqrt()
        mu = torch.sigmoid(self.raw_mu).to(x.dtype)
        limit = torch.minimum(mu * normal, speed / getattr(self, "dt", 0.01))
        fric = -(limit / speed).unsqueeze(-1) * vxy
        return torch.cat([fric, normal.unsqueeze(-1)], -1)

    @torch.no_grad()
    def params(self):
        return {
            "height_m": float(self.height),
            "stiffness_1_per_s2": float(self.log_k.exp()),
            "friction": float(torch.sigmoid(self.raw_mu)),
        }


class PointMass(Term):
    """An extra mass (a clip) at one arc-length position, fitted as the log of its mass. Why a log:
    Adam moves a raw parameter by at most its step times the iterations; on the mass itself (5 g
    per unit of a softplus, tools before v10) that capped every fitted clip at about 10.5 g, whatever
    was planted (13-19 g on the benchmarks' stiffer rods). On the log the steps are relative, and the
    grid starts five positions at three masses."""

    name = "point_mass"
    description = "an extra mass attached at one arc-length position"

    def __init__(self, n, arclength):
        super().__init__(n, arclength)
        self.raw_pos = nn.Parameter(torch.tensor(0.0, dtype=torch.float64))
        self.log_mass = nn.Parameter(torch.tensor(math.log(2.5e-3), dtype=torch.float64))  # kg
        self.sigma = 0.5 / (n - 1)

    def init_from_data(self, context):
        self.raw_pos.fill_(_logit(min(max(context.get("peak_s", 0.5), 0.1), 0.9)))

    def grid(self):  # five positions along the rod at 3, 10 and 30 g: within reach of 0.6-150 g
        return [
            {"raw_pos": _logit(p), "log_mass": math.log(m)}
            for m in (3e-3, 1e-2, 3e-2)
            for p in (0.2, 0.35, 0.5, 0.65, 0.8)
        ]

    def mass(self, mass):
        pos = torch.sigmoid(self.raw_pos)
        w = torch.exp(-0.5 * ((self.s - pos) / self.sigma) ** 2)
        w = w / w.sum()
        return mass + (self.log_mass.exp() * w).to(mass.dtype)

    @torch.no_grad()
    def params(self):
        return {
            "mass_kg": float(self.log_mass.exp()),
            "position_s": float(torch.sigmoid(self.raw_pos)),
        }


class StiffnessVariation(Term):
    name = "stiffness_variation"
    description = "a stretch of the rod with a different bending stiffness"
    edge = 0.03

    def __init__(self, n, arclength):
        super().__init__(n, arclength)
        self.log_ratio = nn.Parameter(torch.tensor(0.0, dtype=torch.float64))
        self.raw_c = nn.Parameter(torch.tensor(0.0, dtype=torch.float64))
        self.raw_w = nn.Parameter(torch.tensor(_logit(0.25), dtype=torch.float64))

    def init_from_data(self, context):
        self.raw_c.fill_(_logit(min(max(context.get("peak_s", 0.5), 0.15), 0.85)))

    def window(self) -> Tensor:
        c, w = torch.sigmoid(self.raw_c), 0.05 + 0.9 * torch.sigmoid(self.raw_w)
        s = self.s[1:-1]
        return torch.sigmoid((s - (c - w / 2)) / self.edge) * torch.sigmoid(((c + w / 2) - s) / self.edge)

    def bind(self, exprs):
        exprs = dict(exprs)
        log_beta = exprs["log_beta"]
        exprs["log_beta"] = log_beta + (2.0 * self.log_ratio * self.window()).to(log_beta.dtype)
        return exprs

    @torch.no_grad()
    def params(self):
        c, w = float(torch.sigmoid(self.raw_c)), float(0.05 + 0.9 * torch.sigmoid(self.raw_w))
        return {
            "stiffness_ratio": float(torch.exp(2.0 * self.log_ratio)),
            "start_s": c - w / 2,
            "end_s": c + w / 2,
        }


class ExternalForce(Term):
    """A uniform horizontal field per unit mass, ``a = w (cos phi, sin phi, 0)``, fitted as the log of
    its strength ``w`` and its azimuth ``phi``. Why polar: Adam moves a raw parameter by at most its
    step times the iterations; on the field's components that capped every fitted wind at about
    0.75 m/s^2 per axis (planted winds of 1.4-3.8 m/s^2 were fitted at 0.75, and on a stiff rope a
    rest curvature then explained more). On the log strength the same steps are relative (a factor
    of about 5 either way), and the grid starts every direction at three strengths."""

    name = "external_force"
    description = (
        "a uniform horizontal force field per unit mass (wind); a vertical one is only a gravity error"
    )
    cannot_tell_from = (
        "a tilt of the gravity vector (a mis-levelled motion-capture frame): the same force per mass"
    )

    def __init__(self, n, arclength):
        super().__init__(n, arclength)
        self.log_strength = nn.Parameter(torch.tensor(math.log(0.05), dtype=torch.float64))  # m/s^2
        self.azimuth = nn.Parameter(torch.tensor(0.0, dtype=torch.float64))  # rad, from +x

    def field(self) -> Tensor:
        """(2,) horizontal acceleration [m/s^2]."""
        return self.log_strength.exp() * torch.stack([self.azimuth.cos(), self.azimuth.sin()])

    @staticmethod
    def _polar(ax: float, ay: float) -> dict[str, Tensor]:
        """The raw parameters of the field with components ``ax``, ``ay`` [m/s^2]."""
        return {
            "log_strength": torch.tensor(math.log(max(math.hypot(ax, ay), 1e-9)), dtype=torch.float64),
            "azimuth": torch.tensor(math.atan2(ay, ax), dtype=torch.float64),
        }

    @torch.no_grad()
    def set_field(self, ax: float, ay: float) -> None:
        """Set the field from its components [m/s^2] (a planted truth)."""
        for name, value in self._polar(ax, ay).items():
            getattr(self, name).copy_(value)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        raw = state_dict.pop(prefix + "raw", None)
        if raw is not None:  # a model saved with the field's components (tools before v10): a = raw / 2
            ax, ay = (0.5 * raw).tolist()
            state_dict.update({prefix + k: v for k, v in self._polar(ax, ay).items()})
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def acceleration(self, x, v, mass, rest):
        a = torch.cat([self.field(), self.log_strength.new_zeros(1)]).to(x.dtype)
        return a.expand_as(x)

    def grid(self):  # eight directions at 0.3, 1 and 3 m/s^2: within reach of any wind of 0.06-15
        return [
            {"log_strength": math.log(w), "azimuth": k * math.pi / 4}
            for w in (0.3, 1.0, 3.0)
            for k in range(8)
        ]

    @torch.no_grad()
    def params(self):
        a = self.field().tolist()
        return {"ax_m_per_s2": a[0], "ay_m_per_s2": a[1]}


class MassScale(Term):
    """Mass error, observable part only. A uniform mass factor s is *exactly* equivalent to dividing
    the (fitted) bending and twisting stiffness by s: gravity and damping act per unit mass. So the
    term has one parameter, the mass of each marker (a point mass at every marker), which differs from
    a uniform factor only through the rod's mass distribution; the report says so."""

    name = "mass_scale"
    description = (
        "mass of the markers (a point mass at every marker); a uniform mass factor is not observable"
    )
    cannot_tell_from = (
        "a stiffness scale: at marker resolution a mass on every marker is a uniform mass "
        "factor, and the motion depends on EI / mass only, so the fitted EI and GJ absorb it"
    )

    def __init__(self, n, arclength):
        super().__init__(n, arclength)
        self.raw_g = nn.Parameter(torch.tensor(inv_softplus(0.2), dtype=torch.float64))
        self.register_buffer("on_marker", torch.ones(n, dtype=torch.float64))
        self.rod_mass_kg = 0.0  # unknown: the grid leaves the stiffness alone

    def set_markers(self, nodes: list[int], n_nodes: int) -> None:
        """Markers at these node ids of a simulator with hidden nodes (mass on the markers only)."""
        on = torch.zeros(n_nodes, dtype=torch.float64)
        on[nodes] = 1.0
        self.on_marker = on

    def mass(self, mass):
        return mass + 1e-3 * softplus(self.raw_g) * self.on_marker.to(mass.dtype)

    def init_from_data(self, context):
        self.rod_mass_kg = float(context.get("rod_mass_kg", 0.0))

    def grid(self):
        # a mass on every marker makes the rod heavier, which the nominal fit has already put into
        # its stiffness (only EI / mass is observable): given the rod's mass (context "rod_mass_kg",
        # passed by the hidden-node study, not yet by `diagnose`), each mass is tried with EI and GJ
        # raised by the factor of mass it adds, so the grid compares distributions, not totals
        free = float(self.on_marker[2:-2].sum())
        points = []
        for g in (0.2, 1.0, 3.0, 10.0):
            point = {"raw_g": inv_softplus(g)}
            if self.rod_mass_kg > 0:
                heavier = math.log1p(free * g * 1e-3 / self.rod_mass_kg)
                point.update({"nominal:log_ei": heavier, "nominal:log_gj": heavier})
            points.append(point)
        return points

    @torch.no_grad()
    def params(self):
        return {"marker_mass_kg": float(1e-3 * softplus(self.raw_g))}


class ActuationDelay(Term):
    name = "actuation_delay"
    description = "gripper inputs lagging (or leading) the rod's motion by a fraction of frames"
    scale = 2.0  # frames per raw unit near zero: one Adam step moves the delay by ~0.16 frames

    def __init__(self, n, arclength, max_frames: float = 5.0):
        super().__init__(n, arclength)
        self.raw = nn.Parameter(torch.tensor(0.0, dtype=torch.float64))
        self.max_frames = max_frames

    @property
    def delay_frames(self) -> Tensor:
        return self.max_frames * torch.tanh(self.scale * self.raw / self.max_frames)

    def grid(self):
        """Whole frames from -2 to +4; a lag also with the nominal damping halved or quartered: damping
        makes the rod trail its grippers as a late input does, so a nominal fit has already put part
        of a delay into its damping, and a delay started at full damping looks no better."""
        raw = [
            self.max_frames / self.scale * math.atanh(d / self.max_frames) for d in (-2, -1, 0, 1, 2, 3, 4)
        ]
        lag = raw[4:]  # 1 to 4 frames late
        return [{"raw": r} for r in raw] + [
            {"raw": r, "nominal:log_damping": math.log(share)} for r in lag for share in (0.5, 0.25)
        ]

    @torch.no_grad()
    def params(self):
        return {"delay_frames": float(self.delay_frames)}


class RestCurvature(Term):
    name = "rest_curvature"
    description = "a natural (rest) curvature of the rod in its material frame"
    # the material frame's roll about the grippers is not in marker data: each recording's is read
    # from its first 0.2 s (Simulator.initial_roll), so a curvature means the same in every recording
    rolls_material_frame = True

    def __init__(self, n, arclength):
        super().__init__(n, arclength)
        self.raw = nn.Parameter(torch.zeros(2, dtype=torch.float64))
        self.nodes_per_interval = 1  # > 1 on a simulator with hidden nodes: the turning is shared

    def set_markers(self, nodes: list[int], n_nodes: int) -> None:
        self.nodes_per_interval = nodes[2] - nodes[1]

    def bind(self, exprs):
        exprs = dict(exprs)
        wbar = exprs["wbar"]
        turn = (0.05 * self.raw / self.nodes_per_interval).to(wbar.dtype)
        exprs["wbar"] = wbar + turn.expand(wbar.shape[0], 2, 2)
        return exprs

    def grid(self):  # turning per vertex 0.05 and 0.15 rad in 4 material directions
        return [
            {"raw": [c * m / 0.05, d * m / 0.05]}
            for m in (0.05, 0.15)
            for c, d in ((1, 0), (0, 1), (-1, 0), (0, -1))
        ]

    @torch.no_grad()
    def params(self):
        w = (0.05 * self.raw).tolist()
        return {"kappa1_per_vertex": w[0], "kappa2_per_vertex": w[1]}


LIBRARY: dict[str, type[Term]] = {
    c.name: c
    for c in (
        AerodynamicDrag,
        InternalDamping,
        GroundContact,
        PointMass,
        StiffnessVariation,
        ExternalForce,
        MassScale,
        ActuationDelay,
        RestCurvature,
    )
}


def beyond_material_level(name: str, params: dict[str, float]) -> bool:
    """Whether a fitted term is more than a rope's own material property (:attr:`Term.material_level`),
    so that it may be named; True for terms without a level.

    Args:
        name: a key of :data:`LIBRARY`.
        params: the term's fitted parameters (``Term.params()``, as stored in a report).

    Returns:
        False when the term's level parameter is at or below its level.
    """
    level = getattr(LIBRARY.get(name), "material_level", None)
    if level is None:
        return True
    key, value = level
    return params.get(key, float("inf")) > value


def fitted_beyond_level(name: str, params: dict[str, float]) -> bool:
    """Whether a term that has a rope's material level (:attr:`Term.material_level`) was fitted
    beyond it; False for terms without a level, or without the level's parameter in ``params``.

    Args:
        name: a key of :data:`LIBRARY`.
        params: the term's fitted parameters (``Term.params()``, as stored in a report).
    """
    level = getattr(LIBRARY.get(name), "material_level", None)
    return level is not None and level[0] in params and params[level[0]] > level[1]


def make_term(
    name: str, n: int, arclength: np.ndarray, context: dict | None = None, read_roll: bool = True
) -> Term:
    """A fresh term of the library, started from the data (``context``).

    Args:
        name: a key of :data:`LIBRARY`.
        n: markers (vertices of the simulated rod).
        arclength: (n,) normalised arc length of each.
        context: data-driven starts (``lowest_z``, ``peak_s``, ...).
        read_roll: a term in the material frame reads each recording's roll from its first frames
            (False: the "up" convention's roll, tool v7).

    Returns:
        The :class:`Term`.
    """
    term = LIBRARY[name](n, arclength)
    if getattr(term, "rolls_material_frame", False):
        term.rolls_material_frame = read_roll
    with torch.no_grad():
        term.init_from_data(context or {})
    return term
