"""Chapter 09's backend (:mod:`flowmod.chapters.ch09_blind_spots`) on tiny hand-made inputs.

Mutation testing of chapter 09's backend found that only the slow notebook tests ran most of
its functions, so that almost every mutant survived the quick tests. These quick tests (no
world, no training; a run folder written by hand where a function reads published
predictions) pin each function's behaviour: which methods it shows, which rows it counts,
which column and seed it reads, the exact numbers and words it glues. Every expected number
is computed here by hand or with numpy / scikit-learn, not with the function under test.
``tests/test_extensions.py`` already checks :func:`~flowmod.chapters.ch09_blind_spots.rule_margin`
and the ends of :func:`~flowmod.chapters.ch09_blind_spots.recall_interval`'s speed bins; this
file complements it.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from handmade import publish
from sklearn.metrics import recall_score

from flowmod.chapters import ch09_blind_spots as ch09
from flowmod.dag import Node
from flowmod.extensions import blind_spots
from flowmod.params import load_profile
from flowmod.select import Selection

#: The cell the chapter answers on, spelled out in its words.
CELL_WORDS = "at 2-3 m/s within 30 degrees of the line of sight"


def _params(flow_methods, **kw):
    """The demo profile on ``flow_methods`` (the other method lists emptied to fit)."""
    kw = {"raw_input_methods": [], "extension_methods": [flow_methods[0]], "wide_methods": [],
          **kw}
    return load_profile("demo", flow_methods=flow_methods, **kw)


def _bootstrap_interval(values, scenes, seed, n=2000):
    """The 95 % percentile interval of the mean of ``values`` with whole scenes resampled
    (each replicate draws as many scenes as there are, multinomially, from numpy's
    ``default_rng(seed)``), written out here with numpy."""
    values, scenes = np.asarray(values, float), np.asarray(scenes)
    uniq, idx = np.unique(scenes, return_inverse=True)
    sums = np.bincount(idx, weights=values)
    counts = np.bincount(idx).astype(float)
    draws = np.random.default_rng(seed).multinomial(len(uniq), np.full(len(uniq), 1 / len(uniq)),
                                                    size=n).astype(float)
    means = (draws @ sums) / (draws @ counts)
    lo, hi = np.quantile(means[~np.isnan(means)], [0.025, 0.975])
    return float(lo), float(hi)


# --- methods --------------------------------------------------------------------------------


def test_main_method_is_the_first_estimated_flow_and_gt_only_without_one():
    """The main method is the first flow method that is not ``gt``, in the profile's order;
    a profile of ``gt`` alone falls back on ``gt``."""
    assert ch09.main_method(_params(["gt", "dis", "farneback"])) == "dis"
    assert ch09.main_method(_params(["farneback", "gt", "dis"])) == "farneback"
    assert ch09.main_method(_params(["gt"])) == "gt"


def test_shown_methods_are_gt_and_the_main_method_in_profile_order():
    """The chapter breaks down ``gt`` and the main method only, in the profile's order; with
    ``gt`` alone, ``gt`` once."""
    assert ch09.shown_methods(_params(["gt", "dis", "farneback"])) == ["gt", "dis"]
    assert ch09.shown_methods(_params(["farneback", "gt", "dis"])) == ["farneback", "gt"]
    assert ch09.shown_methods(_params(["dis", "farneback"])) == ["dis"]
    assert ch09.shown_methods(_params(["gt"])) == ["gt"]


def test_test_geometry_adds_the_motion_geometry_to_each_shown_method_s_predictions(tmp_path):
    """``{method: predictions}`` for ``gt`` and the main method only (a third method is not
    published: reading it would fail), each its own method's published test predictions
    with the geometry of the motion seen from its pair's camera (radial, lateral speed,
    angle to the line of sight, box width)."""
    p = _params(["gt", "dis", "farneback"], run_dir=str(tmp_path / "runs"))
    pairs = pd.DataFrame({"pair_id": ["p1", "p2"], "cam2global_1": [
        np.eye(4).ravel().tolist(),
        [1, 0, 0, 10.0, 0, 1, 0, 0.0, 0, 0, 1, 1.5, 0, 0, 0, 1]]})
    base = pd.DataFrame({"ann_token": ["o1", "o2"], "pair_id": ["p1", "p2"],
                         "center_x": [0.0, 10.0], "center_y": [40.0, 50.0],
                         "xmin": [100.0, 300.0], "xmax": [130.0, 345.0], "label": [1, 1],
                         "scene": ["a", "b"]})
    own = {"gt": base.assign(vx=[0.0, 3.0], vy=[2.0, 0.0], prob=[0.9, 0.8]),
           "dis": base.assign(vx=[3.0, 4.0], vy=[4.0, -3.0], prob=[0.4, 0.3])}
    for m, df in own.items():
        publish(p, Node("evaluate", m), {"test": df})
    got = ch09.test_geometry(p, Selection(pairs, pd.DataFrame(), pd.DataFrame()))
    assert list(got) == ["gt", "dis"]
    # gt: o1 seen straight ahead (sight (0, 1)) moving along it; o2 ahead of a camera at
    # x = 10 (sight (0, 1)) moving across it
    assert got["gt"]["prob"].tolist() == [0.9, 0.8]
    assert got["gt"]["radial_speed"].tolist() == pytest.approx([2.0, 0.0])
    assert got["gt"]["lateral_speed"].tolist() == pytest.approx([0.0, 3.0])
    assert got["gt"]["motion_angle"].tolist() == pytest.approx([0.0, 90.0])
    assert got["gt"]["box_width_px"].tolist() == [30.0, 45.0]
    # dis: (3, 4) along (0, 1): radial 4, lateral 3; (4, -3): radial -3, lateral 4
    assert got["dis"]["prob"].tolist() == [0.4, 0.3]
    assert got["dis"]["radial_speed"].tolist() == pytest.approx([4.0, -3.0])
    assert got["dis"]["lateral_speed"].tolist() == pytest.approx([3.0, 4.0])
    assert got["dis"]["motion_angle"].tolist() == pytest.approx(
        np.degrees(np.arctan2([3.0, 4.0], [4.0, 3.0])).tolist())


# --- tables ---------------------------------------------------------------------------------


def test_moving_summary_describes_the_movers_motion_one_row_per_column():
    """Count, mean, SD, min, quartiles and max of the five motion columns over the movers
    only (a still vehicle with far-off values is left out), one row per column in
    :data:`MOTION_COLUMNS`' order, the column's name first."""
    moving = {"distance": [30.0, 40.0, 62.0], "speed": [2.0, 5.0, 11.0],
              "radial_speed": [-1.0, 4.0, 0.5], "lateral_speed": [1.5, 0.0, 3.0],
              "motion_angle": [10.0, 80.0, 45.0]}
    df = pd.DataFrame({k: v + [999.0] for k, v in moving.items()}).assign(label=[1, 1, 1, 0])
    got = ch09.moving_summary(df)
    assert got.columns.tolist() == ["moving vehicles", "count", "mean", "std", "min", "25%",
                                    "50%", "75%", "max"]
    assert got["moving vehicles"].tolist() == ch09.MOTION_COLUMNS == [
        "distance", "speed", "radial_speed", "lateral_speed", "motion_angle"]
    for (_, row), col in zip(got.iterrows(), ch09.MOTION_COLUMNS, strict=True):
        v = np.array(moving[col])
        want = [3, v.mean(), v.std(ddof=1), v.min(), *np.percentile(v, [25, 50, 75]), v.max()]
        assert row.iloc[1:].tolist() == pytest.approx(want, rel=1e-12), col


def _blind_input(probs0, probs1):
    """Eight vehicles in three scenes: movers at 2-3 m/s (two radial, one crossing), fast
    ones, a still one; two seeds' probabilities."""
    return pd.DataFrame({
        "label": [1, 1, 1, 1, 1, 0, 1, 0],
        "speed": [2.5, 2.2, 2.8, 7.0, 12.0, 0.0, 2.6, 0.0],
        "motion_angle": [5.0, 10.0, 70.0, 5.0, 20.0, 0.0, 15.0, 40.0],
        "distance": [35.0, 45.0, 55.0, 65.0, 35.0, 45.0, 55.0, 65.0],
        "box_width_px": [30.0, 50.0, 90.0, 10.0, 30.0, 50.0, 90.0, 10.0],
        "scene": ["a", "a", "b", "b", "c", "c", "c", "a"],
        "prob_s0": probs0, "prob_s1": probs1})


