"""Chapter 14's backend (:mod:`flowmod.chapters.ch14_answers`): quick tests for mutation
testing, which runs only the quick tests (the chapter's own tests execute its notebook on a
built world and are slow).

They complement tests/test_chapter_numbers.py (each effect A minus B of its own tables,
Holm's procedure, the scope sentence's thresholds) and tests/test_replicate.py (the
replication verdicts): here the effects table's other columns on the hand-made study
(tests/handmade.py), the landing page's table and sentences word for word on hand-made
effects, and the replication record's reading. Expected values are written by hand or
computed here (Holm's procedure, the two-sided p-value) from the chapters' own tables.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pandas as pd
import pytest

from flowmod.chapters import ch07_evaluation as ch07
from flowmod.chapters import ch10_inputs as ch10
from flowmod.chapters import ch11_all_distances as ch11
from flowmod.chapters import ch14_answers as ch
from flowmod.chapters import common
from flowmod.extensions.inputs import chains
from flowmod.params import load_profile

#: The landing page's question of each chapter, as the book prints it.
QUESTIONS = {
    "07": "Table 3: which flow serves the classifier best, and does the classifier reach "
          "the oracle rule on the same flow?",
    "10": "Does another input than the raw flow help? (test scenes)",
    "11": "Does training on all distances help on Table 4's set?",
}


def _holm_by_hand(p: list[float], alpha: float = 0.05) -> list[bool]:
    """Holm's step-down procedure: the k-th smallest p against alpha / (m - k + 1)."""
    order = sorted(range(len(p)), key=lambda i: (math.isnan(p[i]), p[i]))
    out = [False] * len(p)
    for k, i in enumerate(order):
        if math.isnan(p[i]) or p[i] > alpha / (len(p) - k):
            break
        out[i] = True
    return out


@pytest.fixture
def built_all(handmade_study, monkeypatch):
    """The hand-made study with chapters 10 and 11 built (their ``built`` says so: the
    hand-made nodes have no fingerprints to read)."""
    monkeypatch.setattr(ch.ch10, "built", lambda params: chains(params))
    monkeypatch.setattr(ch.ch11, "built", lambda params: list(params.wide_methods))
    return handmade_study[0]


def test_the_effects_table_carries_each_chapter_s_rows_whole(built_all):
    """Every effect's question, interval as numbers (those its text shows), what the
    interval resamples, its two-sided p-value (the comparison table's), Holm's
    verdict over all the effects, and its scenes; the columns in order."""
    p = built_all
    eff = ch.effects(p)
    assert eff.columns.tolist() == [
        "chapter", "question", "comparison", "ΔF1 (points)", "low", "high",
        "95% CI, scenes and seeds (points)", "interval counts", "verdict", "p (two-sided)",
        "Holm, all effects", "scenes"]
    tables = {"07": ch07.comparisons(p), "10": ch10.comparisons(p, "test", ch10.rows(p)),
              "11": ch11.comparisons(p, list(p.wide_methods), "general")}
    rows = pd.concat(list(tables.values()), ignore_index=True)
    assert eff["question"].tolist() == [QUESTIONS[c] for c in eff["chapter"]]
    assert eff["comparison"].tolist() == rows["comparison"].tolist()
    assert eff["interval counts"].tolist() == rows["interval counts"].tolist()
    assert set(eff["interval counts"]) == {"scenes and seeds", "scenes only"}
    assert eff["verdict"].tolist() == rows["verdict"].tolist()
    assert eff["95% CI, scenes and seeds (points)"].tolist() == rows[
        "95% CI, scenes and seeds (points)"].tolist()
    for text, lo, hi in eff[["95% CI, scenes and seeds (points)", "low", "high"]].to_numpy():
        shown = [float(v) for v in re.findall(r"-?\d+\.\d", text)[:2]]
        assert shown == [round(lo, 1) + 0.0, round(hi, 1) + 0.0], text
        assert lo < hi
    want_p = [p for t in tables.values() for p in t.attrs["p_two_sided"]]
    assert eff["p (two-sided)"].tolist() == want_p and np.isfinite(want_p).all()
    # replicates that tie at 0 count on both sides: never below twice the smaller of the
    # shares with A <= B and A > B (the column is rounded to 0.1 %)
    share = rows["replicates with A <= B (%)"].to_numpy(float) / 100
    assert all(w >= min(1.0, 2 * min(s, 1 - s)) - 1e-3 for w, s in zip(want_p, share, strict=True))
    holm = _holm_by_hand(want_p)
    assert eff["Holm, all effects"].tolist() == ["decided" if h else "not decided" for h in holm]
    assert 0 < sum(holm) < len(holm)
    assert eff["scenes"].tolist() == [9] * len(eff)


