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
