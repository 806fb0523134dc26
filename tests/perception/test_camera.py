"""The pinhole camera: an organized cloud gives back the intrinsics it was made with."""

import numpy as np

from perception import Camera, intrinsics_from_cloud


def test_an_organized_cloud_gives_back_its_intrinsics(clear_frames):
    """From a rendered frame (depth noise, dropouts, the background missing), and from the same cloud
    with its missing points as zeros; a shuffled cloud is no pinhole's, a nearly empty one too few."""
    f = clear_frames[0]
    cam = f.camera
    want = [cam.fx, cam.fy, cam.cx, cam.cy]
    np.testing.assert_allclose(intrinsics_from_cloud(f.xyz), want, atol=0.05)
    zeros = np.where(np.isfinite(f.xyz).all(-1, keepdims=True), f.xyz, 0.0)
    np.testing.assert_allclose(intrinsics_from_cloud(zeros), want, atol=0.05)
    wide = Camera(1.2 * cam.fx, cam.fy, cam.cx + 7, cam.cy - 3, cam.width, cam.height)
    rays = wide.ray_directions() * np.random.default_rng(0).uniform(0.5, 2.5, (cam.height, cam.width, 1))
    np.testing.assert_allclose(intrinsics_from_cloud(rays), [wide.fx, wide.fy, wide.cx, wide.cy], atol=1e-6)
    shuffled = f.xyz.reshape(-1, 3)[np.random.default_rng(1).permutation(cam.height * cam.width)]
    assert intrinsics_from_cloud(shuffled.reshape(f.xyz.shape)) is None
    few = np.full_like(f.xyz, np.nan)
    few[:5, :5] = f.xyz[:5, :5]
    assert intrinsics_from_cloud(few) is None
