r"""DEFORM: a discrete elastic rod with identified parameters, a residual GNN and PBD inextensibility.

One step (semi-implicit Euler, ``dt``), for positions ``x`` and velocities ``v``:

1. material angles ``theta* = argmin E`` over interior edges (ends from the grippers);
2. forces ``F = -dE/dx`` at ``theta*`` in closed form (:mod:`deform.rod.forces`; a test checks
   them against finite differences of the energy);
3. ``v' = v + dt (F / M - c v - k |v_n| v_n) + r(x, v)`` with ``r`` the residual network (with
   ``implicit_bending`` in the rod's config, the first part filtered by a backward-Euler step of the
   linear bending, :mod:`deform.rod.implicit`, before ``r`` is added);
4. ``x' = x + dt v'``; gripped vertices 0, 1, n-2, n-1 set to their inputs;
5. PBD projects edges to their rest lengths, gripped vertices being infinitely heavy;
6. ``v = (x_new - x) / dt`` and reference frames are parallel-transported in time.

With ``substeps`` N in the rod's config (the stiffest light cables) a frame is N such steps of
``dt / N``, the grippers moved linearly between frames and ``r`` added in the first only.

Parameters identified from data: per-vertex bending and twisting stiffness (log scale), rest
material curvature, extra point masses per vertex, linear damping and quadratic air drag.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from deform.config import RodConfig, generic_rod, load_rod_config
from deform.nn.residual import ResidualGNN
from deform.rod import geometry as G
from deform.rod.convergence import ConvergenceReport, merge_reports
from deform.rod.energy import (
    ElasticParams,
    curvature_projections,
    fused_geometry_and_projections,
    geometry_and_projections,
    rod_geometry,
)
from deform.rod.forces import fused_rod_forces, rod_forces
from deform.rod.implicit import apply_implicit_filter, implicit_bending_velocity, implicit_filter, step_ratio
from deform.rod.inextensibility import (
    PBDMethod,
    enforce_inextensibility,
    max_relative_error,
    unweighted_inv_mass,
)
from deform.rod.layout import batch_major, vertex_major
from deform.rod.positive import inv_softplus
from deform.rod.tridiagonal import solve_tridiagonal_pd
from deform.rod.twist_solver import gradient_and_hessian, solve_theta

MODEL_DIR = Path(__file__).resolve().parent / "models"

# The explicit step's bending margin (omega_max dt, deform.rod.implicit.step_ratio) above which a model
# whose stiffness is being chosen steps its bending implicitly. Bent by 30 % and held (1 m, 12
# vertices), rods came to rest at ratios up to 1.05 and rang from 1.49 (DLO3's explicit model: 1.78);
# of the DEFORM ropes DLO2 and DLO3 are above it (shipped trained implicitly), DLO1, DLO4, DLO5 below.
IMPLICIT_ABOVE = 1.0
# The same margin per substep that the implicit step keeps: bent and held, implicit rods came to rest
# up to a ratio of 3.64 and rang from 4.70 (bending_stability.json), so a model whose ratio per frame
# is above it takes ceil(ratio / IMPLICIT_RATIO_MAX) substeps a frame.
IMPLICIT_RATIO_MAX = 3.5


def gripped_indices(n: int) -> list[int]:
    """The vertices the grippers hold, given as inputs at every step (the paper's protocol).

    Args:
        n: vertices of the rod.

    Returns:
        ``[0, 1, n-2, n-1]``: the gripper's end vertex and its neighbour on each side.
    """
    return [0, 1, n - 2, n - 1]


def _reach_ratio(grip: Tensor, rest: Tensor) -> Tensor:
    """Distance between the inner gripped vertices 1 and n-2 over the free chain's rest length
    ``sum(rest[1:n-2])``: above 1, no shape of the rod reaches both grippers."""
    return (grip[..., 1, :] - grip[..., 2, :]).norm(dim=-1) / rest[..., 1:-1].sum(-1)


def overstretched(grip: Tensor, rest: Tensor) -> Tensor:
    """True where the grippers hold the rod farther apart than it is long (vertices 1 and n-2 more
    than the free chain's rest length apart). No shape then meets the edge lengths, and the
    projection cannot converge. ``grip`` (..., 4, 3) as ``DeformModel.step`` takes it, ``rest``
    (..., n-1), broadcast against each other.

    Args:
        grip: (..., 4, 3) gripped vertices 0, 1, n-2, n-1 [m].
        rest: (..., n-1) rest lengths [m].

    Returns:
        (...) bool.
    """
    return _reach_ratio(grip, rest) > 1.0


def rest_within_reach(rest: Tensor, grip: Tensor, slack: float = 1e-3) -> Tensor:
    """Edge lengths the inextensibility projection can meet with the grippers at ``grip``: ``rest``
    unless the rod is (nearly) :func:`overstretched`, in which case its free edges are stretched
    uniformly to ``1 + slack`` times what reaching the grippers takes. Why: for a chain held farther
    apart than it is long the projection has no solution, and its Newton-like sweeps (singular
    system for a straight chain) fling the free vertices about at metres per second; stretched, the
    rod lies straight between the grippers. A model change only where no shape was valid: the
    recordings never come within 1 % of it.

    Args:
        rest: (n-1, B) rest lengths [m], vertex-major (:mod:`deform.rod.layout`).
        grip: (4, 3, B) gripped vertices [m].
        slack: relative extra length over what reaching takes.

    Returns:
        (n-1, B) rest lengths to project to.
    """
    scale = (_reach_ratio(grip.movedim(-1, 0), rest.movedim(-1, 0)) * (1.0 + slack)).clamp_min(1.0)
    return torch.cat([rest[:1], rest[1:-1] * scale, rest[-1:]])


@dataclass
class RodState:
    """Batched rod state. ``x``, ``v``: (B, n, 3); ``d1``: (B, m, 3) reference directors of the
    edges of ``x``; ``theta``: (B, m) material angles (warm start); ``rest``: (B, m) edge lengths."""

    x: Tensor
    v: Tensor
    d1: Tensor
    theta: Tensor
    rest: Tensor

    def detach(self) -> RodState:
        return RodState(*(t.detach() for t in (self.x, self.v, self.d1, self.theta, self.rest)))

    def index(self, idx) -> RodState:
        return RodState(*(t[idx] for t in (self.x, self.v, self.d1, self.theta, self.rest)))

    def vertex_major(self, rest: Tensor | None = None) -> VertexMajorState:
        """The same rods with the batch as the last axis, the layout the physics runs in; ``rest``:
        the rest lengths already converted (None: converted here)."""
        return VertexMajorState(
            vertex_major(self.x, 2),
            vertex_major(self.v, 2),
            vertex_major(self.d1, 2),
            vertex_major(self.theta, 1),
            vertex_major(self.rest, 1) if rest is None else rest,
        )


@dataclass
class VertexMajorState:
    """:class:`RodState` with the batch last (:mod:`deform.rod.layout`): ``x``, ``v`` (n, 3, B);
    ``d1`` (m, 3, B); ``theta``, ``rest`` (m, B). What the step computes on and the compiled step
    takes, so that its loops run over the rods innermost."""

    x: Tensor
    v: Tensor
    d1: Tensor
    theta: Tensor
    rest: Tensor

    def index(self, idx) -> VertexMajorState:
        """The rods ``idx`` (an index into the last axis)."""
        return VertexMajorState(*(t[..., idx] for t in (self.x, self.v, self.d1, self.theta, self.rest)))

    def batch_major(self) -> RodState:
        """Back to a :class:`RodState` (B, ...)."""
        batch = (self.x.shape[-1],)
        return RodState(*(batch_major(t, batch) for t in (self.x, self.v, self.d1, self.theta, self.rest)))


class ThetaSolver(str, enum.Enum):
    """Who minimises the energy over the material angles: the fast Newton solver or Theseus (reference)."""

    NEWTON = "newton"
    THESEUS = "theseus"


@dataclass
class ModelOptions:
    residual: bool = True
    weighted_pbd: bool = True  # False: the 'original inextensibility' of the ablation
    pbd_tol: float = 1e-3
    pbd_max_sweeps: int = 20
    pbd_method: PBDMethod = PBDMethod.PROJECTION
    theta_tol: float = 1e-6  # target error of the material angles [rad]
    theta_solver: ThetaSolver = ThetaSolver.NEWTON

    def __post_init__(self):  # strings from configs, the CLI and saved checkpoints, checked once here
        for name, kind in (("pbd_method", PBDMethod), ("theta_solver", ThetaSolver)):
            value = getattr(self, name)
            try:
                setattr(self, name, kind(value))
            except ValueError:
                allowed = ", ".join(m.value for m in kind)
                raise ValueError(f"{name}={value!r}: choose one of {allowed}") from None

    def as_dict(self) -> dict:
        """Plain values (strings for the enums): what a checkpoint stores."""
        return {k: (v.value if isinstance(v, enum.Enum) else v) for k, v in vars(self).items()}


class DeformModel(nn.Module):
    def __init__(self, cfg: RodConfig, options: ModelOptions | None = None):
        super().__init__()
        # its own copy: the bending scheme is set on it (choose_bending_scheme), not on the caller's
        self.cfg = cfg.model_copy()
        self.options = options or ModelOptions()
        n = cfg.n_vertices
        self.n = n
        self.dt = cfg.dt
        self.log_beta = nn.Parameter(torch.full((n - 2,), math.log(cfg.bend_stiffness)))
        self.log_gamma = nn.Parameter(torch.full((n - 2,), math.log(cfg.twist_stiffness)))
        self.wbar = nn.Parameter(torch.zeros(n - 2, 2, 2))
        # extra point masses (markers) in grams through a softplus; rod mass is fixed from the config
        self.extra_mass_raw = nn.Parameter(torch.full((n,), inv_softplus(cfg.marker_mass_kg * 1e3)))
        self.log_damping = nn.Parameter(torch.tensor(math.log(max(cfg.damping, 1e-4))))
        self.log_drag = nn.Parameter(torch.tensor(math.log(max(cfg.drag, 1e-4))))
        self.residual = ResidualGNN(n)
        # optional physics terms added by tools (e.g. the discrepancy tool's candidate effects):
        # modules with `acceleration(x, v, mass, rest) -> (B, n, 3)` and/or `mass(mass) -> (B, n)`
        self.extensions = nn.ModuleList()
        # with create_graph, the elastic parameters and masses of a rollout computed once (for its
        # rest lengths) instead of at every step, as without a graph: right when each rollout is
        # backpropagated once, as the discrepancy tool's fits do (a fifth of their steps); off for
        # training, which may backpropagate a rollout in pieces
        self.graph_params_per_rollout = False
        # the straight-line pieces of a step compiled, forward and backward (deform.rod.fusion): for
        # the discrepancy tool's many small descents; off where a step is compiled whole or
        # differentiated twice (training)
        self.fused_pieces = False
        grip = torch.zeros(n)
        grip[gripped_indices(n)] = 1.0
        self.register_buffer("gripped", grip)
        # typical edge lengths (m,): from the training recordings (see deform.train); the even
        # spread of the configured length until then. Used where no recording gives them (a rod
        # first seen by a camera).
        self.register_buffer(
            "nominal_rest", torch.full((n - 1,), cfg.length_m / (n - 1), dtype=torch.float64)
        )

    # ----- parameters -------------------------------------------------------------------------
    def _physical(self, rest: Tensor, create_graph: bool) -> tuple[ElasticParams, Tensor]:
        """Elastic parameters and vertex masses for these rest lengths.

        At run time they are cached until a parameter changes (an optimiser step or a load bumps
        the parameters' version counters): recomputing them is a fifth of a 13-vertex step.
        """
        if create_graph and not self.graph_params_per_rollout:
            return self.elastic_params(rest), self.vertex_mass(rest)
        if torch.compiler.is_compiling():  # compiled code fuses these; a cache keyed on ids would recompile
            with torch.no_grad():
                return self.elastic_params(rest), self.vertex_mass(rest)
        key = (
            id(rest),
            rest._version,
            rest.dtype,
            tuple(p._version for p in self.parameters()),
            len(self.extensions),
            create_graph,
        )
        cached = getattr(self, "_physical_cache", None)
        if cached is not None and cached[0] == key and cached[1] is rest:
            return cached[2], cached[3]
        if create_graph:  # graph_params_per_rollout: once per rollout (its rest lengths), in the graph
            params, mass = self.elastic_params(rest), self.vertex_mass(rest)
            self._physical_cache = (key, rest, params, mass)
            return params, mass
        with torch.no_grad():
            p = self.elastic_params(rest)
            params = ElasticParams(*(t.detach() for t in (p.beta, p.gamma, p.wbar, p.rest_vor)))
            mass = self.vertex_mass(rest).detach()
        self._physical_cache = (key, rest, params, mass)
        return params, mass

    @torch.no_grad()
    def bending_step_ratio(self) -> float:
        """:func:`deform.rod.implicit.step_ratio` of this model on its typical rest lengths: above
        :data:`IMPLICIT_ABOVE` the explicit step would ring on a bent, held rod."""
        rest = self.nominal_rest.to(torch.float64)[:, None]
        params, mass = self.elastic_params(rest), self.vertex_mass(rest).to(torch.float64)
        return float(
            step_ratio(params.beta.to(torch.float64), rest, mass, self.dt, gripped_indices(self.n)).amax()
        )

    def choose_bending_scheme(self) -> bool:
        """Step the bending implicitly where the explicit step would ring (a stiff light cable, a
        short rope at 12 vertices), and in substeps where even that would (ratio above
        :data:`IMPLICIT_RATIO_MAX`): sets ``cfg.implicit_bending`` and ``cfg.substeps``, returns the
        former. For models whose stiffness is being chosen (system identification, a rope known by
        length and mass)."""
        ratio = self.bending_step_ratio()
        self.cfg.implicit_bending = ratio > IMPLICIT_ABOVE
        self.cfg.substeps = max(1, math.ceil(ratio / IMPLICIT_RATIO_MAX)) if self.cfg.implicit_bending else 1
        return self.cfg.implicit_bending

    @property
    def substep_dt(self) -> float:
        """The time one substep advances: ``dt / cfg.substeps``."""
        return self.dt / self.cfg.substeps

    def _implicit_filter(self, params: ElasticParams, mass: Tensor, rest: Tensor) -> tuple[Tensor, Tensor]:
        """The implicit bending filter's matrices (:func:`deform.rod.implicit.implicit_filter`) for
        these parameters, kept while :meth:`_physical` hands out the same (cached) parameters: a
        rollout inverts once, not at every step."""
        dt = self.substep_dt
        cached = getattr(self, "_implicit_cache", None)
        if cached is not None and cached[0] is params and cached[1] is mass and cached[2] == dt:
            return cached[3]
        matrices = implicit_filter(params.beta, rest, mass, dt, gripped_indices(self.n))
        self._implicit_cache = (params, mass, dt, matrices)
        return matrices

    def vertex_mass(self, rest: Tensor) -> Tensor:
        """(n, B): the rod's mass spread by Voronoi length, plus the extra point masses; ``rest``
        (m, B), vertex-major."""
        half = 0.5 * rest
        vor = torch.cat([half[:1], half[:-1] + half[1:], half[-1:]])
        rod = self.cfg.mass_kg * vor / rest.sum(0, keepdim=True)
        mass = rod + nn.functional.softplus(self.extra_mass_raw).to(rest.dtype)[:, None] * 1e-3
        for ext in self.extensions:
            if hasattr(ext, "mass"):  # terms take and give (B, n)
                mass = ext.mass(mass.T).T.contiguous()  # one layout for every model: fused pieces
        return mass

    def elastic_params(self, rest: Tensor) -> ElasticParams:
        """Vertex-major :class:`ElasticParams` for rest lengths ``rest`` (m, B).

        The parameters are the rod's, shared by every rod of a batch, or per rod: ``log_beta`` and
        ``log_gamma`` (m, B), ``wbar`` (m, 2, 2, B) and ``log_damping`` (B,) give each rod its own
        (the discrepancy tool steps several candidate models as one batch: deform.diagnose.stack)."""
        dtype = rest.dtype
        # fused pieces (deform.rod.fusion) are compiled for per-rod parameters, shared ones widened
        # to them: one compiled piece for a model alone and for several stacked
        rods = rest.shape[-1] if self.fused_pieces else 1

        def per_rod(p: Tensor, dims: int) -> Tensor:
            return (
                p.to(dtype)[..., None].expand(*p.shape, rods).contiguous() if p.dim() == dims else p.to(dtype)
            )

        return ElasticParams(
            beta=per_rod(self.log_beta.exp(), 1),
            gamma=per_rod(self.log_gamma.exp(), 1),
            wbar=per_rod(self.wbar, 3),
            rest_vor=G.voronoi_lengths(rest),
        )

    @property
    def damping(self) -> Tensor:
        return self.log_damping.exp()

    @property
    def drag(self) -> Tensor:
        return self.log_drag.exp()

    def drag_acceleration(self, x: Tensor, v: Tensor) -> Tensor:
        """Air drag: linear damping ``-c v`` plus quadratic drag on the normal velocity
        ``-k |v_n| v_n`` (``v_n`` = velocity across the rod; a rope whipping at a few m/s feels it).
        ``x``, ``v``: (n, 3, B)."""
        v_n = G.normal_velocity(x, v)
        return -self.damping.to(x.dtype) * v - self.drag.to(x.dtype) * G.norm(v_n, keepdim=True) * v_n

    # ----- state ------------------------------------------------------------------------------
    def initial_state(
        self, x0: Tensor, x1: Tensor, dt: float | None = None, d1: Tensor | None = None
    ) -> RodState:
        """State at frame 1 from two observed frames (B, n, 3); rest lengths from frame 0.

        ``d1`` (B, n-1, 3): reference directors at frame 1; default space-parallel, which is what a
        recording's first frames get. A window cut from later in a recording passes the directors
        a rollout from the recording's start carries there (``Recording.reference_frames``)."""
        dt = dt or self.dt
        x0, x1 = torch.as_tensor(x0), torch.as_tensor(x1)
        if x1.dim() == 2:
            x0, x1 = x0.unsqueeze(0), x1.unsqueeze(0)
        batch = x1.shape[:-2]
        t = G.normalize(G.edges(vertex_major(x1, 2)))
        d1 = (
            G.space_parallel_frame(t)
            if d1 is None
            else G.time_transport(vertex_major(torch.as_tensor(d1, dtype=x1.dtype), 2, batch), t, t)
        )
        theta = torch.zeros(*batch, self.n - 1, dtype=x1.dtype)
        rest = G.norm(G.edges(vertex_major(x0, 2, batch)))
        return RodState(
            x=x1, v=(x1 - x0) / dt, d1=batch_major(d1, batch), theta=theta, rest=batch_major(rest, batch)
        )

    def static_state(self, x: Tensor, rest: Tensor | None = None) -> RodState:
        """State at rest at positions ``x`` (B, n, 3), e.g. a guess to be relaxed by :meth:`settle`."""
        if x.dim() == 2:
            x = x.unsqueeze(0)
        batch = x.shape[:-2]
        e = G.edges(vertex_major(x, 2))
        rest = batch_major(G.norm(e), batch) if rest is None else rest
        return RodState(
            x=x,
            v=torch.zeros_like(x),
            d1=batch_major(G.space_parallel_frame(G.normalize(e)), batch),
            theta=torch.zeros(*batch, self.n - 1, dtype=x.dtype),
            rest=rest,
        )

    def rest_lengths(self, grip: Tensor | None = None) -> Tensor:
        """(m,) rest lengths for a rod seen without a recording: the nominal ones, with the two
        gripped end edges as the grippers hold them when ``grip`` (4, 3) is given."""
        rest = self.nominal_rest.clone()
        if grip is not None:
            grip = torch.as_tensor(grip, dtype=rest.dtype).reshape(4, 3)
            rest[0] = (grip[1] - grip[0]).norm()
            rest[-1] = (grip[3] - grip[2]).norm()
        return rest

    def reposition(self, state: RodState, x: Tensor, v: Tensor | None = None) -> RodState:
        """The state moved to positions ``x`` (e.g. corrected by perception).

        ``x`` is first projected onto the rest lengths (gripped vertices 0, 1, n-2, n-1 fixed, the
        same mass-weighted projection as a step): a correction that moves some vertices and not
        their neighbours breaks edge lengths, and left as it is the next step's projection snaps
        them back within one ``dt``, which the velocity update ``(x_new - x) / dt`` turns into
        metres per second of spurious velocity. Then reference frames are parallel-transported
        to the new edges so that twist is carried over consistently, and the material angles
        re-solved for the new shape (ends kept): a corrected shape can turn a naturally curved
        rod's material frame by radians; solved here, the next step's solve starts converged
        instead of taking tens of iterations."""
        batch = state.x.shape[:-2]
        vm = self._vertex_major(state)
        x = vertex_major(x.to(state.x.dtype), 2, batch)
        with torch.no_grad():
            params, mass = self._physical(vm.rest, False)
            inv_mass = self._projection_inv_mass(mass, held=True)
            x = enforce_inextensibility(
                x,
                inv_mass,
                vm.rest,
                self.options.pbd_tol,
                self.options.pbd_max_sweeps,
                self.options.pbd_method,
            )
        d1 = G.time_transport(vm.d1, G.normalize(G.edges(vm.x)), G.normalize(G.edges(x)))
        v = vm.v if v is None else vertex_major(v.to(state.x.dtype), 2, batch)
        moved = VertexMajorState(x=x, v=v, d1=d1, theta=vm.theta, rest=vm.rest)
        with torch.no_grad():
            theta = self._angles(x, moved, params, None)[3]
        # the same rest-length tensor back, as a step hands it on: the parameters cached on it stay valid
        return RodState(*(batch_major(t, batch) for t in (x, v, d1, theta)), state.rest)

    # ----- dynamics ---------------------------------------------------------------------------
    def forces(
        self, state: RodState, theta_ends: Tensor | None = None, create_graph: bool = False
    ) -> tuple[Tensor, Tensor]:
        """Conservative forces ``-dE/dx`` (B, n, 3) at the energy-minimising angles, and those angles
        (B, m); ``theta_ends`` (B, 2) the end edges' angles (None: the state's).

        Closed form (:mod:`deform.rod.forces`); differentiable with first-order autograd when
        ``create_graph`` (training), the angles then carrying implicit-function-theorem gradients.
        """
        vm = state.vertex_major()
        params, mass = self._physical(vm.rest, create_graph)
        ends = None if theta_ends is None else vertex_major(theta_ends, 1)
        force, theta, _ = self._forces(vm, params, mass, ends, create_graph)
        batch = state.x.shape[:-2]
        return batch_major(force, batch), batch_major(theta, batch)

    def _forces(
        self,
        state: VertexMajorState,
        params: ElasticParams,
        mass: Tensor,
        theta_ends: Tensor | None,
        create_graph: bool,
        branch_free: int = 0,
        report: ConvergenceReport | None = None,
        groups: int = 1,
        closed_form_groups: int = 0,
    ):
        """(forces (n, 3, B), angles (m, B), tangents (m, 3, B)) of a vertex-major state."""
        x = state.x if create_graph else state.x.detach()
        geo, a, b, theta = self._angles(
            x, state, params, theta_ends, branch_free, report, groups, closed_form_groups
        )
        force = (fused_rod_forces if self.fused_pieces else rod_forces)(x, geo, a, b, theta, params, mass)
        return force, theta, geo.t

    def _angles(
        self,
        x: Tensor,
        state: VertexMajorState,
        params: ElasticParams,
        theta_ends: Tensor | None,
        branch_free: int = 0,
        report: ConvergenceReport | None = None,
        groups: int = 1,
        closed_form_groups: int = 0,
    ):
        """(geometry, projections a and b, energy-minimising angles (m, B)) at positions ``x``: what
        the forces need, and all a corrected shape needs (:meth:`reposition`)."""
        if theta_ends is None:
            theta_ends = state.theta[[0, -1]].detach()
        # the frame is carried along by parallel transport: identity at x, but it moves with x
        fused = self.fused_pieces
        geo, a, b = (fused_geometry_and_projections if fused else geometry_and_projections)(x, state.d1)
        theta = self._solve_theta(
            a, b, geo.m_ref, theta_ends, params, state.theta, branch_free, report, groups, closed_form_groups
        )
        return geo, a, b, theta

    def _solve_theta(
        self,
        a,
        b,
        m_ref,
        theta_ends,
        params: ElasticParams,
        theta_init,
        branch_free: int = 0,
        report: ConvergenceReport | None = None,
        groups: int = 1,
        closed_form_groups: int = 0,
    ):
        if self.options.theta_solver == ThetaSolver.THESEUS:
            from deform.rod.twist_theseus import theseus_theta

            return theseus_theta(
                a, b, m_ref, theta_ends, params.beta, params.gamma, params.rest_vor, params.wbar
            )
        return solve_theta(
            a,
            b,
            m_ref,
            theta_ends,
            params.beta,
            params.gamma,
            params.rest_vor,
            params.wbar,
            theta_init=theta_init,
            tol=self.options.theta_tol,
            branch_free=branch_free,
            report=report,
            groups=groups,
            closed_form_groups=closed_form_groups,
        )

    def step(
        self,
        state: RodState,
        grip_next: Tensor | None,
        theta_ends: Tensor | None = None,
        create_graph: bool = False,
        branch_free: tuple[int, int] = (0, 0),
        report: ConvergenceReport | None = None,
        network_dtype: torch.dtype | None = None,
    ) -> RodState:
        """Advance one ``dt``. ``grip_next`` (B, 4, 3): vertices 0, 1, n-2, n-1 at the new time
        (``None``: nothing is held, e.g. a dropped rope). ``theta_ends`` (B, 2): the end edges'
        angles (None: the state's). ``branch_free``: iterations of the twist
        solve and sweeps of the projection done without host synchronisation before the checked
        loops (for compiled code; same result per rod, see :func:`newton_theta`). ``report``: a
        :class:`ConvergenceReport` that receives the solvers' per-rod convergence after those iterations (``twist_unconverged``,
        ``length_error``; see :meth:`unconverged_from_report`). ``network_dtype``: the residual
        network's arithmetic (None: float32; bfloat16 in batched rollouts, :mod:`deform.nn.precision`).
        The physics runs vertex-major (:meth:`step_vertex_major`)."""
        grip = None if grip_next is None else vertex_major(grip_next, 2)
        ends = None if theta_ends is None else vertex_major(theta_ends, 1)
        new = self.step_vertex_major(
            self._vertex_major(state), grip, ends, create_graph, branch_free, report, network_dtype
        )
        batch = state.x.shape[:-2]
        return RodState(*(batch_major(t, batch) for t in (new.x, new.v, new.d1, new.theta)), state.rest)

    def _vertex_major(self, state: RodState) -> VertexMajorState:
        """``state.vertex_major()``, the rest lengths' conversion kept while the same tensor comes
        back (a rollout passes its rest lengths on unchanged), so that the parameters cached on it
        (:meth:`_physical`) stay valid from step to step."""
        cached = getattr(self, "_rest_vertex_major", None)
        if cached is not None and cached[0] is state.rest and cached[1] == state.rest._version:
            return state.vertex_major(rest=cached[2])
        vm = state.vertex_major()
        self._rest_vertex_major = (state.rest, state.rest._version, vm.rest)
        return vm

    def step_vertex_major(
        self,
        state: VertexMajorState,
        grip_next: Tensor | None,
        theta_ends: Tensor | None = None,
        create_graph: bool = False,
        branch_free: tuple[int, int] = (0, 0),
        report: ConvergenceReport | None = None,
        network_dtype: torch.dtype | None = None,
        groups: int = 1,
        closed_form_groups: int = 0,
    ) -> VertexMajorState:
        """:meth:`step` on a :class:`VertexMajorState`, ``grip_next`` (4, 3, B) and ``theta_ends``
        (2, B): what compiled steps trace (their callers convert outside the graph). ``groups``: the
        batch is that many equal runs of consecutive rods whose solvers each iterate until their own
        rods converge (several models in one batch, each stepped as if alone: deform.diagnose.stack);
        the first ``closed_form_groups`` of them take the twist angles in closed form (no rest
        curvature), the others the iterative solve (:func:`deform.rod.twist_solver.solve_theta`).

        With ``cfg.substeps`` N > 1 the frame is N steps of ``dt / N``, the grippers moved linearly
        from where they hold the rod to ``grip_next``; the residual network's velocity correction,
        learnt per frame, is added once, in the first. ``report`` then holds the worst of them."""
        r = None
        if self.options.residual:  # the network is batch-first
            r = self.residual(
                state.x.movedim(-1, 0).to(torch.float32),
                state.v.movedim(-1, 0).to(torch.float32),
                network_dtype,
            ).movedim(0, -1)
        solver = (theta_ends, create_graph, branch_free, groups, closed_form_groups)
        substeps = self.cfg.substeps
        if substeps == 1:
            return self._substep(state, grip_next, self.dt, r, report, *solver)
        start = None if grip_next is None else state.x[gripped_indices(self.n)]
        reports = []
        for k in range(1, substeps + 1):
            grip = grip_next
            if grip_next is not None and k < substeps:
                grip = start + (grip_next.to(start.dtype) - start) * (k / substeps)
            sub = None if report is None else ConvergenceReport()
            state = self._substep(state, grip, self.substep_dt, r if k == 1 else None, sub, *solver)
            reports.append(sub)
        if report is not None:
            merge_reports(report, reports)
        return state

    def _substep(
        self,
        state: VertexMajorState,
        grip_next: Tensor | None,
        dt: float,
        residual: Tensor | None,
        report: ConvergenceReport | None,
        theta_ends: Tensor | None,
        create_graph: bool,
        branch_free: tuple[int, int],
        groups: int,
        closed_form_groups: int,
    ) -> VertexMajorState:
        """One step of ``dt`` (the module docstring's steps 1-6); ``residual`` (n, 3, B) or None: the
        network's velocity correction."""
        x, v = state.x, state.v
        params, mass = self._physical(state.rest, create_graph)
        force, theta, t_old = self._forces(
            state, params, mass, theta_ends, create_graph, branch_free[0], report, groups, closed_form_groups
        )
        accel = force / mass.unsqueeze(-2) + self.drag_acceleration(x, v)
        for ext in self.extensions:
            if hasattr(ext, "acceleration"):  # terms take and give (B, n, 3)
                a = ext.acceleration(x.movedim(-1, 0), v.movedim(-1, 0), mass.T, state.rest.T)
                accel = accel + a.movedim(0, -1)
        v_pred = v + dt * accel
        if self.cfg.implicit_bending and grip_next is not None:  # a held rod (deform.rod.implicit)
            held = gripped_indices(self.n)
            v_held = (grip_next.to(x.dtype) - x[held]) / dt
            if torch.compiler.is_compiling():  # the band solve, fused (deform.rod.implicit)
                v_pred = implicit_bending_velocity(v_pred, v_held, params.beta, state.rest, mass, dt, held)
            else:
                v_pred = apply_implicit_filter(
                    v_pred, v_held, self._implicit_filter(params, mass, state.rest), held
                )
        if residual is not None:
            v_pred = v_pred + residual.to(x.dtype)
        x_pred = x + dt * v_pred
        if grip_next is not None:
            x_pred = x_pred.clone()
            x_pred[gripped_indices(self.n)] = grip_next.to(x_pred.dtype)
        inv_mass = self._projection_inv_mass(mass, held=grip_next is not None)
        rest = state.rest if grip_next is None else rest_within_reach(state.rest, grip_next.to(x_pred.dtype))
        x_new = enforce_inextensibility(
            x_pred,
            inv_mass,
            rest,
            self.options.pbd_tol,
            self.options.pbd_max_sweeps,
            self.options.pbd_method,
            branch_free[1],
            report,
            groups,
            self.fused_pieces,
        )
        v_new = (x_new - x) / dt
        t_new = G.normalize(G.edges(x_new))
        d1_new = G.time_transport(state.d1, t_old, t_new)
        new = (x_new, v_new, d1_new, theta)
        return VertexMajorState(*(new if create_graph else (t.detach() for t in new)), state.rest)

    def _projection_inv_mass(self, mass: Tensor, held: bool) -> Tensor:
        """Inverse masses (n, B) for the inextensibility projection: 0 at the gripped vertices when
        ``held`` (infinitely heavy), all free vertices equal for the 'original inextensibility' ablation."""
        inv_mass = 1.0 / mass
        if held:
            inv_mass = inv_mass * (1.0 - self.gripped.to(mass.dtype))[:, None]
        return inv_mass if self.options.weighted_pbd else unweighted_inv_mass(inv_mass)

    def unconverged(self, before: RodState, after: RodState, held: bool = True) -> Tensor:
        """(B,) bool: rods whose step from ``before`` to ``after`` left the twist angles or the edge
        lengths outside the solver tolerances: one more Newton step on theta would exceed
        ``sqrt(theta_tol)`` rad (the solver's own stopping rule), or an edge that can move is off its
        rest length by more than ``pbd_tol``: a second evaluation, against which the tests check
        the flags compiled steps report after their fixed iteration counts
        (:meth:`unconverged_from_report`; ``held``: the grippers held vertices 0, 1, n-2, n-1).
        With substeps the angles were solved at the last substep's positions, which ``before`` does
        not hold: only the lengths are checked (the solvers' report checks both,
        :meth:`unconverged_from_report`)."""
        before, after = before.vertex_major(), after.vertex_major()
        params, mass = self._physical(before.rest, False)
        geo = rod_geometry(before.x, before.d1)
        a, b = curvature_projections(geo)
        grad, diag, off = gradient_and_hessian(
            after.theta, a, b, geo.m_ref, params.beta, params.gamma, params.rest_vor, params.wbar
        )
        step, pd = solve_tridiagonal_pd(diag, off, grad, dim=0)
        twist_bad = ~pd | ~(step.abs().amax(0) < max(self.options.theta_tol, 1e-12) ** 0.5)
        inv_mass = self._projection_inv_mass(mass, held)  # only which vertices can move matters here
        rest = rest_within_reach(before.rest, after.x[gripped_indices(self.n)]) if held else before.rest
        length_bad = ~(max_relative_error(after.x, rest, inv_mass, per_rod=True) < self.options.pbd_tol)
        if self.options.theta_solver == ThetaSolver.THESEUS or self.cfg.substeps > 1:
            twist_bad = torch.zeros_like(twist_bad)
        return twist_bad | length_bad

    def unconverged_from_report(self, report: ConvergenceReport) -> Tensor:
        """(B,) bool: what :meth:`unconverged` says, from the flags a ``branch_free`` step reported
        (the solvers' own stopping rules after their fixed iterations) instead of a second
        evaluation of the twist Hessian: about a fifth of a short compiled step."""
        bad = ~(report.length_error < self.options.pbd_tol)  # NaN counts as unconverged
        if report.twist_unconverged is not None:  # None with the Theseus solver, as in :meth:`unconverged`
            bad = bad | report.twist_unconverged
        return bad

    def rollout(self, state: RodState, grips: Tensor, create_graph: bool = False) -> tuple[Tensor, RodState]:
        """Open-loop prediction. ``grips`` (B, T, 4, 3) -> positions (B, T, n, 3) and the final state."""
        out = []
        for k in range(grips.shape[-3]):
            state = self.step(state, grips[..., k, :, :], create_graph=create_graph)
            out.append(state.x)
        return torch.stack(out, dim=-3), state

    def settle(self, state: RodState, grip: Tensor, max_steps: int = 2000, tol: float = 1e-4) -> RodState:
        """Simulate with the grippers fixed until the rod is static (max speed below ``tol`` m/s)."""
        for _ in range(max_steps):
            state = self.step(state, grip)
            if float(state.v.abs().amax()) < tol:
                break
        return state

    # ----- persistence ------------------------------------------------------------------------
    def save(self, path: str | Path, extra: dict | None = None) -> None:
        payload = {
            "config": self.cfg.model_dump(),
            "options": self.options.as_dict(),
            "state_dict": self.state_dict(),
        }
        if len(self.extensions):  # physics terms trained into the model (deform.terms)
            from deform.terms import attached_names

            payload["terms"] = attached_names(self)
        payload.update(extra or {})
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        torch.save(payload, path)

    @classmethod
    def load(cls, path: str | Path) -> DeformModel:
        """A checkpoint written by :meth:`save` (loaded with ``weights_only``: tensors and plain
        data only). Raises :class:`deform.errors.CheckpointError` naming the file when it is
        missing, unreadable or of another model."""
        from deform.errors import CheckpointError

        if not Path(path).is_file():
            raise CheckpointError(f"{path}: no such model file")
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except OSError as exc:  # there, but not readable (permissions): not a question of its contents
            raise CheckpointError(f"{path}: cannot be read ({exc.strerror or type(exc).__name__})") from None
        except Exception as exc:  # torch raises several types for a file that is no checkpoint
            raise CheckpointError(f"{path}: not a DEFORM checkpoint ({type(exc).__name__})") from None
        if not isinstance(payload, dict) or not {"config", "options", "state_dict"} <= payload.keys():
            raise CheckpointError(f"{path}: not a DEFORM checkpoint (no config, options and state_dict)")
        model = cls(RodConfig(**payload["config"]), ModelOptions(**payload["options"]))
        if payload.get("terms"):
            from deform.terms import rebuild

            rebuild(model, payload["terms"])
        missing, unexpected = model.load_state_dict(payload["state_dict"], strict=False)
        if unexpected or any(k not in ("log_drag", "nominal_rest") for k in missing):
            raise CheckpointError(
                f"{path}: checkpoint does not match the model (missing {missing}, unexpected {unexpected})"
            )
        if payload.get("terms"):
            from deform.terms import fix_rest

            fix_rest(model)  # on the loaded typical rest lengths
        return model


def load_model(rod: str | Path, options: ModelOptions | None = None) -> DeformModel:
    """The trained model of a rod shipped in ``deform/models/<rod>.pt``, a checkpoint path, or
    (when no model is shipped) the untrained model with the config's initial parameters.

    Args:
        rod: a shipped rod's name (``"DLO1"``), a rod YAML's name, or a ``.pt`` checkpoint.
        options: run-time options replacing the stored ones (None: keep them).

    Returns:
        The :class:`DeformModel`, float32 parameters; states are float64.
    """
    path = Path(rod)
    if path.suffix == ".pt":
        model = DeformModel.load(path)
    elif (MODEL_DIR / f"{rod}.pt").is_file():
        model = DeformModel.load(MODEL_DIR / f"{rod}.pt")
    else:
        model = DeformModel(load_rod_config(rod))
    if options is not None:
        model.options = options
    return model


def generic_model(
    length_m: float, mass_kg: float, n_vertices: int = 12, prior: float | None = None
) -> DeformModel:
    """A plain discrete elastic rod (no residual network) for a rope known only by its length and
    mass (:func:`deform.config.generic_rod`): tracking a rope that has no trained model starts here.

    Args:
        length_m: length [m].
        mass_kg: mass [kg].
        n_vertices: vertices of the rod.
        prior: bending stiffness per linear density [N m^3/kg] (None: the default prior).

    Returns:
        The :class:`DeformModel`, in eval mode.
    """
    model = DeformModel(generic_rod(length_m, mass_kg, n_vertices, prior=prior), ModelOptions(residual=False))
    model.choose_bending_scheme()  # a short rope's stiffest mode can outrun the 10 ms step
    return model.eval()
