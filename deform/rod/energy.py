r"""Elastic and gravitational energy of a discrete elastic rod.

With reference directors ``d1, d2 = t x d1`` and material angles ``theta``, the material frame is
``m1 = cos(theta) d1 + sin(theta) d2``, ``m2 = -sin(theta) d1 + cos(theta) d2``. At interior vertex
``i`` and each adjacent edge ``j`` the material curvature is ``w_ij = (kb_i.m2_j, -kb_i.m1_j)``.

    E_bend  = sum_i  beta_i / (2 L_i) * sum_{j in {i-1, i}} |w_ij - wbar_ij|^2
    E_twist = sum_i  gamma_i / L_i * (theta_i - theta_{i-1} + m_ref_i)^2
    E_grav  = sum_v  mass_v * g * z_v

``L_i`` is the rest Voronoi length (twice), ``beta`` the bending stiffness EI [N m^2], ``gamma`` the
twisting stiffness GJ [N m^2], ``wbar`` the rest (natural) curvature and ``m_ref`` the reference
twist. Forces are ``-dE/dx`` at the energy-minimising ``theta`` (envelope theorem), in closed form in
:mod:`deform.rod.forces`; this energy is their reference (tests compare them with its finite
differences and its autograd gradient). Arrays are vertex-major (:mod:`deform.rod.geometry`), the
batch of rods last.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from deform.rod import geometry as G
from deform.rod.fusion import Fused

GRAVITY = 9.81


@dataclass
class RodGeometry:
    """Everything the energy needs from the positions and last step's reference frame."""

    t: Tensor  # (m, 3, B) unit tangents
    d1: Tensor  # (m, 3, B) reference directors (time-parallel transported)
    d2: Tensor  # (m, 3, B)
    kb: Tensor  # (n-2, 3, B) curvature binormals
    m_ref: Tensor  # (n-2, B) reference twist


def rod_geometry(x: Tensor, d1_prev: Tensor, t_prev: Tensor | None = None) -> RodGeometry:
    """Geometry at ``x`` with last step's directors carried to the current tangents.

    ``t_prev=None``: the directors already belong to ``x``; they are still differentiated as carried
    by parallel transport (they move with ``x``) when ``x`` requires grad.

    Args:
        x: (n, 3, B) vertices.
        d1_prev: (m, 3, B) reference directors of the last step (or of ``x``).
        t_prev: (m, 3, B) unit tangents of the last step, or None.

    Returns:
        A :class:`RodGeometry` (tangents, directors, curvature binormals, reference twist).
    """
    e = G.edges(x)
    t = G.normalize(e)
    if t_prev is not None:
        d1 = G.time_transport(d1_prev, t_prev, t)
    elif torch.is_grad_enabled() and x.requires_grad:
        d1 = G.time_transport(d1_prev, t.detach(), t)
    else:
        d1 = d1_prev
    d2 = G.cross(t, d1)
    return RodGeometry(t=t, d1=d1, d2=d2, kb=G.curvature_binormal(e), m_ref=G.reference_twist(d1, t))


def curvature_projections(geo: RodGeometry) -> tuple[Tensor, Tensor]:
    """The curvature binormal projected on the reference directors of both adjacent edges.

    Args:
        geo: from :func:`rod_geometry`.

    Returns:
        ``(A, B)``, each (n-2, 2, B): ``kb_i . d1_j`` and ``kb_i . d2_j`` for j = left, right edge.
    """
    kb = geo.kb
    a = torch.stack([G.dot(kb, geo.d1[:-1]), G.dot(kb, geo.d1[1:])], dim=-2)
    b = torch.stack([G.dot(kb, geo.d2[:-1]), G.dot(kb, geo.d2[1:])], dim=-2)
    return a, b


def geometry_and_projections(x: Tensor, d1_prev: Tensor) -> tuple[RodGeometry, Tensor, Tensor]:
    """:func:`rod_geometry` (the directors belong to ``x``) and its :func:`curvature_projections`:
    one piece for :data:`fused_geometry_and_projections`.

    Args:
        x: (n, 3, B) vertices.
        d1_prev: (m, 3, B) reference directors of ``x``.

    Returns:
        ``(geometry, A, B)``.
    """
    geo = rod_geometry(x, d1_prev)
    a, b = curvature_projections(geo)
    return geo, a, b


fused_geometry_and_projections = Fused(geometry_and_projections)


