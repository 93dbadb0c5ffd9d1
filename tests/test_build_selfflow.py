"""Chapter 12's nodes (:mod:`flowmod.extensions.selfflow`) built on the tiny world: quick tests
for mutation testing, which runs only the quick tests (the chapter's own tests build the
smoke world and are slow).

The inputs: the tiny world (conftest's ``tiny_world``: five scenes x 3 keyframes) and its
``select`` node, built here once per module in a run folder of its own. Each node is built
with tiny settings (frames at 1/8 of their size, one or two pairs, two training steps of
one 64 x 128 frame) through the driver's own :class:`flowmod.dag.Build`. Every expected
number is recomputed here from the same inputs: which pairs each role draws (the folds'
columns read by hand, numpy's seeded permutation), the exact flow of those pairs
(:func:`flowmod.world.gt_flow`), each method's errors against it
(:func:`flowmod.flow.metrics.flow_metrics` of the zero flow, DIS, Farneback and the
network's published weights), and the trained weights themselves, trained again here with
:func:`flowmod.flow.selftrain.train_flow` on the pairs and settings the node should use.
The error cases (missing weights, real data, an empty role) are built on hand-made inputs.
"""

from __future__ import annotations

import contextlib
import io
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import torch
from conftest import shared_scope

from flowmod import dag, pipeline
from flowmod.extensions import selfflow
from flowmod.flow import selftrain
from flowmod.flow.estimators import DISFlow, FarnebackFlow
from flowmod.flow.metrics import flow_metrics
from flowmod.flow.networks import FastFlowNetFlow
from flowmod.flow.registry import read_image
from flowmod.params import load_profile
from flowmod.paths import repo_root
from flowmod.world import gt_flow

#: The frame scale of every flow here (frames of 900 x 1600 px read at 112 x 200).
SCALE = 0.125
#: The selfflow settings of every node built here: tiny, and each value one the tests check.
TINY = dict(device="cpu", flow_scale=SCALE, selfflow_iters=2, selfflow_batch=1,
            selfflow_crop=[64, 128], selfflow_window="frame", selfflow_lr=1e-3,
            selfflow_smooth=2.0, selfflow_warmup=1, selfflow_pairs=1, selfflow_eval_pairs=1,
            selfflow_eval_every=0)
#: The reference methods, in the order the nodes list them.
REFERENCES = ["zero flow", "farneback", "dis (medium)"]
METRICS = ["epe", "epe_boxes", "fl_all", "fl_all_boxes", "bias_boxes"]
#: The files a selfflow node publishes, and the columns of its history per mode.
FILES = ["eval.json", "history.csv", "weights.pt"]
VAL = ["val_seconds_per_pair", "val_epe", "val_epe_boxes", "val_fl_all", "val_fl_all_boxes",
       "val_bias_boxes"]
PHOTO = ["loss", "photometric", "smoothness", "warm-up", "seconds"]


# --- inputs and independent recomputation -------------------------------------------------

@pytest.fixture(scope=shared_scope)
def tiny(tiny_world, tmp_path_factory):
    """The smoke profile on the tiny world with the tiny selfflow settings, its world and
    select nodes built."""
    from conftest import TINY_WORLD

    root, version = tiny_world
    p = load_profile("smoke", dataroot=str(root), version=version, n_jobs=1,
                     run_dir=str(tmp_path_factory.mktemp("selfflow") / "runs"),
                     **TINY_WORLD, **TINY)
    pipeline.GRAPH.build_node(p, dag.Node("world"))
    pipeline.GRAPH.build_node(p, dag.Node("select"))
    return p


def _select(p):
    sel = pipeline.published(p, dag.Node("select"))
    return pd.read_parquet(sel / "pairs.parquet"), pd.read_parquet(sel / "objects.parquet")


def _role(pairs, role):
    """Fold 0's rows of one role, read by hand: fold 0's scenes test, the other folds'
    validation scenes validate, the rest train."""
    r = np.where(pairs["fold"] == 0, "test", np.where(pairs["val_scene"], "val", "train"))
    return pairs[r == role]


def _draw(df, n, stream):
    """``n`` rows of ``df`` drawn by numpy's permutation seeded with ``stream``, in order."""
    idx = np.sort(np.random.default_rng(list(stream)).permutation(len(df))[:n])
    return df.iloc[idx].reset_index(drop=True)


