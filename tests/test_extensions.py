"""flowmod.extensions: the geometry of motion seen from the camera, and its image signal."""

import numpy as np
import pandas as pd
import pytest

from flowmod.extensions import blind_spots


def test_physical_signal_matches_the_pinhole_numbers():
    """f = 1266 px, 2 m/s over 0.5 s (1 m), a car 1.9 m wide: lateral 42 / 25 / 18 px and a
    width change of 2.6 / 0.9 / 0.5 px at 30 / 50 / 70 m (DESIGN section 6)."""
    t = blind_spots.physical_signal(1266.0, 0.5, flow_scale=0.5)
    np.testing.assert_allclose(t["lateral shift (px)"], [42.2, 25.3, 18.1], atol=0.05)
    np.testing.assert_allclose(t["radial: width change (px)"], [2.59, 0.94, 0.48], atol=0.01)
    np.testing.assert_allclose(t["radial at flow_scale 0.5 (px)"],
                               t["radial: width change (px)"] / 2)


def test_motion_geometry_splits_radial_and_lateral():
    pose = np.eye(4)
    pose[:3, 3] = [10.0, 5.0, 1.5]
    pairs = pd.DataFrame({"pair_id": ["p"], "cam2global_1": [pose.ravel().tolist()]})
    objects = pd.DataFrame({
        "pair_id": ["p"] * 3, "center_x": [60.0, 10.0, 40.0], "center_y": [5.0, 55.0, 35.0],
        "vx": [3.0, 3.0, 2.0], "vy": [0.0, 0.0, 0.0],
        "xmin": [0.0] * 3, "xmax": [20.0] * 3})
    g = blind_spots.motion_geometry(objects, pairs)
    # straight ahead along x, moving along x: radial, away from the camera
    assert g["radial_speed"][0] == pytest.approx(3.0) and g["lateral_speed"][0] == 0
    assert g["motion_angle"][0] == pytest.approx(0.0)
    # off to the side along y, moving along x: all lateral
    assert g["radial_speed"][1] == pytest.approx(0.0, abs=1e-12)
    assert g["motion_angle"][1] == pytest.approx(90.0)
    # at 45 degrees
    assert g["motion_angle"][2] == pytest.approx(45.0)
    assert g["box_width_px"].tolist() == [20.0] * 3


def test_blind_spots_and_slow_fast_recall():
    rng = np.random.default_rng(0)
    n = 60
    speed = np.r_[np.zeros(20), np.full(20, 2.5), np.full(20, 8.0)]
    label = (speed >= 2).astype(int)
    # a classifier that finds every fast mover and half the slow ones
    prob = np.r_[np.full(20, 0.1), np.full(10, 0.9), np.full(10, 0.1), np.full(20, 0.9)]
    angle = rng.uniform(0, 10, n)
    angle[30:40] = 80.0  # the slow movers the classifier misses move across the line of sight
    df = pd.DataFrame({"label": label, "speed": speed, "motion_angle": angle,
                       "distance": rng.uniform(30, 70, n), "box_width_px": 50.0,
                       "scene": np.repeat(["a", "b", "c"], 20)})
    t = blind_spots.blind_spots(df, prob[None], df["scene"].to_numpy())
    assert set(t["by"]) == {"angle to the line of sight (deg)", "speed (m/s)", "distance (m)",
                            "box width (px)", blind_spots.RADIAL_SPEED}
    speeds = t[t["by"] == "speed (m/s)"].set_index("bin")
    assert speeds.loc["[2, 3)", "recall"] == 0.5 and speeds.loc["[5, 10)", "recall"] == 1.0
    assert blind_spots.recall_slow_and_fast(t, blind_spots.SPEED) == (0.5, 1.0)
    assert blind_spots.recall_slow_and_fast(t) == (1.0, 1.0), "the radial movers by default"
    # along the line of sight only: the crossing slow movers are not counted
    radial = t[t["by"] == blind_spots.RADIAL_SPEED].set_index("bin")
    assert radial.loc["[2, 3)", "n_moving"] == 10 and radial.loc["[2, 3)", "recall"] == 1.0
    assert radial.loc["[0, 2)", "n"] == 20


def _movers_grid():
    """12 scenes; in each, 3 slow radial movers (2.5 m/s, 10 deg) of which the classifier's
    two seeds find 1 and 2 and the rule all 3, one fast crossing mover (6 m/s, 75 deg) both
    find, and one still vehicle."""
    rows, p0, p1, rule = [], [], [], []
    for s in range(12):
        for j in range(3):
            rows.append({"label": 1, "speed": 2.5, "motion_angle": 10.0, "scene": f"s{s}",
                         "ann_token": f"a{s}{j}"})
            p0.append(0.9 if j == 0 else 0.1)
            p1.append(0.9 if j < 2 else 0.1)
            rule.append(1.0)
        rows.append({"label": 1, "speed": 6.0, "motion_angle": 75.0, "scene": f"s{s}",
                     "ann_token": f"c{s}"})
        rows.append({"label": 0, "speed": 0.0, "motion_angle": 0.0, "scene": f"s{s}",
                     "ann_token": f"z{s}"})
        p0 += [0.9, 0.1]
        p1 += [0.9, 0.1]
        rule += [1.0, 0.0]
    return pd.DataFrame(rows), np.array([p0, p1]), np.array(rule)


def test_speed_by_angle_sets_the_classifier_beside_the_oracle_rule():
    df, probs, rule = _movers_grid()
    t = blind_spots.speed_angle_table(df, probs, rule)
    assert t[["angle to the line of sight (deg)", "speed (m/s)", "movers", "scenes"]
             ].values.tolist() == [["0-30", "2-3", 36, 12], ["60-90", "5-40", 12, 12]]
    assert t["classifier recall (%)"].tolist() == [50.0, 100.0]  # seeds: 1/3 and 2/3
    assert t["oracle rule recall (%)"].tolist() == [100.0, 100.0]
    e = blind_spots.cell_effect(df, probs, rule, (0, 30), (2, 3))
    assert (e["movers"], e["scenes"], e["classifier"], e["rule"]) == (36, 12, 50.0, 100.0)
    assert e["rule_minus_classifier"] == pytest.approx(50.0)
    assert e["ci"] == pytest.approx((50.0, 50.0))  # every scene the same
    words = blind_spots.slow_radial_words(e, "dis")
    assert words.startswith("Of the 36 movers at 2-3 m/s within 30 degrees")
    assert "the classifier loses it" in words and "too few" not in words
    k = df["scene"].isin(["s0", "s1", "s2"]).to_numpy()
    few = blind_spots.cell_effect(df[k], probs[:, k], rule[k], (0, 30), (2, 3))
    assert "3 scenes: too few)" in blind_spots.slow_radial_words(few, "dis")
    blind_rule = blind_spots.cell_effect(df, probs, np.zeros(len(df)), (0, 30), (2, 3))
    assert blind_spots.slow_radial_words(blind_rule, "dis").endswith(
        "the classifier finds more of them than the rule.")
    assert "Only 12 of the movers cross" in blind_spots.crossing_words(t)
    assert blind_spots.crossing_words(t.assign(movers=100)).startswith("100 movers cross")


def test_rule_calls_follow_the_annotation_not_the_row_order():
    df = pd.DataFrame({"ann_token": ["a", "b", "c"]})
    base = pd.DataFrame({"ann_token": ["c", "a"], "prob": [1.0, 0.0]})
    got = blind_spots.rule_calls(df, base)
    assert got[0] == 0.0 and np.isnan(got[1]) and got[2] == 1.0
