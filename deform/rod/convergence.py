"""What the solvers of one step report about convergence, for code that cannot branch on data.

A compiled or ahead-of-time step runs fixed iteration counts (``branch_free``); the twist solver and
the projection then leave their own stopping measures here, per rod, so the caller can redo the
rods that did not converge without evaluating anything twice (:meth:`DeformModel.unconverged_from_report`).
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass
class ConvergenceReport:
    """Per-rod flags of one step, filled by the solvers that ran.

    Attributes:
        length_error: (B,) each rod's largest relative edge error after the branch-free sweeps of
            the projection (NaN counts as unconverged); None until the projection ran.
        twist_unconverged: (B,) bool, rods whose branch-free Newton iterations on the material
            angles had not met the solver's stopping rule; None with the Theseus solver.
    """

    length_error: Tensor | None = None
    twist_unconverged: Tensor | None = None
