"""Quick tests of the chapters' shared backend (``flowmod/chapters/common.py``), written for
mutation testing: the chapters are otherwise checked only by slow tests that execute the
notebooks on a generated world, which mutmut's quick run (``-m "not slow and not world"``)
leaves out.

What the chapters read from published artefacts (the selection, the flow readers, the
crops, the classifiers' predictions and scores, a model's path) is read here from nodes
published by hand in a demo-profile run folder (a manifest and the node's files, as
tests/handmade.py does), and the pure helpers (the words, verdicts and tables the book
shows) are checked on tiny hand-made inputs. Every expected value is written by hand or
computed with pandas / numpy in the test.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from flowmod import metrics, pipeline
from flowmod.artefacts import write_manifest
from flowmod.chapters import common
from flowmod.dag import MissingInput, Node
from flowmod.params import Params, load_profile

# --- hand-published nodes -----------------------------------------------------------------


def _publish(p: Params, node: Node, tables: dict[str, pd.DataFrame] | None = None,
             **record) -> Path:
    """Publish ``node`` by hand: its parquet ``tables`` and a manifest holding ``record``."""
    folder = pipeline.GRAPH.node_dir(p, node)
    folder.mkdir(parents=True)
    for name, df in (tables or {}).items():
        df.to_parquet(folder / f"{name}.parquet", index=False)
    write_manifest(folder / "manifest.json", {"fingerprint": f"hand-made {node}", **record})
    return folder


@pytest.fixture
def demo(tmp_path) -> Params:
    """The demo profile (flow methods gt, dis, farneback, fastflownet; three folds) on an
    empty run folder."""
    return load_profile("demo", run_dir=str(tmp_path / "runs"))


def test_selection_joins_the_keyframe_set_and_the_generalisation_set(demo):
    """``selection``: the select node's pairs and objects, then the general node's (in that
    order, one index), the select node's scenes and the general node's boxes; without the
    select node a MissingInput naming it."""
    with pytest.raises(MissingInput, match=r"^select has not been built"):
        common.selection(demo)
    key_pairs = pd.DataFrame({"pair_id": ["k1", "k2"], "set": "keyframe"})
    gen_pairs = pd.DataFrame({"pair_id": ["g1"], "set": "general"})
    key_obj = pd.DataFrame({"ann_token": ["a", "b", "c"], "set": "keyframe"})
    gen_obj = pd.DataFrame({"ann_token": ["d", "e"], "set": "general"})
    scenes = pd.DataFrame({"scene": ["s1", "s2"], "split": ["train", "test"]})
    boxes = pd.DataFrame({"ann_token": ["x", "y", "z"]})
    _publish(demo, Node("select"), {"pairs": key_pairs, "objects": key_obj, "scenes": scenes},
             params={"min_distance": 30.0})
    _publish(demo, Node("general"), {"pairs": gen_pairs, "objects": gen_obj, "boxes": boxes})
    sel = common.selection(demo)
    assert sel.pairs["pair_id"].tolist() == ["k1", "k2", "g1"]
    assert sel.pairs.index.tolist() == [0, 1, 2]
    assert sel.objects["ann_token"].tolist() == ["a", "b", "c", "d", "e"]
    assert sel.objects["set"].tolist() == ["keyframe"] * 3 + ["general"] * 2
    pd.testing.assert_frame_equal(sel.scenes, scenes)
    pd.testing.assert_frame_equal(sel.boxes, boxes)


def test_made_with_is_the_select_node_s_recorded_parameters(demo):
    """``made_with``: the ``params`` of the select node's manifest, as recorded."""
    made = {"min_distance": 30.0, "max_distance": 70.0, "speed_threshold": 2.0}
    _publish(demo, Node("select"), params=made)
    assert common.made_with(demo) == made


def _flow_node(p: Params, method: str, part: str) -> None:
    """A published flow node listing one pair, ``<method>-<part>``, in file ``<part>.npz``
    of the method's pool, stored at scale 0.5."""
    _publish(p, Node("flow", method, part),
             {"index": pd.DataFrame({"pair_id": [f"{method}-{part}"], "file": [f"{part}.npz"]})},
             store_scale=0.5)


