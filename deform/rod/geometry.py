r"""Discrete geometry of a rod: edges, curvature binormals, frames and their transport.

Shapes: vertices ``x`` are ``(..., n, 3)``; edges ``e_j = x_{j+1} - x_j`` are ``(..., m, 3)`` with
``m = n - 1``; interior vertices ``i = 1 .. n-2`` are indexed ``k = i - 1`` in ``(..., n-2, ...)``
arrays, with left edge ``k`` and right edge ``k + 1``.

Parallel transport of ``u`` from unit tangent ``a`` to unit tangent ``b`` is the rotation about
``a x b`` that takes ``a`` to ``b``; with ``c = a.b`` and ``w = a x b`` it is the branch-free
Rodrigues form  ``P u = c u + w x u + (w.u) w / (1 + c)``  (valid for ``c > -1``).
"""

from __future__ import annotations

import torch
from torch import Tensor


def edges(x: Tensor) -> Tensor:
    """Edge vectors ``e_j = x_{j+1} - x_j``.

    Args:
        x: (..., n, 3) vertices.

    Returns:
        (..., n-1, 3) edges.
    """
    return x[..., 1:, :] - x[..., :-1, :]


_EINSUM_ABOVE = 4096  # elements; measured crossover on 2 cores


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Dot product over the last (x, y, z) axis.

    torch reduces a 3-wide last axis slowly for large batches (3x slower than einsum at B = 1024) but
    einsum's overhead costs more for one rod.

    Args:
        a: (..., 3) vectors.
        b: (..., 3) vectors, broadcast against ``a``.

    Returns:
        (...) dot products.
    """
    if a.numel() > _EINSUM_ABOVE:
        return torch.einsum("...i,...i->...", a, b)
    return (a * b).sum(-1)


def normal_velocity(x: Tensor, v: Tensor) -> Tensor:
    """Vertex velocity across the rod: ``v - (v . t) t`` with central-difference unit tangents
    ``t`` (one-sided at the ends). What air drag acts on.

    Args:
        x: (..., n, 3) vertices [m].
        v: (..., n, 3) vertex velocities [m/s].

    Returns:
        (..., n, 3) the normal part of ``v``.
    """
    t = normalize(
        torch.cat(
            [
                x[..., 1:2, :] - x[..., :1, :],
                x[..., 2:, :] - x[..., :-2, :],
                x[..., -1:, :] - x[..., -2:-1, :],
            ],
            dim=-2,
        )
    )
    return v - dot(v, t).unsqueeze(-1) * t


def normalize(u: Tensor, eps: float = 1e-12) -> Tensor:
    """Unit vectors along the last axis.

    Args:
        u: (..., 3) vectors.
        eps: smallest norm divided by (zero vectors stay zero).

    Returns:
        (..., 3) ``u / |u|``.
    """
    return u / u.norm(dim=-1, keepdim=True).clamp_min(eps)


def parallel_transport(u: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """Transport ``u`` from unit tangent ``a`` to unit tangent ``b`` (minimal rotation; the
    module docstring gives the formula).

    Args:
        u: (..., 3) vectors to carry.
        a: (..., 3) unit tangents they belong to.
        b: (..., 3) unit tangents to carry them to.

    Returns:
        (..., 3) transported vectors.
    """
    c = dot(a, b).unsqueeze(-1)
    w = torch.linalg.cross(a, b, dim=-1)
    return c * u + torch.linalg.cross(w, u, dim=-1) + w * dot(w, u).unsqueeze(-1) / (1.0 + c).clamp_min(1e-9)


def curvature_binormal(e: Tensor) -> Tensor:
    """Curvature binormals ``kb_i = 2 e_{i-1} x e_i / (|e_{i-1}| |e_i| + e_{i-1}.e_i)`` at interior
    vertices; ``|kb| = 2 tan(phi/2)`` with ``phi`` the turning angle.

    Args:
        e: (..., m, 3) edges.

    Returns:
        (..., m-1, 3) one per interior vertex.
    """
    e0, e1 = e[..., :-1, :], e[..., 1:, :]
    denom = e0.norm(dim=-1) * e1.norm(dim=-1) + dot(e0, e1)
    return 2.0 * torch.linalg.cross(e0, e1, dim=-1) / denom.clamp_min(1e-12).unsqueeze(-1)


def any_perpendicular(t: Tensor) -> Tensor:
    """A unit vector perpendicular to each unit ``t`` (smooth away from the switch between helpers).

    Args:
        t: (..., 3) unit vectors.

    Returns:
        (..., 3) unit vectors perpendicular to them.
    """
    ex = torch.zeros_like(t)
    ex[..., 0] = 1.0
    ey = torch.zeros_like(t)
    ey[..., 1] = 1.0
    helper = torch.where((t[..., 0].abs() < 0.9).unsqueeze(-1), ex, ey)
    return normalize(helper - dot(helper, t).unsqueeze(-1) * t)


def up_perpendicular(t: Tensor) -> Tensor:
    """The world up direction (+z) made perpendicular to ``t``; ``any_perpendicular`` where ``t`` is vertical.

    Args:
        t: (..., 3) unit tangents.

    Returns:
        (..., 3) unit vectors perpendicular to ``t``.
    """
    up = torch.zeros_like(t)
    up[..., 2] = 1.0
    d = up - dot(up, t).unsqueeze(-1) * t
    ok = d.norm(dim=-1, keepdim=True) > 1e-3
    return torch.where(ok, normalize(d), any_perpendicular(t))


def space_parallel_frame(t: Tensor) -> Tensor:
    """Reference directors ``d1``: up at edge 0, parallel-transported along the rod.

    Its reference twist is zero, the natural twist-free start for a recording whose twist we cannot
    observe; starting from "up" (not an arbitrary perpendicular) gives every recording the same
    convention, so that a rest curvature identified in the material frame means the same thing in all.

    Args:
        t: (..., m, 3) unit edge tangents.

    Returns:
        (..., m, 3) unit directors, each perpendicular to its edge.
    """
    d1 = [up_perpendicular(t[..., 0, :])]
    for j in range(1, t.shape[-2]):
        d1.append(normalize(parallel_transport(d1[-1], t[..., j - 1, :], t[..., j, :])))
    return torch.stack(d1, dim=-2)


def time_transport(d1_prev: Tensor, t_prev: Tensor, t: Tensor) -> Tensor:
    """Carry the reference director of every edge from last step's tangent to the current one.

    Args:
        d1_prev: (..., m, 3) directors at the last step.
        t_prev: (..., m, 3) unit tangents at the last step.
        t: (..., m, 3) unit tangents now.

    Returns:
        (..., m, 3) directors now, perpendicular to ``t``.
    """
    d1 = parallel_transport(d1_prev, t_prev, t)
    return normalize(d1 - dot(d1, t).unsqueeze(-1) * t)  # remove round-off drift


def transported_frames(x: Tensor) -> Tensor:
    """Reference directors of a recorded motion as an open-loop rollout from its first two frames
    carries them: space-parallel at frame 1, then transported in time along the recorded edges (frame
    0 repeats frame 1; it only gives a rollout its rest lengths).

    The grippers' roll is not observed, so the model's convention is "no roll in a frame transported
    in time". A window cut from the middle of a recording (training, diagnosis) must start in these
    directors, not in fresh space-parallel ones: those differ by the holonomy the motion has
    accumulated, and the material frame (in which the rest curvature and the twist live) with them.

    Args:
        x: (T, n, 3) recorded vertices.

    Returns:
        (T, n-1, 3) directors per frame and edge.
    """
    t = normalize(edges(x))
    out = torch.empty_like(t)
    out[0] = space_parallel_frame(t[1])
    if len(t) > 1:
        out[1] = out[0]
    for k in range(2, len(t)):
        out[k] = time_transport(out[k - 1], t[k - 1], t[k])
    return out


def reference_twist(d1: Tensor, t: Tensor) -> Tensor:
    """Signed angle at each interior vertex from the transported ``d1_{i-1}`` to ``d1_i`` about ``t_i``.

    Args:
        d1: (..., m, 3) reference directors.
        t: (..., m, 3) unit tangents.

    Returns:
        (..., m-1) angles [rad].
    """
    u = parallel_transport(d1[..., :-1, :], t[..., :-1, :], t[..., 1:, :])
    v = d1[..., 1:, :]
    sin = dot(torch.linalg.cross(u, v, dim=-1), t[..., 1:, :])
    cos = dot(u, v)
    return torch.atan2(sin, cos)


def voronoi_lengths(edge_lengths: Tensor) -> Tensor:
    """``l_i = |e_{i-1}| + |e_i|`` at interior vertices (twice the Voronoi length, DER convention).

    Args:
        edge_lengths: (..., m) lengths [m].

    Returns:
        (..., m-1) one per interior vertex.
    """
    return edge_lengths[..., :-1] + edge_lengths[..., 1:]
