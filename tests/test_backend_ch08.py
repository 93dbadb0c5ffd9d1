"""Chapter 08's backend (flowmod.chapters.ch08_generalisation), quick tests for mutation
testing.

mutmut runs only the quick tests, and chapter 08 was otherwise tested only by the slow
notebook runs (tests/test_evaluate.py checks table4 and the failure tagging on hand-made
tables). Here the rest is run on the hand-made study (tests/handmade.py: published
generalisation predictions of the demo profile) and on tiny hand-made tables: the
published predictions read back, Table 4 of the profile's range, F1 by distance and speed,
the numbers the chapter glues, the failure reasons with the profile's threshold and crop
scale, and the words on them. Every expected value is computed here by hand or with
scikit-learn and pandas. No world, no training: a few seconds.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from sklearn.metrics import balanced_accuracy_score, f1_score, precision_score, recall_score

from flowmod.chapters import ch08_generalisation as ch08
from flowmod.dag import Node
from flowmod.params import load_profile

CI = "F1 95% CI, scenes and seeds (%)"


def _seed_cols(df: pd.DataFrame) -> list[str]:
    return [c for c in df.columns if c.startswith("prob_s")] or ["prob"]


def _f1(df: pd.DataFrame) -> float:
    """F1 of a predictions table: the mean over its models (prob > 0.5: a mover)."""
    return float(np.mean([f1_score(df["label"], df[c] > 0.5) for c in _seed_cols(df)]))


def _mean(score, df: pd.DataFrame, y=None) -> float:
    """``score`` of each model's calls (or of the calls ``y``), averaged over the models."""
    return float(np.mean([score(df["label"], df[c] > 0.5 if y is None else y)
                          for c in _seed_cols(df)]))


def _general(tables, method: str) -> pd.DataFrame:
    return tables[Node("generalise", method)]["general"]


# --- the published predictions and Table 4 -------------------------------------------------


def test_predictions_are_each_methods_published_generalisation_table(handmade_study):
    """predictions(): per flow method of the profile (in its order), the generalise node's
    published ``general`` table, row for row."""
    p, tables = handmade_study
    got = ch08.predictions(p)
    assert list(got) == list(p.flow_methods) == ["gt", "dis", "farneback", "fastflownet"]
    for m, df in got.items():
        want = _general(tables, m)
        assert list(df.columns) == list(want.columns)
        assert df["ann_token"].tolist() == want["ann_token"].tolist()
        np.testing.assert_array_equal(df[_seed_cols(want)].to_numpy(),
                                      want[_seed_cols(want)].to_numpy())


def test_table_scores_the_profiles_range_and_beyond_of_the_published_predictions(
        handmade_study):
    """table(): by default the published predictions, split at the profile's
    general_max_distance (70 m, inclusive) into Table 4's range and beyond, one row each per
    method (the hand-made set has no true label at the frame); given ``preds``, those."""
    p, tables = handmade_study
    assert p.general_max_distance == 70.0
    got = ch08.table(p)
    assert got["method"].tolist() == [m for m in p.flow_methods for _ in range(2)]
    assert got["vehicles"].tolist() == ["0-70 m (Table 4)", "beyond 70 m"] * 4
    assert set(got["scored against"]) == {"paper rule (previous keyframe)"}
    for r in got.to_dict("records"):
        df = _general(tables, r["method"])
        inside = df["distance"] <= 70.0
        part = df[inside] if r["vehicles"].endswith("(Table 4)") else df[~inside]
        assert r["objects"] == len(part)
        assert r["F1 (%)"] == pytest.approx(round(100 * _f1(part), 1), abs=1e-9)
        assert r["P (%)"] == pytest.approx(round(100 * _mean(precision_score, part), 1))
        assert r["R (%)"] == pytest.approx(round(100 * _mean(recall_score, part), 1))
        assert r["balanced accuracy (%)"] == f"{100 * _mean(balanced_accuracy_score, part):.1f}"
        moving = np.ones(len(part), dtype=bool)
        assert r["always moving F1 (%)"] == f"{100 * _mean(f1_score, part, moving):.1f}"
    few = _general(tables, "dis").iloc[:40]
    mine = ch08.table(p, {"dis": few})
    assert mine["method"].tolist() == ["dis", "dis"]
    assert mine["objects"].tolist() == [int((few["distance"] <= 70).sum()),
                                        int((few["distance"] > 70).sum())]


# --- F1 by distance and by speed -------------------------------------------------------------