def test_blind_tables_break_down_every_seed_over_scenes_and_blind_table_stacks_them():
    """Per method, its own table: the recall of the radial movers at 2-3 m/s is the mean over
    both seeds of each seed's recall, the scenes counted from ``scene``; stacked, a
    ``method`` column first, the methods' rows in turn."""
    preds = {"gt": _blind_input([0.9, 0.2, 0.9, 0.9, 0.9, 0.1, 0.9, 0.6],
                                [0.9, 0.9, 0.1, 0.9, 0.1, 0.1, 0.3, 0.1]),
             "dis": _blind_input([0.1] * 8, [0.9, 0.1, 0.9, 0.1, 0.9, 0.9, 0.1, 0.1])}
    got = ch09.blind_tables(preds)
    assert list(got) == ["gt", "dis"]
    for m, df in preds.items():
        t = got[m]
        slow = t[(t["by"] == blind_spots.RADIAL_SPEED) & (t["bin"] == "[2, 3)")].iloc[0]
        k = ((df["label"] == 1) & (df["motion_angle"] < 30) & (df["speed"] >= 2)
             & (df["speed"] < 3)).to_numpy()
        want = np.mean([recall_score(df["label"][k], df[c][k] > 0.5)
                        for c in ("prob_s0", "prob_s1")])
        assert slow["recall"] == pytest.approx(want), m
        assert slow["n_moving"] == 3 and slow["scenes"] == 2, m
        angle = t[t["by"] == "angle to the line of sight (deg)"]
        # [0, 15): a, b, c; [15, 30): c; [30, 60): a; [60, 90]: b (still vehicles too)
        assert angle["scenes"].tolist() == [3, 1, 1, 1], m
    assert got["gt"]["recall"].tolist() != got["dis"]["recall"].tolist()
    stacked = ch09.blind_table(got)
    assert stacked.columns.tolist() == ["method", *got["gt"].columns]
    assert stacked["method"].tolist() == ["gt"] * len(got["gt"]) + ["dis"] * len(got["dis"])
    pd.testing.assert_frame_equal(
        stacked.drop(columns="method").reset_index(drop=True),
        pd.concat([got["gt"], got["dis"]], ignore_index=True))


