"""Plain discrete elastic rod: :class:`deform.model.DeformModel` without the residual network.

- :func:`der_initial`: the rod config's initial guesses (bending/twisting stiffness, damping, drag).
- :func:`der_identified`: physical parameters identified on the rod's train recordings by
  :func:`identify` (``deform.train.train`` with ``residual=False``: coarse grid, then gradient
  descent through open-loop rollouts), stored as ``weights/der_ROD.pt`` (physical parameters only).
  Without that file the physical parameters of the shipped DEFORM model ``deform/models/ROD.pt``
  are used with the residual network disabled (``model.baseline_source`` says which).
"""

from __future__ import annotations

from pathlib import Path

import torch

from deform.baselines import WEIGHT_DIR, MissingWeightsError
from deform.config import load_rod_config
from deform.model import MODEL_DIR, DeformModel, ModelOptions

PHYSICS = ("log_beta", "log_gamma", "wbar", "extra_mass_raw", "log_damping", "log_drag")


def der_initial(rod: str) -> DeformModel:
    """Plain DER (no residual network) with the rod config's initial parameters: the untrained model.

    Args:
        rod: a rod config name.

    Returns:
        The model, in eval mode.
    """
    model = DeformModel(load_rod_config(rod), ModelOptions(residual=False))
    model.baseline_source = "config initial parameters"
    return model.eval()


def weight_path(rod: str) -> Path:
    """Args:
        rod: a rod name.

    Returns:
        Where the identified DER parameters of that rod are stored.
    """
    return WEIGHT_DIR / f"der_{rod}.pt"


def save_physics(model: DeformModel, path: str | Path, extra: dict | None = None) -> None:
    """Store only the physical parameters (no network) of a model.

    Args:
        model: the identified model.
        path: the ``.pt`` to write.
        extra: more fields for the file.
    """
    sd = model.state_dict()
    payload = {"rod": model.cfg.name, "physics": {k: sd[k].clone() for k in PHYSICS}, **(extra or {})}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    torch.save(payload, path)


def _with_physics(rod: str, physics: dict, source: str) -> DeformModel:
    model = DeformModel(load_rod_config(rod), ModelOptions(residual=False))
    missing = [k for k in PHYSICS if k not in physics and k != "log_drag"]
    if missing:
        raise ValueError(f"{source}: missing physical parameters {missing}")
    with torch.no_grad():
        for k in PHYSICS:
            if k in physics:
                getattr(model, k).copy_(physics[k])
    model.baseline_source = source
    return model.eval()


def der_identified(rod: str, path: str | Path | None = None) -> DeformModel:
    """Identified plain DER. ``path``: a ``der_ROD.pt`` physics file or any DEFORM checkpoint.

    Args:
        rod: a rod config name.
        path: a physics file or checkpoint, or None (``der_ROD.pt``, else the shipped DEFORM model).

    Returns:
        The model without residual network, in eval mode.

    Raises:
        MissingWeightsError: none of the files exists.
    """
    candidates = [Path(path)] if path else [weight_path(rod), MODEL_DIR / f"{rod}.pt"]
    for p in candidates:
        if p.is_file():
            payload = torch.load(p, map_location="cpu", weights_only=True)
            physics = payload.get("physics") or payload["state_dict"]
            return _with_physics(rod, physics, str(p))
    raise MissingWeightsError(
        f"no identified DER parameters for {rod}: looked at {', '.join(map(str, candidates))}; "
        "run benchmarks/baselines.py"
    )


def identify(
    rod: str,
    train_recs,
    val_recs,
    out_dir: str | Path,
    iterations: int = 100,
    batch: int = 8,
    horizon: int = 100,
    time_limit_s: float | None = None,
    progress: bool = True,
) -> dict:
    """System identification of plain DER (no residual) and save of ``weights/der_ROD.pt``.

    Args:
        rod: a rod config name.
        train_recs: recordings to identify on.
        val_recs: recordings that choose the best parameters.
        out_dir: the training run's directory.
        iterations: updates.
        batch: windows per update.
        horizon: rollout steps per window.
        time_limit_s: stop after this long.
        progress: progress bar.

    Returns:
        :func:`deform.train.train`'s result.
    """
    from deform.train import TrainConfig, train

    model = DeformModel(load_rod_config(rod), ModelOptions(residual=False))
    cfg = TrainConfig(
        iterations=iterations,
        batch=batch,
        horizon=horizon,
        residual=False,
        curriculum=(10, 25, 50),
        curriculum_iters=max(1, iterations // 10),
        log_every=10,
        time_limit_s=time_limit_s,
    )
    result = train(model, train_recs, val_recs, cfg, out_dir, resume=False, progress=progress)
    best = DeformModel.load(Path(out_dir) / "best.pt")
    save_physics(
        best,
        weight_path(rod),
        {"val_l1_m": result["best_val_l1_m"], "iterations": result["last"].get("iteration")},
    )
    return result
