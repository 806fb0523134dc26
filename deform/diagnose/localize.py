"""Where and when the nominal model is wrong: residuals against arc length, time and the state.

Open-loop errors accumulate, which blurs what causes them; so the residual used here is the error
of short rollouts (``horizon`` steps) restarted from observed frames every ``stride`` frames, set
against the observed state at the end of each short rollout.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import torch

from deform.diagnose.simulator import Simulator
from deform.io.recordings import Recording
from deform.model import gripped_indices


def short_rollout_residuals(
    sim: Simulator, recordings: list[Recording], horizon: int = 10, stride: int = 10
) -> dict:
    """Per (window, vertex): error [m] after ``horizon`` steps, and the state features there.

    Args:
        sim: the fitted nominal simulator.
        recordings: recordings to probe.
        horizon: steps per short rollout.
        stride: frames between rollout starts.

    Returns:
        ``error`` (W, n) [m] and the features per (window, vertex): speed, height, height above the
        lowest point, curvature, gripper acceleration, time.
    """
    sim.sync()
    wins, frames, meta = [], [], []
    for ri, r in enumerate(recordings):
        for s in range(0, r.n_frames - horizon - 2, stride):
            wins.append(r.positions[s : s + horizon + 2])
            frames.append(r.reference_frames[s + 1])  # the reference frames a full rollout carries there
            meta.append((ri, s + horizon + 1))
    X = torch.tensor(np.stack(wins), dtype=torch.float64)
    with torch.no_grad():
        pred = sim.rollout(X, horizon, d1=torch.tensor(np.stack(frames)))[:, -1].numpy()
    truth = X[:, -1].numpy()
    err = np.linalg.norm(pred - truth, axis=-1)  # (W, n)
    n = truth.shape[1]
    speed, acc_grip, z, zlow, curv = [], [], [], [], []
    lowest = min(float(r.positions[:, 2:-2, 2].min()) for r in recordings)
    idx = gripped_indices(n)
    for ri, f in meta:
        P = recordings[ri].positions
        a, b = max(f - 2, 0), min(f + 2, len(P) - 1)
        speed.append(np.linalg.norm(P[b] - P[a], axis=-1) / ((b - a) * recordings[ri].dt))
        g = P[max(f - 4, 0) : f + 5, idx]
        acc = (
            np.linalg.norm(g[8] - 2 * g[4] + g[0], axis=-1).max() / (4 * recordings[ri].dt) ** 2
            if len(g) == 9
            else 0.0
        )
        acc_grip.append(np.full(n, acc))
        z.append(P[f, :, 2])
        zlow.append(P[f, :, 2] - lowest)
        e = np.diff(P[f], axis=0)
        t = e / np.linalg.norm(e, axis=-1, keepdims=True)
        ang = np.arccos(np.clip((t[:-1] * t[1:]).sum(-1), -1, 1))
        curv.append(np.concatenate([[0.0], ang, [0.0]]))
    time_s = np.array([f * recordings[ri].dt for ri, f in meta])
    return {
        "error": err,
        "speed": np.array(speed),
        "height": np.array(z),
        "height_above_lowest": np.array(zlow),
        "curvature": np.array(curv),
        "gripper_acceleration": np.array(acc_grip),
        "time_s": np.repeat(time_s[:, None], n, 1),
    }


def _band(profile: np.ndarray, s: np.ndarray) -> tuple[float, float]:
    """Contiguous arc-length band around the peak where the profile is within 80 % of its peak."""
    k = int(np.argmax(profile))
    lo = hi = k
    while lo > 0 and profile[lo - 1] >= 0.8 * profile[k]:
        lo -= 1
    while hi < len(profile) - 1 and profile[hi + 1] >= 0.8 * profile[k]:
        hi += 1
    return float(s[lo]), float(s[hi])


def _binned(feature: np.ndarray, err: np.ndarray, bins: int = 8) -> tuple[list[float], list[float]]:
    edges = np.unique(np.quantile(feature, np.linspace(0, 1, bins + 1)))
    centers, means = [], []
    for a, b in itertools.pairwise(edges):
        m = (feature >= a) & (feature <= b)
        if m.sum() >= 5:
            centers.append(float(np.median(feature[m])))
            means.append(float(err[m].mean()))
    return centers, means


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1]) if len(a) > 2 else 0.0


def localize(res: dict, arclength: np.ndarray) -> dict:
    """Summaries and findings in words.

    Args:
        res: from :func:`short_rollout_residuals`.
        arclength: (n,) normalised marker arc length.

    Returns:
        Profiles by arc length, time, speed, height...; ``peak_s`` and ``findings`` (sentences).
    """
    err = res["error"]
    free = np.ones(err.shape[1], bool)
    free[gripped_indices(err.shape[1])] = False
    e = err[:, free]
    s_free = arclength[free]
    profile = e.mean(0)
    lo, hi = _band(profile, s_free)
    findings = []
    out: dict = {
        "residual": f"error after 10-step rollouts restarted every 10 frames ({err.shape[0]} windows)",
        "mean_error_m": float(e.mean()),
        "by_arclength": {"s": s_free.tolist(), "error_m": profile.tolist()},
    }
    ratio = float(profile.max() / profile.mean())
    if ratio > 1.3:
        findings.append(
            f"error concentrated at {lo * 100:.0f}-{hi * 100:.0f} % of the length (peak {ratio:.1f}x the mean)"
        )
    else:
        findings.append(
            f"error spread along the rod (peak at {s_free[np.argmax(profile)] * 100:.0f} % of the length, only {ratio:.2f}x the mean)"
        )
    out["peak_s"] = float(s_free[np.argmax(profile)])
    t = res["time_s"][:, free].ravel()
    c, m = _binned(t, e.ravel(), 6)
    out["by_time"] = {"t_s": c, "error_m": m}
    for key, label in (
        ("speed", "speed"),
        ("height", "height"),
        ("height_above_lowest", "height above the lowest point reached"),
        ("curvature", "curvature"),
        ("gripper_acceleration", "gripper acceleration"),
    ):
        f = res[key][:, free].ravel()
        ev = e.ravel()
        centers, means = _binned(f, ev)
        rho = _spearman(f, ev)
        entry = {"bin_center": centers, "error_m": means, "spearman": rho}
        if key == "speed":
            ok = (f > 0.05) & (ev > 0)
            p = float(np.polyfit(np.log(f[ok]), np.log(ev[ok]), 1)[0]) if ok.sum() > 10 else 0.0
            entry["power"] = p
            if rho > 0.3:
                findings.append(f"error grows with speed (about speed^{p:.1f}, Spearman {rho:.2f})")
        elif key in ("height", "height_above_lowest"):
            q = float(np.quantile(f, 0.15))
            low, high = ev[f <= q].mean(), ev[f > q].mean()
            entry["low_threshold"] = q
            entry["low_vs_rest_ratio"] = float(low / high)
            if low / high > 1.5:
                where = (
                    f"z = {q:.3f} m"
                    if key == "height"
                    else f"{q * 100:.1f} cm above the lowest point reached"
                )
                findings.append(f"error {low / high:.1f}x larger when vertices are below {where}")
        elif abs(rho) > 0.3:
            findings.append(f"error {'grows' if rho > 0 else 'falls'} with {label} (Spearman {rho:.2f})")
        out[f"by_{key}"] = entry
    if len(m) > 1 and m[-1] > 1.5 * m[0]:
        findings.append(f"error grows over time ({m[0] * 100:.2f} cm early vs {m[-1] * 100:.2f} cm late)")
    out["findings"] = findings
    return out


def plot_localization(loc: dict, path: Path) -> None:
    """Plot the error profiles of :func:`localize` (one panel per feature).

    Args:
        loc: from :func:`localize`.
        path: the PNG to write.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [
        ("by_arclength", "s", "arc length (fraction)"),
        ("by_time", "t_s", "time [s]"),
        ("by_speed", "bin_center", "speed [m/s]"),
        ("by_height", "bin_center", "height z [m]"),
        ("by_height_above_lowest", "bin_center", "height above lowest [m]"),
        ("by_curvature", "bin_center", "turning angle [rad]"),
        ("by_gripper_acceleration", "bin_center", "gripper acceleration [m/s^2]"),
    ]
    fig, axes = plt.subplots(2, 4, figsize=(14, 6))
    for ax, (k, xk, label) in zip(axes.ravel(), keys):
        d = loc[k]
        ax.plot(d[xk], np.array(d["error_m"]) * 100, "o-")
        ax.set_xlabel(label)
        ax.set_ylabel("10-step error [cm]")
    axes.ravel()[-1].axis("off")
    axes.ravel()[-1].text(0, 0.5, "\n".join(loc["findings"]), fontsize=8, wrap=True)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