def _recall_table(slow, fast):
    """A blind-spot table of the radial movers' speed bins: (n_moving, recall) per bin."""
    rows = [{"by": blind_spots.RADIAL_SPEED, "bin": b, "n_moving": n, "recall": r}
            for b, (n, r) in {"[2, 3)": slow, "[5, 10)": fast[0], "[10, 40)": fast[1]}.items()]
    rows.append({"by": blind_spots.SPEED, "bin": "[2, 3)", "n_moving": 50, "recall": 0.0})
    return pd.DataFrame(rows)


def test_recall_numbers_glue_each_method_s_slow_and_fast_recall_in_percent():
    """Per method ``recall_slow_<m>`` and ``recall_fast_<m>`` (%, to 0.1; fast: the movers
    of 5-10 and 10-40 m/s pooled), and the main method's again as the headline."""
    blind = {"gt": _recall_table((4, 0.123456), ((2, 0.5), (6, 1.0))),
             "dis": _recall_table((3, 0.666666), ((1, 0.0), (3, 0.333333)))}
    got = ch09.recall_numbers(blind, "dis")
    assert got == {"recall_slow_gt": 12.3, "recall_fast_gt": 87.5,
                   "recall_slow_dis": 66.7, "recall_fast_dis": 25.0,
                   "headline_recall_slow": 66.7, "headline_recall_fast": 25.0}
    assert list(got) == ["recall_slow_gt", "recall_fast_gt", "recall_slow_dis",
                         "headline_recall_slow", "recall_fast_dis", "headline_recall_fast"]
    on_gt = ch09.recall_numbers(blind, "gt")
    assert on_gt["headline_recall_slow"] == 12.3 and on_gt["headline_recall_fast"] == 87.5


