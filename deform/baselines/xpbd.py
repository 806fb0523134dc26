"""XPBD rope (Macklin et al. 2016, with the 'small steps' substepping of Macklin et al. 2019).

Vertices carry point masses (the rod's mass spread by edge length plus the markers); gripped
vertices 0, 1, n-2, n-1 have infinite mass and move linearly to their inputs over the substeps.
Per substep ``h = dt / substeps``: gravity, exponential damping ``v *= exp(-c h)``, prediction
``p = x + h v``, then one XPBD pass over

- distance constraints ``|p_i - p_{i+1}| = l_i`` (compliance ``alpha_stretch``), rest lengths from
  frame 0;
- bending constraints ``|p_i - p_{i+2}| = l_i + l_{i+1}`` (compliance ``alpha_bend``: the rope
  resists folding, straight at rest),

``dlambda = -C / (w_i + w_j + alpha / h^2)`` (a single iteration per substep, so lambda starts at
zero). Constraints are coloured into groups sharing no vertex, so that each group is one vectorised
numpy update (Gauss-Seidel between groups). Velocities ``v = (p - x) / h``.

Parameters (``alpha_stretch``, ``alpha_bend``, ``damping``; ``substeps`` fixed) are tuned by
:func:`tune` with a coarse-to-fine log grid on the open-loop L1 of train recordings, and stored as
``weights/xpbd_ROD.json``.
"""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from deform.baselines import WEIGHT_DIR, MissingWeightsError
from deform.config import load_rod_config
from deform.model import gripped_indices

GRAVITY = np.array([0.0, 0.0, -9.81])


@dataclass
class XPBDParams:
    alpha_stretch: float = 1e-7  # m/N
    alpha_bend: float = 1.0  # m/N
    damping: float = 1.0  # 1/s
    substeps: int = 10


@dataclass
class XPBDState:
    x: torch.Tensor  # (B, n, 3), what the evaluation reads
    xn: np.ndarray  # (B, n, 3) positions
    vn: np.ndarray  # (B, n, 3) velocities
    rest: np.ndarray  # (B, n-1) edge rest lengths
    brest: np.ndarray  # (B, n-2) bending rest distances