def material_curvature(a: Tensor, b: Tensor, theta_lr: Tensor) -> tuple[Tensor, Tensor]:
    """``w1 = kb.m2 = -sin A + cos B`` and ``w2 = -kb.m1 = -(cos A + sin B)`` for each (vertex, side).

    Args:
        a: (n-2, 2, B) ``kb . d1`` per vertex and side.
        b: (n-2, 2, B) ``kb . d2``.
        theta_lr: (n-2, 2, B) material angles of the left and right edge (:func:`left_right`).

    Returns:
        ``(w1, w2)``, each (n-2, 2, B).
    """
    c, s = torch.cos(theta_lr), torch.sin(theta_lr)
    return -s * a + c * b, -(c * a + s * b)


def left_right(theta: Tensor) -> Tensor:
    """The angles of the left and right edge of each interior vertex.

    Args:
        theta: (m, B) edge angles [rad].

    Returns:
        (n-2, 2, B).
    """
    return torch.stack([theta[:-1], theta[1:]], dim=-2)


def bending_energy(
    a: Tensor, b: Tensor, theta: Tensor, beta: Tensor, rest_vor: Tensor, wbar: Tensor
) -> Tensor:
    """``E_bend = sum_i beta_i / (2 L_i) sum_j |w_ij - wbar_ij|^2`` (module docstring).

    Args:
        a: (n-2, 2, B) ``kb . d1`` from :func:`curvature_projections`.
        b: (n-2, 2, B) ``kb . d2``.
        theta: (m, B) material angles [rad].
        beta: (n-2, 1) bending stiffness EI [N m^2].
        rest_vor: (n-2, B) rest Voronoi lengths (twice) [m].
        wbar: (n-2, 2, 2, 1) rest curvature (vertex, side, component).

    Returns:
        (B,) energy [J].
    """
    w1, w2 = material_curvature(a, b, left_right(theta))
    sq = (w1 - wbar[:, :, 0]) ** 2 + (w2 - wbar[:, :, 1]) ** 2  # (n-2, 2, B)
    return (beta / (2.0 * rest_vor) * sq.sum(1)).sum(0)


def twist_of(theta: Tensor, m_ref: Tensor) -> Tensor:
    """Twist at each interior vertex: ``theta_i - theta_{i-1} + m_ref_i``.

    Args:
        theta: (m, B) material angles [rad].
        m_ref: (n-2, B) reference twist [rad].

    Returns:
        (n-2, B) [rad].
    """
    return theta[1:] - theta[:-1] + m_ref


def twisting_energy(theta: Tensor, m_ref: Tensor, gamma: Tensor, rest_vor: Tensor) -> Tensor:
    """``E_twist = sum_i gamma_i / L_i * twist_i^2`` (module docstring).

    Args:
        theta: (m, B) material angles [rad].
        m_ref: (n-2, B) reference twist [rad].
        gamma: (n-2, 1) twisting stiffness GJ [N m^2].
        rest_vor: (n-2, B) rest Voronoi lengths (twice) [m].

    Returns:
        (B,) energy [J].
    """
    return (gamma / rest_vor * twist_of(theta, m_ref) ** 2).sum(0)


def gravity_energy(x: Tensor, mass: Tensor, g: float = GRAVITY) -> Tensor:
    """``E_grav = sum_v mass_v g z_v``.

    Args:
        x: (n, 3, B) vertices [m], z up.
        mass: (n, B) vertex masses [kg].
        g: gravitational acceleration [m/s^2].

    Returns:
        (B,) energy [J].
    """
    return (mass * g * x[:, 2]).sum(0)


@dataclass
class ElasticParams:
    """Per-rod material parameters, vertex-major, broadcastable against the batch (last axis)."""

    beta: Tensor  # (n-2, 1) bending stiffness at interior vertices [N m^2]
    gamma: Tensor  # (n-2, 1) twisting stiffness [N m^2]
    wbar: Tensor  # (n-2, 2, 2, 1) rest material curvature (vertex, side, component)
    rest_vor: Tensor  # (n-2, B) rest Voronoi lengths [m]


def total_energy(
    x: Tensor, theta: Tensor, d1_prev: Tensor, t_prev: Tensor, p: ElasticParams, mass: Tensor
) -> Tensor:
    """Total potential energy at positions ``x`` and edge angles ``theta`` (ends included).

    Args:
        x: (n, 3, B) vertices [m].
        theta: (m, B) material angles [rad].
        d1_prev: (m, 3, B) reference directors of the last step.
        t_prev: (m, 3, B) unit tangents of the last step.
        p: the rod's :class:`ElasticParams`.
        mass: (n, B) vertex masses [kg].

    Returns:
        (B,) energy [J].
    """
    geo = rod_geometry(x, d1_prev, t_prev)
    a, b = curvature_projections(geo)
    return (
        bending_energy(a, b, theta, p.beta, p.rest_vor, p.wbar)
        + twisting_energy(theta, geo.m_ref, p.gamma, p.rest_vor)
        + gravity_energy(x, mass)
    )
