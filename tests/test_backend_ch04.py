"""Chapter 04's backend (:mod:`flowmod.chapters.ch04_labeling`) in quick tests, for mutation
testing: mutmut runs only the quick tests, and the chapter is otherwise checked only by the
slow notebook runs. Complements tests/test_tables.py (speeds by label, the agreements, one
example's title): the keyframe set's rows, the examples near the threshold drawn with the
profile's seed, the glued numbers' decimals and the titles of several examples. Expected
values are worked out by hand or with pandas directly, on hand-made tables.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from flowmod.chapters import ch04_labeling as ch04
from flowmod.params import load_profile
from flowmod.select import Selection


def _key(speeds, distances=None) -> pd.DataFrame:
    """Keyframe objects with the examples table's columns, one per speed (m/s)."""
    n = len(speeds)
    return pd.DataFrame({
        "pair_id": [f"pair-{i}" for i in range(n)], "category": "vehicle.car",
        "distance": distances if distances is not None else [40.0 + i for i in range(n)],
        "speed": speeds, "label": [int(s > 2.0) for s in speeds],
        "attribute": "vehicle.moving", "box_speed": [s + 0.1 for s in speeds],
    }, index=[10 * i + 3 for i in range(n)])


def test_keyframe_objects_are_the_keyframe_set_s_rows_in_order():
    """keyframe_objects: the selection's objects of the keyframe set only (not the
    generalisation set's), with their rows, index and order unchanged."""
    objects = pd.DataFrame({"set": ["general", "keyframe", "keyframe", "general", "keyframe"],
                            "pair_id": ["g1", "k1", "k2", "g2", "k3"],
                            "label": [1, 0, 1, 1, 0]}, index=[5, 7, 2, 9, 4])
    sel = Selection(pairs=pd.DataFrame(), objects=objects, scenes=pd.DataFrame())
    got = ch04.keyframe_objects(sel)
    assert got["pair_id"].tolist() == ["k1", "k2", "k3"]
    assert got.index.tolist() == [7, 2, 4]
    assert got["label"].tolist() == [0, 1, 0]


def test_the_glued_shares_keep_one_and_two_decimals():
    """moving_fraction rounds the moving share (%) to one decimal, true_agreement the share
    of labels equal to the true ones to two: 1 of 3 is 33.3 and 33.33, 2 of 7 28.6 and
    28.57."""
    three = pd.DataFrame({"label": [1, 0, 0], "true_label": [1, 1, 1]})
    seven = pd.DataFrame({"label": [1, 1, 0, 0, 0, 0, 0], "true_label": [1, 1, 1, 1, 1, 1, 1]})
    assert ch04.moving_fraction(three) == 33.3
    assert ch04.true_agreement(three) == 33.33
    assert ch04.moving_fraction(seven) == 28.6
    assert ch04.true_agreement(seven) == 28.57
    boxes = pd.DataFrame({"label": [1, 0, 1, 0, 1, 1, 1], "box_label": [1, 0, 0, -1, 0, 1, 1]})
    assert ch04.box_agreement(boxes) == 66.7  # 4 of the 6 the devkit can label


def test_near_threshold_shows_the_six_nearest_within_half_a_metre_per_second():
    """near_threshold: at most NEAR_EXAMPLES (6) vehicles whose speed is less than 0.5 m/s
    from the threshold (0.5 away is out), nearest first, with the examples table's columns."""
    speeds = [2.5, 1.6, 2.1, 0.3, 2.45, 1.95, 2.3, 1.8, 2.48, 3.0]
    near = ch04.near_threshold(load_profile("smoke", seed=0), _key(speeds), 2.0)
    assert ch04.NEAR_EXAMPLES == 6
    # gaps: 1.95 0.05, 2.1 0.1, 1.8 0.2, 2.3 0.3, 1.6 0.4, 2.45 0.45 (2.48: 0.48, 7th)
    assert near["speed"].tolist() == [1.95, 2.1, 1.8, 2.3, 1.6, 2.45]
    assert near.index.tolist() == [53, 23, 73, 63, 13, 43]
    assert near[ch04.NEAR_COLUMNS].columns.tolist() == [
        "pair_id", "category", "distance", "speed", "label", "attribute", "box_speed"]
    assert ch04.near_threshold(load_profile("smoke"), _key([0.3, 4.0]), 2.0).empty


def test_near_threshold_draws_its_candidates_with_the_profile_s_seed():
    """With more candidates than four times the examples shown, near_threshold draws 24 of
    them with the profile's seed (pandas' sample) and shows the 6 nearest of those."""
    rng = np.random.default_rng(1)
    speeds = list(2.0 + rng.uniform(-0.49, 0.49, 40).round(4))
    key = _key(speeds)
    seed = 7
    drawn = key.sample(24, random_state=seed)
    want = drawn.assign(gap=(drawn["speed"] - 2.0).abs()).nsmallest(6, "gap")
    got = ch04.near_threshold(load_profile("smoke", seed=seed), key, 2.0)
    assert got.index.tolist() == want.index.tolist()
    assert got.index.tolist() != key.assign(gap=(key["speed"] - 2.0).abs()).nsmallest(
        6, "gap").index.tolist()  # not simply the 6 nearest of all
    other = key.sample(24, random_state=0)
    assert got.index.tolist() != other.assign(gap=(other["speed"] - 2.0).abs()).nsmallest(
        6, "gap").index.tolist()  # nor those of seed 0


def test_near_titles_give_each_example_s_speed_and_distance():
    """near_titles: one title per example, in order: speed to 0.01 m/s, distance to 1 m."""
    near = _key([1.954, 2.1, 0.005], distances=[30.4, 69.6, 45.0])
    assert ch04.near_titles(near) == ["1.95 m/s, 30 m", "2.10 m/s, 70 m", "0.01 m/s, 45 m"]
    assert ch04.near_titles(near.iloc[:0]) == []
