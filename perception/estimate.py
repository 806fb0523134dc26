"""One camera update of the vertex estimates (the state estimation of the DEFORM paper).

1. voxel-downsample the rope points and keep those near the predicted rod;
2. a predicted vertex is occluded when the scene at its pixel is clearly closer than the vertex;
3. DBSCAN groups the remaining points; each unoccluded vertex joins the group of its nearest point;
4. one Gaussian mixture per group, a component per associated vertex, means initialised at the
   predictions (neighbours not associated are fixed components, so they take their share of points);
5. observed vertices move to their component means, pushed back by the rope radius (the camera sees
   the near surface); occluded ones keep the prediction here (the tracker then moves them with their
   corrected neighbours, ``tracker.hidden_coherence``);
6. when that moved a vertex farther than ``repeat_beyond``, or left hidden a vertex that only the
   model's error hid (:func:`hidden_only_by_the_model`: the surface in front of it is no closer than
   its seen neighbours, as when a model that knows no table puts it below one), steps 2-5 again from
   where it ended, looking for that vertex too; up to ``MORE_UNHIDE_PASSES`` more while a pass finds
   such vertices and their hidden neighbours now have seen ones (a stretch inside the table).

A refinement of our own: a component's mean is the centroid of the rope around its vertex, which on
a bent rope lies inside the bend (1-2 mm for 10 cm edges on a 30 cm radius); it is taken back to the
rope at the vertex (:func:`arc_centroid_offset`, ``bend_centroid``).

Refinements over the paper, all for bias near occlusion borders: a vertex counts as observed only
with enough points on both sides of it along the rope, and corrections larger than ``max_shift``
are refused.
"""

from __future__ import annotations

import numpy as np

from perception.camera import Camera
from perception.cloud import voxel_downsample, window_min
from perception.cluster import dbscan
from perception.config import EstimationConfig
from perception.gmm import fit_gmm
from perception.polyline import segment_distances

MAX_SHIFT = 0.1
MORE_UNHIDE_PASSES = 2  # passes beyond the second while they find vertices hidden only by the model


