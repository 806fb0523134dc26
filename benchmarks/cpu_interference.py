"""How much does a busy second core slow a predict rollout on this machine?

The service's predict answers 2-3x slower while the loop and fusion run than when the service is
idle, although those use well under one of the two cores. This isolates the machine's share of it:
the predict rollout (64 plans x 100 steps, compiled ``RolloutStep``, one thread) alone, then with a
pure-Python busy loop in another process (which touches no shared data), then alone again.
On a machine whose cores are independent the three agree.

    python benchmarks/cpu_interference.py [--repeats 5]
"""

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> None:
    from deform import load_model
    from deform.compiled import RolloutStep, rollout

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = load_model("DLO1")
    step = RolloutStep(model)
    step.warmup((64,))
    x = torch.zeros(64, model.n, 3, dtype=torch.float64)
    x[:, :, 0] = torch.cumsum(torch.cat([torch.zeros(1, dtype=x.dtype), model.rest_lengths()]), 0)
    state = model.static_state(x)
    grips = x[:, [0, 1, model.n - 2, model.n - 1]].unsqueeze(1).repeat(1, 100, 1, 1)
    grips[:, :, 2:, 0] -= torch.linspace(0, 0.2, 100, dtype=x.dtype)[None, :, None]  # ends brought together

    def median_ms() -> float:
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            rollout(step, state, grips)
            times.append(time.perf_counter() - t0)
        return round(1e3 * float(np.median(times)), 1)

    out = {"alone": median_ms()}
    burner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.5)
        out["with a busy process"] = median_ms()
    finally:
        burner.kill()
    out["alone again"] = median_ms()
    print(out)


if __name__ == "__main__":
    main()
