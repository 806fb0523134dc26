r"""Discrete geometry of a rod: edges, curvature binormals, frames and their transport.

Layout (vertex-major, :mod:`deform.rod.layout`): the rod's own axes first and the batch of rods as
the last axis, so compiled loops run over the rods innermost (vectorised across rods). Vertices
``x`` are ``(n, 3, B)``; edges ``e_j = x_{j+1} - x_j`` are ``(m, 3, B)`` with ``m = n - 1``; interior
vertices ``i = 1 .. n-2`` are indexed ``k = i - 1`` in ``(n-2, ...)`` arrays, with left edge ``k``
and right edge ``k + 1``. A vector's x, y, z are axis -2; per-vertex or per-edge scalars are
``(k, B)``.

Parallel transport of ``u`` from unit tangent ``a`` to unit tangent ``b`` is the rotation about
``a x b`` that takes ``a`` to ``b``; with ``c = a.b`` and ``w = a x b`` it is the branch-free
Rodrigues form  ``P u = c u + w x u + (w.u) w / (1 + c)``  (valid for ``c > -1``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from deform.rod.layout import batch_major, vertex_major


def edges(x: Tensor) -> Tensor:
    """Edge vectors ``e_j = x_{j+1} - x_j``.

    Args:
        x: (n, 3, B) vertices.

    Returns:
        (n-1, 3, B) edges.
    """
    return x[1:] - x[:-1]


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Dot product over the x, y, z axis (-2).

    Args:
        a: (..., 3, B) vectors.
        b: (..., 3, B) vectors, broadcast against ``a``.

    Returns:
        (..., B) dot products.
    """
    return (a * b).sum(-2)


def cross(a: Tensor, b: Tensor) -> Tensor:
    """Cross product over the x, y, z axis (-2).

    Args:
        a: (..., 3, B) vectors.
        b: (..., 3, B) vectors.

    Returns:
        (..., 3, B) ``a x b``.
    """
    return torch.linalg.cross(a, b, dim=-2)


def norm(u: Tensor, keepdim: bool = False) -> Tensor:
    """Euclidean length over the x, y, z axis (-2).

    The square root of a sum, not ``torch.linalg.vector_norm``: eager, that reduction over a
    middle axis took 10x as long (a quarter of an eager step of 32 rods). The floor under the
    square makes the gradient of a zero vector's length 0 (as the norm's subgradient), not NaN.

    Args:
        u: (..., 3, B) vectors.
        keepdim: keep the axis (as size 1).

    Returns:
        (..., B), or (..., 1, B) with ``keepdim``.
    """
    return (u * u).sum(-2, keepdim=keepdim).clamp_min(1e-30).sqrt()


def normal_velocity(x: Tensor, v: Tensor) -> Tensor:
    """Vertex velocity across the rod: ``v - (v . t) t`` with central-difference unit tangents
    ``t`` (one-sided at the ends). What air drag acts on.

    Args:
        x: (n, 3, B) vertices [m].
        v: (n, 3, B) vertex velocities [m/s].

    Returns:
        (n, 3, B) the normal part of ``v``.
    """
    t = normalize(torch.cat([x[1:2] - x[:1], x[2:] - x[:-2], x[-1:] - x[-2:-1]]))
    return v - dot(v, t).unsqueeze(-2) * t


def normalize(u: Tensor, eps: float = 1e-12) -> Tensor:
    """Unit vectors along the x, y, z axis.

    Args:
        u: (..., 3, B) vectors.
        eps: smallest norm divided by (zero vectors stay zero).

    Returns:
        (..., 3, B) ``u / |u|``.
    """
    return u / norm(u, keepdim=True).clamp_min(eps)


