"""Which way is up: a rope hanging sideways is refused, one bowing up is a warning, a taut one passes."""

import numpy as np
import pytest

from deform.io.orientation import check_up_axis, mean_sag
from deform.io.recordings import Recording, RecordingError


def _rope(height):
    """A rope held at both ends whose middle is ``height(s)`` [m] off the line between the grips."""
    s = np.linspace(0, 1, 10)
    x = np.zeros((30, 10, 3))
    x[:, :, 0] = 0.8 * s
    x[:, :, 2] = 0.5 + height(s)
    return Recording("r", x + np.random.default_rng(0).normal(0, 3e-4, x.shape))


def test_the_sag_says_which_way_the_rope_hangs():
    hanging = _rope(lambda s: -0.12 * np.sin(np.pi * s))
    assert mean_sag([hanging])[2] < -0.05 and check_up_axis([hanging], "d") is None
    y_up = Recording("r", hanging.positions[..., [0, 2, 1]] * [1, 1, -1])  # height in y
    with pytest.raises(RecordingError, match=r"d: the rope hangs along -y"):
        check_up_axis([y_up], "d")
    arch = _rope(lambda s: 0.12 * np.sin(np.pi * s))
    assert "bows upward" in check_up_axis([arch], "d")
    taut = _rope(lambda s: 0.0 * s)  # no sag to read: nothing said
    assert check_up_axis([Recording("r", taut.positions[..., [0, 2, 1]])], "d") is None
