"""The build functions of chapter 11's stages (:mod:`flowmod.extensions.wide`) and of
chapter 10's context stage (:mod:`flowmod.extensions.context`), quick.

Inputs: the ``select`` and ``general`` nodes built by chapter 02 on the tiny five-scene world
(``tiny_world``, seconds), from which the ``wide`` and ``context`` nodes are built; a
hand-made ``select`` node (its scene table changed); hand-made crops nodes (each crop filled
with its row's number) with a stand-in trainer that records what it is given; hand-made
``wtrain`` models whose output is their bias alone (a zero last layer), so that every
probability says which model gave it; hand-made camera images (PNG, exact pixels). The
expected tables, rows, crops and numbers are computed here from the same inputs (by hand,
the devkit, :mod:`flowmod.select`'s and :mod:`flowmod.crops`' functions on their own).
"""

from __future__ import annotations

import inspect
import json
import re

import cv2
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from conftest import shared_scope
from handmade import node_folder

from flowmod import dag, pipeline, select, train
from flowmod.crops import CropsError, crop_image, static_crops
from flowmod.extensions import context, wide
from flowmod.params import load_profile
from flowmod.progress import ENV as PROGRESS_ENV

CROP_SIZE, CROP_SCALE = 16, 2.5


def _tiny(root, version, run_dir, **kw):
    """The smoke profile on the tiny world's data, in its own run folder."""
    return load_profile("smoke", dataroot=str(root), version=version, synthetic=False,
                        n_jobs=1, run_dir=str(run_dir), general_max_scenes=1,
                        crop_size=CROP_SIZE, crop_scale=CROP_SCALE, **kw)


@pytest.fixture(scope=shared_scope)
def tiny_run(tiny_world, tmp_path_factory):
    """The tiny world's ``select`` and ``general`` nodes (chapter 02), built once."""
    p = _tiny(*tiny_world, tmp_path_factory.mktemp("wide_context_run"))
    pipeline.build(p, ["02"])
    return p


@pytest.fixture
def progress_file(tmp_path, monkeypatch):
    """The progress bars' side channel (the runner's), a file read back by the test."""
    f = tmp_path / "progress.txt"
    monkeypatch.setenv(PROGRESS_ENV, str(f))
    return f


def _publish_by_hand(p, node, tables=None, arrays=None, **record):
    """A published folder of ``node``: parquet tables, npy arrays, a manifest (no files)."""
    d = node_folder(p, node, **record)
    for name, df in (tables or {}).items():
        df.to_parquet(d / f"{name}.parquet", index=False)
    for name, a in (arrays or {}).items():
        np.save(d / f"{name}.npy", a)
    return d


def _with_leftover(p, node):
    """A file a killed build left in ``node``'s building folder (a fresh build drops it)."""
    b = pipeline.GRAPH.begin(p, node)
    b.dir.mkdir(parents=True, exist_ok=True)
    (b.dir / "leftover.parquet").write_bytes(b"from a killed build")


def _files(folder):
    return sorted(f.name for f in folder.iterdir())


# --- chapter 11: the wide selection ------------------------------------------------------------


def test_wide_node_publishes_the_selection_of_the_select_node_s_scenes(tiny_run, tiny_world,
                                                                        tmp_path, progress_file):
    """``wide`` reads the scene table of the ``select`` node it is given (here one training
    scene is excluded by hand), selects every distance and the sweeps of those scenes with
    the node's parameters (showing the selection's bars when asked), writes ``pairs`` and
    ``objects`` into a fresh folder and records its rows, pairs and sweep pairs."""
    built = pipeline.published(tiny_run, dag.Node("select"))
    scenes = select.read_table(built, "scenes")
    gone = scenes.loc[scenes["fold"] >= 0, "scene"].iloc[0]
    mine = scenes.assign(fold=np.where(scenes["scene"] == gone, -1, scenes["fold"]),
                         split=np.where(scenes["scene"] == gone, "excluded", scenes["split"]))
    p = _tiny(*tiny_world, tmp_path / "runs", wide_sweep_stride=2)
    _publish_by_hand(p, dag.Node("select"), {"scenes": mine, **{
        t: select.read_table(built, t) for t in ("pairs", "objects")}})
    wide.build_wide(pipeline.GRAPH.begin(p, dag.Node("wide")), False)
    assert not progress_file.exists() or progress_file.read_text() == "", "quiet unless asked"
    _with_leftover(p, dag.Node("wide"))
    folder = pipeline.GRAPH.build_node(p, dag.Node("wide"), progress=True)
    shown = progress_file.read_text()
    assert "keyframe pairs: 100%" in shown and "sweep pairs: 100%" in shown

    nusc = select.open_nuscenes(*tiny_world)
    pairs, objects = select.select_wide(p, mine, nusc, progress=False)
    assert gone in set(select.select_wide(p, scenes, nusc, progress=False)[1]["scene"])
    assert gone not in set(objects["scene"])
    pd.testing.assert_frame_equal(select.read_table(folder, "pairs"), pairs)
    pd.testing.assert_frame_equal(select.read_table(folder, "objects"), objects)
    assert _files(folder) == ["manifest.json", "objects.parquet", "pairs.parquet"]
    rec = json.loads((folder / "manifest.json").read_text())
    sweeps = sum(s == "sweep" for s in pairs["set"])
    assert 0 < sweeps < len(pairs) - sweeps, "both kinds, in unequal numbers"
    assert (rec["rows"], rec["pairs"], rec["sweep_pairs"]) == (len(objects), len(pairs), sweeps)


