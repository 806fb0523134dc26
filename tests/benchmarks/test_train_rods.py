"""Training several rods (benchmarks/train_rods.py), with a stand-in for `deform train`: each rod is a
task whose result and best model are stored as it finishes, and a rerun trains only the rods not
stored."""

import json

from benchmarks import train_rods


def test_each_rod_is_stored_once_and_a_rerun_skips_the_stored_ones(tmp_path, monkeypatch):
    calls = []

    def fake_train(rod, train_args, out):
        calls.append((rod, tuple(train_args)))
        if rod == "DLO3":
            raise RuntimeError("diverged")
        return {"result": {"rod": rod, "out": out, "best_val_l1_m": 0.01}, "seconds": 1.0, "best_pt": b"pt"}

    monkeypatch.setattr(train_rods, "train_rod", fake_train)
    monkeypatch.setattr(train_rods, "ROOT", tmp_path)
    monkeypatch.setattr(train_rods, "RESULTS", tmp_path / "results")
    argv = ["--rods", "DLO1", "DLO2", "DLO3", "--inline", "--", "--iterations", "2"]
    assert train_rods.main(argv) == 1  # DLO3 failed; the others are stored
    assert sorted(calls) == [(r, ("--iterations", "2")) for r in ("DLO1", "DLO2", "DLO3")]
    assert (tmp_path / "runs/train_rods/DLO1/best.pt").read_bytes() == b"pt"
    stored = sorted(p.name for p in (tmp_path / "results/train_rods.runs").rglob("*.json"))
    assert stored == ["DLO1.json", "DLO2.json"]
    summary = json.loads((tmp_path / "results/train_rods.json").read_text())
    assert [r["rod"] for r in summary["rows"]] == ["DLO1", "DLO2"] and not summary["complete"]
    calls.clear()
    assert train_rods.main(argv) == 1
    assert calls == [("DLO3", ("--iterations", "2"))]  # only the rod not stored
    calls.clear()
    train_rods.main(["--rods", "DLO1", "--inline", "--", "--iterations", "3"])
    assert calls == [("DLO1", ("--iterations", "3"))]  # other options: another configuration
