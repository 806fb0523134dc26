"""Speed benchmark (issue 2): `python benchmarks/speed.py [--quick]` -> benchmarks/results/speed.json."""

import argparse
import json
from pathlib import Path

from deform.bench import run_benchmarks

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    result = run_benchmarks(quick=args.quick)
    out = Path(__file__).parent / "results" / "speed.json"
    out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
