r"""Linearly implicit bending: the explicit step's velocity filtered through the rod's bending stiffness.

Why: the model steps the bending forces explicitly, which is stable only while the stiffest bending
mode turns less than about two radians per step (:math:`\omega_{max} dt < 2`). A rope of 1 m at 12
vertices and 10 ms passes that between about 0.003 and 0.03 N m^2 depending on its mass: a stiff
light cable, bent and held, rings at metres a second (DLO3 trained explicitly, 97 g at
0.013 N m^2, rang at 5 m/s when bent by 30 % and held). Smaller steps alone did not cure it; with
this filter they do where it alone does not (``RodConfig.substeps``).

The bending energy of a nearly straight stretch is quadratic in the displacements ``u`` of each axis,
:math:`E \approx \tfrac12 u^T K u` with

.. math::
    K = G^T \operatorname{diag}(2 \beta_i / L_i) G, \qquad
    (G u)_i = \frac{u_{i+1} - u_i}{l_i} - \frac{u_i - u_{i-1}}{l_{i-1}},

``beta_i`` the bending stiffness at interior vertex ``i``, ``l`` the rest edge lengths and
``L_i = l_{i-1} + l_i`` (the model's energy, :func:`deform.rod.energy.bending_energy`, has exactly
this Hessian at a straight rod; a test checks it against finite differences of the forces). The
operator acts the same on x, y and z, so it does not depend on how the rod is turned.

Backward Euler on that linear part, ``M v' = M v + dt F(x) - dt^2 K v'``, is
:math:`(M + dt^2 K) v' = M \hat v` with :math:`\hat v = v + dt\,a` the explicit step's velocity: the
explicit velocity is filtered by :math:`(I + dt^2 M^{-1} K)^{-1}`, which leaves slow modes as they
were (a factor :math:`1/(1 + \omega^2 dt^2)`) and cannot amplify a fast one. The gripped vertices
move as the grippers do, ``v_g = (x_g' - x_g) / dt``; their coupling enters the free vertices'
right-hand side, :math:`-dt^2 K_{fg} v_g`.

Run eagerly, the filter's matrices are inverted once per set of parameters
(:func:`implicit_filter`); compiled code solves each step's system with an unrolled band Cholesky
(:func:`implicit_bending_velocity`; ``K`` has two bands on each side), which inductor fuses, where a
LAPACK call had no compiled kernel and cost 2 ms a step through its fallback.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn.functional import pad


def bending_operator(beta: Tensor, rest: Tensor) -> Tensor:
    """The bending stiffness matrix ``K`` of a straight rod (module docstring), one per rod.

    Args:
        beta: (n-2, 1) or (n-2, B) bending stiffness at interior vertices [N m^2].
        rest: (m, B) rest edge lengths [m], m = n - 1.

    Returns:
        (B, n, n) [N/m], symmetric positive semi-definite (rigid motions are its null space).
    """
    rest = rest.T  # (B, m)
    inv = 1.0 / rest
    prev, nxt = inv[:, :-1], inv[:, 1:]  # (B, n-2)
    # G (B, n-2, n): row i reads vertices i, i+1, i+2 (interior vertex i+1)
    G = torch.stack([prev, -(prev + nxt), nxt], dim=-1)  # (B, n-2, 3)
    weight = 2.0 * beta.T.to(rest.dtype) / (rest[:, :-1] + rest[:, 1:])  # (B, n-2)
    # three diagonals of the band matrix, each shifted into place by padding (no scatter: traceable)
    full = sum(pad(torch.diag_embed(G[:, :, k]), (k, 2 - k)) for k in range(3))  # (B, n-2, n)
    return full.transpose(-1, -2) @ (weight.unsqueeze(-1) * full)


def _free(n: int, held: list[int]) -> list[int]:
    """The vertices not held, in order."""
    return [i for i in range(n) if i not in set(held)]


def _blocks(
    beta: Tensor, rest: Tensor, mass: Tensor, dtype: torch.dtype, held: list[int]
) -> tuple[list[int], Tensor, Tensor, Tensor]:
    """``(free, K_ff (B, f, f), K_fg (B, f, h), m_f (B, f))``: the operator split into the free and held
    vertices' blocks, and the free vertices' masses."""
    free = _free(mass.shape[0], held)
    K_f = bending_operator(beta, rest).to(dtype)[:, free]
    return free, K_f[:, :, free], K_f[:, :, held], mass[free].T.to(dtype)


def implicit_filter(
    beta: Tensor, rest: Tensor, mass: Tensor, dt: float, held: list[int]
) -> tuple[Tensor, Tensor]:
    """The matrices of the backward-Euler filter (module docstring) for one set of parameters: what a
    step applies, computed once while the parameters and rest lengths stay (a rollout).

    Args:
        beta: (n-2, 1) or (n-2, B) bending stiffness at interior vertices [N m^2].
        rest: (m, B) rest edge lengths [m].
        mass: (n, B) vertex masses [kg].
        dt: step [s].
        held: the held vertex indices (the others are free).

    Returns:
        ``(S, C)``: (B, f, f) :math:`(M_f + dt^2 K_{ff})^{-1} M_f` and (B, f, h)
        :math:`dt^2 (M_f + dt^2 K_{ff})^{-1} K_{fg}`, so that ``v_f = S v_hat_f - C v_g``.
    """
    _, K_ff, K_fg, m_f = _blocks(beta, rest, mass, mass.dtype, held)
    inverse = torch.linalg.inv(torch.diag_embed(m_f) + (dt * dt) * K_ff)
    return inverse * m_f.unsqueeze(-2), (dt * dt) * (inverse @ K_fg)


def apply_implicit_filter(
    v_explicit: Tensor, v_held: Tensor, matrices: tuple[Tensor, Tensor], held: list[int]
) -> Tensor:
    """The free vertices' velocities after the backward-Euler step of the linear bending.

    Args:
        v_explicit: (n, 3, B) the explicit step's velocities (vertex-major).
        v_held: (h, 3, B) the held vertices' velocities over the step, ``(x_g' - x_g) / dt``.
        matrices: ``(S, C)`` of :func:`implicit_filter`.
        held: the held vertex indices.

    Returns:
        (n, 3, B): ``v_explicit`` with the free vertices' rows replaced (the held rows unchanged).
    """
    S, C = (m.to(v_explicit.dtype) for m in matrices)
    free = _free(v_explicit.shape[0], held)
    v_free = S @ v_explicit[free].permute(2, 0, 1) - C @ v_held.permute(2, 0, 1)  # (B, f, 3)
    out = v_explicit.clone()
    out[free] = v_free.permute(1, 2, 0)
    return out


def solve_band2_pd(system: Tensor, rhs: Tensor) -> Tensor:
    """Solve symmetric positive definite systems with two bands on each side of the diagonal
    (Cholesky ``L L^T`` with the same bands, unrolled over the k unknowns).

    Args:
        system: (B, k, k), zero beyond the second off-diagonal.
        rhs: (B, k, c).

    Returns:
        (B, k, c).
    """
    k = system.shape[-1]
    d0 = system.diagonal(0, -2, -1).unbind(-1)
    d1 = system.diagonal(-1, -2, -1).unbind(-1)  # d1[i] = A[i+1, i]
    d2 = system.diagonal(-2, -2, -1).unbind(-1)  # d2[i] = A[i+2, i]
    diag: list = []  # L[i, i]
    sub1: list = []  # L[i, i-1] (index i-1)
    sub2: list = []  # L[i, i-2] (index i-2)
    for i in range(k):
        pivot = d0[i]
        if i >= 2:
            sub2.append(d2[i - 2] / diag[i - 2])
            pivot = pivot - sub2[i - 2] ** 2
        if i >= 1:
            a = d1[i - 1] - (sub2[i - 2] * sub1[i - 2] if i >= 2 else 0.0)
            sub1.append(a / diag[i - 1])
            pivot = pivot - sub1[i - 1] ** 2
        diag.append(pivot.sqrt())
    b = rhs.unbind(-2)
    y: list = []
    for i in range(k):
        r = b[i]
        if i >= 1:
            r = r - sub1[i - 1].unsqueeze(-1) * y[i - 1]
        if i >= 2:
            r = r - sub2[i - 2].unsqueeze(-1) * y[i - 2]
        y.append(r / diag[i].unsqueeze(-1))
    z: list = [None] * k
    for i in range(k - 1, -1, -1):
        r = y[i]
        if i + 1 < k:
            r = r - sub1[i].unsqueeze(-1) * z[i + 1]
        if i + 2 < k:
            r = r - sub2[i].unsqueeze(-1) * z[i + 2]
        z[i] = r / diag[i].unsqueeze(-1)
    return torch.stack(z, dim=-2)


def implicit_bending_velocity(
    v_explicit: Tensor, v_held: Tensor, beta: Tensor, rest: Tensor, mass: Tensor, dt: float, held: list[int]
) -> Tensor:
    """:func:`apply_implicit_filter` without the inverse: this step's system solved as a band (what
    compiled code runs; the same values).

    Args:
        v_explicit: (n, 3, B) the explicit step's velocities (vertex-major).
        v_held: (h, 3, B) the held vertices' velocities over the step.
        beta: (n-2, 1) or (n-2, B) bending stiffness [N m^2].
        rest: (m, B) rest edge lengths [m].
        mass: (n, B) vertex masses [kg].
        dt: step [s].
        held: the held vertex indices; the free ones must be consecutive (the band).

    Returns:
        (n, 3, B).
    """
    free, K_ff, K_fg, m_f = _blocks(beta, rest, mass, v_explicit.dtype, held)
    system = torch.diag_embed(m_f) + (dt * dt) * K_ff
    rhs = m_f.unsqueeze(-1) * v_explicit[free].permute(2, 0, 1) - (dt * dt) * (K_fg @ v_held.permute(2, 0, 1))

    out = v_explicit.clone()
    out[free] = solve_band2_pd(system, rhs).permute(1, 2, 0)
    return out


def step_ratio(beta: Tensor, rest: Tensor, mass: Tensor, dt: float, held: list[int]) -> Tensor:
    r"""How far the explicit step is from its stability limit: :math:`\omega_{max} dt`, with
    :math:`\omega_{max}^2` the largest eigenvalue of :math:`M_f^{-1} K_{ff}` (the held rod's stiffest
    bending mode). Symplectic Euler diverges above 2; a bent and held rod rang from about 1.1-1.5.

    Args:
        beta: (n-2, 1) or (n-2, B) bending stiffness [N m^2].
        rest: (m, B) rest edge lengths [m].
        mass: (n, B) vertex masses [kg].
        dt: step [s].
        held: the held vertex indices.

    Returns:
        (B,) the ratio.
    """
    _, K_ff, _, m_f = _blocks(beta, rest, mass, mass.dtype, held)
    scale = m_f.rsqrt()  # (B, f): M^(-1/2) K M^(-1/2) is symmetric with the same spectrum
    lam = torch.linalg.eigvalsh(scale.unsqueeze(-1) * K_ff * scale.unsqueeze(-2))[..., -1]
    return lam.clamp_min(0.0).sqrt() * dt
