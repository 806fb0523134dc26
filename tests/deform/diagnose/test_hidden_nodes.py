"""Simulator with unobserved nodes between the markers (the mass_scale identifiability study)."""

import numpy as np
import torch

from deform.diagnose.simulator import Nominal, Simulator, arclength_of, marker_nodes, refine_markers
from deform.terms.library import make_term

from .conftest import SPEC


def test_marker_nodes_leave_the_gripped_end_edges_whole():
    assert marker_nodes(6, 0) == [0, 1, 2, 3, 4, 5]
    assert marker_nodes(6, 1) == [0, 1, 3, 5, 7, 8]  # hidden nodes 2, 4, 6 in the three free intervals


def test_refined_nodes_keep_the_markers_and_lie_on_a_circle_the_markers_lie_on():
    phi = np.array([0.0, 0.05, 0.3, 0.55, 0.8, 0.85])  # uneven: short gripped end edges
    x = torch.tensor(np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], -1))
    nodes = refine_markers(x, 1)
    assert nodes.shape == (9, 3)
    assert torch.equal(nodes[marker_nodes(6, 1)], x)
    radius = nodes[[2, 4, 6]].norm(dim=-1)
    chord_mid = ((x[[1, 2, 3]] + x[[2, 3, 4]]) / 2).norm(dim=-1)
    assert (radius - 1).abs().max() < 0.1 * (1 - chord_mid).min()  # the cubic is far closer than the chord


def test_one_hidden_node_rollout_holds_the_grips_and_stays_close_to_the_marker_model(sources):
    X = torch.tensor(np.stack([r.positions[:32] for r in sources[:2]]))
    coarse = Simulator(SPEC, Nominal(2e-3, 1.4e-3, 0.5))
    fine = Simulator(SPEC, Nominal(2e-3, 1.4e-3, 0.5), hidden=1)
    assert fine.n == 2 * SPEC.n_vertices - 3 and fine.model.dt == SPEC.dt / 2
    coarse.sync(), fine.sync()
    with torch.no_grad():
        a, b = coarse.rollout(X, 30), fine.rollout(X, 30)
    assert b.shape == a.shape
    grip = [0, 1, SPEC.n_vertices - 2, SPEC.n_vertices - 1]
    assert torch.allclose(b[:, :, grip], X[:, 2:32, grip])
    gap = (a - b).abs().mean()
    assert 1e-5 < gap < 0.3 * (a - X[:, 2:32]).abs().mean() + 5e-3  # different, but the same rod


def test_marker_mass_of_a_hidden_node_model_sits_on_the_markers_only(sources):
    sim = Simulator(SPEC, Nominal(), hidden=1)
    term = make_term(
        "mass_scale", sim.n, sim.node_arclength(arclength_of(sources)), {"rod_mass_kg": SPEC.mass_kg}
    )
    sim = Simulator(SPEC, Nominal(), [term], hidden=1)
    base = torch.ones(1, sim.n)
    added = term.mass(base) - base
    on = torch.zeros(sim.n, dtype=torch.bool)
    on[sim.markers] = True
    assert (added[0, on] > 0).all() and (added[0, ~on] == 0).all()
    # the grid raises EI and GJ by the mass each point adds to the free markers
    point = term.grid()[-1]
    free = len(sim.markers) - 4
    expected = np.log1p(
        free * 1e-3 * float(torch.nn.functional.softplus(torch.tensor(point["raw_g"]))) / SPEC.mass_kg
    )
    assert (
        abs(point["nominal:log_ei"] - expected) < 1e-9 and point["nominal:log_gj"] == point["nominal:log_ei"]
    )