def test_flow_reader_reads_a_method_s_published_flow_from_its_pool(demo):
    """``flow_reader``: the published ``flow[<method>/<part>]`` node (the keyframe part by
    default), its pairs' files under ``<run>/flow/<method>/pool``, its stored scale."""
    _flow_node(demo, "dis", "keyframe")
    _flow_node(demo, "dis", "general")
    r = common.flow_reader(demo, "dis")
    assert (r.method, r.part, r.pair_ids) == ("dis", "keyframe", ["dis-keyframe"])
    assert r.pool == demo.run_path / "flow" / "dis" / "pool"
    assert r.path("dis-keyframe") == demo.run_path / "flow" / "dis" / "pool" / "keyframe.npz"
    assert r.store_scale == 0.5
    g = common.flow_reader(demo, "dis", "general")
    assert (g.method, g.part, g.pair_ids) == ("dis", "general", ["dis-general"])
    with pytest.raises(MissingInput, match=r"^flow\[gt/keyframe\] has not been built"):
        common.flow_reader(demo, "gt")


def test_flow_readers_open_every_method_and_part_of_the_profile(demo):
    """``flow_readers``: ``{method: {part: reader}}`` over the profile's flow methods (in
    their order) and both parts (keyframe, general), each reader its own node's."""
    for m in demo.flow_methods:
        for part in ("keyframe", "general"):
            _flow_node(demo, m, part)
    got = common.flow_readers(demo)
    assert list(got) == ["gt", "dis", "farneback", "fastflownet"]
    for m, parts in got.items():
        assert list(parts) == ["keyframe", "general"]
        for part, r in parts.items():
            assert (r.method, r.part, r.pair_ids) == (m, part, [f"{m}-{part}"])
            assert r.pool == demo.run_path / "flow" / m / "pool"


def _crops_node(p: Params, method: str, part: str, splits: dict[str, pd.DataFrame]) -> None:
    """A published crops node: per split ``<split>.npy`` (N, 2, 2, 2) float16 whose first
    value is the row's ``id``, and ``<split>.parquet`` (the index)."""
    folder = _publish(p, Node("crops", method, part))
    for split, df in splits.items():
        x = np.zeros((len(df), 2, 2, 2), np.float16)
        x[:, 0, 0, 0] = df["id"].to_numpy()
        np.save(folder / f"{split}.npy", x)
        df.to_parquet(folder / f"{split}.parquet", index=False)


def test_open_crops_reads_a_stored_array_or_the_rows_of_fold_0_s_role(demo):
    """``open_crops``: a stored array (``f<k>``, ``general``) read as it is; a role
    (``train``, ``val``, ``test``) gathered for cross-validation fold 0 of the profile's
    three folds: train and val from the other folds' arrays (val: their validation scenes),
    test fold 0's own; the generalisation set from the general part's node."""
    def fold(k: int, ids: list[int], val: list[bool]) -> pd.DataFrame:
        return pd.DataFrame({"id": ids, "fold": k, "val_scene": val, "split": f"f{k}"})

    _crops_node(demo, "dis", "keyframe", {
        "f0": fold(0, [1, 2], [False, True]), "f1": fold(1, [3, 4, 5], [True, False, False]),
        "f2": fold(2, [6, 7], [False, True])})
    _crops_node(demo, "dis", "general", {"general": pd.DataFrame({"id": [8, 9], "fold": [0, 1],
                                                                  "val_scene": False})})
    for split, ids in (("train", [4, 5, 6]), ("val", [3, 7]), ("test", [1, 2]),
                       ("f1", [3, 4, 5]), ("general", [8, 9])):
        x, df = common.open_crops(demo, "dis", split)
        assert df["id"].tolist() == ids, split
        assert x.shape == (len(ids), 2, 2, 2) and x.dtype == np.float16, split
        assert x[:, 0, 0, 0].tolist() == ids, split


