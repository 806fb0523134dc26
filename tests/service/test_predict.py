"""`{ns}/predict`: requests validated before any work; prediction is batched and leaves the state alone."""

import json

import numpy as np
import pytest

from service import messages as M
from service import predict, predict_pool
from service.estimator import Estimator
from tests.service.conftest import make_config
from tests.service.open_loop_tracker import OpenLoopTracker

GOOD = np.array([[-0.4, 0, 0.5, 0, 0, 0, 1], [0.4, 0, 0.5, 0, 0, 1, 0]], dtype=float)
T0 = 1_700_000_000 * 10**9


@pytest.fixture(scope="module")
def est(model):
    e = Estimator(
        make_config(
            limits={
                "max_plans": 8,
                "max_steps": 20,
                "max_plan_steps_total": 100,
                "max_request_bytes": 100_000,
            }
        ),
        model,
        OpenLoopTracker(model, settle_steps=50),
    )
    e.on_poses(M.pose_array(T0, GOOD))
    e.tick(T0)
    return e


_WORKERS: dict = {}


def handle(est, raw):
    """``predict_pool.handle`` with an inline worker (the rollout in this thread), one per estimator."""
    from service.workers import InlineWorker

    worker = _WORKERS.setdefault(id(est), InlineWorker(est.model, est.cfg))
    return predict_pool.handle(est, raw, worker)


def body(plans, **extra):
    return json.dumps({"plans": np.asarray(plans).tolist(), **extra}).encode()


@pytest.mark.parametrize(
    "raw,reason",
    [
        (b"{not json", "bad_json"),
        (b'{"plan": []}', "bad_request"),
        (b"[1, 2]", "bad_request"),
        (body(np.zeros((2, 3, 2, 6))), "bad_shape"),
        (b'{"plans": [[[[0,0,0,0,0,0,1],[0,0,0,0,0,0,1]]], [[[0,0,0]]]]}', "bad_shape"),
        (body(np.tile(GOOD, (9, 2, 1, 1))), "too_large"),
        (body(np.tile(GOOD, (1, 21, 1, 1))), "too_large"),
        (body(np.tile(GOOD, (6, 20, 1, 1))), "too_large"),
        (b'{"plans": [' + b"0," * 60_000 + b"0]}", "too_large"),
        (body(np.tile(GOOD, (1, 2, 1, 1)), dt=0.02), "bad_dt"),
        (b'{"plans": [[[[NaN,0,0,0,0,0,1],[0,0,0,0,0,0,1]]]]}', "nan_pose"),
        (body(np.tile(GOOD * [1, 1, 1, 5, 5, 5, 5], (1, 2, 1, 1))), "bad_quaternion"),
        (body(np.tile(GOOD, (1, 2, 1, 1)), **{"return": "every:0"}), "bad_request"),
        (body(np.tile(GOOD, (1, 2, 1, 1)), **{"return": "last"}), "bad_request"),
        (body(np.tile(GOOD, (1, 2, 1, 1)), encoding="msgpack"), "bad_request"),
        (body(np.tile(GOOD, (1, 2, 1, 1)), id=[1]), "bad_request"),
        (body(np.tile(GOOD, (1, 2, 1, 1)), plan_count=1), "bad_request"),
        (body(np.tile(GOOD, (1, 2, 1, 1)), **{"return": "none"}), "bad_request"),
        (body(np.tile(GOOD, (1, 2, 1, 1)), cost={"goal": [[0, 0, 0]]}), "bad_shape"),
        (body(np.tile(GOOD, (1, 2, 1, 1)), cost={"weights": {"plane": 1}}), "bad_request"),
        (body(np.tile(GOOD, (1, 2, 1, 1)), cost={"plane_z": 0.1, "weights": {"plane": -1}}), "bad_request"),
        (body(np.tile(GOOD, (1, 2, 1, 1)), cost={"speed": 1}), "bad_request"),
    ],
)
def test_invalid_requests_rejected(est, raw, reason):
    before = dict(est.stats.rejected)
    ok, reply = handle(est, raw)
    assert not ok and json.loads(reply)["error"] == reason
    assert est.stats.rejected[f"predict:{reason}"] == before.get(f"predict:{reason}", 0) + 1


