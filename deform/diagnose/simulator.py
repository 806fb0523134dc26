"""The plain DER model (DeformModel without residual) with a few nominal parameters plus terms.

DeformModel identifies per-vertex parameters; a diagnosis needs few, interpretable ones. So the
model's parameters are *bound*: before each rollout they are set to expressions of the nominal
parameters (one bending and one twisting stiffness, a linear damping) and of the terms; after the
backward pass their gradients are chained back to those expressions.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn

from deform.config import RodConfig
from deform.model import DeformModel, ModelOptions, gripped_indices
from deform.diagnose.spec import RodSpec
from deform.diagnose.terms import Term

NEGLIGIBLE_MASS_RAW = -12.0  # softplus(-12) g: no marker mass in the plain model
NEGLIGIBLE_LOG_DRAG = math.log(1e-7)


class Nominal(nn.Module):
    """Plain DER: uniform bending EI and twisting GJ [N m^2], linear velocity damping [1/s]."""

    def __init__(self, ei: float = 1e-3, gj: float = 7e-4, damping: float = 0.5):
        super().__init__()
        self.log_ei = nn.Parameter(torch.tensor(math.log(ei), dtype=torch.float64))
        self.log_gj = nn.Parameter(torch.tensor(math.log(gj), dtype=torch.float64))
        self.log_damping = nn.Parameter(torch.tensor(math.log(damping), dtype=torch.float64))

    @torch.no_grad()
    def params(self) -> dict[str, float]:
        return {"bend_stiffness_Nm2": float(self.log_ei.exp()), "twist_stiffness_Nm2": float(self.log_gj.exp()),
                "damping_1_per_s": float(self.log_damping.exp())}

    def clamp_(self) -> None:
        with torch.no_grad():
            self.log_ei.clamp_(math.log(1e-6), math.log(0.3))
            self.log_gj.clamp_(math.log(1e-6), math.log(0.3))
            self.log_damping.clamp_(math.log(1e-3), math.log(20.0))


def arclength_of(recordings) -> np.ndarray:
    """(n,) normalised arc-length position of each marker (median edge lengths over the data)."""
    edges = np.concatenate([np.linalg.norm(np.diff(r.positions[::25], axis=1), axis=-1) for r in recordings])
    s = np.concatenate([[0.0], np.cumsum(np.median(edges, axis=0))])
    return s / s[-1]


class Simulator:
    """A DeformModel driven by a :class:`Nominal` and a list of :class:`Term`."""

    def __init__(self, spec: RodSpec, nominal: Nominal, terms: list[Term] | None = None):
        cfg = RodConfig(name=spec.name, length_m=spec.length_m, mass_kg=spec.mass_kg, n_vertices=spec.n_vertices,
                        dt=spec.dt, marker_mass_kg=1e-9, bend_stiffness=1e-3, twist_stiffness=7e-4)
        self.model = DeformModel(cfg, ModelOptions(residual=False))
        self.n = spec.n_vertices
        self.nominal = nominal
        self.terms = list(terms or [])
        for t in self.terms:
            if hasattr(t, "set_dt"):
                t.set_dt(spec.dt)
            if hasattr(t, "acceleration") or hasattr(t, "mass"):
                self.model.extensions.append(t)

    def parameters(self) -> list[nn.Parameter]:
        out = list(self.nominal.parameters())
        for t in self.terms:
            out += list(t.parameters())
        return out

    def term_parameters(self) -> list[nn.Parameter]:
        return [p for t in self.terms for p in t.parameters()]

    def _exprs(self) -> dict[str, Tensor]:
        m = self.n - 2
        nom = self.nominal
        exprs = {
            "log_beta": nom.log_ei.expand(m),
            "log_gamma": nom.log_gj.expand(m),
            "wbar": torch.zeros(m, 2, 2, dtype=torch.float64),
            "log_damping": nom.log_damping,
        }
        for t in self.terms:
            exprs = t.bind(exprs)
        return exprs

    def sync(self) -> dict[str, Tensor]:
        """Copy the bound expressions into the model; returns them (for :meth:`backward`)."""
        exprs = self._exprs()
        with torch.no_grad():
            for k, e in exprs.items():
                getattr(self.model, k).copy_(e.detach().to(getattr(self.model, k).dtype))
            self.model.extra_mass_raw.fill_(NEGLIGIBLE_MASS_RAW)
            self.model.log_drag.fill_(NEGLIGIBLE_LOG_DRAG)
        return exprs

    def backward(self, loss: Tensor, exprs: dict[str, Tensor]) -> None:
        """Backpropagate ``loss`` to the nominal and term parameters through the bound model."""
        model_params = {k: getattr(self.model, k) for k in exprs}
        for p in model_params.values():
            p.grad = None
        loss.backward()
        outs, grads = [], []
        for k, e in exprs.items():
            g = model_params[k].grad
            if g is not None and e.requires_grad:
                outs.append(e)
                grads.append(g.to(e.dtype))
        if outs:
            torch.autograd.backward(outs, grads)
        for p in model_params.values():
            p.grad = None

    def delay(self) -> Tensor | None:
        for t in self.terms:
            if hasattr(t, "delay_frames"):
                return t.delay_frames
        return None

    def rollout(self, frames: Tensor, steps: int, margin: int = 0, create_graph: bool = False,
                d1: Tensor | None = None) -> Tensor:
        """Open-loop prediction from ``frames[:, margin]`` and ``frames[:, margin+1]`` for ``steps``
        steps, grippers from the recorded frames (shifted by a delay term if any). ``d1`` (B, m, 3):
        reference directors at ``frames[:, margin+1]`` (see :attr:`Recording.reference_frames`; default: a
        fresh space-parallel frame, right for a rollout from a recording's first frame).
        -> (B, steps, n, 3)."""
        idx = gripped_indices(self.n)
        grips = frames[:, :, idx]
        tau = self.delay()
        T = frames.shape[1]

        def grip_at(frame: int) -> Tensor:
            if tau is None:
                return grips[:, frame]
            pos = (frame - tau).clamp(0, T - 1)
            lo = pos.detach().floor().clamp(max=T - 2)
            i = int(lo)
            a = pos - lo
            return (1 - a) * grips[:, i] + a * grips[:, i + 1]

        x0, x1 = frames[:, margin], frames[:, margin + 1]
        if tau is not None:  # the rod's gripped ends lag the recorded grips from the first frame on
            x0, x1 = x0.clone(), x1.clone()
            x0[:, idx] = grip_at(margin).to(x0.dtype)
            x1[:, idx] = grip_at(margin + 1).to(x1.dtype)
        state = self.model.initial_state(x0, x1)
        if d1 is not None:
            from deform.rod import geometry as G

            t_rec = G.normalize(G.edges(frames[:, margin + 1]))
            d1 = G.time_transport(d1.to(state.d1.dtype), t_rec.to(state.d1.dtype), G.normalize(G.edges(state.x)))
            state = type(state)(x=state.x, v=state.v, d1=d1, theta=state.theta, rest=state.rest)
        out = []
        for k in range(steps):
            g = grip_at(margin + 2 + k)
            state = self.model.step(state, g, create_graph=create_graph)
            out.append(state.x)
        return torch.stack(out, 1)

    def predict(self, recordings, steps: int | None = None) -> list[np.ndarray]:
        """Full open-loop predictions (paper's protocol) of recordings, batched by length."""
        self.sync()
        out: dict[int, np.ndarray] = {}
        groups: dict[int, list[int]] = {}
        for i, r in enumerate(recordings):
            groups.setdefault(r.n_frames, []).append(i)
        with torch.no_grad():
            for T, ids in groups.items():
                s = T - 2 if steps is None else min(steps, T - 2)
                X = torch.tensor(np.stack([recordings[i].positions for i in ids]), dtype=torch.float64)
                P = self.rollout(X, s).numpy()
                for j, i in enumerate(ids):
                    out[i] = P[j]
        return [out[i] for i in range(len(recordings))]


def per_recording_l1(predictions: list[np.ndarray], recordings) -> np.ndarray:
    """Paper's metric per recording: mean |pred - truth| over steps, vertices and axes."""
    return np.array([float(np.nan_to_num(np.abs(p - r.positions[2:2 + len(p)]), nan=1.0).mean())
                     for p, r in zip(predictions, recordings)])
