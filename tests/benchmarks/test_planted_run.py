"""The planted benchmark's runner (benchmarks/planted/run.py): datasets already stored are skipped
(a stopped run resumes), every other one is a task whose row is stored as it arrives, and the
tables are written from every stored row. The tasks are stand-ins (tests/benchmarks/fake_tasks.py)
returning the rows of a stored run, whose own tables they must reproduce."""

import json

import pytest

from benchmarks.planted import independent, run
from benchmarks.planted.cli import build_parser
from benchmarks.planted.config import run_config
from benchmarks.store import RunStore
from tests.benchmarks import fake_tasks

pytest.importorskip("ray")


@pytest.fixture
def fake(monkeypatch):
    calls = []

    def dataset(*a, **kw):
        calls.append(independent.dataset_key(*a[:4]))
        return fake_tasks.independent_dataset(*a, **kw)

    monkeypatch.setattr(independent, "simulate", fake_tasks.simulate)
    monkeypatch.setattr(independent, "independent_dataset", dataset)
    return calls


def args_for(tmp_path, *extra):
    return build_parser().parse_args([*fake_tasks.ARGS, "--runs", str(tmp_path / "x.runs"), *extra])


def stored_summary() -> dict:
    return json.loads((fake_tasks.RESULTS / f"{fake_tasks.STEM}.json").read_text())


def test_a_run_stores_every_dataset_and_resumes_with_the_ones_not_stored(tmp_path, fake):
    args = args_for(tmp_path, "--inline")
    rows = fake_tasks.stored_rows()
    store = RunStore.for_runs(args.runs)
    first = list(rows)[:2]
    for key in first:  # a stopped run stored two datasets
        store.save(rows[key])
    assert run.run_benchmark(args, results=tmp_path, argv=[]) == 0
    assert sorted(fake) == sorted(set(rows) - set(first))  # only the others ran
    stored = store.load(run_config(args))
    assert set(stored) == set(rows)
    assert len(list(store.directory.rglob("*.json"))) == len(rows)  # one file per dataset
    # the tables: the stored run's own summary, from the same rows
    result = json.loads((tmp_path / "diagnose.mujoco.json").read_text())
    assert result["summary"] == stored_summary()["summary"]
    assert "named correctly" in (tmp_path / "diagnose.mujoco.md").read_text()
    assert {"command", "commit", "machine", "workers"} <= set(result)
    fake.clear()
    assert run.run_benchmark(args, results=tmp_path, argv=[]) == 0
    assert fake == []  # all stored: nothing runs again


def test_summary_only_runs_nothing_and_reads_an_old_runs_file(tmp_path, fake):
    legacy = tmp_path / "x.runs.jsonl"
    legacy.write_text(fake_tasks.ROWS.read_text())
    args = args_for(tmp_path, "--summary-only")
    assert run.run_benchmark(args, results=tmp_path, argv=[]) == 0
    assert fake == []
    result = json.loads((tmp_path / "diagnose.mujoco.json").read_text())
    assert result["summary"] == stored_summary()["summary"]
    assert result["runs_file"] == "x.runs.jsonl and x.runs/"
    # the tables as the stored run wrote them, all but the line naming the command and machine
    new = (tmp_path / "diagnose.mujoco.md").read_text().splitlines()
    old = (fake_tasks.RESULTS / f"{fake_tasks.STEM}.md").read_text().splitlines()
    assert len(new) == len(old)
    assert [(a, b) for a, b in zip(new, old) if a != b and not a.startswith("Run: ")] == []


def test_a_failed_dataset_is_reported_and_the_others_are_stored(tmp_path, monkeypatch):
    monkeypatch.setattr(independent, "simulate", fake_tasks.simulate)
    monkeypatch.setattr(independent, "independent_dataset", fake_tasks.failing_dataset)
    args = args_for(tmp_path, "--inline")
    assert run.run_benchmark(args, results=tmp_path, argv=[]) == 1
    stored = RunStore.for_runs(args.runs).load(run_config(args))
    assert set(fake_tasks.stored_rows()) - set(stored) == {"mujoco:light:point_mass:0"}


@pytest.mark.slow  # starts a local Ray (about 10 s)
def test_the_datasets_run_as_ray_tasks_with_one_torch_thread_each(tmp_path, monkeypatch):
    monkeypatch.setattr(independent, "simulate", fake_tasks.simulate)
    monkeypatch.setattr(independent, "independent_dataset", fake_tasks.independent_dataset)
    monkeypatch.setenv("PYTHONPATH", "")  # restored after the test (the runner extends it)
    args = args_for(tmp_path, "--num-cpus", "2")
    assert run.run_benchmark(args, results=tmp_path, argv=[]) == 0
    stored = RunStore.for_runs(args.runs).load(run_config(args))
    assert set(stored) == set(fake_tasks.stored_rows())
    assert {r["task_threads"] for r in stored.values()} == {1}
    result = json.loads((tmp_path / "diagnose.mujoco.json").read_text())
    assert result["workers"] == {"ray": "local", "tasks_at_once": 2}
    assert result["summary"] == stored_summary()["summary"]


def test_names_against_another_run_and_the_wall_time_a_summary_keeps(tmp_path, fake):
    args = args_for(tmp_path, "--inline")
    assert run.run_benchmark(args, results=tmp_path, argv=[]) == 0
    wall = json.loads((tmp_path / "diagnose.mujoco.json").read_text())["run_wall_s"]
    # another run of the same datasets that named one of them differently
    other = stored_summary()
    changed = other["planted"][0]
    changed["selected"] = ["point_mass"] if changed["selected"] != ["point_mass"] else []
    (tmp_path / "other.json").write_text(json.dumps(other))
    args = args_for(tmp_path, "--summary-only", "--names-against", "other")
    assert run.run_benchmark(args, results=tmp_path, argv=[]) == 0
    result = json.loads((tmp_path / "diagnose.mujoco.json").read_text())
    against = result["names_against"]
    assert against["datasets"] == len(other["planted"])
    assert against["same"] == against["datasets"] - 1
    assert [d["key"] for d in against["differ"]] == [changed["key"]]
    assert against["same_first"] == against["datasets"]  # the names re-derived from the scores: unchanged
    assert result["run_wall_s"] == wall  # the wall time of the run that stored the rows is kept
