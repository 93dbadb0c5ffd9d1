"""flowmod.extensions: the geometry of motion seen from the camera, and its image signal."""

import numpy as np
import pandas as pd
import pytest

from flowmod import metrics
from flowmod.extensions import blind_spots


def test_physical_signal_matches_the_pinhole_numbers():
    """f = 1266 px, 2 m/s over 0.5 s (1 m), a car 1.9 m wide: lateral 42 / 25 / 18 px and a
    width change of 2.6 / 0.9 / 0.5 px at 30 / 50 / 70 m (DESIGN section 6)."""
    t = blind_spots.physical_signal(1266.0, 0.5, flow_scale=0.5)
    np.testing.assert_allclose(t["lateral shift (px)"], [42.2, 25.3, 18.1], atol=0.05)
    np.testing.assert_allclose(t["radial: width change (px)"], [2.59, 0.94, 0.48], atol=0.01)
    np.testing.assert_allclose(t["radial at flow_scale 0.5 (px)"],
                               t["radial: width change (px)"] / 2)
    # 2 m/s over 0.25 s is 0.5 m: f x 0.5 / z; at the default scale 1 both columns agree
    t = blind_spots.physical_signal(1266.0, 0.25)
    np.testing.assert_allclose(t["lateral shift (px)"], [1266.0 * 0.5 / z for z in (30, 50, 70)])
    np.testing.assert_allclose(t["lateral at flow_scale 1 (px)"], t["lateral shift (px)"])


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
    # moving straight away along a diagonal line of sight (3-4-5); and half a metre from
    # the camera, where the line of sight is still a unit vector
    near = objects.iloc[:2].assign(center_x=[10.0 + 30.0, 10.0], center_y=[5.0 + 40.0, 5.5],
                                   vx=[3.0, 0.0], vy=[4.0, 2.0])
    g = blind_spots.motion_geometry(near, pairs)
    assert g["radial_speed"].tolist() == pytest.approx([5.0, 2.0])
    assert g["lateral_speed"].tolist() == pytest.approx([0.0, 0.0], abs=1e-12)


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
    # no mover at 5 m/s or more: that recall is undefined (NaN), not an error or 0
    slow_only = blind_spots.blind_spots(df.iloc[:40], prob[None, :40], df["scene"][:40].to_numpy())
    slow, fast = blind_spots.recall_slow_and_fast(slow_only, blind_spots.SPEED)
    assert slow == 0.5 and np.isnan(fast)



def test_blind_spots_bins_are_pinned_and_radial_means_still_or_under_30_degrees():
    """Each breakdown's bins (an object on each lower edge, the last edge's value in the
    last bin); the radial movers' table holds every still vehicle whatever its angle and
    the movers strictly under 30 degrees; one table numbered afresh."""
    df = pd.DataFrame({"label": [1, 1, 1, 1, 1, 0, 0],
                       "speed": [2.5, 2.5, 4.0, 8.0, 12.0, 0.0, 0.0],
                       "motion_angle": [0.0, 15.0, 30.0, 60.0, 90.0, 80.0, 5.0],
                       "distance": [30.0, 40.0, 50.0, 60.0, 70.0, 45.0, 35.0],
                       "box_width_px": [0.0, 20.0, 40.0, 80.0, 1999.5, 30.0, 10.0],
                       "scene": list("aabbcca")})
    t = blind_spots.blind_spots(df, np.full((1, 7), 0.9), df["scene"].to_numpy())
    bins = {by: g["bin"].astype(str).tolist() for by, g in t.groupby("by", sort=False)}
    assert bins["angle to the line of sight (deg)"] == [
        "[0.0, 15.0)", "[15.0, 30.0)", "[30.0, 60.0)", "[60.0, 90.01)"]
    assert bins["distance (m)"] == ["[30.0, 40.0)", "[40.0, 50.0)", "[50.0, 60.0)",
                                    "[60.0, 70.01)"]
    assert bins["box width (px)"] == ["[0, 20)", "[20, 40)", "[40, 80)", "[80, 2000)"]
    assert bins[blind_spots.SPEED] == ["[0, 2)", "[2, 3)", "[3, 5)", "[5, 10)", "[10, 40)"]
    radial = t[t["by"] == blind_spots.RADIAL_SPEED]
    assert radial["bin"].astype(str).tolist() == ["[0, 2)", "[2, 3)"]
    assert radial["n"].tolist() == [2, 2]
    assert t.index.equals(pd.RangeIndex(len(t)))


