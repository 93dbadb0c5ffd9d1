"""Chapter 01's backend (``flowmod.chapters.ch01_world``), quick tests for mutation testing:
the difficulty node's numbers, the table of annotations in view and its counts by category and
distance, the exact-flow figure (of the ``example`` node), the devkit's counts and frames, and the two-column tables.

The world ones run on the tiny five-scene world (``tiny_world``/``tiny_nusc``, seconds); every
expected value is computed here from the world's JSON tables and the devkit directly, or by
hand for the hand-made annotation tables, so that a one-line change of the backend (a
comparison, a bin, a colour, a key, a returned value) fails a test.
"""

from __future__ import annotations

import json
import shutil

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import pytest
from nuscenes.nuscenes import NuScenes
from nuscenes.utils.geometry_utils import BoxVisibility
from PIL import Image

from flowmod import pipeline
from flowmod.artefacts import write_manifest
from flowmod.chapters import ch01_world as ch01
from flowmod.dag import MissingInput, Node
from flowmod.difficulty import read_example
from flowmod.params import load_profile


def test_difficulty_reads_the_published_difficulty_node_s_report(tmp_path):
    """The numbers are the published ``difficulty`` node's ``difficulty.json``, as written;
    a run folder without that node is told to build chapter 01."""
    p = load_profile("smoke", run_dir=str(tmp_path / "runs"))
    with pytest.raises(MissingInput, match="chapter 01"):
        ch01.difficulty(p)
    folder = pipeline.GRAPH.node_dir(p, Node("difficulty"))
    folder.mkdir(parents=True)
    report = {"n_objects": 17, "f1_raw_vs_true": 0.625, "rule": "naive"}
    (folder / "difficulty.json").write_text(json.dumps(report))
    write_manifest(folder / "manifest.json", {"fingerprint": "hand-made difficulty"})
    assert ch01.difficulty(p) == report


def _expected_annotations(nusc, threshold: float) -> pd.DataFrame:
    """Every keyframe annotation with a corner in the CAM_FRONT image, scene by scene and
    sample by sample in the devkit's order, computed from the devkit's tables."""
    rows = []
    for scene in nusc.scene:
        items = [s.strip().lower() for s in scene["description"].split(",")]
        ok = not {"night", "rain", "lightning"} & set(items)
        tok = scene["first_sample_token"]
        while tok:
            sample = nusc.get("sample", tok)
            sd_token = sample["data"]["CAM_FRONT"]
            sd = nusc.get("sample_data", sd_token)
            ego = nusc.get("ego_pose", sd["ego_pose_token"])["translation"]
            seen = {b.token for b in nusc.get_sample_data(
                sd_token, box_vis_level=BoxVisibility.ANY)[1]}
            for ann_token in (a for a in sample["anns"] if a in seen):
                ann = nusc.get("sample_annotation", ann_token)
                vx, vy, _ = nusc.box_velocity(ann_token)
                speed = float(np.hypot(vx, vy))
                rows.append({
                    "scene": scene["name"], "usable": ok, "category": ann["category_name"],
                    "distance": float(np.sqrt(sum((a - e) ** 2 for a, e in
                                                  zip(ann["translation"], ego, strict=True)))),
                    "visibility": ann["visibility_token"], "speed": speed,
                    "label": -1 if np.isnan(speed) else int(speed >= threshold),
                    "attribute": nusc.get("attribute", ann["attribute_tokens"][0])["name"]
                    if ann["attribute_tokens"] else ""})
            tok = sample["next"]
    return pd.DataFrame(rows)


