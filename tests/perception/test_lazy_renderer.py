"""The renderer (open3d) is loaded only when used: the tracker, and so the service's start-up, never
imports it; ``from perception import render_recording`` still works."""

import subprocess
import sys

import pytest


@pytest.mark.slow
def test_the_service_starts_without_importing_open3d():
    code = "import sys, service.node; print('open3d' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_renderer_names_resolve_on_use():
    import perception
    from perception.render import render_recording

    assert perception.render_recording is render_recording
