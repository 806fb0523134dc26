"""`python -m calibrate`: a model deform.load_model loads; bad input is one line, exit code 2 and
nothing written; clips too still give a report that says so and no model."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from benchmarks.calibration.unreadable import shipped_files, withheld
from calibrate.cli import CLOCK_FROM_PARENT, main
from deform import bend_per_linear_density, load_model
from service.bag import write_messages

from .conftest import LENGTH, MASS, N

TINY = ["--iterations", "3", "--refine-iterations", "2", "--rounds", "1", "--horizon", "20", "--batch", "2"]


def _args(clips, bags, out: Path, *extra):
    return [
        *map(str, bags),
        "--length",
        str(LENGTH),
        "--mass",
        str(MASS),
        "--vertices",
        str(N),
        "--config",
        str(clips.config),
        "--out",
        str(out / "rope.pt"),
        *TINY,
        *extra,
    ]


@pytest.fixture(scope="module")
def calibrated(clips, tmp_path_factory) -> tuple[dict, Path]:
    """``python -m calibrate`` run once on the clips, as a user runs it: (its summary line, out dir).
    As in the acceptance, the rope calibrated (DLO3 here) has no part in the prior and its shipped
    files are out of reach: its processes cannot open them."""
    out_dir = tmp_path_factory.mktemp("calibrated")
    root = Path(__file__).resolve().parents[2]
    argv = _args(clips, clips.bags, out_dir, "--prior-without", "DLO3")
    with withheld(shipped_files("DLO3")) as env:
        env["PYTHONPATH"] += os.pathsep + str(root)
        out = subprocess.run(
            [sys.executable, "-m", "calibrate", *argv],
            capture_output=True,
            text=True,
            env=dict(env, OMP_NUM_THREADS="1"),
            timeout=300,
        )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1]), out_dir


@pytest.mark.slow  # a whole calibration: tens of seconds
def test_calibrate_writes_a_model_that_load_model_loads(calibrated):
    summary, out_dir = calibrated
    model = load_model(summary["model"])
    assert model.n == N and model.cfg.length_m == LENGTH and model.cfg.mass_kg == MASS
    report = json.loads((out_dir / "rope_report" / "report.json").read_text())
    prior = report["inputs"]["stiffness_prior"]
    assert prior["without"] == ["DLO3"] and prior["bend_per_linear_density"] == bend_per_linear_density(
        ["DLO3"]
    )
    assert prior["from"] == ["DLO1", "DLO2", "DLO4", "DLO5"]
    assert report["model_written"] and report["held_out_clips"] == ["clip0"]
    assert len(report["coverage_per_vertex"]) == N and report["rounds"][0]["round"] == 0
    # the default time limit is far away: the rounds train their whole budget, and nothing is noted
    assert report["rounds"][1]["train"]["iterations"] == 3 and not report["rounds"][1]["cut_by_time_limit"]
    assert report["time_limit_notes"] == [] and 1100 < report["inputs"]["budget"]["time_limit_s"] <= 1200
    told = report["identified"]["told_within"]  # each parameter's range, from the held-out clips
    assert set(told) == {"bend_stiffness_Nm2", "damping_per_s", "drag_per_m"}
    found = report["identified"]["found"]["bend_stiffness_Nm2"]
    assert all(v is None or v > 0 for span in told.values() for v in span)
    assert told["bend_stiffness_Nm2"][0] is None or told["bend_stiffness_Nm2"][0] < found
    md = (out_dir / "rope_report" / "report.md").read_text()
    assert "| told within |" in md and "Gripper poses in: world." in md
    assert "the median over the shipped ropes DLO1, DLO2, DLO4, DLO5." in md
    assert f"deform-service prebuild --rod {summary['model']}`" in md  # what to run next, with this model
    delay = report["inputs"]["cloud_delay"]  # our renderer's clouds are stamped when taken
    assert (
        delay["delay_s"] == 0.0 and delay["clouds"] > 0 and "Cloud stamps: on the gripper poses' clock" in md
    )
    assert {t["gripper_poses_frame"] for t in report["tracks"]} == {"world"}
    assert {"report.md", "coverage.png", "fit.png"} <= {p.name for p in (out_dir / "rope_report").iterdir()}
    # the bending scheme the model steps with is the one reported, with the model's step ratio
    scheme = report["identified"]["found"]
    assert scheme["implicit_bending"] == model.cfg.implicit_bending
    assert scheme["substeps"] == model.cfg.substeps
    assert scheme["bending_step_ratio"] == pytest.approx(model.bending_step_ratio(), abs=1e-3)
    assert f"Bending stepped {'implicitly' if scheme['implicit_bending'] else 'explicitly'}" in md


@pytest.mark.slow  # a whole calibration: tens of seconds
@pytest.mark.zenoh
def test_the_service_serves_a_calibrated_model(calibrated):
    """``deform-service run --rod MODEL.pt`` with the file calibrate wrote: the service starts on it,
    answers ``vertices`` with its vertex count and a predict that moves the rope as planned."""
    from service.demo import free_port
    from tests.service.conftest import make_config
    from tests.service.test_every_model import serve_and_predict

    summary, _ = calibrated
    cfg = make_config(
        f"tcp/127.0.0.1:{free_port()}",
        namespace="deform/calibrated",
        rod=summary["model"],
        workers={"processes": False, "compile_predict": False, "predict_processes": 1},
    )
    status, shapes = serve_and_predict(cfg, plans=3, steps=10, ready_s=60.0)
    assert status["predict_failed"] is None and shapes.shape == (3, 10, N, 3)
    assert shapes[2, -1, :, 2].mean() > shapes[0, -1, :, 2].mean()


def _refused(capsys, argv, match: str, out: Path) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("deform calibrate: error:") and match in err, err
    assert list(out.iterdir()) == []


@pytest.mark.parametrize(("drop", "match"), [("ee_poses", "no gripper poses"), ("points", "no clouds")])
def test_a_bag_without_poses_or_clouds(clips, tmp_path, capsys, drop, match):
    bag = tmp_path / "in" / "bad.mcap"
    bag.parent.mkdir()
    write_messages(bag, "deform/rod1", [m for m in clips.messages if m.name != drop])
    out = tmp_path / "out"
    out.mkdir()
    _refused(capsys, _args(clips, [bag], out), match, out)


def test_a_colour_range_that_finds_no_rope(clips, tmp_path, capsys):
    settings = tmp_path / "blue.yaml"
    settings.write_text(
        yaml.safe_dump({"segmentation": {"hsv_low": [100, 120, 60], "hsv_high": [130, 255, 255]}})
    )
    out = tmp_path / "out"
    out.mkdir()
    _refused(capsys, _args(clips, clips.bags[:1], out, "--perception", str(settings)), "finds no rope", out)


@pytest.mark.parametrize(("length", "match"), [("0.6", "more than --length"), ("1.6", "never reaches")])
def test_a_length_the_camera_contradicts(clips, tmp_path, capsys, length, match):
    out = tmp_path / "out"
    out.mkdir()
    argv = _args(clips, clips.bags[:1], out)
    argv[argv.index("--length") + 1] = length
    _refused(capsys, argv, match, out)


def test_bad_settings_and_model_name(clips, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    every_rod = ["--prior-without", "DLO1", "DLO2", "DLO3", "DLO4", "DLO5"]
    _refused(capsys, _args(clips, clips.bags[:1], out, *every_rod), "no shipped rod is left", out)
    _refused(
        capsys,
        _args(clips, clips.bags[:1], out, "--config", str(tmp_path / "none.yaml")),
        "no such file",
        out,
    )
    argv = _args(clips, clips.bags[:1], out)
    argv[argv.index("--out") + 1] = str(out / "rope.model")
    _refused(capsys, argv, "must end in .pt", out)


def test_a_rod_that_is_not_shipped_here_has_no_part_in_the_prior_anyway():
    from calibrate.cli import _prior

    assert _prior(["DLO9"]) == (bend_per_linear_density(), ["DLO1", "DLO2", "DLO3", "DLO4", "DLO5"])


def test_clips_too_still_give_a_report_and_no_model(clips, still_bag, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(_args(clips, [still_bag], out)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "too still" in err
    assert not (out / "rope.pt").exists()
    report = json.loads((out / "rope_report" / "report.json").read_text())
    assert not report["model_written"] and "too still" in report["problem"]
    assert "No model was written" in (out / "rope_report" / "report.md").read_text()


@pytest.mark.slow
def test_the_time_limit_counts_from_the_commands_start():
    """``--time-limit`` promises the whole command: the clock starts when the process did (Python's
    start and the imports count), or when ``deform calibrate``, its parent, did. A parent that waited
    1.5 s before starting the child is 1.5 s older than it."""
    child = (
        "import json, time; from calibrate.cli import command_age_s, process_started_at; "
        "print(json.dumps([command_age_s(), time.time() - process_started_at()]))"
    )
    parent = (
        "import os, subprocess, sys, time; time.sleep(1.5); "
        f"env = {{k: v for k, v in os.environ.items() if k != {CLOCK_FROM_PARENT!r}}}; "
        f"subprocess.run([sys.executable, '-c', {child!r}], env=env, check=True); "
        f"subprocess.run([sys.executable, '-c', {child!r}], env=dict(env, {CLOCK_FROM_PARENT}='1'), check=True)"
    )
    root = Path(__file__).resolve().parents[2]
    out = subprocess.run(
        [sys.executable, "-c", parent],
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(root)),
        timeout=120,
        check=True,
    )
    (alone, own), (from_parent, own_too) = (json.loads(line) for line in out.stdout.splitlines())
    assert 0.2 < own < 60.0 and alone == pytest.approx(own, abs=0.2)  # its own start, imports included
    assert from_parent >= own_too + 1.4


def test_deform_calibrate_tells_its_child_to_count_from_its_start(monkeypatch):
    from deform import cli

    seen = {}

    def fake_call(cmd, env):
        seen.update(cmd=cmd, env=env)
        return 0

    monkeypatch.setattr(subprocess, "call", fake_call)
    assert cli.cmd_calibrate(["clip.mcap"]) == 0
    assert seen["cmd"][1:] == ["-m", "calibrate", "clip.mcap"] and seen["env"][CLOCK_FROM_PARENT] == "1"
