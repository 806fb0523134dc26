"""The material frame's roll about the grippers, read from a recording's first frames."""

import math

import numpy as np
import torch

from deform.diagnose.simulator import ROLL_FRAMES, Nominal, Simulator, arclength_of, roll_directors
from deform.rod import geometry as G
from deform.rod.layout import batch_major, vertex_major
from deform.terms.library import make_term

from .conftest import SPEC


def _curved_sim(sources, read_roll=True):
    term = make_term("rest_curvature", SPEC.n_vertices, arclength_of(sources), read_roll=read_roll)
    with torch.no_grad():
        term.raw.copy_(torch.tensor([3.0, 0.0], dtype=torch.float64))  # 0.15 rad turning per vertex
    sim = Simulator(SPEC, Nominal(2e-3, 1.4e-3, 0.5), [term])
    sim.sync()
    return sim


def _frames(x):
    """Unit tangents and space-parallel directors (B, m, 3) of vertices (B, n, 3)."""
    t = G.normalize(G.edges(vertex_major(x, 2)))
    return batch_major(t, x.shape[:1]), batch_major(G.space_parallel_frame(t), x.shape[:1])


def test_rolled_directors_stay_a_twist_free_frame_of_the_same_edges(sources):
    x = torch.tensor(sources[0].positions[5])
    t = G.normalize(G.edges(x[..., None]))  # one rod, vertex-major (m, 3, 1)
    d1 = G.space_parallel_frame(t)
    rolled = roll_directors(
        batch_major(d1, (1,)), batch_major(t, (1,)), torch.tensor([0.9], dtype=torch.float64)
    )
    rolled = vertex_major(rolled, 2)
    assert torch.allclose(G.norm(rolled), torch.ones(len(t), 1, dtype=torch.float64))
    assert G.dot(rolled, t).abs().max() < 1e-12
    assert torch.allclose(G.dot(rolled, d1), torch.full_like(G.dot(rolled, d1), math.cos(0.9)))
    # a roll about every edge commutes with parallel transport: the reference twist is unchanged
    assert torch.allclose(G.reference_twist(rolled, t), G.reference_twist(d1, t), atol=1e-12)


def test_a_recordings_roll_is_read_back_from_its_first_frames(sources):
    sim = _curved_sim(sources)
    truth = torch.tensor([1.2, -2.0], dtype=torch.float64)  # rad, one per recording
    X = torch.tensor(np.stack([r.positions[: ROLL_FRAMES + 2] for r in sources[:2]]))
    t1, d1 = _frames(X[:, 1])
    d1 = roll_directors(d1, t1, truth)
    with torch.no_grad():  # recordings made with the rolled frame: directors given, nothing read
        moved = sim.rollout(X, ROLL_FRAMES, d1=d1)
    made = torch.cat([X[:, :2], moved], 1)
    read = sim.initial_roll(made)
    wrapped = torch.remainder(read - truth + math.pi, 2 * math.pi) - math.pi
    assert wrapped.abs().max() < math.radians(10), read
    # the roll matters: the convention's roll (none) predicts these recordings worse
    with torch.no_grad():
        unrolled = sim.rollout(made, ROLL_FRAMES, d1=_frames(X[:, 1])[1])
        rolled = sim.rollout(made, ROLL_FRAMES)  # from the recordings' start: the roll is read
    err = lambda p: float((p - made[:, 2:]).abs().mean())  # noqa: E731
    assert err(rolled) < 0.3 * err(unrolled)


def test_without_reading_the_roll_the_rollout_is_the_conventions(sources):
    X = torch.tensor(np.stack([r.positions[:40] for r in sources[:2]]))
    with torch.no_grad():
        fixed = _curved_sim(sources, read_roll=False).rollout(X, 38)
        convention = _curved_sim(sources).rollout(X, 38, d1=_frames(X[:, 1])[1])
    assert torch.allclose(fixed, convention, atol=1e-9)  # the same frame, carried another way
