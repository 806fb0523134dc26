"""`deform-service run | record FILE | replay FILE | demo-bag FILE` (also `python -m service`)."""

from __future__ import annotations

import argparse
import functools
import logging
import signal
import sys
import threading

from service.config import ServiceConfigError, load_config


def _argtype(name: str, *args):
    """The argparse type ``deform.argtypes.<name>(*args)``, imported when a value is parsed rather
    than when the parser is built: importing ``deform`` imports torch (about 3 s), which ``run``
    does only once it has started its worker processes (``service.workers.prestart``), so that their
    imports overlap its own (a number option given, such as ``--domain-id``, imports it earlier)."""

    def parse(text: str):
        from deform import argtypes

        return getattr(argtypes, name)(*args)(text)

    return parse


def int_at_least(minimum: int):
    return _argtype("int_at_least", minimum)


def number(positive: bool):
    return _argtype("number", positive)


def _common(p: argparse.ArgumentParser, default=None) -> argparse.ArgumentParser:
    """The options every command shares; accepted before and after the command's name."""
    p.add_argument(
        "--config",
        default=default,
        help="YAML (default: the built-in defaults, which config/service.yaml lists)",
    )
    p.add_argument("--namespace", default=default, help="key prefix, e.g. deform/rod2")
    p.add_argument(
        "--mode",
        choices=["peer", "client"],
        default=default,
        help="Zenoh mode (client: through a zenohd router)",
    )
    p.add_argument(
        "--connect", action="append", default=default, help="Zenoh endpoint to connect to (repeatable)"
    )
    p.add_argument(
        "--listen", action="append", default=default, help="Zenoh endpoint to listen on (repeatable)"
    )
    p.add_argument(
        "--interface",
        choices=["zenoh", "ros2"],
        default=default,
        help="zenoh: plain keys (zenoh-bridge-ros2dds); ros2: rmw_zenoh keys and graph tokens (run, record)",
    )
    p.add_argument(
        "--domain-id", type=int_at_least(0), default=default, help="interface ros2: ROS_DOMAIN_ID (default 0)"
    )
    p.add_argument("-v", "--verbose", action="store_true", default=default or False)
    return p


def _parser() -> argparse.ArgumentParser:
    p = _common(argparse.ArgumentParser(prog="deform-service", description=__doc__))
    # after the command too; SUPPRESS: a subcommand's unset option does not overwrite the top level's
    shared = _common(argparse.ArgumentParser(add_help=False), default=argparse.SUPPRESS)
    sub = p.add_subparsers(dest="command")
    run = sub.add_parser("run", parents=[shared], help="run the estimation service")
    run.add_argument("--clock", choices=["wall", "message"])
    run.add_argument("--rod", help="rod config name or checkpoint")
    run.add_argument("--rerun", choices=["off", "file", "viewer", "connect"])
    run.add_argument("--rerun-url", help="viewer address for --rerun connect (rerun+http://HOST:9876/proxy)")
    run.add_argument("--rrd", help="output .rrd when --rerun file")
    run.add_argument("--perception", help="perception settings YAML (default: perception's defaults)")
    pre = sub.add_parser(
        "prebuild",
        parents=[shared],
        help="build the compiled steps the service loads at start-up into $DEFORM_CACHE (make install runs it)",
    )
    pre.add_argument("--rod", help="rod config name or checkpoint (default: the config's)")
    pre.add_argument(
        "--all-rods",
        action="store_true",
        help="every shipped model (deform/models/*.pt) and the configured rod (make install uses it)",
    )
    pre.add_argument(
        "--workers",
        type=int_at_least(1),
        default=None,
        help="packages built at once, each in a process of its own (default: the cores available; a "
        "build keeps one core busy)",
    )
    rec = sub.add_parser(
        "record", parents=[shared], help="record the input keys to an MCAP file (Ctrl-C to stop)"
    )
    rec.add_argument("file")
    rec.add_argument("--duration", type=number(positive=True), help="seconds, default until interrupted")
    rep = sub.add_parser("replay", parents=[shared], help="publish an MCAP file on the input keys")
    rep.add_argument("file")
    rep.add_argument(
        "--fast", action="store_true", help="as fast as possible (use a service with --clock message)"
    )
    rep.add_argument("--speed", type=number(positive=True), default=1.0)
    bag = sub.add_parser(
        "demo-bag",
        parents=[shared],
        help="write the demo recording (poses and rendered clouds) to an MCAP file",
    )
    bag.add_argument("file")
    bag.add_argument("--frames", type=int_at_least(2), default=500)
    return p


