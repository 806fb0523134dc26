"""The loop from `deform diagnose` back into DEFORM, on the real rods (issue 18, part 5).

For every rod, the terms the discrepancy tool named (benchmarks/results/diagnose.real.json, or
--terms ROD=NAME) are trained into DEFORM and compared on the paper's metric:

* ``shipped``: the shipped model (deform/models/ROD.pt);
* ``with``: the shipped model fine-tuned with the term (an added term is attached; a built-in one,
  see deform.terms.BUILT_IN, stays free);
* ``without``: the same fine-tuning without the term (an added term left out; a built-in one removed:
  uniform stiffness, no quadratic drag...). Same budget and seed as ``with``, so the difference is
  the term and not the extra training.

Validation (the held-out fifth of the train recordings: the shipped models chose their best\ncheckpoint on it but never took a gradient from it)
picks among the three; `--install` ships the ``with`` model only when validation picks it. Eval
(DLO1-DLO3) reports the paper's metric over 500 steps, as benchmarks/accuracy.py does.

    python benchmarks/real_terms.py [--rods DLO2 DLO3] [--iterations 120] [--install]
        [--num-cpus N] [--address ray://HOST:PORT | auto]
        -> benchmarks/results/real_terms.{json,md}, runs in runs/real_terms/

Each rod's shipped scores and each fine-tuning (rod, term, arm) is a Ray task with one torch thread
(benchmarks/cluster.py: a local Ray, one task per core, or a cluster); each is stored as it
finishes in benchmarks/results/<stem>.runs/ (one file per task, the trained model in runs/), and a
rerun with the same budget skips the stored ones.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

if not __package__:  # run as `python benchmarks/real_terms.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from benchmarks.accuracy import test_recordings
from benchmarks.cluster import Workers, add_arguments, call, repo_path
from benchmarks.provenance import machine_text, provenance
from benchmarks.store import RunStore, write_atomic
from deform.evaluate import evaluate
from deform.io.recordings import find_data_root, load_recordings
from deform.model import MODEL_DIR, DeformModel, load_model
from deform.terms import ADDED, BUILT_IN, attached_names, describe
from deform.train import TrainConfig, split_validation, train, validation_l1

ROOT = Path(__file__).resolve().parents[1]

RESULTS = ROOT / "benchmarks" / "results"


def named_terms(rods: list[str], explicit: list[str]) -> dict[str, list[str]]:
    """ROD -> the terms the stored diagnosis selected (or the ones given as ROD=NAME)."""
    if explicit:
        out = {rod: [] for rod in rods}
        for item in explicit:
            rod, name = item.split("=", 1)
            out.setdefault(rod, []).append(name)
        return out
    stored = json.loads((RESULTS / "diagnose.real.json").read_text())
    by_rod = {row["rod"]: row.get("selected", []) for row in stored["real"]}
    return {rod: list(by_rod.get(rod, [])) for rod in rods}


def scores(model: DeformModel, val_recs, test_recs, val_steps: int) -> dict:
    return {
        "val_l1_m": validation_l1(model, val_recs, val_steps),
        "eval_l1_m": evaluate(model, test_recs)["l1_m"],
    }


def _fine_tune_config(args, name: str, arm: str, model: DeformModel) -> TrainConfig:
    """The fine-tuning of one arm: ``with`` attaches an added term; ``without`` removes a built-in
    one, or an added one the shipped model already carries (trained with it)."""
    terms = (name,) if (arm == "with" and name in ADDED) else ()
    removable = name in BUILT_IN or name in attached_names(model)
    removed = (name,) if (arm == "without" and removable) else ()
    return TrainConfig(
        iterations=args.iterations,
        batch=args.batch,
        horizon=args.horizon,
        curriculum=(),
        lr_physics=2e-2 * args.lr_scale,
        lr_network=1e-3 * args.lr_scale,
        coarse_sysid=False,  # fine-tuning an identified model
        terms=terms,
        without=removed,
    )


def _data(rod: str, n: int, horizon: int):
    root = find_data_root()
    if root is None:
        raise RuntimeError("no dataset: set DEFORM_DATA")
    train_recs, val_recs = split_validation(load_recordings(root / rod / "train", n))
    test_recs, split = test_recordings(root, rod, n)
    val_steps = min(horizon * 5, min(r.n_frames for r in val_recs) - 2)
    return train_recs, val_recs, test_recs, split, val_steps


def shipped_task(rod: str, args) -> dict:
    """A task: the shipped model's scores on ``rod``."""
    shipped = load_model(rod)
    _, val_recs, test_recs, split, val_steps = _data(rod, shipped.n, args.horizon)
    return {"rod": rod, "split": split, "shipped": scores(shipped, val_recs, test_recs, val_steps)}