def test_annotation_table_has_one_row_per_annotation_in_view(tiny_world, tiny_nusc):
    """One row per keyframe annotation with a corner in view (not every annotation), with
    its scene, whether the scene is usable (not night/rain), category, distance to the ego
    pose, visibility, planar speed, label at the default 2 m/s (-1 without a speed) and first
    attribute; a dataroot (Path, default version) reads the same world."""
    got = ch01.annotation_table(tiny_nusc)
    want = _expected_annotations(tiny_nusc, 2.0)
    pd.testing.assert_frame_equal(got, want, check_exact=False, rtol=1e-9)
    keyframe_anns = sum(len(s["anns"]) for s in tiny_nusc.sample)
    assert 0 < len(got) < keyframe_anns  # some are out of view
    assert set(got["label"]) == {-1, 0, 1} and not got["usable"].all()
    assert ((got["speed"] >= 2.0) & (got["speed"] < 3.0)).any()  # the threshold is seen
    pd.testing.assert_frame_equal(ch01.annotation_table(tiny_world[0]), got)


def test_annotation_table_labels_a_speed_equal_to_the_threshold_moving(tiny_nusc):
    """The label is ``speed >= threshold``: at a threshold equal to an observed speed that
    vehicle is moving, just below it a slower one is still."""
    base = ch01.annotation_table(tiny_nusc)
    speeds = np.sort(base["speed"].dropna().unique())
    at = float(speeds[(speeds > 2.0) & (speeds < 6.0)][0])
    got = ch01.annotation_table(tiny_nusc, speed_threshold=at)
    pd.testing.assert_frame_equal(got, _expected_annotations(tiny_nusc, at),
                                  check_exact=False, rtol=1e-9)
    assert (got.loc[got["speed"] == at, "label"] == 1).all()
    assert (got.loc[got["speed"] < at, "label"] == 0).all()


def test_annotation_table_without_an_attribute_and_with_vertical_motion(tiny_world, tiny_nusc,
                                                                       tmp_path):
    """An annotation without an attribute gets "" and the speed is the planar (x, y) part of
    the devkit's velocity, a vertical motion left out: on a copy of the tiny world's tables
    where one in-view vehicle has no attribute and its next position is 2 m higher."""
    root, version = tiny_world
    shutil.copytree(root / version, tmp_path / version)
    (tmp_path / "maps").symlink_to(root / "maps")  # the devkit opens the map masks
    sample = tiny_nusc.sample[0]
    _, boxes, _ = tiny_nusc.get_sample_data(sample["data"]["CAM_FRONT"],
                                           box_vis_level=BoxVisibility.ANY)
    token = next(b.token for b in boxes
                 if tiny_nusc.get("sample_annotation", b.token)["next"])
    path = tmp_path / version / "sample_annotation.json"
    anns = {a["token"]: a for a in json.loads(path.read_text())}
    anns[token]["attribute_tokens"] = []
    anns[anns[token]["next"]]["translation"][2] += 2.0
    path.write_text(json.dumps(list(anns.values())))
    nusc = NuScenes(version=version, dataroot=str(tmp_path), verbose=False)
    assert nusc.box_velocity(token)[2] > 1.0  # the vertical motion is there
    got = ch01.annotation_table(nusc)
    pd.testing.assert_frame_equal(got, _expected_annotations(nusc, 2.0), check_exact=False,
                                  rtol=1e-9)
    assert got["attribute"].tolist().count("") == 1


def _annotations() -> pd.DataFrame:
    """Hand-made in-view annotations: cars at 10, 29.99, 30 (a bin edge), 45, 69.5 and 80 m,
    trucks at 70 and 500 m, one bus at 50 m; labels -1 (no speed), 0 or 1."""
    rows = [("car", 10.0, 1), ("car", 29.99, 0), ("car", 30.0, 1), ("car", 45.0, 0),
            ("car", 69.5, -1), ("car", 80.0, 0), ("truck", 70.0, 1), ("truck", 500.0, -1),
            ("bus", 50.0, 0)]
    return pd.DataFrame({"scene": [f"scene-{i % 2}" for i in range(len(rows))],
                         "category": [r[0] for r in rows], "distance": [r[1] for r in rows],
                         "label": [r[2] for r in rows]})