def test_results_are_the_published_predictions_and_scores_of_each_table(handmade_study):
    """``results``: ``test`` (the default) reads the evaluate node's test table and its
    ``scores`` record, ``baseline`` its baseline table and record, ``general`` the
    generalise node's table (no scores: {})."""
    p, tables = handmade_study
    folder = pipeline.GRAPH.node_dir(p, Node("evaluate", "dis"))
    frame, scores = common.results(p, "dis")
    pd.testing.assert_frame_equal(frame, tables[Node("evaluate", "dis")]["test"])
    assert scores == json.loads((folder / "scores.json").read_text())
    assert scores["f1"] > 0
    frame, scores = common.results(p, "dis", "baseline")
    pd.testing.assert_frame_equal(frame, tables[Node("evaluate", "dis")]["baseline"])
    assert scores == json.loads((folder / "baseline.json").read_text())
    frame, scores = common.results(p, "gt", "general")
    pd.testing.assert_frame_equal(frame, tables[Node("generalise", "gt")]["general"])
    assert scores == {}


def test_model_path_is_the_best_weights_of_a_published_training_seed(demo):
    """``model_path``: ``best.pt`` in the published ``train[<method>/<part>]`` node (part
    ``s0`` by default); an unbuilt part is a MissingInput."""
    s0 = _publish(demo, Node("train", "dis", "s0"))
    f1 = _publish(demo, Node("train", "dis", "f1"))
    assert common.model_path(demo, "dis") == s0 / "best.pt"
    assert common.model_path(demo, "dis", "f1") == f1 / "best.pt"
    assert s0 == demo.run_path / "models" / "dis" / "s0"
    with pytest.raises(MissingInput):
        common.model_path(demo, "gt")


# --- words ----------------------------------------------------------------------------------


def test_built_note_counts_what_a_gate_built_and_says_how_to_build_the_rest():
    """``built_note``: "d of n" with the names (or "none"), and while some are missing how
    many, which and the make target of the gate."""
    assert common.built_note("Chains", ["gt/flow"], 3, "dis/flow, images; 6 models",
                             "extension_build") == (
        "Chains with these parameters: **1 of 3** (gt/flow). The other 2 (dis/flow, images; "
        "6 models) are trained by `make extensions` (or this chapter with "
        "`extension_build=true`).")
    assert common.built_note("Networks", [], 1, "raft", "selfflow_build") == (
        "Networks with these parameters: **0 of 1** (none). The other 1 (raft) are trained "
        "by `make selfflow` (or this chapter with `selfflow_build=true`).")
    assert common.built_note("Methods", ["gt", "dis"], 2, "", "extension_build") == (
        "Methods with these parameters: **2 of 2** (gt, dis).")


def _row(verdict: str | None, delta: float = 1.23) -> dict:
    row = {"ΔF1 (points)": delta, "95% CI, scenes and seeds (points)": "-0.5 to 2.9",
           "detectable (points)": 3.456}
    return row if verdict is None else {**row, "verdict": verdict}


def test_difference_words_say_the_effect_its_interval_and_what_an_open_one_means():
    """``difference_words``: the signed effect (0.1) and its interval; an inconclusive one
    adds the smallest difference the scenes would detect, an equivalent one the margin;
    a decided row or one without a verdict nothing; a table row (Series) reads the same."""
    head = "+1.2 F1 points (95 % interval over scenes and training seeds -0.5 to 2.9"
    assert common.difference_words(_row("inconclusive")) == (
        head + "; inconclusive: these scenes would detect 3.5 points or more)")
    assert common.difference_words(_row("equivalent")) == (
        head + "; equivalent: within +/-2 points)")
    assert common.difference_words(_row("A better")) == head + ")"
    assert common.difference_words(_row("B better", -4.06)) == (
        "-4.1 F1 points (95 % interval over scenes and training seeds -0.5 to 2.9)")
    assert common.difference_words(_row(None)) == head + ")"
    assert common.difference_words(pd.Series(_row("inconclusive"))).endswith(
        "would detect 3.5 points or more)")
    assert common.difference_words(pd.Series(_row(None))) == head + ")"


