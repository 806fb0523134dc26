"""Points against a polyline: arc position and distance, the same nearest point for both."""

import numpy as np

from perception.polyline import arc_positions, segment_distances


def test_arc_positions_on_a_straight_line():
    line = np.array([[0.0, 0, 0], [0.5, 0, 0], [1.0, 0, 0]])
    s, d = arc_positions(np.array([[0.25, 0.1, 0], [0.75, 0, -0.2], [-1.0, 0, 0]]), line)
    assert np.allclose(s, [0.25, 0.75, 0.0]) and np.allclose(d, [0.1, 0.2, 1.0])


def test_distance_to_a_bent_polyline_is_to_its_nearest_edge():
    corner = np.array([[0.0, 0, 0], [1.0, 0, 0], [1.0, 1.0, 0]])
    points = np.array([[0.5, -0.2, 0], [1.3, 0.5, 0], [1.2, -0.1, 0], [0.8, 0.1, 0.0]])
    assert np.allclose(segment_distances(points, corner), [0.2, 0.3, np.hypot(0.2, 0.1), 0.1])
    s, _ = arc_positions(points, corner)
    assert np.allclose(s, [0.5, 1.5, 1.0, 0.8])
