"""A compiled inference step: ``torch.compile`` of :meth:`DeformModel.step` for run-time rollouts.

Why: at the sizes used here (13 vertices, up to a few hundred rods) a step is hundreds of tiny
tensor operations and its cost is interpreter and dispatch overhead, not arithmetic. Inductor fuses
the straight-line parts (geometry, forces, residual network, frame transport) into a few C++
kernels, about halving a step; the data-dependent loops (Newton on the twist angles, PBD sweeps)
stay eager between the compiled parts. Values agree with the eager step to rounding (tests).

Compilation costs tens of seconds per batch size and dtype (cached on disk by inductor across
processes), so batches are padded up to a few bucket sizes, and anything that fails to compile
(no C++ compiler, an unsupported build) falls back to the eager step with one warning. Training
never uses this path (it needs second-order autograd through the step).
"""

from __future__ import annotations

import logging
import threading

import torch
from torch import Tensor

from deform.aot import AheadOfTimeStep
from deform.model import DeformModel, RodState, VertexMajorState, overstretched
from deform.nn import precision
from deform.rod.layout import batch_major, vertex_major
from deform.step_graph import COMPILE_OPTIONS, branch_free_step, rod_at_rest

log = logging.getLogger("deform.compiled")

BUCKETS = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024)
# For a real-time loop (B = 1, cost per call matters, see CompiledStep): twist iterations and
# projection sweeps traced without host synchronisation. A plain step needs 2 and 1 (measured on the
# recordings); harder steps (the material frame of a curved rod turning by radians, 0.5 rad per
# Newton step; a rope pulled nearly taut) need more. Converged rods are masked but the iterations
# still run under torch.compile (the ahead-of-time step exits its loops once every rod converged,
# see deform.rod.convergence.masked_loop), so the rare harder steps are redone eagerly instead.
# Why (6, 3): no step of DLO1's eval recordings needs more; in the service benchmark neither it nor
# (12, 6) redid a step in 3000 ticks. (4, 2) redid 123 and put tick p99 at 5.8 ms.
LOOP_BRANCH_FREE = (6, 3)
PREDICT_BRANCH_FREE = (2, 2)  # the predict rollout's fast graph (see RolloutStep)
# the rollout's second try for the rods its fast graph left unconverged: the checked solvers' own
# limits (30 Newton iterations, 20 sweeps) as one graph, in groups of this many rods (one
# ahead-of-time package; its loops exit once every rod converged). The loop's (6, 3) left most such
# rods unconverged: they are rods pulled nearly taut, whose projection needs 5-20 sweeps.
RESCUE_BRANCH_FREE = (30, 20)
RESCUE_BATCH = 8


def bucket_size(batch: int, buckets: tuple[int, ...] = BUCKETS) -> int:
    """Smallest bucket that holds ``batch`` rods (batches above the largest bucket are not padded).

    Args:
        batch: rods to step.
        buckets: the compiled batch sizes, ascending.

    Returns:
        The bucket (a compiled batch size) to pad to, or ``batch`` above the largest.
    """
    for b in buckets:
        if batch <= b:
            return b
    return batch


def _pad(t: Tensor, size: int) -> Tensor:
    """Padded to ``size`` rods and contiguous (compiled code is specialised on strides too)."""
    if t.shape[0] == size:
        return t.contiguous()
    return torch.cat([t, t[:1].expand(size - t.shape[0], *t.shape[1:])], dim=0)


def _pad_last(t: Tensor, size: int) -> Tensor:
    """:func:`_pad` along the last axis (vertex-major arrays, the batch last)."""
    if t.shape[-1] == size:
        return t.contiguous()
    return torch.cat([t, t[..., :1].expand(*t.shape[:-1], size - t.shape[-1])], dim=-1)


def _with_rods(state, rods: Tensor, part):
    """A copy of ``state`` whose rods ``rods`` are those of ``part`` (rest lengths kept): both
    :class:`RodState` (rods the first axis) or both :class:`VertexMajorState` (rods the last)."""
    at = (rods,) if isinstance(state, RodState) else (..., rods)
    out = type(state)(*(t.clone() for t in (state.x, state.v, state.d1, state.theta, state.rest)))
    for t, r in zip((out.x, out.v, out.d1, out.theta), (part.x, part.v, part.d1, part.theta)):
        t[at] = r
    return out