def test_wide_stages_declare_their_nodes_and_inputs():
    """``wide`` exists with chapter 11's methods; ``wtrain`` one node per method and
    extension part, on the method's wide crops; ``wgeneralise`` one per method, on its
    models, its keyframe and generalisation crops and the generalisation set."""
    p = load_profile("demo", wide_methods=["gt", "dis"], extension_seeds=1)
    none = load_profile("demo", wide_methods=[])
    assert wide.WIDE_STAGE.nodes(p) == [dag.Node("wide")] and wide.WIDE_STAGE.nodes(none) == []
    assert wide.WIDE_STAGE.inputs(dag.Node("wide"), p) == (dag.Node("world"),
                                                           dag.Node("select"))
    parts = [f"f{k}" for k in range(p.folds)]
    assert wide.WTRAIN.nodes(p) == [dag.Node("wtrain", m, k) for m in ("gt", "dis")
                                    for k in parts]
    assert wide.WTRAIN.nodes(none) == []
    assert wide.WTRAIN.inputs(dag.Node("wtrain", "gt", "f1"), p) == (
        dag.Node("crops", "gt", "wide"),)
    assert wide.WGENERALISE.nodes(p) == [dag.Node("wgeneralise", "gt"),
                                         dag.Node("wgeneralise", "dis")]
    assert wide.WGENERALISE.inputs(dag.Node("wgeneralise", "dis"), p) == (
        *(dag.Node("wtrain", "dis", k) for k in parts), dag.Node("crops", "dis", "keyframe"),
        dag.Node("crops", "dis", "general"), dag.Node("general"))


# --- chapter 11: the classifier on the wide crops ---------------------------------------------


def _crops_of(tokens, folds, val, first=0, size=4):
    """A crops split: crop i filled with ``first + i``; its index with fold and role."""
    n = len(tokens)
    x = (first + np.arange(n, dtype=np.float16))[:, None, None, None] + np.zeros(
        (n, 2, size, size), np.float16)
    df = pd.DataFrame({"ann_token": tokens, "fold": folds, "val_scene": val,
                       "label": np.arange(n) % 2, "scene": [f"s{f}" for f in folds]})
    return x, df


CROP_RECORD = {"params": {"crop_size": 4, "crop_scale": 3.0}}
FLOW_RECORD = {"params": {"preset": "fast"}, "dtype": "float16", "store_scale": 0.5}