def test_prediction_batched_and_state_untouched(est):
    x_before = est.tracker.state.x.clone()
    plans = np.tile(GOOD, (3, 5, 1, 1))
    plans[1, :, :, 2] -= np.linspace(0, 0.05, 5)[:, None]  # plan 1 lowers both grippers
    ok, reply = handle(est, body(plans, dt=0.01))
    assert ok
    out = json.loads(reply)
    v = np.array(out["vertices"])
    assert v.shape == (3, 5, 13, 3) and out["stamp"] == pytest.approx(T0 / 1e9)
    assert np.array_equal(est.tracker.state.x, x_before)
    np.testing.assert_allclose(v[0], v[2], atol=1e-5)  # same plan, same answer
    assert v[1, -1, 0, 2] == pytest.approx(0.45, abs=1e-4)  # the gripped vertex follows the plan
    # one plan alone gives the same as within the batch
    ok, single = handle(est, body(plans[1:2]))
    np.testing.assert_allclose(np.array(json.loads(single)["vertices"])[0], v[1], atol=2e-5)


def test_rollout_runs_in_the_configured_dtype_and_both_agree(est):
    # float32 is predict's default (faster at planning scale); float64 stays available. They must
    # give the same shapes to well under the estimate's own 0.01 mm resolution of a JSON reply
    from service.geometry import grips_from_poses
    from service.workers import InlineWorker

    plans = np.tile(GOOD, (2, 20, 1, 1))
    plans[1, :, :, 2] -= np.linspace(0, 0.05, 20)[:, None]
    base, _ = predict.snapshot(est)
    out = {}
    for dtype in ("float32", "float64"):
        cfg = est.cfg.model_copy(
            update={"workers": est.cfg.workers.model_copy(update={"predict_dtype": dtype})}
        )
        ctx = InlineWorker(est.model, cfg).ctx
        grips = grips_from_poses(plans, cfg.grippers)
        out[dtype] = predict.rollout(ctx.step, base, grips, ctx.dtype)
    assert out["float32"].dtype == np.float32 and out["float64"].dtype == np.float64
    gap = np.abs(out["float32"] - out["float64"]).max()
    assert 0 < gap < 1e-5, gap  # not the same computation, but the same shapes


def test_no_estimate_yet(model):
    e = Estimator(make_config(), model, OpenLoopTracker(model))
    ok, reply = handle(e, body(np.tile(GOOD, (1, 1, 1, 1))))
    assert not ok and json.loads(reply)["error"] == "no_estimate"


def test_overstretched_plans_flagged(est, model):
    """A plan that pulls the grippers farther apart than the rod is long has no valid shape: the
    reply flags it, and only it."""
    free = float(model.rest_lengths()[1:-1].sum())
    plans = np.tile(GOOD, (2, 5, 1, 1))
    gap = np.linalg.norm(GOOD[1, :3] - GOOD[0, :3])  # the poses; the gripped vertices sit inside them
    plans[1, :, 1, 0] += np.linspace(0, free - gap + 0.2, 5)  # the second gripper pulled out along x
    ok, reply = handle(est, body(plans))
    assert ok and json.loads(reply)["overstretched"] == [False, True]


def test_redone_rollout_steps_counted(est, monkeypatch):
    """Steps the predict rollout redid (its one-graph step left them unconverged; each costs about
    two) reach ``status.counts.predict_steps_redone``."""
    from deform.compiled import RolloutStep

    original = RolloutStep.rollout

    def rollout_redoing_three(self, state, grips):
        self.redone += 3
        return original(self, state, grips)

    monkeypatch.setattr(RolloutStep, "rollout", rollout_redoing_three)
    before = est.status()["counts"].get("predict_steps_redone", 0)
    ok, _ = handle(est, body(np.tile(GOOD, (2, 3, 1, 1))))
    assert ok and est.status()["counts"]["predict_steps_redone"] == before + 3