class CompiledStep:
    """Callable like ``model.step(state, grip_next)`` (inference only, no gradients).

    >>> step = CompiledStep(model)          # compiles lazily, per bucket size and dtype
    >>> state = step(state, grip_next)

    ``branch_free=None`` (batches, e.g. predict): the step keeps its convergence-checked loops,
    each iteration a graph of its own. ``branch_free=(twist, sweeps)`` (a real-time loop, B = 1):
    the whole step is one graph with that many masked iterations, which cuts the per-call cost
    about 3x; rods it leaves unconverged (by the solvers' own per-rod flags) are stepped again
    eagerly. ``network_dtype``: the residual network's arithmetic in every path from
    :data:`deform.nn.precision.BFLOAT16_MIN_BATCH` rods per step on (None, and below that:
    float32; :mod:`deform.nn.precision`).
    ``compile_fallback=False``: where the ahead-of-time step cannot be had, the eager step instead
    of torch.compile (for a graph too large to compile unrolled, see :data:`RESCUE_BRANCH_FREE`).
    ``buckets``: the batch sizes compiled, a batch padded to the smallest that holds it.
    """

    def __init__(
        self,
        model: DeformModel,
        enabled: bool = True,
        branch_free: tuple[int, int] | None = None,
        ahead_of_time: bool = False,
        network_dtype: torch.dtype | None = None,
        compile_fallback: bool = True,
        buckets: tuple[int, ...] = BUCKETS,
    ):
        self.model = model
        self.buckets = buckets
        self.network_dtype = network_dtype
        self.compile_fallback = compile_fallback
        self.enabled = enabled
        self.branch_free = branch_free
        # the branch-free step as an AOTInductor package per (bucket, dtype) (deform.aot: the same
        # values, without dynamo's per-call entry cost); torch.compile if it cannot be built
        self.ahead_of_time = ahead_of_time and branch_free is not None
        self._aot: dict = {}
        self._compiled = None
        self._failed = False
        self.redone = 0  # rods whose compiled step did not converge and were stepped eagerly
        self._lock = threading.Lock()
        # the bucket sizes times two dtypes, plus the residual network's own graphs
        torch._dynamo.config.cache_size_limit = max(torch._dynamo.config.cache_size_limit, 64)

    @property
    def active(self) -> bool:
        """True while the compiled path is in use (False after a fallback to eager)."""
        return self.enabled and not self._failed

    def _one_graph(self) -> bool:
        """Whether the step is the one-graph step (``branch_free``), which runs vertex-major: its
        inputs are converted before the call, outside the graph."""
        return self.branch_free is not None

    def _checked_step(self, state, grip_next: Tensor | None) -> tuple:
        """With ``branch_free``: the step with fixed iteration counts and which rods it left
        unconverged by the solvers' own flags, one graph (vertex-major in and out, see
        :meth:`_one_graph`). Without: the step with its checked loops (a graph per iteration)."""
        if self.branch_free is None:
            return self.eager(state, grip_next), None
        return branch_free_step(
            self.model, state, grip_next, self.branch_free, self._network(state.x.shape[0])
        )

    def eager(self, state: RodState, grip_next: Tensor | None) -> RodState:
        """The model's own step with its checked loops (and this step's network precision)."""
        return self.model.step(state, grip_next, network_dtype=self._network(state.x.shape[0]))

    def _network(self, batch: int) -> torch.dtype | None:
        """The residual network's dtype for a step of ``batch`` rods (:func:`deform.nn.precision.for_batch`)."""
        return precision.for_batch(self.network_dtype, batch)

    def _step_fn(self):
        if self._compiled is None:
            self._compiled = torch.compile(self._checked_step, dynamic=False, options=COMPILE_OPTIONS)
        return self._compiled

    def _aot_fn(self, size: int, dtype: torch.dtype):
        """The ahead-of-time step for this bucket (built on first use), or None."""
        if not self.ahead_of_time:
            return None
        fn = self._aot.get((size, dtype))
        if fn is None:
            try:
                fn = self._aot[(size, dtype)] = AheadOfTimeStep(
                    self.model, self.branch_free, size, dtype, self._network(size)
                )
            except Exception as exc:
                self.ahead_of_time = False
                log.warning(
                    "ahead-of-time step unavailable (%s: %s); using %s",
                    type(exc).__name__,
                    exc,
                    "torch.compile" if self.compile_fallback else "the eager step",
                )
        return fn

    def attempt(self, state: RodState, grip_next: Tensor | None) -> tuple[RodState, Tensor | None]:
        """The compiled step alone: ``(new state, unconverged)``, ``unconverged`` a (B,) bool tensor
        with ``branch_free`` (rods outside the solver tolerances, see ``model.unconverged``), else
        None. Eager (and None) when compilation is off or failed, or with gradients."""
        if self._one_graph():  # vertex-major: converted here, outside the graph (deform.rod.layout)
            grip = None if grip_next is None else vertex_major(grip_next, 2)
            out, unconverged = self.attempt_vertex_major(state.vertex_major(), grip)
            return out.batch_major(), unconverged
        if not self.active or (torch.is_grad_enabled() and state.x.requires_grad):
            return self.eager(state, grip_next), None
        batch = state.x.shape[0]
        size = bucket_size(batch, self.buckets)
        padded = RodState(*(_pad(t, size) for t in (state.x, state.v, state.d1, state.theta, state.rest)))
        grip = None if grip_next is None else _pad(grip_next, size)
        ran = self._run(padded, grip, size, state.x.dtype)
        if ran is None:
            with torch.no_grad():
                return self.eager(state, grip_next), None
        out, unconverged = ran
        if size != batch:
            out = RodState(*(t[:batch] for t in (out.x, out.v, out.d1, out.theta, out.rest)))
        return out, None if unconverged is None else unconverged[:batch]

    def attempt_vertex_major(
        self, state: VertexMajorState, grip_next: Tensor | None
    ) -> tuple[VertexMajorState, Tensor | None]:
        """:meth:`attempt` of the one-graph step on a vertex-major state and grip (4, 3, B), with no
        conversion on the way: what a rollout calls step after step (converting 1024 rods to and
        from the batch-first layout took 0.5 ms a step, a fifth of the step)."""
        if not self.active or (torch.is_grad_enabled() and state.x.requires_grad):
            return self._eager_vertex_major(state, grip_next), None
        batch = state.x.shape[-1]
        size = bucket_size(batch, self.buckets)
        padded = VertexMajorState(
            *(_pad_last(t, size) for t in (state.x, state.v, state.d1, state.theta, state.rest))
        )
        grip = None if grip_next is None else _pad_last(grip_next, size)
        ran = self._run(padded, grip, size, state.x.dtype)
        if ran is None:
            return self._eager_vertex_major(state, grip_next), None
        out, unconverged = ran
        if size != batch:
            out = out.index(slice(0, batch))
        return out, None if unconverged is None else unconverged[:batch]

    def _eager_vertex_major(self, state: VertexMajorState, grip_next: Tensor | None) -> VertexMajorState:
        grip = None if grip_next is None else batch_major(grip_next, state.x.shape[-1:])
        with torch.no_grad():
            return self.eager(state.batch_major(), grip).vertex_major()

    def _run(self, padded, grip: Tensor | None, size: int, dtype: torch.dtype):
        """The compiled step on a padded batch: ahead of time if it can be had, else torch.compile;
        None when compilation failed (the caller steps eagerly; later calls too)."""
        try:
            with torch.no_grad(), self._lock:
                fn = self._aot_fn(size, dtype) if grip is not None else None
                if fn is not None:
                    try:
                        return fn(padded, grip)
                    except Exception as exc:
                        # torch.compile step of the same graph is still good, so only this path goes
                        self.ahead_of_time, fn = False, None
                        self._aot.clear()
                        log.warning(
                            "ahead-of-time step failed (%s: %s); using torch.compile", type(exc).__name__, exc
                        )
                if not self.compile_fallback:
                    raise RuntimeError("no ahead-of-time step, and no torch.compile fallback")
                return self._step_fn()(padded, grip)
        except Exception as exc:
            self._failed = True
            log.warning("compiled step unavailable (%s: %s); using the eager step", type(exc).__name__, exc)
            return None

    def __call__(self, state: RodState, grip_next: Tensor | None) -> RodState:
        out, unconverged = self.attempt(state, grip_next)
        bad = [] if unconverged is None else unconverged.nonzero().squeeze(-1)
        if len(bad):  # rare (a sudden large motion): those rods again, with the eager checked loops
            with torch.no_grad():
                redo = self.eager(state.index(bad), None if grip_next is None else grip_next[bad])
            out = _with_rods(out, bad, redo)
            self.redone += len(bad)
        return out

    def warmup(self, batch_sizes=(1,), dtype: torch.dtype = torch.float64) -> bool:
        """Compile for these batch sizes now (a rod at rest, held at its ends). -> still active."""
        for b in batch_sizes:
            state, grip = rod_at_rest(self.model, b, dtype)
            for _ in range(2):  # the second call runs the warm-start branch of the twist solve
                state = self(state, grip)
        return self.active


