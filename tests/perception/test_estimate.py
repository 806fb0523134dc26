"""Segmentation, clustering, mixture fitting and one camera update, on rendered clouds with ground truth."""

import numpy as np
from sklearn.cluster import DBSCAN

from perception import load_config, render_recording
from perception.camera import Camera
from perception.cloud import depth_image, voxel_downsample
from perception.cluster import dbscan
from perception.estimate import (
    arc_centroid_offset,
    coherent_shift,
    correct_vertices,
    curvature_vector,
    hidden_only_by_the_model,
)
from perception.gmm import fit_gmm
from perception.polyline import segment_distances
from perception.render.mesh import catmull_rom
from perception.segment import segment_rope


def _movable(n):
    m = np.ones(n, dtype=bool)
    m[[0, 1, n - 2, n - 1]] = False
    return m


def test_segmentation_keeps_rope_only(recording):
    f = render_recording(recording.positions, steps=[60], seed=0)[0]
    cfg = load_config()
    pts = f.camera.to_world(segment_rope(f.xyz, f.rgb, cfg.segmentation))
    curve = catmull_rom(recording.positions[60], 8)
    assert len(pts) > 50
    assert np.percentile(segment_distances(pts, curve), 99) < 0.015  # on the tube, not the table
    # without colour the table is kept too
    everything = segment_rope(f.xyz, None, cfg.segmentation)
    assert len(everything) > 10 * len(pts)


def test_voxel_downsample_bounds_density():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 0.1, (5000, 3))
    out = voxel_downsample(pts, 0.02)
    assert len(out) <= 125 and len(out) > 100
    assert np.all(out >= 0) and np.all(out <= 0.1)


def test_dbscan_matches_sklearn():
    rng = np.random.default_rng(1)
    for _ in range(5):
        p = np.concatenate([rng.normal(c, 0.01, (60, 3)) for c in rng.uniform(0, 0.3, (3, 3))])
        ours, ref = dbscan(p, 0.02, 3), DBSCAN(eps=0.02, min_samples=3).fit_predict(p)
        assert np.array_equal(ours < 0, ref < 0)
        pairs = {(a, b) for a, b in zip(ours, ref) if a >= 0}
        assert len(pairs) == len(set(ours[ours >= 0])) == len(set(ref[ref >= 0]))


def test_gmm_moves_free_means_only():
    rng = np.random.default_rng(2)
    pts = np.concatenate([rng.normal([0, 0, 0], 0.005, (100, 3)), rng.normal([0.1, 0, 0], 0.005, (100, 3))])
    init = np.array([[0.02, 0.01, 0.0], [0.08, -0.01, 0.0]])
    mu, resp = fit_gmm(pts, init, np.array([True, False]), 0.02, 10)
    assert np.linalg.norm(mu[0]) < 0.003 and np.array_equal(mu[1], init[1])
    assert resp.shape == (200, 2) and np.allclose(resp.sum(1), 1)
    mu_sk, _ = fit_gmm(pts, init, np.array([True, True]), 0.02, 10, backend="sklearn")
    assert np.linalg.norm(mu_sk[1] - [0.1, 0, 0]) < 0.003


def _perturbed(recording, f, sd: float, seed: int):
    """(truth, a prediction with the free vertices off by ``sd``, rope points, depth image, config)
    for frame ``f``."""
    truth = recording.positions[f.step]
    n = len(truth)
    rng = np.random.default_rng(seed)
    pred = truth + np.concatenate([np.zeros((2, 3)), rng.normal(0, sd, (n - 4, 3)), np.zeros((2, 3))])
    cfg = load_config()
    pts = f.camera.to_world(segment_rope(f.xyz, f.rgb, cfg.segmentation))
    return truth, pred, pts, depth_image(f.xyz, f.camera), cfg


def test_update_moves_visible_and_keeps_occluded(recording, occluded_frames):
    f = [fr for fr in occluded_frames if fr.occluded][3]
    truth, pred, pts, depth, cfg = _perturbed(recording, f, 0.012, 4)
    x, observed = correct_vertices(pred, pts, depth, f.camera, cfg.estimation, _movable(len(truth)))
    assert observed.sum() >= 2
    assert not np.any(observed & ~f.visible)  # never claims a hidden vertex
    assert np.array_equal(x[~observed], pred[~observed])  # occluded ones keep the prediction
    err_before = np.linalg.norm(pred - truth, axis=1)[observed].mean()
    err_after = np.linalg.norm(x - truth, axis=1)[observed].mean()
    assert err_after < 0.6 * err_before


