"""Bi-LSTM dynamics over the rod's vertices, in the style of Yan et al. 2020 (self-supervised state
estimation of DLOs: a bidirectional LSTM runs along the chain of vertices and predicts the next state).

Per time step the vertices form a sequence of length n; each vertex gets (all O(1) scaled)

- its position relative to the centre of the next gripped vertices (``POS_SCALE``), its velocity
  ``(x_t - x_{t-1}) / dt`` (``VEL_SCALE``),
- a gripped flag and, for gripped vertices, the velocity that takes them to their next input.

A linear encoder, one bidirectional LSTM layer and a linear head give a velocity change per vertex:
``v' = v + OUT_SCALE * out``, ``x' = x + dt v'``; gripped vertices are then set to their inputs.
Trained by :func:`train_bilstm` with open-loop multi-step rollouts (L1 as the paper's metric,
horizons growing 5 -> 50 steps) on windows of the train recordings; the best weights on the held-out
recordings are kept. Weights: ``weights/bilstm_ROD.pt`` (float32, ~50 kB).
"""

from __future__ import annotations

import math
import random
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from deform.baselines import WEIGHT_DIR, MissingWeightsError
from deform.model import gripped_indices
from deform.train import sample_windows

POS_SCALE = 0.5  # m
VEL_SCALE = 1.0  # m/s
OUT_SCALE = 0.05  # m/s per step
DT = 0.01


@dataclass
class LSTMState:
    x: torch.Tensor  # (B, n, 3) float64
    v: torch.Tensor  # (B, n, 3) float64, m/s


class BiLSTMDynamics(nn.Module):
    def __init__(self, n: int, hidden: int = 64, dt: float = DT):
        super().__init__()
        self.n = n
        self.dt = dt
        self.hidden = hidden
        self.idx = gripped_indices(n)
        flag = torch.zeros(1, n, 1)
        flag[:, self.idx] = 1.0
        self.register_buffer("flag", flag)
        self.encoder = nn.Linear(10, hidden)
        self.lstm = nn.LSTM(hidden, hidden, batch_first=True, bidirectional=True)
        self.head = nn.Sequential(nn.Linear(2 * hidden, hidden), nn.Tanh(), nn.Linear(hidden, 3))
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)

    # ----- predictor interface (float64 in, float64 out, like DeformModel) ----------------------
    def initial_state(self, x0: torch.Tensor, x1: torch.Tensor) -> LSTMState:
        x0, x1 = torch.as_tensor(x0), torch.as_tensor(x1)
        if x1.dim() == 2:
            x0, x1 = x0.unsqueeze(0), x1.unsqueeze(0)
        return LSTMState(x1, (x1 - x0) / self.dt)

    def features(self, x: torch.Tensor, v: torch.Tensor, grip_next: torch.Tensor) -> torch.Tensor:
        centre = grip_next.mean(1, keepdim=True)
        drive = torch.zeros_like(x)
        drive[:, self.idx] = (grip_next - x[:, self.idx]) / self.dt
        flag = self.flag.expand(x.shape[0], -1, -1).to(x.dtype)
        return torch.cat([(x - centre) / POS_SCALE, v / VEL_SCALE, drive / VEL_SCALE, flag], -1)

    def step(self, state: LSTMState, grip_next: torch.Tensor) -> LSTMState:
        x, v = state.x, state.v
        grip_next = grip_next.to(x.dtype)
        f = self.features(x, v, grip_next).float()
        h, _ = self.lstm(torch.tanh(self.encoder(f)))
        dv = self.head(h).to(x.dtype) * OUT_SCALE
        v_new = v + dv
        x_new = x + self.dt * v_new
        x_new = torch.cat([grip_next[:, :2], x_new[:, 2:-2], grip_next[:, 2:]], 1)
        return LSTMState(x_new, (x_new - x) / self.dt)

    def rollout(self, state: LSTMState, grips: torch.Tensor) -> torch.Tensor:
        out = []
        for k in range(grips.shape[1]):
            state = self.step(state, grips[:, k])
            out.append(state.x)
        return torch.stack(out, 1)


def weight_path(rod: str) -> Path:
    """Args:
        rod: a rod name.

    Returns:
        Where the trained Bi-LSTM of that rod is stored.
    """
    return WEIGHT_DIR / f"bilstm_{rod}.pt"


def save_bilstm(model: BiLSTMDynamics, path: str | Path, extra: dict | None = None) -> None:
    """Args:
    model: the trained network.
    path: the ``.pt`` to write.
    extra: more fields for the file (validation error, iterations).
    """
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "n": model.n,
            "hidden": model.hidden,
            "dt": model.dt,
            "state_dict": model.state_dict(),
            **(extra or {}),
        },
        path,
    )


