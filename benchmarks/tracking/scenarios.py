"""The scenarios of the side-by-side tracking benchmark and the recordings, clouds and models of each.

A *variant* is one row of the table (what the clouds and the truth are); a *unit* is one recording of
one rod and every variant run on it, so that each rendered set of clouds is made once and used by every
method and every variant it serves (the 30 fps unoccluded clouds give ``occ0``, ``fps10`` (every third
cloud), ``fastest`` and, for DLO3, ``wrong_model`` and ``right_model``).

Scenarios and their variants:

- ``occlusion``: ``occ0``, ``occ25``, ``occ50`` (that share of the free rope hidden from 30 % to 80 %
  of the recording, 30 fps);
- ``blackout``: the whole rope hidden for ``BLACKOUT_S`` from ``BLACKOUT_START_S``;
- ``fastest``: the recordings with the highest 95th-percentile gripper speed, per rod;
- ``fps10``: the unoccluded clouds at 10 Hz;
- ``sensor``: the unoccluded motion filmed by a sensor with two artefacts of real RGB-D cameras that
  the other scenarios leave out (``SENSOR``: colour registered 2 px off the depth, half the far
  pixels of depth edges at a mixed depth); reference ``occ0``;
- ``far_camera``: the unoccluded motion filmed as another lab might (``FAR``: 1.6 m away, 50 degrees
  down and 35 off square, three quarters of the resolution, 2.6 times the depth noise, 1 % dropouts)
  at 15 Hz, where the rope is a line two pixels wide; reference ``occ0``;
- ``contact``: truth simulated with a table (``table``) or a post (``post``) the tracker's model does
  not know, and ``nocontact``, the same gripper motion simulated without contact (the reference);
- ``wrong_model``: DLO3 tracked with DLO1's model; ``right_model`` the same clouds with DLO3's.
- ``wrong_length``: DLO3 tracked with DLO3's model whose free rest lengths are ``LENGTH_ERROR`` too
  long (``long_model``) or too short (``short_model``): a rope given the wrong length; reference
  ``right_model``.

Recordings: the ``eval`` split of DLO1..DLO3; DLO4 and DLO5 have none, so their held-out validation
recordings (every fifth training recording, as `deform train` holds them out) stand in. Without the
dataset: synthetic recordings of each rod's model (``deform.generate_recording``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from deform import (
    find_data_root,
    generate_recording,
    generic_model,
    gripped_indices,
    load_model,
    load_recording,
)
from deform.io.arc_length import resample_vertices

RODS = ("DLO1", "DLO2", "DLO3", "DLO4", "DLO5")
SCENARIOS = (
    "occlusion",
    "blackout",
    "fastest",
    "fps10",
    "sensor",
    "far_camera",
    "contact",
    "wrong_model",
    "wrong_length",
    "generic",
)
VARIANTS = {
    "occlusion": ("occ0", "occ25", "occ50"),
    "blackout": ("blackout",),
    "fastest": ("fastest",),
    "fps10": ("fps10",),
    "sensor": ("sensor",),
    "far_camera": ("far",),
    "contact": ("table", "post", "nocontact"),
    "wrong_model": ("wrong_model", "right_model"),
    "wrong_length": ("long_model", "short_model", "right_model"),
    "generic": ("generic_model", "shipped_model"),
}
# what the ratio columns compare: variant -> its reference (same recordings)
REFERENCE = {
    "sensor": "occ0",
    "far": "occ0",
    "table": "nocontact",
    "post": "nocontact",
    "wrong_model": "right_model",
    "long_model": "right_model",
    "short_model": "right_model",
    "generic_model": "shipped_model",
}
GENERIC = "generic:"  # a model key: the generic DER of the rod's length and mass (deform.generic_model)
QUICK_VARIANTS = (
    "occ0",
    "occ50",
    "blackout",
    "fastest",
    "fps10",
    "sensor",
    "far",
    "table",
    "post",
    "nocontact",
    "wrong_model",
    "right_model",
    "generic_model",
    "shipped_model",
)
QUICK_RODS = ("DLO1", "DLO3")
WRONG = ("DLO3", "DLO1")  # (the rod filmed, the model that tracks it)
ONLY_WRONG_ROD = ("wrong_model", "right_model", "long_model", "short_model")  # variants of WRONG[0] only
LENGTH_ERROR = 0.06  # of the free rest length, in ``long_model`` / ``short_model``
RESCALED = "@"  # a model key "DLO3@1.06": the rod's model, its free rest lengths times 1.06
SENSOR = {"color_shift_px": 2, "flying_pixels": 0.5}  # RenderConfig fields of the ``sensor`` clouds
FAR = {  # RenderConfig fields of the ``far`` clouds: the calibration benchmark's other lab's camera
    "scale": 0.75,
    "camera_distance": 1.6,
    "camera_elevation_deg": 50.0,
    "camera_azimuth_deg": 35.0,
    "noise_base": 0.002,
    "noise_quad": 0.0025,
    "dropout": 0.01,
}
FAR_FPS = 15.0
BLACKOUT_START_S = 1.5
BLACKOUT_S = 1.0
FPS = 30.0


@dataclass
class Clouds:
    """One rendered set of clouds: the truth it shows and how it is rendered; ``cases`` the variants
    that use it as ``(variant, fps, model rod)``."""

    name: str
    truth: np.ndarray
    render: dict = field(default_factory=dict)  # RenderConfig fields replaced
    obstacles: list = field(default_factory=list)
    cases: list = field(default_factory=list)
    info: dict = field(default_factory=dict)


@dataclass
class Unit:
    """One recording of one rod and the variants to run on it."""

    rod: str
    name: str
    positions: np.ndarray
    dt: float
    variants: tuple

    @property
    def key(self) -> str:
        return f"{self.rod}.{self.name}"


def _sorted(files):
    return sorted(files, key=lambda p: (len(p.stem), p.stem))


def held_out_files(root: Path, rod: str) -> list[Path]:
    """A rod's held-out recordings: ``eval``, else every fifth ``train`` recording (the validation split)."""
    ev = _sorted((root / rod / "eval").glob("*.pkl"))
    return ev if ev else _sorted((root / rod / "train").glob("*.pkl"))[::5]


