"""Marker label swaps: crossed neighbours restored exactly, a moving rope never taken for one."""

import numpy as np

from deform.io.labels import fix_label_swaps, fix_recordings_labels
from deform.io.recordings import Recording


def _swinging(T=120, n=10, noise=3e-4, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(T)[:, None] * 0.01
    s = np.linspace(0, 1, n)[None, :]
    x = np.stack(
        [
            0.9 * s + 0.05 * np.sin(2 * np.pi * 1.5 * t),
            0.1 * np.sin(np.pi * s) * np.cos(2 * np.pi * 2 * t),
            0.4 - 0.15 * np.sin(np.pi * s) + 0 * t,
        ],
        axis=-1,
    )
    return x + rng.normal(0, noise, x.shape)


def test_neighbours_that_trade_labels_for_a_while_are_restored_exactly():
    truth = _swinging()
    x = truth.copy()
    x[40:60, [3, 4]] = truth[40:60, [4, 3]]  # lost and given back under the neighbour's label
    x[90, [7, 8]] = truth[90, [8, 7]]  # a one-frame swap
    fixed, swaps = fix_label_swaps(x)
    assert swaps == [(t, 3) for t in range(40, 60)] + [(90, 7)]
    assert np.array_equal(fixed, truth)


def test_a_moving_rope_is_never_taken_for_a_swap():
    x = _swinging()
    fixed, swaps = fix_label_swaps(x)
    assert swaps == [] and fixed is x
    # every marker moving along the rope by one spacing per frame: the crossed assignment is as
    # long as the labelled one, not shorter
    n = 10
    spacing = 0.03
    slide = np.zeros((20, n, 3))
    slide[:, :, 0] = spacing * (np.arange(n)[None, :] + np.arange(20)[:, None])
    assert fix_label_swaps(slide)[1] == []


def test_recordings_say_which_markers_crossed():
    truth = _swinging()
    x = truth.copy()
    x[40:60, [3, 4]] = truth[40:60, [4, 3]]
    recs, note = fix_recordings_labels([Recording("a", truth), Recording("b", x)])
    assert np.array_equal(recs[1].positions, truth) and recs[0].positions is truth
    assert note is not None and "b (markers 3-4: 20 frame(s))" in note and "a (" not in note
    assert fix_recordings_labels([Recording("a", truth)])[1] is None
