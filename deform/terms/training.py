"""Physics terms in the trained model: the loop from ``deform diagnose`` back into DEFORM.

The discrepancy tool fits candidate effects on a plain DER model and names the ones the recordings
need. DEFORM itself is richer than that plain model, so a named effect is one of three kinds:

* **built in**: DEFORM already identifies it as free parameters (:data:`BUILT_IN`). Training with
  the term is ordinary training; training *without* it (``without=``, an ablation) ties or freezes
  those parameters, which is how its worth on held-out recordings is measured.
* **added**: a force the model lacks (:data:`ADDED`). The tool's own term module is attached to
  ``DeformModel.extensions`` (its ``acceleration``/``mass`` hooks), trained with the physical
  parameters and saved in the checkpoint (:func:`attached_names`, :func:`attach`).
* **not trainable here** (:data:`NOT_TRAINABLE`): the reason is given instead.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from deform.errors import UsageError

BUILT_IN: dict[str, str] = {
    "aerodynamic_drag": "quadratic drag on the velocity across the rod (log_drag) beside linear damping",
    "stiffness_variation": "a bending and a twisting stiffness per interior vertex (log_beta, log_gamma)",
    "rest_curvature": "a rest curvature per interior vertex in the material frame (wbar)",
    "point_mass": "an extra point mass at every vertex (extra_mass_raw)",
}
ADDED: tuple[str, ...] = ("internal_damping", "ground_contact", "external_force")
NOT_TRAINABLE: dict[str, str] = {
    "actuation_delay": "a delay of the gripper inputs is a property of the recording, not of the rope: "
    "shift the recordings' gripper poses by the delay the diagnosis found",
    "mass_scale": "a uniform mass factor is not observable: the identified stiffness already absorbs it",
}


def check_names(names: list[str] | tuple[str, ...]) -> None:
    """A UsageError naming the choices for an unknown or untrainable term.

    Args:
        names: term names.

    Raises:
        UsageError: an unknown or untrainable name, with the reason or the choices.
    """
    for name in names:
        if name in NOT_TRAINABLE:
            raise UsageError(f"term {name!r} cannot be trained into the model: {NOT_TRAINABLE[name]}")
        if name not in BUILT_IN and name not in ADDED:
            raise UsageError(f"unknown term {name!r}; choose from {', '.join(sorted([*BUILT_IN, *ADDED]))}")


def describe(name: str) -> str:
    """One line on what training with ``name`` means for DEFORM.

    Args:
        name: a term of :data:`BUILT_IN` or :data:`ADDED`.

    Returns:
        The line.
    """
    if name in BUILT_IN:
        return f"{name}: already in DEFORM as {BUILT_IN[name]}"
    return f"{name}: added to DEFORM as an extension term"


def attach(model, names: list[str] | tuple[str, ...], recordings=None) -> list[str]:
    """Attach the :data:`ADDED` terms among ``names`` to ``model.extensions`` (once each).

    Args:
        model: a :class:`deform.model.DeformModel`.
        names: term names; built-in ones need nothing attached and are skipped.
        recordings: training recordings; their marker arc length places the terms along the rod and
            their lowest point starts a contact plane. None: an even spacing, and a plane at z = 0.

    Returns:
        The names attached now.
    """
    from deform.terms.library import make_term

    check_names(names)
    have = set(attached_names(model))
    context, arclength = {}, np.linspace(0.0, 1.0, model.n)
    if recordings:
        from deform.io.recordings import arclength_of

        arclength = arclength_of(recordings)
        context["lowest_z"] = float(min(r.positions[..., 2].min() for r in recordings))
    added = []
    for name in names:
        if name in ADDED and name not in have:
            term = make_term(name, model.n, arclength, context)
            if hasattr(term, "set_dt"):
                term.set_dt(model.dt)
            model.extensions.append(term)
            added.append(name)
    fix_rest(model)
    return added


def fix_rest(model) -> None:
    """Put the attached terms that depend on rest lengths on the model's typical ones
    (``model.nominal_rest``), fixed for the run: a trained model's step then exports ahead of time
    (see ``InternalDamping.fix_rest``). Called on attaching and after a checkpoint is loaded.

    Args:
        model: a :class:`deform.model.DeformModel`.
    """
    for term in model.extensions:
        if hasattr(term, "fix_rest"):
            term.fix_rest(model.nominal_rest)


def attached_names(model) -> list[str]:
    """Names of the extension terms a model carries, in order (saved with the checkpoint).

    Args:
        model: a :class:`deform.model.DeformModel`.

    Returns:
        The names.
    """
    return [getattr(ext, "name", type(ext).__name__) for ext in model.extensions]


def rebuild(model, names: list[str]) -> None:
    """Empty extension terms of these names (a checkpoint's state dict then fills them).

    Args:
        model: a :class:`deform.model.DeformModel` being loaded.
        names: the checkpoint's ``terms``.
    """
    attach(model, [name for name in names if name in ADDED])


def without(model, names: list[str] | tuple[str, ...]) -> list[torch.nn.Parameter]:
    """Remove built-in freedoms for an ablation; returns the parameters to keep frozen.

    Drag goes to its floor, extra masses back to the configured marker mass, the rest curvature to
    zero; all frozen. Stiffness becomes uniform (the mean over vertices); :func:`tie` keeps it so
    after every optimiser step, so it is not frozen. An added term the model carries (a shipped
    model trained with it) is detached; one it does not carry is refused (leave it out instead).

    Args:
        model: a :class:`deform.model.DeformModel`.
        names: built-in terms to remove.

    Returns:
        The parameters frozen.
    """
    from deform.rod.positive import inv_softplus

    check_names(names)
    frozen = []
    with torch.no_grad():
        for name in names:
            if name == "aerodynamic_drag":
                model.log_drag.fill_(math.log(1e-4))
                frozen.append(model.log_drag)
            elif name == "point_mass":
                model.extra_mass_raw.fill_(inv_softplus(model.cfg.marker_mass_kg * 1e3))
                frozen.append(model.extra_mass_raw)
            elif name == "rest_curvature":
                model.wbar.zero_()
                frozen.append(model.wbar)
            elif name == "stiffness_variation":
                tie(model, names)
            elif name in ADDED and name in attached_names(model):
                kept = [ext for ext in model.extensions if getattr(ext, "name", None) != name]
                model.extensions = torch.nn.ModuleList(kept)
            elif name in ADDED:
                raise UsageError(f"term {name!r} is not part of this model: leave it out instead")
    for p in frozen:
        p.requires_grad_(False)
    return frozen


def tie(model, names: list[str] | tuple[str, ...]) -> None:
    """Project the tied built-in parameters back onto their constraint (uniform stiffness).

    Args:
        model: a :class:`deform.model.DeformModel`.
        names: the terms removed (only ``stiffness_variation`` is tied).
    """
    if "stiffness_variation" in names:
        with torch.no_grad():
            model.log_beta.fill_(float(model.log_beta.mean()))
            model.log_gamma.fill_(float(model.log_gamma.mean()))