def grip_speed_p95(positions: np.ndarray, dt: float) -> float:
    """95th percentile over frames of the faster gripper's speed [m/s] (vertices 0 and n-1, smoothed
    over 5 frames: single-frame capture spikes are not motion)."""
    p = np.asarray(positions)[:, [0, -1]]
    k = 5
    kernel = np.ones(k) / k
    smooth = np.stack(
        [np.convolve(p[:, j, d], kernel, mode="valid") for j in range(2) for d in range(3)], -1
    ).reshape(-1, 2, 3)
    speed = np.linalg.norm(np.diff(smooth, axis=0), axis=-1).max(1) / dt
    return float(np.percentile(speed, 95))


def select_units(rods, per_rod: int, variants, root: Path | None = None, synthetic_seeds: int | None = None):
    """The units: per rod the first ``per_rod`` held-out recordings (every variant but ``fastest``) and
    the ``per_rod`` fastest (``fastest``; one unit when a recording is both).

    Args:
        rods: rod names.
        per_rod: recordings per rod (0: all).
        variants: the variants to run.
        root: the dataset (None: find it; none found: synthetic recordings).
        synthetic_seeds: recordings per rod without the dataset (default ``per_rod`` or 1).

    Returns:
        ``(units, ranking)``: the :class:`Unit` s and, per rod, the recordings by p95 gripper speed.
    """
    root = root or find_data_root()
    variants = tuple(variants)
    plain = tuple(v for v in variants if v != "fastest")
    units, ranking = [], {}
    for rod in rods:
        own = tuple(v for v in plain if v not in ONLY_WRONG_ROD or rod == WRONG[0])
        if root is None:
            model = load_model(rod)
            for seed in range(synthetic_seeds or max(per_rod, 1)):
                rec = generate_recording(model, n_frames=500, seed=2 * seed)
                vs = own + (("fastest",) if "fastest" in variants and seed == 0 else ())
                units.append(Unit(rod, f"synthetic_{seed}", rec.positions, float(model.dt), vs))
            continue
        files = held_out_files(root, rod)
        recs = {p.stem: load_recording(p) for p in files}
        speeds = {name: grip_speed_p95(r.positions, r.dt) for name, r in recs.items()}
        ranking[rod] = [
            dict(recording=k, grip_speed_p95=round(v, 3))
            for k, v in sorted(speeds.items(), key=lambda kv: -kv[1])
        ]
        first = [p.stem for p in files][: per_rod or None]
        fast = [r["recording"] for r in ranking[rod]][: per_rod or None] if "fastest" in variants else []
        for name in dict.fromkeys(first + fast):
            vs = (own if name in first else ()) + (("fastest",) if name in fast else ())
            if vs:
                units.append(Unit(rod, name, recs[name].positions, float(recs[name].dt), vs))
    return units, ranking


def model_of(key: str):
    """The model a case names: a shipped rod's (``"DLO1"``), or ``"generic:DLO1"``, the generic DER
    with that rod's length, mass and vertex count and nothing else (``"DLO3@1.06"``: DLO3's; the
    rest-length factor is :func:`rest_scale_of`'s)."""
    key = key.split(RESCALED)[0]
    if key.startswith(GENERIC):
        cfg = load_model(key[len(GENERIC) :]).cfg
        return generic_model(cfg.length_m, cfg.mass_kg, cfg.n_vertices)
    return load_model(key)


