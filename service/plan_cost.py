"""Costs of predicted plans, computed where the rollouts are (the predict worker), so a sampling
planner (MPPI, CEM) receives P numbers instead of P x S x n x 3 vertices.

A request's ``"cost"``: ``{"goal": (n, 3) world-frame vertices, "plane_z": z of a plane the rope
should stay above, "weights": {"goal": 1, "stretch": 0, "plane": 0}}``. Per plan:

* ``goal`` [m]: mean over vertices of ``|x_final - goal|`` at the last step;
* ``stretch`` [-]: the largest relative edge stretch ``max(|e| / rest - 1, 0)`` over steps and edges
  (the model keeps edges within 0.1 %; an overstretched plan reaches its grippers' distance);
* ``plane`` [m]: mean over steps of the deepest penetration ``max(plane_z - z, 0)`` over vertices.

``cost = sum(weights[k] * term[k])``; a term whose weight is 0 is still reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.messages import InputError

TERMS = ("goal", "stretch", "plane")


@dataclass(frozen=True)
class CostSpec:
    goal: np.ndarray | None  # (n, 3)
    plane_z: float | None
    weights: dict[str, float]


def parse_cost(spec, n: int) -> CostSpec:
    """Validate a request's ``"cost"`` object for a rod of ``n`` vertices (InputError if bad)."""
    if not isinstance(spec, dict) or set(spec) - {"goal", "plane_z", "weights"}:
        raise InputError("bad_request", '"cost" must be {"goal": ..., "plane_z": ..., "weights": {...}}')
    goal = None
    if spec.get("goal") is not None:
        try:
            goal = np.asarray(spec["goal"], dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError("bad_shape", "cost goal must be an (n, 3) numeric array") from None
        if goal.shape != (n, 3) or not np.all(np.isfinite(goal)):
            raise InputError("bad_shape", f"cost goal shape {goal.shape}, expected ({n}, 3) finite")
    plane_z = spec.get("plane_z")
    if plane_z is not None and (isinstance(plane_z, bool) or not isinstance(plane_z, (int, float))):
        raise InputError("bad_request", "cost plane_z must be a number")
    weights = {"goal": 1.0 if goal is not None else 0.0, "stretch": 0.0, "plane": 0.0}
    given = spec.get("weights", {})
    if not isinstance(given, dict) or set(given) - set(TERMS):
        raise InputError("bad_request", f"cost weights: a dict with keys from {list(TERMS)}")
    for k, w in given.items():
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not w >= 0:
            raise InputError("bad_request", f"cost weight {k} must be a number >= 0")
        weights[k] = float(w)
    if weights["goal"] > 0 and goal is None:
        raise InputError("bad_request", "a goal weight needs a goal")
    if weights["plane"] > 0 and plane_z is None:
        raise InputError("bad_request", "a plane weight needs plane_z")
    return CostSpec(goal, None if plane_z is None else float(plane_z), weights)


def plan_costs(vertices: np.ndarray, rest: np.ndarray, spec: CostSpec) -> dict:
    """Costs of P rollouts.

    Args:
        vertices: (P, S, n, 3) predicted vertices [m].
        rest: (n-1,) rest lengths of the edges [m].
        spec: from :func:`parse_cost`.

    Returns:
        ``{"costs": (P,), "cost_terms": {"goal": (P,), "stretch": (P,), "plane": (P,)}}`` as lists.
    """
    P = vertices.shape[0]
    terms = {k: np.zeros(P) for k in TERMS}
    if spec.goal is not None:
        terms["goal"] = np.linalg.norm(vertices[:, -1] - spec.goal[None], axis=-1).mean(-1)
    # the largest squared stretch ratio over steps and edges, one square root per plan (not per edge)
    # in the rollout's own precision (float32 by default: 1e-7 of a stretch ratio)
    edges = np.diff(vertices, axis=2)  # (P, S, n-1, 3)
    rest2 = np.square(np.asarray(rest, dtype=vertices.dtype)).reshape(1, 1, -1)
    ratio2 = np.einsum("psei,psei->pse", edges, edges) / rest2
    terms["stretch"] = np.clip(np.sqrt(ratio2.max(axis=(1, 2)), dtype=float) - 1.0, 0.0, None)
    if spec.plane_z is not None:
        terms["plane"] = np.clip(spec.plane_z - vertices[..., 2], 0.0, None).max(-1).mean(-1)
    costs = sum(spec.weights[k] * terms[k] for k in TERMS)
    return {"costs": np.asarray(costs).tolist(), "cost_terms": {k: v.tolist() for k, v in terms.items()}}
