import os
import shutil

import pytest
import torch

torch.set_num_threads(1)  # small tensors: one thread is fastest, and CI has two cores

from deform.io.recordings import find_data_root  # noqa: E402 (after the thread setting)

# torch.compile / AOTInductor compile C++ with $CXX, else g++ (torch._inductor.config.cpp.cxx on Linux)
CXX = shutil.which(os.environ.get("CXX") or "g++")


@pytest.hookimpl(tryfirst=True)  # before pytest's own -m selection, which then sees the added markers
def pytest_collection_modifyitems(config, items):
    no_cxx = pytest.mark.skip(
        reason=f"no C++ compiler ({os.environ.get('CXX') or 'g++'} not on PATH; "
        "set CXX): torch.compile / AOTInductor cannot build"
    )
    for item in items:
        if "data_root" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.needs_data)
        if CXX is None and item.get_closest_marker("compile"):
            item.add_marker(no_cxx)


@pytest.fixture(scope="session", autouse=True)
def _private_deform_cache(tmp_path_factory):
    """Compiled packages (``deform.aot``, ``$DEFORM_CACHE``) go to a directory of this session: tests
    neither reuse nor write the user's ``~/.cache/deform``. Set in ``os.environ`` so worker
    processes started by the tests inherit it."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DEFORM_CACHE", str(tmp_path_factory.mktemp("deform-cache")))
        yield


@pytest.fixture(scope="session", autouse=True)
def _fused_pieces_eager():
    """The discrepancy tool's fused pieces (``deform.rod.fusion``) run eagerly (``DEFORM_COMPILE=0``)
    but in tests marked ``compile``: on a fresh machine each traced variant compiles C++ for
    seconds (the control diagnosis of test_detection.py: 26 s eager, 127 s compiled from an empty cache), and the compiled pieces'
    values and gradients are tested against eager where marked (tests/deform/rod/test_fusion.py: a
    model with fused pieces steps and differentiates as eager). Set in ``os.environ`` so that worker
    processes inherit it."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DEFORM_COMPILE", "0")
        yield


@pytest.fixture(autouse=True)
def _fused_pieces_where_marked(request, monkeypatch):
    if request.node.get_closest_marker("compile"):
        monkeypatch.delenv("DEFORM_COMPILE", raising=False)  # the default: fused pieces compiled


@pytest.fixture(scope="session")
def data_root():
    """The DEFORM recordings (``../shared/data/deform`` or ``$DEFORM_DATA``); tests using it are
    marked ``needs_data`` (see ``pytest_collection_modifyitems``)."""
    root = find_data_root()
    if root is None or not (root / "DLO1").is_dir():
        pytest.skip("DEFORM dataset not available (set DEFORM_DATA)")
    return root


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
