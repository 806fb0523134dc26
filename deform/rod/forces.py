r"""Closed-form forces ``F = -dE/dx`` of the rod energy at fixed material angles.

At the energy-minimising angles ``dE/dtheta = 0``, so the total derivative equals the partial one
(envelope theorem). Frames follow the rod by parallel transport: ``dm = -(m . dt) t``, and since
``kb_i`` is perpendicular to both adjacent tangents, the material frames contribute nothing to the
variation of ``w = (kb.m2, -kb.m1)``. With ``D = |e0||e1| + e0.e1`` and
``G_i = sum_j beta_i / L_i ((w1 - wbar1) m2_j - (w2 - wbar2) m1_j)``:

    d(G.kb)/de0 = 2/D (e1 x G) - (G.kb)/D (|e1| e0/|e0| + e1)
    d(G.kb)/de1 = 2/D (G x e0) - (G.kb)/D (|e0| e1/|e1| + e0)

and the reference twist varies as ``d m_ref = kb . (de0/|e0| + de1/|e1|) / 2`` (Bergou et al. 2008).
Vertex gradients are ``dE/dx_i = dE/de_{i-1} - dE/de_i``. A test checks all of it against autograd
of :func:`deform.rod.energy.total_energy`; written out because a first-order closed form makes the
step and the training backward pass several times cheaper than differentiating twice. Arrays are
vertex-major (:mod:`deform.rod.geometry`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from deform.rod import geometry as G
from deform.rod.energy import GRAVITY, ElasticParams, RodGeometry, left_right, material_curvature, twist_of
from deform.rod.fusion import Fused


def edge_gradient_to_vertices(g_e: Tensor) -> Tensor:
    """Chain rule from edges ``e_j = x_{j+1} - x_j`` to vertices.

    Args:
        g_e: (m, 3, B) gradient with respect to the edges.

    Returns:
        (n, 3, B) gradient with respect to the vertices.
    """
    zero = torch.zeros_like(g_e[:1])
    return torch.cat([zero, g_e]) - torch.cat([g_e, zero])


def rod_forces(
    x: Tensor,
    geo: RodGeometry,
    a: Tensor,
    b: Tensor,
    theta: Tensor,
    p: ElasticParams,
    mass: Tensor,
    g: float = GRAVITY,
) -> Tensor:
    """Forces ``-dE/dx``: bending, twisting and gravity, at the material angles ``theta``, in closed form.

    Args:
        x: (n, 3, B) vertices [m].
        geo: :func:`deform.rod.energy.rod_geometry` at ``x``.
        a: (n-2, 2, B) ``kb . d1`` from :func:`deform.rod.energy.curvature_projections`.
        b: (n-2, 2, B) ``kb . d2``.
        theta: (m, B) energy-minimising material angles [rad].
        p: the rod's :class:`deform.rod.energy.ElasticParams`.
        mass: (n, B) vertex masses [kg].
        g: gravitational acceleration [m/s^2].

    Returns:
        (n, 3, B) forces [N].
    """
    e = G.edges(x)
    e0, e1 = e[:-1], e[1:]
    n0, n1 = G.norm(e0, keepdim=True), G.norm(e1, keepdim=True)
    denom = (n0 * n1 + G.dot(e0, e1).unsqueeze(-2)).clamp_min(1e-12)
    # material frames of the left and right edge of each interior vertex: (n-2, side, 3, B)
    th = left_right(theta)
    c, s = torch.cos(th).unsqueeze(-2), torch.sin(th).unsqueeze(-2)
    d1 = torch.stack([geo.d1[:-1], geo.d1[1:]], dim=1)
    d2 = torch.stack([geo.d2[:-1], geo.d2[1:]], dim=1)
    m1 = c * d1 + s * d2
    m2 = -s * d1 + c * d2
    w1, w2 = material_curvature(a, b, th)
    scale = (p.beta / p.rest_vor).unsqueeze(1)
    r1 = (scale * (w1 - p.wbar[:, :, 0])).unsqueeze(-2)
    r2 = (scale * (w2 - p.wbar[:, :, 1])).unsqueeze(-2)
    gvec = (r1 * m2 - r2 * m1).sum(1)  # (n-2, 3, B)
    # twist: dE/dm_ref = 2 gamma / L * twist, pulled back through d m_ref = kb.(de0/|e0| + de1/|e1|)/2
    tw = (2.0 * p.gamma / p.rest_vor * twist_of(theta, geo.m_ref)).unsqueeze(-2)
    half_kb_tw = 0.5 * tw * geo.kb
    gk = G.dot(gvec, geo.kb).unsqueeze(-2)
    d_e0 = 2.0 / denom * G.cross(e1, gvec) - gk / denom * (n1 * e0 / n0 + e1) + half_kb_tw / n0
    d_e1 = 2.0 / denom * G.cross(gvec, e0) - gk / denom * (n0 * e1 / n1 + e0) + half_kb_tw / n1
    zero = torch.zeros_like(d_e0[:1])
    grad_e = torch.cat([d_e0, zero]) + torch.cat([zero, d_e1])  # (m, 3, B)
    force = -edge_gradient_to_vertices(grad_e)
    gravity = torch.zeros_like(force)
    gravity[:, 2] = -g * mass
    return force + gravity


fused_rod_forces = Fused(rod_forces)
