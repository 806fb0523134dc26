"""The PyElastica planted-effect generator (benchmarks/planted/elastica.py) on small synthetic
gripper motions: no dataset needed; skipped without PyElastica (the `bench` extra)."""

import numpy as np
import pytest

pytest.importorskip("elastica")

from benchmarks.planted.elastica import detectability, generate_elastica
from deform.model import gripped_indices
from tests.benchmarks.swaying_rope import SPEC, WINDOW, N, swaying_source

pytestmark = pytest.mark.slow  # numba start-up and rod integration take seconds


@pytest.fixture(scope="module")
def sources():
    return [swaying_source(0.0), swaying_source(1.0)]


@pytest.fixture(scope="module")
def control(sources):
    return generate_elastica(None, sources, SPEC, "light", n_frames=WINDOW, seed=0, noise_m=0.0)


def test_control_is_a_hanging_rope_held_by_its_grippers(sources, control):
    recs, truth = control
    g = gripped_indices(N)
    inner = [k for k in range(N) if k not in g]
    assert truth["effect"] is None and truth["rod_kind"] == "light"
    assert [r.name for r in recs] == ["elastica_light_control_0_0", "elastica_light_control_0_1"]
    for rec, src, start in zip(recs, sources, truth["numerics"]["starts"]):
        p = rec.positions
        assert p.shape == (WINDOW, N, 3) and np.all(np.isfinite(p))
        np.testing.assert_array_equal(p[:, g], src.positions[start : start + WINDOW][:, g])
        # hangs in a U: every inner marker below the grippers, the middle lowest
        assert np.all(p[:, inner, 2] < p[:, g, 2].min(axis=1, keepdims=True))
        assert p[:, N // 2 - 1 : N // 2 + 1, 2].mean() < p[:, inner, 2].mean()
        # material points: the distance between neighbouring inner markers stays constant
        e = np.linalg.norm(np.diff(p[:, inner], axis=1), axis=-1)
        assert np.all(np.abs(e / np.median(e, axis=0) - 1) < 0.03)
    assert truth["numerics"]["max_stretch"] < 0.01


def test_planted_wind_moves_markers_more_than_noise(sources, control):
    recs, truth = generate_elastica(
        "external_force", sources, SPEC, "light", n_frames=WINDOW, seed=0, noise_m=0.0
    )
    assert truth["ax_m_per_s2"] > 0 and truth["effect"] == "external_force"
    d = detectability(recs, control[0])
    assert d > 3e-3  # markers moved by more than 10x the 0.3 mm mocap noise
    assert detectability(control[0], control[0]) == 0.0
    # the wind pushes the rope along +x, +y
    g = gripped_indices(N)
    inner = [k for k in range(N) if k not in g]
    shift = np.mean(
        [r.positions[:, inner] - c.positions[:, inner] for r, c in zip(recs, control[0])], axis=(0, 1, 2)
    )
    assert shift[0] > 0 and shift[1] > 0


def test_unknown_effect_is_an_error(sources):
    with pytest.raises(ValueError, match="unknown effect"):
        generate_elastica("gravity_off", sources, SPEC)
