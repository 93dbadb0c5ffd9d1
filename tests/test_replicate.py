"""`make replicate`: the record of every effect in two worlds, and how chapter 14 reads it."""

from __future__ import annotations

import math

import pytest

from flowmod import replicate
from flowmod.chapters import ch14_answers as ch14
from flowmod.params import load_profile


def _e(delta: float, low: float, high: float) -> dict[str, float]:
    return {"delta": delta, "low": low, "high": high}


@pytest.mark.parametrize(("book", "again", "verdict"), [
    (_e(2.0, 0.2, 4.4), _e(3.0, 0.1, 5.0), ch14.REPLICATED),
    (_e(-2.0, -4.4, -0.2), _e(-1.0, -2.0, -0.5), ch14.REPLICATED),
    (_e(2.0, 0.2, 4.4), _e(-3.0, -5.0, -0.1), ch14.REVERSED),
    (_e(-2.0, -4.4, -0.2), _e(1.0, 0.5, 2.0), ch14.REVERSED),
    (_e(2.0, 0.2, 4.4), _e(1.0, -0.5, 2.0), ch14.SAME_SIGN),
    (_e(2.0, 0.2, 4.4), _e(-1.0, -2.0, 0.5), ch14.OTHER_SIGN),
    (_e(-2.0, -4.4, -0.2), _e(-1.0, -2.0, 0.5), ch14.SAME_SIGN),
    (_e(2.0, 0.2, 4.4), _e(0.0, 0.0, 1.0), ch14.OTHER_SIGN),  # touching 0, no sign
    (_e(2.0, 0.2, 4.4), _e(math.nan, math.nan, math.nan), ch14.OTHER_SIGN),
    (_e(2.0, 0.0, 4.4), _e(3.0, 1.0, 5.0), ch14.NOT_DECIDED),  # touching 0 decides nothing
    (_e(0.5, -1.0, 2.0), _e(3.0, 1.0, 5.0), ch14.NOT_DECIDED),
    (_e(math.nan, math.nan, math.nan), _e(3.0, 1.0, 5.0), ch14.NOT_DECIDED),
])
def test_an_effect_replicates_only_when_decided_again_on_the_same_side(book, again, verdict):
    assert ch14.replication(book, again) == verdict


SMOKE = load_profile("smoke")

RECORD = {"date": "2026-12-06", "commit": "abc", "profile": "demo", "book_seed": 0,
          "replicate_seed": 7,
          "effects": [
              {"chapter": "07", "comparison": "gt - dis", "book": _e(2.2, 0.2, 4.4),
               "replicate": _e(4.0, 1.0, 7.0)},
              {"chapter": "07", "comparison": "dis - farneback", "book": _e(6.0, 3.0, 9.0),
               "replicate": _e(1.0, -1.0, 3.0)},
              {"chapter": "10", "comparison": "a - b", "book": _e(-5.0, -8.0, -2.0),
               "replicate": _e(3.0, 1.0, 5.0)},
              {"chapter": "13", "comparison": "cost of pull", "book": _e(6.2, 2.7, 10.2),
               "replicate": _e(5.0, 1.0, 9.0)},
              {"chapter": "11", "comparison": "c - d", "book": _e(0.4, -1.0, 1.8),
               "replicate": _e(math.nan, math.nan, math.nan)}],
          "table3": [{"method": "ResNet18 on dis flow", "book": "85.9 (83.1-88.4)",
                      "replicate": "81.8 (78.0-85.0)"}]}


def test_the_replication_table_has_both_worlds_and_the_verdict_per_effect():
    t = ch14.replication_table(RECORD)
    assert list(t.columns) == ["chapter", "comparison", "book, seed 0", "replication, seed 7",
                               "replicates?"]
    assert list(t["replicates?"]) == [ch14.REPLICATED, ch14.SAME_SIGN, ch14.REVERSED,
                                      ch14.REPLICATED, ch14.NOT_DECIDED]
    assert t.loc[0, "book, seed 0"] == "+2.2 (0.2 to 4.4)"
    assert t.loc[3, "replication, seed 7"] == "+5.0 (1.0 to 9.0) /px"  # chapter 13's unit
    assert t.loc[4, "replication, seed 7"] == "undefined"
    t3 = ch14.table3_replication(RECORD)
    assert t3.iloc[0].tolist() == ["ResNet18 on dis flow", "85.9 (83.1-88.4)",
                                   "81.8 (78.0-85.0)"]
    words = ch14.replication_words(RECORD, SMOKE)
    assert "master seed 7 instead of 0" in words and "commit abc" in words
    assert ("Of the 4 effects the book's world decided, 2 replicated (decided again, same "
            "side), 1 kept their sign without deciding, 0 turned sign without deciding and "
            "1 reversed.") in words
    assert "This build is the smoke profile" in words  # the record is the demo's
    assert "No replication is recorded yet" in ch14.replication_words(None, SMOKE)


def test_the_committed_record_names_its_world_and_commit():
    rec = ch14.replication_record()
    assert rec is not None, f"{ch14.REPLICATION_RECORD} is not committed"
    assert rec["replicate_seed"] != rec["book_seed"]
    assert rec["profile"] == "demo" and len(rec["commit"]) >= 7
    chapters = {e["chapter"] for e in rec["effects"]}
    assert {"07", "10", "11", "13"} <= chapters, chapters
    assert len(rec["table3"]) >= 4


def test_the_replication_refuses_the_books_own_seed_before_building(capsys, tmp_path):
    rc = replicate.main(["--profile", "smoke", "--seed", "0", "--set",
                         f"run_dir={tmp_path / 'runs'}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--seed 0 is the book's own master seed" in err[0]
    assert not (tmp_path / "runs").exists()


def test_the_replication_runs_in_its_own_folder_with_only_the_seed_changed():
    over = replicate.replicate_overrides(SMOKE, 5)
    assert over == {"seed": 5, "run_dir": f"{SMOKE.run_dir}-replicate-5"}


def test_a_record_of_one_run_against_itself_replicates_every_decided_effect(smoke_built):
    """The record's assembly on the built smoke study: every effect of chapter 14's table
    and chapter 13's costs, equal in both columns, so each decided one replicates."""
    rec = replicate.record(smoke_built, smoke_built)
    eff = ch14.effects(smoke_built)
    got = [(e["chapter"], e["comparison"]) for e in rec["effects"]]
    assert got[:len(eff)] == list(zip(eff["chapter"], eff["comparison"], strict=True))
    assert {c for c, _ in got[len(eff):]} == {"13"} and len(got) > len(eff)
    first = rec["effects"][0]
    assert first["book"]["delta"] == pytest.approx(eff["ΔF1 (points)"].iloc[0])
    assert first["book"]["low"] == pytest.approx(eff["low"].iloc[0])
    for e in rec["effects"]:
        assert e["book"] == e["replicate"]
        assert ch14.replication(e["book"], e["replicate"]) in (ch14.REPLICATED,
                                                              ch14.NOT_DECIDED)
    assert [r["method"] for r in rec["table3"]][0] == "ResNet18 on gt flow"
    assert all(r["book"] == r["replicate"] for r in rec["table3"])