def test_verdict_words_and_the_constants_the_book_shows():
    """``verdict_words`` (", decided" for either side, ", equivalent", nothing for
    inconclusive), ``decided``, the verdict names, the interval labels and the oracle's
    comparison suffix."""
    assert [common.verdict_words(v) for v in ("A better", "B better", "equivalent",
                                              "inconclusive", "undecided")] == [
        ", decided", ", decided", ", equivalent", "", ""]
    assert [common.decided(v) for v in ("A better", "B better", "equivalent", "undecided",
                                        "decided")] == [True, True, False, False, False]
    assert common.VERDICTS == ("decided", "equivalent", "inconclusive")
    assert (common.COUNTS_SEEDS, common.COUNTS_SCENES) == ("scenes and seeds", "scenes only")
    assert common.UNTRAINED_B == ": classifier - oracle rule"
    assert common.SMALLEST_EFFECT == 2.0


def test_interval_counts_needs_two_models_a_fold_in_every_trained_arm():
    """``interval_counts``: scenes and seeds when every trained arm has 2 or more models a
    fold, else scenes only; the oracle rule (the B of a "classifier - oracle rule" name)
    trains nothing and is not counted; without ``training_seeds``, one model each."""
    seeds, scenes = "scenes and seeds", "scenes only"
    cases = [("a - b", [2, 2], seeds), ("a - b", [3, 2], seeds), ("a - b", [2, 1], scenes),
             ("a - b", [1, 3], scenes), ("a - b", [1, 1], scenes),
             ("dis: classifier - oracle rule", [2, 1], seeds),
             ("dis: classifier - oracle rule", [1, 1], scenes),
             ("dis: classifier - oracle rule x", [2, 1], scenes)]
    for name, n, want in cases:
        assert common.interval_counts(name, {"training_seeds": n}) == want, (name, n)
    assert common.interval_counts("a - b", {}) == scenes
    assert common.interval_counts("dis: classifier - oracle rule", {}) == scenes


def test_comparison_table_gives_three_verdicts_and_what_each_interval_counts():
    """``comparison_table``: the metrics table with "interval counts" as fourth column; a
    decided verdict kept as A/B better, an undecided one "equivalent" only strictly inside
    +/- 2 points, else (an undefined interval too) "inconclusive"."""
    base = {"detectable": 0.03, "per_seed": [0.01], "p_not_better": 0.4, "n_scenes": 12,
            "n": 40, "delta_f1": 0.001}
    rows = {"a - b": {**base, "ci": (0.001, 0.03), "training_seeds": [3, 3]},
            "c - d": {**base, "ci": (-0.0199, 0.0199), "training_seeds": [3, 1]},
            "e - f": {**base, "ci": (-0.02, 0.01), "training_seeds": [2, 2]},
            "g - h": {**base, "ci": (-0.01, 0.02)},
            "i - j": {**base, "ci": (-0.05, -0.021), "training_seeds": [1, 1]},
            "k - l": {**base, "ci": (float("nan"), float("nan"))}}
    t = common.comparison_table(rows)
    assert t.columns.tolist()[:5] == ["comparison", "ΔF1 (points)",
                                      "95% CI, scenes and seeds (points)", "interval counts",
                                      "verdict"]
    assert t["comparison"].tolist() == list(rows)
    assert t["verdict"].tolist() == ["A better", "equivalent", "inconclusive", "inconclusive",
                                     "B better", "inconclusive"]
    assert t["interval counts"].tolist() == ["scenes and seeds", "scenes only",
                                             "scenes and seeds", "scenes only", "scenes only",
                                             "scenes only"]


def test_three_verdicts_reads_each_end_of_the_interval_and_names_bad_input():
    """``three_verdicts``: an interval with one undefined end is inconclusive (whatever the
    other end); a point interval off 0 is decided; the errors name the bad value."""
    assert common.three_verdicts((float("nan"), -1.0), 2.0) == "inconclusive"
    assert common.three_verdicts((1.0, float("nan")), 2.0) == "inconclusive"
    assert common.three_verdicts((0.5, 0.5), 2.0) == "decided"
    assert common.three_verdicts((-0.5, -0.5), 2.0) == "decided"
    assert common.three_verdicts((0.0, 0.0), 2.0) == "equivalent"
    assert common.three_verdicts((-1.99, 1.99), 2.0) == "equivalent"
    assert common.three_verdicts((-2.0, 1.0), 2.0) == "inconclusive"
    assert common.three_verdicts(np.array([-0.1, 0.1]), 0.5) == "equivalent"
    with pytest.raises(ValueError, match=r"^the smallest effect that matters must be positive, "
                                         r"got 0\.0$"):
        common.three_verdicts((-0.1, 0.1), 0.0)
    with pytest.raises(ValueError, match=r"^interval \(0\.5, 0\.1\) has its low end above its "
                                         r"high end$"):
        common.three_verdicts((0.5, 0.1), 1.0)