def test_the_effects_table_holds_only_the_chapters_built(handmade_study, monkeypatch):
    """Chapters 10 and 11 not built: chapter 07's effects alone."""
    monkeypatch.setattr(ch.ch10, "built", lambda params: [])
    monkeypatch.setattr(ch.ch11, "built", lambda params: [])
    eff = ch.effects(handmade_study[0])
    assert eff["chapter"].tolist() == ["07"] * len(ch07.comparisons(handmade_study[0]))


# --- the landing page --------------------------------------------------------------------------


def _eff(rows: list[tuple]) -> pd.DataFrame:
    """Hand-made effects: (chapter, comparison, ΔF1, low, high, text, counts, verdict,
    Holm)."""
    cols = ["chapter", "comparison", "ΔF1 (points)", "low", "high",
            "95% CI, scenes and seeds (points)", "interval counts", "verdict",
            "Holm, all effects"]
    out = pd.DataFrame(rows, columns=cols)
    out.insert(1, "question", [QUESTIONS.get(c, f"question of {c}") for c in out["chapter"]])
    return out


EFFECTS = _eff([
    ("07", "gt - dis", 2.2, 0.2, 4.4, "0.2 to 4.4", "scenes and seeds", "A better",
     "decided"),
    ("07", "dis - raft", -3.0, -5.5, -0.5, "-5.5 to -0.5", "scenes only", "B better",
     "not decided"),
    ("07", "e - f", 0.0, 0.01, 0.09, "0.0 to 0.1", "scenes and seeds", "A better",
     "not decided"),
    ("07", "g - h", 0.4, -1.0, 1.5, "-1.0 to 1.5", "scenes and seeds", "equivalent",
     "not decided"),
    ("10", "a - b", -0.04, -3.0, 2.9, "-3.0 to 2.9 (9 scenes: too few)", "scenes only",
     "inconclusive", "not decided"),
    ("13", "x - y", 1.0, -1.0, 3.0, "-1.0 to 3.0", "scenes and seeds", "inconclusive",
     "not decided"),
])


def test_the_answers_table_word_for_word():
    """One row per effect: the question in a few words (a chapter without them: its whole
    question), the difference with its interval (signed, ``[scenes only]`` where an arm
    was trained once a fold), the verdict as decided, equivalent or inconclusive, Holm's,
    the chapter."""
    got = ch.answers(EFFECTS)
    assert got.columns.tolist() == ["question", "comparison (A - B)",
                                    "ΔF1, 95 % interval (points)", "verdict", "Holm",
                                    "chapter"]
    assert got.values.tolist() == [
        ["Which flow? (Table 3)", "gt - dis", "+2.2 (0.2 to 4.4)", "decided", "decided", "07"],
        ["Which flow? (Table 3)", "dis - raft", "-3.0 (-5.5 to -0.5) [scenes only]", "decided",
         "not decided", "07"],
        ["Which flow? (Table 3)", "e - f", "+0.0 (0.0 to 0.1)", "decided", "not decided", "07"],
        ["Which flow? (Table 3)", "g - h", "+0.4 (-1.0 to 1.5)", "equivalent", "not decided",
         "07"],
        ["Other inputs?", "a - b", "-0.0 (-3.0 to 2.9 (9 scenes: too few)) [scenes only]",
         "inconclusive", "not decided", "10"],
        ["question of 13", "x - y", "+1.0 (-1.0 to 3.0)", "inconclusive", "not decided", "13"],
    ]
    short = ch.answers(_eff([("11", "c - d", 1.0, 0.5, 1.5, "0.5 to 1.5", "scenes only",
                              "A better", "decided")]).drop(columns=["interval counts"]))
    assert short.values.tolist() == [["All distances?", "c - d", "+1.0 (0.5 to 1.5)", "decided",
                                      "decided", "11"]]


def test_each_question_in_one_sentence_with_its_decided_effects_winner_first():
    """Per question: how many effects are decided, each as ``A over B`` with the interval
    turned when B won (a decided effect shown as 0.0 keeps its order), how many are
    equivalent and inconclusive; a chapter without effects is not built."""
    words = ch.question_words(EFFECTS)
    assert list(words) == ["answer_07", "answer_10", "answer_11"]
    assert words["answer_07"] == (
        f"{QUESTIONS['07']} 3 of 4 comparisons decided: gt over dis by 2.2 points (0.2 to "
        "4.4); raft over dis by 3.0 points (0.5 to 5.5); e over f by 0.0 points (0.0 to 0.1)."
        " Equivalent: 1; inconclusive: 0.")
    assert words["answer_10"] == (f"{QUESTIONS['10']} 0 of 1 comparisons decided. "
                                  "Equivalent: 0; inconclusive: 1.")
    assert words["answer_11"] == f"{QUESTIONS['11']} Not built in this run."