def load_bilstm(rod: str, path: str | Path | None = None) -> BiLSTMDynamics:
    """The trained Bi-LSTM of a rod.

    Args:
        rod: a rod name.
        path: a ``.pt`` instead of :func:`weight_path`.

    Returns:
        The network, in eval mode.

    Raises:
        MissingWeightsError: no such file.
    """
    p = Path(path) if path else weight_path(rod)
    if not p.is_file():
        raise MissingWeightsError(f"{p}: no trained Bi-LSTM for {rod}; run benchmarks/baselines.py")
    payload = torch.load(p, map_location="cpu", weights_only=True)
    model = BiLSTMDynamics(payload["n"], payload["hidden"], payload["dt"])
    model.load_state_dict(payload["state_dict"])
    return model.eval()


def _val_l1(model, recordings, steps: int) -> float:
    from deform.evaluate import metrics, predict_recordings

    model.eval()
    err = metrics(predict_recordings(model, recordings, steps))["l1_m"]
    model.train()
    return err if math.isfinite(err) else math.inf


def train_bilstm(
    train_recs,
    val_recs,
    n: int,
    iterations: int = 1500,
    batch: int = 32,
    curriculum: tuple[tuple[int, int], ...] = ((0, 5), (200, 10), (500, 25), (900, 50)),
    lr: float = 2e-3,
    hidden: int = 64,
    seed: int = 0,
    time_limit_s: float | None = None,
    val_every: int = 100,
    val_steps: int = 500,
    out: str | Path | None = None,
    progress: bool = False,
) -> tuple[BiLSTMDynamics, dict]:
    """Train on windows of ``train_recs`` with open-loop rollouts (L1); keep the best on ``val_recs``
    (500-step open loop). ``curriculum``: (from iteration, horizon) pairs. Returns the best model.

    Args:
        train_recs: recordings to train on.
        val_recs: recordings that choose the best weights (none: the last weights).
        n: vertices.
        iterations: updates at most.
        batch: windows per update.
        curriculum: (from iteration, horizon) pairs.
        lr: Adam learning rate.
        hidden: LSTM width.
        seed: initial weights and windows.
        time_limit_s: stop after this long.
        val_every: iterations between validations.
        val_steps: steps of the validation rollouts.
        out: a ``.pt`` to save the best weights to, or None.
        progress: print progress lines.

    Returns:
        ``(model, info)``: info has ``best_val_l1_m``, ``iterations``, ``seconds`` and the ``log``.
    """
    torch.manual_seed(seed)
    rng = random.Random(seed)
    model = BiLSTMDynamics(n, hidden)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda it: 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(it / iterations, 1.0)))
    )
    idx = gripped_indices(n)
    best, best_state, log = math.inf, None, []
    t0 = time.perf_counter()
    it = 0
    for it in range(iterations):
        horizon = [h for start, h in curriculum if it >= start][-1]
        w, _ = sample_windows(train_recs, batch, horizon, rng, transported=False)
        state = model.initial_state(w[:, 0], w[:, 1])
        pred = model.rollout(state, w[:, 2:, idx])
        loss = (pred - w[:, 2:]).abs().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        done = it + 1 == iterations or (time_limit_s is not None and time.perf_counter() - t0 > time_limit_s)
        if (it + 1) % val_every == 0 or done:
            val = _val_l1(model, val_recs, val_steps) if val_recs else float(loss.detach())
            log.append(
                {
                    "iteration": it + 1,
                    "horizon": horizon,
                    "loss_m": float(loss.detach()),
                    "val_l1_m": val,
                    "seconds": time.perf_counter() - t0,
                }
            )
            if progress:
                print(
                    f"  bilstm it {it + 1} h {horizon} loss {float(loss.detach()) * 100:.3f} cm val {val * 100:.3f} cm "
                    f"({time.perf_counter() - t0:.0f} s)",
                    flush=True,
                )
            if val <= best or not val_recs:  # without held-out recordings: the last weights
                best, best_state = val, {k: t.clone() for k, t in model.state_dict().items()}
        if done:
            break
    if best_state is not None:
        model.load_state_dict(best_state)
    model.eval()
    info = {"best_val_l1_m": best, "iterations": it + 1, "seconds": time.perf_counter() - t0, "log": log}
    if out:
        save_bilstm(model, out, {"best_val_l1_m": best, "iterations": it + 1})
    return model, info