_TRUTH: dict[str, tuple] = {}


def _truth(p, row, objects):
    """(exact flow, valid, boxes) of one pair, from the world's truth and the objects."""
    key = f"{p.dataroot_path}/{row.pair_id}"
    if key not in _TRUTH:
        flow, valid = gt_flow(p.dataroot_path, p.version, row.sd_token_1, row.sd_token_2)
        boxes = objects.loc[objects["pair_id"] == row.pair_id,
                            ["xmin", "ymin", "xmax", "ymax"]].to_numpy(float)
        _TRUTH[key] = (flow, valid, boxes)
    return _TRUTH[key]


def _images(p, row):
    return read_image(p.dataroot_path / row.path_1), read_image(p.dataroot_path / row.path_2)


def _errors(p, estimate, rows, objects):
    """flow_metrics of ``estimate`` on each pair of ``rows``, and the flows it gave."""
    out, flows = [], []
    for r in rows.itertuples():
        flow = estimate(*_images(p, r))
        gt, valid, boxes = _truth(p, r, objects)
        out.append(flow_metrics(flow, gt, valid, boxes))
        flows.append(flow)
    return out, flows


def _mean(rows):
    return {k: float(np.nanmean([r[k] for r in rows])) for k in METRICS}


def _estimators():
    return {"zero flow": lambda a, b: np.zeros((*a.shape[:2], 2), np.float32),
            "farneback": FarnebackFlow(scale=SCALE).estimate,
            "dis (medium)": DISFlow("medium", scale=SCALE).estimate}


def _close(got, want):
    """The metrics in ``got`` equal ``want``'s (float32 sums: to 1e-5)."""
    assert {k: got[k] for k in METRICS} == pytest.approx(want, rel=1e-5, abs=1e-6)


# --- the selfflow nodes -------------------------------------------------------------------

#: Per mode: (settings beyond TINY, progress shown).
MODES = {"photometric": ({"selfflow_eval_every": 1, "force": True}, True),
         "supervised": ({}, True),
         "finetune": ({}, False)}


@pytest.fixture(scope=shared_scope)
def built(tiny):
    """Each mode's node built by :func:`selfflow.build` (the photometric one with
    ``force`` and a stray file in its building folder): per mode (params, returned info,
    files, history, evaluation, state_dict, what it printed)."""
    out = {}
    for mode, (more, progress) in MODES.items():
        q = tiny.model_copy(update=more)
        b = pipeline.GRAPH.begin(q, dag.Node("selfflow", None, mode))
        b.dir.mkdir(parents=True, exist_ok=True)
        (b.dir / "stray.txt").write_text("left by a killed build")
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            info = selfflow.build(b, progress)
        hist, ev = selfflow.read_selfflow(b.dir)
        weights = torch.load(selfflow.selfflow_weights(b.dir), weights_only=True)
        out[mode] = SimpleNamespace(q=q, info=info, files=sorted(f.name for f in b.dir.iterdir()),
                                    hist=hist, ev=ev, weights=weights, err=err.getvalue())
    return out


def _train_pairs(p, mode):
    pairs, _ = _select(p)
    return _draw(_role(pairs, "test" if mode == "finetune" else "train"), p.selfflow_pairs,
                 (p.seed, 0))


def test_each_mode_trains_on_its_role_s_pairs_and_reports_them(tiny, built):
    """train_pairs and train_scenes: photometric and supervised draw from fold 0's training
    scenes, finetune from its test scenes (a user's own unlabelled frames); the validation
    and test pairs are counted; the node returns its mode and steps; its building folder
    starts afresh only with ``force``."""
    pairs, _ = _select(tiny)
    assert not set(_role(pairs, "train")["scene"]) & set(_role(pairs, "test")["scene"])
    for mode, r in built.items():
        train = _train_pairs(tiny, mode)
        assert r.info == {"mode": mode, "steps": 2}
        assert len(train) == 1 and (r.ev["mode"], r.ev["steps"], r.ev["train_pairs"]) == (mode, 2, 1)
        assert r.ev["train_scenes"] == sorted(set(train["scene"]))
        assert (r.ev["val_pairs"], r.ev["heldout_pairs"]) == (1, 1)
        # a killed build's folder is kept (resumed) unless forced; no gt/ or last.pt is left
        assert r.files == sorted([*FILES, *([] if r.q.force else ["stray.txt"])]), mode