def test_counts_table_counts_by_category_and_distance_bin_with_the_moving_share():
    """Counts by category (most annotations first) x the default bins 0-30, 30-70 and
    beyond 70 m (left edge in, right edge out; an empty bin shows 0), their total, and the
    moving share (%, one decimal) of the annotations with a known label."""
    t = ch01.counts_table(_annotations())
    assert list(t.columns) == ["0-30 m", "30-70 m", ">70 m", "total", "moving %"]
    assert t.index.tolist() == ["car", "truck", "bus"]
    assert t["0-30 m"].tolist() == [2, 0, 0]
    assert t["30-70 m"].tolist() == [3, 0, 1]
    assert t[">70 m"].tolist() == [1, 2, 0]
    assert t["total"].tolist() == [6, 2, 1]
    assert t["moving %"].tolist() == pytest.approx([40.0, 100.0, 0.0], abs=1e-12)


def test_counts_table_names_the_bins_it_is_given_and_rounds_the_share():
    """Other bins name themselves ("lo-hi m", the last one open as ">lo m"); the moving
    share is rounded to one decimal (1 of 3: 33.3 %)."""
    a = pd.DataFrame({"scene": ["a"] * 4, "category": ["car"] * 3 + ["van"],
                      "distance": [5.0, 12.0, 40.0, 999.0], "label": [1, 0, 0, 1]})
    t = ch01.counts_table(a, bins=(0, 10, 50, 1000))
    assert list(t.columns) == ["0-10 m", "10-50 m", ">50 m", "total", "moving %"]
    assert t.loc["car"].tolist() == [1, 2, 0, 3, 33.3]
    assert t.loc["van"].tolist() == [0, 0, 1, 1, 100.0]
    t = ch01.counts_table(a, bins=(0, 20, 999))
    assert list(t.columns)[:2] == ["0-20 m", "20-999 m"]
    t = ch01.counts_table(a, bins=(0, 10, 20, 30, 1000))  # no annotation from 20 to 30 m
    assert t["20-30 m"].tolist() == [0, 0] and t["10-20 m"].tolist() == [1, 0]


def test_the_chapter_s_constants():
    """The devkit's scene table shows 12 scenes; the world's distance histogram has 5 m bins
    from 0 to 100 m."""
    assert ch01.SCENES_SHOWN == 12
    assert ch01.DISTANCE_BINS.tolist() == list(range(0, 101, 5))


def test_gt_flow_figure_shows_the_example_node_s_frames_flow_and_valid_pixels(tiny_world,
                                                                               tmp_path):
    """A 12 x 7 in 2 x 2 figure of the published ``example`` node, axes off: the two frames
    titled with their timestamps, the flow titled with its largest valid magnitude, the
    valid mask in grey titled with its share."""
    from conftest import TINY_WORLD

    root, version = tiny_world
    p = load_profile("smoke", dataroot=str(root), version=version, n_jobs=1,
                     run_dir=str(tmp_path / "runs"), **TINY_WORLD)
    pipeline.build(p, ["01"])
    (t1, t2), flow, valid = read_example(pipeline.published(p, Node("example")))
    sd = {r["token"]: r for r in json.loads((root / version / "sample_data.json").read_text())}
    fig = ch01.gt_flow_figure(p)
    axes = fig.axes
    assert len(axes) == 4 and tuple(fig.get_size_inches()) == (12.0, 7.0)
    assert all(not ax.axison for ax in axes)
    peak = np.hypot(flow[..., 0], flow[..., 1])[valid].max()
    assert [ax.get_title() for ax in axes] == [
        f"frame 1  t = {sd[t1]['timestamp']} us", f"frame 2  t = {sd[t2]['timestamp']} us",
        f"GT flow (max |flow| {peak:.1f} px)", f"valid ({100 * valid.mean():.1f} %)"]
    for ax, tok in zip(axes[:2], (t1, t2), strict=True):
        shown = ax.get_images()[0].get_array()
        assert np.array_equal(shown, np.asarray(Image.open(root / sd[tok]["filename"])))
    assert axes[2].get_images()[0].get_array().shape == (*valid.shape, 3)
    mask = axes[3].get_images()[0]
    assert np.array_equal(mask.get_array(), valid) and mask.get_cmap().name == "gray"
    assert sd[t1]["timestamp"] < sd[t2]["timestamp"]
    plt.close(fig)