def test_wtrain_trains_on_the_other_folds_wide_crops_and_records_the_recipe(
        tiny_world, tmp_path, monkeypatch):
    """Fold 1's model of three: trained on the rows of folds 0 and 2 outside validation
    scenes, validated on their validation scenes' rows (the wide crops, read through the
    node's input), with the progress flag and the method's name; its record is the
    trainer's and the recipe of the flow and crops it was trained on."""
    p = _tiny(*tiny_world, tmp_path / "runs", folds=3)
    split = {k: _crops_of([f"f{k}-{i}" for i in range(4)], [k] * 4,
                          [i == 1 for i in range(4)], first=10 * k) for k in range(3)}
    _publish_by_hand(p, dag.Node("crops", "dis", "wide"),
                     {f"f{k}": df for k, (_, df) in split.items()},
                     {f"f{k}": x for k, (x, _) in split.items()}, **CROP_RECORD)
    # the keyframe crops made otherwise: the recipe is the wide crops' it trained on
    _publish_by_hand(p, dag.Node("crops", "dis", "keyframe"),
                     params={"crop_size": 8, "crop_scale": 2.0})
    _publish_by_hand(p, dag.Node("flow", "dis", "keyframe"), **FLOW_RECORD)
    seen = {}

    def trainer(*args, **kw):
        seen.update(inspect.signature(train.train_seed).bind(*args, **kw).arguments)
        return {"best_epoch": 3, "best_f1": 0.5}

    monkeypatch.setattr(wide, "train_seed", trainer)
    b = pipeline.GRAPH.begin(p, dag.Node("wtrain", "dis", "f1"))
    info = wide.build_wtrain(b, True)
    assert seen["b"] is b and seen["progress"] is True and seen["what"] == "dis all distances"
    for role, want in (("train", ["f0-0", "f0-2", "f0-3", "f2-0", "f2-2", "f2-3"]),
                       ("val", ["f0-1", "f2-1"])):
        x, df = seen[role]
        assert df["ann_token"].tolist() == want, role
        ids = [10 * int(t[1]) + int(t[3]) for t in want]
        np.testing.assert_array_equal(np.asarray(x)[:, :, 2, 1], np.repeat(
            np.array(ids, np.float16)[:, None], 2, axis=1))
    assert info == {"best_epoch": 3, "best_f1": 0.5, "recipe": {
        "method": "dis", "flow_params": {"preset": "fast"}, "flow_dtype": "float16",
        "store_scale": 0.5, "crop_size": 4, "crop_scale": 3.0}}


# --- chapter 11: predictions of every seed -------------------------------------------------------


def _constant_model(path, bias, width=4):
    """A model whose logit is ``bias`` whatever its input (zero last layer)."""
    import torch

    from flowmod.model import motion_resnet18

    m = motion_resnet18(2, width)
    with torch.no_grad():
        m.fc.weight.zero_()
        m.fc.bias.fill_(bias)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(m.state_dict(), path)


def _sigmoid(z):
    return 1.0 / (1.0 + np.exp(-z))


def test_wgeneralise_predicts_each_row_by_its_fold_s_models_of_every_seed(tiny_world,
                                                                        tmp_path):
    """Two folds by two seeds: every generalisation row and every keyframe test row (fold 0's
    then fold 1's) gets ``prob_s<j>`` of its own fold's seed-j model and ``prob`` of seed
    0's; the record counts the seeds and both tables' rows."""
    p = _tiny(*tiny_world, tmp_path / "runs", extension_seeds=2)
    assert p.folds == 2
    bias = {"f0s0": 1.0, "f0s1": -0.5, "f1s0": 2.0, "f1s1": -1.5}
    for part, z in bias.items():
        node = dag.Node("wtrain", "dis", part)
        d = _publish_by_hand(p, node, amp="off")
        _constant_model(train.model_file(d), z)
    test = {k: _crops_of([f"t{k}-{i}" for i in range(n)], [k] * n, [False] * n)
            for k, n in ((0, 3), (1, 2))}
    _publish_by_hand(p, dag.Node("crops", "dis", "keyframe"),
                     {f"f{k}": df for k, (_, df) in test.items()},
                     {f"f{k}": x for k, (x, _) in test.items()})
    gfold = [1, 0, 1, 1, 0]
    gx, gdf = _crops_of([f"g{i}" for i in range(5)], gfold, [False] * 5)
    _publish_by_hand(p, dag.Node("crops", "dis", "general"), {"general": gdf}, {"general": gx})
    _publish_by_hand(p, dag.Node("general"))
    folder = pipeline.GRAPH.build_node(p, dag.Node("wgeneralise", "dis"))

    want = {"test": pd.concat([test[0][1], test[1][1]], ignore_index=True),
            "general": pd.concat([gdf[gdf["fold"] == k] for k in (0, 1)], ignore_index=True)}
    for split, rows in want.items():
        got = pd.read_parquet(folder / f"{split}.parquet")
        f = rows["fold"].to_numpy()
        for j in (0, 1):
            rows[f"prob_s{j}"] = _sigmoid(np.array([bias[f"f{k}s{j}"] for k in f]))
        rows["prob"] = rows["prob_s0"]
        assert got["ann_token"].tolist() == rows["ann_token"].tolist(), split
        pd.testing.assert_frame_equal(got, rows, check_exact=False, rtol=1e-6)
    rec = json.loads((folder / "manifest.json").read_text())
    assert (rec["seeds"], rec["general"], rec["test"]) == (2, 5, 5)


