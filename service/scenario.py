"""Turn a rod recording (T, n, 3) into the message stream a robot and a depth camera would send:
gripper poses every tick, rendered clouds at the camera rate, camera info and pose once.
Used by the demo, the tests and the benchmark; the ground truth stays with the caller."""

from __future__ import annotations

import logging

import numpy as np

from service import messages as M
from service.bag import Message
from service.config import GripOffsets, Grippers
from service.geometry import matrix_to_pose, poses_from_vertices

log = logging.getLogger("deform.service")
NS = 1_000_000_000


def offsets_for(positions: np.ndarray) -> Grippers:
    """Gripper offsets that reproduce the recording's end edges (the markers sit 2-4 cm apart)."""
    p = np.asarray(positions)
    first = float(np.median(np.linalg.norm(p[:, 1] - p[:, 0], axis=-1)))
    last = float(np.median(np.linalg.norm(p[:, -2] - p[:, -1], axis=-1)))
    return Grippers(first=GripOffsets(d0=0.0, d1=first), last=GripOffsets(d0=0.0, d1=last))


def render(positions: np.ndarray, dt: float, fps: float, seed: int = 0):
    """perception's renderer, or an empty list when perception is not installed."""
    try:
        try:
            from perception import render_recording
        except ImportError:
            from perception.render import render_recording
    except ImportError:
        log.warning("perception renderer not available: the stream has no clouds")
        return []
    return render_recording(positions, dt=dt, fps=fps, seed=seed)


def build_stream(
    positions: np.ndarray,
    grippers: Grippers,
    dt: float = 0.01,
    fps: float = 30.0,
    t0_ns: int = 1_700_000_000 * NS,
    seed: int = 0,
    frames=None,
) -> list[Message]:
    """Messages in send order, each with log time = its header stamp."""
    positions = np.asarray(positions, dtype=float)
    poses = poses_from_vertices(positions, grippers)
    frames = render(positions, dt, fps, seed) if frames is None else frames
    by_step = {f.step: f for f in frames}
    out: list[Message] = []
    step_ns = round(dt * NS)
    if frames:
        cam = frames[0].camera
        K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
        out.append(Message("camera_info", t0_ns, M.camera_info(t0_ns, K, cam.width, cam.height)))
        out.append(
            Message("camera_pose", t0_ns, M.pose_stamped(t0_ns, matrix_to_pose(cam.world_from_camera)))
        )
    for k in range(len(positions)):
        t = t0_ns + k * step_ns
        out.append(Message("ee_poses", t, M.pose_array(t, poses[k])))
        f = by_step.get(k)
        if f is not None:
            out.append(Message("points", t, M.point_cloud(t, f.xyz, f.rgb)))
    return out


def demo_positions(n_frames: int = 500, rod: str = "DLO1") -> tuple[np.ndarray, str]:
    """The first eval recording of the rod from the real dataset when present, else a simulated one."""
    from deform import find_data_root, generate_recording, load_model, load_recording

    root = find_data_root()
    if root is not None:
        files = sorted((root / rod / "eval").glob("*.pkl")) or sorted((root / rod / "train").glob("*.pkl"))
        if files:
            rec = load_recording(files[0])
            return rec.positions[:n_frames], f"{rod}/{files[0].parent.name}/{files[0].name} (real)"
    rec = generate_recording(load_model(rod), n_frames=n_frames, seed=0)
    return rec.positions, f"{rec.name} (simulated, no dataset found)"
