"""A process started with `withheld` cannot open the withheld files, nor can the processes it spawns;
every other file opens as before."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.calibration.unreadable import shipped_files, withheld

ROOT = Path(__file__).resolve().parents[2]

PROBE = """
import json, multiprocessing as mp, sys


def try_load(rod):
    from deform import load_model
    try:
        load_model(rod)
    except Exception as exc:  # deform.errors.CheckpointError: the file cannot be read
        return "refused: " + str(exc)
    return "loaded"


if __name__ == "__main__":
    with mp.get_context("spawn").Pool(1) as pool:  # as calibrate's workers start
        spawned = pool.apply(try_load, ("DLO3",))
    print(json.dumps({"DLO3": try_load("DLO3"), "DLO1": try_load("DLO1"), "spawned DLO3": spawned}))
"""


def _probe(tmp_path, env) -> dict:
    script = tmp_path / "probe.py"
    script.write_text(PROBE)
    env = dict(env, PYTHONPATH=os.pathsep.join(p for p in (env.get("PYTHONPATH"), str(ROOT)) if p))
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_the_withheld_rods_files_cannot_be_opened_even_by_spawned_workers(tmp_path):
    with withheld(shipped_files("DLO3")) as env:
        seen = _probe(tmp_path, env)
    assert seen["DLO3"].startswith("refused") and "deform/models/DLO3.pt: cannot be read" in seen["DLO3"]
    assert seen["spawned DLO3"].startswith("refused")
    assert seen["DLO1"] == "loaded"


@pytest.mark.slow
def test_without_withholding_the_same_probe_loads_every_rod(tmp_path):
    seen = _probe(tmp_path, dict(os.environ))
    assert seen == {"DLO3": "loaded", "DLO1": "loaded", "spawned DLO3": "loaded"}


def test_an_absolute_or_empty_path_end_is_refused():
    for ends in (["/etc/passwd"], [""]):
        with pytest.raises(ValueError, match="relative"), withheld(ends):
            pass
