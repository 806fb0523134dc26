"""Service configuration, validated with pydantic so a typo fails at start-up with the file and field
named, not minutes later inside the loop.

The models below are the one source of the defaults: with no file the service runs on them.
``config/service.yaml`` is a commented copy of them to start a configuration from (a test keeps it
equal to the defaults)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator


class ServiceConfigError(ValueError):
    """A service configuration that cannot be used."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class GripOffsets(_Strict):
    """Distances along the gripper's ``axis`` of the end vertex (d0) and of its neighbour (d1).

    ``axis``: the direction in the gripper's own frame along which the rod leaves it (default +x).
    A parallel gripper holds a rope across its fingers, and which of its frame's axes that is
    depends on the robot (a hand whose rope runs along its y axis gives ``[0, 1, 0]``)."""

    d0: float = 0.0
    d1: float = Field(default=0.03)
    axis: list[float] = Field(default=[1.0, 0.0, 0.0], min_length=3, max_length=3)

    @field_validator("axis")
    @classmethod
    def _unit(cls, v):
        n = float(np.linalg.norm(v))
        if not np.isfinite(n) or n < 1e-6:
            raise ValueError("axis must be a non-zero direction [x, y, z] in the gripper's frame")
        return [float(c) / n for c in v]

    @field_validator("d1")
    @classmethod
    def _distinct(cls, v, info):
        if abs(v - info.data.get("d0", 0.0)) < 1e-4:
            raise ValueError("d1 must differ from d0 (the end edge needs a length)")
        return v


class Grippers(_Strict):
    first: GripOffsets = GripOffsets()
    last: GripOffsets = GripOffsets()


class Camera(_Strict):
    pose: list[float] = Field(
        default=[0.0, -1.2, 0.5, -0.7071068, 0.0, 0.0, 0.7071068], min_length=7, max_length=7
    )
    use_pose_topic: bool = True
    # how late the camera driver stamps its clouds against the gripper poses' clock [s] (a driver that
    # stamps on arrival; `deform calibrate` estimates it): a cloud counts as taken at its stamp less this
    stamp_delay_s: float = Field(default=0.0, ge=-1.0, le=1.0)
    # wall clock: where in time a cloud is fused. stamp: at the tick of its stamp (the steps since are
    # replayed), as the message clock does; arrival: at the tick its fusion starts (a camera's
    # latency then lags the estimate)
    fuse_at: Literal["stamp", "arrival"] = "stamp"


class Timeouts(_Strict):
    pose_s: float = Field(default=0.2, gt=0)
    cloud_s: float = Field(default=0.5, gt=0)
    stale_s: float = Field(default=1.0, gt=0)
    reorder_s: float = Field(default=1.0, gt=0)  # message clock: how far clouds may lag poses in transit
    # message clock, a replay in send order: how long a missing sample is waited for before what
    # follows it is processed (it was lost). Long: on a loaded machine a large cloud can take seconds
    # to arrive, and giving up early made the replay's result depend on the machine's load
    gap_s: float = Field(default=20.0, gt=0)


class Limits(_Strict):
    max_plans: int = Field(default=1024, ge=1)  # a sampling planner's batch (MPPI, CEM)
    max_steps: int = Field(default=500, ge=1)
    max_plan_steps_total: int = Field(default=102400, ge=1)
    max_request_bytes: int = Field(default=16_000_000, ge=1000)  # 1024 x 100 plans binary: 11.5 MB
    max_cloud_bytes: int = Field(default=40_000_000, ge=1000)
    max_cloud_rate_hz: float = Field(default=60.0, gt=0)


