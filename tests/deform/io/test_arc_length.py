"""Markers as vertices by arc length (deform/io/arc_length.py): the gripped vertices kept, points
on the same curve, a round trip that loses only what a coarser polyline cannot hold."""

import numpy as np
import pytest

from deform.io.arc_length import edge_lengths, free_fractions, resample_vertices


def _arc(m: int, frames: int = 3) -> np.ndarray:
    """(frames, m, 3) markers on a circle's lower half of radius 0.3 m, scaled per frame."""
    t = np.linspace(0, np.pi, m)
    base = np.stack([0.3 * np.cos(t), np.zeros(m), -0.3 * np.sin(t)], -1)
    return np.stack([base * (1 + 0.1 * f) for f in range(frames)])


def test_the_gripped_vertices_are_kept_and_the_inner_ones_lie_on_the_curve():
    x = _arc(100)  # dense: its polyline is the circle to 0.05 mm
    y = resample_vertices(x, 9)
    assert y.shape == (3, 9, 3)
    np.testing.assert_array_equal(y[:, [0, 1, -2, -1]], x[:, [0, 1, -2, -1]])
    radius = np.linalg.norm(y[..., [0, 2]], axis=-1)
    expected = np.broadcast_to(0.3 * (1 + 0.1 * np.arange(3))[:, None], radius.shape)
    np.testing.assert_allclose(radius, expected, atol=2e-4)


def test_the_same_count_and_the_same_spacing_is_the_identity():
    x = _arc(12)
    np.testing.assert_allclose(resample_vertices(x, 12, edge_lengths(x[0])), x, atol=1e-12)


def test_a_round_trip_through_fewer_vertices_costs_only_the_chords_of_the_coarser_polyline():
    x = _arc(13)
    back = resample_vertices(resample_vertices(x, 9), 13, edge_lengths(x[0]))
    err = np.linalg.norm(back - x, axis=-1)
    assert err.max() < 0.01  # chord sagitta of 0.3 m radius, 8 free edges: about 4 mm
    assert err[:, [0, 1, -2, -1]].max() == 0


def test_a_cubic_curve_keeps_the_resampled_vertices_on_the_bend_the_polyline_cuts():
    x = _arc(13)  # 10 free edges of 8 cm on a 30 cm radius: a chord sags 2.6 mm
    radius = {}
    for curve in ("linear", "cubic"):
        y = resample_vertices(x, 9, curve=curve)
        np.testing.assert_array_equal(y[:, [0, 1, -2, -1]], x[:, [0, 1, -2, -1]])
        r = np.linalg.norm(y[..., [0, 2]], axis=-1) / (0.3 * (1 + 0.1 * np.arange(3)))[:, None]
        radius[curve] = np.abs(r - 1).max()
    assert radius["linear"] > 2e-3  # inside the bend by the chords' sag
    assert radius["cubic"] < radius["linear"] / 20


def test_a_round_trip_along_the_cubic_curve_loses_far_less_than_along_chords():
    x = _arc(13)
    err = {
        c: np.linalg.norm(
            resample_vertices(resample_vertices(x, 9, curve=c), 13, edge_lengths(x[0]), curve=c) - x, axis=-1
        ).max()
        for c in ("linear", "cubic")
    }
    assert err["cubic"] < err["linear"] / 10


def test_the_cubic_curve_with_the_same_count_and_spacing_is_the_identity_and_survives_repeated_points():
    x = _arc(12)
    same = resample_vertices(x, 12, edge_lengths(x[0]), curve="cubic")
    np.testing.assert_allclose(same, x, atol=1e-4)  # arc fractions of the spline, not of its chords
    x[:, 5] = x[:, 4]  # a marker lost and held: the spline has no chord to grow on; the polyline serves
    y = resample_vertices(x, 9, curve="cubic")
    assert np.isfinite(y).all()
    np.testing.assert_allclose(y, resample_vertices(x, 9), atol=1e-12)


def test_an_unknown_curve_is_refused():
    with pytest.raises(ValueError, match="curve"):
        resample_vertices(_arc(12), 9, curve="quintic")


def test_the_rest_lengths_place_the_inner_vertices():
    f = free_fractions(np.array([0.02, 0.1, 0.3, 0.1, 0.02]), 6)
    np.testing.assert_allclose(f, [0, 0.2, 0.8, 1.0])


@pytest.mark.parametrize("rest, n", [(None, 3), (np.ones(3), 5), (np.array([1.0, 0.0, 1.0, 1.0]), 5)])
def test_impossible_layouts_are_refused(rest, n):
    with pytest.raises(ValueError):
        free_fractions(rest, n)