def test_false_alarm_rate_weighs_objects_calls_only_above_one_half_and_is_nan_without_still():
    """The weighted share of still vehicles called moving; a call of exactly 0.5 is not a
    call; no still vehicle: NaN, without a division warning."""
    import warnings

    assert blind_spots.false_alarm_rate(np.array([1, 0, 1, 1]), np.array([0, 0, 0, 1]),
                                        np.array([1.0, 2.0, 5.0, 100.0])) == 0.75
    assert blind_spots.false_alarm_rate([1, 0, 1], [0, 0, 0], [1, 2, 5]) == 0.75
    assert blind_spots.false_alarm_rate(np.array([0.5, 1.0]), np.array([0, 0])) == 0.5
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(blind_spots.false_alarm_rate(np.array([1.0]), np.array([1])))


def test_slow_radial_words_without_movers_at_the_scene_edge_and_with_one_rate():
    """No mover in the cell: one sentence naming it; 10 scenes (MIN_SCENES) are not few;
    only one of the two false-alarm rates given: none is said."""
    e = {"movers": 0, "angle": (0, 30), "speed": (2, 3)}
    assert blind_spots.slow_radial_words(e, "dis") == (
        "This run has no mover at 2-3 m/s within 30 degrees of the line of sight.")
    e = {"movers": 20, "scenes": 10, "angle": (0, 30), "speed": (2, 3), "classifier": 50.0,
         "rule": 75.0, "rule_minus_classifier": 25.0, "ci": (10.0, 40.0)}
    words = blind_spots.slow_radial_words(e, "dis", 5.0, None)
    assert words.endswith("(rule minus classifier +25.0 points, 95 % interval over scenes "
                          "+10.0 to +40.0).")
    assert "too few" not in words
    assert blind_spots.slow_radial_words(e, "dis", None, 5.0) == words


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
    assert words.endswith("at their own operating points (rule minus classifier +50.0 "
                          "points, 95 % interval over scenes +50.0 to +50.0).")
    assert "loses" not in words and "too few" not in words
    assert blind_spots.slow_radial_words(e, "dis", 5.0, 20.0).endswith(
        "but the rule calls 20.0 % of the still vehicles moving and the classifier 5.0 %, so "
        "these two recalls are not comparable.")
    k = df["scene"].isin(["s0", "s1", "s2"]).to_numpy()
    few = blind_spots.cell_effect(df[k], probs[:, k], rule[k], (0, 30), (2, 3))
    assert "3 scenes: too few)" in blind_spots.slow_radial_words(few, "dis")
    assert blind_spots.crossing_words(t) == (
        "Only 12 of the movers cross the line of sight at 60-90 degrees (fewer than 100): too "
        "few to say how direction itself matters; the table compares speeds within the movers "
        "along the line of sight.")
    assert blind_spots.crossing_words(t.assign(movers=100)) == (
        "100 movers cross the line of sight at 60-90 degrees: the table compares directions "
        "at equal speed.")


def test_speed_by_angle_recalls_to_a_tenth_and_an_empty_table_keeps_its_columns():
    """Three slow radial movers: one seed finds 1 of 3 (33.3 %), the rule 2 (66.7 %), to a
    tenth; without movers, an empty table with the six columns."""
    df = pd.DataFrame({"label": [1, 1, 1, 0], "speed": [2.5, 2.5, 2.5, 0.0],
                       "motion_angle": [10.0, 10.0, 10.0, 0.0], "scene": ["a", "a", "b", "b"]})
    t = blind_spots.speed_angle_table(df, np.array([[0.9, 0.1, 0.1, 0.1]]),
                                      np.array([1.0, 1.0, 0.0, 0.0]))
    assert t["classifier recall (%)"].tolist() == [33.3]
    assert t["oracle rule recall (%)"].tolist() == [66.7]
    empty = blind_spots.speed_angle_table(df.iloc[3:], np.array([[0.1]]), np.array([0.0]))
    assert empty.empty and empty.columns.tolist() == [
        "angle to the line of sight (deg)", "speed (m/s)", "movers", "scenes",
        "classifier recall (%)", "oracle rule recall (%)"]


