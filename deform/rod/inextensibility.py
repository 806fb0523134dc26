r"""Position-based inextensibility: project edges back to their rest lengths, preserving momentum.

Pair correction for edge ``j = (j, j+1)`` with inverse masses ``w``, unit edge ``u_j`` and multiplier
``l_j``: ``dx_j += w_j l_j u_j``, ``dx_{j+1} -= w_{j+1} l_j u_j``. Every pair correction has
``sum_i m_i dx_i = l_j u_j - l_j u_j = 0``, so linear momentum is preserved whatever the ``l``.
Gripped vertices have ``w = 0`` (infinitely heavy) and do not move.

Two ways to choose ``l``, both vectorised over vertices and batch:

- ``"projection"`` (default): all pair corrections at once. Linearising ``|e_j + de_j| = L_j`` gives
  ``(w_j + w_{j+1}) l_j - w_j u_{j-1}.u_j l_{j-1} - w_{j+1} u_{j+1}.u_j l_{j+1} = |e_j| - L_j``:
  a tridiagonal system (fast projection, Goldenthal et al. 2007). Converges in 2-3 sweeps.
- ``"gauss_seidel"``: classic PBD, each pair solved exactly on its own, even and odd edges in turn
  (they share no vertex, so each half is one vectorised update). Converges slowly on long chains.

Sweeps repeat until the largest relative edge error is below ``tol``. Arrays are vertex-major
(:mod:`deform.rod.geometry`).
"""

from __future__ import annotations

import enum

import torch
from torch import Tensor

from deform.rod import geometry as G
from deform.rod.convergence import ConvergenceReport, masked_loop
from deform.rod.fusion import Fused
from deform.rod.tridiagonal import solve_tridiagonal


def max_relative_error(
    x: Tensor, rest: Tensor, inv_mass: Tensor | None = None, per_rod: bool = False
) -> Tensor:
    """Largest ``| |e_j| / L_j - 1 |`` over edges that can move (an edge between two fixed vertices,
    such as the one between the two markers of a gripper, is whatever the inputs make it); over
    everything, or per rod.

    Args:
        x: (n, 3, B) vertices.
        rest: (m, B) rest lengths.
        inv_mass: (n, B) inverse masses, 0 for vertices that cannot move.
        per_rod: one value per rod instead of one for everything.

    Returns:
        A scalar tensor, or (B,) per rod.
    """
    err = (G.norm(G.edges(x)) / rest - 1.0).abs()
    if inv_mass is not None:
        err = err * ((inv_mass[1:] + inv_mass[:-1]) > 0)
    return err.amax(0) if per_rod else err.amax()


def apply_pair_corrections(x: Tensor, inv_mass: Tensor, lam: Tensor, unit: Tensor) -> Tensor:
    """``x_j += w_j l_j u_j``, ``x_{j+1} -= w_{j+1} l_j u_j`` for every edge ``j`` at once.

    Args:
        x: (n, 3, B) vertices.
        inv_mass: (n, B) weights ``w`` (inverse masses).
        lam: (m, B) correction length per edge [m].
        unit: (m, 3, B) unit edge directions.

    Returns:
        (n, 3, B) corrected vertices.
    """
    push = lam.unsqueeze(-2) * unit  # (m, 3, B)
    zero = torch.zeros_like(push[:1])
    delta = torch.cat([push, zero]) - torch.cat([zero, push])
    return x + inv_mass.unsqueeze(-2) * delta


def _unit_edges(x: Tensor) -> tuple[Tensor, Tensor]:
    e = G.edges(x)
    length = G.norm(e).clamp_min(1e-12)
    return e / length.unsqueeze(-2), length


def _projection_sweep(x: Tensor, inv_mass: Tensor, rest: Tensor) -> Tensor:
    unit, length = _unit_edges(x)
    w0, w1 = inv_mass[:-1], inv_mass[1:]
    diag = (w0 + w1).clamp_min(1e-12)  # an edge between two gripped vertices keeps l = 0
    off = -w1[:-1] * G.dot(unit[:-1], unit[1:])
    lam = solve_tridiagonal(diag, off, length - rest, dim=0)
    return apply_pair_corrections(x, inv_mass, lam, unit)


def _gauss_seidel_sweep(x: Tensor, inv_mass: Tensor, rest: Tensor) -> Tensor:
    for start in (0, 1):
        unit, length = _unit_edges(x)
        wsum = (inv_mass[:-1] + inv_mass[1:]).clamp_min(1e-12)
        lam = (length - rest) / wsum
        mask = torch.zeros_like(lam)
        mask[start::2] = 1.0
        x = apply_pair_corrections(x, inv_mass, lam * mask, unit)
    return x


class PBDMethod(str, enum.Enum):
    """How a sweep corrects the edges (see the module docstring)."""

    PROJECTION = "projection"
    GAUSS_SEIDEL = "gauss_seidel"


