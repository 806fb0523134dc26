#!/usr/bin/env python3
"""Regenerate docs/results.md from the stored benchmark results in benchmarks/results/*.json.

    python scripts/make_results.py [--results DIR] [--out FILE]      (or `make results`)

One section per results file, in a fixed order for the files this script knows (accuracy, speed,
perception, service, service_soak, baselines, ablations, diagnose and any diagnose.*.json), then a
short section for any other .json it finds. Each section states where its numbers came from: the
file's own `command`, `commit` and `machine` fields ("not recorded" when the file has none), the
script that writes it, and the git commit that last changed the file. A missing file is listed
as missing; a file whose layout this script does not understand is listed with its top-level fields.

Standard library and numpy only; nothing is measured here, every number is copied from a file.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from results_common import git_last_commit, machine_text, render_generic
from results_model import (
    render_ab_commits,
    render_ablations,
    render_accuracy,
    render_baselines,
    render_batched_throughput,
    render_bending_stability,
    render_float32,
    render_predict_planning,
    render_roofline,
    render_service,
    render_service_latency,
    render_service_timing,
    render_speed,
    render_startup,
)
from results_studies import (
    render_calibrate_rods,
    render_diagnose,
    render_diagnose_ab,
    render_perception,
    render_real_terms,
    render_tracking_peers,
)

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
OUT = ROOT / "docs" / "results.md"

# file -> (title, the script that writes it)
KNOWN = {
    "accuracy.json": ("Accuracy: 500-step open-loop prediction", "python benchmarks/accuracy.py"),
    "speed.json": ("Speed of the model step", "python benchmarks/speed.py"),
    "perception.json": (
        "Perception: tracking from rendered RGB-D clouds",
        "python benchmarks/perception_tracking.py",
    ),
    "service.json": (
        "Service: loop, predict, memory soak",
        "python benchmarks/service_bench.py --json benchmarks/results/service.json",
    ),
    "service_soak.json": (
        "Service: 30-minute soak",
        "python benchmarks/service_bench.py --loop-s 30 --soak-s 1800 --predict-n 20 --json benchmarks/results/service_soak.json",
    ),
    "service_timing.json": (
        "Service: clouds arriving late, poses in bursts (simulated clock)",
        "python benchmarks/service_timing.py --ticks 1500 --json benchmarks/results/service_timing.json",
    ),
    "service_latency.json": (
        "Service: the live service's tracking, start after start",
        'python benchmarks/service_latency.py --modes "stamp, steady poses" --latency-ms 0 100 --run-s 20 '
        "--repeats 8 --json benchmarks/results/service_latency.json",
    ),
    "bending_stability.json": (
        "Stiff and short ropes bent and held: explicit and implicit bending",
        "python benchmarks/bending_stability.py",
    ),
    "baselines.json": ("Baselines beside DEFORM", "python benchmarks/baselines.py"),
    "ablations.json": ("Ablations", "python benchmarks/ablations.py"),
    "diagnose.json": ("deform diagnose: planted-effect benchmark", "python benchmarks/diagnose_planted.py"),
    "real_terms.json": ("Named physics trained into DEFORM, real rods", "python benchmarks/real_terms.py"),
    "real_terms.v6.json": (
        "Named physics trained into DEFORM, real rods: the terms tool v6 newly named",
        "python benchmarks/real_terms.py --rods DLO1 DLO2 DLO4 DLO5 --terms DLO1=internal_damping "
        "DLO2=external_force DLO4=external_force DLO5=external_force --stem real_terms.v6",
    ),
    "real_terms.dlo1.json": (
        "DLO1 with internal damping trained into DEFORM and installed (the shipped model since)",
        "python benchmarks/real_terms.py --rods DLO1 --terms DLO1=internal_damping --stem real_terms.dlo1 --install",
    ),
    "service_startup.json": ("Service start-up, cold and warm", "python benchmarks/service_startup.py"),
    "roofline.json": ("Roofline of the batched model step", "python benchmarks/roofline.py"),
    "float32_accuracy.json": ("float32 rollout against float64", "python benchmarks/float32_accuracy.py"),
    "batched_throughput.json": (
        "Batched step throughput at 1024 rods",
        "python benchmarks/batched_throughput.py",
    ),
    "predict_planning.json": (
        "Planning-scale predict in the service",
        "python benchmarks/predict_planning.py --n 30 --rounds 3 --compare predict_network_dtype=auto",
    ),
    "ab_commits.json": (
        "Today's step against an earlier commit's, same run",
        "python benchmarks/ab_commits.py",
    ),
    "diagnose_ab.json": (
        "deform diagnose against an earlier commit's, same datasets, same run",
        "python benchmarks/diagnose_ab.py",
    ),
    "tracking_peers.json": (
        "Tracking side by side with the published trackers (CPD, CDCPD, TrackDLO, UPETrack)",
        "python benchmarks/tracking_peers.py",
    ),
    "calibrate_rods.json": (
        "deform calibrate: models from camera clips alone, DLO1..DLO5",
        "python benchmarks/calibrate_rods.py",
    ),
}


def provenance(name: str, data, path: Path) -> list[str]:
    meta = data if isinstance(data, dict) else {}
    command = meta.get("command")
    lines = [
        f"- file: `benchmarks/results/{name}`",
        f"- command: `{command.strip()}`"
        if command
        else "- command: not recorded" + (f" (written by `{KNOWN[name][1]}`)" if name in KNOWN else ""),
        f"- commit: `{meta['commit']}`"
        if meta.get("commit")
        else "- commit: not recorded"
        + (f" (file last changed in git commit {c})" if (c := git_last_commit(path)) else ""),
        f"- machine: {machine_text(meta.get('machine'))}",
    ]
    return lines + [""]


RENDER = {
    "calibrate_rods.json": render_calibrate_rods,
    "service_startup.json": render_startup,
    "roofline.json": render_roofline,
    "float32_accuracy.json": render_float32,
    "batched_throughput.json": render_batched_throughput,
    "predict_planning.json": render_predict_planning,
    "ab_commits.json": render_ab_commits,
    "diagnose_ab.json": render_diagnose_ab,
    "tracking_peers.json": render_tracking_peers,
    "accuracy.json": render_accuracy,
    "speed.json": render_speed,
    "perception.json": render_perception,
    "service.json": render_service,
    "service_soak.json": render_service,
    "service_timing.json": render_service_timing,
    "service_latency.json": render_service_latency,
    "bending_stability.json": render_bending_stability,
    "baselines.json": render_baselines,
    "ablations.json": render_ablations,
    "diagnose.json": render_diagnose,
    "real_terms.json": render_real_terms,
    "real_terms.v6.json": render_real_terms,
    "real_terms.dlo1.json": render_real_terms,
}


def renderer(name: str):
    if name in RENDER:
        return RENDER[name]
    if name.startswith("diagnose.") and name.endswith(".json"):
        return render_diagnose
    for stem, render in (
        ("diagnose_ab.", render_diagnose_ab),
        ("ab_commits.", render_ab_commits),
        ("tracking_peers.", render_tracking_peers),
        ("calibrate_rods.", render_calibrate_rods),
    ):
        if name.startswith(stem):
            return render
    return render_generic


# ----- page ------------------------------------------------------------------------------------------
def build(results: Path) -> str:
    present = sorted(p.name for p in results.glob("*.json")) if results.is_dir() else []
    extra_diag = [n for n in present if n.startswith("diagnose.") and n not in KNOWN]
    others = [n for n in present if n not in KNOWN and n not in extra_diag]
    order = list(KNOWN) + extra_diag + others
    lines = [
        "# Results",
        "",
        "<!-- generated by scripts/make_results.py from benchmarks/results/*.json; edit those or the script, not this page -->",
        "",
        "Every number on this page is copied from a results file in `benchmarks/results/`, written by the "
        "benchmark script named in its section; regenerate the page with `make results`. Timings come from "
        "a 2-core x86_64 VM without GPU (torch CPU build) whose speed varies with the host's load; each "
        'section names the machine as the file records it. "Commit: not recorded" means the file does '
        "not say which code produced it; the git commit that last changed the file is given instead "
        "(the results were stored with, or after, the code they measure). The `.md` files beside the JSON "
        "(e.g. `diagnose.md`, per-run detail) and `docs/*.md` have more.",
        "",
    ]
    lines += ["Files: " + ", ".join(f"[{n}](#{anchor(n)})" for n in order) + ".", ""]
    for name in order:
        title = KNOWN.get(name, (f"Other results: {name}",))[0]
        if name.startswith("diagnose.") and name not in KNOWN:
            title = f"deform diagnose: {name}"
        lines += [f"## {name}", "", f"*{title}*", ""]
        path = results / name
        if not path.is_file():
            lines += [
                "Missing: no such file in `benchmarks/results/`"
                + (f" (run `{KNOWN[name][1]}`)." if name in KNOWN else "."),
                "",
            ]
            continue
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            lines += [f"Could not be read: {exc}", ""]
            continue
        lines += provenance(name, data, path)
        try:
            lines += renderer(name)(data)
        except Exception as exc:  # a results layout this script does not know yet: say so, keep going
            lines += [
                f"(The layout of this file was not understood by scripts/make_results.py: "
                f"{type(exc).__name__}: {exc}.)",
                "",
            ] + render_generic(data)
    return "\n".join(lines).rstrip() + "\n"


def anchor(name: str) -> str:
    return "".join(c for c in name.lower() if c.isalnum() or c in "-_ ").replace(" ", "-")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    text = build(args.results)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out} ({text.count(chr(10))} lines)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
