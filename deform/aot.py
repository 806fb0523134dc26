"""The one-graph model step compiled ahead of time (AOTInductor): a shared library called from C++.

Why: a ``torch.compile`` step is entered through dynamo's guards, AOTAutograd's runtime wrappers
and a few Python frames on every call. For the predict rollout (64 rods, 100 calls per request) that
entry costs about a quarter of the step: the same graph exported with ``torch.export`` and compiled
by AOTInductor gives bit-identical values at 0.71x the time per step (scratch A/B at 64 rods,
2026-11-23) and 0.86x per predict rollout (``benchmarks/predict_rollout.py --settings 2,2 2,2:aot``). The price: the package is specialised on one
batch size and dtype, and the model's parameters are frozen into it. So packages are keyed on the
parameters' values (and on the source the step runs and the torch build) and cached on disk
(``$DEFORM_CACHE/aot``, default ``~/.cache/deform/aot``); a step whose model's parameters changed after
the package was made builds a new one rather than use stale weights.

Only the branch-free step (fixed twist iterations and projection sweeps, see
:class:`deform.compiled.CompiledStep`) is compiled this way: the convergence-checked step has
data-dependent loops that do not export into one graph.
"""

from __future__ import annotations

import ast
import fcntl
import functools
import hashlib
import logging
import os
import platform
import tempfile
import time
import warnings
from pathlib import Path

import torch
from torch import Tensor

from deform.model import DeformModel, VertexMajorState
from deform.rod.convergence import loops_when_exported
from deform.step_graph import COMPILE_OPTIONS, branch_free_step, rod_at_rest_vertex_major

log = logging.getLogger("deform.aot")

# torch's deprecations inside its own export and inductor code (torch 2.13), printed on every build
# (`make install` showed 21 of them for the five rods): nothing a user of this package can act on
for _internal in (
    r"`isinstance\(treespec, LeafSpec\)` is deprecated",
    r"`torch\._prims_common\.check` is deprecated",
):
    warnings.filterwarnings("ignore", message=_internal, category=FutureWarning)

_PACKAGE_SOURCE = Path(__file__).resolve().parent
# torch.compile's options for the same graph: its C++ wrapper is what AOTInductor always generates
AOT_OPTIONS = {k: v for k, v in COMPILE_OPTIONS.items() if k != "cpp_wrapper"}
# the solvers' iterations as while loops up to this many rods, unrolled above (exports_loops)
LOOPS_MAX_BATCH = 64


def exports_loops(batch: int) -> bool:
    """Whether the package for ``batch`` rods holds the solvers' iterations as while loops
    (:func:`deform.rod.convergence.masked_loop`) rather than unrolled.

    Why: as loops the package builds in 24.6 instead of 39.5 s for the loop step (1 rod; the cold
    start waits for it) and runs as fast at 1 and 64 rods (127 / 120 us and 385 / 399 us per step,
    loops / unrolled); at 1024 rods the loops cost 6-18 % per step (4.7-5.0 against 4.3-4.4 ms),
    because inductor's memory planning, which cannot plan across them, is off."""
    return batch <= LOOPS_MAX_BATCH


def cache_dir() -> Path:
    """Where compiled packages are kept: ``aot`` in ``$DEFORM_CACHE`` or ``~/.cache/deform``.

    Returns:
        The directory (not created here).
    """
    return Path(os.environ.get("DEFORM_CACHE") or Path.home() / ".cache" / "deform") / "aot"


def package_key(
    model: DeformModel,
    branch_free: tuple[int, int],
    batch: int,
    dtype: torch.dtype,
    network_dtype: torch.dtype | None = None,
) -> str:
    """Hash of everything the compiled code depends on: the model's values and configuration, the
    step's settings, the source the step runs (:func:`step_sources`), the torch build and CPU, and the thread count
    (``torch.get_num_threads()`` now: inductor writes it into the kernels, so a package built on
    one thread runs on one thread in a process that has two; a 1024-rod step ran at 220k instead
    of 370k rod-steps/s that way).

    Args:
        model: the model whose step is compiled.
        branch_free: (twist iterations, projection sweeps) without host synchronisation.
        batch: rods per step (the bucket).
        dtype: the state's dtype.
        network_dtype: the residual network's arithmetic (None: float32).

    Returns:
        A hex digest naming the package file.
    """
    h = hashlib.sha256()
    for part in (
        torch.__version__,
        platform.machine(),
        torch.backends.cpu.get_cpu_capability(),
        f"threads={torch.get_num_threads()}",
        repr(branch_free),
        str(batch),
        str(dtype),
        f"network={network_dtype}",
        repr(model.cfg),
        repr([type(e).__name__ for e in getattr(model, "extensions", [])]),
    ):
        h.update(part.encode())
    for name, t in sorted(model.state_dict().items()):
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    for src in step_sources(_PACKAGE_SOURCE):
        h.update(src.read_bytes())
    return h.hexdigest()[:32]