class RolloutStep:
    """Compiled steps for batched rollouts (the service's predict): many rods, many steps.

    A step whose fixed iterations (``branch_free``, 2 Newton iterations and 2 projection sweeps)
    converge every rod costs one graph call, against a dozen for the convergence-checked loops
    (each iteration a graph and a host synchronisation). A step the fast graph leaves unconverged
    (a plan's first large gripper displacement, a fast-moving start, a plan pulling the rope nearly
    taut) is redone for the rods it left unconverged alone, the others keep the fast result. Those
    rods go through the rescue graph (the checked solvers' limits as one ahead-of-time graph, 8 rods
    a call, :data:`RESCUE_BRANCH_FREE`), or the checked eager loops without it. Why per rod: at
    planning scale (hundreds of plans) some plan misses at most steps, and redoing the whole batch
    then cost more than the fast graph itself (``benchmarks/predict_rollout.py --start sagging
    --plans 512``, one thread: 348 ms per rollout with the eager loops, 223 ms with the rescue
    graph; the whole-batch redo before, timed by a scratch script on that start: 601 ms). When most of the batch misses (every plan
    opening with a jump), the whole batch takes the checked step, and after ``max_misses`` such steps in a row the fast graph pauses
    for one step, then two, four, ... while it keeps missing, so the wasted attempts grow with the
    logarithm of the rollout's length, and a rollout whose hard part passes returns to the fast
    graph. Every step is either verified converged or checked: each rod
    stays within the solver tolerances, except a rod whose grippers are farther apart than it is
    long at that step (:func:`deform.model.overstretched`): no shape meets its lengths, no number of
    sweeps converges, so it is not redone (the service's predict flags such plans in its reply).

    Why (2, 2): ``benchmarks/predict_rollout.py`` (64 random plans of 100 steps from 42 recorded
    DLO1 states, one run): with one sweep the fast graph missed in 18 of the 42 rollouts (median
    90.7 ms, p90 141 ms), with two in 3 (93.5 ms, 99 ms), all three starts where some plan pulls the
    grippers nearly or fully as far apart as the rod is long. A third Newton iteration only costs.

    ``network_dtype``: the residual network's arithmetic in every step of the rollout (None:
    float32; bfloat16 where it is native, :mod:`deform.nn.precision`).
    """

    def __init__(
        self,
        model: DeformModel,
        enabled: bool = True,
        branch_free: tuple[int, int] = PREDICT_BRANCH_FREE,
        max_misses: int = 3,
        ahead_of_time: bool = False,
        compile_checked: bool = True,
        network_dtype: torch.dtype | None = None,
    ):
        self.model = model
        self.fast = CompiledStep(
            model, enabled, branch_free=branch_free, ahead_of_time=ahead_of_time, network_dtype=network_dtype
        )
        # the checked step only redoes the rare steps the fast graph leaves unconverged: eager, it
        # costs no compilation at start-up (its graphs take dynamo 10-20 s even from a warm cache)
        self.checked = CompiledStep(model, enabled and compile_checked, network_dtype=network_dtype)
        # ahead of time only: unrolled under torch.compile its 50 iterations would compile for
        # minutes; one package, every group of rods padded to its size
        self.rescue = CompiledStep(
            model,
            enabled and ahead_of_time,
            branch_free=RESCUE_BRANCH_FREE,
            ahead_of_time=True,
            network_dtype=network_dtype,
            compile_fallback=False,
            buckets=(RESCUE_BATCH,),
        )
        self.max_misses = max_misses
        # False while the rescue graph is deferred (warmup(rescue=False)): its rods go to the eager
        # loops meanwhile, so a step never waits for a package build
        self.rescue_ready = True
        self.redone = 0  # rod-steps the fast graph left unconverged, stepped again by the checked loops
        self.paused = 0  # pauses of the fast graph after ``max_misses`` mostly-missed steps in a row

    @property
    def active(self) -> bool:
        return self.fast.active and (self.checked.active or not self.checked.enabled)

    def warmup(self, batch_sizes=(1,), dtype: torch.dtype = torch.float64, rescue: bool = True) -> bool:
        """Compile (or load) the steps for these batch sizes now. -> the compiled steps are in use
        (the fast graph, and the checked one where it is compiled).

        ``rescue=False`` defers the rescue graph (:meth:`warmup_rescue` later): on a cold start its
        package is a build of its own (about 25 s), which another process can make meanwhile."""
        fast = self.fast.warmup(batch_sizes, dtype)
        if rescue:
            self.warmup_rescue(dtype)
        else:
            self.rescue_ready = False
        return fast & (self.checked.warmup(batch_sizes, dtype) if self.checked.enabled else True)

    def warmup_rescue(self, dtype: torch.dtype = torch.float64) -> None:
        """Build or load the rescue graph now and use it from the next step on."""
        if self.rescue.active:  # (inactive: the rods are redone eagerly, nothing to warm up)
            self.rescue.warmup((RESCUE_BATCH,), dtype)
        self.rescue_ready = True

    def rollout(self, state: RodState, grips: Tensor) -> Tensor:
        """Positions (B, T, n, 3) for grips (B, T, 4, 3). The state is carried vertex-major from
        step to step (the fast graph's layout), converted only for the rare redone rods."""
        n_steps = grips.shape[1]
        vm = state.vertex_major()
        grips_vm = grips.permute(1, 2, 3, 0).contiguous()  # (T, 4, 3, B): each step's grip contiguous
        out = torch.empty(n_steps, *vm.x.shape, dtype=state.x.dtype)
        misses, retry_at = 0, 0  # mostly-missed steps in a row; the next step the fast graph is tried at
        with torch.no_grad():
            # an overstretched rod cannot converge: not a miss (rest lengths do not change in a
            # rollout, so all steps at once: one tensor operation instead of one per step)
            reachable = ~overstretched(grips, state.rest.unsqueeze(-2))  # (B, T)
            for k in range(n_steps):
                new = None
                if k >= retry_at:
                    new, unconverged = self.fast.attempt_vertex_major(vm, grips_vm[k])
                    bad = [] if unconverged is None else (unconverged & reachable[:, k]).nonzero().squeeze(-1)
                    # most of the fast result would be thrown away (and more rods than one rescue
                    # call takes, which costs less than the whole batch's checked step)
                    few = self._rescues() and len(bad) <= RESCUE_BATCH
                    if 2 * len(bad) > len(reachable) and not few:
                        new, misses = None, misses + 1
                        self.redone += len(reachable)
                        if misses >= self.max_misses:  # pause 1, 2, 4, ... steps
                            retry_at = k + 1 + 2 ** (misses - self.max_misses)
                            self.paused += 1
                    else:
                        misses = 0
                        if len(bad):
                            new = self._redo(vm, grips[:, k], new, bad)
                if new is None:
                    new = self.checked(vm.batch_major(), grips[:, k]).vertex_major()
                vm = new
                out[k] = vm.x
        return out.permute(3, 0, 1, 2)

    def _rescues(self) -> bool:
        """Whether unconverged rods go through the rescue graph (else the checked eager loops)."""
        return self.rescue.active and self.rescue_ready

    def _redo(
        self, state: VertexMajorState, grip: Tensor, new: VertexMajorState, bad: Tensor
    ) -> VertexMajorState:
        """``new`` with the rods ``bad`` stepped again from ``state`` (both vertex-major; ``grip``
        (B, 4, 3)): by the rescue graph (the
        checked solvers' limits as one graph, :data:`RESCUE_BATCH` rods a call) and the few it
        leaves unconverged by the checked eager loops, or by those alone without the rescue graph.
        Why the rescue graph: an eager step of a few rods cost about 1.3 ms whatever their number
        (interpreter-bound), two thirds of the fast graph's step of 512 rods; a rescue call 0.5 ms.
        Not the checked compiled step: a subset size warm-up did not see would be compiled in the
        middle of a request."""
        redo = state.index(bad).batch_major()
        if not self._rescues():
            part = self.checked.eager(redo, grip[bad])
        else:  # the rescue step redoes what its graph leaves unconverged with the same eager loops
            rods = torch.arange(len(bad))
            groups = [self.rescue(redo.index(g), grip[bad[g]]) for g in rods.split(RESCUE_BATCH)]
            part = RodState(
                *(torch.cat(ts) for ts in zip(*((o.x, o.v, o.d1, o.theta, o.rest) for o in groups)))
            )
        self.redone += len(bad)
        return _with_rods(new, bad, part.vertex_major())


def rollout(step: RolloutStep | CompiledStep | DeformModel, state: RodState, grips: Tensor) -> Tensor:
    """Open-loop positions (B, T, n, 3) for gripper inputs (B, T, 4, 3), without gradients.

    Args:
        step: a :class:`RolloutStep`, a :class:`CompiledStep` or the model itself.
        state: the :class:`deform.model.RodState` of B rods to start from.
        grips: (B, T, 4, 3) gripped vertices per step [m].

    Returns:
        (B, T, n, 3) positions [m].
    """
    if isinstance(step, RolloutStep):
        return step.rollout(state, grips)
    fn = step if isinstance(step, CompiledStep) else step.step
    out = torch.empty(grips.shape[0], grips.shape[1], state.x.shape[1], 3, dtype=state.x.dtype)
    with torch.no_grad():
        for k in range(grips.shape[1]):
            state = fn(state, grips[:, k])
            out[:, k] = state.x
    return out
