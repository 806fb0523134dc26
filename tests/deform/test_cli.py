"""The command line: clear one-line errors, non-zero exit, nothing written; eval JSON fields."""

import json
import os
import pickle
import subprocess
import sys

import numpy as np
import pytest

from deform import DeformModel, generate_recording, load_rod_config, save_recording
from deform.cli import main


def _run(*args, cwd=None):
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    return subprocess.run(
        [sys.executable, "-m", "deform.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=300,
    )


@pytest.fixture(scope="module")
def synthetic_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("recs")
    model = DeformModel(load_rod_config("DLO2"))
    for s in range(2):
        save_recording(d / f"{s}.pkl", generate_recording(model, n_frames=40, seed=s).positions)
    return d


@pytest.mark.slow
def test_eval_json_on_a_directory_of_unseen_recordings(synthetic_dir):
    out = _run("eval", "--rod", "DLO2", "--recordings", str(synthetic_dir), "--json", "--steps", "30")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    for key in ("rod", "recordings", "steps", "l1_m", "mean_vertex_dist_m", "l1_by_horizon_m", "step_ms_p50"):
        assert key in result
    assert result["recordings"] == 2 and result["steps"] == 30
    assert set(result["l1_by_horizon_m"]) == {"1", "10", "100", "500"}
    assert 0 < result["l1_m"] < 0.05


@pytest.mark.slow
def test_eval_of_a_model_with_another_vertex_count_than_the_markers(synthetic_dir, tmp_path):
    """A 9-vertex model on 12-marker recordings: compared at the markers, by arc length. The
    recordings' own rod (12 vertices, which made them) scores nearly zero; the coarser rod is close
    to it, but not exact."""
    scores = {}
    for n in (12, 9):
        DeformModel(load_rod_config("DLO2").model_copy(update={"n_vertices": n})).save(tmp_path / f"{n}.pt")
        out = _run("eval", "--model", str(tmp_path / f"{n}.pt"), "--recordings", str(synthetic_dir), "--json")
        assert out.returncode == 0, out.stderr
        scores[n] = json.loads(out.stdout)
    assert scores[9]["steps"] == scores[12]["steps"] == 38
    assert scores[12]["l1_m"] < 1e-4 < scores[9]["l1_m"] < 0.01


@pytest.mark.parametrize(
    "setup, args, message",
    [
        ("empty", ["eval", "--rod", "DLO2"], "no .pkl recordings"),
        ("hostile", ["eval", "--rod", "DLO2"], "refusing to load global"),
        ("nan", ["eval", "--rod", "DLO2"], "NaN"),
        ("wrong_n", ["eval", "--rod", "DLO2"], "needs at least 5 markers, has 4"),
        ("ok", ["eval", "--method", "hold_shape"], "eval needs --rod, or --model and --recordings"),
        ("ok", ["eval", "--rod", "DLO9"], "unknown rod 'DLO9'"),
        ("empty", ["train", "--rod", "DLO2", "--iterations", "1"], "no .pkl recordings"),
        ("gap", ["train", "--rod", "DLO2", "--iterations", "1"], "marker 4 is missing for 30 frames"),
        ("y_up", ["train", "--rod", "DLO2", "--iterations", "1"], "the rope hangs along -y"),
    ],
)
def test_bad_input_gives_one_error_line_and_writes_nothing(
    tmp_path, monkeypatch, capsys, setup, args, message
):
    d = tmp_path / "recs"
    d.mkdir()
    if setup == "hostile":
        (d / "evil.pkl").write_bytes(b"cos\nsystem\n(S'echo hi'\ntR.")
    elif setup == "nan":
        (d / "a.pkl").write_bytes(pickle.dumps([np.full((3, 12), np.nan)] * 5))
    elif setup == "wrong_n":
        (d / "a.pkl").write_bytes(pickle.dumps([np.zeros((3, 4))] * 5))
    elif setup == "gap":  # 0.3 s without marker 4: longer than train's --max-gap
        frames = [np.stack([np.linspace(0, 0.6, 12), np.zeros(12), np.full(12, 0.3)]) for _ in range(60)]
        for f in frames[10:40]:
            f[:, 4] = np.nan
        (d / "a.pkl").write_bytes(pickle.dumps(frames))
    elif setup == "y_up":  # a rope hanging 10 cm, exported with y up
        s = np.linspace(0, 1, 12)
        frame = np.stack([0.9 * s, 0.4 - 0.1 * np.sin(np.pi * s), np.zeros(12)])
        (d / "a.pkl").write_bytes(pickle.dumps([frame] * 60))
    elif setup == "ok":
        (d / "a.pkl").write_bytes(pickle.dumps([np.zeros((3, 12))] * 5))
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    code = main(
        [*args, "--recordings", str(d), *(["--out", str(work / "run")] if args[0] == "train" else [])]
    )
    assert code == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], err
    assert list(work.iterdir()) == []