def _groups(pairs: list[tuple[int, int]]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Greedy colouring of constraints (i, j) into groups that share no vertex: (k, i, j) index arrays."""
    groups: list[list[int]] = []
    used: list[set] = []
    for k, (i, j) in enumerate(pairs):
        for g, u in zip(groups, used):
            if i not in u and j not in u:
                g.append(k)
                u.update((i, j))
                break
        else:
            groups.append([k])
            used.append({i, j})
    return [
        (np.array(g), np.array([pairs[k][0] for k in g]), np.array([pairs[k][1] for k in g])) for g in groups
    ]


class XPBDRope:
    def __init__(
        self,
        n: int,
        mass_kg: float,
        marker_mass_kg: float,
        dt: float = 0.01,
        params: XPBDParams | None = None,
    ):
        self.n = n
        self.dt = dt
        self.mass_kg = mass_kg
        self.marker_mass_kg = marker_mass_kg
        self.params = params or XPBDParams()
        self.grip = np.array(gripped_indices(n))
        free = np.ones(n)
        free[self.grip] = 0.0
        self.free = free
        self.stretch_groups = _groups([(i, i + 1) for i in range(n - 1)])
        self.bend_groups = _groups([(i, i + 2) for i in range(n - 2)])

    @classmethod
    def for_rod(cls, rod: str, params: XPBDParams | None = None) -> XPBDRope:
        cfg = load_rod_config(rod)
        return cls(cfg.n_vertices, cfg.mass_kg, cfg.marker_mass_kg, cfg.dt, params)

    def _inv_mass(self, rest: np.ndarray) -> np.ndarray:
        half = 0.5 * rest
        vor = np.concatenate([half[:, :1], half[:, :-1] + half[:, 1:], half[:, -1:]], axis=1)
        mass = self.mass_kg * vor / rest.sum(1, keepdims=True) + self.marker_mass_kg
        return self.free / mass  # (B, n), zero at the gripped vertices

    def initial_state(self, x0, x1) -> XPBDState:
        x0 = np.asarray(torch.as_tensor(x0, dtype=torch.float64)).reshape(-1, self.n, 3).copy()
        x1 = np.asarray(torch.as_tensor(x1, dtype=torch.float64)).reshape(-1, self.n, 3).copy()
        rest = np.linalg.norm(np.diff(x0, axis=1), axis=-1)
        return XPBDState(torch.from_numpy(x1), x1, (x1 - x0) / self.dt, rest, rest[:, :-1] + rest[:, 1:])

    def _project(self, p, w, groups, rest, alpha_tilde):
        for k, i, j in groups:
            d = p[:, i] - p[:, j]  # (B, g, 3)
            length = np.sqrt((d * d).sum(-1))  # (B, g)
            wi, wj = w[:, i], w[:, j]
            dlam = -(length - rest[:, k]) / (wi + wj + alpha_tilde)
            corr = (dlam / np.maximum(length, 1e-12))[..., None] * d
            p[:, i] += wi[..., None] * corr
            p[:, j] -= wj[..., None] * corr

    def step(self, state: XPBDState, grip_next) -> XPBDState:
        prm = self.params
        s = int(prm.substeps)
        h = self.dt / s
        x, v = state.xn.copy(), state.vn.copy()
        w = self._inv_mass(state.rest)
        g0 = x[:, self.grip].copy()
        g1 = np.asarray(torch.as_tensor(grip_next, dtype=torch.float64)).reshape(-1, 4, 3)
        fade = math.exp(-prm.damping * h)
        a_s, a_b = prm.alpha_stretch / h**2, prm.alpha_bend / h**2
        free = self.free[None, :, None]
        for k in range(1, s + 1):
            v = (v + h * GRAVITY * free) * fade
            p = x + h * v
            p[:, self.grip] = g0 + (g1 - g0) * (k / s)
            self._project(p, w, self.stretch_groups, state.rest, a_s)
            self._project(p, w, self.bend_groups, state.brest, a_b)
            v = (p - x) / h
            x = p
        return XPBDState(torch.from_numpy(x), x, v, state.rest, state.brest)


def weight_path(rod: str) -> Path:
    """Args:
        rod: a rod name.

    Returns:
        Where the tuned XPBD parameters of that rod are stored (JSON).
    """
    return WEIGHT_DIR / f"xpbd_{rod}.json"


def load_xpbd(rod: str, path: str | Path | None = None) -> XPBDRope:
    """The tuned XPBD rope of a rod.

    Args:
        rod: a rod name.
        path: a JSON file instead of :func:`weight_path`.

    Returns:
        The :class:`XPBDRope`.

    Raises:
        MissingWeightsError: no such file.
    """
    p = Path(path) if path else weight_path(rod)
    if not p.is_file():
        raise MissingWeightsError(f"{p}: no tuned XPBD parameters for {rod}; run benchmarks/baselines.py")
    data = json.loads(p.read_text())
    return XPBDRope.for_rod(rod, XPBDParams(**data["params"]))


def _score(rope: XPBDRope, recordings, steps: int) -> float:
    from deform.evaluate import metrics, predict_recordings

    with np.errstate(all="ignore"):
        err = metrics(predict_recordings(rope, recordings, steps))["l1_m"]
    return err if math.isfinite(err) else math.inf


def tune(
    rod: str,
    train_recs,
    steps: int = 300,
    max_recordings: int = 12,
    substeps: int = 10,
    save: bool = True,
    progress: bool = False,
) -> dict:
    """Coarse log grid over (alpha_bend, damping) at two stretch compliances, then a finer grid
    around the best; score = open-loop L1 over ``steps`` on up to ``max_recordings`` train recordings.

    Args:
        rod: a rod name.
        train_recs: recordings to score on.
        steps: open-loop steps per recording.
        max_recordings: recordings used at most.
        substeps: XPBD substeps per model step.
        save: write the result to :func:`weight_path`.
        progress: print progress.

    Returns:
        ``rod``, the best ``params``, their ``train_l1_m``, every configuration tried and the tuning setup.
    """
    recs = train_recs[:: max(1, len(train_recs) // max_recordings)][:max_recordings]
    rope = XPBDRope.for_rod(rod)
    best = (math.inf, None)
    tried = 0

    def run(grid):
        nonlocal best, tried
        for a_s, a_b, c in grid:
            rope.params = XPBDParams(a_s, a_b, c, substeps)
            err = _score(rope, recs, steps)
            tried += 1
            if progress:
                print(
                    f"  xpbd {rod} alpha_s={a_s:.1e} alpha_b={a_b:.1e} c={c:.2f}: {err * 100:.3f} cm",
                    flush=True,
                )
            if err < best[0]:
                best = (err, XPBDParams(a_s, a_b, c, substeps))

    run(itertools.product((1e-8, 1e-5), (1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0), (0.1, 0.5, 2.0, 5.0)))
    b = best[1]
    run(
        itertools.product(
            (b.alpha_stretch,),
            [b.alpha_bend * f for f in (0.3, 0.55, 1.0, 1.8, 3.3)],
            [b.damping * f for f in (0.5, 0.75, 1.0, 1.4, 2.0)],
        )
    )
    result = {
        "rod": rod,
        "params": asdict(best[1]),
        "train_l1_m": best[0],
        "configs_tried": tried,
        "tuning": {"steps": steps, "recordings": [r.name for r in recs]},
    }
    if save:
        weight_path(rod).parent.mkdir(parents=True, exist_ok=True)
        weight_path(rod).write_text(json.dumps(result, indent=2) + "\n")
    return result