def _interval_input():
    """Slow radial movers in scenes a, a, b, c (hit shares 1, 0.5: a seed at exactly 0.5 is
    no hit, 0, 1); out of the bin: a mover at exactly 30 degrees and a still vehicle in
    scene d, a mover at 30 degrees in b; fast radial movers (5 m/s and more, under 40) in a
    and b, and one at 40 m/s in d."""
    return pd.DataFrame({
        "label": [1, 1, 1, 1, 1, 0, 1, 1, 1, 1],
        "speed": [2.5, 2.1, 2.7, 2.0, 2.5, 2.5, 2.9, 5.0, 20.0, 40.0],
        "motion_angle": [0.0, 29.9, 12.0, 3.0, 30.0, 5.0, 30.0, 10.0, 10.0, 10.0],
        "scene": ["a", "a", "b", "c", "d", "d", "b", "a", "b", "d"],
        "prob_s0": [0.9, 0.5, 0.1, 0.8, 0.1, 0.9, 0.9, 0.9, 0.2, 0.1],
        "prob_s1": [0.7, 0.9, 0.4, 0.6, 0.1, 0.9, 0.9, 0.9, 0.9, 0.1]})


def test_recall_interval_takes_movers_below_30_degrees_and_hits_above_one_half():
    """The interval resamples the scenes of the movers (not still vehicles) moving less than
    30 degrees off the line of sight in the speed bin, each hit the share of seeds above
    0.5 (0.5 itself is no hit), with the seed given (default 0)."""
    df = _interval_input()
    hits, scenes = [1.0, 0.5, 0.0, 1.0], ["a", "a", "b", "c"]
    lo, hi, n = ch09.recall_interval(df, ch09.SLOW)
    assert n == 3
    assert (lo, hi) == pytest.approx(_bootstrap_interval(hits, scenes, seed=0), abs=1e-12)
    fast = ch09.recall_interval(df, ch09.FAST, seed=5)
    assert fast[2] == 2
    assert fast[:2] == pytest.approx(_bootstrap_interval([1.0, 0.5], ["a", "b"], 5), abs=1e-12)


def test_recall_intervals_glue_both_intervals_in_percent_with_the_seed_given():
    """``headline_recall_slow_ci`` and ``..._fast_ci``: "lo-hi" in percent to 0.1, flagged
    with their few scenes, each from the seed given."""
    df = _interval_input()
    lo, hi = _bootstrap_interval([1.0, 0.5, 0.0, 1.0], ["a", "a", "b", "c"], seed=3)
    flo, fhi = _bootstrap_interval([1.0, 0.5], ["a", "b"], seed=3)
    assert ch09.recall_intervals(df, seed=3) == {
        "headline_recall_slow_ci": f"{100 * lo:.1f}-{100 * hi:.1f} (3 scenes: too few)",
        "headline_recall_fast_ci": f"{100 * flo:.1f}-{100 * fhi:.1f} (2 scenes: too few)"}
    lo0, hi0 = _bootstrap_interval([1.0, 0.5, 0.0, 1.0], ["a", "a", "b", "c"], seed=0)
    assert ch09.recall_intervals(df)["headline_recall_slow_ci"] == (
        f"{100 * lo0:.1f}-{100 * hi0:.1f} (3 scenes: too few)")


def test_speed_angle_sets_the_seed_mean_recall_beside_the_rule_s_calls_by_token():
    """Per angle x speed cell with movers, the classifier's recall (share of seeds) beside
    the oracle rule's, its calls read from its published rows by ``ann_token`` (the rule's
    table in another order, with a row of its own)."""
    df = pd.DataFrame({"ann_token": ["A", "B", "C", "D"], "label": [1, 1, 1, 0],
                       "motion_angle": [10.0, 10.0, 70.0, 10.0], "speed": [2.5, 2.5, 8.0, 2.5],
                       "scene": ["a", "b", "a", "b"], "prob_s0": [0.9, 0.9, 0.1, 0.9],
                       "prob_s1": [0.2, 0.9, 0.1, 0.9]})
    baseline = pd.DataFrame({"ann_token": ["Z", "C", "B", "D", "A"],
                             "prob": [1.0, 1.0, 0.0, 1.0, 1.0]})
    got = ch09.speed_angle(df, baseline)
    want = pd.DataFrame({"angle to the line of sight (deg)": ["0-30", "60-90"],
                         "speed (m/s)": ["2-3", "5-40"], "movers": [2, 1], "scenes": [2, 1],
                         "classifier recall (%)": [75.0, 0.0],
                         "oracle rule recall (%)": [50.0, 100.0]})
    pd.testing.assert_frame_equal(got, want)


