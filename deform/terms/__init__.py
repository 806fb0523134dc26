"""Physics terms a DEFORM model can carry beside its elastic rod: a concept of the model's own.

:mod:`.library` holds the terms themselves (small ``nn.Module`` s with a few physical parameters:
internal damping, ground contact, external force, drag, point mass, stiffness variation, rest
curvature, and the two that are properties of a recording, not of a rope: mass scale, actuation
delay). :mod:`.training` says which of them a trained model holds as built-in parameters, which it
attaches as extensions (``DeformModel.extensions``), and how they are saved, rebuilt and ablated.

``deform diagnose`` fits these same terms as candidate effects; it uses them, it does not own them.
"""

from deform.terms.library import LIBRARY, Term, make_term
from deform.terms.training import (
    ADDED,
    BUILT_IN,
    NOT_TRAINABLE,
    attach,
    attached_names,
    check_names,
    describe,
    fix_rest,
    rebuild,
    tie,
    without,
)

__all__ = [
    "ADDED",
    "BUILT_IN",
    "LIBRARY",
    "NOT_TRAINABLE",
    "Term",
    "attach",
    "attached_names",
    "check_names",
    "describe",
    "fix_rest",
    "make_term",
    "rebuild",
    "tie",
    "without",
]