def test_rule_calls_follow_the_annotation_not_the_row_order():
    df = pd.DataFrame({"ann_token": ["a", "b", "c"]})
    base = pd.DataFrame({"ann_token": ["c", "a"], "prob": [1.0, 0.0]})
    got = blind_spots.rule_calls(df, base)
    assert got[0] == 0.0 and np.isnan(got[1]) and got[2] == 1.0


def _operating_points(n_scenes: int = 12) -> tuple[pd.DataFrame, np.ndarray, np.ndarray]:
    """Per scene 10 still vehicles and 5 slow radial movers; the classifier's score and a
    rule whose score ranks every object exactly as the classifier's does (so at any one
    false-alarm rate they find the same movers) but that calls far more moving at its own
    threshold (0 against the classifier's 0.5)."""
    rows, clf = [], []
    for s in range(n_scenes):
        for i in range(10):
            rows.append({"scene": f"s{s}", "label": 0, "motion_angle": 0.0, "speed": 0.0})
            clf.append(0.06 + 0.09 * i + 0.001 * s)  # stills: 0.06 .. 0.88
        for i in range(5):
            rows.append({"scene": f"s{s}", "label": 1, "motion_angle": 10.0, "speed": 2.5})
            clf.append(0.3 + 0.15 * i + 0.001 * s)  # movers: 0.3 .. 0.9
    clf = np.array(clf)
    return pd.DataFrame(rows), clf, 10 * (clf - 0.2)  # rule: calls moving above 0.2


def test_a_rule_and_a_classifier_are_compared_at_one_false_alarm_rate():
    """Issue 50 item 1: at their own thresholds the rule recalls more slow movers than the
    classifier only because it calls more still vehicles moving; at either one's false-alarm
    rate the two find the same movers, and the words say so."""
    df, clf, rule = _operating_points()
    labels = df["label"].to_numpy()
    far_clf = blind_spots.false_alarm_rate(clf > 0.5, labels)
    far_rule = blind_spots.false_alarm_rate(rule > 0, labels)
    assert (far_clf, far_rule) == (pytest.approx(0.5), pytest.approx(0.8))
    own = blind_spots.cell_effect(df, clf[None], (rule > 0).astype(float), (0, 30), (2, 3))
    assert (own["classifier"], own["rule"]) == (pytest.approx(60.0), pytest.approx(100.0))
    for far in (far_clf, far_rule):
        e = blind_spots.matched_effect(df, clf, rule, (0, 30), (2, 3), far, n=200)
        assert e["far"] == pytest.approx(100 * far)
        assert e["classifier"] == pytest.approx(e["rule"])
        assert e["ci"] == pytest.approx((0.0, 0.0))
    at_clf = blind_spots.matched_effect(df, clf, rule, (0, 30), (2, 3), far_clf, n=200)
    # recall at a false-alarm rate is the most any threshold with no more false alarms
    # finds: below 0.5, down to the highest still under it, the 0.45 movers join (60 -> 80)
    assert at_clf["classifier"] == pytest.approx(80.0)
    at_rule = blind_spots.matched_effect(df, clf, rule, (0, 30), (2, 3), far_rule, n=200)
    words = blind_spots.matched_words(own, at_rule, at_clf, "dis")
    assert words.startswith("Compared at equal false-alarm rates on dis flow, the 60 movers at 2-3 m/s")
    assert words.endswith("these scenes do not tell the two apart (neither interval excludes 0).")
    # a rule that finds more at one rate than a classifier shifted to miss the slow movers
    worse = np.where(labels == 1, clf - 0.25, clf)
    e = blind_spots.matched_effect(df, worse, rule, (0, 30), (2, 3), far_clf, n=200)
    assert e["ci"][0] > 0 and e["rule"] > e["classifier"]
    assert blind_spots.threshold_at(clf, labels, 0.0) == pytest.approx(clf[labels == 0].max())
    assert blind_spots.threshold_at(clf, labels, 1.0) == -np.inf



