"""The calibration benchmark (benchmarks/calibrate_rods.py): clips come from training motions only,
never from the held-out ones it is scored on, and the targets of issue 49 are read off correctly."""

import numpy as np
import pytest

from benchmarks.calibration.clips import held_length_and_mass, motions, split_files
from benchmarks.calibration.report import markdown, summarize
from deform import save_recording


def _dataset(root, rod, train, held):
    for split, count in (("train", train), ("eval", held)):
        (root / rod / split).mkdir(parents=True)
        for i in range(count):
            x = np.zeros((4, 12, 3))
            x[..., 0] = np.linspace(0, 1, 12)
            save_recording(root / rod / split / f"{i}.pkl", x)


def test_clips_are_training_motions_and_never_held_out_ones(tmp_path):
    _dataset(tmp_path, "DLO1", train=20, held=3)
    _dataset(tmp_path, "DLO4", train=20, held=0)  # no eval split: the held-out fifth of train
    train, held = split_files(tmp_path, "DLO4")
    assert [p.stem for p in held] == ["0", "5", "10", "15"] and not set(train) & set(held)
    clips, held = motions("DLO4", 50.0, root=tmp_path)
    assert len(clips) == 10 and not {c.name for c in clips} & {h.name for h in held}
    assert len({c.name for c in clips}) == 10  # spread over the training set, none twice
    clips, held = motions("DLO1", 1000.0, root=tmp_path)  # more time than recorded: all of train
    assert len(clips) == 20 and [h.name for h in held] == ["0", "1", "2"]


def test_another_clip_set_is_as_large_disjoint_and_still_never_held_out(tmp_path):
    _dataset(tmp_path, "DLO4", train=60, held=0)  # 48 training recordings, 12 held out
    usual, held = motions("DLO4", 50.0, root=tmp_path)
    other, held_again = motions("DLO4", 50.0, root=tmp_path, clip_set=1)
    names = {c.name for c in other}
    assert len(names) == len(usual) == 10
    assert not names & {c.name for c in usual}  # disjoint: the picks are ~5 recordings apart
    assert not names & {h.name for h in held}
    assert [h.name for h in held_again] == [h.name for h in held]
    assert [c.name for c in motions("DLO4", 50.0, root=tmp_path, clip_set=0)[0]] == [c.name for c in usual]
    with pytest.raises(ValueError, match="clip_set"):
        motions("DLO4", 50.0, root=tmp_path, clip_set=-1)


def test_the_user_gives_the_length_and_mass_between_the_grippers():
    from deform import Recording, load_rod_config

    x = np.zeros((3, 12, 3))
    x[..., 0] = np.linspace(0, 0.8, 12)  # 0.8 m between the end markers
    length, mass = held_length_and_mass("DLO4", [Recording("a", x), Recording("b", x * 1.01)])
    cfg = load_rod_config("DLO4")
    assert length == pytest.approx(0.804, abs=1e-3)  # the median of 0.8 and 0.808
    assert mass / length == pytest.approx(cfg.mass_kg / cfg.length_m, rel=1e-3)  # the same rope


def _row(key, calibrated, shipped, generic, seconds=600.0):
    scores = {
        m: {"open_loop": {"l1_cm": v[0]}, "tracking_mm": v[1], "prediction_1s_mm": v[2]}
        | ({"tracking_rope_mm": v[3]} if len(v) > 3 else {})
        for m, v in (("calibrated", calibrated), ("shipped", shipped), ("generic", generic))
    }
    return {"key": key, "rod": key.split("-")[0], "seconds": 50.0, "calibrate_s": seconds, "scores": scores}


def test_the_targets_are_met_only_when_every_bound_holds():
    good = _row("DLO3-50s", (0.7, 2.5, 10.0), (0.6, 2.2, 9.0), (2.0, 5.5, 40.0))
    slow = _row("DLO3-120s", (0.7, 2.5, 10.0), (0.6, 2.2, 9.0), (2.0, 5.5, 40.0), seconds=1500.0)
    poor = _row("DLO1-50s", (1.2, 2.9, 12.0), (0.6, 2.2, 9.0), (2.0, 5.5, 40.0))
    s = summarize([good, slow, poor])
    assert all(s["DLO3-50s"]["targets"].values())  # 0.7 <= 0.77 paper, 1.11x, 1.14x, <= half of generic
    assert [k for k, v in s["DLO3-120s"]["targets"].items() if not v] == ["calibrate <= 20 min"]
    missed = {k for k, v in s["DLO1-50s"]["targets"].items() if not v}
    assert missed == {
        "prediction_1s <= 1.25x shipped",  # 1.33x
        "tracking <= 1.2x shipped",  # 1.32x
        "open loop <= paper DEFORM",  # 1.2 > 1.01
        "every error <= half of generic DER",  # tracking 2.9 / 5.5 = 0.53
    }
    text = markdown({"summary": s})
    assert "| DLO3 | 50 | 0.70 / 0.60 / 2.00 | 0.77 |" in text and "DLO1-50s: met 1/5" in text


