r"""Material-frame angles: ``theta* = argmin_theta E(x, theta)`` over the interior edges.

The end edges take their angles from the grippers. With ``w_ij`` the material curvature of vertex
``i`` seen from edge ``j`` (see :mod:`deform.rod.energy`), ``dw/dtheta_j = (w2, -w1)``, so each
bending term contributes

    dE/dtheta_j   = beta_i / L_i * (wbar2 w1 - wbar1 w2)
    d2E/dtheta_j2 = beta_i / L_i * (wbar1 w1 + wbar2 w2)

and each twist term ``gamma_i / L_i (theta_i - theta_{i-1} + m_ref_i)^2`` couples neighbours only:
the Hessian is tridiagonal. Newton steps solve it in O(k).

Gradients (implicit function theorem): at the minimiser ``g(theta*, p) = 0``, so
``dtheta*/dp = -H^{-1} dg/dp``. We get exactly that from autograd by returning
``theta* - H^{-1} g(theta*, p)`` with ``theta*`` and ``H`` detached: its value is ``theta*`` and its
derivative is the IFT one. No iterations are unrolled. Arrays are vertex-major
(:mod:`deform.rod.geometry`): angles (m, B), the batch of rods last.
"""

from __future__ import annotations

import torch
from torch import Tensor

from deform.rod.convergence import ConvergenceReport, masked_loop
from deform.rod.energy import twist_of
from deform.rod.tridiagonal import solve_tridiagonal, solve_tridiagonal_pd


