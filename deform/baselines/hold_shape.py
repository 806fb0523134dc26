"""Trivial baseline: the interior vertices keep their frame-1 positions for ever; the gripped
vertices 0, 1, n-2, n-1 are set to the inputs. Scores about 5 cm on the paper's metric."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from deform.model import gripped_indices


@dataclass
class HoldState:
    x: torch.Tensor  # (B, n, 3)


class HoldShape:
    def __init__(self, n: int):
        self.n = n
        self.idx = gripped_indices(n)

    def initial_state(self, x0: torch.Tensor, x1: torch.Tensor) -> HoldState:
        x1 = torch.as_tensor(x1)
        return HoldState(x1.unsqueeze(0) if x1.dim() == 2 else x1)

    def step(self, state: HoldState, grip_next: torch.Tensor) -> HoldState:
        x = state.x.clone()
        x[:, self.idx] = grip_next.to(x.dtype)
        return HoldState(x)
