"""The exact flow the chapters show comes from nodes (issue 51: no chapter backend computes
flow while its notebook executes): chapter 01's ``example`` node and chapter 03's
``flowcheck`` node, whose rows chapters 03 and 09 aggregate.

Quick: the tiny world (seconds) and hand-made arrays and rows.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from flowmod import dag, difficulty, pipeline
from flowmod.chapters import ch03_flow, ch09_blind_spots
from flowmod.flow import accuracy
from flowmod.params import load_profile
from flowmod.world import gt_flow

# --- chapter 01's example node --------------------------------------------------------------


def test_the_example_pair_is_the_middle_scene_s_first_two_keyframes(tiny_world, tiny_nusc):
    """The tokens the devkit gives for the middle scene's first two CAM_FRONT keyframes (the
    frames chapter 01 shows through the devkit)."""
    root, version = tiny_world
    scene = tiny_nusc.scene[len(tiny_nusc.scene) // 2]
    first = tiny_nusc.get("sample", scene["first_sample_token"])
    second = tiny_nusc.get("sample", first["next"])
    want = (first["data"]["CAM_FRONT"], second["data"]["CAM_FRONT"])
    assert difficulty.example_tokens(root, version) == want
    assert len(tiny_nusc.scene) > 2  # the middle is not the first


def _tiny(root, version, tmp_path):
    """The smoke profile on the tiny world (conftest.py's TINY_WORLD) with its own run
    folder."""
    from conftest import TINY_WORLD

    return load_profile("smoke", dataroot=str(root), version=version, n_jobs=1,
                        run_dir=str(tmp_path / "runs"), **TINY_WORLD)


def test_the_example_node_keeps_the_pair_s_exact_flow(tiny_world, tmp_path):
    """Building chapter 01 publishes the example pair's exact flow (float16: within its
    rounding, 2^-11 of the value) and valid mask, which the chapter's figure reads."""
    root, version = tiny_world
    p = _tiny(root, version, tmp_path)
    assert p.dataroot_path == root and dag.Node("example") in pipeline.nodes(p)
    pipeline.build(p, ["01"])
    tokens, flow, valid = difficulty.read_example(pipeline.published(p, dag.Node("example")))
    assert tokens == difficulty.example_tokens(root, version)
    want, want_valid = gt_flow(root, version, *tokens)
    assert flow.dtype == np.float32 and flow.shape == want.shape
    np.testing.assert_array_equal(valid, want_valid)
    assert (np.abs(flow - want) <= np.abs(want) * 2.0 ** -11 + 1e-4).all()
    assert np.abs(want[valid]).max() > 1  # a pair that moves


# --- chapter 03's flowcheck node ------------------------------------------------------------


def test_pairs_are_drawn_among_those_every_method_stores():
    """``pick_pairs``: ``n`` distinct ids of the set asked, each stored by every method, the
    same for the same stream; all of them when fewer qualify; none when none does."""
    pairs = pd.DataFrame({"pair_id": [f"k{i}" for i in range(8)] + ["g0", "g1"],
                          "set": ["keyframe"] * 8 + ["general"] * 2})
    stored = [{f"k{i}" for i in range(8)} | {"g0"}, {"k0", "k1", "k2", "k3", "k5", "g0", "g1"}]
    got = accuracy.pick_pairs(pairs, "keyframe", stored, 3, np.random.default_rng(4))
    assert len(set(got)) == 3 and set(got) <= {"k0", "k1", "k2", "k3", "k5"}
    assert got == accuracy.pick_pairs(pairs, "keyframe", stored, 3, np.random.default_rng(4))
    assert got == list(np.random.default_rng(4).choice(["k0", "k1", "k2", "k3", "k5"], 3,
                                                       replace=False))
    assert sorted(accuracy.pick_pairs(pairs, "keyframe", stored, 9,
                                      np.random.default_rng(0))) == ["k0", "k1", "k2", "k3", "k5"]
    assert accuracy.pick_pairs(pairs, "general", stored, 2, np.random.default_rng(0)) == ["g0"]
    assert accuracy.pick_pairs(pairs, "general", [set()], 2, np.random.default_rng(0)) == []


def test_a_pair_s_rows_score_each_method_over_the_frame_and_in_the_boxes():
    """``pair_rows``: end-point error (px) and Fl-all (%) over the valid pixels and inside the
    boxes; NaN in the boxes when none of their pixels is valid."""
    gt = np.zeros((20, 30, 2), np.float32)
    gt[..., 0] = 10.0
    valid = np.ones((20, 30), bool)
    valid[:, 25:] = False
    off = gt.copy()
    off[:10, :10] += (3.0, 4.0)  # 5 px off in the top-left corner, beyond 3 px and 5 %
    rows = accuracy.pair_rows("p", {"exact": gt, "off": off}, gt, valid,
                              np.array([[0.0, 0.0, 9.0, 9.0]]))
    assert [r["method"] for r in rows] == ["exact", "off"]
    assert {r["pair_id"] for r in rows} == {"p"}
    exact, bad = rows
    assert exact["epe"] == 0 and exact["fl"] == 0 and exact["epe_box"] == 0
    assert bad["epe"] == pytest.approx(5.0 * 100 / (20 * 25))
    assert bad["fl"] == pytest.approx(100.0 * 100 / (20 * 25))
    assert bad["epe_box"] == pytest.approx(5.0) and bad["fl_box"] == pytest.approx(100.0)
    hidden = accuracy.pair_rows("p", {"off": off}, gt, valid, np.array([[26.0, 0.0, 29.0, 5.0]]))
    assert np.isnan(hidden[0]["epe_box"]) and np.isnan(hidden[0]["fl_box"])
    assert hidden[0]["epe"] == pytest.approx(bad["epe"])


