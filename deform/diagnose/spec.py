"""What the user knows about the rod (ROD.json) and the checks that the recordings agree with it.

A diagnosis on inconsistent inputs would name spurious physics, so contradictions are errors (the
data cannot be used) or warnings carried into the report (it can, but the user should know).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from deform.diagnose.denoise import denoise
from deform.diagnose.resample import TOOL_DT, resample
from deform.io.gaps import MAX_GAP_S, fill_recordings
from deform.io.labels import fix_recordings_labels
from deform.io.orientation import check_up_axis
from deform.io.recordings import Recording, RecordingError, load_recordings

MIN_FRAMES = 40  # at the tool's 100 Hz: a recording shorter than 0.4 s cannot be diagnosed
LENGTH_TOLERANCE = 0.10  # a rope shorter than its markers' polyline by more than this is an error
# the markers must span at least this share of the rope: past them the grippers hold it or it hangs
# in short free tails, which the span's simulation leaves out (DLO1: 90 %)
MIN_SPAN_SHARE = 0.5


def _units_hint(ratio: float) -> str:
    """A hint when the markers' span and the rope's length differ by a unit's factor."""
    for factor, units in ((1000.0, "millimetres"), (100.0, "centimetres")):
        if 0.5 * factor < ratio < 2.0 * factor:
            return f" (recordings in {units}? they are read in metres)"
        if 0.5 / factor < ratio < 2.0 / factor:
            return f" (ROD.json in {units}? length_m is in metres)"
    return ""


class RodSpec(BaseModel):
    """ROD.json: length, mass, marker count and frame period; gripped vertices 0, 1, n-2, n-1."""

    model_config = ConfigDict(extra="ignore")

    length_m: float = Field(gt=0)
    mass_kg: float = Field(gt=0)
    n_vertices: int = Field(ge=6)
    dt: float = Field(default=0.01, gt=0)
    name: str = "rod"


def load_rod_spec(path: str | Path) -> RodSpec:
    """Parse ROD.json; any problem is a one-line :class:`RecordingError` naming the file.

    Args:
        path: ROD.json.

    Returns:
        The :class:`RodSpec`.
    """
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise RecordingError(f"{path}: expected a JSON object with length_m, mass_kg, n_vertices, dt")
    try:
        return RodSpec(**data)
    except ValidationError as exc:
        fields = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise RecordingError(f"{path}: {fields}") from None


@dataclass
class Inputs:
    spec: RodSpec
    fit: list[Recording]
    check: list[Recording]
    warnings: list[str] = field(default_factory=list)


def polyline_length(rec: Recording) -> float:
    """Median over frames of the markers' polyline length (a lower bound of the arc length).

    Args:
        rec: a recording.

    Returns:
        Length [m].
    """
    seg = np.linalg.norm(np.diff(rec.positions, axis=1), axis=-1).sum(-1)
    return float(np.median(seg))


def marker_span_spec(
    spec: RodSpec, span_m: float, source: str | Path = "ROD.json"
) -> tuple[RodSpec, str | None]:
    """The rod the tool simulates: the part between the outer markers.

    Real ropes run past their outer markers (DLO1 is 1.152 m long, its markers span about 1.035 m),
    and the grippers hold the rest, so a rope longer than the span is simulated over the span with
    the mass of that part (mass per length kept) and a warning. A rope *shorter* than the markers'
    polyline (a lower bound of the arc length between them) by more than ``LENGTH_TOLERANCE``
    contradicts the data: an error. -> (spec to simulate, warning or None).

    Args:
        spec: the rope as the user gave it.
        span_m: the markers' polyline length [m].
        source: ROD.json, for messages.

    Returns:
        ``(spec, warning)``: the spec simulated and the warning to report, or None.
    """
    rel = (span_m - spec.length_m) / spec.length_m
    if rel > LENGTH_TOLERANCE:
        raise RecordingError(
            f"{source}: length_m={spec.length_m} but the markers span {span_m:.3f} m, "
            f"{rel * 100:+.0f} % longer than the rope (tolerance {LENGTH_TOLERANCE * 100:.0f} %)"
            + _units_hint(span_m / spec.length_m)
        )
    if span_m < MIN_SPAN_SHARE * spec.length_m:
        raise RecordingError(
            f"{source}: length_m={spec.length_m} but the markers span only {span_m:.3f} m "
            f"({span_m / spec.length_m * 100:.0f} % of the rope, at least {MIN_SPAN_SHARE * 100:.0f} % "
            "needed: the rope between the outer markers is what is simulated)"
            + _units_hint(span_m / spec.length_m)
        )
    if rel >= 0:
        note = (
            (
                f"ROD.json length {spec.length_m} m is {rel * 100:.1f} % shorter than the marker polyline "
                f"{span_m:.3f} m"
            )
            if rel > 0.05
            else None
        )
        return spec, note
    scaled = spec.model_copy(update={"length_m": span_m, "mass_kg": spec.mass_kg * span_m / spec.length_m})
    note = (
        (
            f"the rope ({spec.length_m} m, {spec.mass_kg * 1e3:.1f} g) runs {-rel * 100:.0f} % past its markers: "
            f"simulating the {span_m:.3f} m between the outer markers with {scaled.mass_kg * 1e3:.1f} g "
            f"(mass per length kept)"
        )
        if rel < -0.02
        else None
    )
    return scaled, note