def test_devkit_counts_are_the_sizes_of_the_world_s_tables(tiny_world, tiny_nusc):
    """Scenes, samples, CAM_FRONT frames, annotations and instances: the lengths of the
    world's JSON tables, under those names."""
    root, version = tiny_world

    def n(table: str) -> int:
        return len(json.loads((root / version / f"{table}.json").read_text()))

    assert ch01.devkit_counts(tiny_nusc) == {
        "scenes": n("scene"), "samples": n("sample"), "CAM_FRONT frames": n("sample_data"),
        "annotations": n("sample_annotation"), "instances": n("instance")}


def test_as_table_lists_a_mapping_in_order_with_floats_to_three_decimals():
    """Keys and values in two named columns, in the mapping's order; floats rounded to 3
    decimals, other values as they are."""
    t = ch01.as_table({"f1": 0.123456, "n": 7, "name": "naive", "big": 2.0005001}, "what", "is")
    assert list(t.columns) == ["what", "is"]
    assert t["what"].tolist() == ["f1", "n", "name", "big"]
    assert t["is"].tolist() == [0.123, 7, "naive", 2.001]


def test_gt_flow_figure_of_an_example_without_valid_pixels_says_0_px(tmp_path, monkeypatch):
    """An example pair with no valid pixel (no exact flow anywhere): the flow's title gives 0
    px as its largest magnitude and the mask 0 %."""
    root = tmp_path / "data"
    (root / "v").mkdir(parents=True)
    for name in ("a.jpg", "b.jpg"):
        Image.new("RGB", (6, 4)).save(root / name)
    (root / "v" / "sample_data.json").write_text(json.dumps([
        {"token": "t1", "filename": "a.jpg", "timestamp": 1},
        {"token": "t2", "filename": "b.jpg", "timestamp": 2}]))
    p = load_profile("smoke", dataroot=str(root), version="v", synthetic=False,
                     run_dir=str(tmp_path / "runs"))
    flow = np.full((4, 6, 2), 3.0, np.float32)
    monkeypatch.setattr(ch01, "read_example",
                        lambda folder: (("t1", "t2"), flow, np.zeros((4, 6), bool)))
    monkeypatch.setattr(ch01.pipeline, "published", lambda params, node: tmp_path)
    fig = ch01.gt_flow_figure(p)
    assert [ax.get_title() for ax in fig.axes][2:] == ["GT flow (max |flow| 0.0 px)",
                                                        "valid (0.0 %)"]
    plt.close(fig)


def test_devkit_frames_render_the_middle_scene_s_first_two_keyframes(tiny_nusc, tmp_path,
                                                                      monkeypatch):
    """The middle scene's first sample and the devkit's renders of it and the next keyframe,
    saved as devkit_0.png and devkit_1.png, returned as BGR images; none of its figures left
    open, none shown (in a notebook a shown figure would be an output of its own)."""
    open_before = set(plt.get_fignums())  # another test's figures, if any
    shown: list = []
    monkeypatch.setattr(plt, "show", lambda *a, **k: shown.append(a))
    first, images = ch01.devkit_frames(tiny_nusc, tmp_path)
    assert shown == []
    scene = tiny_nusc.scene[len(tiny_nusc.scene) // 2]
    assert len(tiny_nusc.scene) == 5 and scene["name"] == "synth-0002"
    assert first == tiny_nusc.get("sample", scene["first_sample_token"])
    assert sorted(f.name for f in tmp_path.iterdir()) == ["devkit_0.png", "devkit_1.png"]
    assert len(images) == 2
    for i, image in enumerate(images):
        rgba = plt.imread(tmp_path / f"devkit_{i}.png")
        assert image.shape == (*rgba.shape[:2], 3)
        assert np.array_equal(image, rgba[..., [2, 1, 0]])
    assert not np.array_equal(images[0], images[1])
    assert not set(plt.get_fignums()) - open_before
