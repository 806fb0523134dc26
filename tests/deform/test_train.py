import json

import pytest
import torch

from deform import DeformModel, Recording, generate_recording, load_rod_config
from deform.train import TrainConfig, coarse_identification, train, validation_l1


@pytest.mark.slow
def test_training_on_generated_data_reduces_loss_and_resumes(tmp_path):
    """The 'truth' is the model with stiffer bending and more damping; training starts from the default."""
    cfg = load_rod_config("DLO2")
    truth = DeformModel(cfg.model_copy(update={"bend_stiffness": cfg.bend_stiffness * 4, "damping": 3.0}))
    recs = [generate_recording(truth, n_frames=60, seed=s) for s in range(3)]
    model = DeformModel(cfg)
    before = validation_l1(model, recs[2:], 58)
    tcfg = TrainConfig(
        iterations=16,
        batch=4,
        horizon=30,
        curriculum=(),
        lr_physics=1.5e-1,
        log_every=4,
        seed=1,
        coarse_sysid=False,
    )
    train(model, recs[:2], recs[2:], tcfg, tmp_path, progress=False)
    log = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    vals = [e["val_l1_m"] for e in log if "val_l1_m" in e]
    assert min(vals) < 0.7 * before
    assert model.log_beta.mean() > torch.log(torch.tensor(cfg.bend_stiffness))  # moved towards the truth
    # resume: a longer run continues from the checkpoint instead of starting again
    tcfg.iterations = 18
    result = train(model, recs[:2], recs[2:], tcfg, tmp_path, progress=False)
    assert result["last"]["iteration"] == 18
    assert len((tmp_path / "log.jsonl").read_text().splitlines()) == 18
    # started afresh in the same directory (--fresh): the log is this run's alone
    tcfg.iterations = 2
    train(model, recs[:2], recs[2:], tcfg, tmp_path, resume=False, progress=False)
    log = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [e["iteration"] for e in log] == [1, 2]


@pytest.mark.slow
def test_coarse_identification_finds_the_stiffness_decade():
    cfg = load_rod_config("DLO2")
    truth = DeformModel(
        cfg.model_copy(update={"bend_stiffness": 1e-2, "twist_stiffness": 7e-3, "damping": 1.0})
    )
    recs = [generate_recording(truth, n_frames=80, seed=s) for s in range(2)]
    model = DeformModel(cfg.model_copy(update={"bend_stiffness": 1e-4, "twist_stiffness": 7e-5}))
    found = coarse_identification(model, recs, steps=60, progress=False)
    assert 3e-3 <= found["bend_stiffness"] <= 3e-2
    assert abs(model.log_beta.exp().mean().item() - found["bend_stiffness"]) < 1e-6 * found["bend_stiffness"]


@pytest.mark.slow
def test_coarse_identification_goes_past_the_grid_for_a_softer_rope():
    """A string ten times softer than the grid's softest point (1e-4 N m^2): the grid goes on below
    its edge while the edge wins, and lands on the truth's half decade (it stopped at 1e-4 before)."""
    cfg = load_rod_config("DLO2")
    truth = DeformModel(
        cfg.model_copy(update={"bend_stiffness": 1.2e-5, "twist_stiffness": 8e-6, "damping": 1.0})
    )
    recs = [generate_recording(truth, n_frames=80, seed=s) for s in range(2)]
    model = DeformModel(cfg.model_copy(update={"bend_stiffness": 1e-3, "twist_stiffness": 7e-4}))
    found = coarse_identification(model, recs, steps=60, progress=False)
    assert 5e-6 <= found["bend_stiffness"] <= 3e-5


@pytest.mark.slow
def test_coarse_identification_goes_past_the_grid_for_a_stiff_cable_and_steps_it_implicitly():
    """A cable five times stiffer than the grid's stiffest point (3e-2 N m^2), generated with the
    implicit bending it needs: the grid goes on above its edge, lands on the truth's half decade and
    keeps the implicit scheme, in substeps, for it (explicitly, a 65 g rope rings from about 0.01 N m^2)."""
    cfg = load_rod_config("DLO2")
    truth = DeformModel(
        cfg.model_copy(update={"bend_stiffness": 0.15, "twist_stiffness": 0.1, "damping": 1.0})
    )
    assert truth.choose_bending_scheme()
    recs = [generate_recording(truth, n_frames=80, seed=s) for s in range(2)]
    model = DeformModel(cfg.model_copy(update={"bend_stiffness": 1e-3, "twist_stiffness": 7e-4}))
    found = coarse_identification(model, recs, steps=60, progress=False)
    assert 0.1 <= found["bend_stiffness"] <= 0.3
    assert found["implicit_bending"] and model.cfg.implicit_bending
    assert found["substeps"] == model.cfg.substeps > 1  # its step ratio is above IMPLICIT_RATIO_MAX


