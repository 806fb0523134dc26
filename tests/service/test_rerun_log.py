"""Rerun logging: a file with the shipped layout, and a stream to a viewer elsewhere (connect mode)."""

from types import SimpleNamespace

import numpy as np
import pytest

rr = pytest.importorskip("rerun")

from service.config import RerunSettings  # noqa: E402
from service.rerun_log import RerunLogger, blueprint  # noqa: E402


def _estimate(stamp_ns: int):
    x = np.linspace([-0.4, 0, 0.5], [0.4, 0, 0.5], 13)
    poses = np.array([[-0.4, 0, 0.5, 0, 0, 0, 1], [0.4, 0, 0.5, 0, 0, 1, 0]], dtype=float)
    return SimpleNamespace(
        stamp_ns=stamp_ns, x=x, observed=np.zeros(13, bool), poses=poses, grip=x[[0, 1, -2, -1]]
    )


def test_blueprint_has_the_rope_the_timings_and_the_mode():
    root = blueprint().root_container
    left, right = root.contents
    assert type(left).__name__ == "Spatial3DView"
    assert [type(v).__name__ for v in right.contents] == ["TimeSeriesView", "TimeSeriesView", "TextLogView"]


def test_file_and_connect_modes_log_without_loss(tmp_path):
    path = tmp_path / "run.rrd"
    logger = RerunLogger(RerunSettings(mode="file", path=str(path)), "deform/rod1")
    logger.start()
    for k in range(5):
        logger.submit("estimate", _estimate(k * 10**7), 0.5, 1.0, "tracking")
    logger.close()
    assert path.stat().st_size > 1000
    viewer = rr.RecordingStream("viewer_side")
    port = _free_port()
    served = viewer.serve_grpc(grpc_port=port)
    streamer = RerunLogger(RerunSettings(mode="connect", url=served), "deform/rod2")
    streamer.start()
    streamer.submit("estimate", _estimate(0), None, None, "open-loop")
    streamer.close()
    assert streamer.queue.empty()
    viewer.disconnect()


def test_rope_losses_logged_once_each(tmp_path):
    logger = RerunLogger(RerunSettings(mode="file", path=str(tmp_path / "rope.rrd")), "deform/rod3")
    rope = {"state": "tracking", "lost": 0, "recovered": 0, "redetected": 0, "disagreement": 0.0}
    logger._log_estimate(_estimate(0), None, None, "tracking", rope)
    assert logger._rope_counts == (0, 0)
    logger._log_estimate(_estimate(10**7), None, None, "tracking", {**rope, "lost": 1, "disagreement": 0.9})
    logger._log_estimate(
        _estimate(2 * 10**7), None, None, "tracking", {**rope, "lost": 1, "recovered": 1, "redetected": 1}
    )
    assert logger._rope_counts == (1, 1) and logger._length_scale == 1.0
    logger._log_estimate(
        _estimate(3 * 10**7),
        None,
        None,
        "tracking",
        {**rope, "length_scale": 0.95, "camera_over_model_mm": 1.8},
    )
    assert logger._length_scale == 0.95
    logger.rec.flush()
    logger.rec.disconnect()


def _free_port() -> int:
    from service.demo import free_port

    return free_port()