def _objects() -> pd.DataFrame:
    """Twelve objects of two models in four scenes, at distances and speeds that fill some
    bins of each figure (100.0 m: in the last distance bin, which ends at 100.01)."""
    distance = [1.0, 5.0, 9.0, 15.0, 15.5, 35.0, 36.0, 38.0, 85.0, 99.0, 100.0, 100.0]
    speed = [0.0, 0.5, 0.9, 1.5, 1.5, 2.5, 4.0, 4.5, 7.0, 20.0, 39.0, 0.2]
    label = [0, 1, 1, 0, 1, 1, 0, 1, 1, 0, 1, 1]
    s0 = [0.2, 0.9, 0.4, 0.6, 0.8, 0.7, 0.1, 0.9, 0.3, 0.2, 0.8, 0.9]
    s1 = [0.1, 0.8, 0.7, 0.3, 0.6, 0.2, 0.6, 0.9, 0.8, 0.1, 0.7, 0.4]
    return pd.DataFrame({"scene": [f"s{i % 4}" for i in range(12)], "fold": 0,
                         "label": label, "distance": distance, "speed": speed,
                         "prob_s0": s0, "prob_s1": s1, "prob": s0})


def _by_bins(df: pd.DataFrame, col: str, edges: tuple) -> pd.DataFrame:
    """Objects and mean-over-models F1 per bin (left-closed), computed with pandas."""
    key = pd.cut(df[col], list(edges), right=False)
    rows = [{"bin": str(k), "n": len(g), "f1": _f1(g)}
            for k, g in df.groupby(key, observed=True, sort=True)]
    return pd.DataFrame(rows)


@pytest.mark.parametrize(("fn", "col", "edges"), [
    (ch08.by_distance, "distance", (0, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100.01)),
    (ch08.by_speed, "speed", (0, 1, 2, 3, 5, 10, 40))])
def test_f1_by_distance_and_speed_uses_the_figures_bins(fn, col, edges):
    """by_distance() / by_speed(): per method, one row per non-empty bin of the figure's
    edges (10 m steps to 100.01 m; 0-1-2-3-5-10-40 m/s), its objects and F1 (mean over the
    models), and an interval over scenes."""
    df = _objects()
    got = fn({"dis": df, "gt": df.iloc[::-1]})
    assert list(got) == ["dis", "gt"]
    want = _by_bins(df, col, edges)
    for m in ("dis", "gt"):
        t = got[m]
        assert t[f"{col}_bin"].tolist() == want["bin"].tolist()
        assert t["n"].tolist() == want["n"].tolist()
        assert t["f1"].tolist() == pytest.approx(want["f1"].tolist(), abs=1e-12)
        assert {"ci_lo", "ci_hi", "scenes"} <= set(t.columns)


# --- the numbers chapter 08 records ---------------------------------------------------------


def _row(method, vehicles, against, objects, f1, ci="80.0-90.0 (9 scenes: too few)",
         chance=66.7) -> dict:
    return {"method": method, "vehicles": vehicles, "scored against": against,
            "objects": objects, "F1 (%)": f1, CI: ci, "always moving F1 (%)": chance}


PAPER, TRUE = "paper rule (previous keyframe)", "true label at the frame"
NEAR, FAR = "0-70 m (Table 4)", "beyond 70 m"


def test_numbers_are_table4s_f1_per_method_and_label_and_the_headlines():
    """numbers(): Table 4's F1 per method and label (paper / true), the objects of the
    first paper row, the headline method's (the profile's first estimated flow: dis) F1,
    interval text and always-moving F1, and the F1 beyond the range against the paper's
    label only."""
    table = pd.DataFrame([
        _row("gt", NEAR, PAPER, 76, 93.5, "90.0-96.0 (9 scenes: too few)", 66.1),
        _row("gt", NEAR, TRUE, 77, 92.0),
        _row("gt", FAR, PAPER, 32, 94.8),
        _row("gt", FAR, TRUE, 33, 91.1),
        _row("dis", NEAR, PAPER, 75, 90.4, "83.8-95.5 (9 scenes: too few)", 66.7),
        _row("dis", NEAR, TRUE, 78, 89.0),
        _row("dis", FAR, PAPER, 31, 91.7),
        _row("dis", FAR, TRUE, 34, 88.8)])
    got = ch08.numbers(load_profile("demo"), table)
    assert got == {"general_f1_gt_paper": 93.5, "general_f1_gt_true": 92.0,
                   "general_f1_dis_paper": 90.4, "general_f1_dis_true": 89.0,
                   "n_general": 76, "headline_general_f1": 90.4,
                   "headline_general_ci": "83.8-95.5 (9 scenes: too few)",
                   "headline_general_chance": 66.7,
                   "beyond_f1_gt": 94.8, "beyond_f1_dis": 91.7}
    assert type(got["n_general"]) is int and type(got["headline_general_chance"]) is float
    # rows in another order (beyond the range first) give the same numbers: a row is read
    # for what it is, never overwritten by a later one of the other range
    far_first = table.iloc[[2, 3, 6, 7, 0, 1, 4, 5]].reset_index(drop=True)
    assert ch08.numbers(load_profile("demo"), far_first) == got


