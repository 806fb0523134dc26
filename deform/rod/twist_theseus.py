r"""Reference material-angle solver on Theseus (differentiable nonlinear least squares).

The angle-dependent energy is written as a sum of squares. For a (vertex, side) pair the bending
term is ``beta/(2L) |w - wbar|^2 = c (1 - cos x) + const`` with ``c = beta |w| |wbar| / L`` and ``x``
the angle between ``w`` and ``wbar`` (``|w|`` does not depend on theta), so its residual is the
2-vector ``sqrt(c/2) (w/|w| - wbar/|wbar|)``, whose Gauss-Newton curvature ``c`` matches the true
one ``c cos x`` near the minimum (the plain ``w - wbar`` residual overestimates it by ``|w|/|wbar|``
and converges very slowly). The twist residual is ``sqrt(gamma/L) (theta_i - theta_{i-1} + m_ref)``.

Gradients: ``backward_mode="implicit"`` (Theseus's implicit differentiation) linearises with the
Gauss-Newton Hessian, which differs from the true one where residuals are non-zero at the minimum,
so its gradients are approximate here; ``"unroll"`` through the converged iterations is exact and
is what the tests compare the fast solver's implicit-function-theorem gradients against. Gauss-Newton on them reaches the same minimiser
as the fast Newton solver; gradients come from Theseus's implicit backward mode. Slow (a Python
optimiser per call): tests and the ``--theta-solver theseus`` training option use it, the run-time
path never does.
"""

from __future__ import annotations

import torch
from torch import Tensor

from deform.rod.energy import left_right, material_curvature, twist_of
from deform.rod.twist_solver import twist_only_minimiser


def theseus_theta(
    a: Tensor,
    b: Tensor,
    m_ref: Tensor,
    theta_ends: Tensor,
    beta: Tensor,
    gamma: Tensor,
    rest_vor: Tensor,
    wbar: Tensor,
    theta_init: Tensor | None = None,
    max_iterations: int = 300,
    tol: float = 1e-20,
    backward_mode: str = "implicit",
) -> Tensor:
    """Same contract as :func:`deform.rod.twist_solver.solve_theta` (vertex-major inputs; Theseus
    itself works batch-first, so the inputs are transposed here).

    Args:
        a: (n-2, 2, B) and the other energy inputs as in :func:`deform.rod.twist_solver.newton_theta`.
        b: (n-2, 2, B).
        m_ref: (n-2, B).
        theta_ends: (2, B).
        beta: (n-2, 1).
        gamma: (n-2, 1).
        rest_vor: (n-2, B).
        wbar: (n-2, 2, 2, 1).
        theta_init: (m, B) warm start, or None.
        max_iterations: Gauss-Newton iterations at most.
        tol: absolute error tolerance of the objective.
        backward_mode: Theseus's backward mode (``"implicit"`` by default).

    Returns:
        (m, B) angles [rad].
    """
    import theseus as th

    n_int, batch = a.shape[0], a.shape[-1]
    k = n_int - 1
    dtype = a.dtype
    bw = (beta / (2.0 * rest_vor)).expand(-1, batch).T
    tw = (gamma / rest_vor).expand(-1, batch).T.sqrt()
    wb = wbar[..., 0].expand(batch, -1, -1, -1).reshape(batch, -1)
    if theta_init is None:
        init = twist_only_minimiser(m_ref.detach(), theta_ends.detach()).expand(k, batch).T.clone()
    else:
        init = theta_init[1:-1].detach().T.clone()
    theta_var = th.Vector(tensor=init, name="theta")
    aux = {
        "a": th.Variable(a.permute(2, 0, 1).reshape(batch, -1), name="a"),
        "b": th.Variable(b.permute(2, 0, 1).reshape(batch, -1), name="b"),
        "m_ref": th.Variable(m_ref.T, name="m_ref"),
        "ends": th.Variable(theta_ends.T, name="ends"),
        "bw": th.Variable(bw, name="bw"),
        "tw": th.Variable(tw, name="tw"),
        "wbar": th.Variable(wb, name="wbar"),
    }

    def residual(optim_vars, aux_vars):
        (free,) = optim_vars
        av, bv, mr, ends, bwv, twv, wbv = aux_vars
        theta = torch.cat([ends.tensor[:, :1], free.tensor, ends.tensor[:, 1:]], dim=-1).T  # (m, B)
        w1, w2 = material_curvature(
            av.tensor.view(-1, n_int, 2).permute(1, 2, 0),
            bv.tensor.view(-1, n_int, 2).permute(1, 2, 0),
            left_right(theta),
        )
        wbr = wbv.tensor.view(-1, n_int, 2, 2)
        w = torch.stack([w1, w2], dim=-1).permute(2, 0, 1, 3)  # (B, n-2, side, component)
        w_norm = w.norm(dim=-1, keepdim=True)
        wb_norm = wbr.norm(dim=-1, keepdim=True)
        scale = (bwv.tensor[..., None, None] * w_norm * wb_norm).clamp_min(0).sqrt()
        r_bend = scale * (w / w_norm.clamp_min(1e-12) - wbr / wb_norm.clamp_min(1e-12))
        r_twist = twv.tensor * twist_of(theta, mr.tensor.T).T
        return torch.cat([r_bend.reshape(free.tensor.shape[0], -1), r_twist], dim=-1)

    dim = n_int * 4 + n_int
    cost = th.AutoDiffCostFunction(
        [theta_var],
        residual,
        dim,
        aux_vars=list(aux.values()),
        name="rod_twist",
        cost_weight=th.ScaleCostWeight(torch.ones(1, 1, dtype=dtype)),
    )
    objective = th.Objective(dtype=dtype)
    objective.add(cost)
    optimizer = th.GaussNewton(
        objective,
        max_iterations=max_iterations,
        step_size=1.0,
        abs_err_tolerance=tol,
        rel_err_tolerance=1e-16,
    )
    layer = th.TheseusLayer(optimizer)
    inputs = {"theta": init}
    inputs.update({name: var.tensor for name, var in aux.items()})
    solution, _ = layer.forward(
        inputs, optimizer_kwargs={"backward_mode": backward_mode, "track_best_solution": False}
    )
    free = solution["theta"].T
    return torch.cat([theta_ends[:1], free, theta_ends[1:]])