def test_matched_intervals_set_each_replicate_s_thresholds_on_its_own_stills():
    """Each replicate draws whole scenes and sets both thresholds again on the stills it
    drew (weighted by the draws), its difference in points; defaults: 2000 replicates,
    seed 0. Recomputed here replicate by replicate."""
    df, _, _ = _operating_points()
    labels = df["label"].to_numpy()
    rng = np.random.default_rng(3)
    shift = 0.1 * (df["scene"].str[1:].astype(int) % 4).to_numpy()  # scenes' stills differ
    worse = rng.uniform(0, 1, len(df)) + np.where(labels == 0, shift, 0.0)
    rule = rng.uniform(0, 1, len(df)) + np.where(labels == 0, -shift, 0.2)
    e = blind_spots.matched_effect(df, worse, rule, (0, 30), (2, 3), 0.5, n=300, seed=4)
    k = blind_spots.in_cell(df, (0, 30), (2, 3))
    scenes, idx = np.unique(df["scene"].to_numpy(), return_inverse=True)
    diffs = []
    for d in metrics.scene_draws(len(scenes), 300, 4):
        w = d[idx]
        rec = [blind_spots._recall(x, k, blind_spots.threshold_at(x, labels, 0.5, w), w)
               for x in (worse, rule)]
        diffs.append(rec[1] - rec[0])
    lo, hi = np.quantile(diffs, [0.025, 0.975])
    assert lo < hi and e["ci"] == pytest.approx((100 * lo, 100 * hi), rel=1e-12, abs=1e-12)
    default = blind_spots.matched_effect(df, worse, rule, (0, 30), (2, 3), 0.5)
    assert default == blind_spots.matched_effect(df, worse, rule, (0, 30), (2, 3), 0.5,
                                                 seed=0, n=2000)
    asked = []
    real = blind_spots.scene_draws
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(blind_spots, "scene_draws",
                   lambda k, n, seed: (asked.append((k, n, seed)), real(k, n, seed))[1])
        blind_spots.matched_effect(df, worse, rule, (0, 30), (2, 3), 0.5)
    assert asked == [(12, 2000, 0)]


def test_thresholds_and_recalls_are_weighted_strict_and_nan_without_movers():
    """threshold_at weighs each still (weights of any sum); a mover scoring exactly the
    threshold is not recalled; a cell without movers has no recall (NaN, no warning)."""
    import warnings

    scores, labels = np.array([0.9, 0.8, 0.1, 0.95]), np.array([0, 0, 0, 1])
    assert blind_spots.threshold_at(scores, labels, 0.7) == 0.1  # 2 of 3 stills above
    assert blind_spots.threshold_at(scores, labels, 0.7, np.array([3.0, 1.0, 1.0, 1.0])) == 0.8
    assert blind_spots.threshold_at(scores, labels, 0.3, np.array([0.1, 0.1, 0.1, 0.1])) == 0.9
    cell = np.array([False, False, True, True])
    w = np.ones(4)
    assert blind_spots._recall(np.array([0.0, 0.0, 0.5, 0.7]), cell, 0.5, w) == 0.5
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(blind_spots._recall(scores, np.zeros(4, bool), 0.5, w))


def test_matched_words_give_each_verdict_in_full():
    """The four endings (the rule wins at both rates, at one, loses at both, neither
    interval excludes 0: a lower bound of 0.5 is above 0), every clause joined by "; ",
    the scene count flagged below 10 only; no mover, one sentence."""
    own = {"movers": 20, "scenes": 10, "angle": (0, 30), "speed": (2, 3)}

    def e(lo, hi):
        return {"far": 10.0, "classifier": 40.0, "rule": 50.0, "rule_minus_classifier": 10.0,
                "ci": (lo, hi)}

    clause = ("at {} false-alarm rate (10.0 % of still vehicles called moving) the "
              "classifier recalls 40.0 % and the rule 50.0 % (rule minus classifier +10.0 "
              "points, 95 % interval over scenes {:+.1f} to {:+.1f})")
    head = ("Compared at equal false-alarm rates on dis flow, the 20 movers at 2-3 m/s within "
            "30 degrees of the line of sight: ")
    cases = [((0.5, 9.0), (2.0, 9.0), "the rule finds movers the classifier misses at either "
              "rate: the slow radial motion is in the flow and the classifier loses part of it."),
             ((0.5, 9.0), (-1.0, 9.0), "the rule wins at one rate only: whether the classifier "
              "loses motion the flow carries depends on the operating point."),
             ((-9.0, -0.5), (-9.0, -2.0), "the classifier finds more of them than the rule at "
              "either rate."),
             ((-1.0, 1.0), (-9.0, -2.0), "at equal false-alarm rates these scenes do not tell "
              "the two apart (neither interval excludes 0).")]
    for a, b, end in cases:
        want = (head + clause.format("the rule's", *a) + "; "
                + clause.format("the classifier's", *b) + "; " + end)
        assert blind_spots.matched_words(own, e(*a), e(*b), "dis") == want
    few = blind_spots.matched_words({**own, "scenes": 9}, e(0.5, 9), e(2, 9), "dis")
    assert "line of sight (9 scenes: too few): at the rule's" in few
    assert blind_spots.matched_words({**own, "movers": 0}, e(1, 2), e(1, 2), "dis") == (
        "This run has no mover at 2-3 m/s within 30 degrees of the line of sight.")



