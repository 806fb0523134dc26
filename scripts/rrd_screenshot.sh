#!/usr/bin/env bash
# Screenshot of the Rerun viewer showing an .rrd file, without a display or a GPU.
#
#   scripts/rrd_screenshot.sh RRD PNG [FRACTION]
#
#   e.g. .venv/bin/python -m service.demo --frames 300 --rrd /tmp/demo.rrd
#        scripts/rrd_screenshot.sh /tmp/demo.rrd docs/demo_rerun.png
#
# FRACTION (default 0.66) is where on the active timeline the time cursor is put,
# 0 = first message, 1 = last.
#
# How: the viewer runs with `rerun --headless` (an offscreen egui harness, no X server,
# no window) and is driven over gRPC with rerun.experimental.ViewerClient: wait until the
# recording has loaded, lay the views out as a large 3D view beside the time series (the
# text log is dropped), hide the side panels, collapse the time panel to its time bar,
# point the 3D camera at the bounding box of the FOCUS entity over the whole recording
# (read from the .rrd; default /world/rope, the viewer's own camera if FOCUS is empty or
# the entity has no positions), pause at FRACTION, save a screenshot, and write it as a
# 256-colour PNG (a few times smaller than the raw one).
#
# Needs (Debian 12): the Mesa software Vulkan driver (lavapipe/llvmpipe) and the Vulkan loader
#   apt-get install -y mesa-vulkan-drivers libvulkan1
# Xvfb is NOT needed for --headless. Without a Vulkan driver the viewer stops with
# "No graphics adapter was found" (per the rerun-sdk docs of ViewerClient.spawn).
# Python side: the repo venv with rerun-sdk (>= 0.41, for ViewerClient and --headless) and pillow.
#
# Environment overrides: RERUN (viewer binary), PYTHON (interpreter with rerun-sdk + pillow),
# PORT (gRPC port of the viewer; default: a free one), SIZE (window size, default 1600x1000),
# FOCUS (entity path the 3D camera frames, default /world/rope; empty: the viewer's camera).
set -euo pipefail