# --- chapter 10: camera images and their crops ----------------------------------------------------


def _png(path, rgb):
    """Write an RGB array as a PNG (lossless: read back exactly)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[:, :, ::-1]))


def test_read_image_gives_rgb_and_names_a_missing_or_unreadable_file(tmp_path):
    rgb = np.random.default_rng(1).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    _png(tmp_path / "a.png", rgb)
    got = context.read_image(tmp_path / "a.png")
    np.testing.assert_array_equal(got, rgb)
    assert got.dtype == np.uint8
    (tmp_path / "b.jpg").write_text("not an image")
    for name in ("gone.jpg", "b.jpg"):
        with pytest.raises(CropsError, match=rf"^camera image .*{re.escape(name)} is missing or "
                                             r"not a readable image: restore it from the data "
                                             r"set \(or regenerate the world: make data\)$"):
            context.read_image(tmp_path / name)


def _two_pairs(root):
    """Two pairs of hand-made 40 x 60 frames (four different images under ``root``) and
    three objects, the pairs' rows interleaved."""
    rng = np.random.default_rng(7)
    images = {}
    for pid in ("A", "B"):
        for k in (1, 2):
            images[f"cam/{pid}{k}.png"] = rng.integers(0, 256, (40, 60, 3), dtype=np.uint8)
            _png(root / f"cam/{pid}{k}.png", images[f"cam/{pid}{k}.png"])
    pairs = pd.DataFrame({"pair_id": ["A", "B"], "path_1": ["cam/A1.png", "cam/B1.png"],
                          "path_2": ["cam/A2.png", "cam/B2.png"]})
    objects = pd.DataFrame({"pair_id": ["B", "A", "B"], "xmin": [10.0, 30.0, 40.0],
                            "ymin": [5.0, 12.0, 20.0], "xmax": [22.0, 38.0, 50.0],
                            "ymax": [15.0, 30.0, 26.0]})
    return images, pairs, objects


def _expected_images(images, pairs, objects, size, scale):
    """(N, 6, S, S): each object's window cut from its pair's two frames, one by one."""
    by = pairs.set_index("pair_id")
    out = []
    for o in objects.itertuples(index=False):
        box = np.array([[o.xmin, o.ymin, o.xmax, o.ymax]])
        out.append(np.concatenate([crop_image(images[by.loc[o.pair_id, col]], box, size,
                                              scale)[0].transpose(2, 0, 1)
                                   for col in ("path_1", "path_2")]))
    return np.stack(out)


def test_image_crops_cut_each_object_s_window_from_its_pair_s_two_frames(tmp_path,
                                                                        monkeypatch):
    """Rows as the objects: RGB of frame 1 then of frame 2 in each object's window
    (``scale`` x its box, resized to S); each pair's two images read once."""
    images, pairs, objects = _two_pairs(tmp_path)
    read, real = [], context.read_image
    monkeypatch.setattr(context, "read_image", lambda path: read.append(path) or real(path))
    got = context.image_crops(objects, pairs, tmp_path, 9, 1.5)
    assert got.shape == (3, 6, 9, 9) and got.dtype == np.uint8
    np.testing.assert_array_equal(got, _expected_images(images, pairs, objects, 9, 1.5))
    assert sorted(read) == sorted(tmp_path / f for f in images)


def test_image_crops_show_a_bar_of_pairs_only_when_asked(tmp_path, progress_file):
    images, pairs, objects = _two_pairs(tmp_path)
    context.image_crops(objects, pairs, tmp_path, 5, 2.0)
    assert not progress_file.exists() or progress_file.read_text() == ""
    context.image_crops(objects, pairs, tmp_path, 5, 2.0, progress=True)
    assert re.search(r"image crops: 100%.*\| 2/2 .*pair", progress_file.read_text())


# --- chapter 10: the context node ----------------------------------------------------------------


