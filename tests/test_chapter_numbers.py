"""Chapters 06-13's numbers from hand-made published predictions: every Table 3 row carries
its own method's scores, every paired effect is A minus B of its own two prediction tables,
and a verdict is "decided" only when its interval excludes 0 (issue 53, item 10).

The published nodes are written here by hand: the files each stage publishes (its
``<split>.parquet`` tables through :func:`flowmod.evaluate.write_frames`, the evaluate
node's scores by :func:`flowmod.evaluate.score`, a manifest), in a demo-profile run folder,
with predictions whose tables all score differently. A row given another method's scores,
or an effect taken B minus A or from the wrong table, changes a number. Every expected
number is computed here with scikit-learn from the same tables, not with flowmod.metrics.
Quick: no world, no training.
"""

from __future__ import annotations

from itertools import combinations

import handmade
import numpy as np
import pandas as pd
import pytest
from sklearn.metrics import f1_score, precision_score, recall_score

from flowmod import metrics
from flowmod.chapters import ch06_training as ch06
from flowmod.chapters import ch07_evaluation as ch07
from flowmod.chapters import ch10_inputs as ch10
from flowmod.chapters import ch11_all_distances as ch11
from flowmod.chapters import ch12_self_trained_flow as ch12
from flowmod.chapters import ch14_answers as ch13
from flowmod.dag import Node
from flowmod.extensions.inputs import chains
from flowmod.params import Params, load_profile

#: |A - B| (F1 points) every hand-made effect exceeds, so that B - A is another number.
POWER = handmade.POWER


@pytest.fixture
def study(handmade_study) -> tuple[Params, dict[Node, dict[str, pd.DataFrame]]]:
    """The hand-made study (tests/handmade.py): ``(params, {node: {table: predictions}})``."""
    return handmade_study


def _per_seed(df: pd.DataFrame) -> list[np.ndarray]:
    """Each model's calls (``prob > 0.5``: a mover) on the table's objects."""
    cols = [c for c in df.columns if c.startswith("prob_s")] or ["prob"]
    return [df[c].to_numpy() > 0.5 for c in cols]


def _f1(df: pd.DataFrame) -> float:
    """The F1 of a predictions table: the mean over its models of each one's F1."""
    return float(np.mean([f1_score(df["label"], c) for c in _per_seed(df)]))


def _in_range(p: Params, df: pd.DataFrame, split: str) -> pd.DataFrame:
    """The rows a split is scored on: the test split whole, the generalisation set within
    Table 4's range."""
    return df if split == "test" else df[df["distance"] <= p.general_max_distance]


def _assert_effects(got: pd.DataFrame, pairs: dict[str, tuple[pd.DataFrame, pd.DataFrame]]
                    ) -> None:
    """``got`` (a comparison table, or chapter 14's effects) has one row per name of
    ``pairs``, in order, each effect the F1 of A minus the F1 of B (points, to the 0.1
    shown) of the pair's two tables."""
    assert got["comparison"].tolist() == list(pairs)
    for name, value in zip(got["comparison"], got["ΔF1 (points)"], strict=True):
        a, b = pairs[name]
        want = 100 * (_f1(a) - _f1(b))
        assert abs(want) > POWER, f"{name}: too close to tell A - B from B - A"
        assert value == pytest.approx(want, abs=0.05 + 1e-9), name


def _table(tables, stage: str, method: str | None, name: str, part: str | None = None
           ) -> pd.DataFrame:
    return tables[Node(stage, method, part)][name]


def _chapter07_pairs(p: Params, tables) -> dict[str, tuple[pd.DataFrame, pd.DataFrame]]:
    """Chapter 07's comparisons by name: (A's table, B's table)."""
    test = {m: _table(tables, "evaluate", m, "test") for m in p.flow_methods}
    pairs = {f"{a} - {b}": (test[a], test[b]) for a, b in combinations(p.flow_methods, 2)}
    pairs |= {f"{m}: classifier - oracle rule": (test[m], _table(tables, "evaluate", m,
                                                                 "baseline"))
              for m in p.flow_methods}
    pairs |= {f"{m}: {p.input_scaling} input - raw input": (
        test[m], _table(tables, "evaluate", m, "raw")) for m in p.raw_input_methods}
    return pairs


