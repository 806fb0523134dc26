"""The side-by-side tracking benchmark (benchmarks/tracking): the metric, the blackout render, the contact
generator and the runner with a stand-in peer, on tiny synthetic cases (no dataset)."""

import json

import numpy as np
import pytest
import torch

from benchmarks.tracking import contact, report, scenarios
from benchmarks.tracking.metric import recovery_time, rope_error, two_way_error
from benchmarks.tracking.runner import OURS, run_unit
from deform import generate_recording, gripped_indices, load_model
from deform.io.arc_length import resample_vertices
from perception import load_config, render_recording


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def model():
    return load_model("DLO2")


@pytest.fixture(scope="module")
def recording(model):
    return generate_recording(model, n_frames=150, seed=0)  # starts above its lowest: the table is touched


def test_metric_is_zero_for_identical_and_hand_computed_for_shifted():
    truth = np.array([[0.0, 0, 0], [0.3, 0.1, 0], [0.6, 0, 0.05], [1.0, 0, 0]])
    assert two_way_error(truth, truth) == pytest.approx(0.0, abs=1e-12)
    line = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    assert two_way_error(line + [0, 0, 0.02], line) == pytest.approx(0.02)  # shifted across: d
    # shifted 0.1 along: the tracked end node is 0.1 off (mean of 2 nodes 0.05); of the 11 true samples
    # only x = 0 is off the tracked polyline [0.1, 1.1], by 0.1
    assert two_way_error(line + [0.1, 0, 0], line) == pytest.approx(0.5 * (0.05 + 0.1 / 11))
    # node counts may differ: a finer tracked polyline along the same rope scores 0
    fine = resample_vertices(truth, 25)
    assert two_way_error(fine, truth) < 1e-3


def test_rope_error_scores_the_rendered_curve_not_the_marker_chords():
    from perception import rope_centreline

    bent = np.array(
        [[0.0, 0, 0], [0.03, 0, 0.0], [0.3, 0.0, -0.15], [0.6, 0.0, -0.2], [0.9, 0, 0.0], [0.93, 0, 0]]
    )
    curve = rope_centreline(bent, 8)
    on_curve = curve[::2]  # a tracker with finer nodes that follows the rope the camera shows
    assert rope_error(on_curve, bent) < 1e-3
    assert two_way_error(on_curve, bent) > 1e-3  # the marker chords cut the curve's bends
    assert rope_error(bent, bent) > 1e-3  # nodes at the markers are not the whole rope either
    straight = np.linspace([0.0, 0, 0], [1.0, 0, 0], 6)
    assert rope_error(straight + [0, 0, 0.02], straight) == pytest.approx(0.02)


def test_recovery_time():
    t = np.arange(0, 4, 0.1)
    e = np.where((t >= 1.5) & (t < 2.8), 10.0, 1.0)
    rec, ref = recovery_time(t, e, 1.5, 2.5)
    assert ref == pytest.approx(1.0) and rec == pytest.approx(0.3)
    assert recovery_time(t, np.where(t >= 1.5, 10.0, 1.0), 1.5, 2.5)[0] is None


def test_blackout_hides_every_vertex_inside_the_window_and_none_outside(recording):
    from dataclasses import replace

    base = load_config().render
    steps = list(range(0, 150, 10))
    dark = replace(base, blackout_start_s=0.3, blackout_s=0.4)
    a = render_recording(recording.positions, config=dark, steps=steps, seed=3)
    b = render_recording(recording.positions, config=base, steps=steps, seed=3)
    for fa, fb in zip(a, b):
        inside = 0.3 <= fa.step * 0.01 < 0.7
        if inside:
            assert not fa.visible.any() and fa.occluded
            assert fb.visible[2:-2].any()
        else:
            assert np.array_equal(fa.visible, fb.visible) and not fa.occluded
    assert sum(0.3 <= s * 0.01 < 0.7 for s in steps) == 4


