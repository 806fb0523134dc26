"""The MuJoCo planted-effect generator (benchmarks/planted/mujoco.py) on small synthetic gripper
motions: no dataset needed; skipped without MuJoCo (the `bench` extra)."""

import numpy as np
import pytest

pytest.importorskip("mujoco")

from benchmarks.planted.mujoco import detectability, generate_mujoco
from deform.model import gripped_indices
from tests.benchmarks.swaying_rope import SPEC, WINDOW, N, swaying_source

pytestmark = pytest.mark.slow  # a few seconds of rope integration

G = gripped_indices(N)
INNER = [k for k in range(N) if k not in G]


@pytest.fixture(scope="module")
def sources():
    return [swaying_source(0.0), swaying_source(1.0)]


@pytest.fixture(scope="module")
def control(sources):
    return generate_mujoco(None, sources, SPEC, "light", n_frames=WINDOW, seed=0)


def test_control_is_a_hanging_rope_held_by_its_grippers(sources, control):
    recs, truth = control
    assert truth["effect"] is None and truth["rod_kind"] == "light"
    assert [r.name for r in recs] == ["mujoco_light_control_0_0", "mujoco_light_control_0_1"]
    for rec, src, start in zip(recs, sources, truth["numerics"]["starts"]):
        p = rec.positions
        assert p.shape == (WINDOW, N, 3) and np.all(np.isfinite(p))
        # the gripped markers are the recorded inputs (plus the same 0.3 mm noise as the others)
        assert np.abs(p[:, G] - src.positions[start : start + WINDOW][:, G]).max() < 2e-3
        # hangs in a U: every inner marker below the grippers, the middle lowest
        assert np.all(p[:, INNER, 2] < p[:, G, 2].min(axis=1, keepdims=True))
        assert p[:, N // 2 - 1 : N // 2 + 1, 2].mean() < p[:, INNER, 2].mean()
        # material points of a chain of rigid links: neighbouring inner markers keep their distance
        e = np.linalg.norm(np.diff(p[:, INNER], axis=1), axis=-1)
        assert np.all(np.abs(e / np.median(e, axis=0) - 1) < 0.03)
    assert truth["numerics"]["max_grip_error_m"] < 1e-3  # the welded grips follow their targets


def test_gripped_markers_are_the_recorded_inputs_without_noise(sources):
    recs, truth = generate_mujoco(None, sources[:1], SPEC, "light", n_frames=10, seed=3, noise_m=0.0)
    start = truth["numerics"]["starts"][0]
    np.testing.assert_array_equal(recs[0].positions[:, G], sources[0].positions[start : start + 10][:, G])


def test_planted_wind_moves_markers_more_than_noise(sources, control):
    recs, truth = generate_mujoco("external_force", sources, SPEC, "light", n_frames=WINDOW, seed=0)
    assert truth["ax_m_per_s2"] > 0 and truth["effect"] == "external_force"
    d = detectability(recs, control[0])
    assert d > 3e-3  # markers moved by more than 10x the 0.3 mm mocap noise
    # the wind pushes the rope along +x, +y
    shift = np.mean(
        [r.positions[:, INNER] - c.positions[:, INNER] for r, c in zip(recs, control[0])], axis=(0, 1, 2)
    )
    assert shift[0] > 0 and shift[1] > 0


def test_same_seed_same_recordings(sources, control):
    again, truth = generate_mujoco(None, sources, SPEC, "light", n_frames=WINDOW, seed=0)
    assert truth["numerics"]["starts"] == control[1]["numerics"]["starts"]
    for a, b in zip(again, control[0]):
        np.testing.assert_array_equal(a.positions, b.positions)


def test_unknown_effect_is_an_error(sources):
    with pytest.raises(ValueError, match="unknown effect"):
        generate_mujoco("gravity_off", sources, SPEC)