def _chapter10_pairs(p: Params, tables, split: str, order: list[tuple[str | None, str]]
                     ) -> dict[str, tuple[pd.DataFrame, pd.DataFrame]]:
    """Chapter 10's comparisons of the chains ``order``: each input minus the raw flow of
    its method (the images alone: of the first extension method), on ``split``."""
    flow = {"test": "evaluate", "general": "generalise"}[split]
    out = {}
    for m, v in order:
        ref = m or p.extension_methods[0]
        a = _table(tables, "xevaluate", m, split, v)
        b = _table(tables, flow, ref, split)
        out[ch10.comparison_name(p, m, v)] = (_in_range(p, a, split), _in_range(p, b, split))
    return out


def _chapter11_pairs(p: Params, tables, split: str
                     ) -> dict[str, tuple[pd.DataFrame, pd.DataFrame]]:
    """Chapter 11's comparisons: trained on all distances minus the paper's training."""
    flow = {"test": "evaluate", "general": "generalise"}[split]
    return {f"{m}: all distances - {ch11.band(p)}": (
        _in_range(p, _table(tables, "wgeneralise", m, split), split),
        _in_range(p, _table(tables, flow, m, split), split)) for m in p.wide_methods}


# --- Table 3 ------------------------------------------------------------------------------


def test_each_table3_row_carries_its_own_method_s_scores(study):
    """Every row of Table 3 (the classifiers, the raw-input models, the geometric rule) and
    chapter 07's recorded F1s are its own table's: F1, precision and recall as means over
    its models (issue 53: every "ResNet18 on {m} flow" row given the headline method's F1
    passed the quick tests)."""
    p, tables = study
    rows = {f"ResNet18 on {m} flow": _table(tables, "evaluate", m, "test")
            for m in p.flow_methods}
    rows |= {f"ResNet18 on {m} flow, {ch07.RAW_LABEL}": _table(tables, "evaluate", m, "raw")
             for m in p.raw_input_methods}
    rows |= {f"geometric residual, {m} flow": _table(tables, "evaluate", m, "baseline")
             for m in p.flow_methods}
    got = ch07.table3(p).set_index("Method")
    assert got.index.tolist() == list(rows)
    for name, df in rows.items():
        calls = _per_seed(df)
        want = [100 * float(np.mean([f(df["label"], c) for c in calls]))
                for f in (f1_score, precision_score, recall_score)]
        assert got.loc[name, ["F1 (%)", "P (%)", "R (%)"]].tolist() == pytest.approx(
            want, abs=0.05 + 1e-9), name
    assert got["F1 (%)"].nunique() == len(rows)  # no two rows could swap unseen
    numbers = ch07.numbers(p)
    for m in p.flow_methods:
        assert numbers[f"test_f1_{m}"] == pytest.approx(
            100 * _f1(rows[f"ResNet18 on {m} flow"]), abs=0.05 + 1e-9), m
        assert numbers[f"baseline_f1_{m}"] == pytest.approx(
            100 * _f1(rows[f"geometric residual, {m} flow"]), abs=0.05 + 1e-9), m
    assert numbers["headline_method"] == "dis"
    assert numbers["headline_f1"] == numbers["test_f1_dis"]


# --- paired effects -----------------------------------------------------------------------


def test_chapter07_effects_are_a_minus_b_of_their_own_tables(study):
    """Every pair of flow methods (earlier minus later), each classifier minus the rule on
    its flow, the chosen input minus the raw input."""
    p, tables = study
    _assert_effects(ch07.comparisons(p), _chapter07_pairs(p, tables))


@pytest.mark.parametrize("split", ["test", "general"])
def test_chapter10_effects_are_an_input_minus_its_raw_flow(study, split):
    """Each chain's input minus the raw flow of the same method (the images alone: minus
    the first extension method's), on the test split and on Table 4's range."""
    p, tables = study
    _assert_effects(ch10.comparisons(p, split, chains(p)),
                    _chapter10_pairs(p, tables, split, chains(p)))


@pytest.mark.parametrize("split", ["general", "test"])
def test_chapter11_effects_are_all_distances_minus_the_paper_s_training(study, split):
    """Trained on all distances minus the paper's band, on Table 4's range and on the test
    split (issue 53: the effect with its sign flipped passed a test that counted rows)."""
    p, tables = study
    _assert_effects(ch11.comparisons(p, p.wide_methods, split),
                    _chapter11_pairs(p, tables, split))