def test_the_scope_sentence_in_full():
    """The profile, the most test scenes any effect counts, the seeds, and the warning
    (few scenes are enough for it, with many seeds)."""
    eff = pd.DataFrame({"scenes": [12, 31, 26]})
    warning = (" With this few, the intervals are wide and a point estimate can move by "
               "several points in a rebuild on another world; read the intervals.")
    assert ch.scope_words(load_profile("demo", seeds=1), eff) == (
        "This build: the demo profile, 31 test scenes, one training seed a fold in Table 3."
        + warning)
    assert ch.scope_words(load_profile("demo", seeds=4), eff) == (
        "This build: the demo profile, 31 test scenes, 4 training seeds a fold in Table 3."
        + warning)
    at_edge = pd.DataFrame({"scenes": [60, 12]})  # FEW_SCENES and FEW_SEEDS: enough
    assert ch.scope_words(load_profile("demo", seeds=3), at_edge) == (
        "This build: the demo profile, 60 test scenes, 3 training seeds a fold in Table 3.")


def test_the_book_s_thresholds():
    """The smallest effect that matters (2 points) and Holm's family-wise rate (5 %) the
    landing page states."""
    assert ch.SMALLEST_EFFECT == 2.0
    assert ch.HOLM_ALPHA == 0.05 and ch.HOLM_PERCENT == pytest.approx(5.0, abs=1e-12)
    assert ch.FEW_SCENES == 60 and ch.FEW_SEEDS == 3


# --- the replication record ---------------------------------------------------------------------


def _e(delta: float, low: float, high: float) -> dict[str, float]:
    return {"delta": delta, "low": low, "high": high}


RECORD = {"date": "2026-12-06", "commit": "abc1234", "profile": "demo", "book_seed": 3,
          "replicate_seed": 11,
          "effects": [
              {"chapter": "07", "comparison": "gt - dis", "book": _e(2.2, 0.2, 4.4),
               "replicate": _e(4.04, 1.0, 7.0)},
              {"chapter": "13", "comparison": "cost of pull", "book": _e(-6.2, -10.2, -2.7),
               "replicate": _e(-1.0, -2.0, 0.5)},
              {"chapter": "10", "comparison": "a - b", "book": _e(-5.0, -8.0, -2.0),
               "replicate": _e(0.5, -1.0, 2.0)},
              {"chapter": "10", "comparison": "c - d", "book": _e(3.0, 1.0, 5.0),
               "replicate": _e(-3.0, -5.0, -1.0)},
              {"chapter": "11", "comparison": "e - f", "book": _e(0.4, -1.0, 1.8),
               "replicate": _e(1.0, 0.5, math.nan)},
              {"chapter": "07", "comparison": "h - i", "book": _e(1.0, 0.5, 1.5),
               "replicate": _e(0.2, -0.5, 0.9)}],
          "table3": [{"method": "ResNet18 on gt flow", "book": "90.1 (88.0-92.0)",
                      "replicate": "89.0 (86.5-91.2)"},
                     {"method": "ResNet18 on dis flow", "book": "85.9 (83.1-88.4)",
                      "replicate": "81.8 (78.0-85.0)"}]}


def test_the_replication_table_word_for_word():
    """Each effect's estimate and interval in both worlds (F1 points, chapter 13's per px),
    undefined where any of the three is, and its verdict in the book's words."""
    t = ch.replication_table(RECORD)
    assert t.columns.tolist() == ["chapter", "comparison", "book, seed 3", "replication, seed 11",
                                  "replicates?"]
    assert t.values.tolist() == [
        ["07", "gt - dis", "+2.2 (0.2 to 4.4)", "+4.0 (1.0 to 7.0)", "replicated"],
        ["13", "cost of pull", "-6.2 (-10.2 to -2.7) /px", "-1.0 (-2.0 to 0.5) /px",
         "same sign, not decided"],
        ["10", "a - b", "-5.0 (-8.0 to -2.0)", "+0.5 (-1.0 to 2.0)", "other sign, not decided"],
        ["10", "c - d", "+3.0 (1.0 to 5.0)", "-3.0 (-5.0 to -1.0)", "reversed"],
        ["11", "e - f", "+0.4 (-1.0 to 1.8)", "undefined", "not decided in the book"],
        ["07", "h - i", "+1.0 (0.5 to 1.5)", "+0.2 (-0.5 to 0.9)", "same sign, not decided"]]
    for bad in ({"delta": math.nan, "low": 0.5, "high": 1.0},
                {"delta": 1.0, "low": math.inf, "high": 1.0}):
        rec = {**RECORD, "effects": [{"chapter": "07", "comparison": "x", "book": bad,
                                      "replicate": bad}]}
        assert ch.replication_table(rec).iloc[0, 2] == "undefined"