def test_numbers_without_the_headline_methods_paper_row_are_undefined():
    """No paper-label row of the headline method (dis): its F1 and always-moving F1 are
    nan and its interval 'undefined'; no paper-label row at all: no objects either."""
    only_gt = pd.DataFrame([_row("gt", NEAR, PAPER, 76, 93.5), _row("dis", NEAR, TRUE, 70, 88.0)])
    got = ch08.numbers(load_profile("demo"), only_gt)
    assert got["n_general"] == 76 and got["general_f1_dis_true"] == 88.0
    assert np.isnan(got["headline_general_f1"]) and np.isnan(got["headline_general_chance"])
    assert got["headline_general_ci"] == "undefined"
    none = ch08.numbers(load_profile("demo"), only_gt.iloc[1:])
    assert none["n_general"] == 0 and none["headline_general_ci"] == "undefined"
    assert set(none) == {"general_f1_dis_true", "n_general", "headline_general_f1",
                         "headline_general_ci", "headline_general_chance"}


# --- the failure reasons ----------------------------------------------------------------------


def test_failures_tag_with_the_profiles_speed_threshold_and_crop_scale():
    """failures(): the objects tagged with the profile's speed threshold (3 m/s here: 3.6
    m/s is near it, 1.5 m/s is not) and crop scale (2 here: a's 40 px window misses b, which
    a tripled one would reach), and the shares of each reason among all objects and among
    the wrong predictions."""
    p = load_profile("demo", speed_threshold=3.0, crop_scale=2.0)
    preds = pd.DataFrame({
        "pair_id": ["p", "p", "q", "q"], "instance_token": ["a", "b", "c", "d"],
        "xmin": [100.0, 135.0, 600.0, 610.0], "ymin": [100.0] * 4,
        "xmax": [120.0, 155.0, 620.0, 630.0], "ymax": [120.0] * 4,
        "label": [1, 0, 0, 1], "prob": [0.2, 0.3, 0.9, 0.8],
        "distance": [20.0, 20.0, 60.0, 20.0], "speed": [3.6, 1.5, 0.0, 10.0]})
    boxes = preds[["pair_id", "instance_token", "xmin", "ymin", "xmax", "ymax"]]
    shares, tagged = ch08.failures(p, preds, boxes)
    assert tagged["wrong"].tolist() == [True, False, True, False]
    assert tagged["unclear_flow"].tolist() == [True, False, True, False]
    assert tagged["crowded"].tolist() == [False, False, True, True]
    assert shares["reason"].tolist() == ["remote or slow", "other objects in the crop"]
    assert shares["all objects (%)"].tolist() == [50.0, 50.0]
    assert shares["wrong predictions (%)"].tolist() == [100.0, 50.0]


def _shares(rows: list[tuple[str, float, float]]) -> pd.DataFrame:
    return pd.DataFrame(rows, columns=["reason", "all objects (%)", "wrong predictions (%)"])


def test_failure_words_cover_every_case_at_its_boundary():
    """failure_words(): no such object (0 %) is undefined even with a share among the
    errors of 0; 95.0 % of all objects is untestable; a ratio of exactly 1.05 counts as
    commoner (with its ratio), one under it as no commoner; no wrong prediction (nan) is
    undefined; sentences joined by "; ", ending with a full stop."""
    shares = _shares([("none", 0.0, 0.0), ("most", 95.0, 99.0), ("edge", 20.0, 21.0),
                      ("under", 40.0, 41.9), ("nan", 30.0, float("nan"))])
    assert ch08.failure_words(shares) == (
        "*none*: undefined (no wrong prediction or no such object); "
        "*most* holds for 95.0 % of all objects, so this world cannot test it: nearly every "
        "crop has it, right or wrong; "
        "*edge* holds for 21.0 % of the wrong predictions against 20.0 % of all objects "
        "(1.1 times as common); "
        "*under* holds for 41.9 % of the wrong predictions and 40.0 % of all objects: no "
        "commoner among the errors, so it does not explain them; "
        "*nan*: undefined (no wrong prediction or no such object).")
    assert ch08.failure_words(_shares([("x", 94.9, 100.0)])) == (
        "*x* holds for 100.0 % of the wrong predictions against 94.9 % of all objects "
        "(1.1 times as common).")