# --- the image signal -----------------------------------------------------------------------


def test_signal_table_takes_the_keyframe_pairs_median_focal_length_and_gap():
    """The signal at the keyframe pairs' median f_x (not f_y, not the mean, not the
    generalisation pair's) and median gap (us -> s), at the profile's ``flow_scale``."""
    p = _params(["gt", "dis"], flow_scale=0.75)

    def k(fx):
        return [fx, 0.0, 800.0, 0.0, fx + 100.0, 450.0, 0.0, 0.0, 1.0]

    pairs = pd.DataFrame({"set": ["keyframe", "general", "keyframe", "keyframe"],
                          "intrinsic": [k(1000.0), k(5000.0), k(1200.0), k(1300.0)],
                          "timestamp_1": [0, 0, 10_000_000, 20_000_000],
                          "timestamp_2": [500_000, 2_000_000, 10_450_000, 20_700_000]})
    got = ch09.signal_table(p, pairs)
    f, d = 1200.0, 2.0 * 0.5  # median f_x; 2 m/s over the median gap, 0.5 s
    z = np.array([30.0, 50.0, 70.0])
    lateral, radial = f * d / z, f * 1.9 * (1 / z - 1 / (z + d))
    assert got.columns.tolist() == ["distance (m)", "lateral shift (px)",
                                    "radial: width change (px)", "lateral at flow_scale 0.75 (px)",
                                    "radial at flow_scale 0.75 (px)"]
    assert got["distance (m)"].tolist() == z.tolist()
    assert got["lateral shift (px)"].tolist() == pytest.approx(lateral, rel=1e-12)
    assert got["radial: width change (px)"].tolist() == pytest.approx(radial, rel=1e-12)
    assert got["lateral at flow_scale 0.75 (px)"].tolist() == pytest.approx(0.75 * lateral,
                                                                            rel=1e-12)


def test_radial_px_reads_the_width_change_at_50_m_to_the_hundredth():
    """The radial width change at :data:`SIGNAL_DISTANCE` (50 m) by default or at the
    distance given, rounded to 0.01 px."""
    signal = pd.DataFrame({"distance (m)": [30.0, 50.0, 70.0],
                           "radial: width change (px)": [4.44444, 1.23456, 0.76543],
                           "lateral shift (px)": [9.0, 9.0, 9.0]})
    assert ch09.SIGNAL_DISTANCE == 50.0
    assert ch09.radial_px(signal) == 1.23
    assert ch09.radial_px(signal, 70.0) == 0.77
    assert ch09.radial_px(signal, distance=30.0) == 4.44


def test_far_flow_error_is_none_off_a_synthetic_world(tmp_path):
    """Without a generated world at the dataroot (real data: no exact flow), there is no
    far-box flow error to show: None, before anything reads the selection."""
    p = _params(["gt", "dis"], dataroot=str(tmp_path / "data"), run_dir=str(tmp_path / "r"))
    assert ch09.far_flow_error(p) is None