class Workers(_Strict):
    processes: bool = True  # fusion (wall clock) and predict run in child processes, off the loop's GIL
    compile_predict: bool = True  # torch.compile the predict rollout (eager fallback if it cannot compile)
    # its one-graph step as an AOTInductor package (deform.aot: same values, 0.7x per step; cached
    # on disk, torch.compile if it cannot be built); only with compile_predict
    predict_ahead_of_time: bool = True
    # the checked step that redoes the rare rollout steps the fast graph leaves unconverged (3 of
    # 2000 in service_bench's live predict): compiled, it costs 10-20 s of start-up even warm
    compile_checked_step: bool = False
    # the rollout's state: float64 took 1.21-1.24x float32's time at 256-1024 plans, and float32
    # scores the paper's metric within 0.003 mm of the eager float64 step on DLO1-DLO3
    # (benchmarks/predict_planning.py, benchmarks/float32_accuracy.py); replies are float32 anyway
    predict_dtype: Literal["float32", "float64"] = "float32"
    # the residual network's arithmetic in predict's rollouts of 512 rods or more per process
    # (deform.nn.precision; below, float32 is faster): auto is bfloat16 on a CPU that multiplies it
    # natively (AMX, AVX512-BF16), else float32. Opt-in: in ten paired service runs 1024 x 100
    # plans took 0.92-1.03x the time with it, a gain within this VM's noise (docs/service.md)
    predict_network_dtype: Literal["auto", "float32", "bfloat16"] = "float32"
    # threads of the predict worker's rollouts (null: every core). One by default: the compiled
    # step's parallel loops wait at ~120 barriers per step for their slowest thread, so on 2 cores
    # shared with the loop, fusion and a camera, two threads were slower (a 1024-rod step with one
    # busy process beside it: 53-122k rod-steps/s on two threads, 201-209k on one; 384k against
    # 209k on a quiet machine; benchmarks/predict_planning.py --compare predict_threads=2)
    predict_threads: int | None = Field(default=1, ge=1)
    # predict worker processes: a binary request of at least predict_split_min_plans plans is split
    # across them in consecutive blocks (service.predict_pool.PredictPool: processes do not wait for each
    # other as threads do)
    predict_processes: int = Field(default=2, ge=1)
    predict_split_min_plans: int = Field(default=128, ge=2)
    predict_warmup: list[int] = Field(default=[64])  # plan counts compiled at start-up (others on first use)
    fusion_timeout_s: float = Field(default=5.0, gt=0)
    predict_timeout_s: float = Field(default=120.0, gt=0)  # includes a first-use compile
    # nice value of the fusion worker process: on a busy machine a planner's query gets the core
    # first and fusion (latest-only) catches up after. Not applied to threads of the service's own
    # process: a lowered thread holding the interpreter lock would delay the loop (priority inversion)
    fusion_nice: int = Field(default=5, ge=0, le=19)
    # while a predict runs, the next cloud fusion waits up to this long (0: never): on a small
    # machine predict then has the cores; the estimate runs open-loop meanwhile (latest-only clouds)
    fusion_yields_to_predict_s: float = Field(default=0.5, ge=0)


def _shipped_rods_dir() -> Path | None:
    """``deform/rods`` (the shipped rods' YAML, package data), found without importing ``deform``;
    None if it cannot be found so (the caller then asks ``deform.config``)."""
    import importlib.util

    spec = importlib.util.find_spec("deform")
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    rods = [Path(loc) / "rods" for loc in locations if (Path(loc) / "rods").is_dir()]
    return rods[0] if rods else None


def predict_threads(workers: Workers) -> int:
    """The predict worker's thread count: ``workers.predict_threads``, or every core."""
    return workers.predict_threads or os.cpu_count() or 1


class ZenohSettings(_Strict):
    mode: Literal["peer", "client"] = "peer"
    connect: list[str] = []
    listen: list[str] = []
    multicast_scouting: bool = True


class Ros2Settings(_Strict):
    """``interface: ros2``: how the service appears in a ROS 2 graph on rmw_zenoh (service/ros2.py)."""

    domain_id: int = Field(default=0, ge=0, le=232)  # ROS_DOMAIN_ID of the robot
    node: str = "deform_service"  # node name; its namespace is /<namespace>


class RerunSettings(_Strict):
    mode: Literal["off", "file", "viewer", "connect"] = "off"
    path: str = "deform_service.rrd"
    url: str = "rerun+http://127.0.0.1:9876/proxy"  # mode connect: a viewer elsewhere
    cloud_every: int = Field(default=1, ge=1)

    @field_validator("mode", mode="before")
    @classmethod
    def _yaml_off(cls, v):
        return "off" if v is False else v  # YAML reads a bare `off` as false