if [[ $# -lt 2 || $# -gt 3 ]]; then
    echo "usage: $0 RRD PNG [FRACTION]" >&2
    exit 2
fi
RRD=$(realpath "$1")
PNG=$(realpath -m "$2")
FRACTION=${3:-0.66}
[[ -f "$RRD" ]] || { echo "no such file: $RRD" >&2; exit 1; }

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
RERUN=${RERUN:-$ROOT/.venv/bin/rerun}
PYTHON=${PYTHON:-$ROOT/.venv/bin/python}
SIZE=${SIZE:-1600x1000}
FOCUS=${FOCUS-/world/rope}
PORT=${PORT:-$("$PYTHON" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')}

WORK=$(mktemp -d)
LOG=$WORK/viewer.log
VIEWER_PID=
cleanup() {
    if [[ -n "$VIEWER_PID" ]] && kill -0 "$VIEWER_PID" 2>/dev/null; then
        # its own process group: .venv/bin/rerun is a Python wrapper around the real binary
        kill -- -"$VIEWER_PID" 2>/dev/null || true
        wait "$VIEWER_PID" 2>/dev/null || true
    fi
    rm -rf "$WORK"
}
trap cleanup EXIT

# Vulkan is wgpu's default on Linux anyway; without a GPU the device it finds is lavapipe.
export WGPU_BACKEND=${WGPU_BACKEND:-vulkan}
setsid "$RERUN" --headless --port "$PORT" --window-size "$SIZE" --hide-welcome-screen "$RRD" >"$LOG" 2>&1 &
VIEWER_PID=$!

if ! "$PYTHON" - "rerun+http://127.0.0.1:$PORT/proxy" "$WORK/raw.png" "$PNG" "$FRACTION" "$VIEWER_PID" "$RRD" "$FOCUS" <<'EOF'
import os
import sys
import time
import uuid

import numpy as np
from PIL import Image
from rerun.experimental import ViewerClient

url, raw, out, frac, pid, rrd, focus = sys.argv[1:8]
frac, pid = float(frac), int(pid)


def focus_bounds(rrd: str, entity: str):
    """Bounding box of every position/line strip logged at `entity` or below it."""
    from rerun.chunk import RrdReader

    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for chunk in RrdReader(rrd).stream():
        path = chunk.entity_path
        if path != entity and not path.startswith(entity.rstrip("/") + "/"):
            continue
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if name.endswith(":positions") or name.endswith(":strips"):
                col = batch.column(name).flatten().flatten()  # rows -> points -> floats
                if name.endswith(":strips"):
                    col = col.flatten()  # strips -> points
                pts = np.asarray(col.to_numpy(zero_copy_only=False), float).reshape(-1, 3)
                if len(pts):
                    lo, hi = np.minimum(lo, pts.min(0)), np.maximum(hi, pts.max(0))
    return (lo, hi) if np.isfinite(lo).all() else None


bounds = focus_bounds(rrd, focus) if focus else None
if focus and bounds is None:
    print(f"no positions under {focus}: keeping the viewer's camera", file=sys.stderr)

deadline = time.time() + 120
client = None
while client is None:  # the viewer needs a moment before it accepts connections
    try:
        client = ViewerClient(url)
        state = client.get_state()
    except Exception:
        client = None
        os.kill(pid, 0)  # raises if the viewer died
        if time.time() > deadline:
            sys.exit("could not connect to the viewer")
        time.sleep(1)

while not (state.recordings and state.active_recording and not state.loading):
    if time.time() > deadline:
        sys.exit(f"the viewer did not finish loading: {state}")
    time.sleep(1)
    state = client.get_state()

rec = next(r for r in state.recordings if r.store_id == state.active_recording)
timeline = next(t for t in rec.timelines if t.name == rec.current_timeline)

# Layout: the 3D view(s) on the left, the time series stacked on the right, the rest dropped.
bp = dict(client.get_blueprint().blueprint)
root = bp["/viewport"]["ViewportBlueprint"]["root_container"]
views3d = [f"/view/{v.view_id}" for v in state.views if v.view_class == "3D"]
plots = [f"/view/{v.view_id}" for v in sorted(state.views, key=lambda v: v.origin) if v.view_class == "TimeSeries"]
if not views3d:
    sys.exit(f"no 3D view in the default blueprint: {state.views}")
for v in state.views:
    if v.view_class not in ("3D", "TimeSeries"):
        for key in [k for k in bp if k.startswith(f"/view/{v.view_id}/")]:
            del bp[key]
        bp[f"/view/{v.view_id}"] = {"Clear": {"is_recursive": True}}
contents, shares = list(views3d), [2.2] * len(views3d)
if plots:
    side = str(uuid.uuid4())
    bp[f"/container/{side}"] = {"ContainerBlueprint": {"container_kind": "Vertical", "contents": plots, "visible": True}}
    contents.append(f"/container/{side}")
    shares.append(1.0)
bp[f"/container/{root}"] = {"ContainerBlueprint": {
    "container_kind": "Horizontal", "contents": contents, "col_shares": shares, "visible": True}}
bp["/blueprint_panel"] = {"PanelBlueprint": {"state": "Hidden"}}
bp["/selection_panel"] = {"PanelBlueprint": {"state": "Hidden"}}
bp["/time_panel"] = {"TimePanelBlueprint": {"state": "Collapsed", "play_state": "Paused"}}
if bounds is not None:  # Z up, looking at the box from the -y side, a little from above
    lo, hi = bounds
    center, diag = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)), 1e-3)
    direction = np.array([1.0, -1.5, 0.8]) / np.linalg.norm([1.0, -1.5, 0.8])
    for v in views3d:
        bp[f"{v}/EyeControls3D"] = {"EyeControls3D": {
            "kind": "Orbital", "position": (center + 1.4 * diag * direction).tolist(),
            "look_target": center.tolist(), "eye_up": [0.0, 0.0, 1.0]}}
client.set_blueprint(bp, of="recording")

t = int(timeline.start + frac * (timeline.end - timeline.start))
if timeline.time_type == "timestamp":
    client.set_time(timeline.name, timestamp=np.datetime64(t, "ns"), play_state="paused")
elif timeline.time_type == "sequence":
    client.set_time(timeline.name, sequence=t, play_state="paused")
else:
    client.set_time(timeline.name, duration=np.timedelta64(t, "ns"), play_state="paused")
time.sleep(3)  # let the software renderer settle on the new layout and time
client.save_screenshot(raw)

img = Image.open(raw).convert("RGB")
img.quantize(colors=256, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE).save(out, optimize=True)
print(f"wrote {out}: {img.size[0]}x{img.size[1]}, {os.path.getsize(out) // 1024} KiB, "
      f"{timeline.name} at {frac:.2f} of the recording, viewer {state.viewer_version}")
EOF
then
    echo "screenshot failed; viewer log:" >&2
    tail -n 30 "$LOG" >&2
    exit 1
fi
