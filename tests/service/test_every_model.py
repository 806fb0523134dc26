"""The service with every shipped model, and with a model carrying each physics term: it starts,
answers ``vertices`` and a float32 ``predict``, and (where ``make install`` prebuilt them) starts
warm on its compiled steps and answers a 64 x 100 predict with them.

Why (issue 52): with DLO4 (the wind term) predict's warm-up failed and the service kept answering
"being prepared"; nothing started the service with each model. The model alone at every entry point:
tests/deform/test_every_model.py.
"""

from __future__ import annotations

import shutil
import threading

import numpy as np
import pytest

from deform.aot import cache_dir
from service import messages as M
from service.client import ShapeClient
from service.geometry import poses_from_vertices
from service.node import Service
from tests.model_matrix import ALL_TERMS, SHIPPED, TERMS, save_term_models
from tests.service.conftest import make_config, package_paths, wait_for
from tests.service.test_zenoh import GOOD, wait_matched

pytestmark = pytest.mark.zenoh

# the user's package cache, read before tests/conftest.py points $DEFORM_CACHE at the session's own
# (a test module is imported at collection, before any session fixture runs)
USER_CACHE = cache_dir()


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    return save_term_models(tmp_path_factory.mktemp("term-models"))


class Feeder:
    """Gripper poses at 100 Hz on ``{ns}/ee_poses`` until stopped (the service needs nothing else
    for an estimate)."""

    def __init__(self, rope: ShapeClient):
        self.pub = rope.session.declare_publisher(rope.key("ee_poses"))
        assert wait_matched(rope.session, [rope.key("ee_poses")])
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        k = 0
        while not self.stop.is_set():
            self.pub.put(M.pose_array(10**9 + k * 10**7, GOOD))
            k += 1
            self.stop.wait(0.01)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()


def serve_and_predict(cfg, plans: int, steps: int, ready_s: float) -> tuple[dict, np.ndarray]:
    """Start the service with ``cfg`` (its own model: ``cfg.rod``), wait until predict is ready,
    feed poses, and ask for ``vertices`` and a predict of ``plans`` x ``steps``. -> (status once
    ready, predicted vertices)."""
    with Service(cfg) as svc, ShapeClient(cfg.namespace, connect=cfg.zenoh.listen, timeout_s=5.0) as rope:
        assert wait_for(lambda: rope.status()["predict_state"] != "preparing" and svc.step_ready, ready_s), (
            f"{cfg.rod}: predict or the loop step not ready within {ready_s} s"
        )
        status = rope.status()
        assert status["predict_state"] == "ready", status["predict_failed"]
        with Feeder(rope):
            assert wait_for(lambda: rope.status()["ticks"] > 3)
            _, x, _ = rope.vertices()
            assert x.shape == (svc.est.model.n, 3) and np.isfinite(x).all()
            base = poses_from_vertices(x.astype(float), cfg.grippers)
            lift = np.zeros((plans, steps, 2, 7))
            lift[..., 2] = (
                np.linspace(0.0, 0.03, steps)[None, :, None] * np.linspace(0, 1, plans)[:, None, None]
            )
            shapes = rope.predict(np.tile(base, (plans, steps, 1, 1)) + lift, timeout_s=60.0)
        assert shapes.shape == (plans, steps, svc.est.model.n, 3) and np.isfinite(shapes).all()
        return status, shapes


@pytest.mark.slow
@pytest.mark.parametrize("name", [*SHIPPED, *TERMS, ALL_TERMS])
def test_the_service_answers_vertices_and_a_float32_predict(name, checkpoints, endpoint):
    """Eager float32 predict (``workers.predict_dtype``'s default) in this process; DLO4 through a
    predict worker process, as ``deform-service run`` serves it."""
    rod = name if name in SHIPPED else str(checkpoints[name])
    processes = name == "DLO4"
    cfg = make_config(
        endpoint,
        namespace=f"deform/{name}",
        rod=rod,
        workers={"processes": processes, "compile_predict": False, "predict_processes": 1},
    )
    assert cfg.workers.predict_dtype == "float32"
    status, shapes = serve_and_predict(cfg, plans=3, steps=10, ready_s=60.0)
    assert status["predict_mode"] == "eager" and status["predict_failed"] is None
    # plans lifting further end higher: the rollout moved the rope as asked
    assert shapes[2, -1, :, 2].mean() > shapes[0, -1, :, 2].mean()


# ----- compiled, from the packages `make install` prebuilt ----------------------------------------


def _take_prebuilt(cfg) -> list[str]:
    """Copy the packages a start with ``cfg`` loads (``service.cli.prebuild_jobs``) from the user's
    cache into the session's, where ``make install`` (``python -m service prebuild --all-rods``)
    built them. -> the labels of those it has not (built for other sources or another machine)."""
    missing = []
    for label, ours in package_paths(cfg).items():
        theirs = USER_CACHE / ours.name
        if theirs.is_file():
            ours.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(theirs, ours)
        else:
            missing.append(label)
    return missing


@pytest.mark.slow
@pytest.mark.compile
@pytest.mark.parametrize("rod", SHIPPED)
def test_a_prebuilt_rod_starts_on_its_compiled_steps(rod, endpoint):
    """``deform-service run --rod DLOk``'s configuration (predict and loop steps ahead of time, a
    predict process; compiles nothing here) on the packages ``make install`` prebuilt: ready
    within 60 s (about 10 s on a quiet machine, benchmarks/service_startup.py --rods), on its
    compiled steps, and answers a 64 x 100 predict."""
    cfg = make_config(
        endpoint, namespace=f"deform/{rod}", rod=rod, workers={"predict_processes": 1}, compile_step=True
    )
    assert cfg.workers.compile_predict and cfg.workers.predict_ahead_of_time and cfg.step_ahead_of_time
    missing = _take_prebuilt(cfg)
    if missing:
        pytest.skip(
            f"{rod}: {', '.join(missing)} not prebuilt for this source in {USER_CACHE} "
            "(`python -m service prebuild --all-rods`, which `make install` runs)"
        )
    status, _ = serve_and_predict(cfg, plans=64, steps=100, ready_s=60.0)
    assert status["predict_mode"] == "compiled" and status["step"] == "compiled", status
