"""Cloud utilities: the depth noise a cloud shows."""

import numpy as np

from perception.camera import Camera
from perception.cloud import depth_image, depth_noise, measured_depth


def _tilted_plane(h=200, w=240, z0=1.5, slope=0.002):
    """(h, w) depth of a plane tilted along rows and columns [m]."""
    rows, cols = np.mgrid[0:h, 0:w]
    return z0 + slope * cols + 0.5 * slope * rows


def test_the_noise_of_a_tilted_plane_is_measured():
    rng = np.random.default_rng(0)
    for sigma in (0.001, 0.004, 0.012):
        depth = _tilted_plane() + rng.normal(0.0, sigma, (200, 240))
        assert abs(depth_noise(depth, 1.0, 3.0) - sigma) < 0.1 * sigma


def test_edges_and_missing_pixels_are_not_noise():
    """A noiseless scene of steps (a rope in front of a table every 12 columns) and dropouts."""
    depth = _tilted_plane()
    depth[:, ::12] -= 0.3
    depth[::7, ::5] = np.nan
    assert depth_noise(depth, 1.0, 3.0) < 1e-6


def test_only_the_depths_asked_for_count():
    """Near pixels quiet, far ones noisy: measured at the near depths, the noise is the near one's."""
    rng = np.random.default_rng(1)
    depth = _tilted_plane(z0=1.0, slope=0.0)
    depth[:, 120:] = 2.5
    depth[:, :120] += rng.normal(0.0, 0.002, (200, 120))
    depth[:, 120:] += rng.normal(0.0, 0.02, (200, 120))
    assert abs(depth_noise(depth, 0.9, 1.1) - 0.002) < 0.0003
    assert depth_noise(depth, 2.4, 2.6) > 0.015


def test_too_few_pixels_give_no_estimate():
    depth = np.full((4, 4), 1.0)
    assert depth_noise(depth, 0.0, 5.0) == 0.0
    assert depth_noise(_tilted_plane(), 5.0, 6.0) == 0.0  # nothing at those depths


def test_every_drivers_missing_point_is_missing_depth():
    """NaN, (0, 0, 0) and +-inf all mean "no measurement"; a point on the optical axis is one."""
    xyz = np.array([[0.1, 0.2, 1.5], [np.nan] * 3, [0.0, 0.0, 0.0], [0.0, 0.0, np.inf], [0, 0, -np.inf],
                    [0.0, 0.0, 0.8], [0.0, 0.0, -0.5]])  # fmt: skip
    np.testing.assert_array_equal(measured_depth(xyz), [1.5, np.nan, np.nan, np.nan, np.nan, 0.8, np.nan])
    cam = Camera(100.0, 100.0, 1.5, 1.0, 3, 2, np.eye(4))
    depth = depth_image(xyz[1:].reshape(2, 3, 3), cam)
    assert depth.shape == (2, 3) and np.isfinite(depth).sum() == 1 and depth[1, 1] == 0.8


def test_an_unorganized_cloud_comes_back_on_its_image_grid():
    """A camera's cloud with the pixels without depth dropped and the rest shuffled into one row (as
    RealSense's pointcloud filter sends it) is put back pixel for pixel; where two points fall in one
    pixel the nearer is kept; zeros are no points."""
    from perception.cloud import organize_cloud

    cam = Camera(80.0, 80.0, 32.0, 24.0, 64, 48, np.eye(4))
    rng = np.random.default_rng(1)
    depth = 1.0 + 0.3 * rng.random((48, 64))
    depth[rng.random((48, 64)) < 0.2] = np.nan  # no return
    xyz = (cam.ray_directions() * depth[..., None]).astype(np.float32)
    rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    seen = np.isfinite(depth).ravel()
    order = rng.permutation(int(seen.sum()))
    flat_xyz, flat_rgb = xyz.reshape(-1, 3)[seen][order], rgb.reshape(-1, 3)[seen][order]
    got_xyz, got_rgb = organize_cloud(flat_xyz[None], flat_rgb[None], cam)
    np.testing.assert_array_equal(np.isnan(got_xyz[..., 2]), np.isnan(depth))
    np.testing.assert_array_equal(got_xyz[seen.reshape(48, 64)], xyz[seen.reshape(48, 64)])
    np.testing.assert_array_equal(got_rgb[seen.reshape(48, 64)], rgb[seen.reshape(48, 64)])
    behind = flat_xyz[:1] * 1.5  # on the first point's ray, farther: hidden by it
    zero = np.zeros((1, 3), np.float32)
    again, _ = organize_cloud(np.vstack([behind, flat_xyz, zero]), None, cam)
    np.testing.assert_array_equal(again, got_xyz)