def test_history_has_a_row_per_step_with_evaluations_where_asked(built):
    """history.csv: step 0 (the untrained network's validation error), then one row per
    step with its loss's parts; the validation columns at every ``selfflow_eval_every``
    steps and at the last; the photometric mode's first ``selfflow_warmup`` steps use the
    warm-up distance; supervised rows hold the end-point error."""
    photo, sup, fine = (built[m].hist for m in ("photometric", "supervised", "finetune"))
    assert photo.columns.tolist() == ["step", *VAL, *PHOTO]
    assert fine.columns.tolist() == ["step", *VAL, *PHOTO]
    assert sup.columns.tolist() == ["step", *VAL, "loss", "epe", "seconds"]
    for h in (photo, sup, fine):
        assert h["step"].tolist() == [0, 1, 2] and h["loss"].iloc[1:].notna().all()
    assert photo["val_epe"].notna().tolist() == [True, True, True]  # eval_every 1
    assert fine["val_epe"].notna().tolist() == [True, False, True]  # eval_every 0: the end
    assert photo["warm-up"].tolist()[1:] == [1.0, 0.0]
    assert fine["warm-up"].tolist()[1:] == [0.0, 0.0], "finetune: census from the first step"
    for r in built.values():
        assert r.ev["seconds_per_step"] == pytest.approx(r.hist["seconds"].median(), rel=1e-12)


def test_the_weights_are_those_of_the_modes_training_on_its_pairs(tiny, built):
    """weights.pt is the network :func:`selftrain.train_flow` trains on the mode's pairs at
    flow_scale with the profile's settings (finetune: from ``selfflow_init``; supervised:
    on the pairs' exact flow), as a float32 state_dict on the CPU."""
    for mode, r in built.items():
        q, train = r.q, _train_pairs(tiny, mode)
        root = q.dataroot_path
        work = q.run_path / "again" / mode
        gt = (selftrain.cache_gt(train, root, q.version, SCALE, work / "gt", False)
              if mode == "supervised" else None)
        data = selftrain.FramePairs([(root / a, root / b) for a, b in
                                     zip(train["path_1"], train["path_2"], strict=True)],
                                    SCALE, gt)
        model, hist = selftrain.train_flow(
            data, mode, work, iters=2, batch=1, lr=1e-3, crop=[64, 128], smooth=2.0, seed=0,
            progress=False, window="frame", warmup=1 if mode == "photometric" else 0,
            init=repo_root() / "weights/fastflownet_synth/weights.pt"
            if mode == "finetune" else None)
        want = model.state_dict()
        assert list(r.weights) == list(want)
        for k, v in want.items():
            assert r.weights[k].dtype == v.dtype and torch.equal(r.weights[k], v), (mode, k)
        assert r.hist["loss"].iloc[1:].tolist() == pytest.approx(hist["loss"].tolist(),
                                                                 rel=1e-6)


def _held(p, n_role, stream):
    pairs, objects = _select(p)
    return _draw(_role(pairs, n_role), p.selfflow_eval_pairs, stream), objects


def test_validation_and_test_errors_are_the_networks_and_the_baselines(tiny, built):
    """eval.json: the network's last validation row and its test error equal the published
    weights' errors against the exact flow on the validation (seed, 2) and test (seed, 1)
    pairs; the baselines' are the zero flow's, Farneback's and DIS's on the same pairs."""
    val, objects = _held(tiny, "val", (tiny.seed, 2))
    test, _ = _held(tiny, "test", (tiny.seed, 1))
    base = {name: (_mean(_errors(tiny, est, val, objects)[0]),
                   _mean(_errors(tiny, est, test, objects)[0]))
            for name, est in _estimators().items()}
    for r in built.values():
        net = FastFlowNetFlow(r.weights, device="cpu", scale=SCALE).estimate
        on_val, on_test = (_mean(_errors(tiny, net, d, objects)[0]) for d in (val, test))
        _close(r.ev["validation"]["fastflownet"], on_val)
        last = r.hist.iloc[-1]
        assert r.ev["validation"]["fastflownet"] == pytest.approx({k[4:]: last[k] for k in VAL})
        _close(r.ev["fastflownet"], on_test)
        assert sorted(r.ev["baselines"]) == sorted(r.ev["validation"]["baselines"]) \
            == sorted(REFERENCES)
        for name, (v, t) in base.items():
            _close(r.ev["validation"]["baselines"][name], v)
            _close(r.ev["baselines"][name], t)
    assert base["zero flow"][0] != pytest.approx(base["zero flow"][1]), "two different pairs"


