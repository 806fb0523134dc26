"""A small isotropic Gaussian mixture fitted by EM, with means initialised at the predicted vertices.

Written out (rather than sklearn's GaussianMixture, available as ``backend="sklearn"``) because the
tracker needs a few components on a few hundred points in well under a millisecond, and because some
components must keep their means fixed: occluded neighbours absorb their share of the points without
being moved.
"""

from __future__ import annotations

import numpy as np

VAR_FLOOR = 0.003**2


def fit_gmm(
    points: np.ndarray, means: np.ndarray, free: np.ndarray, sigma: float, iters: int, backend: str = "numpy"
) -> tuple[np.ndarray, np.ndarray]:
    """Means (K, 3) and responsibilities (N, K) of a K-component isotropic mixture.

    ``free`` (K,) bool: components whose means EM may move; the others stay at ``means``.

    Args:
        points: (N, 3) points [m].
        means: (K, 3) initial means (the predicted vertices) [m].
        free: (K,) bool.
        sigma: initial isotropic standard deviation [m].
        iters: EM iterations.
        backend: ``"numpy"`` or ``"sklearn"``.

    Returns:
        ``(means, resp)``: (K, 3) and (N, K).
    """
    if backend == "sklearn":
        return _fit_sklearn(points, means, free, sigma, iters)
    mu = np.array(means, dtype=np.float64)
    k = len(mu)
    var = np.full(k, sigma * sigma)
    weight = np.full(k, 1.0 / k)
    resp = np.zeros((len(points), k))
    for _ in range(max(iters, 1)):
        d2 = ((points[:, None, :] - mu[None]) ** 2).sum(-1)
        log_p = np.log(weight) - 1.5 * np.log(var) - 0.5 * d2 / var
        log_p -= log_p.max(1, keepdims=True)
        resp = np.exp(log_p)
        resp /= resp.sum(1, keepdims=True)
        mass = resp.sum(0) + 1e-9
        new_mu = (resp.T @ points) / mass[:, None]
        mu[free] = new_mu[free]
        d2 = ((points[:, None, :] - mu[None]) ** 2).sum(-1)
        var = np.maximum((resp * d2).sum(0) / (3 * mass), VAR_FLOOR)
        weight = np.maximum(mass / mass.sum(), 1e-6)
    return mu, resp


def _fit_sklearn(points, means, free, sigma, iters):
    from sklearn.mixture import GaussianMixture

    k = len(means)
    if len(points) < k:
        return np.array(means, dtype=np.float64), np.zeros((len(points), k))
    gm = GaussianMixture(
        k,
        covariance_type="spherical",
        means_init=means,
        precisions_init=np.full(k, 1 / sigma**2),
        max_iter=max(iters, 1),
        tol=1e-6,
        reg_covar=VAR_FLOOR,
    )
    gm.fit(points)
    mu = np.where(free[:, None], gm.means_, means)
    return mu, gm.predict_proba(points)