def gradient_and_hessian(
    theta: Tensor,
    a: Tensor,
    b: Tensor,
    m_ref: Tensor,
    beta: Tensor,
    gamma: Tensor,
    rest_vor: Tensor,
    wbar: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """Gradient (k, B), Hessian diagonal (k, B) and off-diagonal (k-1, B) over the free edges.

    Args:
        theta: (m, B) material angles, ends included [rad].
        a: (n-2, 2, B) ``kb . d1`` (:func:`deform.rod.energy.curvature_projections`).
        b: (n-2, 2, B) ``kb . d2``.
        m_ref: (n-2, B) reference twist [rad].
        beta: (n-2, 1) bending stiffness [N m^2].
        gamma: (n-2, 1) twisting stiffness [N m^2].
        rest_vor: (n-2, B) rest Voronoi lengths (twice) [m].
        wbar: (n-2, 2, 2, 1) rest curvature.

    Returns:
        ``(g, diag, off)`` of the energy over the k = m - 2 free angles.
    """
    cos, sin = torch.cos(theta), torch.sin(theta)
    scale = beta / rest_vor
    g_side, h_side = [], []
    for side, edges in ((0, slice(None, -1)), (1, slice(1, None))):  # the vertex's left, right edge
        c_j, s_j, a_j, b_j = cos[edges], sin[edges], a[:, side], b[:, side]
        w1, w2 = -s_j * a_j + c_j * b_j, -(c_j * a_j + s_j * b_j)  # material_curvature of this side
        g_side.append(scale * (wbar[:, side, 1] * w1 - wbar[:, side, 0] * w2))
        h_side.append(scale * (wbar[:, side, 0] * w1 + wbar[:, side, 1] * w2))
    c = 2.0 * gamma / rest_vor  # (n-2, B) twist coupling at each interior vertex
    tw = c * twist_of(theta, m_ref)
    # interior vertex k touches edge k (left side) and edge k+1 (right side); free edges are 1..m-2
    grad = g_side[0][1:] + g_side[1][:-1] + tw[:-1] - tw[1:]
    diag = h_side[0][1:] + h_side[1][:-1] + c[:-1] + c[1:]
    off = -c[1:-1]
    return grad, diag, off


def twist_only_minimiser(m_ref: Tensor, theta_ends: Tensor) -> Tensor:
    """Free angles that spread the total twist evenly (the minimiser without rest curvature, equal weights).

    Args:
        m_ref: (n-2, B) reference twist [rad].
        theta_ends: (2, B) angles of the first and last edge [rad].

    Returns:
        (m-2, B) free angles.
    """
    k = m_ref.shape[0] - 1
    frac = torch.linspace(0, 1, k + 2, dtype=m_ref.dtype, device=m_ref.device)[1:-1, None]
    free = theta_ends[:1] + frac * (theta_ends[1:] - theta_ends[:1])
    return free - torch.cumsum(m_ref, 0)[:-1] + frac * m_ref.sum(0, keepdim=True)


def twist_minimiser(m_ref: Tensor, theta_ends: Tensor, c: Tensor) -> Tensor:
    r"""Free angles that minimise the energy when there is no rest curvature (``wbar`` = 0), exactly.

    Without rest curvature the bending energy ``beta / L |w|^2`` does not depend on the angles (they
    only rotate ``w``), and what is left is the twist energy ``sum_i c_i / 2 tau_i^2`` of the
    twists ``tau_i = theta_{i+1} - theta_i + m_ref_i``. Its minimum has ``c_i tau_i = lambda`` at
    every interior vertex, and the twists add up to what the ends impose:

        sum_i tau_i = theta_last - theta_first + sum_i m_ref_i,   so   lambda = that / sum_i (1 / c_i).

    Why: it is what Newton converges to, in a dozen operations instead of two to three Newton steps
    and an implicit-gradient solve, and differentiable as it stands.

    Args:
        m_ref: (n-2, B) reference twist [rad].
        theta_ends: (2, B) angles of the first and last edge [rad].
        c: (n-2, B) twist coupling ``2 gamma / rest_vor`` at each interior vertex.

    Returns:
        (m-2, B) free angles.
    """
    inv = 1.0 / c
    lam = (theta_ends[1] - theta_ends[0] + m_ref.sum(0)) / inv.sum(0)
    return theta_ends[:1] + torch.cumsum(lam * inv - m_ref, 0)[:-1]


def _with_free(theta_ends: Tensor, free: Tensor) -> Tensor:
    return torch.cat([theta_ends[:1], free, theta_ends[1:]])


def newton_theta(
    a: Tensor,
    b: Tensor,
    m_ref: Tensor,
    theta_ends: Tensor,
    beta: Tensor,
    gamma: Tensor,
    rest_vor: Tensor,
    wbar: Tensor,
    theta_init: Tensor | None = None,
    tol: float = 1e-10,
    max_iter: int = 30,
    max_step: float = 0.5,
    branch_free: int = 0,
    report: ConvergenceReport | None = None,
    groups: int = 1,
) -> Tensor:
    """Minimise over the free angles by damped Newton; returns all m angles (ends included), detached.

    ``tol`` is the target error in rad: iterations stop once a plain Newton step is below
    ``sqrt(tol)`` (quadratic convergence leaves an error of order ``tol``) or any step below ``tol``.

    Where the exact Hessian is positive definite the step is plain Newton (quadratic convergence at
    a minimum); elsewhere it uses the twist Hessian plus the absolute value of the bending curvature,
    which is positive definite and so a descent direction. Steps are clipped to ``max_step`` rad.

    ``branch_free``: that many iterations first run without a single host synchronisation, each
    rod stopping by the same rule on its own (its later updates masked out), so that compiled code
    holds a converging solve in one graph (warm-started solves converge in two); the checked loop
    then goes on only if a rod is still unconverged. Per rod the result is that of the checked loop.
    ``report``: when given, receives ``twist_unconverged`` (per rod, after the branch-free
    iterations, by the same stopping rule), so compiled code checks convergence for free.

    Args:
        a: (n-2, 2, B) and the other energy inputs as in :func:`gradient_and_hessian`.
        b: (n-2, 2, B).
        m_ref: (n-2, B).
        theta_ends: (2, B) the end edges' angles, held (from the grippers).
        beta: (n-2, 1).
        gamma: (n-2, 1).
        rest_vor: (n-2, B).
        wbar: (n-2, 2, 2, 1).
        theta_init: (m, B) warm start (last step's angles), or None.
        tol: target error [rad].
        max_iter: iterations at most.
        max_step: largest step [rad].
        branch_free: iterations without host synchronisation first.
        report: a :class:`deform.rod.convergence.ConvergenceReport` to fill, or None.
        groups: the batch is that many equal runs of consecutive rods, each iterated until its own
            rods are converged, as if it were solved alone (several models stepped as one batch:
            deform.diagnose.stack).

    Returns:
        (m, B) angles [rad].
    """
    with torch.no_grad():
        a, b, m_ref, theta_ends = a.detach(), b.detach(), m_ref.detach(), theta_ends.detach()
        beta, gamma, rest_vor, wbar = beta.detach(), gamma.detach(), rest_vor.detach(), wbar.detach()
        tol = max(tol, 50 * torch.finfo(a.dtype).eps)  # reachable in float32 too
        if theta_init is None:
            free = twist_only_minimiser(m_ref, theta_ends)
        else:
            free = theta_init.detach()[1:-1].clone()
        if branch_free:

            def iteration(carry, active):
                (free,) = carry
                new, size, exact = _newton_update(
                    free, theta_ends, a, b, m_ref, beta, gamma, rest_vor, wbar, max_step, per_rod=True
                )
                free = torch.where(active, new, free)
                return (free,), active & ~((size < tol) | (exact & (size * size < tol)))

            active = torch.ones(free.shape[1:], dtype=torch.bool, device=free.device)
            (free,), active = masked_loop(iteration, (free,), active, branch_free)
            # compiled code cannot branch on data: it returns here and its caller checks convergence
            # afterwards (deform.compiled); eager code goes on while a rod is unconverged
            if report is not None:
                report.twist_unconverged = active
            if torch.compiler.is_compiling() or not bool(active.any()):
                return _with_free(theta_ends, free)
            max_iter -= branch_free
        if groups > 1:
            return _with_free(
                theta_ends,
                _newton_by_group(
                    free,
                    theta_ends,
                    a,
                    b,
                    m_ref,
                    beta,
                    gamma,
                    rest_vor,
                    wbar,
                    max_step,
                    tol,
                    max_iter,
                    groups,
                ),
            )
        for _ in range(max_iter):
            free, size, exact = _newton_update(
                free, theta_ends, a, b, m_ref, beta, gamma, rest_vor, wbar, max_step
            )
            size, exact = float(size), bool(exact)
            # exact Newton converges quadratically: the error left after a step of size s is ~s^2
            if size < tol or (exact and size * size < tol):
                break
        return _with_free(theta_ends, free)


def _newton_by_group(
    free, theta_ends, a, b, m_ref, beta, gamma, rest_vor, wbar, max_step, tol, max_iter, groups
):
    """The checked Newton loop of :func:`newton_theta` for ``groups`` runs of consecutive rods, each
    updated until its own largest step meets the stopping rule: per group the iterations, and so
    the angles, of that group solved alone."""
    active = torch.ones(groups, dtype=torch.bool, device=free.device)
    width = free.shape[-1] // groups
    for _ in range(max_iter):
        new, size, exact = _newton_update(
            free, theta_ends, a, b, m_ref, beta, gamma, rest_vor, wbar, max_step, per_rod=True
        )
        free = torch.where(active.repeat_interleave(width), new, free)
        size, exact = size.reshape(groups, width).amax(1), exact.reshape(groups, width).all(1)
        active = active & ~((size < tol) | (exact & (size * size < tol)))
        if not bool(active.any()):
            break
    return free


def _newton_update(
    free, theta_ends, a, b, m_ref, beta, gamma, rest_vor, wbar, max_step: float, per_rod: bool = False
):
    """One damped Newton update -> (free angles, largest step, whether the exact Hessian was used).
    One function, so that compiled code fuses the whole iteration. ``per_rod``: step size and
    exactness per rod, and no data-dependent branch (the safe step is always computed)."""
    theta = _with_free(theta_ends, free)
    grad, diag, off = gradient_and_hessian(theta, a, b, m_ref, beta, gamma, rest_vor, wbar)
    step, ok = solve_tridiagonal_pd(diag, off, grad, dim=0)
    if per_rod or not bool(ok.all()):
        c = 2.0 * gamma / rest_vor
        twist_diag = c[:-1] + c[1:]
        safe = twist_diag + (diag - twist_diag).abs()
        step = torch.where(ok, step, solve_tridiagonal(safe, off, grad, dim=0))
    step = step.clamp(-max_step, max_step)
    if per_rod:
        return free - step, step.abs().amax(0), ok
    return free - step, step.abs().max(), ok.all()


def attach_implicit_gradient(
    theta_star: Tensor,
    a: Tensor,
    b: Tensor,
    m_ref: Tensor,
    theta_ends: Tensor,
    beta: Tensor,
    gamma: Tensor,
    rest_vor: Tensor,
    wbar: Tensor,
    converged_tol: float = 1e-4,
) -> Tensor:
    """Value ``theta*``; derivative ``-H^{-1} dg/dp`` (implicit function theorem).

    Rods whose solve did not reach a minimum (Newton step above ``converged_tol`` rad or Hessian
    not positive definite) keep ``theta*`` with no gradient rather than a meaningless one.

    Args:
        theta_star: (m, B) converged angles [rad].
        a, b, m_ref, theta_ends, beta, gamma, rest_vor, wbar: as for :func:`newton_theta`; the gradient
            flows to those that require it.
        converged_tol: largest Newton step [rad] that counts as converged.

    Returns:
        (m, B) ``theta*`` carrying the implicit gradient.
    """
    theta0 = _with_free(theta_ends, theta_star.detach()[1:-1])
    grad, diag, off = gradient_and_hessian(theta0, a, b, m_ref, beta, gamma, rest_vor, wbar)
    diag, off = diag.detach(), off.detach()
    step, pd = solve_tridiagonal_pd(diag, off, grad, dim=0)  # differentiable in grad
    ok = pd & (step.detach().abs().amax(0) < converged_tol)
    if not bool(ok.all()):
        c = (2.0 * gamma / rest_vor).detach()
        twist_diag = c[:-1] + c[1:]
        diag = torch.where(ok, diag, twist_diag + (diag - twist_diag).abs())
        step = solve_tridiagonal(diag, off, grad * ok, dim=0)
    free = theta_star.detach()[1:-1] - step
    return _with_free(theta_ends, free)


def solve_theta(
    a: Tensor,
    b: Tensor,
    m_ref: Tensor,
    theta_ends: Tensor,
    beta: Tensor,
    gamma: Tensor,
    rest_vor: Tensor,
    wbar: Tensor,
    theta_init: Tensor | None = None,
    tol: float = 1e-10,
    max_iter: int = 30,
    branch_free: int = 0,
    report: ConvergenceReport | None = None,
    groups: int = 1,
    closed_form_groups: int = 0,
) -> Tensor:
    """Fast batched solver; differentiable through the implicit function theorem when needed.

    Args:
        a, b, m_ref, theta_ends, beta, gamma, rest_vor, wbar, theta_init, tol, max_iter, branch_free,
        report, groups: as for :func:`newton_theta`.
        closed_form_groups: the first that many of the ``groups`` runs of rods have no rest curvature
            and none being learnt: their angles come in closed form (:func:`twist_minimiser`), each
            other run's from the iterative solve, as each would alone (several models stepped as one
            batch, some fitting a rest curvature: deform.diagnose.stack).

    Returns:
        (m, B) energy-minimising angles [rad], differentiable when an input requires grad.
    """
    if closed_form_groups:
        return _closed_form_first(
            closed_form_groups,
            a,
            b,
            m_ref,
            theta_ends,
            beta,
            gamma,
            rest_vor,
            wbar,
            theta_init,
            tol,
            max_iter,
            groups,
        )
    if _quadratic(wbar, branch_free, report):
        return _closed_form_angles(m_ref, theta_ends, gamma, rest_vor)
    theta_star = newton_theta(
        a,
        b,
        m_ref,
        theta_ends,
        beta,
        gamma,
        rest_vor,
        wbar,
        theta_init,
        tol,
        max_iter,
        branch_free=branch_free,
        report=report,
        groups=groups,
    )
    inputs = (a, b, m_ref, theta_ends, beta, gamma, rest_vor, wbar)
    if torch.is_grad_enabled() and any(t.requires_grad for t in inputs):
        return attach_implicit_gradient(theta_star, *inputs)
    return theta_star


def _closed_form_first(
    closed_groups, a, b, m_ref, theta_ends, beta, gamma, rest_vor, wbar, theta_init, tol, max_iter, groups
) -> Tensor:
    """:func:`solve_theta` of a batch whose first ``closed_groups`` of ``groups`` equal runs of rods
    take the closed form and the rest the iterative solve: each part on its own rods, joined."""
    if not 0 < closed_groups <= groups:
        raise ValueError(f"closed_form_groups must be in 1..groups ({groups}), got {closed_groups}")
    k = theta_ends.shape[-1] // groups * closed_groups

    def rods(t: Tensor | None, part: slice) -> Tensor | None:
        return t if t is None or t.shape[-1] == 1 else t[..., part]  # (m, 1): shared by every rod

    head, tail = slice(None, k), slice(k, None)
    closed = _closed_form_angles(*(rods(t, head) for t in (m_ref, theta_ends, gamma, rest_vor)))
    if k == theta_ends.shape[-1]:
        return closed
    iterative = solve_theta(
        *(rods(t, tail) for t in (a, b, m_ref, theta_ends, beta, gamma, rest_vor, wbar, theta_init)),
        tol=tol,
        max_iter=max_iter,
        groups=groups - closed_groups,
    )
    return torch.cat([closed, iterative], -1)


def _closed_form_angles(m_ref: Tensor, theta_ends: Tensor, gamma: Tensor, rest_vor: Tensor) -> Tensor:
    """All m angles, the free ones from :func:`twist_minimiser` (no rest curvature)."""
    return _with_free(theta_ends, twist_minimiser(m_ref, theta_ends, 2.0 * gamma / rest_vor))


def _quadratic(wbar: Tensor, branch_free: int, report: ConvergenceReport | None) -> bool:
    """Whether :func:`twist_minimiser` gives the minimum: no rest curvature, none being learnt (its
    gradient flows through the bending terms that vanish with it), on the eager, checked path
    (compiled steps keep one graph for every model)."""
    if wbar.requires_grad or branch_free or report is not None or torch.compiler.is_compiling():
        return False
    return not bool(wbar.any())