@functools.lru_cache(maxsize=8)
def step_sources(package: Path, start: str = __name__) -> tuple[Path, ...]:
    """The source files of ``package`` a compiled step can depend on: the modules ``start`` imports,
    directly or through others (imports inside functions count, and so does every enclosing
    package's ``__init__``), found by reading the sources, not by importing them.

    Why not every file of the package: an edit to the discrepancy tool, training or the command line
    would then make every prebuilt package stale, and the next service start would compile again.
    Found once per process (parsing them takes ~50 ms, and a service start keys several packages);
    :func:`package_key` still reads their bytes at every call.

    Args:
        package: the package's directory (``deform/``).
        start: the dotted module the closure starts from.

    Returns:
        The files, sorted.
    """
    name = package.name

    def file_of(module: str) -> Path | None:
        path = package.parent.joinpath(*module.split("."))
        for candidate in (path / "__init__.py", path.with_suffix(".py")):
            if candidate.is_file():
                return candidate
        return None

    def imported(module: str, path: Path) -> set[str]:
        here = module if path.name == "__init__.py" else module.rpartition(".")[0]
        out = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                out |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative: from .x import y
                    parts = here.split(".")[: len(here.split(".")) - node.level + 1]
                    base = ".".join(parts + ([node.module] if node.module else []))
                out |= {base} | {f"{base}.{a.name}" for a in node.names}  # a name may be a module
        return {m for m in out if m == name or m.startswith(name + ".")}

    found: dict[str, Path] = {}
    queue = [start]
    while queue:
        module = queue.pop()
        path = None if module in found else file_of(module)
        if path is None:
            continue
        found[module] = path
        parts = module.split(".")
        queue += [".".join(parts[:i]) for i in range(1, len(parts))]
        queue += sorted(imported(module, path))
    return tuple(sorted(set(found.values())))


class _BranchFreeStep(torch.nn.Module):
    """``model.step`` with fixed iterations on flat tensors, and the rods it left unconverged."""

    def __init__(
        self, model: DeformModel, branch_free: tuple[int, int], network_dtype: torch.dtype | None = None
    ):
        super().__init__()
        self.model, self.branch_free, self.network_dtype = model, branch_free, network_dtype

    def forward(self, x: Tensor, v: Tensor, d1: Tensor, theta: Tensor, rest: Tensor, grip: Tensor):
        new, unconverged = branch_free_step(
            self.model, VertexMajorState(x, v, d1, theta, rest), grip, self.branch_free, self.network_dtype
        )
        return new.x, new.v, new.d1, new.theta, new.rest, unconverged


def _build(
    model: DeformModel,
    branch_free: tuple[int, int],
    batch: int,
    dtype: torch.dtype,
    path: Path,
    network_dtype: torch.dtype | None = None,
) -> None:
    """Export the step for a rod at rest (shapes and dtype are all that matter) and compile it."""
    state, grip = rod_at_rest_vertex_major(model, batch, dtype)
    args = (state.x, state.v, state.d1, state.theta, state.rest, grip)
    t0 = time.perf_counter()
    loops = exports_loops(batch)
    options = {**AOT_OPTIONS, "memory_planning": False} if loops else AOT_OPTIONS
    with torch.no_grad(), loops_when_exported(loops):
        exported = torch.export.export(_BranchFreeStep(model, branch_free, network_dtype), args, strict=False)
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=path.parent) as tmp:  # atomic: no half-written package
            part = Path(tmp) / path.name
            torch._inductor.aoti_compile_and_package(
                exported, package_path=str(part), inductor_configs=options
            )
            os.replace(part, path)
    log.info(
        "compiled the step ahead of time for %d rods (%s) in %.0f s: %s",
        batch,
        dtype,
        time.perf_counter() - t0,
        path,
    )


