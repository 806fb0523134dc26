"""Speed benchmark (issue 2): `python benchmarks/speed.py [--quick]` -> benchmarks/results/speed.json."""

import argparse
import json
import sys
from pathlib import Path

if not __package__:  # run as `python benchmarks/speed.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from benchmarks.provenance import provenance
from deform.bench import run_benchmarks

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    meta, bench = provenance(), run_benchmarks(quick=args.quick)
    # the machine as every benchmark names it, with what the speed benchmark adds (threads, load)
    result = {**meta, **bench, "machine": {**meta["machine"], **bench.get("machine", {})}}
    out = Path(__file__).parent / "results" / "speed.json"
    out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
