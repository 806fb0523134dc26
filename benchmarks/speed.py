"""Speed benchmark (issue 2): `python benchmarks/speed.py [--quick]` -> benchmarks/results/speed.json."""

import argparse
import json
import subprocess
import sys
from pathlib import Path

from deform.bench import run_benchmarks

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    root = Path(__file__).resolve().parent.parent
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True)
    result = {
        "command": "python benchmarks/speed.py " + " ".join(sys.argv[1:]),
        "commit": commit.stdout.strip(),
        **run_benchmarks(quick=args.quick),
    }
    out = Path(__file__).parent / "results" / "speed.json"
    out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