def rest_scale_of(key: str) -> float:
    """The factor on the free rest lengths a model key names (``"DLO3@1.06"``: 1.06; else 1)."""
    _, _, scale = key.partition(RESCALED)
    return float(scale) if scale else 1.0


def resample_to(positions: np.ndarray, model) -> np.ndarray:
    """(T, m, 3) a trajectory as ``model``'s vertices (for tracking a rod with another rod's model):
    the gripped vertices where the grippers hold the rope, the inner ones along the marker polyline
    at the model's rest-length fractions (:func:`deform.io.arc_length.resample_vertices`)."""
    return resample_vertices(positions, model.n, model.nominal_rest.detach().double().numpy())


def on_rendered_rope(x: np.ndarray, model, per_segment: int = 8) -> np.ndarray:
    """(n, 3) ``model``'s vertices laid on the rope the camera sees (the renderer's smooth curve
    through the markers ``x`` (m, 3)), gripped ones at the gripped markers: a tracker that followed
    the camera exactly with this model. The tracking error of this shape is the least a model of
    another vertex count can score against the marker polyline."""
    from perception import rope_centreline

    m = len(x)
    curve = rope_centreline(x, per_segment)
    source = np.concatenate([x[:1], curve[per_segment : (m - 2) * per_segment + 1], x[-1:]])
    return resample_vertices(source, model.n, model.nominal_rest.detach().double().numpy())


def clouds_of(unit: Unit) -> list[Clouds]:
    """The rendered sets of clouds a unit needs, with the variants each serves."""
    from benchmarks.tracking.contact import place_post, place_table, simulate

    v = set(unit.variants)
    out = []
    plain = [
        (c, FPS if c != "fps10" else 10.0)
        for c in ("occ0", "fps10", "fastest", *ONLY_WRONG_ROD, "generic_model", "shipped_model")
        if c in v
    ]
    if plain:
        tracked_by = {
            "wrong_model": WRONG[1],
            "long_model": f"{unit.rod}{RESCALED}{1 + LENGTH_ERROR:g}",
            "short_model": f"{unit.rod}{RESCALED}{1 - LENGTH_ERROR:g}",
            "generic_model": GENERIC + unit.rod,
        }
        cases = [(c, fps, tracked_by.get(c, unit.rod)) for c, fps in plain]
        out.append(Clouds("occ0", unit.positions, {"occlusion": 0.0}, cases=cases))
    for c, occ in (("occ25", 0.25), ("occ50", 0.5)):
        if c in v:
            out.append(Clouds(c, unit.positions, {"occlusion": occ}, cases=[(c, FPS, unit.rod)]))
    if "sensor" in v:
        out.append(Clouds("sensor", unit.positions, dict(SENSOR), cases=[("sensor", FPS, unit.rod)]))
    if "far" in v:
        out.append(Clouds("far", unit.positions, dict(FAR), cases=[("far", FAR_FPS, unit.rod)]))
    if "blackout" in v:
        out.append(
            Clouds(
                "blackout",
                unit.positions,
                {"blackout_start_s": BLACKOUT_START_S, "blackout_s": BLACKOUT_S},
                cases=[("blackout", FPS, unit.rod)],
                info=dict(blackout_start_s=BLACKOUT_START_S, blackout_s=BLACKOUT_S),
            )
        )
    if v & {"table", "post", "nocontact"}:
        model = load_model(unit.rod)
        ref = simulate(model, unit.positions)
        if "nocontact" in v:
            out.append(Clouds("nocontact", ref, {}, cases=[("nocontact", FPS, unit.rod)]))
        if "table" in v:
            table = place_table(ref)
            truth = simulate(model, unit.positions, table=table)
            from benchmarks.tracking.contact import contact_fraction

            out.append(
                Clouds(
                    "table",
                    truth,
                    {"table_z": table.surface_z},
                    cases=[("table", FPS, unit.rod)],
                    info=dict(
                        table_surface_z=table.surface_z, contact_fraction=contact_fraction(truth, table)
                    ),
                )
            )
        if "post" in v:
            post = place_post(ref, unit.dt)
            truth = simulate(model, unit.positions, post=post)
            from benchmarks.tracking.contact import post_contact_fraction

            out.append(
                Clouds(
                    "post",
                    truth,
                    {},
                    obstacles=[post.mesh()],
                    cases=[("post", FPS, unit.rod)],
                    info=dict(
                        post_xy=list(post.xy),
                        post_radius=post.radius,
                        post_top_z=post.top_z,
                        contact_fraction=post_contact_fraction(truth, post),
                    ),
                )
            )
    return out


def render_config(base, clouds: Clouds):
    """The :class:`perception.config.RenderConfig` of a set of clouds."""
    return replace(base, **clouds.render)


def grips(positions: np.ndarray) -> np.ndarray:
    """(T, 4, 3) the gripped vertices of a trajectory."""
    return np.asarray(positions)[:, gripped_indices(positions.shape[1])]