def test_table3_in_both_worlds():
    """Table 3's rows as the record keeps them, each world's column named by its seed."""
    t = ch.table3_replication(RECORD)
    assert t.columns.tolist() == ["method", "book, seed 3", "replication, seed 11"]
    assert t.values.tolist() == [["ResNet18 on gt flow", "90.1 (88.0-92.0)", "89.0 (86.5-91.2)"],
                                 ["ResNet18 on dis flow", "85.9 (83.1-88.4)",
                                  "81.8 (78.0-85.0)"]]


def test_the_replication_paragraph_word_for_word():
    """When, where and on what the replication ran, and the decided effects by verdict;
    the note on another profile only when this build is one; no record, what to run."""
    words = ch.replication_words(RECORD, load_profile("demo"))
    assert words == (
        "`make replicate` ran the whole study again on a world drawn with master seed 11 "
        "instead of 3 (demo profile, 2026-12-06, commit abc1234; no choice of the study ever "
        "read that world). Of the 5 effects the book's world decided, 1 replicated (decided "
        "again, same side), 2 kept their sign without deciding, 1 turned sign without "
        "deciding and 1 reversed.")
    other = ch.replication_words(RECORD, load_profile("classroom"))
    assert other == words + (" This build is the classroom profile, so its own rows above "
                             "are not the record's book column.")
    counts = {**RECORD, "effects": [
        {"chapter": "07", "comparison": f"e{i}", "book": _e(2.0, 1.0, 3.0), "replicate": r}
        for i, r in enumerate([_e(2.0, 1.0, 3.0), _e(1.0, -1.0, 3.0), _e(0.5, -1.0, 2.0),
                               _e(-1.0, -2.0, 1.0), _e(-0.5, -2.0, 1.0), _e(-0.1, -2.0, 1.0)])]}
    assert ("Of the 6 effects the book's world decided, 1 replicated (decided again, same "
            "side), 2 kept their sign without deciding, 3 turned sign without deciding and 0 "
            "reversed.") in ch.replication_words(counts, load_profile("demo"))
    assert ch.replication_words(None, load_profile("demo")) == (
        "No replication is recorded yet (`make replicate` writes "
        "`benchmarks/replication.json`): read a decided row as this world's answer only.")


def test_the_record_is_read_from_the_repository_or_is_none(tmp_path, monkeypatch):
    """The record is ``benchmarks/replication.json`` under the repository root, read as
    JSON; None where there is none."""
    monkeypatch.setattr(common, "repo_root", lambda: tmp_path)  # where records are read
    assert ch.replication_record() is None
    (tmp_path / "benchmarks").mkdir()
    rec = {**RECORD, "effects": RECORD["effects"][:2]}
    (tmp_path / "benchmarks" / "replication.json").write_text(json.dumps(rec))
    assert ch.replication_record() == rec


def test_holm_at_the_rate_it_is_given():
    """Holm's procedure at the rate it is given, an undefined p-value last and never
    rejected."""
    assert ch.holm(np.array([0.005, 0.02]), alpha=0.02).tolist() == [True, True]
    assert ch.holm(np.array([0.005, 0.02]), alpha=0.0199).tolist() == [True, False]
    assert ch.holm(np.array([np.nan, 0.01, 0.04])).tolist() == [False, True, False]
    assert ch.holm(np.array([0.5, 0.6])).dtype == bool  # none rejected: still a mask


def test_no_effect_built_is_an_empty_table_with_every_column(handmade_study, monkeypatch):
    """No chapter with a paired effect: an empty effects table with every column (Holm's
    too), not an error."""
    monkeypatch.setattr(ch, "_chapter_tables",
                        lambda params: [("07", ch.common.comparison_table({}))])
    eff = ch.effects(handmade_study[0])
    assert eff.empty and eff.columns.tolist() == ch.EFFECT_COLUMNS
    assert "Holm, all effects" in ch.EFFECT_COLUMNS


def test_an_interval_that_touches_0_is_not_decided_in_either_world():
    """An interval with 0 as its bound holds 0: the book did not decide it, or the
    replication did not; an estimate of exactly 0 has the other sign."""
    yes = _e(1.0, 0.5, 1.5)
    assert ch.replication(_e(1.0, 0.0, 2.0), yes) == ch.NOT_DECIDED
    assert ch.replication(_e(-1.0, -2.0, 0.0), yes) == ch.NOT_DECIDED
    assert ch.replication(yes, _e(1.0, 0.0, 2.0)) == ch.SAME_SIGN
    assert ch.replication(_e(-1.0, -2.0, -0.5), _e(-1.0, -2.0, 0.0)) == ch.SAME_SIGN
    assert ch.replication(yes, _e(0.0, -1.0, 1.0)) == ch.OTHER_SIGN
    assert ch.replication(_e(-1.0, -2.0, -0.5), _e(0.0, -1.0, 1.0)) == ch.OTHER_SIGN