def test_far_flow_error_reads_the_flowcheck_node_s_far_boxes_in_the_methods_order(
        tmp_path, monkeypatch):
    """On a generated world: each method's mean EPE and Fl-all inside the far boxes of the
    published flowcheck rows, keyframe pairs with a valid box pixel only (a missing whole-
    frame error does not drop a row), methods in the order the rows give them."""
    p = _params(["gt", "dis"], run_dir=str(tmp_path / "r"))
    nan = float("nan")
    rows = pd.DataFrame({
        "set": ["keyframe"] * 6 + ["general"],
        "pair_id": ["a", "a", "a", "b", "b", "b", "c"],
        "scene": ["s0"] * 7,
        "method": ["gt", "farneback", "dis", "gt", "farneback", "dis", "dis"],
        "epe": [0.1, 2.0, nan, 0.2, 3.0, 1.0, 9.0],
        "fl": [0.0, 5.0, nan, 0.0, 6.0, 2.0, 90.0],
        "epe_box": [0.0, 1.0, 3.0, 0.5, nan, 1.0, 9.0],
        "fl_box": [0.0, 10.0, 30.0, 1.0, nan, 20.0, 90.0]})
    publish(p, Node("flowcheck"), {"accuracy": rows})
    monkeypatch.setattr(ch09.world, "is_synthetic", lambda root, version: True)
    got = ch09.far_flow_error(p)
    assert got.columns.tolist() == ["method", "EPE boxes (px)", "Fl-all boxes (%)"]
    assert got.to_numpy().tolist() == [["gt", 0.25, 0.5], ["farneback", 1.0, 10.0],
                                       ["dis", 2.0, 25.0]]


def test_rule_margin_falls_back_on_the_single_threshold_when_none_per_fold():
    """An empty per-fold list (a run without folds) means the one ``threshold_m_s``; rows
    are matched by token."""
    df = pd.DataFrame({"ann_token": ["b", "a"]})
    base = pd.DataFrame({"ann_token": ["a", "b"], "fold": [0, 1],
                         "residual_speed": [1.0, 0.25]})
    got = ch09.rule_margin(df, base, {"thresholds_m_s": [], "threshold_m_s": 0.5})
    assert got.tolist() == pytest.approx([-0.25, 0.5])


# --- the slow radial movers -----------------------------------------------------------------

#: (token, scene, label, angle, speed, prob_s0, prob_s1, rule margin): ten still vehicles
#: (seed means .9 .7 .5 .4 .3 .2 .1 .05 0 0; the rule calls one), six movers in the cell
#: (seed-mean .95 .6 .45 .8 .3 .75), three movers out of it (45 deg; 3.0 m/s; 30 deg).
SLOW_ROWS = [
    ("t0", "a", 0, 0.0, 0.0, 0.9, 0.9, 0.3), ("t1", "b", 0, 0.0, 0.0, 0.7, 0.7, -0.1),
    ("t2", "c", 0, 0.0, 0.0, 0.6, 0.4, -0.2), ("t3", "d", 0, 0.0, 0.0, 0.4, 0.4, -0.3),
    ("t4", "a", 0, 0.0, 0.0, 0.3, 0.3, -0.4), ("t5", "b", 0, 0.0, 0.0, 0.2, 0.2, -0.5),
    ("t6", "c", 0, 0.0, 0.0, 0.1, 0.1, -0.6), ("t7", "d", 0, 0.0, 0.0, 0.05, 0.05, -0.7),
    ("t8", "a", 0, 0.0, 0.0, 0.0, 0.0, -0.8), ("t9", "b", 0, 0.0, 0.0, 0.0, 0.0, -0.9),
    ("m1", "a", 1, 0.0, 2.5, 0.95, 0.95, 1.0), ("m2", "a", 1, 10.0, 2.0, 0.7, 0.5, 0.05),
    ("m3", "b", 1, 10.0, 2.5, 0.6, 0.3, -0.05), ("m4", "b", 1, 29.0, 2.5, 0.8, 0.8, -0.15),
    ("m5", "c", 1, 10.0, 2.99, 0.3, 0.3, 0.5), ("m6", "d", 1, 10.0, 2.5, 0.9, 0.6, -0.3),
    ("m7", "c", 1, 45.0, 2.5, 0.2, 0.2, 0.2), ("m8", "d", 1, 10.0, 3.0, 0.9, 0.9, -0.5),
    ("m9", "a", 1, 30.0, 2.5, 0.1, 0.1, 0.4)]
#: The rule's per-fold thresholds (m/s): scenes a and b are fold 0, c and d fold 1.
THRESHOLDS = [0.5, 1.0]


