"""The planted-effect benchmark of `deform diagnose` (``python benchmarks/diagnose_planted.py``).

* versions, budgets and the rule: :mod:`~benchmarks.planted.config`;
* what the tool is given and what a row measures: :mod:`~benchmarks.planted.inputs`;
* datasets per simulator: :mod:`~benchmarks.planted.own` (this project's simulator, and the real
  rods), :mod:`~benchmarks.planted.independent` (PyElastica, MuJoCo: the generators are
  :mod:`~benchmarks.planted.elastica` and :mod:`~benchmarks.planted.mujoco`, their shared geometry
  :mod:`~benchmarks.planted.geometry` and table :mod:`~benchmarks.planted.detectability`);
  :mod:`~benchmarks.planted.splice` (``--refit``);
* running (Ray tasks, one stored file per dataset): :mod:`~benchmarks.planted.run`;
* tables: :mod:`~benchmarks.planted.tables`;
* the studies beside the benchmark: :mod:`~benchmarks.planted.studies_own`,
  :mod:`~benchmarks.planted.studies_independent`;
* the command line: :mod:`~benchmarks.planted.cli`.
"""