class ServiceConfig(_Strict):
    namespace: str = "deform/rod1"
    rod: str = "DLO1"
    rate_hz: float = Field(default=100.0, gt=0, le=1000)
    clock: Literal["wall", "message"] = "wall"
    # wall clock: each tick steps to the gripper poses this long before the newest stamp, interpolated
    # between the two around it, advancing one period a tick (service/pose_timeline.py); null
    # (default): 1.5 times the poses' median interval; 0: the newest pose as it arrived (poses in
    # bursts, or at another rate than the loop's, then step the model unevenly)
    pose_delay_s: float | None = Field(default=None, ge=0, le=1)
    torch_threads: int = Field(default=1, ge=1)
    realtime_priority: int | None = Field(
        default=10, ge=1, le=99
    )  # SCHED_FIFO for the loop thread; null: off
    # wall clock: the loop's step compiled once ready (eager until then, and if it cannot)
    compile_step: bool = True
    # the compiled loop step as an AOTInductor package (deform.aot), cached on disk: a warm start
    # loads it instead of compiling again; torch.compile if it cannot be built
    step_ahead_of_time: bool = True
    grippers: Grippers = Grippers()
    camera: Camera = Camera()
    timeouts: Timeouts = Timeouts()
    limits: Limits = Limits()
    workers: Workers = Workers()
    zenoh: ZenohSettings = ZenohSettings()
    # zenoh: plain keys <namespace>/<name> (with zenoh-bridge-ros2dds for DDS robots); ros2: rmw_zenoh's
    # keys, attachments and liveliness tokens, so ROS 2 nodes on rmw_zenoh see the topics directly
    interface: Literal["zenoh", "ros2"] = "zenoh"
    ros2: Ros2Settings = Ros2Settings()
    frame_id: str = Field(default="world", min_length=1)  # frame of the published vertices and shape
    rerun: RerunSettings = RerunSettings()
    perception: str | None = None  # perception settings YAML (perception.load_config); null: its defaults

    @field_validator("perception")
    @classmethod
    def _settings_file(cls, v: str | None) -> str | None:
        if v is not None:
            from perception import load_config as load_perception

            try:
                load_perception(v)  # fail at start-up, naming the file, not in the fusion worker
            except (OSError, ValueError, TypeError) as exc:
                raise ValueError(f"perception settings {v}: {exc}") from None
        return v

    @field_validator("rod")
    @classmethod
    def _rod(cls, v: str) -> str:
        """A rod name or a checkpoint that exists: fail at start-up naming it, not in a worker after
        the processes started (the content of a checkpoint is read by the loop)."""
        if v.endswith(".pt"):
            if not Path(v).is_file():
                raise ValueError(f"rod {v}: no such model file")
            return v
        shipped = _shipped_rods_dir()
        if shipped is not None and not Path(v).suffix:
            # a shipped rod's name, looked up without importing deform: that imports torch (about
            # 3 s), which `deform-service run` does only once it has started its worker processes
            # (service.workers.prestart), so that their imports overlap its own
            if not (shipped / f"{v}.yaml").is_file():
                known = ", ".join(sorted(p.stem for p in shipped.glob("*.yaml")))
                raise ValueError(f"unknown rod {v!r}; known rods: {known}")
            return v
        from deform.config import ConfigError, load_rod_config

        try:
            load_rod_config(v)
        except ConfigError as exc:
            raise ValueError(str(exc)) from None
        return v

    @field_validator("namespace")
    @classmethod
    def _key(cls, v: str) -> str:
        v = v.strip("/")
        if not v or any(c in v for c in "*$?#") or "//" in v:
            raise ValueError(f"not a plain key expression: {v!r}")
        return v

    @model_validator(mode="after")
    def _ros_names(self):
        if self.interface == "ros2":
            from service.ros2 import check_names

            check_names(self.namespace, self.ros2.node)
        return self

    def topic(self, name: str) -> str:
        """The ROS 2 topic of an input or output: ``/<namespace>/<name>``."""
        return f"/{self.namespace}/{name}"

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz

    def key(self, name: str) -> str:
        return f"{self.namespace}/{name}"


def load_config(path: str | Path | None = None, **overrides) -> ServiceConfig:
    """Read a YAML (None: the defaults of :class:`ServiceConfig`) and apply top-level overrides."""
    where = str(path) if path else "service config"
    try:
        data = {}
        if path:
            path = Path(path)
            if not path.is_file():
                raise ServiceConfigError(f"{path}: no such file")
            data = yaml.safe_load(path.read_text()) or {}
        data.update({k: v for k, v in overrides.items() if v is not None})
        return ServiceConfig(**data)
    except (yaml.YAMLError, TypeError, ValidationError) as exc:
        raise ServiceConfigError(f"{where}: {str(exc).replace(chr(10), '; ')}") from None