def _slow_radial_input():
    """(predictions, (the rule's published rows, its record)) of :data:`SLOW_ROWS`."""
    cols = ["ann_token", "scene", "label", "motion_angle", "speed", "prob_s0", "prob_s1",
            "margin"]
    df = pd.DataFrame(SLOW_ROWS, columns=cols)
    fold = df["scene"].isin(["c", "d"]).astype(int)
    base = pd.DataFrame({"ann_token": df["ann_token"], "fold": fold,
                         "residual_speed": df["margin"] + np.take(THRESHOLDS, fold),
                         "prob": (df["margin"] > 0).astype(float)}).iloc[::-1]
    record = {"thresholds_m_s": THRESHOLDS, "threshold_m_s": 0.75}
    return df.drop(columns="margin"), (base, record)


def test_slow_radial_compares_the_classifier_and_the_rule_at_own_and_matched_rates():
    """On the cell (2-3 m/s, under 30 degrees, movers only): at their own operating points
    the classifier finds 4 of 6 (seed shares), the rule 3 of 6, and they call 20 % and 10 %
    of the still vehicles moving (a still at exactly 0.5 is no call); at the rule's 10 % the
    classifier's threshold is 0.7 (3 of 6) and the rule's -0.1 (4 of 6), at the classifier's
    20 % 0.5 (4 of 6) and -0.2 (5 of 6); the intervals from ``params.seed``; the words say
    these numbers; the ROC scores are the seed-mean and the margin."""
    p = _params(["gt", "dis"], seed=7)
    df, baseline = _slow_radial_input()
    got = ch09.slow_radial(p, df, baseline, "dis")
    own = got["own"]
    assert (own["angle"], own["speed"], own["movers"], own["scenes"]) == (
        (0.0, 30.0), (2.0, 3.0), 6, 4)
    assert [own["classifier"], own["rule"], own["rule_minus_classifier"]] == pytest.approx(
        [400 / 6, 50.0, 50.0 - 400 / 6])
    diffs, scenes = [0.0, 0.5, -0.5, -1.0, 1.0, -1.0], ["a", "a", "b", "b", "c", "d"]
    lo, hi = _bootstrap_interval(diffs, scenes, seed=7)
    assert own["ci"] == pytest.approx((100 * lo, 100 * hi), abs=1e-9)
    assert got["far_rule"] == pytest.approx(10.0) and got["far_clf"] == pytest.approx(20.0)
    for key, far, clf, rule in (("at_rule", 10.0, 50.0, 400 / 6),
                                ("at_clf", 20.0, 400 / 6, 500 / 6)):
        e = got[key]
        assert (e["angle"], e["speed"], e["movers"], e["scenes"]) == ((0.0, 30.0), (2.0, 3.0),
                                                                      6, 4), key
        assert [e["far"], e["classifier"], e["rule"], e["rule_minus_classifier"]] == \
            pytest.approx([far, clf, rule, rule - clf]), key
    clf_score = df[["prob_s0", "prob_s1"]].mean(axis=1).to_numpy()
    margin = np.array([r[-1] for r in SLOW_ROWS])
    assert got["scores"]["classifier"] == pytest.approx(clf_score)
    assert got["scores"]["oracle rule"] == pytest.approx(margin)
    assert list(got["scores"]) == ["classifier", "oracle rule"]
    assert got["labels"].tolist() == df["label"].tolist()
    assert got["cell"].tolist() == [False] * 10 + [True] * 6 + [False] * 3
    assert got["own_words"] == (
        f"Of the 6 movers {CELL_WORDS} (4 scenes), the classifier on dis flow recalls 66.7 % "
        "and the oracle rule on the same flow 50.0 % at their own operating points (rule "
        f"minus classifier -16.7 points, 95 % interval over scenes {100 * lo:+.1f} to "
        f"{100 * hi:+.1f}, 4 scenes: too few); but the rule calls 10.0 % of the still "
        "vehicles moving and the classifier 20.0 %, so these two recalls are not comparable.")
    words = got["matched_words"]
    assert words.startswith(
        f"Compared at equal false-alarm rates on dis flow, the 6 movers {CELL_WORDS} (4 scenes: too "
        "few): at the rule's false-alarm rate (10.0 % of still vehicles called moving) the "
        "classifier recalls 50.0 % and the rule 66.7 % (rule minus classifier +16.7 points, "
        "95 % interval over scenes ")
    assert ("; at the classifier's false-alarm rate (20.0 % of still vehicles called moving) "
            "the classifier recalls 66.7 % and the rule 83.3 % (rule minus classifier +16.7 "
            "points, 95 % interval over scenes ") in words
    assert set(got) == {"own", "far_rule", "far_clf", "at_rule", "at_clf", "own_words",
                        "matched_words", "scores", "labels", "cell"}