def parallel_transport(u: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """Transport ``u`` from unit tangent ``a`` to unit tangent ``b`` (minimal rotation; the
    module docstring gives the formula).

    Args:
        u: (..., 3, B) vectors to carry.
        a: (..., 3, B) unit tangents they belong to.
        b: (..., 3, B) unit tangents to carry them to.

    Returns:
        (..., 3, B) transported vectors.
    """
    c = dot(a, b).unsqueeze(-2)
    w = cross(a, b)
    return c * u + cross(w, u) + w * dot(w, u).unsqueeze(-2) / (1.0 + c).clamp_min(1e-9)


def curvature_binormal(e: Tensor) -> Tensor:
    """Curvature binormals ``kb_i = 2 e_{i-1} x e_i / (|e_{i-1}| |e_i| + e_{i-1}.e_i)`` at interior
    vertices; ``|kb| = 2 tan(phi/2)`` with ``phi`` the turning angle.

    Args:
        e: (m, 3, B) edges.

    Returns:
        (m-1, 3, B) one per interior vertex.
    """
    e0, e1 = e[:-1], e[1:]
    denom = norm(e0) * norm(e1) + dot(e0, e1)
    return 2.0 * cross(e0, e1) / denom.clamp_min(1e-12).unsqueeze(-2)


def _axis(t: Tensor, k: int) -> Tensor:
    """The unit vector along world axis ``k``, shaped as ``t`` (..., 3, B)."""
    out = torch.zeros_like(t)
    out[..., k, :] = 1.0
    return out


def any_perpendicular(t: Tensor) -> Tensor:
    """A unit vector perpendicular to each unit ``t`` (smooth away from the switch between helpers).

    Args:
        t: (..., 3, B) unit vectors.

    Returns:
        (..., 3, B) unit vectors perpendicular to them.
    """
    helper = torch.where((t[..., 0, :].abs() < 0.9).unsqueeze(-2), _axis(t, 0), _axis(t, 1))
    return normalize(helper - dot(helper, t).unsqueeze(-2) * t)


def up_perpendicular(t: Tensor) -> Tensor:
    """The world up direction (+z) made perpendicular to ``t``; ``any_perpendicular`` where ``t`` is vertical.

    Args:
        t: (..., 3, B) unit tangents.

    Returns:
        (..., 3, B) unit vectors perpendicular to ``t``.
    """
    up = _axis(t, 2)
    d = up - dot(up, t).unsqueeze(-2) * t
    ok = norm(d, keepdim=True) > 1e-3
    return torch.where(ok, normalize(d), any_perpendicular(t))


def space_parallel_frame(t: Tensor) -> Tensor:
    """Reference directors ``d1``: up at edge 0, parallel-transported along the rod.

    Its reference twist is zero, the natural twist-free start for a recording whose twist we cannot
    observe; starting from "up" (not an arbitrary perpendicular) gives every recording the same
    convention, so that a rest curvature identified in the material frame means the same thing in all.

    Args:
        t: (m, 3, B) unit edge tangents.

    Returns:
        (m, 3, B) unit directors, each perpendicular to its edge.
    """
    d1 = [up_perpendicular(t[0])]
    for j in range(1, t.shape[0]):
        d1.append(normalize(parallel_transport(d1[-1], t[j - 1], t[j])))
    return torch.stack(d1)


def time_transport(d1_prev: Tensor, t_prev: Tensor, t: Tensor) -> Tensor:
    """Carry the reference director of every edge from last step's tangent to the current one.

    Args:
        d1_prev: (m, 3, B) directors at the last step.
        t_prev: (m, 3, B) unit tangents at the last step.
        t: (m, 3, B) unit tangents now.

    Returns:
        (m, 3, B) directors now, perpendicular to ``t``.
    """
    d1 = parallel_transport(d1_prev, t_prev, t)
    return normalize(d1 - dot(d1, t).unsqueeze(-2) * t)  # remove round-off drift


def transported_frames(x: Tensor) -> Tensor:
    """Reference directors of a recorded motion as an open-loop rollout from its first two frames
    carries them: space-parallel at frame 1, then transported in time along the recorded edges (frame
    0 repeats frame 1; it only gives a rollout its rest lengths).

    The grippers' roll is not observed, so the model's convention is "no roll in a frame transported
    in time". A window cut from the middle of a recording (training, diagnosis) must start in these
    directors, not in fresh space-parallel ones: those differ by the holonomy the motion has
    accumulated, and the material frame (in which the rest curvature and the twist live) with them.

    Args:
        x: (T, n, 3) recorded vertices (frames first, as recordings are stored).

    Returns:
        (T, n-1, 3) directors per frame and edge.
    """
    t = normalize(edges(vertex_major(x, 2, x.shape[:1])))  # frames as the batch: (m, 3, T)
    frames = [space_parallel_frame(t[..., 1:2])]
    if t.shape[-1] > 1:
        frames.append(frames[0])
    for k in range(2, t.shape[-1]):
        frames.append(time_transport(frames[-1], t[..., k - 1 : k], t[..., k : k + 1]))
    return batch_major(torch.cat(frames, dim=-1), x.shape[:1])


def reference_twist(d1: Tensor, t: Tensor) -> Tensor:
    """Signed angle at each interior vertex from the transported ``d1_{i-1}`` to ``d1_i`` about ``t_i``.

    Args:
        d1: (m, 3, B) reference directors.
        t: (m, 3, B) unit tangents.

    Returns:
        (m-1, B) angles [rad].
    """
    u = parallel_transport(d1[:-1], t[:-1], t[1:])
    v = d1[1:]
    return torch.atan2(dot(cross(u, v), t[1:]), dot(u, v))


def voronoi_lengths(edge_lengths: Tensor) -> Tensor:
    """``l_i = |e_{i-1}| + |e_i|`` at interior vertices (twice the Voronoi length, DER convention).

    Args:
        edge_lengths: (m, B) lengths [m].

    Returns:
        (m-1, B) one per interior vertex.
    """
    return edge_lengths[:-1] + edge_lengths[1:]
