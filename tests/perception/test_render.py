"""The renderer: organized clouds with sensor effects, and ground-truth visibility that follows the occluder."""

import numpy as np

from perception import Camera, camera_steps, render_recording
from perception.cloud import depth_image
from perception.render.mesh import catmull_rom
from tests.perception.conftest import occluded_config


def test_camera_steps_are_subsets_across_rates():
    s30, s10, s1 = (set(camera_steps(500, 0.01, f)) for f in (30, 10, 1))
    assert len(s30) == 150 and len(s10) == 50 and len(s1) == 5
    assert s1 <= s10 <= s30
    assert camera_steps(500, 0.01, 0) == []


def test_spline_passes_through_vertices():
    x = np.array([[0, 0, 0], [0.02, 0, 0], [0.1, 0.05, 0], [0.2, 0.0, 0.03], [0.25, 0, 0]], dtype=float)
    c = catmull_rom(x, samples_per_segment=6)
    assert np.allclose(c[::6], x)
    assert (
        np.linalg.norm(np.diff(c, axis=0), axis=1).sum()
        < 1.2 * np.linalg.norm(np.diff(x, axis=0), axis=1).sum()
    )


def test_cloud_format_and_seed(recording):
    a = render_recording(recording.positions, steps=[0, 50], seed=7)
    b = render_recording(recording.positions, steps=[0, 50], seed=7)
    f = a[0]
    cam = f.camera
    assert f.xyz.shape == (cam.height, cam.width, 3) and f.xyz.dtype == np.float32
    assert f.rgb.shape == (cam.height, cam.width, 3) and f.rgb.dtype == np.uint8
    missing = np.isnan(f.xyz[..., 2])
    assert 0.001 < missing.mean() < 0.9  # some dropouts/edges, mostly data
    assert np.all(f.rgb[missing] == 0)
    assert np.array_equal(a[1].xyz, b[1].xyz, equal_nan=True) and np.array_equal(a[1].rgb, b[1].rgb)
    # rope points are orange and lie on the rope: every free vertex is seen near its pixel
    n = len(f.visible)
    assert f.visible[2 : n - 2].all() and not f.visible[[0, n - 1]].any()  # ends are inside the gripper boxes


def test_visibility_follows_occluder(recording, occluded_frames):
    n = recording.positions.shape[1]
    before = [f for f in occluded_frames if not f.occluded]
    during = [f for f in occluded_frames if f.occluded]
    assert before and during
    assert all(f.visible[2 : n - 2].all() for f in before)
    hidden = np.array([1 - f.visible[2 : n - 2].mean() for f in during])
    assert 0.1 < hidden.mean() < 0.6
    # a hidden free vertex really has something in front of it in the depth image
    f = during[len(during) // 2]
    x = recording.positions[f.step]
    uv, z = f.camera.project(f.camera.to_camera(x))
    depth = depth_image(f.xyz, f.camera)
    for i in np.flatnonzero(~f.visible[2 : n - 2]) + 2:
        u, v = int(uv[i, 0]), int(uv[i, 1])
        patch = depth[v - 1 : v + 2, u - 1 : u + 2]
        assert np.nanmin(patch) < z[i] - 0.05


def test_occlusion_fraction_scales(recording):
    n = recording.positions.shape[1]
    hidden = []
    for frac in (0.2, 0.5):
        frames = render_recording(recording.positions, steps=[100, 150], config=occluded_config(frac), seed=2)
        hidden.append(np.mean([1 - f.visible[2 : n - 2].mean() for f in frames]))
    assert hidden[1] > hidden[0] > 0


def test_custom_camera_is_used(recording):
    from perception.config import load_config
    from perception.render import default_camera

    base = default_camera(recording.positions, load_config().render)
    cam = Camera(100.0, 100.0, 40.0, 30.0, 80, 60, base.world_from_camera)
    f = render_recording(recording.positions, steps=[0], camera=cam)[0]
    assert f.xyz.shape == (60, 80, 3)
