"""Fused pieces (deform.rod.fusion) give the eager values and gradients, and fall back to eager."""

import dataclasses
import logging

import pytest
import torch

from deform import DeformModel, generate_recording, gripped_indices, load_rod_config
from deform.rod import fusion
from deform.rod.energy import fused_geometry_and_projections, geometry_and_projections
from deform.rod.forces import fused_rod_forces, rod_forces
from deform.rod.inextensibility import FUSED_SWEEPS, SWEEPS, PBDMethod
from tests.deform.rod.helpers import random_params, random_rod, twisted_frame


def _pieces(geometry, forces, sweep, x, d1, p, theta, mass, inv_mass, rest):
    """Every piece once, chained as a step chains them; -> outputs and their gradients in x and beta."""
    x = x.clone().requires_grad_(True)
    beta = p.beta.clone().requires_grad_(True)
    geo, a, b = geometry(x, d1)
    force = forces(x, geo, a, b, theta, dataclasses.replace(p, beta=beta), mass)
    projected = sweep(x + 1e-4 * force, inv_mass, rest)
    loss = (projected**2).sum() + (a * b).sum()
    return (force, projected, a, b, *torch.autograd.grad(loss, (x, beta)))


@pytest.mark.compile
@pytest.mark.parametrize(("batch", "n"), [(3, 9), (8, 9)])  # one compile serves every batch size
def test_fused_pieces_give_the_eager_values_and_gradients(batch, n):
    x, gen = random_rod(batch, n, bend=0.4, seed=batch)
    d1, _ = twisted_frame(x, gen)
    p = random_params(batch, n, gen, wbar_scale=0.3)
    theta = 0.3 * torch.randn(n - 1, batch, generator=gen, dtype=x.dtype)
    mass = torch.rand(n, batch, generator=gen, dtype=x.dtype) + 0.5
    inv_mass = 1.0 / mass
    inv_mass[0] = 0.0
    rest = torch.full((n - 1, batch), 0.1, dtype=x.dtype)
    eager = _pieces(
        geometry_and_projections,
        rod_forces,
        SWEEPS[PBDMethod.PROJECTION],
        x,
        d1,
        p,
        theta,
        mass,
        inv_mass,
        rest,
    )
    fused = _pieces(
        fused_geometry_and_projections,
        fused_rod_forces,
        FUSED_SWEEPS[PBDMethod.PROJECTION],
        x,
        d1,
        p,
        theta,
        mass,
        inv_mass,
        rest,
    )
    assert fusion.fusion_enabled()  # no fallback happened: the fused path was compared
    for e, f in zip(eager, fused, strict=True):
        torch.testing.assert_close(f, e, rtol=1e-10, atol=1e-12 * float(e.abs().max()))


@pytest.mark.compile
def test_a_model_with_fused_pieces_steps_and_differentiates_as_eager():
    model = DeformModel(load_rod_config("DLO2"))
    model.options.residual = False
    X = torch.tensor(generate_recording(model, n_frames=12, seed=2).positions, dtype=torch.float64)[None]

    def loss_and_gradient(fused: bool):
        model.fused_pieces = fused
        model.zero_grad()
        _, final = model.rollout(
            model.initial_state(X[:, 0], X[:, 1]), X[:, 2:, gripped_indices(model.n)], True
        )
        loss = (final.x - X[:, -1]).abs().mean()
        loss.backward()
        return loss.detach(), model.log_beta.grad.clone()

    (loss_e, grad_e), (loss_f, grad_f) = loss_and_gradient(False), loss_and_gradient(True)
    assert grad_e.abs().max() > 0
    torch.testing.assert_close(loss_f, loss_e, rtol=1e-9, atol=0)  # rounding of 10 steps
    torch.testing.assert_close(grad_f, grad_e, rtol=1e-8, atol=1e-12 * float(grad_e.abs().max()))


def _compile_that_fails(monkeypatch):
    def compile_(fn, **_):
        def broken(*args, **kwargs):
            raise RuntimeError("no C++ compiler")

        return broken

    monkeypatch.setattr(fusion, "_failed", [])
    monkeypatch.setattr(fusion.torch, "compile", compile_)


def test_a_failed_compile_steps_eagerly_after_one_warning(monkeypatch, caplog):
    monkeypatch.delenv("DEFORM_COMPILE", raising=False)  # the default (tests/conftest.py sets 0)
    _compile_that_fails(monkeypatch)
    piece = fusion.Fused(lambda a, b: a * b + 1)
    with caplog.at_level(logging.WARNING, logger="deform.fusion"):
        assert piece(torch.tensor(2.0), torch.tensor(3.0)) == 7.0
        assert piece(torch.tensor(1.0), torch.tensor(3.0)) == 4.0
    assert [r.getMessage().startswith("fused pieces unavailable (RuntimeError") for r in caplog.records] == [
        True
    ]
    assert not fusion.fusion_enabled()


def test_deform_compile_0_and_steps_without_gradients_stay_eager(monkeypatch):
    monkeypatch.delenv("DEFORM_COMPILE", raising=False)  # the default (tests/conftest.py sets 0)
    _compile_that_fails(monkeypatch)
    piece = fusion.Fused(lambda a: a + 1)
    with torch.no_grad():
        assert piece(torch.tensor(1.0)) == 2.0
    monkeypatch.setenv("DEFORM_COMPILE", "0")
    assert piece(torch.tensor(1.0)) == 2.0
    assert fusion._failed == []  # never compiled, so nothing failed