#: Hand-made flowcheck rows: two far pairs (scenes a, b) and one near pair, two methods;
#: the far pair of scene b has no valid box pixel (NaN).
ROWS = pd.DataFrame([
    ("keyframe", "k1", "a", "dis", 1.0, 10.0, 2.0, 20.0),
    ("keyframe", "k1", "a", "gt", 0.0, 0.0, 0.0, 0.0),
    ("keyframe", "k2", "b", "dis", 3.0, 30.0, np.nan, np.nan),
    ("keyframe", "k2", "b", "gt", 0.5, 1.0, np.nan, np.nan),
    ("general", "g1", "c", "dis", 4.0, 40.0, 6.0, 60.0),
    ("general", "g1", "c", "gt", 0.0, 0.0, 1.0, 2.0),
], columns=list(accuracy.COLUMNS))


def test_chapter03_aggregates_the_node_s_rows_per_set_and_method():
    """Chapter 03's table: means over the node's pairs, the boxes' over the pairs with a
    valid box pixel, the median seconds of every stored pair, in set then method order."""
    p = load_profile("demo")
    readers = {m: {part: SimpleNamespace(index=pd.DataFrame({"seconds": secs}))
                   for part in ("keyframe", "general")}
               for m, secs in (("gt", [0.2, 0.4, 0.9]), ("dis", [1.0, 3.0]))}
    got = ch03_flow.accuracy_table(p, ROWS, readers)
    assert list(zip(got["set"], got["method"], strict=True)) == [
        ("keyframe", "gt"), ("keyframe", "dis"), ("general", "gt"), ("general", "dis")]
    assert got["vehicles"].tolist() == ["30-70 m"] * 2 + ["0-30 m"] * 2
    assert got["EPE all (px)"].tolist() == pytest.approx([0.25, 2.0, 0.0, 4.0])
    assert got["Fl-all (%)"].tolist() == pytest.approx([0.5, 20.0, 0.0, 40.0])
    assert got["EPE boxes (px)"].tolist() == pytest.approx([0.0, 2.0, 1.0, 6.0])
    assert got["Fl-all boxes (%)"].tolist() == pytest.approx([0.0, 20.0, 2.0, 60.0])
    assert got["s / pair"].tolist() == pytest.approx([0.4, 2.0, 0.4, 2.0])
    assert got["pairs"].tolist() == [2, 2, 1, 1]
    assert got["EPE boxes 95% CI, scenes (px)"].str.contains("too few").all()


def test_chapter03_table_skips_a_method_without_rows_and_reads_the_profile_s_seed():
    """A method of the readers without rows in a set is left out of it (the methods after
    it are not); a pair whose whole-frame Fl-all is missing still counts in the boxes' mean;
    the boxes' interval over scenes draws with the profile's seed."""
    from flowmod.chapters import common

    boxes = [0.0, 0.3, 1.7, 0.2, 5.0, 0.9]
    rows = pd.DataFrame([("keyframe", f"k{i}", f"s{i}", "dis", 1.0 + i,
                          np.nan if i == 0 else 10.0, e, 5.0 * i) for i, e in enumerate(boxes)],
                        columns=list(accuracy.COLUMNS))
    readers = {m: {part: SimpleNamespace(index=pd.DataFrame({"seconds": [1.0]}))
                   for part in ("keyframe", "general")} for m in ("farneback", "dis")}
    p = load_profile("demo", seed=3)
    got = ch03_flow.accuracy_table(p, rows, readers)
    assert got["method"].tolist() == ["dis"] and got["set"].tolist() == ["keyframe"]
    assert got["EPE boxes (px)"].tolist() == pytest.approx([sum(boxes) / 6], rel=1e-12)
    ci = got["EPE boxes 95% CI, scenes (px)"].iloc[0]
    assert ci == common.epe_ci(boxes, rows["scene"], 3) == "0.27-2.83 (6 scenes: too few)"
    assert ci != common.epe_ci(boxes, rows["scene"], 1)


def test_chapter03_reads_the_published_flowcheck_rows(tmp_path):
    """accuracy_rows: the rows of the published ``flowcheck`` node, as written."""
    from handmade import publish

    p = load_profile("demo", run_dir=str(tmp_path / "runs"))
    publish(p, dag.Node("flowcheck"), {"accuracy": ROWS})
    pd.testing.assert_frame_equal(ch03_flow.accuracy_rows(p), ROWS)


def test_chapter09_reads_the_far_boxes_error_of_the_node_s_keyframe_pairs():
    """Chapter 09's table: per method, the mean over the far pairs with a valid box pixel."""
    got = ch09_blind_spots.far_box_error(ROWS)
    assert got["method"].tolist() == ["dis", "gt"]
    assert got["EPE boxes (px)"].tolist() == pytest.approx([2.0, 0.0])
    assert got["Fl-all boxes (%)"].tolist() == pytest.approx([20.0, 0.0])