def test_a_correction_across_the_rope_only_has_no_share_along_it(recording, occluded_frames):
    """``along_rope`` 0: each corrected vertex moves perpendicular to the predicted rope at it (the
    camera shows where a featureless rope lies, not how far along it a vertex sits), and still
    towards the truth; 1 (the full shift) moves some along it."""
    from dataclasses import replace

    f = occluded_frames[0]
    truth, pred, pts, depth, cfg = _perturbed(recording, f, 0.01, 5)
    n = len(truth)
    tangent = pred[2:] - pred[:-2]
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)

    def along(x):
        return np.abs(((x - pred)[1:-1] * tangent).sum(1))

    across, obs = correct_vertices(
        pred, pts, depth, f.camera, replace(cfg.estimation, along_rope=0.0), _movable(n)
    )
    full, _ = correct_vertices(
        pred, pts, depth, f.camera, replace(cfg.estimation, along_rope=1.0), _movable(n)
    )
    assert obs.sum() >= 4 and along(across).max() < 1e-12 and along(full).max() > 1e-3
    # the true observed vertices' distance to the estimated rope: the error across it
    assert segment_distances(truth[obs], across).mean() < 0.6 * segment_distances(truth[obs], pred).mean()


def _arc(radius: float, angles: np.ndarray) -> np.ndarray:
    return radius * np.stack([np.sin(angles), 1.0 - np.cos(angles), np.zeros_like(angles)], axis=1)


def test_the_curvature_vector_of_a_circle_points_to_its_centre_one_over_the_radius_long():
    x = _arc(0.3, np.linspace(-0.4, 0.4, 9))  # centre at (0, 0.3, 0)
    k = curvature_vector(x, 4)
    assert np.allclose(k / np.linalg.norm(k), [0.0, 1.0, 0.0], atol=1e-9)
    assert abs(np.linalg.norm(k) - 1 / 0.3) < 0.01 / 0.3
    assert not curvature_vector(x, 0).any() and not curvature_vector(x[[0, 4, 8]] * [1, 0, 0], 1).any()


def test_the_centroid_of_an_arc_is_taken_back_to_the_rope_at_the_vertex():
    """Points spread over one 10 cm edge of a rope bent on a 30 cm radius: their centroid lies
    l^2 / (24 R) = 1.4 mm inside the bend; less the offset it is on the rope at the vertex."""
    radius, edge = 0.3, 0.1
    x = _arc(radius, np.arange(-2, 3) * edge / radius)  # vertices, the middle one at the origin
    points = _arc(radius, np.linspace(-0.5, 0.5, 201) * edge / radius)
    centroid = points.mean(0)
    assert abs(np.linalg.norm(centroid - x[2]) - edge**2 / (24 * radius)) < 1e-4
    offset = arc_centroid_offset(points, np.ones(len(points)), x, 2)
    assert np.linalg.norm(centroid - offset - x[2]) < 0.05 * np.linalg.norm(centroid - x[2])


def test_corrections_lose_the_pull_inside_the_bend(recording, clear_frames):
    """From a perfect prediction, the camera's correction of a bent rope errs towards the centre of
    the bend by the arc's centroid offset; ``bend_centroid`` 1 takes most of that back."""
    from dataclasses import replace

    cfg = load_config()
    inward = {}
    for share in (0.0, 1.0):
        est = replace(cfg.estimation, bend_centroid=share)
        errs = []
        for f in clear_frames[2::2]:
            truth = recording.positions[f.step]
            pts = f.camera.to_world(segment_rope(f.xyz, f.rgb, cfg.segmentation))
            x, obs = correct_vertices(
                truth, pts, depth_image(f.xyz, f.camera), f.camera, est, _movable(len(truth))
            )
            for i in np.flatnonzero(obs):
                k = curvature_vector(truth, i)
                if np.linalg.norm(k) > 1.0:  # radius under 1 m
                    errs.append((x[i] - truth[i]) @ k / np.linalg.norm(k))
        inward[share] = float(np.mean(errs))
    assert inward[0.0] > 5e-4 and abs(inward[1.0]) < 0.5 * inward[0.0], inward


def test_a_correction_that_moved_far_is_made_again_and_lands_closer(recording, clear_frames):
    """From a prediction 3 cm off, one EM pass stops short of the rope; ``repeat_beyond`` makes a
    second one from where the first ended."""
    from dataclasses import replace

    f = clear_frames[5]
    truth, pred, pts, depth, cfg = _perturbed(recording, f, 0.03, 6)
    n = len(truth)
    err = {}
    for reach in (0.0, 0.02):
        x, obs = correct_vertices(
            pred, pts, depth, f.camera, replace(cfg.estimation, repeat_beyond=reach), _movable(n)
        )
        assert obs.sum() >= 3
        err[reach] = segment_distances(truth[obs], x).mean()
    assert err[0.02] < 0.8 * err[0.0]