def _config(args):
    zenoh = {}
    base = load_config(args.config)
    if args.mode:
        zenoh["mode"] = args.mode
    if args.connect:
        zenoh["connect"] = args.connect
    if args.listen:
        zenoh["listen"] = args.listen
    over = {
        "namespace": args.namespace,
        "interface": args.interface,
        "zenoh": base.zenoh.model_copy(update=zenoh).model_dump() if zenoh else None,
    }
    if args.domain_id is not None:
        over["ros2"] = base.ros2.model_copy(update={"domain_id": args.domain_id}).model_dump()
    if args.command in (None, "run", "prebuild"):
        over.update(
            clock=getattr(args, "clock", None),
            rod=getattr(args, "rod", None),
            perception=getattr(args, "perception", None),
        )
        rr = {}
        if getattr(args, "rerun", None):
            rr["mode"] = args.rerun
        if getattr(args, "rrd", None):
            rr["path"] = args.rrd
        if getattr(args, "rerun_url", None):
            rr["url"] = args.rerun_url
        if rr:
            over["rerun"] = base.rerun.model_copy(update=rr).model_dump()
    return load_config(args.config, **over)


def _check_files(args) -> None:
    """A file to replay must exist, a file to write must have its directory: one line, before a
    session is opened (a missing replay file was a traceback)."""
    from pathlib import Path

    path = getattr(args, "file", None)
    if path is None:
        return
    if args.command == "replay" and not Path(path).is_file():
        raise ServiceConfigError(f"{path}: no such file to replay")
    if args.command in ("record", "demo-bag") and not Path(path).resolve().parent.is_dir():
        raise ServiceConfigError(f"{path}: its directory does not exist")


def _wait(stop: threading.Event, duration: float | None = None) -> None:
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    stop.wait(duration)
    stop.set()


def shipped_rods() -> list[str]:
    """The rods a model is shipped for (``deform/models/<rod>.pt``), sorted."""
    from deform.model import MODEL_DIR

    return sorted(path.stem for path in MODEL_DIR.glob("*.pt"))


def prebuild_jobs(cfg) -> list[tuple]:
    """The ahead-of-time packages a start with ``cfg`` loads: the loop step, the predict step per
    warm-up size, predict's rescue graph. -> ``(label, branch_free, batch, dtype, network dtype,
    threads)`` each; the thread count is part of a package's key, so each is built as its user runs it."""
    import torch

    from deform.compiled import LOOP_BRANCH_FREE, PREDICT_BRANCH_FREE, RESCUE_BATCH, RESCUE_BRANCH_FREE
    from service.config import predict_threads

    jobs = []
    if cfg.compile_step and cfg.step_ahead_of_time:
        jobs.append(("loop step", LOOP_BRANCH_FREE, 1, torch.float64, None, cfg.torch_threads))
    if cfg.workers.compile_predict and cfg.workers.predict_ahead_of_time:
        from deform.compiled import bucket_size
        from deform.nn.precision import for_batch, network_dtype
        from service.predict_pool import share_sizes

        dtype, threads = getattr(torch, cfg.workers.predict_dtype), predict_threads(cfg.workers)
        network = network_dtype(cfg.workers.predict_network_dtype)
        # the sizes each predict process rolls out for those plan counts (a large request is split)
        w = cfg.workers
        sizes = share_sizes(w.predict_warmup, w.predict_processes, w.predict_split_min_plans)
        buckets = sorted({bucket_size(b) for per in sizes for b in per})
        jobs += [
            (f"predict step, {b} plans", PREDICT_BRANCH_FREE, b, dtype, for_batch(network, b), threads)
            for b in buckets
        ]
        # the second try for the rods a predict step leaves unconverged (deform.compiled.RolloutStep)
        rescue_network = for_batch(network, RESCUE_BATCH)
        jobs.append(("predict rescue step", RESCUE_BRANCH_FREE, RESCUE_BATCH, dtype, rescue_network, threads))
    return jobs