def test_returned_steps_and_id_and_binary_reply_match_json(est):
    from service import predict_codec

    plans = np.tile(GOOD, (2, 10, 1, 1))
    plans[1, :, :, 2] += np.linspace(0, 0.05, 10)[:, None]
    ok, full = handle(est, body(plans, id="req-7"))
    assert ok
    full = json.loads(full)
    assert full["id"] == "req-7" and "steps" not in full
    all_steps = np.asarray(full["vertices"])
    ok, final = handle(est, body(plans, **{"return": "final"}))
    final = json.loads(final)
    assert final["steps"] == [10] and np.array_equal(np.asarray(final["vertices"]), all_steps[:, 9:])
    ok, every = handle(est, body(plans, **{"return": "every:4"}))
    every = json.loads(every)
    assert every["steps"] == [4, 8, 10]
    assert np.array_equal(np.asarray(every["vertices"]), all_steps[:, [3, 7, 9]])
    ok, raw = handle(est, body(plans, id=3, encoding="binary", **{"return": "every:4"}))
    assert ok and predict_codec.is_binary(raw)
    header, verts = predict_codec.decode(raw)
    assert header["id"] == 3 and header["steps"] == [4, 8, 10] and verts.dtype == np.float32
    assert header["overstretched"] == every["overstretched"]
    assert np.abs(verts - all_steps[:, [3, 7, 9]]).max() < 1e-5  # JSON rounds to 0.01 mm
    assert len(raw) < len(json.dumps(every))


def test_binary_reply_refuses_other_versions_and_truncation():
    from service import predict_codec

    raw = predict_codec.encode(np.zeros((1, 2, 3, 3)), {"id": None})
    assert predict_codec.decode(raw)[1].shape == (1, 2, 3, 3)
    with pytest.raises(predict_codec.CodecError, match="version 2"):
        predict_codec.decode(raw[:4] + (2).to_bytes(2, "little") + raw[6:])
    with pytest.raises(predict_codec.CodecError, match="values for shape"):
        predict_codec.decode(raw[:-4])


def test_binary_request_answers_as_json_and_bad_ones_are_refused(est):
    from service import predict_codec

    plans = np.tile(GOOD, (2, 6, 1, 1))
    plans[1, :, :, 2] += np.linspace(0, 0.05, 6)[:, None]
    ok, as_json = handle(est, body(plans, id=3, **{"return": "final"}))
    for dtype in ("<f8", "<f4"):
        raw = predict_codec.encode_request(plans, {"id": 3, "return": "final"}, dtype=dtype)
        ok, reply = handle(est, raw)
        assert ok and json.loads(reply)["id"] == 3
        atol = 0 if dtype == "<f8" else 1e-5
        assert np.allclose(json.loads(reply)["vertices"], json.loads(as_json)["vertices"], atol=atol, rtol=0)
    raw = predict_codec.encode_request(plans, {})
    bad = [
        raw[:-8],  # truncated
        raw[:4] + (2).to_bytes(2, "little") + raw[6:],  # another version
        predict_codec.encode_request(plans, {"plans": 1}),  # plans in the header
        predict_codec.encode_request(plans[..., :5], {}),  # not (P, S, 2, 7)
        predict_codec.encode_request(np.tile(GOOD, (9, 2, 1, 1)), {}),  # over max_plans
    ]
    reasons = [json.loads(handle(est, b)[1])["error"] for b in bad]
    assert reasons == ["bad_request", "bad_request", "bad_request", "bad_shape", "too_large"]