def _seen_depth(x_world: np.ndarray, depth: np.ndarray, camera: Camera, cfg: EstimationConfig):
    """``(seen, z, inside)``: the nearest depth the image shows around each vertex's pixel, the
    vertex's own depth [m] and whether its pixel lies in the image."""
    uv, z = camera.project(camera.to_camera(x_world))
    seen = window_min(depth, uv, cfg.occlusion_window)
    inside = (
        (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    )
    return seen, z, inside


def occluded_vertices(
    x_world: np.ndarray, depth: np.ndarray, camera: Camera, cfg: EstimationConfig
) -> np.ndarray:
    """(n,) True where something in the depth image is ``occlusion_margin`` closer than the vertex,
    or where the vertex is outside the image (not observable).

    Args:
        x_world: (n, 3) predicted vertices, world frame [m].
        depth: (H, W) observed depth image [m], NaN where unknown.
        camera: the camera.
        cfg: the estimation settings (``occlusion_margin``, ``occlusion_window``).

    Returns:
        (n,) bool.
    """
    seen, z, inside = _seen_depth(x_world, depth, camera, cfg)
    closer = np.isfinite(seen) & (seen < z - cfg.occlusion_margin)
    return closer | ~inside


def hidden_only_by_the_model(
    x_pred: np.ndarray,
    x_new: np.ndarray,
    observed: np.ndarray,
    depth: np.ndarray,
    camera: Camera,
    cfg: EstimationConfig,
) -> np.ndarray:
    """(n,) True at an unobserved vertex that the occlusion check hid at ``x_pred`` although what
    hides it is no closer to the camera than its observed neighbours as corrected (``x_new``), less
    ``occlusion_margin``.

    An occluder lies between the camera and the rope, so it is closer than the rope's seen
    neighbours too. A surface at the neighbours' depth or beyond is one the rope lies on or beside
    (a table, a post the model does not know) with the vertex predicted inside it: the camera can see
    that vertex, and the correction should look for it."""
    n = len(x_pred)
    out = np.zeros(n, dtype=bool)
    seen, z, inside = _seen_depth(x_pred, depth, camera, cfg)
    hidden = inside & np.isfinite(seen) & (seen < z - cfg.occlusion_margin) & ~observed
    if not hidden.any():
        return out
    _, z_new = camera.project(camera.to_camera(x_new))
    for i in np.flatnonzero(hidden):
        near = [j for j in (i - 1, i + 1) if 0 <= j < n and observed[j]]
        out[i] = bool(near) and seen[i] >= min(z_new[j] for j in near) - cfg.occlusion_margin
    return out


def _tangent(x: np.ndarray, i: int) -> tuple[np.ndarray, float]:
    """The rope's unit tangent at vertex ``i`` of ``x`` (n, 3), along the central difference
    :math:`x_{i+1} - x_{i-1}` (one-sided at the ends; zero when that vanishes), and that chord's length."""
    t = x[min(i + 1, len(x) - 1)] - x[max(i - 1, 0)]
    chord = float(np.linalg.norm(t))
    return (np.zeros(3) if chord < 1e-12 else t / chord), chord


def _two_sided(points, resp, j, x_pred, idx, frac) -> bool:
    """Does component ``j`` (vertex ``idx``) own points on both sides of the vertex along the rope?"""
    mine = points[resp.argmax(1) == j]
    if len(mine) == 0:
        return False
    tang, chord = _tangent(x_pred, idx)
    half = 0.25 * chord  # half of the mean edge length
    s = (mine - x_pred[idx]) @ tang
    return bool(s.max() > frac * half and s.min() < -frac * half)


def along_rope(shift: np.ndarray, x: np.ndarray, i: int) -> np.ndarray:
    """The component of ``shift`` along the rope at vertex ``i`` of ``x`` (n, 3): along the central
    difference :math:`x_{i+1} - x_{i-1}` (one-sided at the ends)."""
    t, _ = _tangent(x, i)
    return (shift @ t) * t


def curvature_vector(x: np.ndarray, i: int) -> np.ndarray:
    r"""The discrete curvature vector at inner vertex ``i`` of the polyline ``x`` (n, 3): the second
    derivative of the curve by arc length, pointing to the centre of the bend, of length 1 / radius:
    :math:`\kappa_i = \frac{2}{l_0 + l_1} (e_1 / l_1 - e_0 / l_0)` with :math:`e_0 = x_i - x_{i-1}`,
    :math:`e_1 = x_{i+1} - x_i`. Zero at the ends."""
    if i <= 0 or i >= len(x) - 1:
        return np.zeros(3)
    e0, e1 = x[i] - x[i - 1], x[i + 1] - x[i]
    l0, l1 = np.linalg.norm(e0), np.linalg.norm(e1)
    if l0 < 1e-12 or l1 < 1e-12:
        return np.zeros(3)
    return 2.0 / (l0 + l1) * (e1 / l1 - e0 / l0)


def arc_centroid_offset(points: np.ndarray, weights: np.ndarray, x: np.ndarray, i: int) -> np.ndarray:
    r"""How far inside the bend the weighted centroid of rope points around vertex ``i`` lies from the
    rope at the vertex. Near the vertex the rope is :math:`p(s) = x_i + t s + \tfrac12 \kappa s^2`
    (tangent ``t``, curvature vector :math:`\kappa`, :func:`curvature_vector` of ``x``), so the
    centroid of points at arc lengths ``s`` from the vertex sits
    :math:`\tfrac12 \kappa \langle s^2 \rangle` towards the centre of the bend (for points
    spread evenly over an edge length ``l``: :math:`\kappa l^2 / 24`, 1.4 mm for 10 cm edges on a
    30 cm radius). Subtract it from the centroid to get the vertex."""
    total = weights.sum()
    if total <= 0:
        return np.zeros(3)
    t, _ = _tangent(x, i)
    s = (points - x[i]) @ t  # arc length from the vertex, to first order
    return 0.5 * curvature_vector(x, i) * (weights @ (s * s)) / total


def coherent_shift(shift: np.ndarray, observed: np.ndarray, fill: np.ndarray) -> np.ndarray:
    """(n, 3) shifts for the vertices ``fill`` that were not observed: the ``shift`` (n, 3) of the
    observed vertices interpolated linearly by vertex index; every vertex neither observed nor in
    ``fill`` (a gripped or a hidden one) is an anchor of shift 0. Zero elsewhere.

    The motion coherence of point-set trackers (CPD, TrackDLO) for the one case where our model's
    prediction is the worse guess: a vertex the camera sees but the correction could not associate
    (the model lost hold of the rope there), between neighbours that the camera moved."""
    n = len(shift)
    fill = fill & ~observed
    anchors = np.flatnonzero(~fill)
    out = np.zeros((n, 3))
    targets = np.flatnonzero(fill)
    if len(targets) == 0 or len(anchors) == 0:
        return out
    known = np.where(observed[:, None], shift, 0.0)[anchors]
    for d in range(3):
        out[targets, d] = np.interp(targets, anchors, known[:, d])
    return out


def correct_vertices(
    x_pred: np.ndarray,
    rope_world: np.ndarray,
    depth: np.ndarray,
    camera: Camera,
    cfg: EstimationConfig,
    movable: np.ndarray,
    backend: str = "numpy",
) -> tuple[np.ndarray, np.ndarray]:
    """Corrected vertices (n, 3) and observed flags (n,) from rope points in the world frame.

    DBSCAN groups of the points near the prediction, a GMM per group with the group's visible
    vertices as components; only observed, movable vertices move.

    Args:
        x_pred: (n, 3) predicted vertices, world frame [m].
        rope_world: (N, 3) segmented rope points, world frame [m].
        depth: (H, W) depth image for the occlusion check [m].
        camera: the camera.
        cfg: the estimation settings.
        movable: (n,) bool, vertices that may be corrected (not the gripped ones).
        backend: ``"numpy"`` (the EM here) or ``"sklearn"``.

    Returns:
        ``(x, observed)``: x (n, 3), observed (n,) bool.
    """
    x_new, observed = _correct_once(x_pred, rope_world, depth, camera, cfg, movable, backend)
    if not observed.any():
        return x_new, observed
    far = cfg.repeat_beyond > 0 and np.linalg.norm(x_new - x_pred, axis=1)[observed].max() > cfg.repeat_beyond
    unhide = np.zeros(len(x_pred), dtype=bool)
    if cfg.unhide:
        unhide = movable & hidden_only_by_the_model(x_pred, x_new, observed, depth, camera, cfg)
    if far or unhide.any():
        x_new, again = _correct_once(x_new, rope_world, depth, camera, cfg, movable, backend, unhide)
        observed = observed | again
        for _ in range(MORE_UNHIDE_PASSES):  # a stretch comes back a vertex a pass from its seen ends
            if not (again & unhide).any():  # the last pass found none of those it looked for
                break
            more = movable & hidden_only_by_the_model(x_pred, x_new, observed, depth, camera, cfg)
            if not more.any():
                break
            unhide = unhide | more
            x_new, again = _correct_once(x_new, rope_world, depth, camera, cfg, movable, backend, unhide)
            observed = observed | again
    return x_new, observed


def _correct_once(x_pred, rope_world, depth, camera, cfg, movable, backend, unhide=None):
    """One pass of :func:`correct_vertices` from ``x_pred``; ``unhide``: vertices to look for even
    where the occlusion check hides them."""
    n = len(x_pred)
    x_new = x_pred.copy()
    observed = np.zeros(n, dtype=bool)
    pts = voxel_downsample(rope_world, cfg.voxel)
    if len(pts) == 0:
        return x_new, observed
    pts = pts[segment_distances(pts, x_pred) < cfg.filter_radius]
    if len(pts) < cfg.dbscan_min_samples:
        return x_new, observed
    candidate = movable & ~occluded_vertices(x_pred, depth, camera, cfg)
    if unhide is not None:
        candidate |= movable & unhide
    labels = dbscan(pts, cfg.dbscan_eps, cfg.dbscan_min_samples)
    d = np.linalg.norm(pts[None] - x_pred[:, None], axis=-1)  # (n, N)
    nearest = d.argmin(1)
    group = np.where((d.min(1) < cfg.assoc_radius) & (labels[nearest] >= 0), labels[nearest], -1)
    eye = camera.position
    for g in np.unique(group[candidate & (group >= 0)]):
        members = np.flatnonzero(candidate & (group == g))
        neighbours = sorted({j for i in members for j in (i - 1, i + 1) if 0 <= j < n} - set(members))
        comps = np.array(list(members) + neighbours)
        free = np.zeros(len(comps), dtype=bool)
        free[: len(members)] = True
        gp = pts[labels == g]
        mu, resp = fit_gmm(gp, x_pred[comps], free, cfg.gmm_sigma, cfg.gmm_iters, backend)
        mass = resp.sum(0)
        for j, i in enumerate(members):
            if mass[j] < cfg.min_points or not _two_sided(gp, resp, j, x_pred, i, cfg.two_sided):
                continue
            ray = mu[j] - eye
            at = mu[j] - cfg.bend_centroid * arc_centroid_offset(gp, resp[:, j], x_pred, i)
            shift = at + cfg.surface_offset * ray / max(np.linalg.norm(ray), 1e-12) - x_pred[i]
            if cfg.along_rope < 1:
                shift = shift - (1 - cfg.along_rope) * along_rope(shift, x_pred, i)
            if np.linalg.norm(shift) > MAX_SHIFT or not np.all(np.isfinite(shift)):
                continue
            x_new[i] = x_pred[i] + shift
            observed[i] = True
    return x_new, observed
