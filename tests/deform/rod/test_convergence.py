"""masked_loop: per-rod stopping, the same values eager and exported (a while loop), and an exported
step whose size does not grow with the iteration counts (what keeps the ahead-of-time build short)
unless the iterations are asked unrolled."""

import pytest
import torch

from deform import load_model
from deform.aot import _BranchFreeStep
from deform.rod.convergence import loops_when_exported, masked_loop
from deform.step_graph import rod_at_rest_vertex_major


class _Halving(torch.nn.Module):
    """Halve each rod's values until its largest is below 1e-3, at most ``count`` times."""

    def __init__(self, count: int):
        super().__init__()
        self.count = count

    def forward(self, y):
        def body(carry, active):
            (y,) = carry
            y = torch.where(active[:, None], 0.5 * y, y)
            return (y,), y.abs().amax(-1) >= 1e-3

        (y,), active = masked_loop(body, (y,), y.abs().amax(-1) >= 1e-3, self.count)
        return y, active


def test_each_rod_stops_by_its_own_rule_and_export_agrees_with_eager():
    y = torch.tensor([[1.0, -0.5], [1e-4, 0.0], [0.01, 0.002]], dtype=torch.float64)
    eager, active = _Halving(20)(y)
    # rod 0 needs 10 halvings, rod 1 none, rod 2 four; none of them is halved once more
    assert torch.equal(eager[0], y[0] / 2**10) and torch.equal(eager[1], y[1])
    assert torch.equal(eager[2], y[2] / 2**4) and not active.any()
    short, still = _Halving(3)(y)
    assert torch.equal(short[0], y[0] / 8) and still.tolist() == [True, False, True]
    for count in (3, 20):
        exported = torch.export.export(_Halving(count), (y,), strict=False).module()
        out, act = exported(y)
        ref, ref_act = _Halving(count)(y)
        assert torch.equal(out, ref) and torch.equal(act, ref_act)


@pytest.mark.slow
def test_exported_step_does_not_grow_with_the_iteration_counts():
    model = load_model("DLO1")
    state, grip = rod_at_rest_vertex_major(model, 1, torch.float64)
    args = (state.x, state.v, state.d1, state.theta, state.rest, grip)

    def size(branch_free, loops):
        with torch.no_grad(), loops_when_exported(loops):
            ep = torch.export.export(_BranchFreeStep(model, branch_free), args, strict=False)
        return sum(len(m.graph.nodes) for m in ep.graph_module.modules() if hasattr(m, "graph"))

    assert size((2, 1), True) == size((8, 4), True)
    assert size((2, 1), False) < size((8, 4), False)  # unrolled (large batches, deform.aot.exports_loops)


def test_merged_reports_keep_the_worst_substep_per_rod():
    """A frame in substeps is as unconverged as its worst substep: largest length error (NaN kept),
    any unconverged twist."""
    from deform.rod.convergence import ConvergenceReport, merge_reports

    first = ConvergenceReport(
        torch.tensor([1e-9, 5e-3, 0.0], dtype=torch.float64), torch.tensor([False, False, True])
    )
    second = ConvergenceReport(
        torch.tensor([2e-9, 1e-9, float("nan")], dtype=torch.float64), torch.tensor([True, False, False])
    )
    merged = ConvergenceReport()
    merge_reports(merged, [first, second])
    assert merged.length_error[:2].tolist() == [2e-9, 5e-3] and merged.length_error[2].isnan()
    assert merged.twist_unconverged.tolist() == [True, False, True]
    untouched = ConvergenceReport()
    merge_reports(untouched, [ConvergenceReport(), ConvergenceReport()])  # solvers that did not report
    assert untouched.length_error is None and untouched.twist_unconverged is None