def load_inputs(
    rod: str | Path,
    fit_dir: str | Path,
    check_dir: str | Path,
    min_fit: int = 2,
    min_check: int = 1,
    smooth_noise: bool = True,
    max_gap_s: float = MAX_GAP_S,
) -> Inputs:
    """Load and cross-check ROD.json, fit/ and check/; raise on what cannot be diagnosed.

    Args:
        rod: ROD.json.
        fit_dir: recordings to fit.
        check_dir: held-out recordings.
        min_fit: fit recordings needed.
        min_check: check recordings needed.
        smooth_noise: smooth recordings whose marker noise is far above the calibrated level
            (:func:`deform.diagnose.denoise.denoise`; only at 100 Hz or faster, where the noise can
            be told from the rope's motion).
        max_gap_s: markers missing (NaN) for at most this long are filled in time, incomplete
            frames at the ends dropped (:func:`deform.io.gaps.fill_gaps`); a longer gap is an error.

    Returns:
        The :class:`Inputs` (spec, fit, check, warnings).

    Raises:
        RecordingError: one line naming what cannot be diagnosed.
    """
    spec = load_rod_spec(rod)
    fit = load_recordings(fit_dir, allow_gaps=True)
    check = load_recordings(check_dir, allow_gaps=True)
    both, gap_note = fill_recordings(fit + check, max_gap_s, dt=spec.dt)  # the pickles hold no period
    both, label_note = fix_recordings_labels(both)
    fit, check = both[: len(fit)], both[len(fit) :]
    for _, recs, d in (("fit", fit, fit_dir), ("check", check, check_dir)):
        n = recs[0].n_vertices
        if n != spec.n_vertices:
            raise RecordingError(f"{d}: recordings have {n} markers, {rod} says n_vertices={spec.n_vertices}")
    if len(fit) < min_fit:
        raise RecordingError(f"{fit_dir}: {len(fit)} recording(s); at least {min_fit} are needed to fit")
    if len(check) < min_check:
        raise RecordingError(
            f"{check_dir}: {len(check)} recording(s); at least {min_check} are needed for a held-out check"
        )
    # a DEFORM pickle holds positions only: the frame period is ROD.json's, and the tool works at
    # its calibrated 100 Hz (deform.diagnose.resample); a recording must span 40 frames of it
    short = [r.name for r in fit + check if (r.n_frames - 1) * spec.dt < (MIN_FRAMES - 1) * TOOL_DT - 1e-9]
    if short:
        raise RecordingError(
            f"{fit_dir if short[0] in {r.name for r in fit} else check_dir}: recording(s) {short} are "
            f"shorter than {MIN_FRAMES} frames at {1 / TOOL_DT:.0f} Hz ({(MIN_FRAMES - 1) * TOOL_DT:.2f} s)"
        )
    warnings: list[str] = [n for n in (gap_note, label_note) if n]
    given_dt = spec.dt
    if not math.isclose(spec.dt, TOOL_DT, rel_tol=1e-9):
        fit = [resample(r, spec.dt) for r in fit]
        check = [resample(r, spec.dt) for r in check]
        warnings.append(
            f"recordings at {1 / spec.dt:.4g} Hz (ROD.json dt={spec.dt}) resampled to the tool's "
            f"{1 / TOOL_DT:.0f} Hz by cubic splines; frames and delays in the report are {TOOL_DT * 1e3:.0f} ms frames"
        )
        spec = spec.model_copy(update={"dt": TOOL_DT})
    # below 100 Hz a rope's own motion fills the 4th difference the noise is measured from
    if smooth_noise and given_dt <= TOOL_DT * (1 + 1e-9):
        smoothed, note = denoise(fit + check)
        if note:
            fit, check = smoothed[: len(fit)], smoothed[len(fit) :]
            warnings.append(note)
    note = check_up_axis(fit + check, f"{fit_dir}, {check_dir}")
    if note:
        warnings.append(note)
    lengths = np.array([polyline_length(r) for r in fit + check])
    spec, note = marker_span_spec(spec, float(np.median(lengths)), rod)
    if note:
        warnings.append(note)
    if len(check) < 3:
        warnings.append(
            f"only {len(check)} check recording(s): the bootstrap interval over recordings is unreliable"
        )
    names = {r.name for r in fit} & {r.name for r in check}
    if names and any(
        np.array_equal(a.positions, b.positions) for a in fit for b in check if a.name == b.name
    ):
        warnings.append(
            f"fit/ and check/ share identical recordings {sorted(names)}: the check is not held out"
        )
    jumps = []
    for r in fit + check:
        v = np.linalg.norm(np.diff(r.positions, axis=0), axis=-1) / spec.dt
        if float(np.percentile(v, 99.99)) > 20.0:
            jumps.append(r.name)
    if jumps:
        warnings.append(f"marker speeds above 20 m/s (tracking glitches?) in {jumps}")
    return Inputs(spec=spec, fit=fit, check=check, warnings=warnings)
