"""Ground truth with contact the tracker's model does not know: the rope lies on or drags over a table,
or catches on a vertical post. Simulated with this project's own model of the rod, driven by the
gripper motion of a real recording, started from its first two frames.

- Table: the library's :class:`deform.terms.library.GroundContact` (penalty normal force and Coulomb
  friction) attached to a copy of the model, plus a hard floor after every step (a free vertex below
  the contact plane is put back on it, its downward velocity dropped): the penalty alone lets a rope
  falling at 1 m/s sink centimetres into the table at 10 ms steps.
- Post: a vertical cylinder; after every step each free edge closer to its axis than post radius +
  rope radius (below the top) is pushed out sideways, its two vertices weighted by where along the edge
  the contact is (an edge, not only its vertices: markers are 10 cm apart, the post is thinner).
  This force lives in the benchmark only, not in the model.

The plane of a table is where the rope's centreline rests: the table's surface is a rope radius below.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from benchmarks.tracking.metric import point_to_polyline
from deform import gripped_indices
from deform.terms import make_term


@dataclass
class Table:
    """A horizontal table whose surface is at ``surface_z``; the rope's centreline rests at
    ``surface_z + rope_radius``."""

    surface_z: float
    rope_radius: float = 0.005
    stiffness: float = 5000.0  # 1/s^2 of the penalty (GroundContact's k)
    friction: float = 0.5

    @property
    def plane_z(self) -> float:
        return self.surface_z + self.rope_radius


@dataclass
class Post:
    """A vertical cylinder at ``xy`` of ``radius`` from ``bottom_z`` up to ``top_z``."""

    xy: tuple[float, float]
    radius: float
    bottom_z: float
    top_z: float
    rope_radius: float = 0.005

    def mesh(self):
        from perception.render.mesh import cylinder

        return cylinder(np.asarray(self.xy), self.radius, self.bottom_z, self.top_z)


def _movable(n: int) -> np.ndarray:
    w = np.ones(n)
    w[gripped_indices(n)] = 0.0
    return w


def floor(x: np.ndarray, table: Table) -> np.ndarray:
    """Free vertices below the table's plane put on it (gripped ones are inputs, left alone)."""
    out = x.copy()
    free = _movable(len(x)) > 0
    out[free, 2] = np.maximum(out[free, 2], table.plane_z)
    return out


def push_out(x: np.ndarray, post: Post, sweeps: int = 4) -> np.ndarray:
    """Edges closer to the post's axis than its radius + the rope's (below the top) pushed out sideways."""
    out = x.copy()
    w = _movable(len(x))
    reach = post.radius + post.rope_radius
    c = np.asarray(post.xy, dtype=np.float64)
    for _ in range(sweeps):
        moved = False
        for i in range(len(out) - 1):
            wa, wb = w[i], w[i + 1]
            if wa == 0 and wb == 0:
                continue
            a, b = out[i], out[i + 1]
            e = b[:2] - a[:2]
            t = float(np.clip(np.dot(c - a[:2], e) / max(np.dot(e, e), 1e-12), 0.0, 1.0))
            q = a + t * (b - a)
            if q[2] > post.top_z or q[2] < post.bottom_z:
                continue
            d = q[:2] - c
            dist = float(np.linalg.norm(d))
            if dist >= reach:
                continue
            nrm = d / dist if dist > 1e-9 else np.array([1.0, 0.0])
            ga, gb = wa * (1 - t), wb * t
            s = (reach - dist) / max(ga * ga + gb * gb, 1e-9)
            out[i, :2] += ga * s * nrm
            out[i + 1, :2] += gb * s * nrm
            moved = True
        if not moved:
            break
    return out


def _constrain(x: np.ndarray, table: Table | None, post: Post | None) -> np.ndarray:
    if post is not None:
        x = push_out(x, post)
    if table is not None:
        x = floor(x, table)
    return x


def with_ground_contact(model, table: Table):
    """A copy of ``model`` carrying the library's ground-contact term at the table's plane."""
    m = copy.deepcopy(model)
    term = make_term("ground_contact", m.n, np.linspace(0.0, 1.0, m.n), {"lowest_z": table.plane_z - 0.002})
    with torch.no_grad():
        term.log_k.fill_(math.log(table.stiffness))
        term.raw_mu.fill_(math.log(table.friction / (1 - table.friction)))
    term.set_dt(m.dt)
    m.extensions.append(term)
    return m