def test_chapter13_gathers_each_chapter_s_effects_unchanged(study, monkeypatch):
    """The landing page's effects: chapter 07's, chapter 10's on the test scenes, chapter
    11's on Table 4's range, each still A minus B of its own tables. (Whether a chain counts
    as built reads every fingerprint above it, which hand-made nodes do not have: the
    chapters' ``built`` say what is built here.)"""
    p, tables = study
    monkeypatch.setattr(ch13.ch10, "built", lambda params: chains(params))
    monkeypatch.setattr(ch13.ch11, "built", lambda params: list(params.wide_methods))
    eff = ch13.effects(p)
    shown = [c for c in ch10.rows(p) if c[1] != "flow"]  # the chapter's table order
    assert sorted(shown, key=str) == sorted(chains(p), key=str)
    pairs = {**_chapter07_pairs(p, tables), **_chapter10_pairs(p, tables, "test", shown),
             **_chapter11_pairs(p, tables, "general")}
    _assert_effects(eff, pairs)
    assert eff["chapter"].tolist() == (["07"] * len(_chapter07_pairs(p, tables))
                                       + ["10"] * len(chains(p)) + ["11"] * len(p.wide_methods))
    assert (eff["low"] < eff["high"]).all()


def test_chapter12_effects_are_the_shipped_network_minus_dis(study, monkeypatch):
    """The paper's observation on this study's numbers: the shipped network's classifier
    minus DIS's on Table 3 and on Table 4's range, and its end-point error in the boxes
    minus DIS's, paired per pair."""
    p, tables = study
    monkeypatch.setattr(ch12.pipeline, "built", lambda params, node: True)  # as in ch13's
    obs = ch12.observation(p, None)
    for split, flow in (("test", "evaluate"), ("general", "generalise")):
        a, b = (_in_range(p, _table(tables, flow, m, split), split)
                for m in ("fastflownet", "dis"))
        _assert_effects(obs[split].to_frame().T, {obs[split]["comparison"]: (a, b)})
    errors = pd.DataFrame({"scene": ["a", "a", "b", "c"], ch12.SHIPPED: [1.0, 3.0, 2.0, 6.0],
                           f"dis ({ch12.DIS_PRESET})": [2.0, 2.5, np.nan, 1.0]})
    assert ch12.box_difference(errors)["diff"] == pytest.approx((-1.0 + 0.5 + 5.0) / 3)


def test_chapter06_effects_are_the_variant_minus_the_recipe_of_the_committed_rows():
    """Chapter 06's ablation steps (benchmarks/ablation_steps.json): each effect, recipe and
    variant is the mean over (method, fold, seed) units of the record's own rows, the
    variant minus the recipe (to the 0.01 the record keeps)."""
    rec = ch06.steps_record()
    if rec is None:
        pytest.skip("no ablation_steps.json committed")
    rows = pd.DataFrame(rec["rows"])
    recipe = rows[rows["step"] == "recipe"].set_index(["method", "fold", "seed"])
    for e in rec["effects"]:
        col = {"annotated": "val_f1", "true": "val_f1_true"}[e["scored against"]]
        mine = rows[(rows["step"] == e["step"]) & (rows["variant"] == e["variant"])]
        var = mine.set_index(["method", "fold", "seed"])[col]
        ref = recipe.loc[var.index, col]
        assert len(var) == e["units"]
        assert e["effect (points)"] == pytest.approx(100 * (var - ref).mean(), abs=0.006)
        assert e["variant (%)"] - e["recipe (%)"] == pytest.approx(e["effect (points)"],
                                                                   abs=0.011)
        assert e["low"] < e["effect (points)"] < e["high"]
    shown = ch06.steps_table(rec)
    assert shown["effect (points)"].tolist() == [round(e["effect (points)"], 1)
                                                 for e in rec["effects"]]


# --- verdicts -----------------------------------------------------------------------------

#: (low, high) of an effect's interval (points) and whether it decides: both signs, and
#: intervals that reach 0 exactly (they hold 0: not decided).
INTERVALS = [((0.4, 2.0), True), ((-2.0, -0.4), True), ((-1.0, 1.0), False),
             ((-1.5, 0.0), False), ((0.0, 1.5), False), ((0.0, 0.0), False)]


