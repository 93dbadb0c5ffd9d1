"""Chapter 11: the classifier trained on all distances and on the training scenes' sweeps:
its training set (on the smoke world through the devkit), its nodes in the graph, its crops
and models, and the Table-4 rows built from them."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from flowmod import crops, dag, pipeline, select
from flowmod.chapters import ch11_all_distances as ch11
from flowmod.chapters import common
from flowmod.evaluate import seed_probs
from flowmod.metrics import metrics
from flowmod.params import ProfileError, load_profile


@pytest.fixture(scope="module")
def smoke_scenes(smoke_world, smoke_nusc):
    """The smoke world's scene table with the keyframe stage's split."""
    root, version = smoke_world
    p = load_profile("smoke", dataroot=str(root), version=version)
    return p, select.select_keyframes(p, smoke_nusc, progress=False).scenes


def test_training_set_holds_every_distance_of_the_generalisation_range(smoke_scenes, smoke_nusc):
    p, scenes = smoke_scenes
    paper = select.select_keyframes(p, smoke_nusc, progress=False).objects
    near = p.model_copy(update={"general_min_distance": 5.0, "general_max_distance": 50.0})
    pairs, obj = select.select_wide(near, scenes, smoke_nusc, progress=False)
    # cross-validation: every kept scene trains the other folds' models (never its own)
    assert set(obj["split"]) == {"f0", "f1"} and set(obj["scene"]) <= set(
        scenes.loc[scenes["fold"] >= 0, "scene"])
    assert obj["distance"].between(5.0, 50.0).all()
    assert set(obj["set"]) <= {"keyframe", "sweep"}
    assert set(obj["pair_id"]) <= set(pairs["pair_id"])
    # a range that holds the paper's: every paper train/val object is in it, labelled alike
    _, obj = select.select_wide(p.model_copy(update={"general_min_distance": 5.0}), scenes,
                                smoke_nusc, progress=False)
    key = ["pair_id", "instance_token"]
    mine = paper
    both = mine.merge(obj, on=key, suffixes=("", "_wide"))
    assert len(both) == len(mine) > 0
    assert (both["label"] == both["label_wide"]).all()
    with pytest.raises(select.SelectionError, match="general_min_distance"):
        select.select_wide(p.model_copy(update={"general_min_distance": 150.0,
                                                "general_max_distance": 160.0}),
                           scenes, smoke_nusc, progress=False)


def test_sweep_pairs_of_a_training_scene_are_labelled_like_the_generalisation_set(
        smoke_scenes, smoke_nusc):
    """The smoke world's one swept scene is a test scene; made a training scene here, its
    non-keyframe pairs join the training set: first frame a sweep, ``general_interval``
    frames apart, each object as the generalisation set labels it."""
    p, scenes = smoke_scenes
    swept = scenes["has_sweeps"] & (scenes["split"] != "excluded")
    assert swept.sum() == 1
    as_train = scenes.assign(split=np.where(swept, "train", scenes["split"]))
    pairs, obj = select.select_wide(p, as_train, smoke_nusc, progress=False)
    sweeps = pairs[pairs["set"] == "sweep"]
    assert len(sweeps) > 0 and (obj["set"] == "sweep").sum() > 0
    for r in sweeps.itertuples():
        sd1 = smoke_nusc.get("sample_data", r.sd_token_1)
        assert not sd1["is_key_frame"]
        sd = sd1
        for _ in range(p.general_interval):
            sd = smoke_nusc.get("sample_data", sd["next"])
        assert sd["token"] == r.sd_token_2
    # the generalisation set of the same scene labels the same (frame, vehicle) alike
    gp, go, _ = select.general_set(smoke_nusc, as_train[swept], p, progress=False,
                                   far=p.general_max_distance)
    so = obj[obj["set"] == "sweep"].assign(frame=lambda d: d["pair_id"].str[-4:])
    go = go.assign(frame=go["pair_id"].str[-4:])
    m = so.merge(go, on=["frame", "instance_token"], suffixes=("", "_g"))
    assert len(m) == len(so)
    np.testing.assert_array_equal(m["label"], m["label_g"])
    np.testing.assert_allclose(m["distance"], m["distance_g"])
    # every second frame; none
    half = select.select_wide(p.model_copy(update={"wide_sweep_stride": 2}), as_train,
                              smoke_nusc, progress=False)[0]
    assert (half["set"] == "sweep").sum() < len(sweeps)
    none = select.select_wide(p.model_copy(update={"wide_sweep_stride": 0}), as_train,
                              smoke_nusc, progress=False)[0]
    assert (none["set"] == "sweep").sum() == 0


def test_wide_methods_default_and_checks():
    p = load_profile("demo")
    assert p.wide_methods == ["dis"]
    q = load_profile("demo", wide_methods=None, extension_methods=["dis"])
    assert q.wide_methods == ["dis"], "default: chapter 10's methods"
    with pytest.raises(ProfileError, match="wide_methods.*farneback.*not in flow_methods"):
        load_profile("demo", flow_methods=["gt", "dis"], wide_methods=["farneback"],
                     extension_methods=["gt"])
    assert load_profile("paper", dataroot="/nowhere").wide_methods == []


def test_chapter11_nodes_belong_to_chapter_11_and_need_extension_build():
    demo = load_profile("demo", wide_methods=["gt", "dis"])  # make extensions' matrix
    eleven = [str(n) for n in pipeline.nodes(demo, ["11"])]
    # stage by stage in data order, each node after its inputs
    assert eleven == ["wide", "crops[gt/wide]", "crops[dis/wide]", "wtrain[gt/f0]",
                      "wtrain[gt/f1]", "wtrain[gt/f2]", "wtrain[dis/f0]", "wtrain[dis/f1]",
                      "wtrain[dis/f2]", "wgeneralise[gt]", "wgeneralise[dis]"]
    assert "crops[gt/wide]" not in [str(n) for n in pipeline.nodes(demo, ["05"])]
    smoke = load_profile("smoke")  # flow_store: pairs keeps the flow of the wide pairs too
    assert "flow[dis/wide]" in [str(n) for n in pipeline.nodes(smoke, ["11"])]
    assert [n for n in pipeline.nodes(demo) if pipeline.gate(n) == "extension_build"] == [
        n for n in pipeline.nodes(demo)
        if n.stage in ("xtrain", "xevaluate", "wtrain", "wgeneralise") or n.part == select.WIDE]
    assert pipeline.gate(dag.Node("wide")) is None
    assert pipeline.inputs(dag.Node("crops", "dis", "wide"), demo)[-1] == dag.Node("wide")
    assert not [n for n in pipeline.nodes(load_profile("paper", dataroot="/x"))
                if pipeline.chapter(n) == "11"]


def test_a_missing_gated_node_says_how_to_build_it(tmp_path):
    p = load_profile("smoke", run_dir=str(tmp_path / "runs"))
    with pytest.raises(dag.MissingInput, match="extension_build=true.*make extensions"):
        pipeline.published(p, dag.Node("wtrain", "dis", "f0"))
    with pytest.raises(dag.MissingInput, match=r"run chapter 11 first \(python"):
        pipeline.published(p, dag.Node("wide"))


def test_wide_crops_are_the_keyframe_crops_of_the_same_vehicles(smoke_built):
    """A vehicle in both training sets has the same crop: the same flow, the same window."""
    p = smoke_built
    for split in crops.part_splits("wide", p.folds):
        wx, wdf = crops.read_crops(pipeline.published(p, dag.Node("crops", "dis", "wide")), split)
        kx, kdf = common.open_crops(p, "dis", split)
        key = ["pair_id", "instance_token"]
        m = wdf[key].reset_index().merge(kdf[key].reset_index(), on=key,
                                         suffixes=("_w", "_k"))
        assert len(m) == len(kdf) > 0
        np.testing.assert_array_equal(np.asarray(wx)[m["index_w"]], np.asarray(kx)[m["index_k"]])


def test_table4_rows_and_comparisons_come_from_the_predictions(smoke_built):
    p = smoke_built
    done = ch11.built(p)
    assert done == ["dis"]
    t = ch11.table4(p, done)
    assert list(t["method"].unique()) == [ch11.label(p, "dis", False), ch11.label(p, "dis", True)]
    row = t[(t["method"] == ch11.label(p, "dis", True)) & t["vehicles"].str.endswith("(Table 4)")
            & (t["scored against"] == "paper rule (previous keyframe)")].iloc[0]
    d = ch11.predictions(p, "dis", "general", True)
    d = d[d["distance"] <= p.general_max_distance]
    f1 = np.mean([metrics(d["label"], pr)["f1"] for pr in seed_probs(d)])
    assert row["F1 (%)"] == round(100 * f1, 1) and row["objects"] == len(d)
    # both classifiers on the same objects: the paper's generalisation and test objects
    for split in ("general", "test"):
        a = ch11.predictions(p, "dis", split, True)
        b = ch11.predictions(p, "dis", split, False)
        assert a["ann_token"].equals(b["ann_token"])
        assert len(ch11.comparisons(p, done, split)) == 1
    by = ch11.by_distance(p, done)
    assert list(by) == [ch11.label(p, "dis", False), ch11.label(p, "dis", True)]
    assert sum(by[ch11.label(p, "dis", True)]["n"]) == len(ch11.predictions(
        p, "dis", "general", True).query(f"distance < {ch11.EDGES[-1]}"))
    nf = ch11.near_far(p, done)
    assert (nf.filter(regex="^n ").sum(axis=1) == len(d)).all()
    assert (nf.filter(regex="^moving ").sum(axis=1) == d["label"].sum()).all()
    assert "dis classifier reaches Table 4 F1" in ch11.headline(p, t, done)


def test_chapter11_shows_only_what_was_built_with_these_parameters(smoke_built):
    p = smoke_built.model_copy(update={"extension_build": False})
    assert ch11.built(p) == ["dis"]
    other = p.model_copy(update={"lr": p.lr * 2})  # other models asked for
    pipeline.build(other, ["11"])  # without extension_build: trains nothing
    assert ch11.built(other) == []
    assert "make extensions" in ch11.headline(other, pd.DataFrame(), [])
    assert "make extensions" in ch11.built_note(other, [])
    # the training set is rebuilt by make book (cheap); the models are not
    stride = p.model_copy(update={"wide_sweep_stride": 3})
    st = {s.node: s.state for s in pipeline.status(stride)}
    assert st[dag.Node("wide")] == "stale" and st[dag.Node("wtrain", "dis", "f0")] != "up to date"
    assert ch11.built(stride) == []
    assert "chapter 11's" in pipeline.format_status(stride).splitlines()[-1]
