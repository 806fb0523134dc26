"""The planted-effect benchmark's bookkeeping (benchmarks/diagnose_planted.py): parallel runs that
share a runs file share its datasets instead of running one twice."""

import json
import subprocess
import sys

from benchmarks.diagnose_planted import append_run, claim


def test_a_dataset_claimed_by_a_live_process_is_skipped_and_released_when_its_row_is_appended(tmp_path):
    runs = tmp_path / "x.runs.jsonl"
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        # the other process holds the claim (as if it had claimed first)
        assert claim("a:1", runs)
        (path,) = (runs.parent / (runs.name + ".claims")).iterdir()
        path.write_text(str(other.pid))
        assert not claim("a:1", runs)
        assert claim("b:1", runs)  # another dataset is free
    finally:
        other.kill()
        other.wait()
    # its process is gone: the claim is taken over
    assert claim("a:1", runs)
    append_run(runs, {"key": "a:1", "config": {}})
    assert json.loads(runs.read_text())["key"] == "a:1"
    claims = runs.parent / (runs.name + ".claims")
    assert not (claims / path.name).exists() and claims.exists()  # b:1 is still held
    append_run(runs, {"key": "b:1", "config": {}})
    assert not claims.exists()  # the last claim took its directory with it


def test_a_claim_being_written_counts_as_held(tmp_path):
    runs = tmp_path / "x.runs.jsonl"
    assert claim("a:1", runs)
    (path,) = (runs.parent / (runs.name + ".claims")).iterdir()
    path.write_text("")
    assert not claim("a:1", runs)