@torch.no_grad()
def simulate(
    model, positions: np.ndarray, table: Table | None = None, post: Post | None = None
) -> np.ndarray:
    """(T, n, 3) the rope under ``model`` driven by the grippers of ``positions`` (T, n, 3), started from
    its first two frames, with a table and/or a post (None: neither, the reference).

    Args:
        model: the rod's :class:`deform.DeformModel` (not modified).
        positions: (T, n, 3) a recording: its gripped vertices drive the simulation.
        table: a :class:`Table` or None.
        post: a :class:`Post` or None.

    Returns:
        (T, n, 3) float64, frames 0 and 1 those of ``positions`` (constrained).
    """
    p = np.asarray(positions, dtype=np.float64)
    m = with_ground_contact(model, table) if table is not None else model
    gi = gripped_indices(m.n)
    x0, x1 = _constrain(p[0], table, post), _constrain(p[1], table, post)
    state = m.initial_state(torch.as_tensor(x0)[None], torch.as_tensor(x1)[None])
    out = [x0, x1]
    for k in range(2, len(p)):
        prev = state.x
        new = m.step(state, torch.as_tensor(p[k, gi])[None])
        x = new.x[0].numpy()
        fixed = _constrain(x, table, post)
        if not np.array_equal(fixed, x):
            xt = torch.as_tensor(fixed)[None]
            new = m.reposition(new, xt, (xt - prev) / m.dt)
            x = _constrain(new.x[0].numpy(), table, post)
            new = replace(new, x=torch.as_tensor(x)[None])
        state = new
        out.append(x.copy())
    return np.stack(out)


def place_table(reference: np.ndarray, quantile: float = 0.4, rope_radius: float = 0.005) -> Table:
    """A table under the rope of a contact-free run ``reference`` (T, n, 3): its plane at the
    ``quantile`` of the free rope's lowest point over the frames (so the rope would be below it that
    share of the time: it lies on it and drags over it), but below the first frames' rope and 1 cm
    below the grippers (which hold the rope and cannot be pushed).

    Args:
        reference: (T, n, 3) the same motion without contact.
        quantile: the share of frames the rope would reach below the plane.
        rope_radius: the rope's radius [m] (the surface is this much below the plane).

    Returns:
        The :class:`Table`.
    """
    n = reference.shape[1]
    free = _movable(n) > 0
    low = reference[:, free, 2].min(1)
    plane = min(float(np.quantile(low, quantile)), float(low[:2].min()) - 0.002)
    plane = min(plane, float(reference[:, ~free, 2].min()) - 0.01)
    return Table(surface_z=plane - rope_radius, rope_radius=rope_radius)


def place_post(
    reference: np.ndarray, dt: float, radius: float = 0.02, rope_radius: float = 0.005, clear_s: float = 0.3
) -> Post:
    """A post the rope of ``reference`` (T, n, 3) runs into: its axis where a middle vertex is at some
    time between 30 % and 70 % of the run, chosen so that the rope is clear of it for the first
    ``clear_s`` seconds (the most clearance when no time gives that), its top 15 cm above that vertex.

    Args:
        reference: (T, n, 3) the same motion without contact.
        dt: seconds per frame.
        radius: post radius [m].
        rope_radius: rope radius [m].
        clear_s: how long the rope must start clear of the post [s].

    Returns:
        The :class:`Post`.
    """
    T, n = reference.shape[:2]
    head = reference[: max(int(clear_s / dt), 2)]
    best, best_gap = None, -np.inf
    for frac in (0.4, 0.5, 0.6, 0.3, 0.7):
        k = int(frac * (T - 1))
        for i in (n // 2, n // 2 - 1, n // 2 + 1):
            xy = reference[k, i, :2]
            gap = min(
                float(point_to_polyline(np.array([[xy[0], xy[1], 0.0]]), f * np.array([1.0, 1.0, 0.0]))[0])
                for f in head
            )
            if gap > best_gap:
                best, best_gap = (xy, reference[k, i, 2]), gap
            if gap > radius + rope_radius + 0.02:
                return _post(xy, reference[k, i, 2], reference, radius, rope_radius)
    return _post(best[0], best[1], reference, radius, rope_radius)


def _post(xy, z, reference, radius, rope_radius) -> Post:
    bottom = float(reference[..., 2].min()) - 0.3
    return Post(
        xy=(float(xy[0]), float(xy[1])),
        radius=radius,
        bottom_z=bottom,
        top_z=float(z) + 0.15,
        rope_radius=rope_radius,
    )


def contact_fraction(x: np.ndarray, table: Table, tol: float = 0.003) -> float:
    """Share of frames in which some free vertex rests on the table (within ``tol`` of its plane)."""
    free = _movable(x.shape[1]) > 0
    return float(((x[:, free, 2] - table.plane_z) < tol).any(1).mean())


def post_contact_fraction(x: np.ndarray, post: Post, tol: float = 0.003) -> float:
    """Share of frames in which some edge (below the top) touches the post."""
    hits = 0
    for f in x:
        pushed = push_out(f, Post(post.xy, post.radius + tol, post.bottom_z, post.top_z, post.rope_radius), 1)
        hits += not np.array_equal(pushed, f)
    return hits / len(x)