def test_finetune_starts_from_the_shipped_weights_and_photometric_from_scratch(tiny, built):
    """Step 0's validation error: the file ``selfflow_init`` names for finetune (and
    :func:`selfflow.init_weights` is that file), an untrained network for the others."""
    val, objects = _held(tiny, "val", (tiny.seed, 2))
    shipped = repo_root() / "weights/fastflownet_synth/weights.pt"
    assert selfflow.init_weights(dag.StageParams(tiny, dag.Node("selfflow", None,
                                                                "finetune"))) == shipped
    start = FastFlowNetFlow(shipped, device="cpu", scale=SCALE).estimate
    want = _mean(_errors(tiny, start, val, objects)[0])
    step0 = {k[4:]: v for k, v in built["finetune"].hist.iloc[0].items() if k in VAL}
    _close(step0, want)
    assert built["photometric"].hist["val_epe"].iloc[0] != pytest.approx(want["epe"], rel=1e-3)


def test_progress_shows_the_training_and_exact_flow_bars_only_when_asked(built):
    """With progress, the training bar names the mode, and only the supervised mode caches
    the exact flow of its training pairs; without, nothing is printed."""
    assert "train fastflownet (photometric)" in built["photometric"].err
    assert "exact flow of the training pairs" not in built["photometric"].err
    assert "train fastflownet (supervised)" in built["supervised"].err
    assert "exact flow of the training pairs" in built["supervised"].err
    assert built["finetune"].err == ""


# --- the selfflow node's checks on hand-made inputs ---------------------------------------

def _handmade_build(p, node, tmp_path, pairs=None, objects=None):
    """A Build of ``node`` whose select input is a folder of the given tables."""
    sel = tmp_path / "select"
    sel.mkdir(exist_ok=True)
    for name, df in (("pairs", pairs), ("objects", objects)):
        if df is not None:
            df.to_parquet(sel / f"{name}.parquet", index=False)
    graph = SimpleNamespace(node_dir=lambda params, n: sel)
    return dag.Build(graph=graph, node=node, params=dag.StageParams(p, node),
                     inputs={"world": {}, "select": {}}, payload={}, fingerprint="f",
                     final=tmp_path / "runs" / str(node), up_to_date=False)


def _real_data(tiny, tmp_path):
    """The profile on a dataroot without a generated world (read as real nuScenes)."""
    (tmp_path / "real" / tiny.version).mkdir(parents=True)
    return tiny.model_copy(update={"dataroot": str(tmp_path / "real"), "synthetic": False})


def test_supervised_needs_a_generated_world_and_others_need_every_role(tiny, tmp_path):
    """On real data the supervised mode stops with one line; the photometric mode goes on
    and stops, before any work, where a role has no pair (here: no validation scene)."""
    real = _real_data(tiny, tmp_path)
    assert real.dataroot_path == tmp_path / "real"
    node = dag.Node("selfflow", None, "supervised")
    with pytest.raises(selftrain.SelfFlowError) as e:
        selfflow.build(_handmade_build(real, node, tmp_path), False)
    assert str(e.value) == (
        f"selfflow_modes has 'supervised', but {tmp_path / 'real'} ({tiny.version}) is not a "
        "generated world: there is no exact flow to supervise with; use "
        "selfflow_modes=[photometric]")
    pairs, objects = _select(tiny)
    no_val = pairs[~pairs["val_scene"].astype(bool) | (pairs["fold"] == 0)]
    test = _role(no_val, "test")
    assert len(test) > 1 and len(_role(no_val, "train")) > 0 and _role(no_val, "val").empty
    node = dag.Node("selfflow", None, "photometric")
    b = _handmade_build(real.model_copy(update={"selfflow_eval_pairs": 2}), node, tmp_path,
                        no_val, objects)
    with pytest.raises(selftrain.SelfFlowError) as e:
        selfflow.build(b, False)
    assert str(e.value) == ("no training (1), validation (0) or test (2) pair in chapter 02's "
                            "selection: run chapter 02 first")
    assert not b.dir.exists(), "nothing is started"