def test_a_cell_without_movers_and_the_cell_s_words_and_draws(monkeypatch):
    """A cell without movers: no recall (NaN, no warning); a rule score of exactly 0.5 is no
    hit; a cell away from the line of sight is named by both angles; the interval is drawn
    with seed 0 unless another is given."""
    import warnings

    df, probs, rule = _movers_grid()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        e = blind_spots.cell_effect(df, probs, rule, (30, 60), (2, 3))
    assert e["movers"] == 0
    assert all(np.isnan(e[c]) for c in ("classifier", "rule", "rule_minus_classifier"))
    half = np.where(rule > 0, 0.5, 0.0)
    assert blind_spots.cell_effect(df, probs, half, (0, 30), (2, 3))["rule"] == 0.0
    assert blind_spots.slow_radial_words({**e, "angle": (60, 90)}, "dis") == (
        "This run has no mover at 2-3 m/s at 60-90 degrees to the line of sight.")
    seeds = []
    real = blind_spots.group_mean_bootstrap
    monkeypatch.setattr(blind_spots, "group_mean_bootstrap",
                        lambda v, g, seed: (seeds.append(seed), real(v, g, seed=seed))[1])
    blind_spots.cell_effect(df, probs, rule, (0, 30), (2, 3))
    blind_spots.cell_effect(df, probs, rule, (0, 30), (2, 3), seed=7)
    assert seeds == [0, 7]


def test_the_rules_score_is_its_margin_over_its_folds_threshold():
    from flowmod.chapters import ch09_blind_spots as ch09

    df = pd.DataFrame({"ann_token": ["b", "a", "c"]})
    base = pd.DataFrame({"ann_token": ["a", "b", "c"], "fold": [0, 1, 1],
                         "residual_speed": [1.0, 0.5, 3.0]})
    got = ch09.rule_margin(df, base, {"thresholds_m_s": [0.2, 0.7], "threshold_m_s": 0.45})
    assert got.tolist() == pytest.approx([-0.2, 0.8, 2.3])
    one = ch09.rule_margin(df, base, {"threshold_m_s": 0.5})  # one split: one threshold
    assert one.tolist() == pytest.approx([0.0, 0.5, 2.5])


def test_chapter_09_s_recall_intervals_resample_scenes_of_the_radial_movers_in_the_bin():
    """Two seeds; slow radial movers in three scenes with hit shares 1, 0.5 and 0 (a
    crossing slow mover and a slow mover at 3 m/s are not in the bin): the interval spans
    the scene means and holds the table's recall; fast movers all found: a point."""
    from flowmod.chapters import ch09_blind_spots as ch09

    df = pd.DataFrame({
        "label": [1, 1, 1, 1, 1, 1, 0, 1, 1],
        "speed": [2.5, 2.5, 2.5, 2.9, 2.5, 3.0, 0.0, 8.0, 12.0],
        "motion_angle": [5.0, 5.0, 5.0, 10.0, 80.0, 5.0, 0.0, 5.0, 5.0],
        "scene": ["a", "a", "b", "c", "c", "c", "c", "a", "b"],
        "prob_s0": [0.9, 0.9, 0.9, 0.1, 0.9, 0.9, 0.1, 0.9, 0.9],
        "prob_s1": [0.9, 0.9, 0.1, 0.1, 0.9, 0.9, 0.1, 0.9, 0.9],
        "distance": 50.0, "box_width_px": 30.0})
    df["prob"] = df[["prob_s0", "prob_s1"]].mean(axis=1)
    lo, hi, n = ch09.recall_interval(df, ch09.SLOW, seed=1)
    assert n == 3  # scenes a, b, c hold the four slow radial movers
    # scene means: a 1.0 (two movers), b 0.5, c 0.0; resampling whole scenes
    assert 0.0 <= lo < 0.625 < hi <= 1.0  # the pooled recall (1 + 1 + 0.5 + 0) / 4
    t = blind_spots.blind_spots(df, np.stack([df["prob_s0"], df["prob_s1"]]),
                                df["scene"].to_numpy())
    slow, fast = blind_spots.recall_slow_and_fast(t)
    assert slow == pytest.approx(0.625) and fast == 1.0
    assert ch09.recall_interval(df, ch09.FAST)[:2] == (1.0, 1.0)
    assert ch09.recall_interval(df, (3.0, 5.0)) == (1.0, 1.0, 1)  # [lo, hi): 3.0 is here
    assert ch09.recall_interval(df, (2.0, 2.9))[2] == 2  # and 2.9 is not
    words = ch09.recall_intervals(df)
    assert words["headline_recall_fast_ci"] == "100.0-100.0 (2 scenes: too few)"
    assert set(words) == {"headline_recall_slow_ci", "headline_recall_fast_ci"}


