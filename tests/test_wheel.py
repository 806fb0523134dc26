"""The built wheel works outside the checkout: configs and models are package data, no path leads
back into the source tree, and the `deform` and `deform-service` commands run.

The wheel is installed without dependencies into a fresh venv that sees this interpreter's
site-packages through a path file (installing torch and the rest again is `make install`'s job);
the path file adds that directory without running its own path files, so the checkout's editable
install stays out."""

import os
import site
import subprocess
import sys
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow

CHECK = """
import sys
from pathlib import Path
import deform, perception, service
root = Path(sys.argv[1])
for mod in (deform, perception, service):
    assert root not in Path(mod.__file__).resolve().parents, mod.__file__
from deform import available_rods, generate_recording, load_model, save_recording
from deform.config import load_rod_config
assert available_rods() == ["DLO1", "DLO2", "DLO3", "DLO4", "DLO5"], available_rods()
for rod in available_rods():
    load_rod_config(rod)
model = load_model("DLO2")
assert model.residual is not None and float(model.log_beta.exp().mean()) != model.cfg.bend_stiffness
from deform.terms import attached_names
assert attached_names(load_model("DLO1")) == ["internal_damping"]  # a trained-in term loads from the wheel
from service.config import load_config
from perception import load_config as perception_config
assert load_config().rod == "DLO1" and perception_config().tracker.stale_after_s > 0
out = Path(sys.argv[2])
out.mkdir()
for seed in range(2):
    save_recording(out / f"{seed}.pkl", generate_recording(model, n_frames=30, seed=seed).positions)
print("ok")
"""


def test_wheel_installs_and_runs_outside_the_checkout(tmp_path):
    wheels = tmp_path / "wheels"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            str(ROOT),
            "-w",
            str(wheels),
        ],
        check=True,
        capture_output=True,
    )
    (wheel,) = wheels.glob("*.whl")
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    py = env_dir / "bin" / "python"
    target = subprocess.run(
        [str(py), "-c", "import site; print(site.getsitepackages()[0])"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    (Path(target) / "zz_dependencies.pth").write_text(site.getsitepackages()[0] + "\n")
    subprocess.run(
        [str(py), "-m", "pip", "install", "-q", "--no-deps", str(wheel)], check=True, capture_output=True
    )
    run_dir = tmp_path / "elsewhere"
    run_dir.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH",)}
    check = subprocess.run(
        [str(py), "-c", CHECK, str(ROOT), str(run_dir / "recs")],
        cwd=run_dir,
        env=env,
        capture_output=True,
        text=True,
    )
    assert check.returncode == 0 and check.stdout.strip() == "ok", check.stderr[-2000:]
    bin_dir = env_dir / "bin"
    out = subprocess.run(
        [str(bin_dir / "deform"), "eval", "--rod", "DLO2", "--recordings", "recs", "--steps", "20", "--json"],
        cwd=run_dir,
        env=env,
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0 and '"l1_m"' in out.stdout, out.stderr[-2000:]
    out = subprocess.run(
        [str(bin_dir / "deform-service"), "--help"], cwd=run_dir, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0 and "deform-service" in out.stdout
