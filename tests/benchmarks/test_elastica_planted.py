"""The PyElastica planted-effect generator (benchmarks/elastica_planted.py) on small synthetic
gripper motions: no dataset needed; skipped without PyElastica (the `bench` extra)."""

import math

import numpy as np
import pytest

pytest.importorskip("elastica")

from benchmarks.elastica_planted import detectability, generate_elastica
from deform.diagnose.spec import RodSpec
from deform.io.recordings import Recording
from deform.model import gripped_indices

pytestmark = pytest.mark.slow  # numba start-up and rod integration take seconds

N, FRAMES, WINDOW = 10, 60, 40
SPEC = RodSpec(length_m=1.0, mass_kg=0.05, n_vertices=N, dt=0.01)


def _source(phase: float) -> Recording:
    """A rope hanging in a half circle (radius 0.3 m, lowest point 0.2 m) between two grippers 0.6 m
    apart that sway sideways by 4 cm at 1 Hz, in opposite phase; 3 cm gripped end edges."""
    radius, edge = 0.3, 0.03
    arc = math.pi * radius
    s = np.concatenate([[0.0, edge], np.linspace(edge, arc - edge, N - 2)[1:-1], [arc - edge, arc]])
    theta = math.pi + s / radius
    base = np.stack([radius * np.cos(theta), np.zeros_like(theta), 0.5 + radius * np.sin(theta)], axis=1)
    t = np.arange(FRAMES) * SPEC.dt
    pos = np.repeat(base[None], FRAMES, axis=0)
    sway = 0.04 * np.sin(2 * math.pi * t + phase)
    pos[:, : N // 2, 1] += sway[:, None]
    pos[:, N // 2 :, 1] -= sway[:, None]
    return Recording(name=f"synthetic_{phase}", positions=pos, dt=SPEC.dt)


@pytest.fixture(scope="module")
def sources():
    return [_source(0.0), _source(1.0)]


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
