"""`python -m service.demo`: the service on an embedded Zenoh peer, a demo recording replayed into it,
demo.rrd written, tracking error and loop timing printed.

The recording is the first DLO1 eval file of the real dataset when present, else a simulated one;
the depth camera is perception's renderer. The loop runs on the message clock, so the run is
deterministic and as fast as the machine allows.
"""

from __future__ import annotations

import argparse
import logging
import socket
import time

import numpy as np

from deform.argtypes import int_at_least
from service import bag, scenario
from service.client import ServiceError, ShapeClient
from service.config import load_config
from service.node import Service, open_session


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(
    positions: np.ndarray,
    rrd: str | None = "demo.rrd",
    rod: str = "DLO1",
    fps: float = 30.0,
    namespace: str = "deform/rod1",
    tracker=None,
    stream=None,
    predict_plans: int = 64,
    predict_steps: int = 100,
    workers: dict | None = None,
):
    """Replay ``positions`` through a running service; returns a dict of results (and the estimates)."""
    grippers = scenario.offsets_for(positions)
    ep = f"tcp/127.0.0.1:{free_port()}"
    cfg = load_config(
        namespace=namespace,
        rod=rod,
        clock="message",
        grippers=grippers.model_dump(),
        zenoh={"mode": "peer", "listen": [ep], "multicast_scouting": False},
        rerun={"mode": "file" if rrd else "off", "path": rrd or "demo.rrd", "cloud_every": 3},
        workers=workers,
    )
    t0 = time.perf_counter()
    stream = scenario.build_stream(positions, grippers, fps=fps) if stream is None else stream
    t_render = time.perf_counter() - t0
    n_poses = sum(m.name == "ee_poses" for m in stream)
    got: dict[int, np.ndarray] = {}
    svc = Service(cfg, tracker=tracker).start()
    client = open_session(cfg.zenoh.model_copy(update={"listen": [], "connect": [ep]}))
    rope = ShapeClient(cfg.namespace, session=client, timeout_s=5.0)
    try:
        rope.subscribe(lambda stamp, x, observed: got.__setitem__(stamp, x.astype(np.float64)))
        if not _wait_for(lambda: _status(rope) is not None, 30):
            raise RuntimeError(f"the service at {ep} did not answer its status query within 30 s")
        t1 = time.perf_counter()
        bag.replay(client, cfg.namespace, stream, fast=True)
        _wait_for(lambda: len(got) >= n_poses, 120)
        t_replay = time.perf_counter() - t1
        status = _status(rope)
        stamps = sorted(got)
        est = np.stack([got[s] for s in stamps])
        if svc.rerun is not None:
            for s, x in zip(stamps, positions):
                svc.rerun.submit("truth", s, x)
        pred_ms, pred_shape = _predict(rope, positions[-1], grippers, predict_plans, predict_steps)
    finally:
        rope.close()
        client.close()
        svc.stop()
    truth = positions[: len(est)]
    free = [
        i
        for i in range(positions.shape[1])
        if i not in (0, 1, positions.shape[1] - 2, positions.shape[1] - 1)
    ]
    return {
        "frames": len(est),
        "render_s": round(t_render, 2),
        "replay_s": round(t_replay, 2),
        "mae_cm": round(100 * float(np.abs(est - truth).mean()), 3),
        "mae_cm_after_1s": round(100 * float(np.abs(est[100:] - truth[100:]).mean()), 3)
        if len(est) > 100
        else None,
        "free_vertex_dist_cm": round(
            100 * float(np.linalg.norm(est[:, free] - truth[:, free], axis=-1).mean()), 3
        ),
        "status": status,
        "predict_ms": pred_ms,
        "predict_shape": pred_shape,
        "estimates": est,
        "truth": truth,
    }


def _wait_for(cond, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.05)
    return False


def _status(rope: ShapeClient) -> dict | None:
    try:
        return rope.status()
    except ServiceError:
        return None


