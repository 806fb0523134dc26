"""Coherent Point Drift, non-rigid (Myronenko & Song, "Point Set Registration: Coherent Point Drift",
IEEE TPAMI 32(12), 2010), used for tracking by registration: the nodes are the centroids of a
Gaussian mixture, the previous frame's nodes are the template, the current cloud the data.

The registration (also the core the CDCPD and TrackDLO peers build on, :func:`coherent_em`)::

    E-step   P_mn = e_m exp(-|x_n - y_m|^2 / 2σ²) / (Σ_k e_k exp(-|x_n - y_k|^2 / 2σ²) + c),
             c = (2πσ²)^{3/2} w/(1-w) M/N                   (uniform outlier weight w; e_m = 1 in CPD)
    M-step   Y = Y0 + G W,  G_ij = exp(-|y0_i - y0_j|^2 / 2β²)          (motion coherence)
             (diag(P1) G + λσ² I + σ² γ H G + diag(a) G) W
                 = P X - diag(P1) Y0 - σ² γ H Y0 + diag(a) (T - Y0)
             σ² = (tr(Xᵀ d(Pᵀ1) X) - 2 tr((PX)ᵀ Y) + tr(Yᵀ d(P1) Y)) / (3 N_P)

CPD itself has γ = 0 and a = 0. γ H is a locally-linear-embedding shape term (H = (I-W)ᵀ(I-W),
CDCPD and TrackDLO), ``a``/``T`` pull chosen nodes towards targets (CDCPD2's prediction prior,
TrackDLO's correspondence priors); ``e`` (per-node emission prior) carries visibility. These need a
modified M-step and E-step, which is why the EM is written here by hand: pycpd and probreg expose
neither the extra M-step terms nor per-node priors.

Departures from the paper, and why:

- Nodes: one every 3.33 cm (CDCPD's rope template, 25 nodes on 0.8 m, on which the CDCPD paper
  runs CPD as its baseline); CPD itself prescribes no template.
- Scale: CPD works on point sets normalised to zero mean and unit variance, where β = 2, λ = 3 are
  the authors' defaults (their code's examples; w = 0.1). CPD normalises each set by its own
  centroid and spread, which for a partly hidden rope shifts the template towards the visible part. Here β and λ are those defaults expressed in metres by the initial shape's spread s
  (β = 2 s, λ = 2 / s²), once at :meth:`initialize`, so a frame's cloud (which can be a fragment of
  the rope) does not change the regularisation from frame to frame.
- σ² is re-estimated from the data at every frame (as CPD starts); w = 0.1. At most 150 iterations (the authors' default), stopping
  when no node moves more than 10 µm in an iteration.
- Gripped nodes: CPD has no constraints. The template's gripped nodes are set to the grippers and
  held there during the EM by a stiff pull (the a/T term above with a = ``hold`` = 10⁴, which is
  Golyanik et al.'s extended CPD with correspondence priors); the output's are pinned. Without the
  hold, the end nodes (centroids of half a node spacing of rope each) drag the whole rope inwards:
  35-43 mm at the far nodes of a 1.1 m synthetic rope after a 4 mm translation.
- The cloud is voxel-downsampled at 8 mm (CPD prescribes none; an O(MN) EM needs a few hundred
  points at most).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from deform import gripped_indices
from perception.baselines.common import gaussian_kernel, pin, squared_distances
from perception.baselines.interface import BaselineTracker

SIGMA2_FLOOR = 1e-8  # (0.1 mm)^2: keeps the E-step finite once the fit is exact


@dataclass
class MStepTerms:
    """Optional terms of the M-step (see the module docstring): LLE shape ``lle`` (H, weight γ)
    and pulls ``weight`` (M,) towards ``target`` (M, 3)."""

    lle: np.ndarray | None = None
    lle_weight: float = 0.0
    weight: np.ndarray | None = None
    target: np.ndarray | None = None


def initial_sigma2(points: np.ndarray, y: np.ndarray) -> float:
    """CPD's initial variance: the mean squared point-node distance over the 3 dimensions."""
    return float(squared_distances(y, points).mean() / 3)


