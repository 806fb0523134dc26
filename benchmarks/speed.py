"""Speed benchmark (issue 2): `python benchmarks/speed.py [--quick]` -> benchmarks/results/speed.json."""

import argparse
import json
import sys
from pathlib import Path

from deform.bench import run_benchmarks, source_commit

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    result = {
        "command": "python benchmarks/speed.py " + " ".join(sys.argv[1:]),
        "commit": source_commit(),
        **run_benchmarks(quick=args.quick),
    }
    out = Path(__file__).parent / "results" / "speed.json"
    out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