def test_cost_mode_scores_plans_in_the_worker(est):
    plans = np.tile(GOOD, (3, 10, 1, 1))
    plans[1, :, :, 2] += np.linspace(0, 0.05, 10)[:, None]  # lift 5 cm
    plans[2, :, :, 2] -= np.linspace(0, 0.05, 10)[:, None]  # lower 5 cm
    ok, raw = handle(est, body(plans))
    final = np.asarray(json.loads(raw)["vertices"])[:, -1]  # (P, n, 3)
    goal = final[1]  # the lifted plan's own end shape is the goal
    low = float(final[0, :, 2].min())  # a plane just under the rope's lowest point when held still
    request = {
        "cost": {"goal": goal.tolist(), "plane_z": low + 0.01, "weights": {"plane": 2.0, "stretch": 1.0}}
    }
    ok, raw = handle(est, body(plans, **{"return": "none"}, **request))
    assert ok
    out = json.loads(raw)
    assert "vertices" not in out or np.asarray(out["vertices"]).size == 0
    terms = {k: np.asarray(v) for k, v in out["cost_terms"].items()}
    assert terms["goal"][1] < 1e-4 < terms["goal"][0] < terms["goal"][2]  # lifted = goal; lowered farthest
    assert terms["plane"][2] > terms["plane"][0] > terms["plane"][1] >= 0  # lowering dips into the plane
    assert np.all(terms["stretch"] >= 0) and np.all(terms["stretch"] < 0.01)
    expected = terms["goal"] + 2.0 * terms["plane"] + 1.0 * terms["stretch"]
    assert np.allclose(out["costs"], expected)


def test_plan_cost_stretch_is_the_largest_edge_stretch_over_steps():
    """One plan stretches one edge by 5 % at one step, the other is compressed: 0.05 and 0."""
    from service.plan_cost import parse_cost, plan_costs

    rest = np.full(3, 0.1)
    line = np.stack([np.arange(4) * 0.1, np.zeros(4), np.zeros(4)], axis=-1)  # 4 vertices at rest
    verts = np.repeat(line[None, None], 2, axis=0).repeat(3, axis=1).astype(np.float32)  # (2, 3, 4, 3)
    verts[0, 1, 3:, 0] += 0.005  # plan 0, step 1: the last edge 5 % long
    verts[1, :, 3:, 0] -= 0.02  # plan 1: the last edge 20 % short at every step
    out = plan_costs(verts, rest, parse_cost({"weights": {"stretch": 1.0}}, 4))
    np.testing.assert_allclose(out["cost_terms"]["stretch"], [0.05, 0.0], atol=1e-6)
    np.testing.assert_allclose(out["costs"], [0.05, 0.0], atol=1e-6)


def _five_plans():
    plans = np.tile(GOOD, (5, 20, 1, 1))
    plans[:, :, :, 2] -= np.linspace(0, 0.05, 20)[None, :, None] * np.arange(5)[:, None, None]
    return plans


def _same_reply(a: bytes, b: bytes) -> None:
    """Two replies with the same fields, vertices within the solvers' tolerances and the same costs.
    Why not equal: a block of plans rolls out in another batch, and a step the one-graph step leaves
    unconverged for one rod is redone with the checked step for its whole batch (pbd_tol 1e-3 of a
    9 cm edge is 0.09 mm); the plans differ by centimetres, so a wrong order still fails."""
    from service import predict_codec

    if predict_codec.is_binary(a):
        (ha, va), (hb, vb) = predict_codec.decode(a), predict_codec.decode(b)
    else:
        ha, hb = json.loads(a), json.loads(b)
        va, vb = np.array(ha.pop("vertices")), np.array(hb.pop("vertices"))
    assert va.shape == vb.shape and list(ha) == list(hb)
    np.testing.assert_allclose(va, vb, atol=2e-4)
    np.testing.assert_allclose(ha.get("costs", []), hb.get("costs", []), atol=2e-4)
    assert {k: v for k, v in ha.items() if k not in ("costs", "cost_terms")} == {
        k: v for k, v in hb.items() if k not in ("costs", "cost_terms")
    }