def arm_task(rod: str, name: str, arm: str, args, out: str) -> dict:
    """A task: the shipped model of ``rod`` fine-tuned ``with`` or ``without`` the term ``name`` (in
    ``out``, relative to the repository); its scores and its best model's bytes (``best_pt``, which
    the benchmark's process writes to ``out`` on its own disk)."""
    model = load_model(rod)
    train_recs, val_recs, test_recs, _, val_steps = _data(rod, model.n, args.horizon)
    cfg = _fine_tune_config(args, name, arm, model)
    path = repo_path(out)
    t0 = time.perf_counter()
    result = train(model, train_recs, val_recs, cfg, path, resume=False, progress=False)
    best = DeformModel.load(path / "best.pt")
    return {
        **scores(best, val_recs, test_recs, val_steps),
        "seconds": time.perf_counter() - t0,
        "terms": list(cfg.terms),
        "without": list(cfg.without),
        "term_starts": result.get("term_starts"),
        "path": str(Path(out) / "best.pt"),
        "best_pt": (path / "best.pt").read_bytes(),
    }


def model_id(rod: str) -> str:
    """``ROD@HASH``: the rod and its shipped model's content, a stored task's key prefix (rows of a
    model since replaced, e.g. by ``--install``, are not reused)."""
    import hashlib

    path = MODEL_DIR / f"{rod}.pt"
    digest = hashlib.sha1(path.read_bytes()).hexdigest()[:8] if path.is_file() else "none"
    return f"{rod}@{digest}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rods", nargs="*", default=["DLO1", "DLO2", "DLO3", "DLO4", "DLO5"])
    ap.add_argument("--terms", nargs="*", default=[], help="ROD=NAME instead of the stored diagnosis")
    ap.add_argument("--iterations", type=int, default=120)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--horizon", type=int, default=100)
    ap.add_argument("--lr-scale", type=float, default=0.25, help="of the training learning rates")
    ap.add_argument("--install", action="store_true", help="ship a with-term model validation picks")
    ap.add_argument("--runs", default="runs/real_terms", help="training runs (relative to the repository)")
    ap.add_argument("--stem", default="real_terms", help="result files benchmarks/results/<stem>.{json,md}")
    add_arguments(ap)
    args = ap.parse_args(argv)
    named = named_terms(args.rods, args.terms)
    config = {
        "iterations": args.iterations,
        "batch": args.batch,
        "horizon": args.horizon,
        "lr_scale": args.lr_scale,
    }
    store = RunStore.for_runs(RESULTS / f"{args.stem}.runs")
    done = store.load(config)
    # one task per rod (the shipped model's scores) and per rod, term and arm (a fine-tuning)
    ids = {rod: model_id(rod) for rod in args.rods}
    tasks = {}
    for rod in args.rods:
        if f"{ids[rod]}:shipped" not in done:
            tasks[f"{ids[rod]}:shipped"] = call(shipped_task, rod, args)
        for name in named[rod]:
            for arm in ("with", "without"):
                key = f"{ids[rod]}:{name}:{arm}"
                if key not in done:
                    tasks[key] = call(arm_task, rod, name, arm, args, f"{args.runs}/{rod}/{name}.{arm}")
    t_all = time.perf_counter()

    def stored(key: str, value: dict) -> None:
        best_pt = value.pop("best_pt", None)
        if best_pt is not None:  # the model, on this machine's disk (a cluster's worker has its own)
            (ROOT / value["path"]).parent.mkdir(parents=True, exist_ok=True)
            (ROOT / value["path"]).write_bytes(best_pt)
        row = {"key": key, "config": config, **value}
        store.save(row)
        done[key] = row
        what = value.get("shipped", value)
        workers.log(f"{key}: val {what['val_l1_m'] * 100:.3f} cm, test {what['eval_l1_m'] * 100:.3f} cm")

    with Workers.from_args(args) as workers:
        failures = workers.run(tasks, stored, desc=args.stem)
    rows = []
    for rod in args.rods:
        if f"{ids[rod]}:shipped" not in done:
            continue
        base, split = done[f"{ids[rod]}:shipped"]["shipped"], done[f"{ids[rod]}:shipped"]["split"]
        if not named[rod]:
            rows.append({"rod": rod, "term": None, "split": split, "shipped": base})
        for name in named[rod]:
            arms = {
                arm: done[f"{ids[rod]}:{name}:{arm}"]
                for arm in ("with", "without")
                if f"{ids[rod]}:{name}:{arm}" in done
            }
            if len(arms) < 2:
                continue
            arms = {
                arm: {k: v for k, v in row.items() if k not in ("key", "config")} for arm, row in arms.items()
            }
            picked = min([("shipped", base), *arms.items()], key=lambda kv: kv[1]["val_l1_m"])[0]
            installed = False
            if args.install and picked == "with":
                DeformModel.load(ROOT / arms["with"]["path"]).save(MODEL_DIR / f"{rod}.pt")
                installed = True
            rows.append(
                {
                    "rod": rod,
                    "term": name,
                    "kind": "built in" if name in BUILT_IN else "added",
                    "meaning": describe(name),
                    "split": split,
                    "shipped": base,
                    **arms,
                    "validation_picks": picked,
                    "installed": installed,
                }
            )
    result = {
        **provenance(argv, threads=1),
        "workers": workers.describe(),
        "threads": 1,
        "budget": config,
        "seconds_total": time.perf_counter() - t_all,
        "seconds_tasks": float(
            sum(row.get("seconds", 0.0) for row in done.values() if row.get("key", "").count(":") == 2)
        ),
        "complete": not failures,
        "rows": rows,
    }
    RESULTS.mkdir(exist_ok=True)
    write_atomic(RESULTS / f"{args.stem}.json", json.dumps(result, indent=2))
    write_atomic(RESULTS / f"{args.stem}.md", markdown(result))
    print(markdown(result))
    if failures:
        print(f"{len(failures)} task(s) failed, not stored: {', '.join(failures)}", file=sys.stderr)
        return 1
    return 0


