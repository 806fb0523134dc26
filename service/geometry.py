"""Poses (x y z qx qy qz qw) to rotations and gripped vertices: the only place that knows how a
gripper holds the rod (the rod leaves along an axis of the gripper's frame, +x unless the config
names another)."""

from __future__ import annotations

import numpy as np

from service.config import Grippers


def quat_to_matrix(q) -> np.ndarray:
    """(..., 4) unit quaternions x y z w -> (..., 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=float)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def quat_x_axis(q) -> np.ndarray:
    """(..., 4) unit quaternions x y z w -> (..., 3) the rotated +x axis: the first column of
    :func:`quat_to_matrix`, without the other six entries (a third of the work for a planner's
    1024 x 100 x 2 poses)."""
    q = np.asarray(q, dtype=float)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + z * w), 2 * (x * z - y * w)], axis=-1)


def quat_rotate(q, a) -> np.ndarray:
    """(..., 4) unit quaternions x y z w and a (3,) vector -> (..., 3) the rotated vector ``R(q) a``."""
    a = np.asarray(a, dtype=float)
    if a[1] == 0.0 and a[2] == 0.0:  # the default +x: the cheap column
        return a[0] * quat_x_axis(q)
    return quat_to_matrix(q) @ a


def quat_multiply(p, q) -> np.ndarray:
    """(..., 4) x (..., 4) quaternions x y z w -> their product ``p q`` (rotate by q, then by p)."""
    p, q = np.broadcast_arrays(np.asarray(p, dtype=float), np.asarray(q, dtype=float))
    px, py, pz, pw = np.moveaxis(p, -1, 0)
    qx, qy, qz, qw = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
            pw * qw - px * qx - py * qy - pz * qz,
        ],
        axis=-1,
    )


def quat_from_x_axis(u) -> np.ndarray:
    """(..., 3) directions -> (..., 4) the shortest rotation taking +x onto each direction."""
    u = np.asarray(u, dtype=float)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    q = np.zeros(u.shape[:-1] + (4,))
    q[..., 0] = 0.0
    q[..., 1] = -u[..., 2]
    q[..., 2] = u[..., 1]
    q[..., 3] = 1.0 + u[..., 0]
    flip = q[..., 3] < 1e-9  # u = -x: any half turn about an axis normal to x
    q[flip] = [0.0, 0.0, 1.0, 0.0]
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def pose_matrix(pose) -> np.ndarray:
    """(7,) pose -> (4, 4) homogeneous transform."""
    M = np.eye(4)
    M[:3, :3] = quat_to_matrix(pose[3:7])
    M[:3, 3] = pose[:3]
    return M


def grips_from_poses(poses: np.ndarray, offsets: Grippers) -> np.ndarray:
    """(..., 2, 7) gripper poses -> (..., 4, 3) positions of vertices 0, 1, n-2, n-1."""
    poses = np.asarray(poses, dtype=float)
    a, b = offsets.first, offsets.last
    ex = np.stack([quat_rotate(poses[..., 0, 3:7], a.axis), quat_rotate(poses[..., 1, 3:7], b.axis)], axis=-2)
    p = poses[..., :3]
    return np.stack(
        [
            p[..., 0, :] + a.d0 * ex[..., 0, :],
            p[..., 0, :] + a.d1 * ex[..., 0, :],
            p[..., 1, :] + b.d1 * ex[..., 1, :],
            p[..., 1, :] + b.d0 * ex[..., 1, :],
        ],
        axis=-2,
    )


def poses_from_vertices(x: np.ndarray, offsets: Grippers) -> np.ndarray:
    """(..., n, 3) vertex positions -> (..., 2, 7) gripper poses that hold them (inverse of the above
    for the end vertices; used to turn recordings into ee_poses streams)."""
    x = np.asarray(x, dtype=float)
    out = []
    for (i0, i1), off in (((0, 1), offsets.first), ((-1, -2), offsets.last)):
        u = x[..., i1, :] - x[..., i0, :]
        u = u / np.linalg.norm(u, axis=-1, keepdims=True)
        q = quat_from_x_axis(u)
        if off.axis != [1.0, 0.0, 0.0]:  # turn the gripper's axis onto +x first
            q = quat_multiply(q, quat_from_x_axis(off.axis) * [-1.0, -1.0, -1.0, 1.0])
        out.append(np.concatenate([x[..., i0, :] - off.d0 * u, q], axis=-1))
    return np.stack(out, axis=-2)


def matrix_to_pose(M: np.ndarray) -> np.ndarray:
    """(4, 4) homogeneous transform -> (7,) pose x y z qx qy qz qw."""
    R = np.asarray(M, dtype=float)[:3, :3]
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
        q[i], q[j], q[k] = 0.25 * s, (R[j, i] + R[i, j]) / s, (R[k, i] + R[i, k]) / s
    q = np.asarray(q) / np.linalg.norm(q)
    return np.concatenate([np.asarray(M, dtype=float)[:3, 3], q])


def interpolate_poses(stamps_ns: np.ndarray, poses: np.ndarray, times_ns: np.ndarray) -> np.ndarray:
    """(K, 2, 7) poses at ``times_ns`` (K,) from poses (P, 2, 7) at ``stamps_ns`` (P,), increasing
    (calibration resamples a bag's poses to the model's step; the wall-clock service samples one per
    tick, :mod:`service.pose_timeline`).

    Positions are interpolated linearly; quaternions by nlerp after flipping each onto the
    hemisphere of its predecessor (q and -q are the same rotation, and interpolating between the two
    would pass through zero). Times outside the stamps take the nearest pose.
    """
    poses = np.asarray(poses, dtype=float).copy()
    q = poses[..., 3:7]
    for i in range(1, len(q)):
        flip = (q[i] * q[i - 1]).sum(-1) < 0
        q[i, flip] *= -1
    t = (np.asarray(stamps_ns) - stamps_ns[0]).astype(float)
    tt = np.clip((np.asarray(times_ns) - stamps_ns[0]).astype(float), t[0], t[-1])
    flat = poses.reshape(len(poses), -1)
    out = np.stack([np.interp(tt, t, flat[:, j]) for j in range(flat.shape[1])], axis=1).reshape(
        (len(tt),) + poses.shape[1:]
    )
    out[..., 3:7] /= np.linalg.norm(out[..., 3:7], axis=-1, keepdims=True)
    return out