def prebuild(cfg, rods: list[str] | None = None, workers: int = 1) -> int:
    """Build the ahead-of-time packages a start with ``cfg`` loads (:func:`prebuild_jobs`) for each
    of ``rods`` (None: the config's rod), so that the first start of each is a warm one (predict
    ready in seconds instead of a minute or more). A package already in the cache is not built
    again. ``workers`` > 1: that many packages at once, each in a spawned process of its own (a
    build keeps one core busy: in one ad-hoc timing two rods took 109 s side by side on two cores,
    one alone 109 s; fork is unsafe once torch has started threads). -> exit code: 1 when a package cannot be built (no
    compiler, ...; the service then compiles at start-up instead), the jobs not yet started cancelled."""
    import contextlib
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from deform.aot import cache_dir

    rods = rods or [cfg.rod]
    _model.cache_clear()  # a checkpoint rewritten since an earlier call in this process is read again
    for rod in rods:  # a checkpoint that cannot be read stops here (CheckpointError), before any build
        _model(rod)
    work = [(rod, *job) for rod in rods for job in prebuild_jobs(cfg)]
    with contextlib.ExitStack() as stack:
        if workers > 1 and len(work) > 1:  # (job, its result when asked), as the builds end
            ctx = multiprocessing.get_context("spawn")
            pool = stack.enter_context(ProcessPoolExecutor(min(workers, len(work)), mp_context=ctx))
            stack.callback(pool.shutdown, wait=True, cancel_futures=True)
            futures = {pool.submit(_build_package, *job): job for job in work}
            results = ((futures[f], f.result) for f in as_completed(futures))
        else:
            results = ((job, functools.partial(_build_package, *job)) for job in work)
        for (rod, label, *_), result in results:
            try:
                name, built, seconds = result()
            except Exception as exc:  # no compiler, ...: the service compiles at start-up instead
                print(f"{rod} {label}: not built ({type(exc).__name__}: {exc})", file=sys.stderr)
                return 1
            how = f"built in {seconds:.0f} s" if built else "already built"
            print(f"{rod} {label}: {name} ({how})", flush=True)
    print(f"cache: {cache_dir()}")
    return 0


def _build_package(rod, label, branch_free, batch, dtype, network, threads) -> tuple[str, bool, float]:
    """One package of :func:`prebuild_jobs` for ``rod``, built on the threads its user runs it with
    (the thread count is part of its key). -> (file name, built rather than found, seconds)."""
    import time

    import torch

    from deform.aot import ensure_package

    t0 = time.perf_counter()
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        path, built = ensure_package(_model(rod), branch_free, batch, dtype, network)
    finally:
        torch.set_num_threads(before)
    return path.name, built, time.perf_counter() - t0


@functools.cache
def _model(rod: str):
    """The rod's model, loaded once per :func:`prebuild` call and worker process."""
    from deform import load_model

    return load_model(rod)


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        cfg = _config(args)
        _check_files(args)
    except ServiceConfigError as exc:
        print(f"deform-service: {exc}", file=sys.stderr)
        return 2
    if args.command in (None, "run"):
        from service.workers import prestart

        prestart(cfg)  # the workers import torch while this process does
    from service import bag
    from service.node import Service, open_session

    if args.command in (None, "run", "prebuild"):
        from deform.errors import CheckpointError

        try:
            if args.command == "prebuild":
                rods = [*shipped_rods(), cfg.rod] if getattr(args, "all_rods", False) else None
                workers = args.workers
                if workers is None:
                    from deform.cores import available_cores

                    workers = available_cores()
                return prebuild(cfg, None if rods is None else list(dict.fromkeys(rods)), workers)
            svc = Service(cfg).start()
        except CheckpointError as exc:  # the config checks that the file exists, not what it holds
            print(f"deform-service: {exc}", file=sys.stderr)
            return 2
        _wait(threading.Event())
        svc.stop()
        return 0
    if args.command == "record":
        session = open_session(cfg.zenoh)
        stop = threading.Event()
        signal.signal(signal.SIGINT, lambda *_: stop.set())
        timer = threading.Timer(args.duration, stop.set) if args.duration else None
        if timer:
            timer.start()
        key = None
        if cfg.interface == "ros2":  # the robot's topics on rmw_zenoh keys, any type hash
            from service.node import INPUT_TYPES
            from service.ros2 import topic_key

            types = dict(INPUT_TYPES, vertices="sensor_msgs/msg/PointCloud2")
            key = lambda n: topic_key(cfg.ros2.domain_id, cfg.topic(n), types[n], "*")  # noqa: E731
        n = bag.record(session, cfg.namespace, args.file, stop, key=key)
        print(f"recorded {n} messages to {args.file}")
        session.close()
        return 0
    if args.command == "replay":
        try:
            messages = bag.read_messages(args.file)
        except bag.BagError as exc:
            print(f"deform-service: {exc}", file=sys.stderr)
            return 2
        session = open_session(cfg.zenoh)
        n = bag.replay(session, cfg.namespace, messages, fast=args.fast, speed=args.speed)
        print(f"replayed {n} messages on {cfg.namespace}/*")
        session.close()
        return 0
    if args.command == "demo-bag":
        from service import scenario

        positions, name = scenario.demo_positions(args.frames, cfg.rod)
        bag.write_messages(
            args.file, cfg.namespace, scenario.build_stream(positions, scenario.offsets_for(positions))
        )
        print(f"wrote {name} as {args.file}")
        return 0
    return 1


if __name__ == "__main__":
    sys.exit(main())