def _by_hand(p, part):
    """What ``context[part]`` holds, split by split: (index, static with the frame's boxes,
    static from the ground, images), from the selection's tables, the devkit and the
    crops module's functions one object at a time; and the frames' box count."""
    folder = pipeline.published(p, select.objects_node(part))
    objects, pairs = select.read_table(folder, "objects"), select.read_table(folder, "pairs")
    if part == "general":
        objects = objects.assign(split="general")
    nusc = select.open_nuscenes(p.dataroot_path, p.version)
    used = pairs[pairs["pair_id"].isin(objects["pair_id"])]
    boxes = {r.pair_id: select.frame_boxes_3d(nusc, r.sd_token_1) for r in used.itertuples()}
    out = {}
    for split in sorted(set(objects["split"])):
        df = objects[objects["split"] == split].sort_values("pair_id", kind="stable")
        df = df.reset_index(drop=True)
        st = static_crops(df, used, CROP_SIZE, CROP_SCALE, frame_boxes=boxes,
                          depths=("boxes", "ground"))
        frames = {path: cv2.imread(str(p.dataroot_path / path))[:, :, ::-1]
                  for path in (*used["path_1"], *used["path_2"])}
        out[split] = (df, st["boxes"].astype(np.float16), st["ground"].astype(np.float16),
                      _expected_images(frames, used, df, CROP_SIZE, CROP_SCALE))
    return out, sum(len(v) for v in boxes.values()), used, boxes


@pytest.mark.parametrize("part, progress", [("keyframe", True), ("general", False)])
def test_context_node_holds_static_flow_and_images_of_every_object_by_split(
        tiny_run, part, progress, progress_file):
    """``context[<part>]``: per split of the part (the folds; the generalisation set), the
    objects in pair order, their static-world flow with the frame's annotated boxes and
    with the ground (float16 px), their two images' crops; records rows per split and the
    boxes read; built in a fresh folder; bars of each step only when asked."""
    node = dag.Node("context", None, part)
    _with_leftover(tiny_run, node)
    folder = pipeline.GRAPH.build_node(tiny_run, node, progress=progress)
    want, n_boxes, used, boxes = _by_hand(tiny_run, part)
    assert list(want) == (["f0", "f1"] if part == "keyframe" else ["general"])
    assert _files(folder) == sorted(["manifest.json"] + [
        f"{s}.{k}" for s in want for k in ("parquet", "static.npy", "deployed.npy",
                                           "images.npy")])
    for split, (df, boxes_st, ground, images) in want.items():
        static, imgs, index = context.read_context(folder, split)
        pd.testing.assert_frame_equal(index, df)
        assert pq.read_schema(folder / f"{split}.parquet").names == df.columns.tolist()
        for got, exp in ((static, boxes_st), (context.read_context(folder, split, "ground")[0],
                                              ground), (imgs, images)):
            assert got.dtype == exp.dtype, split
            np.testing.assert_array_equal(np.asarray(got), exp)
    rec = json.loads((folder / "manifest.json").read_text())
    assert rec["rows"] == {s: len(v[0]) for s, v in want.items()}
    assert rec["boxes"] == n_boxes > len(used), "every annotated box of each first frame"
    shown = progress_file.read_text() if progress_file.exists() else ""
    if not progress:
        assert shown == ""
    else:
        assert re.search(rf"annotated boxes: 100%.*\| {len(used)}/{len(used)} .*pair", shown)
        for v in want.values():  # each split's static-world and image crops
            assert re.search(rf"static-world crops: 100%.*\| {len(v[0])}/{len(v[0])} ", shown)
        assert len(re.findall(r"image crops: 100%", shown)) == len(want)
    if part == "keyframe":
        # the occluders matter: the object's own box alone gives other static flow
        df = want["f0"][0]
        own = static_crops(df, used, CROP_SIZE, CROP_SCALE)["boxes"].astype(np.float16)
        assert not np.array_equal(own, want["f0"][1])


def test_build_split_writes_one_split_s_files_quietly_by_default(tiny_run, tmp_path,
                                                                progress_file):
    """One split of a hand-made split column: its rows in pair order, nothing shown
    without ``progress``; returns its row count."""
    folder = pipeline.published(tiny_run, dag.Node("select"))
    objects, pairs = select.read_table(folder, "objects"), select.read_table(folder, "pairs")
    objects = objects.assign(split=np.where(np.arange(len(objects)) % 3 == 0, "x", "y"))
    n = context.build_split(objects, pairs, tiny_run.dataroot_path, tmp_path, "x", 6, 2.0)
    want = objects[objects["split"] == "x"].sort_values("pair_id", kind="stable")
    assert n == len(want) > 0
    static, images, index = context.read_context(tmp_path, "x")
    assert index["ann_token"].tolist() == want["ann_token"].tolist()
    assert static.shape == (n, 2, 6, 6) and images.shape == (n, 6, 6, 6)
    assert not progress_file.exists() or progress_file.read_text() == ""