def test_coherent_shift_interpolates_between_corrected_neighbours_and_anchors():
    n = 9
    shift = np.zeros((n, 3))
    shift[2] = [0.0, 0.0, 0.02]
    shift[6] = [0.0, 0.0, 0.04]
    observed = np.zeros(n, bool)
    observed[[2, 6]] = True
    fill = _movable(n)
    fill[4] = False  # hidden: an anchor of shift 0
    out = coherent_shift(shift, observed, fill)
    assert np.allclose(out[3, 2], 0.01) and np.allclose(out[5, 2], 0.02)
    assert np.allclose(out[[0, 1, 2, 4, 6, 7, 8]], 0.0)  # gripped, hidden and observed ones get none
    assert np.allclose(coherent_shift(shift, np.zeros(n, bool), _movable(n)), 0.0)  # nothing seen, no shift


def test_a_vertex_hidden_by_what_its_neighbours_lie_on_is_told_from_one_behind_an_occluder():
    """The camera at the origin looking along +z; the rope lies at depth 1 m. Vertex 3 predicted
    6 cm deeper is hidden by a surface at the rope's own depth (a table under it): looked for. Behind
    an occluder 15 cm in front of the rope it stays hidden, and so does one whose neighbours were
    not seen."""
    cam = Camera.kinect()  # world = camera frame
    cfg = load_config().estimation
    n = 7
    x = np.stack([np.linspace(-0.15, 0.15, n), np.zeros(n), np.ones(n)], axis=1)
    pred = x.copy()
    pred[3, 2] += 0.06
    observed = np.ones(n, dtype=bool)
    observed[3] = False
    table = np.full((cam.height, cam.width), 1.0 + cfg.occlusion_margin / 2)  # a surface under the rope
    found = hidden_only_by_the_model(pred, x, observed, table, cam, cfg)
    assert found.tolist() == [False, False, False, True, False, False, False]
    occluder = np.full_like(table, 0.85)  # 15 cm in front of the rope
    assert not hidden_only_by_the_model(pred, x, observed, occluder, cam, cfg).any()
    alone = observed.copy()
    alone[[2, 4]] = False  # no seen neighbour to compare with
    assert not hidden_only_by_the_model(pred, x, alone, table, cam, cfg).any()
    assert not hidden_only_by_the_model(x, x, observed, table, cam, cfg).any()  # not hidden at all


def test_a_vertex_predicted_behind_the_rope_it_belongs_to_is_corrected(recording, clear_frames):
    """A vertex pushed 4 cm along its line of sight away from the camera is hidden by the rope's own
    near surface; ``unhide`` looks for it in the second pass and brings it back, without it the
    prediction stays."""
    from dataclasses import replace

    f = clear_frames[4]
    truth, pred, pts, depth, cfg = _perturbed(recording, f, 0.0, 0)
    i = len(truth) // 2
    ray = truth[i] - f.camera.position
    pred[i] = truth[i] + 0.04 * ray / np.linalg.norm(ray)
    out = {}
    for unhide in (False, True):
        x, obs = correct_vertices(
            pred, pts, depth, f.camera, replace(cfg.estimation, unhide=unhide), _movable(len(truth))
        )
        out[unhide] = (np.linalg.norm(x[i] - truth[i]), obs[i])
    assert abs(out[False][0] - 0.04) < 1e-9 and not out[False][1]
    assert out[True][1] and out[True][0] < 0.01, out


def test_a_stretch_predicted_behind_the_rope_comes_back_from_its_seen_ends(
    recording, clear_frames, monkeypatch
):
    """Three neighbouring vertices pushed 4 cm along their lines of sight: the second pass finds the
    two beside seen ones, the next the middle one, whose neighbours it has just seen (without that
    further pass it stays hidden)."""
    import perception.estimate as estimate

    f = clear_frames[4]
    truth, pred, pts, depth, cfg = _perturbed(recording, f, 0.0, 0)
    mid = len(truth) // 2
    for i in (mid - 1, mid, mid + 1):
        ray = truth[i] - f.camera.position
        pred[i] = truth[i] + 0.04 * ray / np.linalg.norm(ray)
    x, obs = correct_vertices(pred, pts, depth, f.camera, cfg.estimation, _movable(len(truth)))
    assert obs[mid - 1 : mid + 2].all()
    assert np.linalg.norm(x[mid - 1 : mid + 2] - truth[mid - 1 : mid + 2], axis=1).max() < 0.6 * 0.04
    monkeypatch.setattr(estimate, "MORE_UNHIDE_PASSES", 0)
    x, obs = correct_vertices(pred, pts, depth, f.camera, cfg.estimation, _movable(len(truth)))
    assert obs[[mid - 1, mid + 1]].all() and not obs[mid]