def _many_scenes():
    """(predictions, rule's rows and record) of 240 random vehicles in 30 scenes: enough
    scenes that another bootstrap seed gives another interval; probabilities to 0.1, so
    that some are exactly 0.5 (no hit)."""
    rng = np.random.default_rng(1)
    n = 240
    label = (rng.random(n) < 0.5).astype(int)
    margin = rng.normal(0.0, 1.0, n)
    fold = np.arange(n) % 30 % 2
    df = pd.DataFrame({"ann_token": [f"t{i}" for i in range(n)],
                       "scene": [f"s{i % 30}" for i in range(n)], "label": label,
                       "motion_angle": rng.uniform(0.0, 60.0, n),
                       "speed": np.where(label == 1, rng.uniform(1.5, 3.5, n), 0.0),
                       "prob_s0": rng.random(n).round(1),
                       "prob_s1": rng.random(n).round(1)})
    base = pd.DataFrame({"ann_token": df["ann_token"], "fold": fold,
                         "residual_speed": margin + np.take(THRESHOLDS, fold),
                         "prob": (margin > 0).astype(float)})
    return df, (base, {"thresholds_m_s": THRESHOLDS}), margin


def test_the_intervals_draw_scenes_with_the_seed_given():
    """On 30 scenes (where the seed moves the interval), the recall interval, its glued
    text and the slow radial movers' intervals (own and matched operating points) come
    from the seed given (``params.seed`` for :func:`slow_radial`), not from seed 0."""
    df, baseline, margin = _many_scenes()
    probs = df[["prob_s0", "prob_s1"]].to_numpy().T
    labels = df["label"].to_numpy()
    k = ((labels == 1) & (df["motion_angle"] < 30) & (df["speed"] >= 2)
         & (df["speed"] < 3)).to_numpy()
    share, scenes = (probs[:, k] > 0.5).mean(axis=0), df["scene"].to_numpy()[k]
    by_seed = {s: _bootstrap_interval(share, scenes, seed=s) for s in (0, 3)}
    assert by_seed[0] != by_seed[3]
    for s, (lo, hi) in by_seed.items():
        got = ch09.recall_interval(df, ch09.SLOW, seed=s)
        assert got == pytest.approx((lo, hi, len(set(scenes))), abs=1e-12), s
        assert ch09.recall_intervals(df, seed=s)["headline_recall_slow_ci"] == (
            f"{100 * lo:.1f}-{100 * hi:.1f}"), s  # 30 scenes: not flagged
    assert ch09.recall_interval(df, ch09.SLOW)[:2] == pytest.approx(by_seed[0], abs=1e-12)
    assert ch09.recall_intervals(df)["headline_recall_slow_ci"] == (
        f"{100 * by_seed[0][0]:.1f}-{100 * by_seed[0][1]:.1f}")

    got = ch09.slow_radial(_params(["gt", "dis"], seed=7), df, baseline, "dis")
    lo, hi = _bootstrap_interval((margin[k] > 0) - share, scenes, seed=7)
    assert got["own"]["ci"] == pytest.approx((100 * lo, 100 * hi), abs=1e-9)
    assert _bootstrap_interval((margin[k] > 0) - share, scenes, seed=0) != (lo, hi)
    # the matched intervals' draws (the bootstrap itself is blind_spots.matched_effect's)
    clf, still = probs.mean(axis=0), labels == 0
    for key, far in (("at_rule", np.mean(margin[still] > 0)),
                     ("at_clf", np.mean(clf[still] > 0.5))):
        seeded = [blind_spots.matched_effect(df, clf, margin, (0.0, 30.0), (2.0, 3.0), far,
                                             seed=s)["ci"] for s in (7, 0)]
        assert seeded[0] != seeded[1]
        assert got[key]["ci"] == pytest.approx(seeded[0], abs=1e-9), key