def test_headline_method_is_the_first_estimated_flow():
    """``headline_method``: the first flow method other than gt, the exact flow only when
    it is the only one."""
    def of(*methods: str) -> str:
        return common.headline_method(SimpleNamespace(flow_methods=list(methods)))

    assert of("gt", "dis", "farneback") == "dis"
    assert of("farneback", "gt", "dis") == "farneback"
    assert of("gt", "fastflownet") == "fastflownet"
    assert of("gt") == "gt"
    assert common.headline_method(load_profile("demo")) == "dis"


def test_split_order_puts_the_splits_in_book_order_then_the_folds():
    """``split_order``: train, val, test (those present), then any other split sorted,
    each once."""
    assert common.split_order(["f1", "test", "train", "f0", "val", "train"]) == [
        "train", "val", "test", "f0", "f1"]
    assert common.split_order(pd.Series(["test", "val"])) == ["val", "test"]
    assert common.split_order(["f2", "f10", "f1"]) == ["f1", "f10", "f2"]
    assert common.split_order([]) == []


# --- the selection's counts ---------------------------------------------------------------


def _selection(fold_pairs: bool) -> common.Selection:
    """Keyframe pairs and objects by split (or by fold, with validation scenes), and
    generalisation rows that the keyframe counts must leave out."""
    if fold_pairs:
        key = pd.DataFrame({"split": ["f0", "f0", "f0", "f1", "f2", "f2"],
                            "scene": ["a", "a", "b", "c", "d", "e"],
                            "val_scene": [True, True, False, False, True, True]})
        obj = pd.DataFrame({"split": ["f0", "f0", "f0", "f1"], "label": [1, 0, 0, 1]})
    else:
        key = pd.DataFrame({"split": ["test", "train", "train", "train", "test", "val"],
                            "scene": ["t1", "s1", "s1", "s2", "t2", "v1"],
                            "val_scene": False})
        obj = pd.DataFrame({"split": ["train"] * 4 + ["val"] + ["test"] * 3,
                            "label": [1, 1, 0, 1, 1, 0, 1, 0]})
    key = key.assign(set="keyframe", fold=0)
    gen = pd.DataFrame({"split": ["general"] * 3, "scene": ["g1", "g2", "g2"],
                        "val_scene": False, "set": "general", "fold": 0})
    gobj = pd.DataFrame({"split": ["general"] * 5, "label": [1, 0, 0, 0, 0], "set": "general"})
    return common.Selection(pd.concat([key, gen], ignore_index=True),
                            pd.concat([obj.assign(set="keyframe"), gobj], ignore_index=True),
                            pd.DataFrame())


def test_split_sizes_count_scenes_pairs_and_movers_per_split():
    """``split_sizes`` of the keyframe set (default) and of the generalisation set: scenes,
    pairs, objects, moving, still and the moving share (0.1) per split in book order."""
    t = common.split_sizes(_selection(False))
    assert t.index.tolist() == ["train", "val", "test"]
    assert t.columns.tolist() == ["scenes", "pairs", "objects", "moving", "still", "moving %"]
    assert t.to_dict("list") == {"scenes": [2, 1, 2], "pairs": [3, 1, 2],
                                 "objects": [4, 1, 3], "moving": [3, 1, 1],
                                 "still": [1, 0, 2], "moving %": [75.0, 100.0, 33.3]}
    assert t["scenes"].dtype == np.int64 and t["moving %"].dtype == np.float64
    g = common.split_sizes(_selection(False), "general")
    assert g.index.tolist() == ["general"]
    assert g.iloc[0].tolist() == [2, 3, 5, 1, 4, 20.0]