def test_train_fills_a_short_marker_gap_and_says_so(tmp_path, monkeypatch, capsys, synthetic_dir):
    import deform.train

    d = tmp_path / "recs"
    d.mkdir()
    for i, f in enumerate(sorted(synthetic_dir.glob("*.pkl"))):
        frames = pickle.loads(f.read_bytes())
        if i == 0:
            for frame in frames[20:25]:  # 50 ms without marker 6
                frame[:, 6] = np.nan
        (d / f.name).write_bytes(pickle.dumps(frames))
    seen = []

    def stop(model, train_recs, val_recs, *a, **k):
        seen.extend(train_recs + val_recs)
        raise SystemExit(0)

    monkeypatch.setattr(deform.train, "train", stop)
    with pytest.raises(SystemExit):
        main(
            [
                "train",
                "--rod",
                "DLO2",
                "--recordings",
                str(d),
                "--out",
                str(tmp_path / "run"),
            ]
        )
    assert len(seen) == 2 and not any(np.isnan(r.positions).any() for r in seen)
    assert "5 marker-frame(s) filled" in capsys.readouterr().err


@pytest.mark.parametrize("bending", ["implicit", "explicit"])
def test_train_steps_the_bending_as_told(tmp_path, synthetic_dir, bending):
    """`--bending` fixes the scheme for the whole run, the coarse identification included (a 65 g
    rope at the grid's stiff points would otherwise switch), and the model file keeps it."""
    out = tmp_path / "run"
    args = ["train", "--rod", "DLO2", "--recordings", str(synthetic_dir), "--out", str(out)]
    main([*args, "--bending", bending, "--iterations", "1", "--batch", "2", "--horizon", "5"])
    assert DeformModel.load(out / "best.pt").cfg.implicit_bending == (bending == "implicit")


@pytest.mark.parametrize(
    "args",
    [
        ["train", "--iterations", "0"],
        ["train", "--batch", "0"],
        ["train", "--horizon", "-1"],
        ["train", "--curriculum", "10", "0"],
        ["train", "--threads", "0"],
        ["train", "--val-every", "0"],
        ["train", "--time-limit", "-1"],
        ["train", "--lr-physics", "nan"],
        ["train", "--max-gap", "-0.1"],
        ["train", "--bending", "sideways"],
        ["eval", "--steps", "0"],
        ["diagnose", "--rod", "r.json", "--fit", "f", "--check", "c", "--out", "o", "--max-gap", "inf"],
    ],
)
def test_bad_numbers_stop_at_the_command_line_before_any_work(tmp_path, monkeypatch, capsys, args):
    """They used to end in tracebacks after creating the run directory (--iterations 0, --batch 0,
    --horizon 0, --threads 0, --steps 0)."""
    monkeypatch.chdir(tmp_path)
    rod = [] if args[0] == "diagnose" else ["--rod", "DLO2"]
    with pytest.raises(SystemExit) as stop:
        main([*args[:1], *rod, *args[1:]])
    assert stop.value.code == 2
    assert [a for a in args if a.startswith("--")][-1] in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_calibrate_runs_the_calibration_program_and_passes_its_errors_on(tmp_path, capfd):
    """`deform calibrate` runs `python -m calibrate` (a layer above the model): its arguments pass
    through unchanged, its one-line errors and exit code come back."""
    code = main(
        [
            "calibrate",
            str(tmp_path / "none.mcap"),
            "--length",
            "1",
            "--mass",
            "0.1",
            "--out",
            str(tmp_path / "m.pt"),
        ]
    )
    err = capfd.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "none.mcap: no such file" in err, err
    assert [p.name for p in tmp_path.iterdir()] == []