def markdown(result: dict) -> str:
    def cm(row, arm, key):
        return f"{row[arm][key] * 100:.3f}" if arm in row else "-"

    b = result["budget"]
    machine = machine_text(result["machine"])
    lines = [
        "# Named physics trained into DEFORM, real rods",
        "",
        f"Run: `{result['command']}` at commit {result['commit']} on "
        f"{machine}; "
        f"{result['seconds_total']:.0f} s. Fine-tuning from the shipped model: {b['iterations']} "
        f"iterations of {b['batch']} windows x {b['horizon']} steps, learning rates x {b['lr_scale']}, "
        "the same seed for both arms.",
        "",
        "| rod | term named | in DEFORM | val shipped [cm] | val with [cm] | val without [cm] "
        "| test shipped [cm] | test with [cm] | test without [cm] | test split | validation picks |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['rod']} | {r['term'] or 'none'} | {r.get('kind', '-')} | {cm(r, 'shipped', 'val_l1_m')} "
            f"| {cm(r, 'with', 'val_l1_m')} | {cm(r, 'without', 'val_l1_m')} "
            f"| {cm(r, 'shipped', 'eval_l1_m')} | {cm(r, 'with', 'eval_l1_m')} | {cm(r, 'without', 'eval_l1_m')} "
            f"| {r['split'].split(' ')[0]} | {r.get('validation_picks', 'shipped')}"
            f"{' (installed)' if r.get('installed') else ''} |"
        )
    lines += [
        "",
        "Test: the paper's metric (500-step open-loop L1, gripped vertices given) on eval (DLO1-DLO3) "
        "or on the held-out fifth of train (DLO4, DLO5, which is then also the validation set).",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
