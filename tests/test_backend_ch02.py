"""Chapter 02's backend (``flowmod.chapters.ch02_filtering``), quick tests for mutation
testing: the distance histogram's bins, Table 1 as the chapter shows it, what each step of the
selection keeps, the keyframe distances by split and the sentence the chapter glues about
them. Inputs are hand-made (a profile's values, a tiny ``Selection``), and every expected
cell and word is written here by hand. No world, no run folder.
"""

from __future__ import annotations

import pandas as pd

from flowmod.chapters import ch02_filtering as ch02
from flowmod.params import load_profile
from flowmod.select import Selection


def test_distance_bins_step_2_5_m_over_the_selected_band_ends_included():
    """The bins run from the band's near end to its far end in 2.5 m steps, both ends
    included (the chapter's constant is 2.5 m, and four example frames)."""
    assert ch02.DISTANCE_BIN == 2.5 and ch02.EXAMPLES == 4
    got = ch02.distance_bins(load_profile("smoke", min_distance=30.0, max_distance=40.0))
    assert got.tolist() == [30.0, 32.5, 35.0, 37.5, 40.0]
    got = ch02.distance_bins(load_profile("smoke", min_distance=5.0, max_distance=10.0))
    assert got.tolist() == [5.0, 7.5, 10.0]


def test_table1_words_every_setting_from_the_parameters():
    """Table 1: five settings in the paper's order; categories one a line, the band with
    ``:g`` numbers and the origin, visibility bins sorted by token, the camera, the excluded
    descriptions joined by commas."""
    p = load_profile("smoke", categories=["vehicle.car", "vehicle.truck"], min_distance=12.5,
                     max_distance=60.0, distance_mode="camera", visibility_tokens=["4", "2"],
                     exclude_descriptions=["night", "rain"])
    t = ch02.table1(p)
    assert list(t.columns) == ["setting", "description"]
    assert t["setting"].tolist() == ["Target categories", "Distance", "Visibility", "Sensor",
                                     "Excluded scenes"]
    assert t["description"].tolist() == ["vehicle.car\nvehicle.truck",
                                         "12.5 m - 60 m (camera origin)",
                                         "40-60 %, 80-100 %", "CAM_FRONT", "night, rain"]


def test_table1_names_each_visibility_bin_and_says_none_when_no_scene_is_excluded():
    """Each of the four visibility tokens has its own range; no excluded description reads
    "none"; the ego origin is named as such."""
    p = load_profile("smoke", visibility_tokens=["3", "1", "4", "2"], exclude_descriptions=[],
                     min_distance=30.0, max_distance=70.0, distance_mode="ego")
    d = ch02.table1(p).set_index("setting")["description"]
    assert d["Visibility"] == "0-40 %, 40-60 %, 60-80 %, 80-100 %"
    assert d["Excluded scenes"] == "none"
    assert d["Distance"] == "30 m - 70 m (ego origin)"


def _selection() -> Selection:
    """Seven scenes (two night, one rain: three excluded), five keyframe pairs and four
    generalisation pairs over two scenes; seven keyframe and three generalisation objects."""
    scenes = pd.DataFrame({"scene": [f"s{i}" for i in range(7)],
                           "excluded_by": ["", "night", "", "rain", "night", "", ""]})
    pairs = pd.DataFrame({"set": ["keyframe"] * 5 + ["general"] * 4,
                          "scene": ["s0", "s0", "s2", "s5", "s6", "s5", "s5", "s6", "s5"]})
    objects = pd.DataFrame({"set": ["keyframe"] * 7 + ["general"] * 3})
    return Selection(pairs=pairs, objects=objects, scenes=scenes)


def test_step_counts_lists_each_step_with_the_scenes_pairs_and_objects_it_keeps():
    """The steps in order: all scenes, each exclusion reason (most scenes first) quoted,
    the scenes kept, keyframe pairs and objects, generalisation scenes, pairs and objects."""
    t = ch02.step_counts(_selection())
    assert list(t.columns) == ["step", "count"]
    assert t["step"].tolist() == [
        "scenes in the data set", "scenes excluded: 'night'", "scenes excluded: 'rain'",
        "scenes kept", "keyframe pairs with a target vehicle",
        "target vehicles in keyframe pairs", "generalisation scenes", "generalisation pairs",
        "generalisation objects"]
    assert t["count"].tolist() == [7, 2, 1, 4, 5, 7, 2, 4, 3]


def test_step_counts_without_exclusions_has_no_exclusion_rows():
    """No scene excluded: no "scenes excluded" row, every scene kept."""
    sel = _selection()
    sel.scenes["excluded_by"] = ""
    t = ch02.step_counts(sel)
    assert t["step"].tolist()[:2] == ["scenes in the data set", "scenes kept"]
    assert t["count"].tolist()[:2] == [7, 7]


def _objects() -> pd.DataFrame:
    return pd.DataFrame({
        "set": ["keyframe", "keyframe", "general", "keyframe", "keyframe", "keyframe",
                "general"],
        "split": ["f1", "f0", "f0", "f1", "f2", "f0", "f3"],
        "distance": [31.0, 42.5, 99.0, 55.25, 64.0, 38.0, 12.0]})


def test_distance_groups_are_the_keyframe_distances_of_each_split_sorted_by_name():
    """One group per split with keyframe objects (a split only in the generalisation set is
    none), keyed by its name as text and sorted, holding those objects' distances."""
    got = ch02.distance_groups(_objects())
    assert list(got) == ["f0", "f1", "f2"]
    assert got["f0"].tolist() == [42.5, 38.0]
    assert got["f1"].tolist() == [31.0, 55.25]
    assert got["f2"].tolist() == [64.0]
    numbered = _objects().assign(split=[1, 0, 0, 1, 2, 0, 3])
    assert list(ch02.distance_groups(numbered)) == ["0", "1", "2"]


def test_distance_words_give_each_group_s_count_range_and_median():
    """Each non-empty group: "<name>: <n> vehicles, <min>-<max> m, median <median> m" (one
    decimal), joined by "; " and ended by a full stop."""
    groups = {"train": pd.Series([31.0, 42.46, 55.26, 38.0]), "test": pd.Series([64.04])}
    assert ch02.distance_words(groups) == (
        "train: 4 vehicles, 31.0-55.3 m, median 40.2 m; test: 1 vehicles, 64.0-64.0 m, "
        "median 64.0 m.")


def test_distance_words_name_the_groups_without_a_vehicle():
    """Groups without a vehicle are left out of the figures and named after them."""
    empty = pd.Series([], dtype=float)
    groups = {"f0": empty, "f1": pd.Series([30.0, 70.0]), "f2": empty}
    assert ch02.distance_words(groups) == (
        "f1: 2 vehicles, 30.0-70.0 m, median 50.0 m. No vehicle in f0, f2.")
    assert ch02.distance_words({"f1": pd.Series([33.33])}) == (
        "f1: 1 vehicles, 33.3-33.3 m, median 33.3 m.")