def test_training_windows_start_in_the_frames_evaluation_carries():
    """A window cut at frame s starts with the reference directors a rollout from the recording's
    first frame carries there: at s = 0 exactly evaluation's start, later perpendicular to the edges
    and different from fresh space-parallel frames once the grippers have turned."""
    import random

    import numpy as np

    from deform.rod import geometry as G
    from deform.rod.layout import batch_major, vertex_major
    from deform.train import sample_windows

    cfg = load_rod_config("DLO2")
    rec = generate_recording(DeformModel(cfg), n_frames=120, seed=3, amplitude=0.3)
    X, d1 = sample_windows([rec], 8, 20, random.Random(0))
    assert X.shape == (8, 22, cfg.n_vertices, 3) and d1.shape == (8, cfg.n_vertices - 1, 3)
    frames = torch.tensor(rec.reference_frames)
    starts = [int(np.flatnonzero((rec.positions == X[b, 0].numpy()).all(axis=(1, 2)))[0]) for b in range(8)]
    for b, s in enumerate(starts):
        assert torch.equal(d1[b], frames[s + 1])
    model = DeformModel(cfg)
    x = torch.tensor(rec.positions)
    assert torch.allclose(frames[1], model.initial_state(x[0], x[1]).d1[0], atol=1e-12)
    t = torch.nn.functional.normalize(x[:, 1:] - x[:, :-1], dim=-1)
    assert float((frames[1:] * t[1:]).sum(-1).abs().max()) < 1e-9
    fresh = batch_major(G.space_parallel_frame(vertex_major(t[-1:], 2)), (1,))[0]
    assert float((fresh - frames[-1]).norm(dim=-1).max()) > 1e-3
    _, none = sample_windows([rec], 2, 20, random.Random(0), transported=False)
    assert none is None


