"""The PyElastica generator simulates all rods in one collection with features that act on every rod
at once (benchmarks/planted/elastica.py, ``_features``): each rod's recording must not depend on the
other rods or on its place among them. Skipped without PyElastica (the `bench` extra)."""

import numpy as np
import pytest

pytest.importorskip("elastica")

from benchmarks.planted.elastica import generate_elastica
from tests.benchmarks.swaying_rope import FRAMES, SPEC, swaying_source

pytestmark = pytest.mark.slow  # numba start-up and rod integration take seconds


def test_a_rods_recording_does_not_depend_on_its_place_among_the_rods():
    a, b = swaying_source(0.0), swaying_source(1.0)
    # the whole recording as the window (start 0 for every source): the same motions in both orders;
    # ground contact, as it exercises every per-rod kernel (grips, gravity, contact, damping)
    kw = {"rod_kind": "light", "n_frames": FRAMES, "seed": 0, "noise_m": 0.0}
    ab, truth_ab = generate_elastica("ground_contact", [a, b], SPEC, **kw)
    ba, truth_ba = generate_elastica("ground_contact", [b, a], SPEC, **kw)
    assert truth_ab["height_m"] == truth_ba["height_m"]
    assert not np.array_equal(ab[0].positions, ab[1].positions)
    np.testing.assert_array_equal(ab[0].positions, ba[1].positions)
    np.testing.assert_array_equal(ab[1].positions, ba[0].positions)