def test_split_sizes_by_fold_count_the_validation_scenes():
    """``split_sizes`` with cross-validation: one row per fold, a fold without objects
    counted 0 (0.0 % moving), and each fold's scenes that the other folds' models validate
    on."""
    t = common.split_sizes(_selection(True))
    assert t.index.tolist() == ["f0", "f1", "f2"]
    assert t.columns.tolist() == ["scenes", "pairs", "objects", "moving", "still", "moving %",
                                  "val scenes"]
    assert t.to_dict("list") == {"scenes": [2, 1, 2], "pairs": [3, 1, 2],
                                 "objects": [3, 1, 0], "moving": [1, 1, 0],
                                 "still": [2, 0, 0], "moving %": [33.3, 100.0, 0.0],
                                 "val scenes": [1, 0, 2]}
    assert t["val scenes"].dtype == np.int64


def test_n_scored_objects_is_the_test_split_or_every_keyframe_object():
    """``n_scored_objects``: one fold scores the keyframe test split's objects; with
    cross-validation every keyframe object (never the generalisation set's)."""
    sel = _selection(False)
    assert common.n_scored_objects(sel, 1) == 3
    assert common.n_scored_objects(sel, 2) == 8
    assert common.n_scored_objects(sel, 3) == 8
    assert isinstance(common.n_scored_objects(sel, 1), int)


def test_epe_ci_resamples_scenes_with_the_given_seed():
    """``epe_ci``: the percentile interval (2 decimals) of the mean over pairs with whole
    scenes resampled by the given seed; the flag counts distinct scenes."""
    values = [1.0, 2.0, 4.0, 8.0, 3.0, 5.0, 9.0, 0.5, 6.0, 7.0, 2.5, 1.5]
    scenes = [f"s{i}" for i in range(12)]
    for seed in (0, 7):
        lo, hi = metrics.interval(metrics.group_mean_bootstrap(values, scenes, seed=seed))
        assert common.epe_ci(values, scenes, seed) == f"{lo:.2f}-{hi:.2f}"
    assert common.epe_ci(values, scenes, 0) != common.epe_ci(values, scenes, 7)
    few = common.epe_ci(values, [f"s{i % 9}" for i in range(12)], 3)
    assert few.endswith(" (9 scenes: too few)")
    assert common.epe_ci(np.array(values), tuple(scenes), 0) == common.epe_ci(values, scenes, 0)


def test_breakdown_scores_each_group_over_every_seed():
    """``breakdown`` of a predictions table by category: per group the objects, movers and
    F1 as the mean over the seeds' F1, and the scenes its interval resamples."""
    df = pd.DataFrame({"label": [1, 1, 0, 1, 0, 1, 0, 0], "scene": list("aabbccdd"),
                       "category": ["car", "bus"] * 4,
                       "prob_s0": [0.9, 0.8, 0.7, 0.2, 0.1, 0.9, 0.6, 0.3],
                       "prob_s1": [0.2, 0.9, 0.1, 0.8, 0.9, 0.7, 0.2, 0.1]})
    got = common.breakdown(df, "category").set_index("category")
    # car: labels 1 0 0 0, s0 calls 1 1 0 1 (F1 2/4), s1 0 0 1 0 (F1 0)
    # bus: labels 1 1 1 0, s0 calls 1 0 1 0 (F1 4/5), s1 1 1 1 0 (F1 1)
    assert got.index.tolist() == ["bus", "car"]
    assert got["n"].tolist() == [4, 4] and got["n_moving"].tolist() == [3, 1]
    assert got["f1"].tolist() == pytest.approx([(0.8 + 1.0) / 2, 0.25])
    assert got["scenes"].tolist() == [4, 4]
    assert not math.isnan(got.loc["bus", "ci_lo"])
    binned = common.breakdown(df.assign(distance=[5.0, 15.0, 25.0, 35.0] * 2), "distance",
                              bins=[0, 20, 40])
    assert binned["distance_bin"].tolist() == ["[0, 20)", "[20, 40)"]
    assert binned["n"].tolist() == [4, 4] and binned["n_moving"].tolist() == [3, 1]
