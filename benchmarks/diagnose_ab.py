"""`deform diagnose` of this checkout against an earlier commit's, on the same recordings, in one run.

What it answers: is the tool faster per dataset, and does it still name the same effects? The
datasets are the PyElastica planted benchmark's (``diagnose_planted.py --simulator elastica
--quick``, 8 fit + 4 check recordings of 300 frames), simulated once here and handed to both
checkouts as arrays. Each measurement is a fresh process of one checkout on one thread, as a Ray
task of the planted benchmark runs; the checkouts take turns, so that the machine's drift falls on
both (this VM's speed wanders by tens of percent within minutes).

    python benchmarks/diagnose_ab.py [--base COMMIT] [--datasets KIND:EFFECT:SEED ...] [--rounds 1]
        -> benchmarks/results/diagnose_ab.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

PLANTED = "--simulator elastica --quick --fit 8 --check 4 --frames 300"
DATASETS = ("light:none:1", "stiff:internal_damping:0")

# run inside the checkout under test (its own deform and benchmark helpers): prints one JSON line
_DIAGNOSE = """
import json, sys, time, numpy as np, torch
sys.path.insert(0, {root!r})
torch.set_num_threads(1)
from benchmarks.planted.cli import build_parser
from benchmarks.planted.config import tool_budget
from benchmarks.planted.inputs import as_user_inputs
from benchmarks.rods import SOURCE_ROD, rod_spec
from deform.diagnose.selection import diagnose
from deform.io.recordings import Recording
args = build_parser().parse_args({planted!r}.split())
data = np.load({npz!r})
recs = [Recording(name=f"rec{{i}}", positions=data[f"rec{{i}}"], dt=float(data["dt"])) for i in range(args.fit + args.check)]
spec = rod_spec(SOURCE_ROD[{kind!r}], {kind!r} + "-elastica")
inputs = as_user_inputs(spec, recs[: args.fit], recs[args.fit :], smooth_noise=True)
t = time.perf_counter()
rep = diagnose(inputs, tool_budget(args)).report
seconds = time.perf_counter() - t
print(json.dumps({{
    "seconds": seconds,
    "selected": rep["selected"],
    "final_check_l1_m": rep["final_check_l1_m"],
    "improvements": {{f"{{c['name']}}@{{c['round']}}": c["improvement"] for c in rep["candidates"]}},
}}))
"""


def simulate(dataset: str, out: Path) -> Path:
    """The dataset's recordings (PyElastica, the planted benchmark's settings) as arrays in ``out``."""
    from benchmarks.planted.cli import build_parser
    from benchmarks.planted.independent import simulate as simulate_dataset

    kind, effect, seed = dataset.split(":")
    args = build_parser().parse_args(PLANTED.split())
    sim = simulate_dataset("elastica", kind, None if effect == "none" else effect, int(seed), args)
    if "diverged" in sim:
        raise SystemExit(f"{dataset}: the simulator diverged ({sim['diverged']})")
    path = out / f"{dataset.replace(':', '.')}.npz"
    arrays = {f"rec{i}": r.positions for i, r in enumerate(sim["recs"])}
    np.savez(path, dt=sim["recs"][0].dt, **arrays)
    return path


def measure(root: Path, dataset: str, npz: Path) -> dict:
    """One diagnosis of ``dataset`` by the checkout at ``root``."""
    code = _DIAGNOSE.format(root=str(root), planted=PLANTED, npz=str(npz), kind=dataset.split(":")[0])
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{root} on {dataset}: {out.stderr.strip().splitlines()[-1]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def summarize(rows: dict) -> dict:
    """Per dataset: median seconds of each checkout, base / head, and whether the names and scores agree."""
    out = {}
    for dataset, runs in rows.items():
        base = statistics.median(r["seconds"] for r in runs["base"])
        head = statistics.median(r["seconds"] for r in runs["head"])
        b, h = runs["base"][0], runs["head"][0]
        out[dataset] = {
            "base_s": base,
            "head_s": head,
            "speedup": base / head,
            "same_names": all(r["selected"] == b["selected"] for r in runs["base"] + runs["head"]),
            "selected": h["selected"],
            "max_improvement_difference": max(
                abs(h["improvements"][k] - b["improvements"][k]) for k in b["improvements"]
            )
            if set(h["improvements"]) == set(b["improvements"])
            else None,
        }
    total_base = sum(v["base_s"] for v in out.values())
    total_head = sum(v["head_s"] for v in out.values())
    return {"datasets": out, "speedup": total_base / total_head}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", default="e195a5b", help="the earlier commit (default: before the faster fits)")
    ap.add_argument("--datasets", nargs="+", default=list(DATASETS), metavar="KIND:EFFECT:SEED")
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/diagnose_ab.json"))
    args = ap.parse_args()
    from benchmarks.provenance import provenance

    meta = provenance()
    rows: dict[str, dict] = {d: {"base": [], "head": []} for d in args.datasets}
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "base"
        subprocess.run(
            ["git", "worktree", "add", "-q", "--detach", str(base), args.base], cwd=ROOT, check=True
        )
        try:
            for dataset in args.datasets:
                npz = simulate(dataset, Path(tmp))
                for r in range(args.rounds):
                    for name, root in (("base", base), ("head", ROOT)):
                        rows[dataset][name].append(measure(root, dataset, npz))
                        print(dataset, name, r, json.dumps(rows[dataset][name][-1]), flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base)], cwd=ROOT, check=False)
    result = {**meta, "base": args.base, "planted": PLANTED, "rounds": rows, "summary": summarize(rows)}
    Path(args.json).write_text(json.dumps(result, indent=2))
    print(json.dumps(result["summary"], indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
