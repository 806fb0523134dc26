"""The benchmarks' tasks (benchmarks/cluster.py) without Ray (``--inline``): every task runs with one
torch thread, a shared task is computed once, and a failing task is reported while the others go on.
Through a local Ray: tests/benchmarks/test_planted_run.py."""

import argparse

import torch

from benchmarks.cluster import Workers, add_arguments, call

COUNT = {"shared": 0}


def shared_value(x):
    COUNT["shared"] += 1
    return {"x": x, "threads": torch.get_num_threads()}


def task(i, shared):
    if i == 3:
        raise ValueError("three")
    return {"i": i, "x": shared["x"], "threads": torch.get_num_threads(), "shared_threads": shared["threads"]}


def test_inline_tasks_share_one_computation_and_a_failure_does_not_stop_the_others():
    COUNT["shared"] = 0
    got = {}
    workers = Workers(inline=True)
    shared = workers.shared(shared_value, 7)
    failures = workers.run({f"t{i}": call(task, i, shared) for i in range(5)}, got.__setitem__)
    assert set(got) == {"t0", "t1", "t2", "t4"} and set(failures) == {"t3"}
    assert "ValueError: three" in failures["t3"]
    assert COUNT["shared"] == 1
    assert {(r["x"], r["threads"], r["shared_threads"]) for r in got.values()} == {(7, 1, 1)}
    assert workers.describe() == {"ray": None, "tasks_at_once": 1}


def test_nothing_to_run_starts_nothing():
    workers = Workers()  # a local Ray, were there any task
    assert workers.run({}, print) == {}
    assert workers._ray is None


def test_the_options_and_the_cluster_address(monkeypatch):
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["--workers", "3"])
    assert args.num_cpus == 3 and args.address is None and not args.inline
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    assert Workers.from_args(args).describe() == {"ray": "local", "tasks_at_once": 3}
    monkeypatch.setenv("RAY_ADDRESS", "ray://head:10001")
    assert Workers.from_args(args).describe() == {"ray": "ray://head:10001", "tasks_at_once": 3}
    args = p.parse_args(["--address", "auto"])
    assert Workers.from_args(args).address == "auto"
