"""The benchmarks: scripts that measure the model, the service and `deform diagnose`, and write the
stored results in ``benchmarks/results/`` (rendered into docs/results.md by scripts/make_results.py).

Each script runs from the repository's root as ``python benchmarks/NAME.py`` (or, the same,
``python -m benchmarks.NAME``). Shared pieces: :mod:`benchmarks.provenance` (the command, commit and
machine every stored result names), :mod:`benchmarks.cluster` (independent datasets as Ray tasks, on
this machine or a cluster), :mod:`benchmarks.store` (one result file per dataset, resumed),
:mod:`benchmarks.rods` (the rods and motion sources of the planted-effect benchmarks) and the
package :mod:`benchmarks.planted` (the planted-effect benchmark of `deform diagnose`).
"""