@pytest.mark.parametrize("ret", ["all", "every:6", "none"])
def test_a_request_answered_in_shares_is_the_whole_answer(est, ret):
    """A binary request cut into blocks of 1 + 2 + 2 plans, each answered as a request of its own
    and joined, gives the one-process reply."""
    from service import predict_codec
    from service.workers import InlineWorker

    ctx = InlineWorker(est.model, est.cfg).ctx
    plans = _five_plans()
    fields = {
        "id": "x",
        "return": ret,
        "encoding": "binary",
        "cost": {"goal": np.zeros((est.model.n, 3)).tolist()},
    }
    raw = predict_codec.encode_request(plans, fields)
    base, stamp = predict.snapshot(est)
    whole = predict.answer(ctx, raw, base, stamp)
    assert whole[0]
    shares = predict_codec.split_request(raw, [predict.share(5, i, 3) for i in range(3)])
    assert [predict_codec.request_plans(b) for b in shares] == [1, 2, 2]
    parts = [predict.answer_part(ctx, b, base, stamp) for b in shares]
    joined = predict.assemble(parts)
    assert joined[0]
    _same_reply(joined[1], whole[1])


def test_a_bad_share_is_the_reply_and_a_request_that_does_not_decode_is_not_split():
    """The first share (in plan order) whose parse fails gives the reply's error; a request whose
    data does not match its header is not cut (the process it goes to whole reports that)."""
    from service import predict_codec

    ok = predict.Part(True, header={"id": None, "stamp": 0.0}, shape=(1, 1, 2, 3), overstretched=[False])
    bad = predict.Part(False, b'{"error": "nan_pose"}', "nan_pose", "")
    worse = predict.Part(False, b'{"error": "bad_quaternion"}', "bad_quaternion", "")
    assert predict.assemble([ok, bad, worse])[2] == "nan_pose"
    raw = predict_codec.encode_request(_five_plans(), {})
    assert predict_codec.split_request(raw[:-8], [(0, 2), (2, 5)]) is None
    assert (
        predict_codec.split_request(predict_codec.encode_request(_five_plans()[..., :5], {}), [(0, 5)])
        is None
    )


def test_the_pool_splits_large_binary_requests_only(est):
    """Binary requests of at least ``split_min_plans`` plans go to every process, a share each; a
    smaller one or a JSON one goes to the first process alone."""
    from service import predict_codec
    from service.predict_pool import PredictPool
    from service.workers import InlineWorker

    class Counting(InlineWorker):
        def __init__(self, *a):
            super().__init__(*a)
            self.jobs = []

        def call(self, op, *args, timeout=None):
            self.jobs.append((op, args))
            return super().call(op, *args, timeout=timeout)

    workers = [Counting(est.model, est.cfg) for _ in range(2)]
    pool = PredictPool(workers, split_min_plans=4)
    base, stamp = predict.snapshot(est)
    plans = _five_plans()
    large = predict_codec.encode_request(plans, {"id": 1})
    ok, reply, *_ = pool.predict(large, base, stamp)
    sent = [[(op, predict_codec.request_plans(args[0])) for op, args in w.jobs] for w in workers]
    assert ok and sent == [[("predict", 2)], [("predict", 3)]]  # each process its block of plans alone
    _same_reply(reply, predict.answer(InlineWorker(est.model, est.cfg).ctx, large, base, stamp)[1])
    for w in workers:
        w.jobs.clear()
    for raw in (predict_codec.encode_request(plans[:3], {}), body(plans)):
        pool.predict(raw, base, stamp)
    assert [len(w.jobs) for w in workers] == [2, 0]
    # a bad request of many plans: not cut, the first process finds the error
    ok, reply, reason, *_ = pool.predict(predict_codec.encode_request(plans[..., :5], {}), base, stamp)
    assert not ok and reason == "bad_shape"
    # a bad pose in the second block: that share's error is the reply
    nan = plans.copy()
    nan[4, 0, 0, 0] = np.nan
    ok, reply, reason, *_ = pool.predict(predict_codec.encode_request(nan, {}), base, stamp)
    assert not ok and reason == "nan_pose"
    # more plans than the limits allow: refused before any process is sent a share of it
    for w in workers:
        w.jobs.clear()
    ok, reply = predict_pool.handle(est, predict_codec.encode_request(np.tile(GOOD, (9, 2, 1, 1)), {}), pool)
    assert not ok and json.loads(reply)["error"] == "too_large" and not any(w.jobs for w in workers)