def test_init_weights_names_the_file_or_says_how_to_make_it(tiny, tmp_path):
    """init_weights: the path ``selfflow_init`` names (relative to the repository, or
    absolute); a missing file is one line naming it and ``make flownet``."""
    node = dag.Node("selfflow", None, "finetune")
    other = tmp_path / "mine.pt"
    other.write_bytes(b"x")
    got = selfflow.init_weights(dag.StageParams(
        tiny.model_copy(update={"selfflow_init": str(other)}), node))
    assert got == other
    missing = tmp_path / "none.pt"
    with pytest.raises(selftrain.SelfFlowError) as e:
        selfflow.init_weights(dag.StageParams(
            tiny.model_copy(update={"selfflow_init": str(missing)}), node))
    assert str(e.value) == (f"selfflow_init={missing}: no such file ({missing}); `make flownet` "
                            "makes the shipped weights, or name another FastFlowNet state_dict")


# --- the shipped node ---------------------------------------------------------------------

def _clock():
    """A perf_counter that advances one second per call: each estimator call takes 1 s."""
    t = iter(range(10**6))
    return SimpleNamespace(perf_counter=lambda: float(next(t)))


@pytest.fixture(scope=shared_scope)
def shipped(tiny):
    """The shipped node built by :func:`selfflow.build_shipped` on two pairs (a stray file
    in its building folder), with a clock of one second per estimator call."""
    q = tiny.model_copy(update={"selfflow_eval_pairs": 2})
    b = pipeline.GRAPH.begin(q, dag.Node("shipped"))
    b.dir.mkdir(parents=True, exist_ok=True)
    (b.dir / "stray.txt").write_text("left by a killed build")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(selftrain, "time", _clock())
        info = selfflow.build_shipped(b, False)
    table, per_pair = selfflow.read_shipped(b.dir)
    return SimpleNamespace(q=q, dir=b.dir, info=info, table=table, per_pair=per_pair,
                           example=selfflow.read_shipped_example(b.dir))


def _shipped_pick(q):
    pairs, objects = _select(q)
    return _draw(pairs[pairs["set"] == "keyframe"], 2, (q.seed, 12)), objects


def test_shipped_node_scores_every_method_on_the_seeds_keyframe_pairs(shipped):
    """world.parquet: one row per method (the references, then the shipped weights) with its
    mean errors against the exact flow on the keyframe pairs drawn with (seed, 12), and
    seconds per pair (here 1: one clock second per call); pairs.parquet: each pair's."""
    q = shipped.q
    pick, objects = _shipped_pick(q)
    assert len(pick) == 2 and shipped.info == {"pairs": 2, "exact_flow": True}
    ests = {**_estimators(), selftrain.SHIPPED: FastFlowNetFlow(
        repo_root() / "weights/fastflownet_synth/weights.pt", device="cpu", scale=SCALE).estimate}
    assert shipped.table.columns.tolist() == ["method", *METRICS, "seconds_per_pair"]
    assert shipped.table["method"].tolist() == list(ests)
    assert shipped.per_pair.columns.tolist() == ["pair_id", "scene", "path_1", "method", "epe",
                                                 "epe_boxes"]
    assert shipped.table["seconds_per_pair"].tolist() == [1.0] * 4
    for i, (name, est) in enumerate(ests.items()):
        rows, _ = _errors(q, est, pick, objects)
        _close(shipped.table.iloc[i].to_dict(), _mean(rows))
        mine = shipped.per_pair.iloc[2 * i:2 * i + 2]
        assert mine["method"].tolist() == [name, name]
        for c in ("pair_id", "scene", "path_1"):
            assert mine[c].tolist() == pick[c].tolist()
        for k in ("epe", "epe_boxes"):
            assert mine[k].tolist() == pytest.approx([r[k] for r in rows], rel=1e-5)
    assert sorted(f.name for f in shipped.dir.iterdir()) == [
        "example.npz", "pairs.parquet", "world.parquet"], "a fresh folder"
    for name in ("world.parquet", "pairs.parquet"):
        assert "__index_level_0__" not in pq.read_schema(shipped.dir / name).names


