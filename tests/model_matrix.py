"""The models of the entry-point matrix (tests/deform/test_every_model.py and
tests/service/test_every_model.py): every shipped model, and a small model carrying each physics
term a model can carry, with values that act.

Why: DLO4, the one shipped model with the wind term, failed the service's float32 predict step
(issue 52) while DLO1 passed; nothing ran every model, or every term, through every step.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from deform import DeformModel, load_rod_config
from deform.model import MODEL_DIR
from deform.terms import ADDED, attach

SHIPPED = ("DLO1", "DLO2", "DLO3", "DLO4", "DLO5")
# every term a trained model can carry: the added ones as extension modules, the built-in ones as
# the model's own parameters (deform.terms.BUILT_IN)
TERMS = (
    "internal_damping",
    "ground_contact",
    "external_force",
    "aerodynamic_drag",
    "point_mass",
    "stiffness_variation",
    "rest_curvature",
)
ALL_TERMS = "all_terms"
SMALL_VERTICES = 8


def shipped_models() -> tuple[str, ...]:
    """The rods a model is shipped for (``deform/models/*.pt``)."""
    return tuple(sorted(p.stem for p in MODEL_DIR.glob("*.pt")))


def term_model(term: str) -> DeformModel:
    """An untrained model of DLO4's rod on :data:`SMALL_VERTICES` vertices carrying ``term`` (one
    of :data:`TERMS`, or :data:`ALL_TERMS` for every one at once): an added term attached with
    :func:`deform.terms.attach`, a built-in one with its parameters away from their defaults.

    Args:
        term: the term's name.

    Returns:
        The model (float32 parameters, float64 terms, as a trained one).
    """
    cfg = load_rod_config("DLO4").model_copy(update={"n_vertices": SMALL_VERTICES, "name": f"small-{term}"})
    model = DeformModel(cfg)
    names = TERMS if term == ALL_TERMS else (term,)
    attach(model, [name for name in names if name in ADDED])
    n = model.n
    with torch.no_grad():
        for ext in model.extensions:
            if ext.name == "internal_damping":
                ext.log_nu.fill_(math.log(30.0))  # 3e-4 m^4/s: a planted damping's level
            elif ext.name == "ground_contact":
                ext.h0.fill_(0.005)  # 5 mm above a rod lying at z = 0 (deform.step_graph.rod_at_rest)
            elif ext.name == "external_force":
                ext.set_field(1.5, -0.8)  # m/s^2: a wind
        if "aerodynamic_drag" in names:
            model.log_drag.fill_(math.log(2.0))
            model.log_damping.fill_(math.log(0.3))
        if "point_mass" in names:
            model.extra_mass_raw.copy_(torch.linspace(-1.0, 3.0, n))
        if "stiffness_variation" in names:
            model.log_beta.add_(torch.linspace(-1.0, 1.0, n - 2))
            model.log_gamma.add_(torch.linspace(0.5, -0.5, n - 2))
        if "rest_curvature" in names:
            model.wbar.copy_(0.02 * torch.linspace(-1.0, 1.0, 4 * (n - 2)).reshape(n - 2, 2, 2))
    return model


def save_term_models(directory: Path) -> dict[str, Path]:
    """Every term model of :data:`TERMS` and :data:`ALL_TERMS` saved as a checkpoint in
    ``directory``: loaded as a user's model is (``load_model(path)``, ``--rod path``).

    Returns:
        ``{term: checkpoint path}``.
    """
    out = {}
    for term in (*TERMS, ALL_TERMS):
        out[term] = Path(directory) / f"{term}.pt"
        term_model(term).save(out[term])
    return out
