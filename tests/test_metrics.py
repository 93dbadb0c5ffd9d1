"""flowmod.metrics: defaults, thresholds passed through, input shapes and dtypes, table
columns, and the threshold fit, on small hand-made sets with numbers worked out by hand."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from sklearn.metrics import precision_recall_fscore_support

from flowmod import metrics as ev

# 6 objects, 2 categories; at 0.5: truck tp 2 fp 1 fn 0, car tp 0 fp 1 fn 1;
# at 0.3 the car at 0.4 becomes a true positive: car tp 1 fp 1 fn 0.
CAT = ["truck", "car", "truck", "car", "truck", "car"]
Y6 = np.array([1, 1, 0, 0, 1, 0])
P6 = np.array([0.9, 0.4, 0.6, 0.2, 0.8, 0.7])
G6 = np.array(["a", "b", "a", "b", "a", "b"])


def _scenes(n_scenes: int = 40, seed: int = 7):
    """(y, p, scenes) with scenes of 2-20 objects and noisy scores: bootstrap replicates that
    take many distinct values, so their percentiles move with n and the seed."""
    rng = np.random.default_rng(seed)
    g = np.repeat(np.arange(n_scenes), rng.integers(2, 21, n_scenes))
    y = rng.integers(0, 2, len(g))
    p = np.clip(0.5 + 0.3 * (2 * y - 1) + rng.normal(0, 0.3, len(g)), 0, 1)
    return y, p, g


# --- threshold sweep, PR curve -----------------------------------------------------------


def test_threshold_sweep_default_grid_is_005_to_095():
    """Without thresholds: 19 rows at 0.05, 0.10, ..., 0.95 exactly, each scored at its own
    threshold."""
    sweep = ev.threshold_sweep(Y6, P6)
    assert sweep["threshold"].tolist() == [round(0.05 * i, 2) for i in range(1, 20)]
    assert list(sweep.columns) == ["threshold", "precision", "recall", "f1", "accuracy"]
    for _, row in sweep.iterrows():
        m = ev.metrics(Y6, P6, row["threshold"])
        assert row["f1"] == m["f1"] and row["accuracy"] == m["accuracy"]
    assert sweep.loc[0, "f1"] == pytest.approx(2 * 3 / (2 * 3 + 3))  # all moving
    assert sweep.loc[18, "f1"] == 0.0  # nothing above 0.95


def test_threshold_sweep_uses_each_given_threshold():
    """Given thresholds are applied, not 0.5: car at 0.4 is moving at 0.3 only."""
    sweep = ev.threshold_sweep(Y6, P6, [0.3, 0.5, 0.85])
    # 0.3: tp 3 fp 2 fn 0; 0.5: tp 2 fp 2 fn 1; 0.85: tp 1 fp 0 fn 2
    np.testing.assert_allclose(sweep["f1"], [6 / 8, 4 / 7, 2 / 4])
    np.testing.assert_allclose(sweep["precision"], [3 / 5, 2 / 4, 1.0])


def test_pr_curve_from_the_highest_threshold_down():
    """Every distinct score as a threshold (prob >= t), highest first, index 0..n-1; AP as the
    step sum of precision over recall gains."""
    y = np.array([1, 0, 1, 1, 0])
    p = np.array([0.9, 0.8, 0.6, 0.4, 0.2])
    curve, ap = ev.pr_curve(y, p)
    want = pd.DataFrame({"threshold": [0.9, 0.8, 0.6, 0.4, 0.2],
                         "precision": [1.0, 1 / 2, 2 / 3, 3 / 4, 3 / 5],
                         "recall": [1 / 3, 1 / 3, 2 / 3, 1.0, 1.0]})
    pd.testing.assert_frame_equal(curve, want)
    assert ap == pytest.approx(1 / 3 * 1 + 1 / 3 * 2 / 3 + 1 / 3 * 3 / 4)


def test_pr_curve_thresholds_are_float64_for_float32_scores():
    """float32 scores (as a model writes them) give float64 thresholds, the same values."""
    y = np.array([1, 0, 1, 1, 0])
    p32 = np.array([0.9, 0.8, 0.6, 0.4, 0.2], dtype=np.float32)
    curve, ap = ev.pr_curve(y, p32)
    want, want_ap = ev.pr_curve(y, p32.astype(np.float64))
    pd.testing.assert_frame_equal(curve, want)
    assert curve["threshold"].dtype == np.float64 and ap == want_ap


# --- scene bootstrap and intervals --------------------------------------------------------


def test_bootstrap_defaults_are_2000_replicates_with_seed_0():
    """n=2000, seed=0 by default in every bootstrap entry point (and the data are such that
    another n or seed gives another interval)."""
    y, p, g = _scenes()
    q = np.clip(p + 0.2, 0, 1)
    reps = ev.scene_bootstrap(y, p, g)
    np.testing.assert_array_equal(reps, ev.scene_bootstrap(y, p, g, n=2000, seed=0))
    ci = ev.bootstrap_f1_ci(y, p, g)
    assert ci == ev.bootstrap_f1_ci(y, p, g, n=2000, seed=0)
    assert ci != ev.bootstrap_f1_ci(y, p, g, n=2000, seed=1)
    assert ci != ev.bootstrap_f1_ci(y, p, g, n=2001, seed=0)
    assert ev.seed_summary(y, p, g)["ci"] == ci
    d = ev.paired_comparison(y, p, q, g)
    assert d == ev.paired_comparison(y, p, q, g, n=2000, seed=0)
    assert d["ci"] != ev.paired_comparison(y, p, q, g, n=2001, seed=0)["ci"]
    assert d["ci"] != ev.paired_comparison(y, p, q, g, n=2000, seed=1)["ci"]


def test_scene_bootstrap_of_one_object_and_of_none():
    """One object: every replicate is its F1; no objects: n undefined replicates."""
    np.testing.assert_array_equal(ev.scene_bootstrap([1], [0.9], ["s"], n=5), np.ones(5))
    assert np.isnan(ev.scene_bootstrap([], [], [], n=4)).all()
    assert len(ev.scene_bootstrap([], [], [], n=4)) == 4


@pytest.mark.filterwarnings("error")
def test_scene_bootstrap_issues_no_warnings():
    """Counting per scene uses no deprecated numpy call (warnings are errors here)."""
    reps = ev.scene_bootstrap(Y6, P6, G6, n=50, seed=0)
    assert reps.shape == (50,) and ((0 <= reps) & (reps <= 1)).all()


def test_scene_bootstrap_compares_float32_scores_in_float64():
    """A float32 score of 0.3 is above the threshold 0.3 (as in metrics), not equal to it."""
    y = np.array([1, 0, 1, 0])
    p32 = np.array([0.3, 0.3, 0.9, 0.1], dtype=np.float32)
    f1 = ev.metrics(y, p32, 0.3)["f1"]
    assert f1 == pytest.approx(4 / 5)  # tp 2 fp 1 fn 0
    reps = ev.scene_bootstrap(y, p32, np.zeros(4), n=20, threshold=0.3)
    np.testing.assert_allclose(reps, f1)


def test_scene_bootstrap_flattens_labels_and_groups():
    """Labels as a column (N, 1) and scenes as a row (1, N) count as N objects."""
    y, p, g = _scenes(12)
    flat = ev.scene_bootstrap(y, p, g, n=100, seed=4)
    np.testing.assert_array_equal(ev.scene_bootstrap(y[:, None], p, g[None], n=100, seed=4),
                                  flat)


def test_interval_of_float32_replicates_is_computed_in_float64():
    """float32 replicates are interpolated in float64, the same as their float64 copy."""
    reps = np.array([0.1, 0.7, 0.3, 0.9, 0.45], dtype=np.float32)
    assert ev.interval(reps, 0.7) == ev.interval(reps.astype(np.float64), 0.7)


def test_bootstrap_f1_ci_passes_level_seed_and_threshold():
    """The interval is interval(scene_bootstrap(..., n, seed, threshold), level)."""
    y, p, g = _scenes(20)
    reps = ev.scene_bootstrap(y, p, g, n=300, seed=3, threshold=0.3)
    assert ev.bootstrap_f1_ci(y, p, g, n=300, seed=3, threshold=0.3, level=0.5) == \
        ev.interval(reps, 0.5)
    assert ev.interval(reps, 0.5) != ev.interval(reps)
    assert ev.interval(reps) != ev.interval(ev.scene_bootstrap(y, p, g, n=300, seed=3))


# --- seed summary, paired comparison ------------------------------------------------------


def test_seed_summary_scores_each_seed_at_the_given_threshold():
    """Per-seed counts and scores at threshold 0.3 (not 0.5), under the key per_seed."""
    perfect = np.where(Y6 == 1, 0.9, 0.1)
    s = ev.seed_summary(Y6, np.stack([P6, perfect]), G6, n=50, threshold=0.3)
    assert s["per_seed"] == [  # P6 at 0.3: tp 3 fp 2 fn 0
        {"f1": 0.75, "precision": 0.6, "recall": 1.0, "tp": 3, "fp": 2, "fn": 0},
        {"f1": 1.0, "precision": 1.0, "recall": 1.0, "tp": 3, "fp": 0, "fn": 0}]
    assert (s["f1"], s["f1_min"], s["f1_max"]) == pytest.approx((0.875, 0.75, 1.0))


def test_seed_summary_interval_at_the_given_level():
    """ci is the scene interval at the given level, and the level is reported."""
    y, p, g = _scenes(20)
    probs = np.stack([p, np.clip(p + 0.1, 0, 1)])
    s = ev.seed_summary(y, probs, g, n=300, seed=2, threshold=0.3, level=0.5)
    assert s["level"] == 0.5
    assert s["ci"] == ev.bootstrap_f1_ci(y, probs, g, 300, 2, 0.3, 0.5)
    assert s["ci"] != ev.bootstrap_f1_ci(y, probs, g, 300, 2, 0.3, 0.95)


def test_paired_comparison_at_the_given_threshold_and_level():
    """Point difference, interval and share all at threshold 0.3 and level 0.5."""
    perfect = np.where(Y6 == 1, 0.9, 0.1)
    d = ev.paired_comparison(Y6, P6, perfect, G6, n=50, threshold=0.3)
    assert d["delta_f1"] == pytest.approx(0.75 - 1.0) and d["per_seed"] == [pytest.approx(-0.25)]
    y, p, g = _scenes(20)
    q = np.clip(p + 0.15, 0, 1)
    d = ev.paired_comparison(y, p, q, g, n=300, seed=2, threshold=0.3, level=0.5)
    diff = (ev.scene_bootstrap(y, p, g, 300, 2, 0.3) - ev.scene_bootstrap(y, q, g, 300, 2, 0.3))
    assert d["ci"] == ev.interval(diff, 0.5) and d["ci"] != ev.interval(diff)
    assert d["p_not_better"] == np.mean(diff <= 0)
    assert d["p_two_sided"] == ev.two_sided_p(diff)
    assert d["delta_f1"] == pytest.approx(ev.metrics(y, p, 0.3)["f1"] - ev.metrics(y, q, 0.3)["f1"])


def test_two_sided_p_counts_ties_on_both_sides_and_agrees_with_the_interval():
    """Twice the smaller of the shares with A - B <= 0 and >= 0, at most 1, over the
    defined replicates. Replicates that tie at 0 count on both sides: 95 of 100 at or
    below 0 with 10 of them exactly 0 is p = 0.3 (the share with A <= B alone said 0.1),
    and 100 of 100 at or below 0 with 30 at 0 is p = 0.6, where it said 0: the percentile
    interval of those ends at 0, so neither is decided (an effect chapter 14's Holm column
    called decided on the smoke study)."""
    r = np.r_[np.full(85, -0.02), np.zeros(10), np.full(5, 0.01)]
    assert ev.two_sided_p(r) == pytest.approx(0.3)
    r = np.r_[np.full(97, -0.02), np.zeros(2), np.full(1, 0.01), [np.nan] * 7]
    assert ev.two_sided_p(r) == pytest.approx(0.06)
    ties = np.r_[np.full(70, -0.02), np.zeros(30)]
    assert ev.two_sided_p(ties) == pytest.approx(0.6) and ev.interval(ties)[1] == 0.0
    assert ev.verdict(ev.interval(ties)) == "undecided"
    assert ev.two_sided_p(np.full(50, 0.03)) == 0.0 and ev.two_sided_p(np.full(50, -0.03)) == 0.0
    assert ev.two_sided_p(np.r_[np.full(50, 0.03), np.full(50, -0.03)]) == 1.0
    assert np.isnan(ev.two_sided_p([np.nan, np.nan])) and np.isnan(ev.two_sided_p([]))
    # every decided-by-p effect has an interval that excludes 0, on random replicates
    rng = np.random.default_rng(3)
    for _ in range(200):
        r = np.round(rng.normal(rng.uniform(-0.05, 0.05), 0.02, 400), 2)
        if ev.two_sided_p(r) < 0.05:
            assert ev.verdict(ev.interval(r)) != "undecided"


def test_paired_comparison_says_whether_it_decides_and_what_it_could_detect():
    """The verdict follows the interval; the detectable difference is 2.8 standard errors of
    the replicates (95 %, 80 % power): far apart decided, identical undecided."""
    y, p, g = _scenes(20)
    better = np.where(y == 1, 0.9, 0.1)
    d = ev.paired_comparison(y, better, p, g, n=300, seed=1)
    diff = ev.scene_bootstrap(y, better, g, 300, 1) - ev.scene_bootstrap(y, p, g, 300, 1)
    assert d["detectable"] == pytest.approx(2.8016 * np.std(diff, ddof=1), rel=1e-3)
    same = ev.paired_comparison(y, p, p, g, n=300, seed=1)
    t = ev.comparison_table({"better - p": d, "p - p": same})
    assert t["verdict"].tolist() == ["A better", "undecided"]
    assert t.loc[0, "detectable (points)"] == round(100 * d["detectable"], 1) > 0
    assert ev.verdict((-0.2, -0.1)) == "B better" and ev.verdict((np.nan, np.nan)) == "undecided"
    assert np.isnan(ev.detectable([0.1]))


def test_paired_comparison_per_seed_pairs_only_common_seeds():
    """A with 2 seeds against B with 1: one per-seed difference (seed 0 against seed 0)."""
    perfect = np.where(Y6 == 1, 0.9, 0.1)
    d = ev.paired_comparison(Y6, np.stack([P6, perfect]), P6, G6, n=50)
    assert d["per_seed"] == [0.0]
    assert d["delta_f1"] == pytest.approx((4 / 7 + 1) / 2 - 4 / 7)


# --- breakdown ------------------------------------------------------------------------------


def _frame(name, keys, n, n_moving, prec, rec, f1, acc):
    return pd.DataFrame({name: keys, "n": n, "n_moving": n_moving, "precision": prec,
                         "recall": rec, "f1": f1, "accuracy": acc})


def test_breakdown_by_category_by_default_in_sorted_order():
    """Default by='category'; rows sorted by value (truck comes first in the data)."""
    got = ev.breakdown(pd.DataFrame({"category": CAT}), Y6, P6)
    # car: y [1,0,0] yhat [0,0,1]; truck: y [1,0,1] yhat [1,1,1]
    want = _frame("category", ["car", "truck"], [3, 3], [1, 2], [0.0, 2 / 3], [0.0, 1.0],
                  [0.0, 0.8], [1 / 3, 2 / 3])
    pd.testing.assert_frame_equal(got, want)


def test_breakdown_at_the_given_threshold():
    """threshold=0.3 makes the car at 0.4 a true positive: car tp 1 fp 1 fn 0."""
    got = ev.breakdown(pd.DataFrame({"category": CAT}), Y6, P6, threshold=0.3)
    np.testing.assert_allclose(got["f1"], [2 / 3, 0.8])


def test_breakdown_bins_are_left_closed_and_empty_bins_dropped():
    """Default distance bins [a, b): 10.0 falls in [10, 20), 0.0 in [0, 10); bins without
    objects give no row."""
    df = pd.DataFrame({"distance": [0.0, 9.5, 10.0, 12.0, 35.0, 80.0]})
    y = np.array([1, 0, 1, 1, 0, 1])
    p = np.array([0.9, 0.1, 0.8, 0.2, 0.6, 0.9])
    got = ev.breakdown(df, y, p, by="distance")
    want = _frame("distance_bin", ["[0.0, 10.0)", "[10.0, 20.0)", "[30.0, 40.0)", "[70.0, inf)"],
                  [2, 2, 1, 1], [1, 2, 0, 1], [1.0, 1.0, 0.0, 1.0], [1.0, 0.5, np.nan, 1.0],
                  [1.0, 2 / 3, np.nan, 1.0], [1.0, 0.5, 0.0, 1.0])
    pd.testing.assert_frame_equal(got, want)


def test_breakdown_uses_the_given_bins():
    """bins replace DISTANCE_BINS."""
    df = pd.DataFrame({"distance": [0.0, 9.5, 10.0, 12.0, 35.0, 80.0]})
    got = ev.breakdown(df, Y6, P6, by="distance", bins=[0, 20, 100])
    assert got["distance_bin"].tolist() == ["[0, 20)", "[20, 100)"]
    assert got["n"].tolist() == [4, 2]


def test_breakdown_columns_and_scene_interval():
    """With groups: ci_lo, ci_hi (the row's scene bootstrap with n_boot, seed, threshold)
    and scenes; without: exactly the seven metric columns."""
    df = pd.DataFrame({"category": CAT})
    plain = ev.breakdown(df, Y6, P6)
    assert list(plain.columns) == ["category", "n", "n_moving", "precision", "recall", "f1",
                                   "accuracy"]
    got = ev.breakdown(df, Y6, P6, groups=G6, n_boot=50, seed=2, threshold=0.3)
    assert list(got.columns) == list(plain.columns) + ["ci_lo", "ci_hi", "scenes"]
    for row, cat in zip(got.itertuples(), ["car", "truck"], strict=True):
        i = np.flatnonzero(np.array(CAT) == cat)
        assert (row.ci_lo, row.ci_hi) == ev.bootstrap_f1_ci(Y6[i], P6[i], G6[i], 50, 2, 0.3)
        assert row.scenes == 1
    pd.testing.assert_frame_equal(ev.breakdown(df, Y6, P6, groups=G6[None], n_boot=50, seed=2,
                                               threshold=0.3), got)


def test_breakdown_interval_defaults_are_1000_replicates_with_seed_0():
    """n_boot=1000, seed=0 by default."""
    y, p, g = _scenes()
    df = pd.DataFrame({"category": np.where(np.arange(len(y)) % 3, "car", "truck")})
    got = ev.breakdown(df, y, p, groups=g)
    pd.testing.assert_frame_equal(got, ev.breakdown(df, y, p, groups=g, n_boot=1000, seed=0))
    for other in ({"n_boot": 1001, "seed": 0}, {"n_boot": 1000, "seed": 1}):
        assert not got.equals(ev.breakdown(df, y, p, groups=g, **other))


def test_breakdown_of_nothing_keeps_the_columns():
    """No objects: an empty table with all its columns."""
    df = pd.DataFrame({"category": pd.Series([], dtype=object)})
    assert list(ev.breakdown(df, [], []).columns) == [
        "category", "n", "n_moving", "precision", "recall", "f1", "accuracy"]
    got = ev.breakdown(df, [], [], groups=[])
    assert len(got) == 0 and list(got.columns)[-3:] == ["ci_lo", "ci_hi", "scenes"]


# --- tables ---------------------------------------------------------------------------------


def test_table3_seed_range_needs_more_than_one_seed():
    """f1_min/f1_max without a seed count (or with 1 seed) give no seed range."""
    row = {"method": "m", "f1": 0.5, "precision": 0.4, "recall": 0.6, "f1_min": 0.45,
           "f1_max": 0.55}
    t = ev.table3([row, {**row, "seeds": 1}, {**row, "seeds": 2}])
    assert t["seed range (%)"].tolist() == ["", "", "45.0-55.0"]
    assert t["seeds"].tolist() == ["", 1, 2]


def test_comparison_table_interval_in_points():
    """The CI bounds are both multiplied by 100."""
    r = {"delta_f1": 0.15, "ci": (0.1, 0.2), "per_seed": [0.15], "p_not_better": 0.0,
         "n_scenes": 3, "n": 30}
    t = ev.comparison_table({"A - B": r})
    assert t.loc[0, "95% CI, scenes and seeds (points)"] == "10.0 to 20.0 (3 scenes: too few)"
    assert list(t.columns) == ev.COMPARISON_COLUMNS
    empty = ev.comparison_table({})
    assert len(empty) == 0 and list(empty.columns) == ev.COMPARISON_COLUMNS, "columns kept"


# --- the original protocol ------------------------------------------------------------------

# 130 moving objects, all found except the last: batches of 128 are [128 right | 1 right,
# 1 missed], batches of 129 are [129 right | 1 missed].
Y130 = np.ones(130, dtype=int)
P130 = np.r_[np.full(129, 0.9), 0.1]

# 6 objects for threshold 0.3: moving, still, ... alternating.
YT = np.array([1, 0, 1, 0, 1, 0])
PT = np.array([0.4, 0.4, 0.9, 0.2, 0.35, 0.1])


def test_paper_protocol_defaults_are_batch_128_threshold_05():
    """Default batch 128 and threshold 0.5: per-batch P (1, 1), R (1, 1/2), F1 (1, 2/3)."""
    assert ev.paper_protocol_scores(Y130, P130) == pytest.approx(
        {"precision": 1.0, "recall": 0.75, "f1": 5 / 6})
    assert ev.paper_protocol_f1(Y130, P130) == pytest.approx(5 / 6)
    assert ev.paper_protocol_f1(Y130, P130, 129) == pytest.approx(0.5)


def test_paper_protocol_of_one_object_and_of_none():
    """One object makes one batch of its own; no objects score 0."""
    assert ev.paper_protocol_scores([1], [0.9]) == {"precision": 1.0, "recall": 1.0, "f1": 1.0}
    assert ev.paper_protocol_scores([], []) == {"precision": 0.0, "recall": 0.0, "f1": 0.0}


def test_paper_protocol_f1_at_the_given_threshold():
    """Batches of 2 at 0.3: F1 (2/3, 1, 1), against (0, 1, 0) at 0.5."""
    assert ev.paper_protocol_f1(YT, PT, 2, 0.3) == pytest.approx(8 / 9)
    assert ev.paper_protocol_f1(YT, PT, 2) == pytest.approx(1 / 3)


def test_thin_still_can_keep_every_still_object():
    """keep == every keeps all; labels as a column give a flat (N,) mask."""
    np.testing.assert_array_equal(ev.thin_still([0, 0, 1, 0], keep=2, every=2), [1, 1, 1, 1])
    mask = ev.thin_still(np.array([[0], [0], [1], [0]]))
    assert mask.shape == (4,)
    np.testing.assert_array_equal(mask, [1, 0, 1, 1])


def test_protocol_comparison_at_the_given_threshold():
    """Every row scored at 0.3; inputs shaped (1, N) are flattened."""
    t = ev.protocol_comparison(YT, PT, batch_size=2, threshold=0.3)
    # thinned keeps objects 0, 1, 2, 4, 5 (stills 1 and 5: 1st of every 2)
    assert t["n"].tolist() == [6, 6, 5, 5]
    np.testing.assert_allclose(t["precision"], [3 / 4, 5 / 6, 3 / 4, 1 / 2])
    np.testing.assert_allclose(t["recall"], [1.0, 1.0, 1.0, 2 / 3])
    np.testing.assert_allclose(t["f1"], [6 / 7, 8 / 9, 6 / 7, 5 / 9])
    pd.testing.assert_frame_equal(ev.protocol_comparison(YT[None], PT[None], 2, 0.3), t)


def test_protocol_comparison_default_batch_is_128():
    """Per-batch rows use batches of 128 by default."""
    t = ev.protocol_comparison(Y130, P130)
    np.testing.assert_allclose(t["f1"], [258 / 259, 5 / 6, 258 / 259, 5 / 6])


# --- threshold fit --------------------------------------------------------------------------


def test_fit_threshold_midpoints_and_the_ends():
    """Midpoint below the lowest score called moving; 0.5 below the smallest score when all
    are called moving; the maximum when nothing moves; one object works."""
    assert ev.fit_threshold([1.0, 2.0, 3.0], [0, 0, 1]) == 2.5
    assert ev.fit_threshold([1.0, 2.0, 3.0], [1, 1, 1]) == 0.5
    assert ev.fit_threshold([1.0, 2.0, 3.0], [0, 0, 0]) == 3.0
    assert ev.fit_threshold([2.0], [1]) == 1.5


def test_fit_threshold_never_cuts_inside_a_tie():
    """Scores 3, 2, 2, 1 (labels 1, 1, 0, 0): cutting between the two 2s is impossible, so the
    best is both 2s (F1 4/5) against 3 alone (2/3): t = 1.5."""
    assert ev.fit_threshold([3.0, 2.0, 2.0, 1.0], [1, 1, 0, 0]) == 1.5
    assert ev.fit_threshold([2.0, 1.0, 3.0, 2.0], [0, 0, 1, 1]) == 1.5


def test_fit_threshold_brute_force():
    """Equals the first best of every cut between distinct scores, from the top."""
    rng = np.random.default_rng(5)
    for _ in range(20):
        s = rng.integers(0, 6, 15).astype(float)
        y = rng.integers(0, 2, 15)
        if y.sum() == 0:
            continue
        cuts = np.r_[s.min() - 1, np.unique(s)][::-1]  # highest first
        f1 = [precision_recall_fscore_support(y, (s > c).astype(int), average="binary",
                                              zero_division=0)[2] for c in cuts]
        best = cuts[int(np.argmax(f1))]
        above = s[s > best]
        assert ev.fit_threshold(s, y) == (best + above.min()) / 2


def test_fit_threshold_accepts_unsigned_and_column_inputs():
    """uint8 scores are ranked as numbers (not negated with wrap-around); (N, 1) columns are
    flattened."""
    assert ev.fit_threshold(np.array([0, 2, 4], dtype=np.uint8), [1, 0, 0]) == -0.5
    assert ev.fit_threshold(np.array([[1.0], [2.0], [3.0]]), [0, 0, 1]) == 2.5
    assert ev.fit_threshold([1.0, 2.0, 3.0], np.array([[0], [0], [1]])) == 2.5


def test_fit_threshold_rejects_bad_input():
    """Different lengths or no scores: a ValueError that says so."""
    for scores, labels in (([1.0, 2.0, 3.0], [1, 0]), ([], [])):
        with pytest.raises(ValueError, match="need equally long non-empty scores"):
            ev.fit_threshold(scores, labels)


def test_apply_threshold_is_strict_int_and_float64():
    """1 where score > t (not >=), int64; a float32 0.3 is above 0.3."""
    out = ev.apply_threshold([0.5, 0.6, 0.4], 0.5)
    assert out.dtype == np.int64 and out.tolist() == [0, 1, 0]
    p32 = np.array([0.3, 0.2], dtype=np.float32)
    assert ev.apply_threshold(p32, 0.3).tolist() == [1, 0]


@pytest.mark.parametrize("fn", [
    lambda y: ev.metrics(y, [0.8, 0.8, 0.1]), lambda y: ev.pr_curve(y, [0.8, 0.8, 0.1]),
    lambda y: ev.fit_threshold([3.0, 2.0, 1.0], y), lambda y: ev.thin_still(y),
    lambda y: ev.scene_bootstrap(y, [0.8, 0.8, 0.1], ["a", "a", "b"], n=5),
    lambda y: ev.protocol_comparison(y, [0.8, 0.8, 0.1])])
def test_labels_other_than_0_and_1_are_refused_not_truncated(fn):
    """A label of 0.9 (or 2, or -1 for unknown) is an error, not a still object."""
    fn([1, 1, 0])  # the same call with valid labels works
    for bad in ([0.9, 1, 0], [2, 1, 0], [-1, 1, 0]):
        with pytest.raises(ValueError, match="0 \\(still\\) / 1 \\(moving\\)"):
            fn(bad)


# --- undefined numbers: NaN, not 0 ---------------------------------------------------------


def test_recall_and_f1_without_a_mover_are_undefined_not_0():
    """Without a true mover recall and F1 are undefined (NaN), also when a still vehicle is
    called moving; precision is undefined without a predicted mover; a missed mover gives a
    defined F1 of 0."""
    m = ev.metrics([0, 0, 0], [0.9, 0.1, 0.2])
    assert m["precision"] == 0.0 and np.isnan(m["recall"]) and np.isnan(m["f1"])
    m = ev.metrics([0, 0], [0.1, 0.2])
    assert np.isnan(m["precision"]) and np.isnan(m["recall"]) and np.isnan(m["f1"])
    assert m["accuracy"] == 1.0
    m = ev.metrics([1, 0], [0.1, 0.2])
    assert np.isnan(m["precision"]) and m["recall"] == 0.0 and m["f1"] == 0.0
    assert np.isnan(ev.metrics([], [])["accuracy"])


def test_bootstrap_replicates_without_a_mover_are_left_out_not_0():
    """Scene a holds the one mover (found), scenes b and c still vehicles (called still): F1
    is 1 wherever it is defined; the replicates that drew no a are undefined, not 0, and the
    interval is over the defined ones."""
    y, p, g = [1, 0, 0], [0.9, 0.1, 0.1], ["a", "b", "c"]
    r = ev.scene_bootstrap(y, p, g, n=300, seed=0)
    undefined = np.isnan(r)
    assert 0.2 < undefined.mean() < 0.4  # (2/3)^3 = 0.30 of the draws miss scene a
    assert (r[~undefined] == 1.0).all()
    assert ev.interval(r) == (1.0, 1.0)
    assert ev.bootstrap_f1_ci(y, p, g, n=300) == (1.0, 1.0)
    assert all(np.isnan(ev.interval([np.nan, np.nan])))
    # B calls b's still vehicle moving: never better than A where defined
    d = ev.paired_comparison(y, p, [0.9, 0.9, 0.1], g, n=300, seed=0)
    assert d["undefined_replicates"] == int(undefined.sum())
    assert d["ci"][0] == 0.0 and d["ci"][1] > 0
    draws = np.random.default_rng(0).multinomial(3, [1 / 3] * 3, size=300)
    with_a = draws[:, 0] > 0
    want = np.mean(draws[with_a, 1] == 0)  # A = B exactly where b is not drawn
    assert d["p_not_better"] == pytest.approx(want)


def test_undefined_numbers_are_shown_as_a_dash():
    """Tables print "-" for an undefined F1, interval or seed range, never "nan" or 0."""
    nan = float("nan")
    t = ev.table3({"dis": {"f1": nan, "precision": 0.0, "recall": nan, "f1_min": nan,
                           "f1_max": nan, "seeds": 2, "ci": (nan, nan)}})
    assert t.loc[0, "seed range (%)"] == "-" and t.loc[0, "F1 95% CI, scenes and seeds (%)"] == "-"
    assert np.isnan(t.loc[0, "F1 (%)"]) and t.loc[0, "P (%)"] == 0.0
    c = ev.comparison_table({"a - b": {"delta_f1": 0.1, "ci": (nan, 0.2), "per_seed": [nan, 0.1],
                                       "p_not_better": nan, "n_scenes": 1, "n": 3}})
    assert c.loc[0, "95% CI, scenes and seeds (points)"] == "-"
    assert c.loc[0, "per seed (points)"] == "-, +10.0"
    assert ev.span(0.105, 0.2) == "10.5-20.0" and ev.points(0.5, "+.1f") == "+50.0"


def test_book_tables_show_undefined_as_a_dash():
    from flowmod.report import viz

    html = viz.table(pd.DataFrame({"group": ["a", "b"], "F1 (%)": [50.0, float("nan")],
                                   "note": ["x", None]})).to_html()
    assert "nan" not in html.lower() and "none" not in html.lower()
    assert html.count(">-</td>") == 2 and ">50.0</td>" in html


def test_false_alarm_rate_uses_the_strict_threshold_of_every_other_number():
    """Still objects called moving: prob > 0.5 as in metrics (0.5 itself is still); NaN
    without a still object."""
    assert ev.false_alarm_rate([0, 0, 0, 0, 1], [0.5, 0.51, 0.2, 0.9, 0.1]) == 0.5
    assert ev.false_alarm_rate([0, 0], [0.5, 0.3], threshold=0.4) == 0.5
    assert np.isnan(ev.false_alarm_rate([1, 1], [0.9, 0.1]))


# --- training seeds in the interval (issue 38) ------------------------------------------------


def _identical_scenes(n_scenes: int = 20):
    """Scenes that are copies of one another (so resampling them moves nothing) and three
    seeds that disagree: all of an interval's width is training noise."""
    y = np.tile([1, 1, 0, 0], n_scenes)
    g = np.repeat(np.arange(n_scenes), 4)
    seeds = np.array([np.tile(row, n_scenes) for row in
                      ([0.9, 0.9, 0.1, 0.1], [0.9, 0.1, 0.1, 0.1], [0.9, 0.9, 0.9, 0.1])])
    return y, seeds, g


def test_the_interval_counts_training_seeds_not_only_scenes():
    y, seeds, g = _identical_scenes()
    f1 = [ev.metrics(y, p)["f1"] for p in seeds]  # 1, 2/3, 0.8
    lo, hi = ev.bootstrap_f1_ci(y, seeds, g)
    assert lo < np.mean(f1) - 0.02 and hi > np.mean(f1) + 0.02  # seeds resampled
    assert lo >= min(f1) - 1e-9 and hi <= max(f1) + 1e-9
    one = ev.bootstrap_f1_ci(y, seeds[:1], g)  # one seed: nothing left to resample
    assert one == (pytest.approx(f1[0]), pytest.approx(f1[0]))
    s = ev.seed_summary(y, seeds, g)
    assert s["seed_sd"] == pytest.approx(np.std(f1, ddof=1)) and s["training_seeds"] == 3
    assert np.isnan(ev.seed_summary(y, seeds[:1], g)["seed_sd"])


def test_a_single_seed_keeps_the_scene_bootstrap():
    y, p, g = _scenes()
    w = ev.scene_draws(len(np.unique(g)), 2000, 0)
    tp, fp, fn = ev._counts(y, p[None], g, 0.5)
    want = ev._prf(w @ tp.T, w @ fp.T, w @ fn.T)[2][:, 0]
    assert np.allclose(ev.scene_bootstrap(y, p, g), want, equal_nan=True)


def test_seeds_are_drawn_within_each_fold_and_paired_across_methods():
    d = ev.seed_draws(3, 2, 500, seed=4)
    assert d.shape == (500, 2, 3) and set(np.unique(d)) == {0, 1, 2}
    assert (d[:, 0] != d[:, 1]).any()  # the folds' seeds are drawn apart
    assert (d == ev.seed_draws(3, 2, 500, seed=4)).all()
    assert (ev.seed_draws(1, 2, 5, seed=4) == 0).all()
    y, seeds, g = _identical_scenes()
    folds = (g >= 10).astype(int)
    # seeds that agree in fold 0 and disagree in fold 1: the width comes from fold 1 alone
    calm = seeds.copy()
    calm[:, folds == 0] = seeds[0, folds == 0]
    wide = ev.bootstrap_f1_ci(y, seeds, g, folds=folds)
    narrow = ev.bootstrap_f1_ci(y, calm, g, folds=folds)
    assert narrow[1] - narrow[0] < wide[1] - wide[0]
    # a method against itself: the same scenes and seeds drawn, every replicate 0
    c = ev.paired_comparison(y, seeds, seeds, g, folds=folds)
    assert c["ci"] == (0.0, 0.0) and c["training_seeds"] == [3, 3]
    # against a constant (no training noise) the interval is the seeds' spread
    c = ev.paired_comparison(y, seeds, np.full(len(y), 0.9), g)
    assert c["ci"][0] < c["delta_f1"] < c["ci"][1]


def test_chance_reference_and_balanced_accuracy():
    y = np.array([1, 0, 0, 0])
    assert ev.always_moving_f1(y) == pytest.approx(2 / 5)  # 2P / (2P + N), P 1, N 3
    assert np.isnan(ev.always_moving_f1([0, 0]))
    assert ev.balanced_accuracy(y, np.ones(4)) == 0.5  # a constant answer
    assert ev.balanced_accuracy(y, [0.9, 0.9, 0.1, 0.1]) == pytest.approx((1 + 2 / 3) / 2)
    assert np.isnan(ev.balanced_accuracy([1, 1], [0.9, 0.1]))
    s = ev.seed_summary(y, [[0.9, 0.9, 0.1, 0.1], [0.9, 0.1, 0.1, 0.1]], [0, 0, 1, 1])
    assert s["always_moving_f1"] == pytest.approx(0.4)
    assert s["balanced_accuracy"] == pytest.approx(((1 + 2 / 3) / 2 + 1) / 2)
    t = ev.table3({"x": s})
    assert t.loc[0, "always moving F1 (%)"] == "40.0" and t.loc[0, "training seeds"] == 2
    assert t.loc[0, "balanced accuracy (%)"] == "91.7" and ev.CI_COLUMN in t


def test_an_interval_over_few_scenes_is_flagged():
    """A bootstrap over fewer than 10 scenes is shown flagged (issue 39: "> 70 m" had an
    interval 0.0-91.6 from 3 scenes); from 10 scenes on it is shown as it is."""
    assert ev.ci_text((0.0, 0.916), 3) == "0.0-91.6 (3 scenes: too few)"
    assert ev.ci_text((0.0, 0.916), ev.MIN_SCENES) == "0.0-91.6"
    assert ev.ci_text((0.1, 0.2), 9, sep=" to ") == "10.0 to 20.0 (9 scenes: too few)"
    assert ev.ci_text((float("nan"), 0.2), 3) == "-"  # undefined stays undefined, unflagged
    assert ev.ci_text(None, 3) == "" and ev.ci_text((0.1, 0.2), "") == "10.0-20.0"
    # an interval in its own unit (an end-point error in px, chapter 03), flagged the same way
    assert ev.ci_text((0.812, 1.333), 12, fmt=".2f") == "0.81-1.33"
    assert ev.ci_text((0.812, 1.333), 4, fmt=".2f") == "0.81-1.33 (4 scenes: too few)"
    assert ev.ci_text((float("nan"), 1.0), 12, fmt=".2f") == "-"


def test_chapter03_epe_interval_resamples_scenes():
    """The interval of a mean box EPE over pairs resamples whole scenes: two scenes whose
    pairs agree give a point interval; the flag counts scenes, not pairs."""
    from flowmod.chapters import common

    assert common.epe_ci([1.0, 1.0, 3.0, 3.0], ["a", "a", "b", "b"], 0).startswith("1.00-3.00")
    assert common.epe_ci([2.0] * 12, [f"s{i}" for i in range(12)], 0) == "2.00-2.00"
    assert common.epe_ci([2.0] * 12, ["s"] * 12, 0) == "2.00-2.00 (1 scenes: too few)"
    assert common.epe_ci([], [], 0) == "-"


def test_group_mean_bootstrap_resamples_whole_groups_of_the_defined_values():
    """Each replicate: the mean of the items of the drawn groups (a group drawn twice counts
    twice), NaN values left out; n replicates (2000 by default, seed 0); all NaN: n NaNs."""
    from flowmod import metrics as ev

    v = np.array([[1.0], [3.0], [np.nan], [10.0], [20.0]])  # any shape: read flat
    g = np.array(["a", "a", "a", "b", "c"])
    w = ev.scene_draws(3, 50, 4)  # groups a, b, c in sorted order
    want = (w @ np.array([4.0, 10.0, 20.0])) / (w @ np.array([2.0, 1.0, 1.0]))
    np.testing.assert_allclose(ev.group_mean_bootstrap(v, g[:, None], n=50, seed=4), want)
    default = ev.group_mean_bootstrap(v, g)
    w0 = ev.scene_draws(3, 2000, 0)
    np.testing.assert_allclose(default, (w0 @ [4.0, 10.0, 20.0]) / (w0 @ [2.0, 1.0, 1.0]))
    none = ev.group_mean_bootstrap([np.nan, np.nan], ["a", "b"], n=7)
    assert none.shape == (7,) and none.dtype == np.float64 and np.isnan(none).all()
    with pytest.raises(ValueError, match=r"^groups has 2 values but values has 3$"):
        ev.group_mean_bootstrap([1.0, 2.0, 3.0], ["a", "b"])


def test_breakdown_intervals_resample_within_folds_and_errors_name_the_problem():
    from flowmod import metrics as ev

    rng = np.random.default_rng(5)
    n = 120
    df = pd.DataFrame({"category": np.where(np.arange(n) % 2, "car", "bus"),
                       "distance": rng.uniform(30, 70, n)})
    y = rng.integers(0, 2, n)
    p = np.clip(y * 0.6 + rng.normal(0.2, 0.3, (2, n)), 0, 1)
    scenes = np.arange(n) // 6
    folds = scenes % 3
    got = ev.breakdown(df, y, p, groups=scenes, folds=folds, n_boot=200)
    for row in got.itertuples():
        i = np.flatnonzero(df["category"].to_numpy() == row.category)
        lo, hi = ev.bootstrap_f1_ci(y[i], p[:, i], scenes[i], 200, 0, 0.5, folds=folds[i])
        assert (row.ci_lo, row.ci_hi) == (lo, hi)
    unfolded = ev.breakdown(df, y, p, groups=scenes, n_boot=200)
    assert not np.allclose(got[["ci_lo", "ci_hi"]], unfolded[["ci_lo", "ci_hi"]])
    with pytest.raises(ValueError, match=r"^df has 120 rows but y_true has 3 values$"):
        ev.breakdown(df, y[:3], p[:, :3])
    with pytest.raises(KeyError, match=r"breakdown by 'speed': no such column \(have "
                                       r"\['category', 'distance'\]\)"):
        ev.breakdown(df, y, p, by="speed")


def test_table3_shows_both_seed_spreads_in_points():
    from flowmod import metrics as ev

    row = {"method": "dis", "f1": 0.8, "precision": 0.7, "recall": 0.9, "seed_sd": 0.0123,
           "retrain_sd": 0.0345}
    t = ev.table3([row])
    assert t[ev.POOLED_SD_COLUMN].tolist() == ["1.2"]
    assert t[ev.RETRAIN_SD_COLUMN].tolist() == ["3.5"]
    bare = ev.table3([{k: v for k, v in row.items() if k not in ("seed_sd", "retrain_sd")}])
    assert bare[ev.POOLED_SD_COLUMN].tolist() == ["-"]
    assert bare[ev.RETRAIN_SD_COLUMN].tolist() == ["-"]


def test_one_retraining_s_sd_is_the_within_fold_seed_sd_pooled_over_folds():
    """Fold 0's two seeds score F1 1 and 2/3, fold 1's 1 and 0: the retraining SD pools the
    two folds' variances; the pooled-F1 SD (over seeds of all objects) is another number;
    without folds both are the seeds' SD on all objects."""
    from flowmod import metrics as ev

    y = np.array([1, 1, 0, 0, 1, 0])
    folds = np.array([0, 0, 0, 0, 1, 1])
    probs = np.array([[0.9, 0.9, 0.1, 0.1, 0.9, 0.1],
                      [0.9, 0.1, 0.1, 0.1, 0.1, 0.1]])
    f0 = [ev.metrics(y[:4], p[:4])["f1"] for p in probs]
    f1 = [ev.metrics(y[4:], p[4:])["f1"] for p in probs]
    assert f0 == [1.0, pytest.approx(2 / 3)] and f1 == [1.0, 0.0]
    want = np.sqrt((np.var(f0, ddof=1) + np.var(f1, ddof=1)) / 2)
    assert ev.retrain_sd(y, probs, folds) == pytest.approx(want)
    s = ev.seed_summary(y, probs, np.arange(6), folds=folds, n=10)
    assert s["retrain_sd"] == pytest.approx(want)
    pooled = [ev.metrics(y, p)["f1"] for p in probs]
    assert s["seed_sd"] == pytest.approx(np.std(pooled, ddof=1)) and s["seed_sd"] < want
    assert ev.retrain_sd(y, probs, None) == pytest.approx(np.std(pooled, ddof=1))
    assert np.isnan(ev.retrain_sd(y, probs[:1], folds))  # one seed: nothing to spread
    # a fold without movers (F1 undefined) is left out of the pool
    y2 = np.array([1, 1, 0, 0, 0, 0])
    only0 = ev.retrain_sd(y2, probs, folds)
    assert only0 == pytest.approx(np.std([ev.metrics(y2[:4], p[:4])["f1"] for p in probs],
                                         ddof=1))


def test_metric_errors_name_what_disagrees():
    y = np.array([1, 0, 1, 0])
    with pytest.raises(ValueError, match=r"^y_true has 4 values but y_prob has shape \(1, 3\)$"):
        ev.seed_summary(y, [0.1, 0.2, 0.3], ["a"] * 4)
    with pytest.raises(ValueError, match=r"^groups has 3 values but y_true has 4$"):
        ev.scene_bootstrap(y, [0.9, 0.1, 0.8, 0.2], ["a", "b", "c"])
    with pytest.raises(ValueError, match=r"^folds has 3 values but groups has 4$"):
        ev.scene_bootstrap(y, [0.9, 0.1, 0.8, 0.2], list("abcd"), folds=[0, 1, 1])
    with pytest.raises(ValueError, match=r"^scores contain NaN/inf$"):
        ev.fit_threshold([1.0, np.nan, 2.0, 3.0], y)


def test_scores_read_column_shaped_inputs_flat_and_pass_the_threshold_on():
    """Probabilities, replicates and folds of shape (N, 1) read as (N,); a threshold other
    than 0.5 reaches every score; balanced accuracy is the mean of the two recalls."""
    rng = np.random.default_rng(2)
    y = np.array([1, 0, 1, 1, 0, 0, 1, 0] * 3)
    p = np.clip(y * 0.3 + rng.uniform(0, 0.7, (2, len(y))), 0, 1)
    scenes = np.arange(len(y)) // 4
    folds = scenes % 2
    assert ev.metrics(y, p[0][:, None]) == ev.metrics(y, p[0])
    r = rng.normal(0, 1, 50)
    assert ev.interval(r[:, None]) == ev.interval(r)
    assert ev.detectable(r[:, None]) == pytest.approx(ev.detectable(r))
    assert ev.scene_bootstrap(y, p, scenes, n=30, folds=folds[:, None]).tolist() == \
        ev.scene_bootstrap(y, p, scenes, n=30, folds=folds).tolist()
    m = ev.metrics(y, p[0], 0.3)
    assert ev.balanced_accuracy(y, p[0], 0.3) == pytest.approx(
        (m["tp"] / m["n_moving"] + m["tn"] / m["n_still"]) / 2)
    assert ev.balanced_accuracy(y, p[0], 0.3) != ev.balanced_accuracy(y, p[0])
    s = ev.seed_summary(y, p, scenes, n=50, threshold=0.3, folds=folds)
    per = [np.mean([ev.metrics(y[folds == k], q[folds == k], 0.3)["f1"] for q in p])
           for k in (0, 1)]
    assert [x["f1"] for x in s["per_seed"]] == pytest.approx(per)
    assert s["balanced_accuracy"] == pytest.approx(np.mean([ev.balanced_accuracy(y, q, 0.3)
                                                           for q in p]))
    assert s["ci"] == ev.bootstrap_f1_ci(y, p, scenes, 50, 0, 0.3, 0.95, folds)
    assert s["ci"] != ev.bootstrap_f1_ci(y, p, scenes, 50, 0, 0.3, 0.95)


def test_a_difference_is_detectable_from_two_replicates_on_and_a_paired_result_says_its_unit():
    assert np.isnan(ev.detectable([0.1])) and np.isfinite(ev.detectable([0.1, 0.3]))
    r = np.random.default_rng(0).normal(0, 0.02, 400)
    assert ev.detectable(r) == pytest.approx(ev.detectable(r, level=0.95, power=0.8))
    assert ev.detectable(r, level=0.9) < ev.detectable(r)
    y = np.array([1, 0] * 20)
    a, b = np.where(y == 1, 0.9, 0.1), np.where(y == 1, 0.6, 0.4)
    b[::3] = 1 - b[::3]  # B errs on a third of the objects
    scenes = np.arange(40) // 4
    d = ev.paired_comparison(y, a, b, scenes, n=200, level=0.9)
    assert d["detectable"] > 0
    assert d["unit"] == "seed"
    reps = ev.scene_bootstrap(y, a, scenes, 200) - ev.scene_bootstrap(y, b, scenes, 200)
    assert d["detectable"] == pytest.approx(ev.detectable(reps, 0.9))
    none = ev.paired_comparison(np.zeros(40, int), a, b, scenes, n=20)  # no mover: undefined
    assert np.isnan(none["p_not_better"])


def test_seed_draws_are_fixed_by_the_seed():
    """The training-seed draws of the bootstrap are a fixed function of its seed (the
    book's intervals are reproducible)."""
    assert ev.seed_draws(3, 2, 2, 0).tolist() == [[[1, 2, 2], [1, 0, 2]], [[0, 2, 2], [0, 0, 0]]]
    assert ev.seed_draws(1, 2, 3, 0).shape == (3, 2, 1)


def test_the_comparison_table_keeps_each_interval_as_numbers():
    rows = {"A - B": {"delta_f1": 0.05, "ci": (0.01, 0.09), "n_scenes": 12, "per_seed": [0.04],
                      "p_not_better": 0.01, "n": 100, "detectable": 0.0312, "unit": "seed"},
            "C - D": {"delta_f1": 0.0, "ci": None, "n_scenes": 12, "per_seed": [0.0],
                      "p_not_better": 0.5, "n": 100, "unit": "seed"}}
    rows["C - D"]["ci"] = (float("nan"), float("nan"))
    t = ev.comparison_table(rows)
    assert t.attrs["ci_points"][0] == pytest.approx((1.0, 9.0))
    assert t["detectable (points)"].tolist()[0] == 3.1
    assert np.isnan(t["detectable (points)"].tolist()[1])


def test_label_and_probability_errors_in_full():
    with pytest.raises(ValueError, match=r"^y_true must hold 0 \(still\) / 1 \(moving\) only$"):
        ev.labels01([0, 2])
    with pytest.raises(ValueError, match=r"^y_true has 4 values but y_prob has 3$"):
        ev.metrics([0, 1, 0, 1], [0.1, 0.2, 0.3])
