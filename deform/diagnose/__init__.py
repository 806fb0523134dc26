"""Discrepancy tool: locate where the plain DER model and recordings differ, name the missing physics.

``deform diagnose --rod ROD.json --fit DIR --check DIR --out OUTDIR [--json] [--model PT]
[--budget full|quick] [--clamp fit|METRES] [--denoise auto|off] [--max-gap SECONDS] [--workers N]``

Modules: :mod:`.spec` (inputs and their checks; marker dropouts filled by :mod:`deform.io.gaps`), :mod:`.resample` (other frame rates to 100 Hz),
:mod:`.denoise` (marker noise measured; smoothing far above the calibrated level),
:mod:`.simulator` (bound DER model),
:mod:`deform.terms` (the term library the candidates come from), :mod:`.fitting` (multi-step fits), :mod:`.localize`,
:mod:`.scoring` (bootstrap + parameter penalty), :mod:`.selection` (forward selection),
:mod:`.checked_fit` (a fit and its check errors), :mod:`.pool` (fits side by side in processes),
:mod:`.report`, :mod:`.planted` (benchmark data with planted effects).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import tempfile
from pathlib import Path

from deform.io.gaps import MAX_GAP_S


def given_clamp(value: str, spec) -> float | None:
    """``--clamp``: None for ``fit``, else the length [m] to hold (UsageError when it is not a
    length between 0 and half the marker spacing, :func:`deform.diagnose.simulator.clamp_bound`)."""
    from deform.diagnose.simulator import clamp_bound
    from deform.errors import UsageError

    if value == "fit":
        return None
    try:
        clamp = float(value)
    except ValueError:
        raise UsageError(f"--clamp {value!r}: expected fit or a length in metres") from None
    bound = clamp_bound(spec)
    if not 0.0 <= clamp <= bound:
        raise UsageError(
            f"--clamp {value}: a clamp ends before the next marker, between 0 and {bound:.4f} m "
            "(half the marker spacing) for this rod"
        )
    return clamp


def run_cli(args) -> int:
    """Entry point of ``deform diagnose``: errors are raised before anything is written.

    Args:
        args: the parsed ``deform diagnose`` arguments.

    Returns:
        The exit code.
    """
    import torch

    from deform.diagnose.report import write_report
    from deform.diagnose.selection import DiagnoseBudget, diagnose
    from deform.diagnose.spec import load_inputs
    from deform.errors import UsageError

    torch.set_num_threads(1)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{out}: --out exists and is not a directory")
    if getattr(args, "model", None) and not Path(args.model).is_file():
        raise UsageError(f"{args.model}: --model: no such file")
    inputs = load_inputs(
        args.rod,
        args.fit,
        args.check,
        smooth_noise=getattr(args, "denoise", "auto") != "off",
        max_gap_s=getattr(args, "max_gap", MAX_GAP_S),  # bounded at parsing (deform.argtypes)
    )
    budget = DiagnoseBudget.quick() if getattr(args, "budget", "full") == "quick" else DiagnoseBudget()
    clamp = given_clamp(getattr(args, "clamp", "fit"), inputs.spec)
    if clamp is not None:
        budget = dataclasses.replace(budget, fit_clamp=False, clamp_m=clamp)
    from deform.cores import available_cores

    workers = getattr(args, "workers", None) or available_cores()
    diag = diagnose(inputs, budget, start_model=getattr(args, "model", None), workers=workers)
    tmp = Path(tempfile.mkdtemp(prefix=".diagnose-", dir=out.parent if out.parent.exists() else None))
    try:
        write_report(diag, inputs.check, tmp)
        out.mkdir(parents=True, exist_ok=True)
        for f in tmp.iterdir():
            shutil.move(str(f), out / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if args.json:
        print(json.dumps(diag.report, indent=2))
    else:
        print(
            f"selected: {', '.join(diag.report['selected']) or 'none'}; check L1 "
            f"{diag.report['nominal']['check_l1_m'] * 100:.3f} -> {diag.report['final_check_l1_m'] * 100:.3f} cm; "
            f"report in {out / 'report.md'}"
        )
    return 0
