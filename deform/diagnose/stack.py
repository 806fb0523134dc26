"""Several simulators stepped as one batch: the candidate fits of a selection round, together.

A diagnosis fits many small models (a reference and, per candidate term, a descent from each of its
grid's best starts) on the same windows of the same recordings. A step of one 13-vertex rod on 12
windows is a few hundred small tensor operations whose cost is their count, not their size: on one
core, 8 such models in one batch of 96 rods cost 1.7x one model's step, not 8x. So the models of
one round are stepped together: one :class:`deform.model.DeformModel` whose parameters are per rod
(each model's bound expressions repeated over its windows), whose terms act on their own model's
rods only (:class:`PerModelTerms`), started and ended by each simulator's own
:meth:`Simulator.begin` / :meth:`Simulator.end` (its clamp, delay, roll).

Each model's loss, gradient, optimiser and clipping stay its own (:mod:`deform.diagnose.joint_fit`),
and the twist solve and the length projection iterate per model until that model's rods converge
(``groups``: they would otherwise go on until every rod of the batch does, moving a model by up to
its solver tolerance, 0.1 mm over 25 steps): each model's numbers are those it gets alone, to
rounding (1e-15 of a rollout). Even so the groups are chosen from the round's candidates alone
(:func:`groups_of`), never from the workers, so that a diagnosis gives the same numbers whatever
``--workers`` is. A model with a rest curvature (fitted or not zero) needs the iterative twist
solve where every other model takes the closed form (deform.rod.twist_solver): the stack puts the
others first and the solve gives each part its own method (``closed_form_groups``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from deform.diagnose.simulator import (
    CHECK_MARGIN,
    Simulator,
    backward_through_bound,
    check_windows,
    full_rollouts,
    per_recording_l1,
    window_l1,
)
from deform.model import DeformModel, VertexMajorState

# the most models stepped as one batch: per step a batch of 16 models x 12 windows costs about 2.5x
# one model's step on one core (deform.diagnose.stack docstring); past that the arithmetic, not the
# count of operations, sets the time and a larger group gains little
GROUP_MODELS = 16


def groups_of(sizes: Sequence[int], most: int = GROUP_MODELS) -> list[list[int]]:
    """Split items of ``sizes`` models each, in order, into the fewest groups of at most ``most``
    models that are about equal (an item larger than ``most`` is a group of its own).

    Args:
        sizes: models per item (a candidate's starts, 1 for a reference).
        most: models per group at most.

    Returns:
        Item indices per group.
    """
    total = sum(sizes)
    if total == 0:
        return []
    n_groups = max(1, math.ceil(total / most))
    target = total / n_groups
    groups: list[list[int]] = [[]]
    filled = 0
    for i, size in enumerate(sizes):
        if groups[-1] and (filled + size > most or filled >= target - 1e-9):
            groups.append([])
            filled = 0
        groups[-1].append(i)
        filled += size
    return groups


class PerModelTerms(nn.Module):
    """The terms of each stacked model acting on that model's rods only: rods ``k * width`` to
    ``(k + 1) * width`` of the batch belong to model ``k``. Batch-first, as
    :class:`deform.model.DeformModel` hands terms their inputs."""

    def __init__(self, terms: list[list[nn.Module]], width: int):
        super().__init__()
        rods = [slice(k * width, (k + 1) * width) for k in range(len(terms))]
        self.accelerating = [
            (sl, [t for t in ts if hasattr(t, "acceleration")]) for sl, ts in zip(rods, terms)
        ]
        self.accelerating = [(sl, ts) for sl, ts in self.accelerating if ts]
        self.weighing = [(sl, [t for t in ts if hasattr(t, "mass")]) for sl, ts in zip(rods, terms)]
        self.weighing = [(sl, ts) for sl, ts in self.weighing if ts]

    def acceleration(self, x: Tensor, v: Tensor, mass: Tensor, rest: Tensor) -> Tensor:
        out = torch.zeros_like(x)
        for sl, terms in self.accelerating:
            a = terms[0].acceleration(x[sl], v[sl], mass[sl], rest[sl])
            for t in terms[1:]:
                a = a + t.acceleration(x[sl], v[sl], mass[sl], rest[sl])
            out[sl] = a
        return out

    def mass(self, mass: Tensor) -> Tensor:
        if not self.weighing:
            return mass
        parts, done = [], 0
        for sl, terms in self.weighing:
            parts.append(mass[done : sl.start])
            m = mass[sl]
            for t in terms:
                m = t.mass(m)
            parts.append(m)
            done = sl.stop
        return torch.cat([*parts, mass[done:]], 0)


class Stack:
    """Simulators of one rod and layout (the same node count and frame period), stepped as one
    batch. Each keeps its own nominal parameters, terms and model step: a model stepped every
    ``r``-th tick of the finest one (its substeps a divisor of the finest's) keeps its state on the
    ticks between, and is stepped with its own step length on its own grips, as alone."""

    def __init__(self, sims: list[Simulator]):
        first = sims[0]
        frame = first.model.dt * first.substeps
        self.ticks = max(s.substeps for s in sims)  # model steps per frame of the finest model
        for s in sims[1:]:
            if (s.n, s.hidden) != (first.n, first.hidden) or not math.isclose(
                s.model.dt * s.substeps, frame, rel_tol=1e-12
            ):
                raise ValueError("stacked simulators must share nodes, hidden nodes and frame period")
        if any(self.ticks % s.substeps for s in sims):
            raise ValueError(
                f"stacked simulators' substeps {sorted({s.substeps for s in sims})} must divide the finest's"
            )
        # the models whose twist angles come in closed form first (see :meth:`_bind`); the caller's
        # order is given back by :meth:`rollout`
        closed = [_closed_form(s._exprs()["wbar"]) for s in sims]
        self._order = sorted(range(len(sims)), key=lambda k: not closed[k])
        self.sims = [sims[k] for k in self._order]
        finest = next(s for s in self.sims if s.substeps == self.ticks)
        self.model = DeformModel(finest.model.cfg, finest.model.options)
        self.model.graph_params_per_rollout = True
        self.model.fused_pieces = finest.model.fused_pieces
        self._width = None
        self._closed_form_groups = 0

    def _bind(self, width: int) -> dict[str, Tensor]:
        """Every model's bound expressions, repeated over its ``width`` rods, copied into the batch
        model's per-rod parameters; -> the stacked expressions (for :meth:`backward`)."""
        exprs = [s.sync() for s in self.sims]
        # the leading models without a rest curvature (none learnt) take the closed-form twist
        # angles, as each does alone; the others the iterative solve
        closed = [_closed_form(e["wbar"]) for e in exprs] + [False]
        self._closed_form_groups = closed.index(False)
        stacked = {}
        for k in exprs[0]:
            per = [e[k] for e in exprs]
            stacked[k] = torch.cat([p.unsqueeze(-1).expand(*p.shape, width) for p in per], -1)
        if width != self._width:
            for k, e in stacked.items():
                setattr(self.model, k, nn.Parameter(torch.empty_like(e, dtype=getattr(self.model, k).dtype)))
            self.model.extensions = nn.ModuleList(
                [PerModelTerms([[t for t in s.model.extensions] for s in self.sims], width)]
            )
            self._width = width
        with torch.no_grad():
            for k, e in stacked.items():
                getattr(self.model, k).copy_(e.detach())
            for k in ("extra_mass_raw", "log_drag"):  # what every simulator's sync set, unbound
                getattr(self.model, k).copy_(getattr(self.sims[0].model, k))
                getattr(self.model, k).requires_grad_(False)
        for k, e in stacked.items():
            getattr(self.model, k).requires_grad_(e.requires_grad)
        return stacked

    def rollout(
        self,
        frames: Tensor | list[Tensor],
        steps: int,
        margin: int = 0,
        create_graph: bool = False,
        d1: Tensor | list | None = None,
        origin: Tensor | list | None = None,
    ) -> tuple[list[Tensor], dict[str, Tensor]]:
        """Every simulator's :meth:`Simulator.rollout` of the same windows, or of its own: ``frames``,
        ``d1`` and ``origin`` a list with one per simulator (of equal shapes).

        Returns:
            ``(predictions, stacked expressions)``: a (B, steps, n_markers, 3) per simulator, and
            what :meth:`backward` takes.
        """
        own = isinstance(frames, list)

        def mine(value, k: int):  # the caller's k-th model's windows
            return value[self._order[k]] if own else value

        width = mine(frames, 0).shape[0]
        stacked = self._bind(width)
        begun = [
            s.begin(mine(frames, k), steps, margin, mine(d1, k), mine(origin, k))
            for k, s in enumerate(self.sims)
        ]
        vm = VertexMajorState(
            *(torch.cat([getattr(b[0], f) for b in begun], -1) for f in ("x", "v", "d1", "theta", "rest"))
        )
        ticks = self.ticks
        markers, hidden = self.sims[0].markers, self.sims[0].hidden
        # per tick j of a frame, a model of r = ticks / substeps ticks per step is due when
        # (j + 1) % r == 0, on its step (frame * substeps + j // r): the grips of every tick at once
        every = [ticks // s.substeps for s in self.sims]
        held = torch.cat(
            [
                b[1].index_select(
                    0, torch.tensor([f * s.substeps + j // r for f in range(steps) for j in range(ticks)])
                )
                if r > 1
                else b[1]
                for b, s, r in zip(begun, self.sims, every)
            ],
            -1,
        )
        due = [
            None
            if all((j + 1) % r == 0 for r in every)
            else torch.tensor([(j + 1) % r == 0 for r in every]).repeat_interleave(width)
            for j in range(ticks)
        ]
        if len(set(every)) > 1:  # each rod its own step length
            self.model.dt = torch.cat([torch.full((width,), s.model.dt, dtype=vm.x.dtype) for s in self.sims])
        out = []
        for k in range(steps):
            for j in range(ticks):
                new = self.model.step_vertex_major(
                    vm,
                    held[k * ticks + j],
                    create_graph=create_graph,
                    groups=len(self.sims),
                    closed_form_groups=self._closed_form_groups,
                )
                if due[j] is not None:  # the models not due keep their state
                    new = VertexMajorState(
                        *(torch.where(due[j], a, b) for a, b in zip(_moving(new), _moving(vm))), vm.rest
                    )
                vm = new
            out.append(vm.x[markers] if hidden else vm.x)
        x = torch.stack(out)  # (steps, n_markers, 3, models * B)
        preds = [
            s.end(x[..., k * width : (k + 1) * width], mine(frames, k), steps, margin)
            for k, s in enumerate(self.sims)
        ]
        ordered: list[Tensor] = [None] * len(preds)  # type: ignore[list-item]
        for k, p in zip(self._order, preds):
            ordered[k] = p
        return ordered, stacked

    def backward(self, loss: Tensor, stacked: dict[str, Tensor]) -> None:
        """Backpropagate ``loss`` to every simulator's nominal and term parameters (as
        :meth:`Simulator.backward` does for one)."""
        backward_through_bound(self.model, loss, stacked)


def _moving(state: VertexMajorState) -> tuple[Tensor, ...]:
    """The fields of a state that a step changes (not the rest lengths)."""
    return state.x, state.v, state.d1, state.theta


def _closed_form(wbar: Tensor) -> bool:
    """Whether a model's bound rest curvature ``wbar`` lets its twist angles come in closed form:
    none, and none being learnt (deform.rod.twist_solver.solve_theta's own rule for one model)."""
    return not wbar.requires_grad and not bool(wbar.detach().any())


# models in one forward-only batch at most (grid points, check errors): no graph is kept, so the
# batch may be larger than a descent's group
FORWARD_MODELS = 24


def _chunks(items: list, size: int) -> list[list]:
    return [items[i : i + size] for i in range(0, len(items), size)]


@torch.no_grad()
def window_losses(sims: list[Simulator], windows, margin: int) -> list[float]:
    """Each simulator's open-loop L1 [m] over the same windows (from
    :func:`deform.diagnose.fitting.make_windows`), without gradients, stepped as one batch
    (:data:`FORWARD_MODELS` at a time); a diverged rollout scores infinity."""
    X, d1, origin = windows
    horizon = X.shape[1] - 2 - 2 * margin
    truth = X[:, margin + 2 : margin + 2 + horizon]
    out = []
    for part in _chunks(sims, FORWARD_MODELS):
        preds, _ = Stack(part).rollout(X, horizon, margin, d1=d1, origin=origin)
        out += [float(torch.nan_to_num((p - truth).abs().mean(), nan=math.inf)) for p in preds]
    return out


@torch.no_grad()
def check_errors(sims: list[Simulator], recordings) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per simulator ``(paper's open-loop L1, one-second window L1)`` per recording [m]: what
    :func:`~deform.diagnose.simulator.per_recording_l1` of :meth:`Simulator.predict` and
    :func:`~deform.diagnose.simulator.per_recording_window_l1` give each alone, stepped as one batch."""
    out = []
    for part in _chunks(sims, FORWARD_MODELS):
        stack = Stack(part)
        full = full_rollouts(lambda X, s, stack=stack: stack.rollout(X, s)[0], recordings)
        windows = np.zeros((len(part), len(recordings)))
        for r_i, r in enumerate(recordings):
            X, d1, origin, h = check_windows(r)
            preds, _ = stack.rollout(X, h, CHECK_MARGIN, d1=d1, origin=origin)
            windows[:, r_i] = [window_l1(p, X, CHECK_MARGIN) for p in preds]
        out += [(per_recording_l1(f, recordings), windows[k]) for k, f in enumerate(full)]
    return out
