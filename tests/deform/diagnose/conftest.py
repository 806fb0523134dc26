"""Tiny synthetic datasets for the diagnosis tests (seconds, not minutes)."""

import pytest
import torch

from deform import DeformModel, RodConfig, generate_recording
from deform.diagnose.fitting import FitBudget
from deform.diagnose.selection import DiagnoseBudget
from deform.diagnose.spec import RodSpec

N = 8
SPEC = RodSpec(length_m=0.6, mass_kg=0.04, n_vertices=N, name="tiny")


@pytest.fixture(scope="session")
def sources():
    torch.set_num_threads(1)
    cfg = RodConfig(
        name="tiny", length_m=0.6, mass_kg=0.04, n_vertices=N, bend_stiffness=2e-3, twist_stiffness=1.4e-3
    )
    model = DeformModel(cfg)
    model.options.residual = False
    return [generate_recording(model, n_frames=90, seed=s, warmup_s=1.0, amplitude=0.25) for s in range(6)]


def tiny_budget(candidates):
    # 25 iterations as in the quick budget: at 15 the strong wind scored +7.2 % against its 7.7 %
    # threshold once windows started in transported frames (nominal fits of 15 iterations are noisy)
    return DiagnoseBudget(
        nominal_iterations=25,
        candidate=FitBudget(iterations=25, batch=6, horizon=15, lr_terms=0.15),
        max_rounds=1,
        candidates=tuple(candidates),
        localization_recordings=3,
        progress=False,
    )


# the truth's linear damping at a rope's material level (under the nominal model's bound), and a strong
# wind: the tiny coarse model needs about 1 /s of numerical damping of its own, which the bound
# withholds, so a weak wind (0.8, 0.5 m/s^2) scores +6 % against its 7.7 % threshold here
WIND = {"ax_m_per_s2": 1.6, "ay_m_per_s2": 1.0}


def planted_inputs(effect, sources):
    """3 fit + 3 check recordings of the tiny rod with ``effect`` planted (the strong wind for
    ``external_force``; None: a control), and the truth."""
    from deform.diagnose.planted import generate_planted
    from deform.diagnose.spec import Inputs

    recs, truth = generate_planted(
        effect,
        sources,
        SPEC,
        n_frames=80,
        refine=2,
        substeps=2,
        settle_s=0.5,
        seed=1,
        damping=0.2,
        truth_override=WIND if effect == "external_force" else None,
    )
    return Inputs(spec=SPEC, fit=recs[:3], check=recs[3:]), truth
