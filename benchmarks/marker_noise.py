"""Marker noise as `deform diagnose` measures it (deform.diagnose.denoise.marker_noise): on the DEFORM
recordings and on the independent simulators' seed-0 controls at their default 0.3 mm, and at 0 and
1 mm. Why: the tool smooths only above 0.5 mm, so this says which inputs reach the fits as given.

    python benchmarks/marker_noise.py [--json benchmarks/results/marker_noise.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

if not __package__:  # run as `python benchmarks/marker_noise.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", default="benchmarks/results/marker_noise.json")
    p.add_argument("--frames", type=int, default=300)
    args = p.parse_args()

    from benchmarks.planted.inputs import independent_simulator
    from benchmarks.provenance import provenance
    from benchmarks.rods import independent_rod, seeded_sources
    from deform.diagnose.denoise import SMOOTH_ABOVE_M, marker_noise, smoothing_window
    from deform.io.recordings import find_data_root, load_recordings

    root = find_data_root()
    rows = []
    if root is not None:
        for rod in ("DLO1", "DLO2", "DLO3", "DLO4", "DLO5"):
            recs = load_recordings(root / rod / "train")
            sigma = marker_noise(recs)
            rows.append({"source": f"DEFORM {rod} train", "recordings": len(recs), "noise_mm": sigma * 1e3})
        for simulator in ("elastica", "mujoco"):
            _, generate, _ = independent_simulator(simulator)
            for kind in ("light", "stiff"):
                spec, sources = independent_rod(kind, root, simulator)
                src = seeded_sources(sources, 0, 12)
                for planted_mm in (0.0, 0.3, 1.0):
                    recs, _ = generate(
                        None,
                        src,
                        spec,
                        rod_kind=kind,
                        n_frames=args.frames,
                        seed=0,
                        noise_m=planted_mm * 1e-3,
                    )
                    sigma = marker_noise(recs)
                    rows.append(
                        {
                            "source": f"{simulator} {kind} control seed 0",
                            "planted_mm": planted_mm,
                            "recordings": len(recs),
                            "noise_mm": sigma * 1e3,
                            "smoothing_window": smoothing_window(recs, sigma),
                        }
                    )
                    print(rows[-1], flush=True)
    out = {
        **provenance(),
        "smooth_above_mm": SMOOTH_ABOVE_M * 1e3,
        "rows": rows,
    }
    Path(args.json).write_text(json.dumps(out, indent=2))
    for r in rows:
        print(f"{r['source']:<32} {r.get('planted_mm', '-')!s:>5} -> {r['noise_mm']:.3f} mm")


if __name__ == "__main__":
    main()