def test_contact_generator_keeps_the_rope_on_the_table_and_touches_it(model, recording):
    ref = contact.simulate(model, recording.positions)
    table = contact.place_table(ref)
    x = contact.simulate(model, recording.positions, table=table)
    free = np.ones(x.shape[1], bool)
    free[gripped_indices(x.shape[1])] = False
    assert x[:, free, 2].min() >= table.plane_z - 1e-3
    assert table.surface_z < table.plane_z
    assert contact.contact_fraction(x, table) > 0.05
    assert np.abs(x - ref).max() > 0.005  # the table changed the motion
    post = contact.place_post(ref, model.dt)
    y = contact.simulate(model, recording.positions, post=post)
    assert contact.post_contact_fraction(y, post) > 0
    pushed = np.stack([contact.push_out(f, post, 1) for f in y])
    assert np.abs(pushed - y).max() < 1e-3  # no edge left inside the post


class Hold:
    """Stand-in peer: the last estimate with the gripped nodes moved."""

    def initialize(self, x0, grip):
        self.x = np.array(x0, dtype=float)

    def update(self, points, grip, depth, camera):
        assert points.ndim == 2 and points.shape[1] == 3 and depth.shape == (camera.height, camera.width)
        self.x[gripped_indices(len(self.x))] = grip
        return self.x.copy()


class Broken(Hold):
    def update(self, points, grip, depth, camera):
        raise RuntimeError("no")


def test_runner_with_a_stand_in_peer_gives_the_json_fields(model, recording, monkeypatch, tmp_path):
    monkeypatch.setattr(scenarios, "BLACKOUT_START_S", 0.4)
    monkeypatch.setattr(scenarios, "BLACKOUT_S", 0.3)
    pos = recording.positions[:90]
    unit = scenarios.Unit("DLO2", "tiny", pos, 0.01, ("occ0", "fps10", "blackout"))
    peers = {"hold": Hold, "broken": Broken}
    methods = [OURS, "hold", "broken"]
    row = run_unit(unit, methods, peers, models={"DLO2": model})
    assert [c["variant"] for c in row["cases"]] == ["occ0", "fps10", "blackout"]
    for c in row["cases"]:
        assert set(c["methods"]) == set(methods)
        for g in c["methods"].values():
            assert len(g["errors_mm"]) == len(c["times_s"]) > 0 and g["mean_error_mm"] >= 0
            assert g["mean_rope_error_mm"] > 0  # the nodes are never the whole rendered curve
            assert g["update_ms"]["n"] == len(c["times_s"])
    occ0, fps10, dark = row["cases"]
    assert len(fps10["times_s"]) < len(occ0["times_s"])
    assert occ0["methods"][OURS]["mean_error_mm"] < occ0["methods"]["hold"]["mean_error_mm"]
    assert occ0["methods"]["broken"]["failures"] == len(occ0["times_s"])
    assert "recovery_s" in dark["methods"][OURS] and "step_ms" in occ0["methods"][OURS]
    res = report.summarize([row], methods)
    assert set(res["summary"]) == {"occ0", "fps10", "blackout"}
    assert res["summary"]["blackout"][OURS]["recovery_s"]["n"] == 1
    assert len(res["series"]["occ0"][OURS]) == len(res["series"]["occ0"]["times_s"])
    assert res["summary"]["occ0"][OURS]["per_recording_rope_mm"]["DLO2.tiny"] > 0
    res.update(methods=methods, args=dict(per_rod=1, rods=["DLO2"]), timing_ms=report.timing([row], methods))
    md = report.markdown(res)
    assert "| no occlusion | 1 |" in md and "hold" in md
    json.dumps(res)
    assert report.plot(res, tmp_path / "p.png").stat().st_size > 1000


def test_a_model_key_with_a_rest_length_factor():
    assert scenarios.rest_scale_of("DLO3@1.06") == 1.06 and scenarios.rest_scale_of("DLO3") == 1.0
    assert scenarios.model_of("DLO3@0.94").n == load_model("DLO3").n


def test_ours_given_a_length_6_percent_long_takes_the_cameras(model, recording):
    """``long_model``: the tracker starts with its free rest lengths 6 % long and the camera's
    length replaces them (``length_scale`` in its result)."""
    pos = recording.positions[:120]
    unit = scenarios.Unit("DLO2", "tiny", pos, 0.01, ("long_model", "right_model"))
    row = run_unit(unit, [OURS], {}, models={"DLO2": model, "DLO2@1.06": model})
    by = {c["variant"]: c["methods"][OURS] for c in row["cases"]}
    long, right = by["long_model"], by["right_model"]
    assert right["length_scale"] == 1.0 and 0.9 < long["length_scale"] < 0.98