def test_shipped_example_holds_the_first_pairs_flows_in_float16(shipped):
    """example.npz: the first drawn pair's exact flow, valid mask (bool), DIS's and the
    shipped network's flow of that pair (not of the last pair), each float16."""
    q = shipped.q
    pick, objects = _shipped_pick(q)
    ex = shipped.example
    assert sorted(ex) == sorted(["exact", "valid", "dis (medium)", selftrain.SHIPPED])
    gt, valid, _ = _truth(q, next(pick.itertuples()), objects)
    assert ex["valid"].dtype == bool and np.array_equal(ex["valid"], valid)
    assert ex["exact"].dtype == np.float16
    np.testing.assert_array_equal(ex["exact"], gt.astype(np.float16))
    first = next(pick.itertuples())
    net = FastFlowNetFlow(repo_root() / "weights/fastflownet_synth/weights.pt", device="cpu",
                          scale=SCALE)
    for name, est in (("dis (medium)", DISFlow("medium", scale=SCALE)), (selftrain.SHIPPED, net)):
        want = est.estimate(*_images(q, first)).astype(np.float16)
        assert ex[name].dtype == np.float16
        np.testing.assert_allclose(ex[name].astype(np.float32), want.astype(np.float32),
                                   rtol=2e-3, atol=2e-3)


def test_shipped_node_on_real_data_writes_empty_tables(tiny, tmp_path):
    """Without exact flow (real nuScenes) the node writes empty tables and an empty example,
    in a fresh folder, and says so."""
    real = _real_data(tiny, tmp_path)
    b = _handmade_build(real, dag.Node("shipped"), tmp_path)
    b.dir.mkdir(parents=True)
    (b.dir / "stray.txt").write_text("x")
    assert selfflow.build_shipped(b, False) == {"pairs": 0, "exact_flow": False}
    assert sorted(f.name for f in b.dir.iterdir()) == ["example.npz", "pairs.parquet",
                                                       "world.parquet"]
    table, per_pair = selfflow.read_shipped(b.dir)
    assert table.shape == per_pair.shape == (0, 0)
    assert selfflow.read_shipped_example(b.dir) == {}


def test_shipped_node_without_its_weights_says_how_to_make_them(tiny, tmp_path):
    """A missing ``shipped_weights`` file: one line naming it and ``make flownet``; nothing
    is started."""
    missing = tmp_path / "none.pt"
    q = tiny.model_copy(update={"shipped_weights": str(missing)})
    b = _handmade_build(q, dag.Node("shipped"), tmp_path)
    with pytest.raises(selftrain.SelfFlowError) as e:
        selfflow.build_shipped(b, False)
    assert str(e.value) == (f"shipped_weights={missing}: no such file ({missing}); "
                            "`make flownet` makes the shipped weights")
    assert not b.dir.exists()


def test_keep_first_passes_the_flow_through_and_keeps_the_first(tmp_path):
    """_keep_first: the estimator's flow of each call, its first call's kept by name."""
    calls = []

    def est(a, c):
        calls.append((a, c))
        return a - c
    flows = {}
    run = selfflow._keep_first(est, flows, "m")
    one, two = np.ones((2, 2)), np.full((2, 2), 5.0)
    np.testing.assert_array_equal(run(two, one), two - one)
    np.testing.assert_array_equal(run(one, two), one - two)
    assert calls[0][0] is two and calls[0][1] is one
    assert list(flows) == ["m"] and np.array_equal(flows["m"], two - one)


def test_the_stages_declare_their_nodes_inputs_gate_and_files(tiny):
    """SHIPPED_STAGE: one node, always built; STAGE: one node per mode, gated by
    selfflow_build; both read the world and the selection."""
    s, t = selfflow.SHIPPED_STAGE, selfflow.STAGE
    assert [str(n) for n in s.nodes(tiny)] == ["shipped"]
    assert [str(n) for n in t.nodes(tiny.model_copy(update={"selfflow_modes": ["finetune",
                                                                                "photometric"]}))
            ] == ["selfflow[finetune]", "selfflow[photometric]"]
    for stage in (s, t):
        assert stage.inputs(dag.Node(stage.name), tiny) == (dag.Node("world"), dag.Node("select"))
    assert (s.build, t.build, t.gate, s.gate) == (selfflow.build_shipped, selfflow.build,
                                                  "selfflow_build", None)
    assert (s.chapter, t.chapter, s.folder, t.folder) == ("12", "12", "selfflow/shipped",
                                                          "selfflow/{part}")
    assert s.outputs == ("world.parquet", "pairs.parquet", "example.npz")
    assert t.outputs == ("weights.pt", "history.csv", "eval.json")
