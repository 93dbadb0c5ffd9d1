"""The book's tables cell by cell, and the label equations on exact inputs.

The tables are what a reader sees: a renamed column, a lost rounding or a swapped field is a
wrong book even when every number upstream is right. Each test builds one table from inputs
whose fields all differ and compares the whole frame."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from flowmod import labels
from flowmod import metrics as ev


def test_table3_every_cell():
    rows = [
        {"method": "dis", "f1": 0.81234, "f1_min": 0.7512, "f1_max": 0.8466, "seeds": 3,
         "precision": 0.9049, "recall": 0.7351, "ci": (0.6049, 0.9151), "n_scenes": 6,
         "n": 409, "n_instances": 47},
        {"method": "one seed", "f1": 0.5, "f1_min": 0.5, "f1_max": 0.5, "seeds": 1,
         "precision": 0.25, "recall": 1.0},
        {"method": "bare", "f1": 0.125, "precision": 0.0666, "recall": 0.95},
    ]
    want = pd.DataFrame({
        "Method": ["dis", "one seed", "bare"],
        "F1 (%)": [81.2, 50.0, 12.5],
        "seed SD of the pooled F1 (points)": ["-", "-", "-"],
        "one retraining's SD (points)": ["-", "-", "-"],
        "seed range (%)": ["75.1-84.7", "", ""],
        "seeds": [3, 1, ""],
        "training seeds": ["", "", ""],
        "P (%)": [90.5, 25.0, 6.7],
        "R (%)": [73.5, 100.0, 95.0],
        "balanced accuracy (%)": ["-", "-", "-"],
        "always moving F1 (%)": ["-", "-", "-"],
        "F1 95% CI, scenes and seeds (%)": ["60.5-91.5 (6 scenes: too few)", "", ""],
        "scenes": [6, "", ""],
        "objects": [409, "", ""],
        "vehicles": [47, "", ""],
    })
    pd.testing.assert_frame_equal(ev.table3(rows), want)
    by_name = ev.table3({r["method"]: {k: v for k, v in r.items() if k != "method"}
                         for r in rows})
    pd.testing.assert_frame_equal(by_name, want)
    assert list(ev.table3([]).columns) == ["Method"]


def test_comparison_table_every_cell():
    rows = {"gt - dis": {"delta_f1": 0.0312, "ci": (-0.0149, 0.0851),
                         "per_seed": [0.02, -0.011, 0.05], "p_not_better": 0.1234,
                         "n_scenes": 5, "n": 409}}
    want = pd.DataFrame({
        "comparison": ["gt - dis"], "ΔF1 (points)": [3.1],
        "95% CI, scenes and seeds (points)": ["-1.5 to 8.5 (5 scenes: too few)"],
        "verdict": ["undecided"], "detectable (points)": [float("nan")],
        "per seed (points)": ["+2.0, -1.1, +5.0"],
        "replicates with A <= B (%)": [12.3], "scenes": [5], "objects": [409],
    })
    got = ev.comparison_table(rows)
    pd.testing.assert_frame_equal(got, want)
    assert got.attrs["ci_points"] == [pytest.approx((-1.49, 8.51))]  # the interval as numbers


def test_protocol_comparison_every_cell():
    # 6 objects: moving, still, still, moving, still, still; batch 2.
    y = np.array([1, 0, 0, 1, 0, 0])
    p = np.array([0.9, 0.6, 0.2, 0.4, 0.1, 0.7])
    t = ev.protocol_comparison(y, p, batch_size=2)
    assert list(t.columns) == ["protocol", "n", "precision", "recall", "f1"]
    assert t["protocol"].tolist() == [
        "clean: whole set", "per-batch F1, all objects", "stills thinned 1 of 2, whole set",
        "paper protocol: thinned + per-batch"]
    # thinned: every moving object and the 1st, 3rd still: y, p at [0, 1, 3, 4].
    assert t["n"].tolist() == [6, 6, 4, 4]
    # clean: tp 1 fp 2 fn 1 -> P 1/3, R 1/2, F1 0.4.
    np.testing.assert_allclose(t.loc[0, ["precision", "recall", "f1"]].astype(float),
                               [1 / 3, 0.5, 0.4])
    # per batch [1,0|0,1|0,0] with yhat [1,1|0,0|0,1]: P (0.5, 0, 0), R (1, 0, 0).
    np.testing.assert_allclose(t.loc[1, ["precision", "recall", "f1"]].astype(float),
                               [0.5 / 3, 1 / 3, (2 / 3) / 3])
    # thinned whole set: y [1,0,1,0], yhat [1,1,0,0]: tp 1 fp 1 fn 1.
    np.testing.assert_allclose(t.loc[2, ["precision", "recall", "f1"]].astype(float),
                               [0.5, 0.5, 0.5])
    # thinned per batch [1,0|1,0] yhat [1,1|0,0]: P (0.5, 0), R (1, 0), F1 (2/3, 0).
    np.testing.assert_allclose(t.loc[3, ["precision", "recall", "f1"]].astype(float),
                               [0.25, 0.5, 1 / 3])


def test_thin_still_keeps_movers_and_the_first_of_every_group():
    y = np.array([0, 0, 1, 0, 0, 0, 1, 0])
    np.testing.assert_array_equal(ev.thin_still(y), [1, 0, 1, 1, 0, 1, 1, 0])
    np.testing.assert_array_equal(ev.thin_still(y, keep=3, every=5), [1, 1, 1, 1, 0, 0, 1, 1])
    with pytest.raises(ValueError, match="need 0 < keep <= every"):
        ev.thin_still(y, keep=0)
    with pytest.raises(ValueError, match="keep=3, every=2"):
        ev.thin_still(y, keep=3, every=2)


def test_velocity_speed_label_on_exact_values():
    p1 = np.array([[0.0, 0.0, 0.0], [10.0, 5.0, 1.0]])
    p2 = np.array([[1.0, 0.0, 0.0], [10.0, 5.0, 2.0]])
    v = labels.velocity(p1, p2, np.array([0, 1_000_000]), np.array([500_000, 1_250_000]))
    np.testing.assert_allclose(v, [[2.0, 0.0, 0.0], [0.0, 0.0, 4.0]])
    np.testing.assert_allclose(labels.velocity(p1[1], p2[1], 0, 2_000_000), [0, 0, 0.5])
    np.testing.assert_allclose(labels.speed(np.array([[3, 4, 12], [0, 0, 0]])), [13.0, 0.0])
    out = labels.motion_label(np.array([1.99, 2.0, np.nan, 7.0]))
    assert out.dtype == np.int8 and out.tolist() == [0, 1, -1, 1]
    assert labels.motion_label(np.array([2.5]), threshold=3.0).tolist() == [0]
    with pytest.raises(ValueError, match=r"timestamps must increase from frame 1 to frame 2"):
        labels.velocity(p1, p2, 5, 5)


def test_chapter07_answer_says_decided_only_when_the_interval_excludes_0():
    from flowmod.chapters import ch07_evaluation as ch07
    from flowmod.chapters.common import comparison_table

    table = comparison_table({
        "gt - dis": {"delta_f1": 0.03, "ci": (0.01, 0.05), "detectable": 0.02,
                     "per_seed": [0.03], "p_not_better": 0.0, "n_scenes": 29, "n": 90},
        "dis - farneback": {"delta_f1": -0.01, "ci": (-0.03, 0.01), "detectable": 0.03,
                            "per_seed": [-0.01], "p_not_better": 0.8, "n_scenes": 29, "n": 90},
        "gt: classifier - oracle rule": {
            "delta_f1": -0.04, "ci": (-0.06, -0.02), "detectable": 0.02, "per_seed": [-0.04],
            "p_not_better": 1.0, "n_scenes": 29, "n": 90}})
    words = ch07.answer(table).split("; gt: classifier")
    assert words[0].startswith("gt - dis: +3.0 F1 points (95 % interval over scenes and "
                               "training seeds 1.0 to 5.0), decided: the first is better")
    assert "dis - farneback: -1.0 F1 points" in words[0] and "; inconclusive: " in words[0]
    assert words[0].count(", decided: ") == 1
    assert words[1].endswith("decided: the second is better.")


def test_chapter06_shows_the_validation_choice_of_the_input():
    """The committed record's choice is the rule applied to its rows, the table's last row
    is the mean the rule compares, and a profile trained otherwise is named as such."""
    from flowmod.chapters import ch06_training as ch06
    from flowmod.params import load_profile

    rec = ch06.ablation_record()
    t = ch06.ablation_table(rec)
    last = t.iloc[-1].drop(["method", "fold"]).astype(float)
    assert last.idxmax() == rec["choice"] == load_profile("demo").input_scaling
    rows = pd.DataFrame(rec["rows"])
    assert last["raw"] == round(100 * rows.loc[rows["mode"] == "raw", "val_f1"].mean(), 1)
    assert "no test row read" in ch06.ablation_words(rec, load_profile("demo"))
    other = ch06.ablation_words(rec, load_profile("paper", dataroot="/x"))
    assert "trains with **raw** instead" in other


def test_the_landing_page_quotes_decided_comparisons_as_decided():
    from flowmod.chapters import ch07_evaluation as ch07
    from flowmod.chapters.common import comparison_table
    from flowmod.params import load_profile

    row = {"detectable": 0.02, "per_seed": [0.0], "p_not_better": 0.0, "n_scenes": 29, "n": 90}
    table = comparison_table({
        "gt - dis": {**row, "delta_f1": 0.022, "ci": (0.002, 0.044)},
        "dis: classifier - oracle rule": {**row, "delta_f1": 0.021, "ci": (-0.009, 0.05)}})
    w = ch07.landing_words(table, load_profile("demo"))
    assert w["exact_vs_headline"].endswith("0.2 to 4.4), decided")
    assert w["headline_vs_oracle"].endswith("or more)")
    assert "inconclusive" in w["headline_vs_oracle"]
    assert ch07.landing_words(table.iloc[:1], load_profile("demo"))["headline_vs_oracle"] == (
        "not in this profile")


def test_the_answers_page_gathers_each_chapters_rows_and_draws_them_all(monkeypatch, tmp_path):
    """Chapter 14 (the landing page's table and forest plot): every row of chapters 07, 10
    and 11's comparison tables once, with its interval as numbers; one answer per question,
    counting only the decided rows as decided; a chapter not built contributes nothing."""
    from flowmod.chapters import ch14_answers as ch13
    from flowmod.params import load_profile
    from flowmod.report import viz

    row = {"detectable": 0.02, "per_seed": [0.0], "p_not_better": 0.0, "p_two_sided": 0.0,
           "n_scenes": 29, "n": 90}
    t07 = ev.comparison_table({
        "gt - dis": {**row, "delta_f1": 0.022, "ci": (0.002, 0.044)},
        "dis: classifier - oracle rule": {**row, "delta_f1": 0.021, "ci": (-0.009, 0.05)}})
    t11 = ev.comparison_table({
        "dis: all distances - 30-70 m": {**row, "delta_f1": -0.05, "ci": (-0.08, -0.01)}})
    monkeypatch.setattr(ch13.ch07, "comparisons", lambda p: t07)
    monkeypatch.setattr(ch13.ch10, "built", lambda p: [])
    monkeypatch.setattr(ch13.ch11, "built", lambda p: ["dis"])
    monkeypatch.setattr(ch13.ch11, "comparisons", lambda p, done, split: t11)
    eff = ch13.effects(load_profile("demo"))
    assert eff["comparison"].tolist() == ["gt - dis", "dis: classifier - oracle rule",
                                          "dis: all distances - 30-70 m"]
    assert eff["chapter"].tolist() == ["07", "07", "11"]
    assert eff[["low", "high"]].to_numpy().round(1).tolist() == [[0.2, 4.4], [-0.9, 5.0],
                                                                   [-8.0, -1.0]]
    # each table's two-sided p-value (0 here): every effect decided after Holm too
    assert eff["p (two-sided)"].tolist() == [0.0, 0.0, 0.0]
    assert eff["Holm, all effects"].tolist() == ["decided"] * 3
    table = ch13.answers(eff)  # one row per effect
    assert table["chapter"].tolist() == ["07", "07", "11"]
    assert table["ΔF1, 95 % interval (points)"].tolist() == [
        "+2.2 (0.2 to 4.4)", "+2.1 (-0.9 to 5.0)", "-5.0 (-8.0 to -1.0)"]
    assert table["verdict"].tolist() == ["decided", "inconclusive", "decided"]
    assert (table.map(len) <= 300).all().all()
    words = ch13.question_words(eff)
    assert words["answer_07"].endswith(
        "1 of 2 comparisons decided: gt over dis by 2.2 points (0.2 to 4.4). Equivalent: 0; "
        "inconclusive: 1.")
    assert "30-70 m over dis: all distances by 5.0 points" in words["answer_11"]
    assert words["answer_10"].endswith("Not built in this run.")
    fig = viz.forest(eff)
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.get_yticklabels()] == [
        "07: gt - dis", "07: dis: classifier - oracle rule", "11: dis: all distances - 30-70 m"]
    filled = [ln.get_markerfacecolor() for ln in ax.get_lines() if ln.get_marker() == "o"]
    assert [f == "white" for f in filled] == [False, True, False]  # hollow: undecided
    assert viz.figure_problems(fig) == []
    viz.plt.close(fig)


def test_a_figure_that_shows_nothing_is_refused(tmp_path):
    """viz.show refuses a figure with an axes but no data on it (no artist, all-NaN data,
    only a reference line, bars of height 0) or a legend entry counting n=0, naming the
    file: chapter 02's histogram of three empty splits was published with a confident
    caption (issue 39)."""
    import matplotlib.pyplot as plt

    from flowmod.report import viz

    def hist(values: dict) -> plt.Figure:
        return viz.histogram(values, bins=np.arange(30, 72.5, 2.5), xlabel="m", vline=50.0)

    empty = hist({"train": [], "val": [], "test": []})
    assert "counts nothing" in "; ".join(viz.figure_problems(empty))
    with pytest.raises(viz.EmptyFigure, match=r"dist.png: .*'train \(n=0\)' counts nothing"):
        viz.show(empty, tmp_path / "dist.png")
    assert not (tmp_path / "dist.png").exists()
    fig, ax = plt.subplots()
    ax.plot([1, 2], [np.nan, np.nan])
    ax.axvline(1.5)
    assert viz.figure_problems(fig) == ["'axes 0' has no data", "no axes has data"]
    fig, ax = plt.subplots()
    ax.bar([1, 2], [0, 0])
    ax.set_title("F1")
    assert viz.figure_problems(fig)[0] == "'F1' has no data"
    good = hist({"f0": [31.0, 45.0], "f1": [60.0]})
    assert viz.figure_problems(good) == []
    grid = viz.frames_grid([np.zeros((4, 6, 3), np.uint8)] * 3, ["a", "b", "c"], ncols=2)
    assert viz.figure_problems(grid) == []  # the fourth cell is switched off
    plt.close("all")


def test_the_committed_ablation_steps_record_is_its_rows():
    """Chapter 06 shows benchmarks/ablation_steps.json: its effects are the paired
    differences of its own rows (recomputed here), every row is a validation score, and the
    chapter's table and words say what the record says."""
    import sys

    from flowmod.chapters import ch06_training as ch06
    from flowmod.paths import repo_root

    rec = ch06.steps_record()
    if rec is None:
        pytest.skip("no ablation_steps.json committed")
    sys.path.insert(0, str(repo_root() / "benchmarks"))
    import bench_ablation

    rows = pd.DataFrame(rec["rows"]).assign(seconds=0.0)
    again = bench_ablation.step_effects(rows)
    stored = pd.DataFrame(rec["effects"])
    for col in ("effect (points)", "low", "high", "recipe (%)", "variant (%)"):
        np.testing.assert_allclose(again[col], stored[col], atol=0.011)
    assert rows["val_f1"].between(0, 1).all() and set(rows["step"]) >= {"recipe"}
    table = ch06.steps_table(rec)
    assert list(table["step"]) == list(stored["step"])
    words = ch06.steps_words(rec)
    for r in stored[stored["scored against"] == "annotated"].to_dict("records"):
        assert f"{r['step']} ({r['variant']}): {r['effect (points)']:+.1f} points" in words


def test_a_failure_reason_that_holds_for_every_object_is_said_to_be_untestable():
    """Chapter 08: the crop holding other objects held for 100 % of the demo's objects and
    100 % of its wrong predictions; the words say this world cannot test it (issue 50), a
    reason no commoner among the errors explains nothing, a reason commoner among them
    gets its ratio, and no wrong prediction leaves the share undefined."""
    from flowmod.chapters import ch08_generalisation as ch08

    tagged = pd.DataFrame({"wrong": [True, True, False, False, False],
                           "unclear_flow": [True, True, True, False, False],
                           "crowded": [True, True, True, True, True]})
    shares = ch08.failure_shares(tagged)
    words = ch08.failure_words(shares)
    assert "*other objects in the crop* holds for 100.0 % of all objects, so this world " \
           "cannot test it" in words
    almost = ch08.failure_shares(tagged.assign(crowded=[True, False, True, True, True]))
    assert "*other objects in the crop* holds for 50.0 % of the wrong predictions and " \
           "80.0 % of all objects: no commoner among the errors" in ch08.failure_words(almost)
    assert "*remote or slow* holds for 100.0 % of the wrong predictions against 60.0 % of " \
           "all objects (1.7 times as common)" in words
    none = ch08.failure_shares(tagged.assign(wrong=False))
    assert none["wrong predictions (%)"].isna().all()
    assert ch08.failure_words(none).count("undefined") == 2


def test_near_threshold_picks_the_nearest_within_half_a_metre_per_second():
    """Chapter 04's examples: by default at most 6 objects within 0.5 m/s of the threshold,
    nearest first, a sample seeded by 0 when more than 24 qualify."""
    speeds = np.r_[np.linspace(1.55, 2.45, 41), [1.45, 2.6, 9.0]]
    df = pd.DataFrame({"speed": speeds, "token": [f"t{i}" for i in range(len(speeds))]})
    near = labels.near_threshold(df, 2.0)
    assert len(near) == 6 and (near["gap"] < 0.5).all()
    assert near["gap"].is_monotonic_increasing
    pd.testing.assert_frame_equal(near, labels.near_threshold(df, 2.0, width=0.5, n=6, seed=0))
    assert not near.equals(labels.near_threshold(df, 2.0, seed=1))
    few = labels.near_threshold(df.iloc[-3:], 2.0)
    assert few.empty, "1.45, 2.6 and 9.0 m/s are all 0.5 m/s or more away"
    assert labels.near_threshold(pd.DataFrame({"speed": [2.5, 1.5]}), 2.0).empty, "0.5 away"
    inside = df[(df["speed"] - 2.0).abs() < 0.5]
    drawn = inside.sample(24, random_state=0)  # 4 n of the 41 candidates, then the nearest
    assert near.index.tolist() == (drawn["speed"] - 2.0).abs().nsmallest(6).index.tolist()


def test_near_threshold_draws_four_per_example_before_taking_the_nearest():
    """With more candidates than 4 n, the examples are the nearest of a seeded draw of 4 n
    (n 2, seed 1: speeds 19 and 23 of the lattice, where a draw of 5 n gives 19 and 22)."""
    speeds = np.r_[np.linspace(1.55, 2.45, 41), [1.45, 2.6, 9.0]]
    df = pd.DataFrame({"speed": speeds})
    assert labels.near_threshold(df, 2.0, n=2, seed=1).index.tolist() == [19, 23]


def test_three_verdicts_in_the_chapters_tables_words_and_forest():
    """Issue 52 item 5: a paired effect is decided (its interval excludes 0), equivalent
    (inside +/- the smallest effect that matters, 2 points) or inconclusive; the chapters'
    tables, their words, the landing page's count and the forest plot say which."""
    from flowmod.chapters import ch07_evaluation as ch07
    from flowmod.chapters import ch14_answers as ch13
    from flowmod.chapters.common import SMALLEST_EFFECT, comparison_table
    from flowmod.report import viz

    assert SMALLEST_EFFECT == 2.0
    row = {"detectable": 0.02, "per_seed": [0.0], "p_not_better": 0.0, "n_scenes": 29, "n": 90}
    table = comparison_table({
        "a - b": {**row, "delta_f1": 0.03, "ci": (0.01, 0.05)},
        "c - d": {**row, "delta_f1": 0.002, "ci": (-0.019, 0.019)},
        "e - f": {**row, "delta_f1": 0.002, "ci": (-0.021, 0.019)},
        "g - h": {**row, "delta_f1": -0.03, "ci": (-0.05, -0.001)}})
    assert table["verdict"].tolist() == ["A better", "equivalent", "inconclusive", "B better"]
    assert ("c - d: +0.2 F1 points (95 % interval over scenes and training seeds -1.9 to 1.9; "
            "equivalent: within +/-2 points); e - f") in ch07.answer(table)
    assert "inconclusive: these scenes would detect 2.0 points or more" in ch07.answer(table)
    assert ch07.answer(table).count(", decided: ") == 2
    eff = pd.DataFrame({"chapter": "07", "question": "q", "comparison": table["comparison"],
                        "ΔF1 (points)": table["ΔF1 (points)"], "verdict": table["verdict"],
                        "low": [p[0] for p in table.attrs["ci_points"]],
                        "high": [p[1] for p in table.attrs["ci_points"]],
                        "95% CI, scenes and seeds (points)": table[
                            "95% CI, scenes and seeds (points)"],
                        "Holm, all effects": ["decided", "not decided", "not decided",
                                              "not decided"]})
    ans = ch13.answers(eff)
    assert ans["Holm"].tolist() == ["decided", "not decided", "not decided", "not decided"]
    assert ans["verdict"].tolist() == ["decided", "equivalent", "inconclusive", "decided"]
    assert "2 of 4 comparisons decided" in ch13.question_words(eff)["answer_07"]
    assert ch13.question_words(eff)["answer_07"].endswith(
        "decided: a over b by 3.0 points (1.0 to 5.0); h over g by 3.0 points (0.1 to 5.0). "
        "Equivalent: 1; inconclusive: 1.")
    ax = viz.forest(eff, SMALLEST_EFFECT).axes[0]
    marks = [(ln.get_marker(), ln.get_markerfacecolor() == "white") for ln in ax.get_lines()
             if ln.get_marker() in ("o", "s")]
    assert marks == [("o", False), ("s", True), ("o", True), ("o", False)]


def test_an_interval_without_an_arms_training_noise_is_labelled_scenes_only():
    """Issue 50 item 2: a comparison whose trained arm has one model a fold carries no
    training noise in its interval: its table row, chapter 14's line and the forest plot
    (a dashed bar) say "scenes only"; the oracle rule trains nothing, so its one model
    does not count."""
    from flowmod.chapters import ch14_answers as ch13
    from flowmod.chapters.common import comparison_table
    from flowmod.report import viz

    row = {"detectable": 0.02, "per_seed": [0.0], "p_not_better": 0.0, "n_scenes": 29, "n": 90,
           "delta_f1": 0.03, "ci": (0.01, 0.05)}
    table = comparison_table({
        "gt - dis": {**row, "training_seeds": [3, 3]},
        "dis: log input - raw input": {**row, "training_seeds": [3, 1]},
        "dis: classifier - oracle rule": {**row, "training_seeds": [3, 1]},
        "fastflownet: classifier - oracle rule": {**row, "training_seeds": [1, 1]}})
    assert table["interval counts"].tolist() == ["scenes and seeds", "scenes only",
                                                 "scenes and seeds", "scenes only"]
    eff = pd.DataFrame({"chapter": "07", "question": "q", "comparison": table["comparison"],
                        "ΔF1 (points)": table["ΔF1 (points)"], "verdict": table["verdict"],
                        "interval counts": table["interval counts"],
                        "low": [p[0] for p in table.attrs["ci_points"]],
                        "high": [p[1] for p in table.attrs["ci_points"]],
                        "95% CI, scenes and seeds (points)": table[
                            "95% CI, scenes and seeds (points)"],
                        "Holm, all effects": "decided"})
    lines = ch13.answers(eff)["ΔF1, 95 % interval (points)"]
    assert [ln.endswith("[scenes only]") for ln in lines] == [False, True, False, True]
    ax = viz.forest(eff).axes[0]
    styles = [c.get_linestyle()[0][1] is not None for c in ax.collections]  # dashed: a pattern
    assert styles == [False, True, False, True]


def test_chapter_04_s_numbers_are_the_keyframe_set_s_shares():
    """Chapter 04's backend: the keyframe set's speeds by label, the moving share and the
    agreements in percent (one and two decimals), the examples' titles."""
    from flowmod.chapters import ch04_labeling as ch04

    key = pd.DataFrame({"label": [1, 0, 0, 1], "true_label": [1, 0, 1, 1],
                        "box_label": [1, -1, 1, 1], "speed": [3.0, 0.5, 1.9, 2.2],
                        "distance": [40.0, 50.0, 60.0, 35.4]})
    assert ch04.speeds(key)["moving"].tolist() == [3.0, 2.2]
    assert ch04.speeds(key)["still"].tolist() == [0.5, 1.9]
    assert ch04.moving_fraction(key) == 50.0
    assert ch04.true_agreement(key) == 75.0
    assert ch04.box_agreement(key) == round(100 * 2 / 3, 1)
    assert ch04.near_titles(key.iloc[:1]) == ["3.00 m/s, 40 m"]
    assert ch04.SPEED_BINS[0] == 0 and ch04.SPEED_BINS[-1] == 25.0


def test_chapter_09_s_signal_is_read_by_distance_and_its_recalls_in_percent():
    """Chapter 09's backend: the focal length and time gap of the keyframe pairs (us -> s)
    feed the signal table, whose 50 m row gives the glued width change; recalls in %."""
    from flowmod.chapters import ch09_blind_spots as ch09
    from flowmod.extensions import blind_spots
    from flowmod.params import load_profile

    p = load_profile("smoke")
    k = [1000.0, 0, 800, 0, 1000.0, 450, 0, 0, 1]
    pairs = pd.DataFrame({"set": ["keyframe", "keyframe", "general"],
                          "intrinsic": [k, k, [5.0] * 9], "timestamp_1": [0, 10, 0],
                          "timestamp_2": [500_000, 500_010, 1]})
    got = ch09.signal_table(p, pairs)
    want = blind_spots.physical_signal(1000.0, 0.5, flow_scale=p.flow_scale)
    pd.testing.assert_frame_equal(got, want)
    assert ch09.radial_px(got) == round(float(want.iloc[1, 2]), 2)
    blind = pd.DataFrame({"by": [blind_spots.RADIAL_SPEED] * 2, "bin": ["[2, 3)", "[5, 10)"],
                          "recall": [0.25, 0.5], "n_moving": [4, 2]})
    assert ch09.recall_numbers({"gt": blind, "dis": blind}, "dis") == {
        "recall_slow_gt": 25.0, "recall_fast_gt": 50.0, "recall_slow_dis": 25.0,
        "recall_fast_dis": 50.0, "headline_recall_slow": 25.0, "headline_recall_fast": 50.0}


def test_the_small_backend_helpers_of_chapters_02_05_and_12():
    from flowmod.chapters import ch02_filtering as ch02
    from flowmod.chapters import ch05_preprocessing as ch05
    from flowmod.chapters import ch12_self_trained_flow as ch12
    from flowmod.flow import flow_to_color
    from flowmod.params import load_profile

    p = load_profile("smoke")
    bins = ch02.distance_bins(p)
    assert bins[0] == p.min_distance and bins[-1] >= p.max_distance
    assert np.allclose(np.diff(bins), ch02.DISTANCE_BIN)
    crop = np.random.default_rng(0).normal(size=(2, 4, 4)).astype(np.float32)
    assert np.array_equal(ch05.crop_color(crop), flow_to_color(crop.transpose(1, 2, 0)))
    assert ch12.shipped_steps(None) == 0 and ch12.shipped_steps({"steps": 7}) == 7


def test_the_protocol_gap_is_each_model_s_original_minus_clean_f1():
    from flowmod.chapters import ch07_evaluation as ch07

    rec = {"per_seed_original": [0.9, 0.8, 0.95], "per_seed_clean": [0.85, 0.82, 0.7]}
    assert ch07.protocol_gaps(rec) == pytest.approx([0.05, -0.02, 0.25])
    with pytest.raises(ValueError):  # a model without its other score is an error
        ch07.protocol_gaps({"per_seed_original": [0.9], "per_seed_clean": []})


def test_f1_by_flags_few_scenes_and_shows_the_still_groups_false_alarms():
    """A group without a mover (F1 NaN) gets a cross at its still vehicles' false-alarm rate
    (1 - accuracy); a group over fewer than MIN_SCENES scenes is flagged in its tick."""
    from flowmod import metrics
    from flowmod.report import viz

    t = pd.DataFrame({"speed_bin": ["[0, 2)", "[2, 5)"], "n": [40, 30], "n_moving": [0, 30],
                      "precision": [np.nan, 1.0], "recall": [np.nan, 0.8],
                      "f1": [np.nan, 0.89], "accuracy": [0.75, 0.8], "ci_lo": [np.nan, 0.8],
                      "ci_hi": [np.nan, 0.95], "scenes": [metrics.MIN_SCENES, 3]})
    fig = viz.f1_by({"dis": t, "gt": t}, "speed_bin", "speed (m/s)")
    ax = fig.axes[0]
    ticks = [x.get_text() for x in ax.get_xticklabels()]
    assert ticks == [f"[0, 2)\nn=40\n{metrics.MIN_SCENES} sc.", "[2, 5)\nn=30\n3 sc. (too few)"]
    crosses = [ln for ln in ax.get_lines() if ln.get_marker() == "x"]
    assert len(crosses) == 2 and all(ln.get_ydata()[0] == pytest.approx(0.25) for ln in crosses)
    labels = ax.get_legend_handles_labels()[1]
    assert sorted(labels) == ["dis", "gt", "still vehicles called moving (no mover in the group)"]
    assert ax.get_ylabel() == "F1 (dots); false alarms (crosses)"
    assert viz.figure_problems(fig) == []
