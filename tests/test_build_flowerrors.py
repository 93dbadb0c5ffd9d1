"""Chapter 13's stages (:mod:`flowmod.extensions.flowerrors`: ``elevels``, ``etrain``,
``eevaluate``) built on hand-made published inputs, and the geometry their batches rest on:
quick tests for mutation testing, which runs only the quick tests.

The inputs are written here by hand into a tmp run folder, each with a manifest: the exact
flow's ``crops[gt/keyframe]`` node (two folds stored as ``f0``/``f1``: ``<split>.npy``
(N, 2, S, S) float16 px and ``<split>.parquet``, :mod:`flowmod.crops`' format) and
chapter 10's ``context[keyframe]`` node (``<split>.static.npy``, ``.deployed.npy``,
``.images.npy`` and ``.parquet``, :mod:`flowmod.extensions.context`'s format). Each object's
crop is a still-world gradient plus, inside its box, a motion of its own (magnitudes 0.3 to 6
px), so a level matched on some objects is another than on others. The ``elevels`` nodes'
``levels.json`` of the ``etrain`` and ``eevaluate`` runs are written by hand too, with levels
chosen here. Every expected number is computed here from those arrays with numpy: the
degraded crops each split is read as, the levels that reach the targets on the objects drawn
with the seed, the realised errors, the rows each model scores. The classifiers train one
epoch at width 4 on 16 px crops (about a second each).
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from conftest import shared_scope
from handmade import node_folder

from flowmod import pipeline
from flowmod.artefacts import read_manifest
from flowmod.dag import Node
from flowmod.extensions import flowerrors as fe
from flowmod.params import Params, load_profile

S, SCALE, SEED = 16, 2.0, 20
#: Scenes of each fold (the last one of each validates), objects per scene.
SCENES, PER_SCENE = 3, 4
PER_FOLD = SCENES * PER_SCENE
#: The hand-made levels of the ``etrain``/``eevaluate`` runs, per kind and target index.
LEVELS = {"noise": [0.3, 0.7], "pull": [0.6, 1.0], "scale": [0.25, 1.0]}


# --- the hand-made inputs -----------------------------------------------------------------------


def _split(fold: int) -> dict[str, np.ndarray | pd.DataFrame]:
    """One fold's objects: their index, exact-flow crops (float16 as stored), still-world and
    deployed-depth flow crops."""
    rng = np.random.default_rng(100 + fold)
    n = PER_FOLD
    w = rng.uniform(5, 14, n)
    h = w * rng.uniform(0.5, 1.0, n)
    x0, y0 = rng.uniform(10, 1500, n), rng.uniform(300, 600, n)
    boxes = np.stack([x0, y0, x0 + w, y0 + h], axis=1)
    scene = np.repeat(np.arange(SCENES), PER_SCENE) + SCENES * fold
    df = pd.DataFrame({"ann_token": [f"f{fold}-{i}" for i in range(n)],
                       "pair_id": [f"pair-{fold}-{i // 2}" for i in range(n)],
                       "scene": [f"scene-{s}" for s in scene], "split": f"f{fold}",
                       "fold": fold, "val_scene": scene % SCENES == SCENES - 1,
                       "label": np.arange(n) % 2, "xmin": boxes[:, 0], "ymin": boxes[:, 1],
                       "xmax": boxes[:, 2], "ymax": boxes[:, 3]})
    yy, xx = np.mgrid[0:S, 0:S] / S
    still = np.stack([1.5 * xx + 0.3 * np.sin(9 * yy), 0.5 * yy + 0.2 * np.cos(7 * xx)])
    still = still[None] * rng.uniform(0.5, 2.0, (n, 1, 1, 1))
    box = fe.box_masks(boxes, S, SCALE)
    size = rng.uniform(0.3, 6.0, n) * (np.arange(n) % 2)  # the movers' own motion, px
    angle = rng.uniform(0, 2 * np.pi, n)
    own = np.stack([np.cos(angle), np.sin(angle)], axis=1)[:, :, None, None] * size[:, None,
                                                                                      None, None]
    flow = (still + own * box[:, None]).astype(np.float16)
    return {"df": df, "flow": flow, "still": still.astype(np.float16),
            "deployed": (0.5 * still + 1.0).astype(np.float16)}


SPLITS = {f"f{k}": _split(k) for k in range(2)}


def _clean(split: str) -> np.ndarray:
    return SPLITS[split]["flow"].astype(np.float32)


def _box(split: str) -> np.ndarray:
    df = SPLITS[split]["df"]
    return fe.box_masks(df[["xmin", "ymin", "xmax", "ymax"]].to_numpy(), S, SCALE)


def _write_crops(folder, shuffle_context: bool = False) -> None:
    """The crops node's and the context node's files of both folds into ``folder`` (a pair
    of folders: crops, context)."""
    crops, ctx = folder
    for d in folder:
        d.mkdir(parents=True, exist_ok=True)
    for split, s in SPLITS.items():
        np.save(crops / f"{split}.npy", s["flow"])
        s["df"].to_parquet(crops / f"{split}.parquet", index=False)
        cdf = s["df"].iloc[::-1] if shuffle_context else s["df"]
        np.save(ctx / f"{split}.static.npy", s["still"])
        np.save(ctx / f"{split}.deployed.npy", s["deployed"])
        np.save(ctx / f"{split}.images.npy", np.zeros((PER_FOLD, 6, S, S), np.uint8))
        cdf.to_parquet(ctx / f"{split}.parquet", index=False)


def _params(root, **over) -> Params:
    """The smoke profile, shrunk: two folds, one seed, 1 epoch at width 4."""
    kw = {"run_dir": str(root / "runs"), "dataroot": str(root / "data"), "seed": SEED,
          "folds": 2, "seeds": 1, "crop_scale": SCALE, "error_kinds": ["noise", "pull", "scale"],
          "error_targets": [0.5, 1000.0], "error_calibration": 10, "error_folds": 2,
          "error_width": 4, "epochs": 1, "batch_size": 4, "device": "cpu", "n_jobs": 1,
          **over}
    return load_profile("smoke", **kw)


def _publish_inputs(p: Params, levels: dict | None = None) -> None:
    """The published crops and context nodes (and, given, each kind's ``levels.json``)."""
    crops = node_folder(p, Node("crops", "gt", "keyframe"))
    ctx = node_folder(p, Node("context", None, "keyframe"))
    _write_crops((crops, ctx))
    for kind, lv in (levels or {}).items():
        rec = {"kind": kind, "levels": lv, "targets": list(p.error_targets)}
        (node_folder(p, Node("elevels", "gt", kind)) / fe.LEVELS_FILE).write_text(json.dumps(rec))


@pytest.fixture(scope=shared_scope)
def inputs(tmp_path_factory):
    """(crops folder, context folder) of the hand-made objects, no run around them."""
    root = tmp_path_factory.mktemp("fe_inputs")
    dirs = (root / "crops", root / "context")
    _write_crops(dirs)
    return dirs


# --- the geometry of a batch -------------------------------------------------------------------


def test_box_masks_follow_the_crop_scale() -> None:
    """A box of 8 px at scale 2 fills crop columns and rows 3..11 of 16 (window x0 = 97,
    y0 = 47, n = 16: one crop px per frame px); at scale 3 fewer."""
    m = fe.box_masks(np.array([[100.0, 50.0, 108.0, 58.0]]), 16, 2.0)[0]
    want = np.zeros((16, 16), bool)
    want[3:12, 3:12] = True
    assert np.array_equal(m, want)
    assert fe.box_masks(np.array([[100.0, 50.0, 108.0, 58.0]]), 16, 3.0)[0].sum() == 7 * 7


def test_a_box_wider_than_its_window_is_clipped_at_the_crop_edge() -> None:
    """At scale 1 a 10.4 px box has a window of 10 px starting at 101: the mask starts at
    column 0 (not cut off, not wrapped) and spans rows 2..7 of the 5 px tall box."""
    m = fe.box_masks(np.array([[100.0, 50.0, 110.4, 55.0]]), 10, 1.0)[0]
    want = np.zeros((10, 10), bool)
    want[2:8, :] = True
    assert np.array_equal(m, want)


def test_integer_boxes_give_the_masks_of_the_same_float_boxes() -> None:
    """uint8 boxes ending at 255 (whose ``+ 1`` would wrap in uint8) mask as floats do."""
    b = np.array([[200, 100, 255, 150]], np.uint8)
    m = fe.box_masks(b, 40, 3.0)
    assert m.any() and np.array_equal(m, fe.box_masks(b.astype(float), 40, 3.0))


def test_crop_batch_holds_the_still_flow_and_the_windows_of_its_scale() -> None:
    """The batch keeps the still-world flow (float32) and the windows of its own scale,
    x0 y0 n by hand; without still-world flow it has none and builds all the same."""
    boxes = np.array([[100.0, 50.0, 108.0, 58.0], [10.0, 20.0, 14.0, 30.0]])
    flow = np.arange(2 * 2 * 16 * 16, dtype=np.float16).reshape(2, 2, 16, 16) / 100
    still = -flow
    b = fe.crop_batch(flow, boxes, 2.0, still)
    assert b.windows.tolist() == [[97, 47, 16], [3, 16, 20]]
    assert b.still.dtype == np.float32 and np.array_equal(b.still, still.astype(np.float32))
    assert np.array_equal(b.box, fe.box_masks(boxes, 16, 2.0))
    bare = fe.crop_batch(flow, boxes, 2.0)
    assert bare.still is None and bare.windows.tolist() == [[97, 47, 16], [3, 16, 20]]


def test_outlier_directions_are_uniform_over_the_circle() -> None:
    """Every outlier is 16 px long, its direction spread evenly over 8 sectors of the full
    circle (12.5 % each, within 3 points over 6400 pixels)."""
    d = fe.outliers(np.zeros((4, 2, 40, 40)), 1.0, 5)
    assert np.allclose(np.hypot(d[:, 0], d[:, 1]), fe.OUTLIER_PX, rtol=1e-5)
    angle = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
    share = np.histogram(angle, bins=8, range=(0, 2 * np.pi))[0] / angle.size
    assert np.abs(share - 0.125).max() < 0.03


def test_nearest_cells_left_of_the_frame_origin_are_averaged() -> None:
    """A window from frame px (-30, -20) (one crop px per frame px) at k = 8, nearest: each
    pixel takes the mean of its frame cell's pixels inside the crop (cells start at
    multiples of 8 frame px, negative ones too)."""
    rng = np.random.default_rng(2)
    f = rng.normal(size=(1, 2, 40, 40)).astype(np.float32)
    got = fe.lost_resolution(f, 8, np.array([[-30, -20, 40]]), upsample="nearest")
    cx = np.floor((np.arange(40) - 30 + 0.5) / 8).astype(int)
    cy = np.floor((np.arange(40) - 20 + 0.5) / 8).astype(int)
    want = np.empty_like(f)
    for a in np.unique(cy):
        for b in np.unique(cx):
            cell = np.ix_(cy == a, cx == b)
            for c in range(2):
                want[0, c][cell] = f[0, c][cell].mean()
    assert np.allclose(got, want, atol=1e-6)


# --- the degraded crops each split is read as ---------------------------------------------------


def _reader(inputs, kind: str, target: int, level: float):
    q = _params(inputs[0].parent)
    return fe.degraded_reader(q, inputs[0], inputs[1], kind, target, level)


def test_the_exact_arm_reads_the_stored_crops_unchanged(inputs) -> None:
    """The exact arm: the stored float16 crops as float32, the index as stored."""
    [x], df = _reader(inputs, fe.EXACT, 0, 0.0)("f1")
    assert np.array_equal(x, _clean("f1"))
    pd.testing.assert_frame_equal(df, SPLITS["f1"]["df"])


def test_noise_is_drawn_from_the_split_s_own_generator(inputs) -> None:
    """Noise at sigma on split f1 of target 1: the draw of the generator of (seed, noise,
    1, f1); the same again on a second read, another draw on f0."""
    read = _reader(inputs, "noise", 1, 0.7)
    [x], df = read("f1")
    z = fe._split_rng(SEED, "noise", 1, "f1").standard_normal((PER_FOLD, 2, S, S), np.float32)
    assert np.allclose(x, _clean("f1") + np.float32(0.7) * z, atol=1e-6)
    assert np.array_equal(read("f1")[0][0], x)
    assert df["ann_token"].tolist() == SPLITS["f1"]["df"]["ann_token"].tolist()
    z0 = fe._split_rng(SEED, "noise", 1, "f0").standard_normal((PER_FOLD, 2, S, S), np.float32)
    assert np.allclose(read("f0")[0][0], _clean("f0") + np.float32(0.7) * z0, atol=1e-6)


def test_the_pull_reads_the_annotated_still_world_flow_in_the_box(inputs) -> None:
    """The pull at alpha: the box's flow moved alpha of the way to the still-world flow of
    the annotated boxes (not the deployed depth's), the ring unchanged."""
    [x], _ = _reader(inputs, "pull", 0, 0.6)("f0")
    clean, still = _clean("f0"), SPLITS["f0"]["still"].astype(np.float32)
    want = np.where(_box("f0")[:, None], clean + np.float32(0.6) * (still - clean), clean)
    assert np.allclose(x, want, atol=1e-6)
    assert not np.allclose(x, clean, atol=1e-3)


def test_the_scale_error_multiplies_the_flow(inputs) -> None:
    [x], _ = _reader(inputs, "scale", 0, 0.25)("f0")
    assert np.allclose(x, _clean("f0") * 1.25, rtol=1e-6)


def test_context_crops_of_other_objects_are_refused_only_by_the_pull(tmp_path) -> None:
    """A context node whose rows are other objects (here: reversed) stops the pull with
    one error; the other kinds never read it."""
    dirs = (tmp_path / "crops", tmp_path / "context")
    _write_crops(dirs, shuffle_context=True)
    q = _params(tmp_path)
    with pytest.raises(ValueError, match=r"^f0 split: the exact-flow crops and chapter 10's "
                                         r"context crops hold other objects; rebuild"):
        fe.degraded_reader(q, *dirs, "pull", 0, 0.5)("f0")
    [x], _ = fe.degraded_reader(q, *dirs, "scale", 0, 0.5)("f0")
    assert np.allclose(x, _clean("f0") * 1.5, rtol=1e-6)


# --- elevels: each kind's levels at the targets -------------------------------------------------


def _scored(name: str) -> np.ndarray:
    """Every scored row's array ``name`` (fold 0's test rows, then fold 1's), float32."""
    return np.concatenate([SPLITS[s][name] for s in ("f0", "f1")]).astype(np.float32)


def _box_mean(err: np.ndarray, box: np.ndarray) -> float:
    """Mean over objects of each object's mean of ``err`` (N, S, S) over its box pixels."""
    return float(((err * box).sum((1, 2)) / box.sum((1, 2))).mean())


def _calibration(count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(flow, still, box) of the objects drawn with the seed from every scored row, and
    the rows drawn."""
    n = 2 * PER_FOLD
    pick = np.sort(np.random.default_rng(SEED).choice(n, min(count, n), replace=False))
    box = np.concatenate([_box("f0"), _box("f1")])[pick]
    return _scored("flow")[pick], _scored("still")[pick], box, pick


@pytest.fixture(scope=shared_scope)
def levels_run(tmp_path_factory) -> Params:
    """A run whose elevels nodes of noise, pull and scale are built on the inputs."""
    p = _params(tmp_path_factory.mktemp("fe_levels"))
    _publish_inputs(p)
    for kind in p.error_kinds:
        pipeline.GRAPH.build_node(p, Node("elevels", "gt", kind))
    return p


def _levels(p: Params, kind: str) -> tuple[dict, dict]:
    folder = pipeline.GRAPH.node_dir(p, Node("elevels", "gt", kind))
    return fe.read_levels(folder), read_manifest(folder / "manifest.json")


def _check_levels(p: Params, kind: str, per_level: float, hi: float) -> float:
    """The record of one kind whose box error is ``per_level`` px per unit of its level:
    the first target reached within 1 %, the second out of reach (the kind's largest level);
    returns the first level."""
    rec, man = _levels(p, kind)
    level = rec["levels"][0]
    assert rec["kind"] == kind and rec["unit"] == fe.KINDS[kind].level
    assert rec["targets"] == [0.5, 1000.0] and rec["objects"] == man["objects"] == 10
    assert abs(level * per_level - 0.5) <= 0.005
    assert rec["levels"][1] == hi and rec["reached"] == [True, False]
    assert rec["realised"] == pytest.approx([level * per_level, hi * per_level], rel=1e-4)
    assert man["levels"] == rec["levels"]
    return level


def test_the_scale_level_reaches_the_target_on_the_drawn_objects(levels_run) -> None:
    """Scale s makes a box error of s x the box's flow length: the level is 0.5 px over the
    mean length of the 10 drawn objects' boxes, not of all 24."""
    flow, _, box, _ = _calibration(10)
    length = _box_mean(np.hypot(flow[:, 0], flow[:, 1]), box)
    level = _check_levels(levels_run, "scale", length, 1.0)
    every = np.concatenate([_box("f0"), _box("f1")])
    other = _box_mean(np.hypot(*_scored("flow").transpose(1, 0, 2, 3)), every)
    assert abs(level * other - 0.5) > 0.02  # another set of objects, another level


def test_the_noise_level_reaches_the_target_with_the_seed_s_draw(levels_run) -> None:
    """Noise sigma makes a box error of sigma x the mean length of the seed's standard
    normal draw over the drawn objects (seed 20's draw, 3.8 % longer than seed 0's: a
    level matched on another draw misses the target)."""
    _, _, box, _ = _calibration(10)

    def length(seed: int) -> float:
        z = np.random.default_rng(seed).standard_normal((10, 2, S, S), dtype=np.float32)
        return _box_mean(np.hypot(z[:, 0], z[:, 1]), box)

    assert length(SEED) / length(0) > 1.03
    _check_levels(levels_run, "noise", length(SEED), 20.0)


def test_the_pull_level_reaches_the_target_toward_the_annotated_still_world(levels_run
                                                                           ) -> None:
    """The pull alpha makes a box error of alpha x the distance from the exact flow to the
    still-world flow of the annotated boxes (chapter 10's ``static`` crops)."""
    flow, still, box, _ = _calibration(10)
    d = still - flow
    _check_levels(levels_run, "pull", _box_mean(np.hypot(d[:, 0], d[:, 1]), box), 1.0)


def test_a_calibration_larger_than_the_rows_takes_every_row(tmp_path) -> None:
    """40 objects asked, 24 scored: the level is matched on all 24."""
    p = _params(tmp_path, error_calibration=40, error_kinds=["scale"], error_targets=[0.5])
    _publish_inputs(p)
    pipeline.GRAPH.build_node(p, Node("elevels", "gt", "scale"))
    rec, man = _levels(p, "scale")
    every = np.concatenate([_box("f0"), _box("f1")])
    length = _box_mean(np.hypot(*_scored("flow").transpose(1, 0, 2, 3)), every)
    assert rec["objects"] == man["objects"] == 24 and rec["reached"] == [True]
    assert abs(rec["levels"][0] * length - 0.5) <= 0.005


def test_the_pull_s_levels_refuse_context_crops_of_other_objects(tmp_path) -> None:
    """The pull is calibrated on the still-world flow of the very rows it degrades: a
    context node whose rows are other objects (reversed) is one error, before any level."""
    p = _params(tmp_path, error_kinds=["pull"])
    _publish_inputs(p)
    dirs = (pipeline.GRAPH.node_dir(p, Node("crops", "gt", "keyframe")),
            pipeline.GRAPH.node_dir(p, Node("context", None, "keyframe")))
    _write_crops(dirs, shuffle_context=True)
    with pytest.raises(ValueError, match=r"^the scored rows: the exact-flow crops and "
                                         r"chapter 10's context crops hold other objects"):
        pipeline.GRAPH.build_node(p, Node("elevels", "gt", "pull"))
    assert not (pipeline.GRAPH.node_dir(p, Node("elevels", "gt", "pull")) / fe.LEVELS_FILE
                ).exists()


# --- etrain: what each classifier trains on -----------------------------------------------------


@pytest.fixture(scope=shared_scope)
def arms_run(tmp_path_factory) -> Params:
    """A run of the inputs and hand-made levels (:data:`LEVELS`)."""
    p = _params(tmp_path_factory.mktemp("fe_arms"))
    _publish_inputs(p, LEVELS)
    return p


def _trained_on(p: Params, part: str, monkeypatch) -> tuple[dict, dict]:
    """What ``etrain[gt/<part>]``'s build hands the trainer (train_seed's arguments) and
    the manifest fields it returns."""
    seen = {}

    def fake(b, train, val, progress, what, **kw):
        seen.update(node=b.node, train=train, val=val, what=what, progress=progress, **kw)
        return {"best_epoch": 0}

    monkeypatch.setattr(fe, "train_seed", fake)
    info = fe.build_etrain(pipeline.GRAPH.begin(p, Node("etrain", "gt", part)), True)
    assert seen.pop("progress") is True  # the bar asked for is shown
    return seen, info


def _role(split: str, val: bool) -> np.ndarray:
    return SPLITS[split]["df"]["val_scene"].to_numpy() == val


def test_fold_1_s_noise_model_trains_on_fold_0_s_rows_with_the_split_s_noise(arms_run,
                                                                              monkeypatch):
    """etrain[gt/noise/1/f1]: fold 0's non-validation scenes to train, its validation
    scenes to choose the epoch, both read with target 1's level (0.7) of noise drawn for
    split f0; width error_width; the kind and level in the manifest."""
    seen, info = _trained_on(arms_run, "noise/1/f1", monkeypatch)
    z = fe._split_rng(SEED, "noise", 1, "f0").standard_normal((PER_FOLD, 2, S, S), np.float32)
    noisy = _clean("f0") + np.float32(0.7) * z
    for role, val in (("train", False), ("val", True)):
        x, df = seen[role]
        keep = _role("f0", val)
        assert np.allclose(x, noisy[keep], atol=1e-6)
        assert df["ann_token"].tolist() == SPLITS["f0"]["df"]["ann_token"][keep].tolist()
    assert seen["width"] == 4 and seen["what"] == "exact flow, noise/1"
    assert info == {"best_epoch": 0, "kind": "noise", "level": 0.7}


def test_fold_0_s_pull_model_trains_on_fold_1_pulled(arms_run, monkeypatch) -> None:
    """etrain[gt/pull/0/f0]: fold 1's rows, pulled at target 0's level (0.6)."""
    seen, info = _trained_on(arms_run, "pull/0/f0", monkeypatch)
    clean, still = _clean("f1"), SPLITS["f1"]["still"].astype(np.float32)
    pulled = np.where(_box("f1")[:, None], clean + np.float32(0.6) * (still - clean), clean)
    for role, val in (("train", False), ("val", True)):
        assert np.allclose(seen[role][0], pulled[_role("f1", val)], atol=1e-6)
    assert seen["what"] == "exact flow, pull/0"
    assert info["kind"] == "pull" and info["level"] == 0.6


def test_the_exact_arm_trains_on_the_exact_flow_at_level_0(arms_run, monkeypatch) -> None:
    """etrain[gt/exact/f0] reads no levels: the stored crops, level 0."""
    seen, info = _trained_on(arms_run, "exact/f0", monkeypatch)
    assert np.array_equal(seen["train"][0], _clean("f1")[_role("f1", False)])
    assert seen["val"][1]["ann_token"].tolist() == SPLITS["f1"]["df"]["ann_token"][
        _role("f1", True)].tolist()
    assert info["kind"] == "exact" and info["level"] == 0.0


# --- eevaluate: each arm's models on their test rows --------------------------------------------

#: The arms scored: (key, its test crops of split f<k> as the models read them).
SCORED = {"exact": lambda split: _clean(split),
          "noise/0": lambda split: _clean(split) + np.float32(0.3) * fe._split_rng(
              SEED, "noise", 0, split).standard_normal((PER_FOLD, 2, S, S), np.float32)}


@pytest.fixture(scope=shared_scope)
def scored_run(arms_run) -> Params:
    """The arms of :data:`SCORED` trained (one epoch, both folds) and scored."""
    for key in SCORED:
        for part in ("f0", "f1"):
            pipeline.GRAPH.build_node(arms_run, Node("etrain", "gt", f"{key}/{part}"))
        pipeline.GRAPH.build_node(arms_run, Node("eevaluate", "gt", key))
    return arms_run


def _arm_dir(p: Params, key: str):
    return pipeline.GRAPH.node_dir(p, Node("eevaluate", "gt", key))


@pytest.mark.parametrize("key", list(SCORED))
def test_each_row_is_scored_by_its_fold_s_model_on_the_arm_s_crops(scored_run, key) -> None:
    """Fold 0's rows, then fold 1's, each predicted by the model of its fold from the crops
    as the arm reads them (the noise of the split's generator), which the exact flow does
    not give."""
    from flowmod.model import load_model, predict

    got = fe.read_arm(_arm_dir(scored_run, key))
    want = pd.concat([SPLITS[s]["df"] for s in ("f0", "f1")], ignore_index=True)
    assert got["ann_token"].tolist() == want["ann_token"].tolist()
    assert got["fold"].tolist() == want["fold"].tolist()
    for k in range(2):
        model = load_model(pipeline.GRAPH.node_dir(
            scored_run, Node("etrain", "gt", f"{key}/f{k}")) / "best.pt", "cpu")
        prob = got.loc[got["fold"] == k, "prob"].to_numpy()
        assert np.allclose(prob, predict(model, SCORED[key](f"f{k}"), device="cpu"),
                           rtol=0, atol=1e-6)
        if key != "exact":
            assert not np.allclose(prob, predict(model, _clean(f"f{k}"), device="cpu"),
                                   rtol=0, atol=1e-6)


@pytest.mark.parametrize("key", list(SCORED))
def test_each_scored_object_carries_its_realised_error(scored_run, key) -> None:
    """epe_box and epe_ring: each object's mean end-point error of the arm's crops against
    the exact flow over its box pixels and over the rest of its crop (0 for the exact arm);
    the arm, its target and level recorded beside."""
    got = fe.read_arm(_arm_dir(scored_run, key))
    for k, split in enumerate(("f0", "f1")):
        err = np.sqrt(((SCORED[key](split).astype(np.float64) - _clean(split)) ** 2).sum(1))
        box, rows = _box(split), got["fold"] == k
        assert np.allclose(got.loc[rows, "epe_box"], (err * box).sum((1, 2)) / box.sum((1, 2)),
                           rtol=1e-6, atol=1e-9)
        assert np.allclose(got.loc[rows, "epe_ring"],
                           (err * ~box).sum((1, 2)) / (~box).sum((1, 2)), rtol=1e-6, atol=1e-9)
    kind, target = fe.parse_arm(key)
    level = 0.3 if key == "noise/0" else 0.0
    arm = json.loads((_arm_dir(scored_run, key) / "arm.json").read_text())
    assert arm == {"kind": kind, "target": target, "level": level}
    man = read_manifest(_arm_dir(scored_run, key) / "manifest.json")
    assert (man["n"], man["kind"], man["level"]) == (2 * PER_FOLD, kind, level)
    assert (got["epe_box"] > 0.3).all() if key != "exact" else (got["epe_box"] == 0).all()


def test_predictions_and_errors_of_other_objects_are_refused(tmp_path) -> None:
    """read_arm: a test table and an errors table of other objects are one error naming the
    folder."""
    df = pd.DataFrame({"ann_token": ["a", "b"], "prob": [0.2, 0.9]})
    df.to_parquet(tmp_path / "test.parquet", index=False)
    df.iloc[::-1].assign(epe_box=1.0, epe_ring=2.0).to_parquet(tmp_path / "errors.parquet",
                                                               index=False)
    with pytest.raises(ValueError, match=f"^{tmp_path}: predictions and realised errors hold "
                                         "other objects$"):
        fe.read_arm(tmp_path)


# --- the declarations ---------------------------------------------------------------------------


def test_the_stages_plan_their_nodes_inputs_and_folders(tmp_path) -> None:
    """One elevels node a kind, reading the crops (and the context for the pull); one etrain
    node per arm and fold, reading the levels of its kind (none for the exact arm); one
    eevaluate node per arm reading its models; none without the exact flow."""
    p = _params(tmp_path)
    crops, ctx = Node("crops", "gt", "keyframe"), Node("context", None, "keyframe")
    lv = {k: Node("elevels", "gt", k) for k in p.error_kinds}
    assert fe.ELEVELS.nodes(p) == list(lv.values())
    assert fe.ELEVELS.inputs(lv["pull"], p) == (crops, ctx)
    assert fe.ELEVELS.inputs(lv["noise"], p) == (crops,)
    arms = ["exact"] + [f"{k}/{t}" for k in p.error_kinds for t in (0, 1)]
    assert fe.ETRAIN.nodes(p) == [Node("etrain", "gt", f"{a}/f{k}") for a in arms
                                  for k in (0, 1)]
    assert fe.ETRAIN.inputs(Node("etrain", "gt", "pull/1/f0"), p) == (crops, ctx, lv["pull"])
    assert fe.ETRAIN.inputs(Node("etrain", "gt", "exact/f1"), p) == (crops,)
    assert fe.EEVALUATE.nodes(p) == [Node("eevaluate", "gt", a) for a in arms]
    assert fe.EEVALUATE.inputs(Node("eevaluate", "gt", "scale/1"), p) == (
        Node("etrain", "gt", "scale/1/f0"), Node("etrain", "gt", "scale/1/f1"), crops,
        lv["scale"])
    assert fe._needs("exact") == (crops,)
    run = p.run_path
    assert pipeline.GRAPH.node_dir(p, lv["noise"]) == run / "flowerrors/levels/noise"
    assert pipeline.GRAPH.node_dir(p, Node("etrain", "gt", "noise/1/f0")) == (
        run / "flowerrors/models/gt/noise/1/f0")
    assert pipeline.GRAPH.node_dir(p, Node("eevaluate", "gt", "exact")) == (
        run / "flowerrors/metrics/gt/exact")
    assert fe.ETRAIN.parallel and not fe.EEVALUATE.parallel
    none = p.model_copy(update={"flow_methods": ["dis"]})
    assert fe.ELEVELS.nodes(none) == fe.ETRAIN.nodes(none) == fe.EEVALUATE.nodes(none) == []


#: Arms of the single split: key -> (level, its test crops from the clean ones and the
#: still-world flow).
SINGLE = {"scale/1": (1.0, lambda clean, still, box: 2 * clean),
          "pull/0": (0.6, lambda clean, still, box: np.where(
              box[:, None], clean + np.float32(0.6) * (still - clean), clean))}


@pytest.mark.parametrize("key", list(SINGLE))
def test_the_single_split_scores_its_test_split(tmp_path, monkeypatch, key) -> None:
    """With the paper's single split (folds 1), an arm scores the ``test`` split once, as the
    arm reads it (scaled at target 1's level, 1.0: twice the flow; pulled at target 0's,
    0.6, toward the annotated still world), and hands the predictor its training nodes'
    key; the predictor is faked (no model trains here): its ``prob`` is each crop's mean."""
    p = _params(tmp_path, folds=1, error_folds=1)
    crops = node_folder(p, Node("crops", "gt", "keyframe"))
    ctx = node_folder(p, Node("context", None, "keyframe"))
    s, df = SPLITS["f0"], SPLITS["f0"]["df"].assign(split="test")
    np.save(crops / "test.npy", s["flow"])
    df.to_parquet(crops / "test.parquet", index=False)
    for name in ("still", "deployed"):
        np.save(ctx / f"test.{'static' if name == 'still' else name}.npy", s[name])
    np.save(ctx / "test.images.npy", np.zeros((PER_FOLD, 6, S, S), np.uint8))
    df.to_parquet(ctx / "test.parquet", index=False)
    kind, target = fe.parse_arm(key)
    lv = node_folder(p, Node("elevels", "gt", kind))
    (lv / fe.LEVELS_FILE).write_text(json.dumps({"levels": LEVELS[kind]}))
    node_folder(p, Node("etrain", "gt", f"{key}/s0"))
    seen = {}

    def fake(b, stage, key, splits):
        seen.update(stage=stage, key=key, splits=splits)
        x, df = splits["test"]
        df.assign(prob=x.mean((1, 2, 3))).to_parquet(b.start(fresh=True) / "test.parquet")

    monkeypatch.setattr(fe, "predict_splits", fake)
    b = pipeline.GRAPH.begin(p, Node("eevaluate", "gt", key))
    level, crops_of = SINGLE[key]
    assert fe.build_eevaluate(b, False) == {"n": PER_FOLD, "kind": kind, "level": level}
    assert (seen["stage"], seen["key"], list(seen["splits"])) == ("etrain", f"gt/{key}", ["test"])
    got = fe.read_arm(b.dir)
    clean, box = _clean("f0"), _box("f0")
    want = crops_of(clean, s["still"].astype(np.float32), box)
    assert np.allclose(got["prob"], want.mean((1, 2, 3)), rtol=1e-5)
    err = np.hypot(*(want - clean).transpose(1, 0, 2, 3))
    assert np.allclose(got["epe_box"], (err * box).sum((1, 2)) / box.sum((1, 2)), rtol=1e-5)
    assert np.allclose(got["epe_ring"], (err * ~box).sum((1, 2)) / (~box).sum((1, 2)),
                       rtol=1e-5, atol=1e-9)
    assert got["ann_token"].tolist() == df["ann_token"].tolist()