# --- chapter 10's context files -------------------------------------------------------------


def _context_files(folder, n=3, static_ch=2, image_ch=6, rows=None):
    from flowmod.extensions import context

    f = context.paths(folder, "f0")
    folder.mkdir(parents=True, exist_ok=True)
    for k in ("static", "deployed"):
        np.save(f[k], np.full((n, static_ch, 4, 4), 1.5 if k == "static" else 2.5, np.float16))
    np.save(f["images"], np.zeros((n, image_ch, 4, 4), np.uint8))
    pd.DataFrame({"ann_token": [f"a{i}" for i in range(n if rows is None else rows)]}
                 ).to_parquet(f["index"])
    return f


def test_read_context_maps_each_depth_and_refuses_missing_disagreeing_or_pickled_files(
        tmp_path):
    """Both depths memory-mapped (never unpickled); a missing file names itself and the
    command that builds it; rows or channels that disagree name the split and the fix; an
    object array in place of a .npy of numbers is refused, not unpickled."""
    from flowmod.crops import CropsError
    from flowmod.extensions import context

    f = _context_files(tmp_path / "ok")
    static, images, df = context.read_context(tmp_path / "ok", "f0")
    assert isinstance(static, np.memmap) and isinstance(images, np.memmap)
    assert static.dtype == np.float16 and float(static[0, 0, 0, 0]) == 1.5
    assert float(context.read_context(tmp_path / "ok", "f0", "ground")[0][0, 0, 0, 0]) == 2.5
    assert images.shape == (3, 6, 4, 4) and df["ann_token"].tolist() == ["a0", "a1", "a2"]
    f["images"].unlink()
    with pytest.raises(CropsError, match=r"^context artefact missing: .*f0\.images\.npy; run "
                       r"chapter 10's stages \(python -m flowmod\.runner --only 10 --set "
                       r"extension_build=true\)$"):
        context.read_context(tmp_path / "ok", "f0")
    for name, kw in (("rows", {"rows": 2}), ("static", {"static_ch": 3}),
                     ("images", {"image_ch": 5})):
        _context_files(tmp_path / name, **kw)
        with pytest.raises(CropsError, match=r": f0 files disagree \(static .*, images .*, "
                           r"index \d rows\); rebuild with force=true$"):
            context.read_context(tmp_path / name, "f0")
    for k in ("static", "images"):
        g = _context_files(tmp_path / f"pickled-{k}")
        np.save(g[k], np.array([{"a": 1}] * 3, dtype=object), allow_pickle=True)
        with pytest.raises(ValueError, match="Python objects"):
            context.read_context(tmp_path / f"pickled-{k}", "f0")


def test_the_context_node_exists_for_chapter_10_or_for_chapter_13_s_pull():
    """Chapter 13's pull needs the still-world flow: the context nodes exist when it pulls
    the exact flow, even with chapter 10 off; not for its other kinds or without gt."""
    from types import SimpleNamespace

    from flowmod.extensions import context
    from flowmod.params import load_profile

    def nodes(**kw):
        return context.STAGE.nodes(load_profile("demo", **kw))

    off = {"extension_inputs": []}
    assert len(nodes(**off, error_kinds=["pull"])) == len(context.PARTS) > 0
    assert nodes(**off, error_kinds=["noise"]) == []
    assert not context._pulled(SimpleNamespace(error_kinds=["pull"], flow_methods=["dis"]))
    assert context._pulled(SimpleNamespace(error_kinds=["pull"], flow_methods=["dis", "gt"]))
    assert nodes(**off, error_kinds=["noise", "pull"]) != []
    assert len(nodes(error_kinds=["noise"])) == len(context.PARTS), "chapter 10's inputs"