def package_path(
    model: DeformModel,
    branch_free: tuple[int, int],
    batch: int,
    dtype: torch.dtype,
    network_dtype: torch.dtype | None = None,
) -> Path:
    """Where the package of this step is (or would be) cached.

    Args:
        model: the model whose step it is.
        branch_free: (twist iterations, projection sweeps).
        batch: rods per step.
        dtype: the state's dtype.
        network_dtype: the residual network's arithmetic (None: float32).

    Returns:
        The path in :func:`cache_dir`.
    """
    return cache_dir() / f"step-{package_key(model, branch_free, batch, dtype, network_dtype)}.pt2"


def ensure_package(
    model: DeformModel,
    branch_free: tuple[int, int],
    batch: int,
    dtype: torch.dtype,
    network_dtype: torch.dtype | None = None,
) -> tuple[Path, bool]:
    """The cached package of this step, compiled now if the cache has none (not loaded: another
    process may build it for one that loads it). A process that finds another building the same
    package waits for it instead of building it again. Arguments as for :func:`package_path`.

    Returns:
        ``(path, built)``: built is True when it was compiled by this call.
    """
    path = package_path(model, branch_free, batch, dtype, network_dtype)
    if path.exists():
        return path, False
    path.parent.mkdir(parents=True, exist_ok=True)
    # one builder per package: the service's predict processes meet a new size at the same request,
    # and two builds at once took both cores for a minute to make one file
    with open(path.with_suffix(".lock"), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if path.exists():  # built while this process waited
            return path, False
        _build(model, branch_free, batch, dtype, path, network_dtype)
    return path, True


class AheadOfTimeStep:
    """``(state, grip_next) -> (new state, unconverged (B,) bool)`` for exactly ``batch`` rods of
    ``dtype``, no gradients; values identical to the ``torch.compile`` one-graph step.

    >>> step = AheadOfTimeStep(model, (2, 2), batch=64)  # builds or loads the package
    >>> new, unconverged = step(state, grip_next)
    """

    def __init__(
        self,
        model: DeformModel,
        branch_free: tuple[int, int],
        batch: int,
        dtype: torch.dtype = torch.float64,
        network_dtype: torch.dtype | None = None,
    ):
        self.model, self.branch_free, self.batch, self.dtype = model, branch_free, batch, dtype
        self.network_dtype = network_dtype
        self._runner = None
        self._run_flat = None
        self._tensors: list[Tensor] = []  # the parameters and buffers the package was made from
        self._versions: tuple[int, ...] = ()
        self.path: Path | None = None
        self.load()

    def load(self) -> None:
        """The package for the model's current parameters and the process's thread count: from the
        cache, else compiled now."""
        self.threads = torch.get_num_threads()
        self.path, _ = ensure_package(
            self.model, self.branch_free, self.batch, self.dtype, self.network_dtype
        )
        self._runner = torch._inductor.aoti_load_package(str(self.path))
        # the loader's flat call: the package's own __call__ parses its input and output tree specs
        # from JSON and flattens the arguments on every call, 35 us of a 157 us step at one rod
        # (122 us this way); inputs and outputs here are flat tuples of tensors already. A torch
        # without it fails here, and CompiledStep falls back to torch.compile as for any load error.
        self._run_flat = self._runner.loader.boxed_run
        # their version counters change on any in-place update (an optimiser step, load_state_dict);
        # kept as a list because walking the modules costs 60 us, a tenth of a step
        self._tensors = [*self.model.parameters(), *self.model.buffers()]
        self._versions = self._current_versions()

    def _current_versions(self) -> tuple[int, ...]:
        return tuple(t._version for t in self._tensors)

    def __call__(self, state: VertexMajorState, grip_next: Tensor) -> tuple[VertexMajorState, Tensor]:
        """Vertex-major in and out (:class:`deform.model.VertexMajorState`, grip (4, 3, B))."""
        if self._current_versions() != self._versions or torch.get_num_threads() != self.threads:
            self.load()  # parameters changed in place, or threads: not this package
        x, v, d1, theta, rest, unconverged = self._run_flat(
            [state.x, state.v, state.d1, state.theta, state.rest, grip_next]
        )
        return VertexMajorState(x, v, d1, theta, rest), unconverged