def test_chapter06_calls_a_step_decided_only_when_its_interval_excludes_0():
    """Chapter 06's table and words on a record of one step per interval of
    :data:`INTERVALS` (issue 53: an interval that holds 0 called "decided" passed a test
    that read the words' prefix)."""
    effects = [{"step": f"step {i}", "variant": f"variant {i}", "scored against": "annotated",
                "units": 3, "recipe (%)": 80.0, "variant (%)": 80.0 + (lo + hi) / 2,
                "effect (points)": (lo + hi) / 2, "low": lo, "high": hi,
                "seconds a model": 10.0} for i, ((lo, hi), _) in enumerate(INTERVALS)]
    rec = {"date": "2026-12-06", "commit": "abc1234", "effects": effects}
    table = ch06.steps_table(rec)
    assert table["decided"].tolist() == ["yes" if d else "no" for _, d in INTERVALS]
    words = ch06.steps_words(rec)
    for i, ((lo, hi), decided) in enumerate(INTERVALS):
        said = "decided" if decided else "not decided"
        assert (f"step {i} (variant {i}): {(lo + hi) / 2:+.1f} points ({lo:+.1f} to "
                f"{hi:+.1f}, {said})") in words


def test_a_paired_verdict_decides_only_when_its_interval_excludes_0():
    """The paired comparisons' verdict (chapters 07, 10-13) on the same intervals: A or B
    better by the interval's side of 0, undecided when it holds 0; chapter 07's words and
    chapter 14's count follow it."""
    want = {(0.4, 2.0): "A better", (-2.0, -0.4): "B better"}
    row = {"detectable": 0.02, "per_seed": [0.0], "p_not_better": 0.5, "n_scenes": 29,
           "n": 90}
    rows = {f"a{i} - b{i}": {**row, "delta_f1": (lo + hi) / 200, "ci": (lo / 100, hi / 100)}
            for i, ((lo, hi), _) in enumerate(INTERVALS)}
    table = metrics.comparison_table(rows)
    verdicts = [want.get(ci, "undecided") for ci, _ in INTERVALS]
    assert [metrics.verdict(ci) for ci, _ in INTERVALS] == verdicts
    assert table["verdict"].tolist() == verdicts
    answer = ch07.answer(table)
    assert answer.count(", decided: the first is better") == 1
    assert answer.count(", decided: the second is better") == 1
    eff = pd.DataFrame({"chapter": "07", "question": "q", "comparison": table["comparison"],
                        "ΔF1 (points)": table["ΔF1 (points)"], "verdict": table["verdict"],
                        "95% CI, scenes and seeds (points)": table[
                            "95% CI, scenes and seeds (points)"], "Holm, all effects": "decided",
                        "low": [lo for (lo, _), _ in INTERVALS],
                        "high": [hi for (_, hi), _ in INTERVALS]})
    assert (ch13.answers(eff)["verdict"] == "decided").sum() == 2
    assert f"2 of {len(INTERVALS)} comparisons decided" in ch13.question_words(eff)["answer_07"]


def test_the_landing_page_names_its_build_and_says_when_intervals_are_wide():
    """Chapter 14's scope sentence: the profile, the test scenes (the most any effect
    counts) and the seeds; the warning only below 60 scenes or 3 seeds."""
    eff = pd.DataFrame({"scenes": [31, 26]})
    few = ch13.scope_words(load_profile("classroom"), eff)
    assert few.startswith("This build: the classroom profile, 31 test scenes, one training "
                          "seed a fold in Table 3.")
    assert "intervals are wide" in few
    demo = load_profile("demo")
    many = ch13.scope_words(demo, pd.DataFrame({"scenes": [100, 60]}))
    assert many == "This build: the demo profile, 100 test scenes, 3 training seeds a fold in Table 3."
    assert "wide" in ch13.scope_words(demo, pd.DataFrame({"scenes": [59]}))
    assert "wide" in ch13.scope_words(load_profile("demo", seeds=2), pd.DataFrame({"scenes": [100]}))
    assert "0 test scenes" in ch13.scope_words(demo, pd.DataFrame({"scenes": []}))


def test_holm_corrects_over_all_the_books_effects():
    """Issue 50 item 4: Holm's step-down procedure at 5 % over every effect, from the
    bootstrap's two-sided p-values; a p-value that fails stops the procedure."""
    p = np.array([0.01, 0.04, 0.03, 0.005, np.nan])
    # sorted 0.005 <= 0.05/5, 0.01 <= 0.05/4, 0.03 > 0.05/3: stop; 0.04 never tested
    assert ch13.holm(p).tolist() == [True, False, False, True, False]
    assert ch13.holm(np.array([0.02, 0.024])).tolist() == [True, True]  # 0.02 <= .025, .024 <= .05
    assert ch13.holm(np.array([0.051, 0.001])).tolist() == [False, True]
    assert ch13.holm(np.array([0.025, 0.05])).tolist() == [True, True]  # at the bounds
    assert ch13.holm(np.array([])).tolist() == []