SWEEPS = {PBDMethod.PROJECTION: _projection_sweep, PBDMethod.GAUSS_SEIDEL: _gauss_seidel_sweep}
FUSED_SWEEPS = {method: Fused(sweep) for method, sweep in SWEEPS.items()}  # deform.rod.fusion


def enforce_inextensibility(
    x: Tensor,
    inv_mass: Tensor,
    rest: Tensor,
    tol: float = 1e-3,
    max_sweeps: int = 50,
    method: PBDMethod | str = PBDMethod.PROJECTION,
    branch_free: int = 0,
    report: ConvergenceReport | None = None,
    groups: int = 1,
    fused: bool = False,
) -> Tensor:
    """Project ``x`` (n, 3, B) so every edge has its rest length (m, B) within relative ``tol``.

    ``inv_mass`` (n, B): 0 for vertices that must not move. Differentiable (plain tensor ops).
    ``branch_free``: that many sweeps first run without a host synchronisation, each rod sweeping
    only while its own error is above ``tol`` (so compiled code holds the usual one or two sweeps
    in one graph); the checked loop then continues only if a rod is still above ``tol``.
    ``report``: when given, receives ``length_error``, each rod's largest relative edge error after
    the branch-free sweeps (what a convergence check would measure, already computed).

    Args:
        x: (n, 3, B) vertices after the unconstrained step.
        inv_mass: (n, B) inverse masses, 0 for vertices that must not move.
        rest: (m, B) rest lengths [m].
        tol: relative edge-length error to reach.
        max_sweeps: sweeps at most in the checked loop.
        method: :class:`PBDMethod` (or its string).
        branch_free: sweeps without host synchronisation first.
        report: a :class:`deform.rod.convergence.ConvergenceReport` to fill, or None.
        groups: the batch is that many equal runs of consecutive rods, each swept until its own
            rods are within ``tol``, as if it were projected alone (deform.diagnose.stack).
        fused: sweeps compiled (:data:`FUSED_SWEEPS`, :mod:`deform.rod.fusion`).

    Returns:
        (n, 3, B) projected vertices.
    """
    # a PBDMethod or its string: str enums hash and compare as their values
    sweep = (FUSED_SWEEPS if fused else SWEEPS)[method]
    if branch_free:

        def iteration(carry, active):
            x, err = carry
            swept, swept_err = _sweep_and_measure(sweep, x, inv_mass, rest, per_rod=True)
            x = torch.where(active, swept, x)
            err = torch.where(active, swept_err, err)
            return (x, err), err >= tol

        err = max_relative_error(x.detach(), rest.detach(), inv_mass, per_rod=True)
        (x, err), _ = masked_loop(iteration, (x, err), err >= tol, branch_free)
        if report is not None:
            report.length_error = err
        if torch.compiler.is_compiling():  # no data-dependent branch: the caller checks (deform.compiled)
            return x
        max_sweeps -= branch_free
        err = err.amax()
    elif groups > 1:
        return _sweep_by_group(sweep, x, inv_mass, rest, tol, max_sweeps, groups)
    else:
        err = max_relative_error(x.detach(), rest.detach(), inv_mass)
    for _ in range(max_sweeps):
        if float(err) < tol:
            break
        x, err = _sweep_and_measure(sweep, x, inv_mass, rest)
    return x


def _sweep_by_group(
    sweep, x: Tensor, inv_mass: Tensor, rest: Tensor, tol: float, max_sweeps: int, groups: int
):
    """The checked loop of :func:`enforce_inextensibility` for ``groups`` runs of consecutive rods,
    each swept while its own largest error is above ``tol``: per group the sweeps of that group
    projected alone."""
    width = x.shape[-1] // groups
    err = max_relative_error(x.detach(), rest.detach(), inv_mass, per_rod=True)
    active = err.reshape(groups, width).amax(1) >= tol
    for _ in range(max_sweeps):
        if not bool(active.any()):
            break
        swept, err = _sweep_and_measure(sweep, x, inv_mass, rest, per_rod=True)
        x = torch.where(active.repeat_interleave(width), swept, x)
        active = active & (err.reshape(groups, width).amax(1) >= tol)
    return x


def _sweep_and_measure(
    sweep, x: Tensor, inv_mass: Tensor, rest: Tensor, per_rod: bool = False
) -> tuple[Tensor, Tensor]:
    """One sweep and the error it leaves, in one function so compiled code fuses them."""
    x = sweep(x, inv_mass, rest)
    return x, max_relative_error(x.detach(), rest.detach(), inv_mass, per_rod)


def unweighted_inv_mass(inv_mass: Tensor) -> Tensor:
    """The 'original inextensibility' of the ablation: equal weights for every free vertex.

    Args:
        inv_mass: (n, B) inverse masses, 0 where fixed.

    Returns:
        (n, B) 1 for every free vertex, 0 where fixed.
    """
    return (inv_mass > 0).to(inv_mass.dtype)