def test_tracking_is_judged_against_the_rendered_rope_when_measured():
    # against the markers 1.32x (the shipped model's vertices are the markers); against the rope 1.05x
    row = _row("DLO3-50s", (0.7, 2.9, 10.0, 2.1), (0.6, 2.2, 9.0, 2.0), (2.0, 5.5, 40.0, 5.0))
    cell = summarize([row])["DLO3-50s"]
    assert cell["tracking_judged_on"] == "tracking_rope_mm" and cell["targets"]["tracking <= 1.2x shipped"]
    assert cell["tracking_mm_vs_shipped"] == pytest.approx(1.318, abs=1e-3)
    row = _row("DLO3-50s", (0.7, 2.9, 10.0, 2.9), (0.6, 2.2, 9.0, 2.0), (2.0, 5.5, 40.0, 5.0))
    missed = {k for k, v in summarize([row])["DLO3-50s"]["targets"].items() if not v}
    assert missed == {"tracking <= 1.2x shipped", "every error <= half of generic DER"}  # 1.45x, 0.58
    assert "1.32x / 1.45x" in markdown({"summary": summarize([row])})


def test_a_rescored_run_names_the_calibrations_it_scored():
    row = _row("DLO3-50s", (0.7, 2.5, 10.0), (0.6, 2.2, 9.0), (2.0, 5.5, 40.0))
    assert "Scored again" not in markdown({"summary": summarize([row]), "rows": [row]})
    row["rescored_from"] = "86b12ada2b"
    assert "stored run of code 86b12ada2b" in markdown({"summary": summarize([row]), "rows": [row]})


def _swing(frames=12, n=12):
    x = np.zeros((frames, n, 3))
    x[..., 0] = np.linspace(-0.4, 0.4, n)
    x[..., 2] = 0.5 - 0.2 * np.sin(np.linspace(0, np.pi, n))[None] * np.linspace(1, 0.8, frames)[:, None]
    return x


def test_the_default_lab_films_as_the_benchmark_always_did():
    from dataclasses import replace

    from benchmarks.calibration.setups import SETUPS, session_camera
    from perception import default_camera

    lab, x = SETUPS["session"], _swing()
    render = replace(lab.perception().render, camera_distance=1.2, camera_elevation_deg=30.0)
    assert lab.perception().render == render  # the default renderer at the session's place
    assert np.array_equal(
        session_camera(lab, [x]).world_from_camera, default_camera(x, render).world_from_camera
    )
    assert [lab.occlusion_of_clip(i) for i in range(4)] == [0.0, 0.25, 0.0, 0.25]
    assert lab.settings_file(None) is None  # the default colour range: no file for the user to give


def test_another_labs_rope_is_found_by_its_own_colour_range_only(tmp_path):
    from benchmarks.calibration.setups import SETUPS, session_camera
    from perception import load_config, render_recording, segment_rope

    lab, x = SETUPS["other_lab"], _swing()
    camera = session_camera(lab, [x])
    square_on = session_camera(SETUPS["session"], [x])
    assert camera.width == round(640 * 0.75) and not np.allclose(
        camera.world_from_camera, square_on.world_from_camera
    )
    (frame,) = render_recording(x[:1], dt=0.01, fps=lab.fps, config=lab.perception().render, camera=camera)
    users = load_config(str(lab.settings_file(tmp_path)))  # what the user passes: the colour range
    assert (
        users.render == load_config(None).render
    )  # the file holds the colour range, nothing of the renderer
    found = segment_rope(frame.xyz, frame.rgb, users.segmentation).sum()
    assert found > 100 and segment_rope(frame.xyz, frame.rgb, load_config(None).segmentation).sum() == 0


def test_the_hidden_part_is_scored_on_the_markers_the_cloud_does_not_show():
    from benchmarks.calibration.score import hidden_error

    truth = np.zeros((12, 3))
    truth[:, 0] = np.linspace(0.0, 1.1, 12)
    visible = np.ones(12, dtype=bool)
    assert hidden_error(truth, truth, visible) is None  # nothing hidden
    assert hidden_error(truth, truth, None) is None  # a camera that says nothing of visibility
    visible[[0, 1, 10, 11]] = False  # the grippers' markers: placed by the grippers, not scored
    assert hidden_error(truth, truth, visible) is None
    estimate = truth.copy()
    estimate[4:7, 2] += 0.01  # the model bent three vertices 1 cm off
    visible[5] = False
    assert hidden_error(truth, truth, visible) == pytest.approx(0.0, abs=1e-12)
    assert hidden_error(estimate, truth, visible) == pytest.approx(0.01, abs=1e-3)
    visible[5], visible[8] = True, False  # a hidden marker the model got right
    assert hidden_error(estimate, truth, visible) == pytest.approx(0.0, abs=1e-3)
    fewer = truth[::2]  # another vertex count: the curve through it, not its chords
    assert hidden_error(fewer, truth, visible) == pytest.approx(0.0, abs=1e-9)


def test_the_hidden_part_is_shown_beside_the_judged_errors_and_not_judged():
    row = _row("DLO3-50s", (0.7, 2.5, 10.0, 2.1), (0.6, 2.2, 9.0, 2.0), (2.0, 5.5, 40.0, 5.0))
    for m, hidden in (("calibrated", 4.0), ("shipped", 3.0), ("generic", 16.0)):
        row["scores"][m]["tracking_hidden_mm"] = hidden
    cell = summarize([row])["DLO3-50s"]
    assert cell["tracking_hidden_mm_vs_generic"] == pytest.approx(0.25)
    assert all(cell["targets"].values())  # 1.33x the shipped's hidden part judges nothing
    assert "| 4.0 / 3.0 / 16.0 |" in markdown({"summary": summarize([row])})
    old = _row("DLO3-50s", (0.7, 2.5, 10.0, 2.1), (0.6, 2.2, 9.0, 2.0), (2.0, 5.5, 40.0, 5.0))
    assert "| - / - / - |" in markdown({"summary": summarize([old])})  # a row scored before it