def test_chapter_10_s_chains_read_their_method_s_crops_and_the_context():
    """An ``xtrain`` node reads its method's keyframe crops (none for the image-only input)
    and the keyframe context; ``xevaluate`` reads its chain's models of every part, the
    method's crops of both parts and both parts' context; a node's chain is (method, the
    input before its seed)."""
    from flowmod.dag import Node
    from flowmod.extensions import inputs
    from flowmod.params import load_profile

    p = load_profile("demo")
    assert inputs._chain(Node("xtrain", "dis", "residual/f1s0")) == ("dis", "residual")
    assert inputs._chain(Node("xevaluate", None, "images")) == (None, "images")
    assert inputs._xtrain_inputs(Node("xtrain", "dis", "residual/f0s0"), p) == (
        Node("crops", "dis", "keyframe"), Node("context", None, "keyframe"))
    assert inputs._xtrain_inputs(Node("xtrain", None, "images/f0s0"), p) == (
        Node("context", None, "keyframe"),)
    got = inputs._xevaluate_inputs(Node("xevaluate", "dis", "residual"), p)
    parts = inputs.extension_parts(p)
    assert len(parts) == 3  # one seed a fold
    assert got == (*(Node("xtrain", "dis", f"residual/{k}") for k in parts),
                   Node("crops", "dis", "keyframe"), Node("crops", "dis", "general"),
                   Node("context", None, "keyframe"), Node("context", None, "general"))
    assert inputs._xevaluate_inputs(Node("xevaluate", None, "images"), p) == (
        *(Node("xtrain", None, f"images/{k}") for k in parts),
        Node("context", None, "keyframe"), Node("context", None, "general"))


def test_each_input_is_composed_from_its_parts_in_float32():
    """Every variant's channels from the flow, the still-world flow and the images (uint8
    standardised as (x / 255 - 0.5) / 0.25); a missing part is named; Inputs composes a
    batch by index and refuses parts of different lengths."""
    from flowmod.extensions import inputs

    rng = np.random.default_rng(0)
    flow = rng.normal(0, 2, (3, 2, 4, 4)).astype(np.float16)
    static = rng.normal(0, 2, (3, 2, 4, 4)).astype(np.float16)
    images = rng.integers(0, 256, (3, 6, 4, 4)).astype(np.uint8)
    f32, s32 = flow.astype(np.float32), static.astype(np.float32)
    img = (images.astype(np.float32) / 255.0 - 0.5) / 0.25
    np.testing.assert_array_equal(inputs.standardise_images(images), img)
    assert inputs.standardise_images(np.array([0, 255], np.uint8)).tolist() == [-2.0, 2.0]
    want = {"flow": f32, "residual": f32 - s32, "residual-deployed": f32 - s32,
            "flow+static": np.concatenate([f32, s32], axis=1), "images": img,
            "images+flow": np.concatenate([f32, img], axis=1)}
    assert set(want) == set(inputs.VARIANTS)
    for v, x in want.items():
        got = inputs.compose(v, flow, static, images)
        assert got.dtype == np.float32 and got.shape[1] == inputs.VARIANTS[v].channels, v
        np.testing.assert_array_equal(got, x)
        batch = inputs.Inputs(v, flow, static, images)
        assert batch.shape == (3, inputs.VARIANTS[v].channels, 4, 4) and len(batch) == 3
        np.testing.assert_array_equal(batch[[2, 0]], x[[2, 0]])
        # parts of a wider float type (float64) come out float32 all the same
        wide = inputs.compose(v, flow.astype(np.float64), static.astype(np.float64), images)
        assert wide.dtype == np.float32, v
    with pytest.raises(ValueError, match=r"^input 'images\+flow' needs \['images'\]$"):
        inputs.compose("images+flow", flow, static, None)
    with pytest.raises(ValueError, match=r"^input 'residual' needs \['flow', 'static'\]$"):
        inputs.compose("residual", images=images)
    with pytest.raises(ValueError, match=r"^input 'residual': parts of different lengths "
                       r"\{'flow': 3, 'static': 2\}$"):
        inputs.Inputs("residual", flow, static[:2])