def test_a_horizon_longer_than_every_recording_is_a_clear_error_before_any_work(tmp_path):
    """Windows cannot be cut from recordings shorter than the horizon: training says so up front
    (the CLI prints it as one line) instead of failing inside the random window sampler; shorter
    recordings among longer ones are simply not sampled."""
    import random

    from deform.errors import UsageError
    from deform.train import TrainConfig, sample_windows, train

    cfg = load_rod_config("DLO2")
    model = DeformModel(cfg)
    short = generate_recording(model, n_frames=30, seed=1)
    long = generate_recording(model, n_frames=60, seed=2)
    with pytest.raises(UsageError, match="at least 52 frames; the longest has 30"):
        train(model, [short], [], TrainConfig(iterations=1, horizon=50), tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()
    X, _ = sample_windows([short, long], 6, 50, random.Random(0))
    assert X.shape[1] == 52 and all(
        (X[b, 0].numpy() == long.positions).all(axis=(1, 2)).any() for b in range(6)
    )


def test_a_weighted_loss_learns_nothing_from_positions_of_weight_zero():
    """Positions nobody saw (weight 0, e.g. a camera track behind an occluder) change neither the
    loss nor its gradient; all weights 1 is the plain mean; windows carry their own weights."""
    import random

    import numpy as np

    from deform.train import rollout_loss, sample_weighted_windows

    cfg = load_rod_config("DLO2")
    model = DeformModel(cfg)
    rec = generate_recording(model, n_frames=60, seed=4)
    weights = np.ones(rec.positions.shape[:2])
    weights[:, 5] = 0.0
    weights[30:, 6] = 0.0
    bad = rec.positions.copy()
    bad[:, 5] += 0.05  # what an occluded vertex's track may be
    bad[30:, 6] -= 0.03
    X, d1, W = sample_weighted_windows(
        [Recording("w", rec.positions, weights=weights)], 4, 20, random.Random(1)
    )
    Xb, _, Wb = sample_weighted_windows([Recording("w", bad, weights=weights)], 4, 20, random.Random(1))
    assert W.shape == (4, 20, cfg.n_vertices) and torch.equal(W, Wb)
    starts = [int(np.flatnonzero((rec.positions == X[b, 0].numpy()).all(axis=(1, 2)))[0]) for b in range(4)]
    for b, s in enumerate(starts):
        assert torch.equal(W[b], torch.tensor(weights[s + 2 : s + 22]))
    Xb[:, :2] = X[:, :2]  # the same start: only the predicted frames' targets differ

    def loss_and_grad(windows, w):
        model.zero_grad()
        loss = rollout_loss(model, windows, d1, w)
        loss.backward()
        return float(loss), model.log_beta.grad.clone()

    clean, g_clean = loss_and_grad(X, W)
    corrupted, g_bad = loss_and_grad(Xb, W)
    assert clean == pytest.approx(corrupted, rel=1e-12) and torch.allclose(g_clean, g_bad, rtol=1e-10)
    assert float(rollout_loss(model, Xb, d1)) > 2 * clean  # unweighted, the corruption dominates
    ones = torch.ones_like(W)
    assert float(rollout_loss(model, X, d1, ones)) == pytest.approx(
        float(rollout_loss(model, X, d1)), rel=1e-12
    )


def test_windows_start_from_positions_and_score_against_targets():
    """A recording with ``targets`` (a camera track: scored as corrected, started smoothed): a
    window's two start frames are its positions, the predicted frames its targets; without
    targets both are the positions."""
    import random

    from deform.train import sample_weighted_windows

    rec = generate_recording(DeformModel(load_rod_config("DLO2")), n_frames=60, seed=4)
    targets = rec.positions + 0.01
    X, _, _ = sample_weighted_windows(
        [Recording("t", rec.positions, targets=targets)], 3, 20, random.Random(2)
    )
    P, _, _ = sample_weighted_windows([rec], 3, 20, random.Random(2))
    assert torch.equal(X[:, :2], P[:, :2])
    torch.testing.assert_close(X[:, 2:], P[:, 2:] + 0.01, rtol=0, atol=1e-12)


def test_validation_weighs_targets_and_is_the_paper_metric_without_weights():
    """Validation and the coarse identification score a camera track as training does: only the
    weighted positions, against the targets; a marker recording by the paper's metric."""
    import numpy as np

    from deform.evaluate import metrics, predict_recordings

    model = DeformModel(load_rod_config("DLO2"))
    recs = [generate_recording(model, n_frames=40, seed=s) for s in range(2)]
    assert validation_l1(model, recs, 30) == pytest.approx(
        metrics(predict_recordings(model, recs, 30))["l1_m"]
    )
    rec = recs[0]
    weights = np.zeros(rec.positions.shape[:2])
    weights[10, 4] = 1.0
    targets = rec.positions.copy()
    targets[10, 4, 2] += 0.02  # the only scored coordinate is 2 cm off
    targets[20:] += 1.0  # unweighted: never scored
    shifted = Recording("w", rec.positions, weights=weights, targets=targets)
    pred = predict_recordings(model, [rec], 30)[0].prediction
    expected = np.abs(pred[8, 4] - targets[10, 4]).sum() / 3
    assert validation_l1(model, [shifted], 30) == pytest.approx(expected, rel=1e-9)
    assert expected > 0.006


def test_a_validation_set_that_never_scores_leaves_the_last_weights_as_best(tmp_path):
    """Held-out camera tracks that no cloud corrected (all weights 0) have no fit: training still
    writes best.pt (the last weights) instead of leaving calibration without a model."""
    import numpy as np

    model = DeformModel(load_rod_config("DLO2"))
    recs = [generate_recording(model, n_frames=40, seed=s) for s in range(2)]
    unseen = Recording("unseen", recs[1].positions, weights=np.zeros(recs[1].positions.shape[:2]))
    cfg = TrainConfig(iterations=2, batch=2, horizon=10, curriculum=(), log_every=1, coarse_sysid=False)
    result = train(model, recs[:1], [unseen], cfg, tmp_path, progress=False)
    assert result["best_val_l1_m"] == float("inf") and (tmp_path / "best.pt").exists()