def _predict(rope: ShapeClient, x_last, grippers, plans: int, steps: int):
    from service.geometry import poses_from_vertices

    base = poses_from_vertices(x_last, grippers)
    rng = np.random.default_rng(0)
    ramp = np.linspace(0, 1, steps)[None, :, None, None]
    shift = np.zeros((plans, 1, 2, 7))
    shift[..., :3] = rng.uniform(-0.1, 0.1, (plans, 1, 2, 3))

    # the predict worker compiles its rollout at start-up (about 30 s the first time on a machine):
    # time the query, not the compilation (a failed warm-up is final: the query then says why)
    def settled() -> bool:
        status = _status(rope) or {}
        return bool(status.get("predict_ready")) or status.get("predict_state") == "failed"

    _wait_for(settled, 300)
    t = time.perf_counter()
    try:
        shapes = rope.predict(base[None, None] + ramp * shift, dt=0.01, timeout_s=60.0)
    except ServiceError:
        return None, None
    return round(1e3 * (time.perf_counter() - t), 1), list(shapes.shape)


def plot(result: dict, path: str, title: str) -> None:
    """A picture of the demo: the rope estimate vs ground truth at a few instants, and the error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    est, truth = result["estimates"], result["truth"]
    fig = plt.figure(figsize=(11, 4.6))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    frames = np.linspace(0, len(est) - 1, 4).astype(int)
    colors = plt.cm.viridis(np.linspace(0, 0.85, len(frames)))
    for k, c in zip(frames, colors):
        ax.plot(*truth[k].T, "-", color=c, lw=4, alpha=0.35)
        ax.plot(*est[k].T, "o-", color=c, ms=3, lw=1.2, label=f"t = {k / 100:.1f} s")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title("estimate (dots) over ground truth (thick)")
    ax.legend(fontsize=8, loc="upper left")
    ax2 = fig.add_subplot(1, 2, 2)
    err = 100 * np.linalg.norm(est - truth, axis=-1)
    t = np.arange(len(est)) / 100
    ax2.plot(t, err.mean(1), label="mean over vertices")
    ax2.plot(t, err.max(1), alpha=0.6, label="worst vertex")
    ax2.set_xlabel("message time [s]")
    ax2.set_ylabel("position error [cm]")
    ax2.set_title("tracking error (clouds at 30 Hz)")
    ax2.legend()
    ax2.grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m service.demo", description=__doc__)
    ap.add_argument("--frames", type=int_at_least(2), default=500)
    ap.add_argument("--rrd", default="demo.rrd")
    ap.add_argument("--png", help="also save a picture of the run (e.g. docs/demo.png)")
    ap.add_argument("--rod", default="DLO1")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    positions, name = scenario.demo_positions(args.frames, args.rod)
    print(
        f"demo recording: {name}, {len(positions)} frames at 100 Hz; rendering clouds at 30 Hz ...",
        flush=True,
    )
    res = run(positions, rrd=args.rrd, rod=args.rod)
    st = res["status"] or {}
    print(
        f"replayed over Zenoh (embedded peer, message clock): {res['frames']} estimates in {res['replay_s']} s "
        f"(rendering took {res['render_s']} s)"
    )
    print(
        f"tracking error: {res['mae_cm']} cm mean abs coordinate error over all vertices "
        f"({res['mae_cm_after_1s']} cm after the first second); {res['free_vertex_dist_cm']} cm mean distance of the free vertices"
    )
    print(
        f"loop timing [ms]: model step p50 {st.get('step_ms', {}).get('p50')} p99 {st.get('step_ms', {}).get('p99')}; "
        f"tick-to-publish p50 {st.get('tick_to_publish_ms', {}).get('p50')} p99 {st.get('tick_to_publish_ms', {}).get('p99')} "
        f"(includes cloud fusion on the message clock); fusion p50 {st.get('fusion_ms', {}).get('p50')}; "
        f"clouds fused {st.get('counts', {}).get('clouds_fused')}, tracker {st.get('tracker')}"
    )
    print(f"predict: {res['predict_shape']} in {res['predict_ms']} ms")
    if args.rrd:
        print(f"wrote {args.rrd}: open it with `.venv/bin/rerun {args.rrd}`")
    if args.png:
        plot(
            res,
            args.png,
            f"deform-service demo: {name}, tracker {st.get('tracker')}, mean abs error {res['mae_cm']} cm",
        )
        print(f"wrote {args.png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
