"""`deform-service` options: accepted before and after the command, bad input is one line and exit 2."""

import pytest

from service import cli


@pytest.mark.parametrize(
    "argv",
    [
        [
            "run",
            "--mode",
            "client",
            "--connect",
            "tcp/10.0.0.2:7447",
            "--interface",
            "ros2",
            "--domain-id",
            "3",
        ],
        [
            "--mode",
            "client",
            "--connect",
            "tcp/10.0.0.2:7447",
            "--interface",
            "ros2",
            "--domain-id",
            "3",
            "run",
        ],
    ],
)
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
