"""`deform-service` options: accepted before and after the command, bad input is one line and exit 2."""

import pytest

from service import cli

SHARED = ["--mode", "client", "--connect", "tcp/10.0.0.2:7447", "--interface", "ros2", "--domain-id", "3"]


@pytest.mark.parametrize("argv", [["run", *SHARED], [*SHARED, "run"]])
def test_shared_options_before_or_after_the_command(argv):
    cfg = cli._config(cli._parser().parse_args(argv))
    assert cfg.zenoh.mode == "client" and cfg.zenoh.connect == ["tcp/10.0.0.2:7447"]
    assert cfg.interface == "ros2" and cfg.ros2.domain_id == 3


def test_unset_options_after_the_command_keep_the_ones_before():
    cfg = cli._config(cli._parser().parse_args(["--namespace", "deform/rod7", "record", "x.mcap"]))
    assert cfg.namespace == "deform/rod7" and cfg.interface == "zenoh"


def test_bad_config_is_one_line_and_exit_2(tmp_path, capsys):
    assert cli.main(["--interface", "ros2", "--namespace", "deform/7rod", "run"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a ROS 2 name" in err[0]


def test_prebuild_builds_the_packages_a_start_loads(monkeypatch, tmp_path, model, capsys):
    """What `prebuild` builds must be what the service and its workers look up: the same batch
    sizes and iterations, and the same cache key for the worker's copy of the model (saved and
    loaded through a file) as for the model prebuild loads."""
    import torch

    import deform.aot as aot
    from deform import DeformModel, load_model
    from deform.compiled import LOOP_BRANCH_FREE, RESCUE_BATCH, RESCUE_BRANCH_FREE

    built = []

    def recorder(m, branch_free, batch, dtype, network_dtype=None):
        key = aot.package_key(m, branch_free, batch, dtype, network_dtype)
        built.append((tuple(branch_free), batch, dtype, key, torch.get_num_threads(), network_dtype))
        return tmp_path / f"step-{key}.pt2", True

    monkeypatch.setattr(aot, "ensure_package", recorder)
    config = tmp_path / "service.yaml"
    config.write_text(
        "workers:\n  predict_threads: 2\n  predict_warmup: [64, 1000]\n  predict_network_dtype: bfloat16\n"
    )
    threads_before = torch.get_num_threads()
    assert cli.main(["prebuild", "--rod", "DLO1", "--config", str(config), "--workers", "1"]) == 0
    assert torch.get_num_threads() == threads_before  # prebuild leaves the process as it found it
    # the loop's state is float64; predict rolls out in workers.predict_dtype (float32 by default)
    # 1000 plans are split across the two predict processes: 500 each, padded to the 512 bucket
    assert [b[:3] for b in built] == [
        (LOOP_BRANCH_FREE, 1, torch.float64),
        ((2, 2), 64, torch.float32),
        ((2, 2), 512, torch.float32),
        (RESCUE_BRANCH_FREE, RESCUE_BATCH, torch.float32),  # the rods a predict step left unconverged
    ]
    # each built on the threads its user runs it with: the loop's (torch_threads), predict's
    assert [b[4] for b in built] == [1, 2, 2, 2]
    # the loop's network in float32, predict's in the configured precision from 512 rods on (its
    # workers' key: deform.nn.precision.for_batch)
    assert [b[5] for b in built] == [None, None, torch.bfloat16, None]
    model.save(tmp_path / "worker.pt")  # what service/workers.py hands its child processes
    worker_copy = DeformModel.load(tmp_path / "worker.pt")
    before = torch.get_num_threads()
    try:
        for branch_free, batch, dtype, key, threads, network in built:
            torch.set_num_threads(threads)
            assert aot.package_key(worker_copy, branch_free, batch, dtype, network) == key
    finally:
        torch.set_num_threads(before)
    assert aot.package_key(load_model("DLO1"), (2, 2), 65, torch.float32) != built[1][3]


def test_prebuild_all_rods_builds_every_shipped_model(monkeypatch, tmp_path, capsys):
    """`make install` prebuilds every shipped rod's packages (issue 52: DLO4 compiled for 48 s at
    its first start), the same packages for each, once each."""
    import deform.aot as aot
    from tests.model_matrix import SHIPPED

    built = []

    def recorder(m, branch_free, batch, dtype, network_dtype=None):
        built.append((m.cfg.name, tuple(branch_free), batch, dtype))
        return tmp_path / f"step-{len(built)}.pt2", False

    monkeypatch.setattr(aot, "ensure_package", recorder)
    assert cli.main(["prebuild", "--all-rods", "--workers", "1"]) == 0
    jobs = {rod: [b[1:] for b in built if b[0] == rod] for rod in dict.fromkeys(b[0] for b in built)}
    assert list(jobs) == list(SHIPPED)
    assert all(len(j) == 3 and j == jobs["DLO1"] for j in jobs.values())  # loop, predict, rescue
    out = capsys.readouterr().out
    assert "DLO4 predict step, 64 plans:" in out and "already built" in out


def test_prebuild_side_by_side_finds_the_packages_in_worker_processes(monkeypatch, tmp_path, capsys):
    """`prebuild --workers 2` (the default on two cores) hands its jobs to spawned processes; they
    find the cache's packages under the keys computed here (placeholder files: nothing compiles)
    and each job is reported once."""
    from service.config import ServiceConfig
    from tests.service.conftest import package_paths

    monkeypatch.setenv("DEFORM_CACHE", str(tmp_path))  # the children inherit it
    paths = package_paths(ServiceConfig(rod="DLO2"))
    for path in paths.values():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"")
    assert cli.main(["prebuild", "--rod", "DLO2", "--workers", "2"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert sorted(lines[:-1]) == sorted(
        f"DLO2 {label}: {p.name} (already built)" for label, p in paths.items()
    )
    assert lines[-1] == f"cache: {tmp_path / 'aot'}"


def test_prebuild_side_by_side_stops_at_the_first_failure(monkeypatch, tmp_path, capsys):
    """A package a worker cannot build (here: the cache is a file) is one line on stderr and exit 1;
    the jobs not yet started are cancelled."""
    cache = tmp_path / "a_file"
    cache.write_text("")
    monkeypatch.setenv("DEFORM_CACHE", str(cache))
    assert cli.main(["prebuild", "--rod", "DLO2", "--workers", "2"]) == 1
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("DLO2 ") and ": not built (" in err[0]
    assert "cache:" not in captured.out


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["replay", "{tmp}/missing.mcap"], "no such file to replay"),
        (["replay", "{tmp}/garbage.mcap"], "not a readable MCAP recording"),
        (["demo-bag", "{tmp}/no/such/dir/x.mcap", "--frames", "10"], "directory does not exist"),
    ],
)
def test_unusable_files_are_one_line_and_exit_2_before_a_session(tmp_path, capsys, monkeypatch, argv, needle):
    import service.node

    monkeypatch.setattr(service.node, "open_session", lambda *a: pytest.fail("a session was opened"))
    (tmp_path / "garbage.mcap").write_bytes(b"not an mcap file")
    assert cli.main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]
    assert not (tmp_path / "no").exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["replay", "x.mcap", "--speed", "0"],
        ["record", "x.mcap", "--duration", "-1"],
        ["demo-bag", "x.mcap", "--frames", "0"],
    ],
)
def test_bad_numbers_stop_at_parsing(tmp_path, monkeypatch, capsys, argv):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stop:
        cli.main(argv)
    assert stop.value.code == 2 and argv[-2] in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_model_file_that_is_no_checkpoint_is_one_line_and_exit_2(tmp_path, capsys):
    bad = tmp_path / "model.pt"
    bad.write_text("not a checkpoint")  # exists, so the config accepts it; its content is read at start
    assert cli.main(["prebuild", "--rod", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a DEFORM checkpoint" in err[0]


def test_run_starts_its_workers_before_it_imports_torch():
    """`deform-service run` starts its worker processes before it imports torch, so that their
    imports (3-4 s each) overlap its own (service.workers.prestart): nothing before that may import
    `deform`, which imports torch (the number types and the rod check once did, 3 s of start-up;
    a number option given, e.g. --domain-id, still imports it to parse the value)."""
    import os
    import subprocess
    import sys

    code = (
        "import subprocess, sys\n"
        "def started(*args, **kwargs):\n"
        "    print('torch' in sys.modules, flush=True)\n"
        "    raise SystemExit(0)\n"
        "subprocess.Popen = started\n"
        "from service import cli\n"
        "cli.main(['run', '--rod', 'DLO4'])\n"
    )
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.stdout.strip() == "False", out.stderr[-2000:]