def coherent_em(
    points: np.ndarray,
    y0: np.ndarray,
    kernel: np.ndarray,
    lam: float,
    w: float,
    sigma2: float,
    max_iter: int,
    tol: float,
    terms: MStepTerms | None = None,
    emit: np.ndarray | None = None,
    sq_dist: Callable[[np.ndarray], np.ndarray] | None = None,
    stop: str = "shift",
) -> tuple[np.ndarray, float]:
    """Register the nodes ``y0`` (M, 3) to ``points`` (N, 3) by coherent EM.

    Args:
        points: (N, 3) data [m].
        y0: (M, 3) template (the previous estimate) [m].
        kernel: (M, M) motion-coherence kernel G.
        lam: λ, the weight of coherence [1/m²].
        w: uniform outlier weight in [0, 1).
        sigma2: initial variance [m²].
        max_iter: most EM iterations.
        tol: stop threshold: the largest node move [m] (``stop="shift"``), the squared change of
            all nodes [m²] (``"shift2"``) or the change of σ² [m²] (``"sigma2"``).
        terms: the optional M-step terms.
        emit: (M,) per-node emission prior e_m (default 1).
        sq_dist: the E-step's squared point-node distances (M, N) from the current nodes (default
            Euclidean; TrackDLO passes a geodesic one).
        stop: ``"shift"``, ``"shift2"`` or ``"sigma2"``.

    Returns:
        ``(y, sigma2)``: (M, 3) registered nodes and the final variance.
    """
    m, n = len(y0), len(points)
    terms = terms or MStepTerms()
    e = np.ones(m) if emit is None else np.asarray(emit, dtype=np.float64)
    a = np.zeros((m, m))
    b0 = np.zeros((m, 3))
    if terms.lle is not None and terms.lle_weight > 0:
        lle_g, lle_y = terms.lle @ kernel, terms.lle @ y0
    if terms.weight is not None:
        a = terms.weight[:, None] * kernel
        b0 = terms.weight[:, None] * (terms.target - y0)
    xx = (points * points).sum(1)
    y = y0.copy()
    s2 = max(float(sigma2), SIGMA2_FLOOR)
    for _ in range(max(max_iter, 1)):
        d2 = squared_distances(y, points) if sq_dist is None else sq_dist(y)
        k = e[:, None] * np.exp(-d2 / (2 * s2))
        c = (2 * np.pi * s2) ** 1.5 * w / (1 - w) * m / n
        p = k / (k.sum(0) + c + 1e-300)
        p1, pt1 = p.sum(1), p.sum(0)
        np_ = p1.sum()
        if np_ < 1e-9:
            break  # no point belongs to any node: nothing to register
        px = p @ points
        lhs = p1[:, None] * kernel + lam * s2 * np.eye(m) + a
        rhs = px - p1[:, None] * y0 + b0
        if terms.lle is not None and terms.lle_weight > 0:
            lhs += s2 * terms.lle_weight * lle_g
            rhs -= s2 * terms.lle_weight * lle_y
        y_new = y0 + kernel @ np.linalg.solve(lhs, rhs)
        s2_old = s2
        s2 = (pt1 @ xx - 2 * (px * y_new).sum() + p1 @ (y_new * y_new).sum(1)) / (3 * np_)
        s2 = max(float(s2), SIGMA2_FLOOR)
        shift = float(np.abs(y_new - y).max())
        change = {"shift": shift, "shift2": float(((y_new - y) ** 2).sum()), "sigma2": abs(s2 - s2_old)}
        y = y_new
        if change[stop] < tol:
            break
    return y, s2


class CPDTracker(BaselineTracker):
    """Non-rigid CPD from frame to frame (see the module docstring).

    Args:
        beta: kernel width in CPD's normalised units (2).
        lam: coherence weight in normalised units (3).
        w: outlier weight (0.1).
        max_iter: most EM iterations per frame (150).
        tol: stop when no node moves more than this in an iteration [m].
        voxel: downsampling cell [m].
        hold: weight of the pull holding the gripped nodes at the grippers.
        nodes: node count (default: one every :attr:`node_spacing` metres).
    """

    name = "cpd"
    node_spacing = 0.8 / 24  # CDCPD's rope template (25 nodes on 0.8 m), on which it compares CPD

    def __init__(
        self,
        beta: float = 2.0,
        lam: float = 3.0,
        w: float = 0.1,
        max_iter: int = 150,
        tol: float = 1e-5,
        voxel: float = 0.008,
        hold: float = 1e4,
        nodes: int | None = None,
    ) -> None:
        super().__init__(nodes)
        self.beta, self.lam, self.w, self.hold = beta, lam, w, hold
        self.max_iter, self.tol, self.voxel = max_iter, tol, voxel

    def _setup(self, x0: np.ndarray) -> None:
        s = float(np.sqrt(((x0 - x0.mean(0)) ** 2).sum(1).mean()))
        self.beta_m = self.beta * s
        self.lam_m = self.lam / (s * s)

    def _register(self, points, grip, depth, camera) -> np.ndarray:
        y0 = pin(self.x, grip)
        kernel = gaussian_kernel(y0, self.beta_m)
        weight = np.zeros(len(y0))
        weight[gripped_indices(len(y0))] = self.hold
        terms = MStepTerms(weight=weight, target=y0)
        sigma2 = initial_sigma2(points, y0)
        y, _ = coherent_em(points, y0, kernel, self.lam_m, self.w, sigma2, self.max_iter, self.tol, terms)
        return y
