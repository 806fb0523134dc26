"""The plain DER model (DeformModel without residual) with a few nominal parameters plus terms.

DeformModel identifies per-vertex parameters; a diagnosis needs few, interpretable ones. So the
model's parameters are *bound*: before each rollout they are set to expressions of the nominal
parameters (one bending and one twisting stiffness, a linear damping) and of the terms; after the
backward pass their gradients are chained back to those expressions.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn

from deform.config import RodConfig
from deform.diagnose.spec import RodSpec
from deform.evaluate import batches_by_horizon, paper_l1
from deform.io.recordings import arclength_of  # noqa: F401  (part of the simulator's API)
from deform.model import DeformModel, ModelOptions, VertexMajorState, gripped_indices
from deform.rod import geometry as G
from deform.rod.layout import batch_major, vertex_major
from deform.terms.library import Term

NEGLIGIBLE_MASS_RAW = -12.0  # softplus(-12) g: no marker mass in the plain model
NEGLIGIBLE_LOG_DRAG = math.log(1e-7)


# The most linear velocity damping the nominal model may hold [1/s]: what a nominal fit gives when
# nothing but a rope's own material damping (and the model's discretisation) dissipates. A damping of
# absolute velocity is, physically, an external drag: beyond this level the nominal damping would
# absorb air drag, contact friction or strong internal damping (measured: 1.8-2.1 /s with PyElastica's
# drag against 0.15 /s on the paired controls; 5.1-5.3 /s against 0.7 /s on another simulator's stiff
# rope) and leave no candidate anything to explain, so the nominal fit is bounded here and what is
# left must be named. 2x the largest free fit on 11 controls, PyElastica's light and stiff rods and
# this project's own planted controls (`python benchmarks/diagnose_planted.py --calibrate-damping`:
# 0.13-0.16 and 0.32-0.52 /s), never on the cases a benchmark scores. Known limit: a coarse model of
# a much finer, violently moved rod needs numerical damping of its own (an 8-vertex model of a
# 15-node truth at 0.3 m/s per frame wanted 2.7 /s on a control), which the bound then withholds.
MATERIAL_DAMPING_LEVEL = 1.03
MATERIAL_DAMPING_MAX = MATERIAL_DAMPING_LEVEL  # the nominal fit's bound
CLAMP_MAX_M = 0.05  # the longest clamp past a gripped marker the nominal fit considers
CLAMP_UNIT_M = 0.1  # the clamp parameter's unit: Adam's nominal step (0.03) then moves it 3 mm
# The longest model step [s]. A longer frame period is stepped in equal substeps with the grippers
# interpolated linearly between frames. Why: the step's bending forces are explicit; seen at 50 Hz,
# one 20 ms step per frame left the tool's own rod's 100 Hz motion by 1.2 cm, two 10 ms substeps
# within 1 mm (tests/deform/diagnose/test_frame_rate.py). 10 ms is the DEFORM dataset's frame
# period, the one the tool was calibrated at (``diagnose`` resamples recordings to it anyway,
# deform.diagnose.resample; this keeps a Simulator built for another period sound).
MAX_STEP_S = 0.01


def clamp_bound(spec: RodSpec) -> float:
    """The longest clamp [m] a rod's model takes: it ends before the next marker, at most half the
    mean marker spacing (and at most CLAMP_MAX_M)."""
    return min(CLAMP_MAX_M, 0.5 * spec.length_m / (spec.n_vertices - 1))


class Nominal(nn.Module):
    """Plain DER: uniform bending EI and twisting GJ [N m^2], linear velocity damping [1/s] (at most
    ``damping_max`` when fitted: see MATERIAL_DAMPING_MAX), and the clamp length [m] past the
    gripped markers where the free rope starts (see :func:`clamped`)."""

    def __init__(
        self,
        ei: float = 1e-3,
        gj: float = 7e-4,
        damping: float = 0.5,
        damping_max: float = MATERIAL_DAMPING_MAX,
        clamp_m: float = 0.0,
    ):
        super().__init__()
        self.damping_max = damping_max
        self.log_ei = nn.Parameter(torch.tensor(math.log(ei), dtype=torch.float64))
        self.log_gj = nn.Parameter(torch.tensor(math.log(gj), dtype=torch.float64))
        self.log_damping = nn.Parameter(torch.tensor(math.log(damping), dtype=torch.float64))
        self.clamp_dm = nn.Parameter(torch.tensor(clamp_m / CLAMP_UNIT_M, dtype=torch.float64))

    @torch.no_grad()
    def params(self) -> dict[str, float]:
        return {
            "bend_stiffness_Nm2": float(self.log_ei.exp()),
            "twist_stiffness_Nm2": float(self.log_gj.exp()),
            "damping_1_per_s": float(self.log_damping.exp()),
            "clamp_m": float(self.clamp_length()),
        }

    def clamp_(self, clamp_max_m: float) -> None:
        """Keep the parameters in their physical ranges, the clamp at most ``clamp_max_m`` [m] (the
        rod's :func:`clamp_bound`, which a :class:`Simulator` passes)."""
        with torch.no_grad():
            self.log_ei.clamp_(math.log(1e-6), math.log(0.3))
            self.log_gj.clamp_(math.log(1e-6), math.log(0.3))
            self.log_damping.clamp_(math.log(1e-3), math.log(self.damping_max))
            self.clamp_dm.clamp_(0.0, clamp_max_m / CLAMP_UNIT_M)

    def set_clamp(self, clamp_m: float, fitted: bool) -> None:
        """Start the clamp at ``clamp_m`` [m]; ``fitted``: the fit moves it, else it is held there."""
        with torch.no_grad():
            self.clamp_dm.fill_(clamp_m / CLAMP_UNIT_M)
        self.clamp_dm.requires_grad_(fitted)

    def clamp_length(self) -> Tensor:
        """The clamp past the gripped markers [m] (differentiable)."""
        return self.clamp_dm * CLAMP_UNIT_M

    def at_damping_bound(self) -> bool:
        """The fit wants more velocity damping than a rope's material damping gives."""
        return float(self.log_damping.detach().exp()) >= 0.98 * self.damping_max


def marker_nodes(n_markers: int, hidden: int) -> list[int]:
    """Node ids of the markers on a rod with ``hidden`` extra nodes in every free marker interval
    (none in the two gripped end edges, which the grippers hold straight).

    Args:
        n_markers: markers.
        hidden: extra nodes per free interval.

    Returns:
        The node index of each marker.
    """
    return (
        [0] + [1 + (hidden + 1) * k for k in range(n_markers - 2)] + [1 + (hidden + 1) * (n_markers - 3) + 1]
    )


def refine_markers(x: Tensor, hidden: int) -> Tensor:
    """(..., n, 3) marker positions -> (..., N, 3) nodes, ``hidden`` nodes per free interval on a
    cubic Hermite curve in chord length (a smooth rod's shape between its markers, where a straight
    chord would start every window with kinks at the markers). Tangents at the markers are the
    three-point derivative for uneven spacing, ``(h_j d_{j-1} + h_{j-1} d_j) / (h_{j-1} + h_j)`` with
    ``d_j`` the slope of interval ``j``: exact on a parabola, so the short gripped end edges do not
    bend the first and last intervals as the plain Catmull-Rom secant would.

    Args:
        x: (..., n, 3) markers.
        hidden: nodes per free interval.

    Returns:
        (..., N, 3) nodes.
    """
    if hidden == 0:
        return x
    n = x.shape[-2]
    h = (x[..., 1:, :] - x[..., :-1, :]).norm(dim=-1, keepdim=True).clamp_min(1e-9)  # (..., n-1, 1)
    d = (x[..., 1:, :] - x[..., :-1, :]) / h  # slopes of the intervals
    tangent = (h[..., 1:, :] * d[..., :-1, :] + h[..., :-1, :] * d[..., 1:, :]) / (
        h[..., 1:, :] + h[..., :-1, :]
    )
    parts = [x[..., :2, :]]
    for j in range(1, n - 2):
        p0, p1, m0, m1, hj = (
            x[..., j, :],
            x[..., j + 1, :],
            tangent[..., j - 1, :],
            tangent[..., j, :],
            h[..., j, :],
        )
        for k in range(1, hidden + 1):
            t = k / (hidden + 1)
            h00, h10, h01, h11 = (
                2 * t**3 - 3 * t**2 + 1,
                t**3 - 2 * t**2 + t,
                -2 * t**3 + 3 * t**2,
                t**3 - t**2,
            )
            parts.append((h00 * p0 + h10 * hj * m0 + h01 * p1 + h11 * hj * m1).unsqueeze(-2))
        parts.append(x[..., j + 1 : j + 2, :])
    parts.append(x[..., n - 1 :, :])
    return torch.cat(parts, -2)


def between_markers(values: np.ndarray, hidden: int) -> np.ndarray:
    """(n, ...) values at the markers -> (N, ...), ``hidden`` values evenly (linearly) spaced in
    every free interval: node arc length, or a straight start for a finer simulated rod.

    Args:
        values: (n, ...) per marker.
        hidden: values per free interval.

    Returns:
        (N, ...).
    """
    values = np.asarray(values)
    if hidden == 0:
        return values
    out = [values[0], values[1]]
    for j in range(1, len(values) - 2):
        for k in range(1, hidden + 2):
            a = k / (hidden + 1)
            out.append((1 - a) * values[j] + a * values[j + 1])
    out.append(values[-1])
    return np.stack(out)


ROLL_ANGLES = 16  # rolls tried by Simulator.initial_roll (22.5 degrees apart, then refined)
ROLL_FRAMES = 20  # frames after the first two that a recording's roll is read from (0.2 s at 100 Hz)


def clamped(grip: Tensor, clamp: Tensor) -> Tensor:
    """Gripped vertices (..., 4, 3) with the inner two moved ``clamp`` [m] along the gripper's axis
    towards the free rope: where the rod leaves the gripper, not where its marker sits.

    Why: a gripper holds the rope past the marker it carries (the jaws' length); the rope leaves it
    straight along the axis of the gripped edge, so the free part is shorter and its ends stiffer
    than a model freeing the rope at the marker. Unseen in marker data, so a nominal parameter.

    Args:
        grip: (..., 4, 3) vertices 0, 1, n-2, n-1.
        clamp: scalar clamp length past the markers 1 and n-2 [m].

    Returns:
        (..., 4, 3).
    """
    a = torch.nn.functional.normalize(grip[..., 1, :] - grip[..., 0, :], dim=-1, eps=1e-12)
    b = torch.nn.functional.normalize(grip[..., 2, :] - grip[..., 3, :], dim=-1, eps=1e-12)
    c = clamp.to(grip.dtype)
    return torch.stack(
        [grip[..., 0, :], grip[..., 1, :] + c * a, grip[..., 2, :] + c * b, grip[..., 3, :]], -2
    )


def frame_substeps(dt: float, max_step_s: float = MAX_STEP_S) -> int:
    """Model steps per recorded frame of period ``dt`` [s]: the fewest that keep each at most
    ``max_step_s`` (with :data:`MAX_STEP_S`: 1 at 100 Hz and above; 2 at 50 Hz; 4 at 30 Hz).

    Args:
        dt: the recordings' frame period [s].
        max_step_s: the longest model step [s].

    Returns:
        Substeps per frame.
    """
    return max(1, math.ceil(dt / max_step_s - 1e-9))


def roll_directors(d1: Tensor, t: Tensor, roll: Tensor) -> Tensor:
    """Directors ``d1`` (B, m, 3) turned by ``roll`` (B,) [rad] about their unit tangents ``t``:
    the whole material frame rolled, twist unchanged (rotation about the tangent commutes with
    parallel transport)."""
    c, s = roll.cos()[:, None, None], roll.sin()[:, None, None]
    return c * d1 + s * torch.linalg.cross(t, d1, dim=-1)


def backward_through_bound(model: DeformModel, loss: Tensor, exprs: dict[str, Tensor]) -> None:
    """Backpropagate ``loss`` into ``model``'s bound parameters, then chain their gradients back to
    the expressions ``exprs`` they were copied from (:meth:`Simulator.sync`); the model's own
    gradients are cleared again."""
    model_params = {k: getattr(model, k) for k in exprs}
    for p in model_params.values():
        p.grad = None
    loss.backward()
    outs, grads = [], []
    for k, e in exprs.items():
        g = model_params[k].grad
        if g is not None and e.requires_grad:
            outs.append(e)
            grads.append(g.to(e.dtype))
    if outs:
        torch.autograd.backward(outs, grads)
    for p in model_params.values():
        p.grad = None


class Simulator:
    """A DeformModel driven by a :class:`Nominal` and a list of :class:`Term`.

    ``hidden``: unobserved nodes simulated in every free marker interval (0: nodes only at the
    markers), stepped at ``dt / (hidden + 1)``. Why: at marker resolution a mass on every marker is
    the same as a uniform mass factor, which the fitted stiffness absorbs; with mass between the
    markers the two differ. Terms are then built on the node arc length (:meth:`node_arclength`).
    ``substeps``: model steps per frame instead (a study of the step's own error).
    A frame period longer than ``max_step_s`` (default :data:`MAX_STEP_S`) is stepped in
    ``ceil(dt / max_step_s)`` substeps as well (:func:`frame_substeps`)."""

    def __init__(
        self,
        spec: RodSpec,
        nominal: Nominal,
        terms: list[Term] | None = None,
        hidden: int = 0,
        substeps: int | None = None,
        max_step_s: float = MAX_STEP_S,
    ):
        self.hidden = hidden
        self.substeps = substeps or (hidden + 1) * frame_substeps(spec.dt, max_step_s)
        self.n_markers = spec.n_vertices
        self.markers = marker_nodes(spec.n_vertices, hidden)
        n = self.markers[-1] + 1
        cfg = RodConfig(
            name=spec.name,
            length_m=spec.length_m,
            mass_kg=spec.mass_kg,
            n_vertices=n,
            dt=spec.dt / self.substeps,
            marker_mass_kg=1e-9,
            bend_stiffness=1e-3,
            twist_stiffness=7e-4,
        )
        self.model = DeformModel(cfg, ModelOptions(residual=False))
        self.model.graph_params_per_rollout = True  # every rollout here is backpropagated once
        self.model.fused_pieces = True  # many small descents: pieces compiled (deform.rod.fusion)
        self.n = n
        self.nominal = nominal
        self.clamp_max_m = clamp_bound(spec)
        self.clamp_()
        self.terms = list(terms or [])
        emap = (
            [0]
            + [j for j in range(1, spec.n_vertices - 2) for _ in range(hidden + 1)]
            + [spec.n_vertices - 2]
        )
        self._edge_of_node_edge = emap  # marker edge each node edge lies on
        for t in self.terms:
            if hasattr(t, "set_dt"):
                t.set_dt(cfg.dt)
            if hasattr(t, "set_markers"):
                t.set_markers(self.markers, n)
            if hasattr(t, "acceleration") or hasattr(t, "mass"):
                self.model.extensions.append(t)

    def clamp_(self) -> None:
        """Keep the nominal parameters in range, the clamp within this rod's bound."""
        self.nominal.clamp_(self.clamp_max_m)

    def node_arclength(self, marker_arclength: np.ndarray) -> np.ndarray:
        return between_markers(marker_arclength, self.hidden)

    def parameters(self) -> list[nn.Parameter]:
        out = list(self.nominal.parameters())
        for t in self.terms:
            out += list(t.parameters())
        return out

    def term_parameters(self) -> list[nn.Parameter]:
        return [p for t in self.terms for p in t.parameters()]

    def _exprs(self) -> dict[str, Tensor]:
        m = self.n - 2
        nom = self.nominal
        exprs = {
            "log_beta": nom.log_ei.expand(m),
            "log_gamma": nom.log_gj.expand(m),
            "wbar": torch.zeros(m, 2, 2, dtype=torch.float64),
            "log_damping": nom.log_damping,
        }
        for t in self.terms:
            exprs = t.bind(exprs)
        return exprs

    def sync(self) -> dict[str, Tensor]:
        """Copy the bound expressions into the model; returns them (for :meth:`backward`)."""
        exprs = self._exprs()
        with torch.no_grad():
            for k, e in exprs.items():
                getattr(self.model, k).copy_(e.detach().to(getattr(self.model, k).dtype))
            self.model.extra_mass_raw.fill_(NEGLIGIBLE_MASS_RAW)
            self.model.log_drag.fill_(NEGLIGIBLE_LOG_DRAG)
        # a model parameter takes part in the backward pass only when its expression has something to
        # fit: no work on gradients that :meth:`backward` would drop, and without a rest curvature
        # term the twist angles come in closed form (deform.rod.twist_solver.twist_minimiser)
        for k, p in self.model.named_parameters(recurse=False):  # its own: not the terms' (extensions)
            p.requires_grad_(k in exprs and exprs[k].requires_grad)
        return exprs

    def backward(self, loss: Tensor, exprs: dict[str, Tensor]) -> None:
        """Backpropagate ``loss`` to the nominal and term parameters through the bound model."""
        backward_through_bound(self.model, loss, exprs)

    def delay(self) -> Tensor | None:
        for t in self.terms:
            if hasattr(t, "delay_frames"):
                return t.delay_frames
        return None

    def rollout(
        self,
        frames: Tensor,
        steps: int,
        margin: int = 0,
        create_graph: bool = False,
        d1: Tensor | None = None,
        origin: Tensor | None = None,
    ) -> Tensor:
        """Open-loop prediction from ``frames[:, margin]`` and ``frames[:, margin+1]`` for ``steps``
        frames, grippers from the recorded frames (shifted by a delay term if any; linearly
        interpolated between frames for the substeps of hidden nodes or long frame periods).
        ``d1`` (B, n-1, 3): reference
        directors of the marker edges at ``frames[:, margin+1]`` (see :attr:`Recording.reference_frames`;
        default: a fresh space-parallel frame, right for a rollout from a recording's first frame).
        The gripped markers of the output are the recorded inputs, also under a delay term.
        ``origin`` (B, k, n, 3): the first frames of each window's recording (default, without
        ``d1``: the window's own first frames). With a term that needs the material frame's roll
        (``rolls_material_frame``), each window's directors are rolled by its recording's
        :meth:`initial_roll`.
        -> (B, steps, n_markers, 3)."""
        vm, held = self.begin(frames, steps, margin, d1, origin)
        sub = self.substeps
        out = []
        for k in range(steps):
            for j in range(sub):
                vm = self.model.step_vertex_major(vm, held[k * sub + j], create_graph=create_graph)
            out.append(vm.x[self.markers] if self.hidden else vm.x)
        return self.end(torch.stack(out), frames, steps, margin)

    def begin(
        self,
        frames: Tensor,
        steps: int,
        margin: int = 0,
        d1: Tensor | None = None,
        origin: Tensor | None = None,
    ) -> tuple[VertexMajorState, Tensor]:
        """What :meth:`rollout` steps from: the vertex-major state at ``frames[:, margin + 1]`` and
        the held vertices of every model step, vertex-major (steps * substeps, 4, 3, B). Apart from
        the stepping so that several simulators can be stepped as one batch
        (:mod:`deform.diagnose.stack`)."""
        idx = gripped_indices(self.n_markers)
        grips = frames[:, :, idx]
        tau = self.delay()
        T = frames.shape[1]

        def grips_at(times: list[float]) -> Tensor:
            """(B, len(times), 4, 3): the grips at fractional frames (shifted by a delay), linear
            between frames; all of a rollout's at once, as a step's own few operations cost as much
            as the arithmetic of all of them."""
            if tau is None and all(float(t).is_integer() for t in times):
                return grips[:, [int(t) for t in times]]
            t = frames.new_tensor(times)
            pos = (t - tau if tau is not None else t).clamp(0, T - 1)
            lo = pos.detach().floor().clamp(max=T - 2)
            a = (pos - lo)[None, :, None, None]
            i = lo.long()
            return (1 - a) * grips[:, i] + a * grips[:, i + 1]

        clamp = self.nominal.clamp_length()
        x0, x1 = frames[:, margin], frames[:, margin + 1]
        # the rod's gripped ends lag the recorded grips from the first frame on (delay), and its free
        # part starts where the clamp ends
        x0, x1 = x0.clone(), x1.clone()
        start = clamped(grips_at([margin, margin + 1]), clamp)
        x0[:, idx] = start[:, 0].to(x0.dtype)
        x1[:, idx] = start[:, 1].to(x1.dtype)
        state = self.model.initial_state(
            refine_markers(x0, self.hidden), refine_markers(x1, self.hidden), dt=self.model.dt * self.substeps
        )
        if d1 is None and origin is None:
            origin = frames[:, margin : margin + 2 + ROLL_FRAMES]
        rolls = any(getattr(t, "rolls_material_frame", False) for t in self.terms)
        batch = frames.shape[:1]
        # the recorded tangents at the start, vertex-major (m, 3, B) as the geometry takes them
        t_rec = G.normalize(G.edges(vertex_major(frames[:, margin + 1], 2)))
        if origin is not None and origin.shape[1] > 2 and rolls:
            if d1 is None:
                d1 = batch_major(G.space_parallel_frame(t_rec), batch)
            d1 = roll_directors(d1.to(t_rec.dtype), batch_major(t_rec, batch), self.initial_roll(origin))
        if d1 is not None:
            emap = self._edge_of_node_edge
            d1 = G.time_transport(
                vertex_major(d1, 2)[emap].to(state.d1.dtype),
                t_rec[emap].to(state.d1.dtype),
                G.normalize(G.edges(vertex_major(state.x, 2))),
            )
            d1 = batch_major(d1, batch)
            state = type(state)(x=state.x, v=state.v, d1=d1, theta=state.theta, rest=state.rest)
        sub = self.substeps
        held = clamped(
            grips_at([margin + 1 + k + j / sub for k in range(steps) for j in range(1, sub + 1)]), clamp
        )
        # stepped vertex-major (the layout the physics runs in), converted back once at the end
        return state.vertex_major(), vertex_major(held, 3)  # held: (steps * sub, 4, 3, B)

    def end(self, x: Tensor, frames: Tensor, steps: int, margin: int = 0) -> Tensor:
        """:meth:`rollout`'s output from the stepped markers ``x`` (steps, n_markers, 3, B), vertex-major.

        The gripped markers are the protocol's inputs, given at every step: with a delay the rod's
        ends lag them and with a clamp its nodes 1 and n-2 are the clamp's ends, but the prediction
        is not scored on where the inputs are.

        Returns:
            (B, steps, n_markers, 3).
        """
        x = batch_major(x, (frames.shape[0],))  # (B, steps, n_markers, 3)
        grips = frames[:, :, gripped_indices(self.n_markers)]
        recorded = grips[:, margin + 2 : margin + 2 + steps].to(x.dtype)
        return torch.cat([recorded[:, :, :2], x[:, :, 2:-2], recorded[:, :, 2:]], 2)

    @torch.no_grad()
    def initial_roll(self, origin: Tensor, n_angles: int = ROLL_ANGLES) -> Tensor:
        """Roll of the material frame about the tangents (from the space-parallel "up" frame, about
        every edge) that best predicts each recording's first frames: the open-loop L1 of the free
        markers over ``origin``'s frames after the first two, for ``n_angles`` rolls, refined by a
        parabola through the best three.

        Why: a gripper's roll about the rope is part of its pose, yet not in marker data, so the
        frame a rest curvature lives in is known only by convention; near a vertical end edge the
        "up" convention turns with the slightest tilt, and the same curvature points elsewhere in
        every recording. The recording's first 0.2 s say which roll holds it. From the first two
        frames alone (the roll that puts the first state closest to rest) the choice was
        noise-limited: 0.3 mm of marker noise is as large as one step of the roll's effect; over
        0.1 s it still missed on a light rope (PyElastica, docs/diagnose.md).

        Args:
            origin: (B, k, n, 3) the first frames of each window's recording (k >= 3).
            n_angles: rolls tried.

        Returns:
            (B,) roll [rad].
        """
        B, k, n, _ = origin.shape
        uniq, inverse = torch.unique(origin.reshape(B, -1), dim=0, return_inverse=True)
        U = uniq.reshape(-1, k, n, 3).to(torch.float64)
        step = 2 * math.pi / n_angles
        angles = torch.arange(n_angles, dtype=torch.float64) * step
        frames = U.repeat_interleave(n_angles, 0)
        t1 = G.normalize(G.edges(vertex_major(frames[:, 1], 2)))
        batch = frames.shape[:1]
        d1 = roll_directors(
            batch_major(G.space_parallel_frame(t1), batch), batch_major(t1, batch), angles.repeat(len(U))
        )
        pred = self.rollout(frames, k - 2, 0, d1=d1)  # directors given, no origin: not rolled again
        free = [j for j in range(n) if j not in set(gripped_indices(n))]
        err = (pred[:, :, free] - frames[:, 2:, free]).abs().mean((1, 2, 3)).reshape(len(U), n_angles)
        err = torch.nan_to_num(err, nan=math.inf)
        best = err.argmin(1)
        rows = torch.arange(len(U))
        lo, mid, hi = err[rows, (best - 1) % n_angles], err[rows, best], err[rows, (best + 1) % n_angles]
        curv = lo - 2 * mid + hi
        ok = torch.isfinite(curv) & (curv > 0)
        shift = torch.where(
            ok, 0.5 * (lo - hi) / torch.where(ok, curv, torch.ones_like(curv)), torch.zeros_like(curv)
        )
        return ((best.to(torch.float64) + shift.clamp(-0.5, 0.5)) * step)[inverse]

    def predict(self, recordings, steps: int | None = None) -> list[np.ndarray]:
        """Full open-loop predictions (paper's protocol) of recordings, batched by length."""
        self.sync()
        return full_rollouts(lambda X, s: [self.rollout(X, s)], recordings, steps)[0]


@torch.no_grad()
def full_rollouts(rollout, recordings, steps: int | None = None) -> list[list[np.ndarray]]:
    """Open loops over whole recordings from their first two frames, recordings of one length in
    one batch: ``rollout(X, steps)`` gives one (B, steps, n, 3) prediction per model (one for a
    :class:`Simulator`, several for a stack of them). -> per model, per recording, (S, n, 3)."""
    out: list[dict[int, np.ndarray]] = []
    for full, ids in batches_by_horizon(recordings, None).items():  # same length: one batch
        s = full if steps is None else min(steps, full)
        X = torch.tensor(np.stack([recordings[i].positions for i in ids]), dtype=torch.float64)
        for k, P in enumerate(rollout(X, s)):
            if k == len(out):
                out.append({})
            for j, i in enumerate(ids):
                out[k][i] = P[j].numpy()
    return [[o[i] for i in range(len(recordings))] for o in out]


def per_recording_l1(predictions: list[np.ndarray], recordings) -> np.ndarray:
    """Paper's metric per recording: mean |pred - truth| over steps, vertices and axes.

    Args:
        predictions: (S, n, 3) per recording.
        recordings: the recordings predicted.

    Returns:
        (R,) L1 [m].
    """
    return np.array(
        [paper_l1(p, r.positions[2 : 2 + len(p)], nan_as=1.0) for p, r in zip(predictions, recordings)]
    )


# The horizon of the check statistic that decides (docs/diagnose.md, "Scoring"): one second ahead.
CHECK_HORIZON = 100
CHECK_EVERY = 20  # frames between window starts
CHECK_MARGIN = 3  # frames kept before each window's start (a delay term's shifted inputs)


def per_recording_window_l1(
    sim: Simulator,
    recordings,
    horizon: int = CHECK_HORIZON,
    every: int = CHECK_EVERY,
    margin: int = CHECK_MARGIN,
) -> np.ndarray:
    """Mean open-loop L1 of ``horizon``-step predictions restarted every ``every`` frames, per
    recording: the prediction a fit is made for (short windows from transported frames), scored
    on held-out recordings. Why not only the full rollout: a 300-500 step open loop drifts, and
    small parameter changes move its error by several per cent, so on control datasets the full
    rollout's paired improvements spread twice as wide (sd 2.6 % against 1.4-1.7 %, PyElastica
    controls) and hide effects of that size.

    Args:
        sim: the simulator.
        recordings: held-out recordings, each ``positions`` (T, n, 3).
        horizon: steps per window (shortened to fit a short recording).
        every: frames between window starts.
        margin: frames kept before each window's start (a delay term's shifted inputs).

    Returns:
        (R,) L1 [m] (1.0 where a rollout diverged).
    """
    sim.sync()
    out = []
    with torch.no_grad():
        for r in recordings:
            X, d1, origin, h = check_windows(r, horizon, every, margin)
            pred = sim.rollout(X, h, margin, d1=d1, origin=origin)
            out.append(window_l1(pred, X, margin))
    return np.array(out)


def check_windows(
    recording, horizon: int = CHECK_HORIZON, every: int = CHECK_EVERY, margin: int = CHECK_MARGIN
):
    """The windows :func:`per_recording_window_l1` predicts on one recording: ``(X, d1, origin,
    steps)``, ``X`` (W, steps + 2 + 2 margin, n, 3) restarted every ``every`` frames, the reference
    directors at each start and the recording's first frames (where a roll is read)."""
    r = recording
    h = max(1, min(horizon, r.n_frames - 2 - 2 * margin))
    length = h + 2 + 2 * margin
    starts = list(range(0, r.n_frames - length + 1, every))
    X = torch.tensor(np.stack([r.positions[s : s + length] for s in starts]), dtype=torch.float64)
    frames = r.reference_frames
    d1 = torch.tensor(np.stack([frames[s + margin + 1] for s in starts]), dtype=torch.float64)
    origin = torch.tensor(r.positions[: 2 + ROLL_FRAMES], dtype=torch.float64)
    return X, d1, origin.expand(len(starts), -1, -1, -1), h


def window_l1(pred: Tensor, X: Tensor, margin: int) -> float:
    """Mean L1 [m] of window predictions ``pred`` (W, steps, n, 3) against ``X``; 1.0 where diverged."""
    err = (pred - X[:, margin + 2 : margin + 2 + pred.shape[1]]).abs().mean()
    return float(torch.nan_to_num(err, nan=1.0))
