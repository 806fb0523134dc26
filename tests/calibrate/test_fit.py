"""Which tracked motion trains and which is held out (calibrate.fit.split)."""

import numpy as np

from calibrate.fit import split
from calibrate.tracks import Track


def _track(name: str, frames: int) -> Track:
    steps = np.arange(0, frames, 10)
    return Track(
        name=name,
        positions=np.zeros((frames, 6, 3)),
        grips=np.zeros((frames, 4, 3)),
        dt=0.01,
        cloud_steps=steps,
        cloud_observed=np.zeros((len(steps), 6), dtype=bool),
        cloud_points=tuple(np.zeros((0, 3)) for _ in steps),
        status={},
    )


def _frames(tracks):
    return sum(t.n_frames for t in tracks)


def test_a_few_recordings_train_on_most_of_each_and_hold_out_their_ends():
    tracks = [_track("b", 3000), _track("a", 2000)]  # two 20-30 s bags
    train, held = split(tracks, every=5, min_frames=52)
    assert [t.name for t in held] == ["a[held out]", "b[held out]"]
    assert _frames(train) == 1400 + 2100 and _frames(held) == 600 + 900  # 70 %, not a whole bag
    assert held[0].cloud_steps.min() == 0 and held[0].cloud_steps.max() < 600  # re-based on the piece


def test_many_clips_hold_out_every_fifth_whole():
    tracks = [_track(f"clip{i}", 500) for i in range(10)]
    train, held = split(tracks, every=5, min_frames=52)
    assert [t.name for t in held] == ["clip0", "clip5"] and len(train) == 8
    assert all(t.n_frames == 500 for t in train + held)


def test_clips_too_short_to_cut_keep_one_whole_clip_back():
    tracks = [_track(f"clip{i}", 150) for i in range(3)]  # 30 % = 45 frames < the 52 scored
    train, held = split(tracks, every=5, min_frames=52)
    assert [t.name for t in held] == ["clip0"] and [t.name for t in train] == ["clip1", "clip2"]
    (one,) = split([_track("long", 1000)], every=5, min_frames=52)[1]  # a single recording: always cut
    assert one.name == "long[held out]" and one.n_frames == 300
