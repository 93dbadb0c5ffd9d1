"""Chapter 14, the book's answers at a glance: every paired effect the chapters report on
the test scenes or Table 4's set, one row each with its interval over scenes and training
seeds and whether it decides (the landing page shows the table and its forest plot).

Reads what chapters 07, 10 and 11 read (their published predictions); computes nothing new.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd

from flowmod.chapters import ch07_evaluation as ch07
from flowmod.chapters import ch10_inputs as ch10
from flowmod.chapters import ch11_all_distances as ch11
from flowmod.chapters import common
from flowmod.chapters.common import committed_record, decided
from flowmod.params import Params

#: The smallest effect that matters (F1 points), as every chapter's verdicts use it.
SMALLEST_EFFECT = common.SMALLEST_EFFECT

#: The question each chapter's paired effects answer (landing-page wording).
QUESTIONS = {
    "07": "Table 3: which flow serves the classifier best, and does the classifier reach "
          "the oracle rule on the same flow?",
    "10": "Does another input than the raw flow help? (test scenes)",
    "11": "Does training on all distances help on Table 4's set?",
}

#: Columns of :func:`effects`.
EFFECT_COLUMNS = ["chapter", "question", "comparison", "ΔF1 (points)", "low", "high",
                  "95% CI, scenes and seeds (points)", "interval counts", "verdict",
                  "p (two-sided)",
                  "Holm, all effects", "scenes"]

#: The family-wise error rate of :func:`holm` (two-sided, as the 95 % intervals).
HOLM_ALPHA = 0.05
#: :data:`HOLM_ALPHA` in percent, as the book states it.
HOLM_PERCENT = 100 * HOLM_ALPHA


def _chapter_tables(params: Params) -> list[tuple[str, pd.DataFrame]]:
    """(chapter, :func:`flowmod.metrics.comparison_table`) of every chapter built in this run."""
    out = [("07", ch07.comparisons(params))]
    if ch10.built(params):
        out.append(("10", ch10.comparisons(params, "test", ch10.rows(params))))
    done = ch11.built(params)
    if done:
        out.append(("11", ch11.comparisons(params, done, "general")))
    return out


def effects(params: Params) -> pd.DataFrame:
    """Every paired effect (F1 points, A - B) with its interval as text and as numbers
    (``low``, ``high``) and its verdict; columns :data:`EFFECT_COLUMNS`."""
    rows = []
    for chapter, table in _chapter_tables(params):
        for (_, r), (lo, hi), p in zip(table.iterrows(), table.attrs["ci_points"],
                                       table.attrs["p_two_sided"], strict=True):
            rows.append({"chapter": chapter, "question": QUESTIONS[chapter],
                         "comparison": r["comparison"], "ΔF1 (points)": r["ΔF1 (points)"],
                         "low": lo, "high": hi,
                         "95% CI, scenes and seeds (points)": r[
                             "95% CI, scenes and seeds (points)"],
                         "interval counts": r.get("interval counts", common.COUNTS_SEEDS),
                         "verdict": r["verdict"],
                         "p (two-sided)": p,
                         "scenes": r["scenes"]})
    out = pd.DataFrame(rows, columns=EFFECT_COLUMNS)
    out["Holm, all effects"] = np.where(holm(out["p (two-sided)"].to_numpy(float)),
                                        "decided", "not decided")
    return out


def holm(p: np.ndarray, alpha: float = HOLM_ALPHA) -> np.ndarray:
    """(m,) bool: which of ``m`` p-values Holm's step-down procedure rejects at family-wise
    error rate ``alpha`` (the k-th smallest against alpha / (m - k + 1), stopping at the
    first that fails); an undefined p-value is never rejected."""
    p = np.where(np.isfinite(p), p, np.inf)
    reject = np.zeros(len(p), dtype=bool)
    for rank, i in enumerate(np.argsort(p, kind="stable")):
        if p[i] > alpha / (len(p) - rank):
            break
        reject[i] = True
    return reject


#: Each question in a few words (the landing page's table, one row per effect).
SHORT = {"07": "Which flow? (Table 3)", "10": "Other inputs?", "11": "All distances?"}


def answers(eff: pd.DataFrame) -> pd.DataFrame:
    """The landing page's table: one row per effect, in the chapters' order: the question
    in a few words (:data:`SHORT`), the comparison, its difference with its interval
    (``[scenes only]`` where an arm was trained once a fold), the verdict, whether it
    survives Holm's correction over all the book's effects, the chapter."""
    rows = []
    for _, r in eff.iterrows():
        rows.append({
            "question": SHORT.get(r["chapter"], r["question"]),
            "comparison (A - B)": r["comparison"],
            "ΔF1, 95 % interval (points)": f"{r['ΔF1 (points)']:+.1f} "
            f"({r['95% CI, scenes and seeds (points)']})"
            + (" [scenes only]" if r.get("interval counts") == common.COUNTS_SCENES else ""),
            "verdict": "decided" if decided(r["verdict"]) else (
                "equivalent" if r["verdict"] == "equivalent" else "inconclusive"),
            "Holm": r["Holm, all effects"], "chapter": r["chapter"]})
    return pd.DataFrame(rows)


def _winner(r: pd.Series) -> str:
    """A decided effect ``A - B`` (an :func:`effects` row) in words, the winner first:
    ``A over B by 2.2 points (0.2 to 4.4)``, the interval turned with it."""
    a, _, b = r["comparison"].partition(" - ")
    d, lo, hi = r["ΔF1 (points)"], r["low"], r["high"]
    if d < 0:
        a, b, d, lo, hi = b, a, -d, -hi, -lo
    return f"{a} over {b} by {d:.1f} points ({lo:.1f} to {hi:.1f})"


def question_words(eff: pd.DataFrame) -> dict[str, str]:
    """One sentence per question of :data:`QUESTIONS` (``answer_<chapter>``): how many of
    its effects are decided, each decided one as ``A over B`` with its difference and
    interval, how many are equivalent and inconclusive; a chapter not built says so."""
    out = {}
    for chapter, question in QUESTIONS.items():
        g = eff[eff["chapter"] == chapter]
        if g.empty:
            out[f"answer_{chapter}"] = f"{question} Not built in this run."
            continue
        dec = g[g["verdict"].map(decided)]
        wins = [_winner(r) for _, r in dec.iterrows()]
        n_eq = int((g["verdict"] == "equivalent").sum())
        words = (f"{question} {len(dec)} of {len(g)} comparisons decided"
                 + (": " + "; ".join(wins) if wins else "")
                 + f". Equivalent: {n_eq}; inconclusive: {len(g) - len(dec) - n_eq}.")
        out[f"answer_{chapter}"] = words
    return out


#: Fewer test scenes than this, or fewer training seeds a fold than :data:`FEW_SEEDS`, and the
#: landing page says its intervals are wide (the demo: 100 scenes, 3 seeds).
FEW_SCENES = 60
FEW_SEEDS = 3


def scope_words(params: Params, eff: pd.DataFrame) -> str:
    """One sentence for the landing page: which profile built this book, on how many test
    scenes and training seeds, and (when few) that its intervals are wide."""
    scenes = int(eff["scenes"].max()) if len(eff) else 0
    seeds = "one training seed" if params.seeds == 1 else f"{params.seeds} training seeds"
    words = (f"This build: the {params.profile} profile, {scenes} test scenes, {seeds} a fold "
             "in Table 3.")
    if scenes < FEW_SCENES or params.seeds < FEW_SEEDS:
        words += (" With this few, the intervals are wide and a point estimate can move by"
                  " several points in a rebuild on another world; read the intervals.")
    return words


# --- the replication on a world no choice has read (benchmarks/replication.json) -------------

#: The dated record of the replication (written by ``make replicate``: :mod:`flowmod.replicate`).
REPLICATION_RECORD = "benchmarks/replication.json"

#: What :func:`replication` says of an effect the book decided, and of one it did not.
REPLICATED, SAME_SIGN, REVERSED, OTHER_SIGN = (
    "replicated", "same sign, not decided", "reversed", "other sign, not decided")
NOT_DECIDED = "not decided in the book"


def replication_record() -> dict[str, Any] | None:
    """The committed record of ``make replicate`` (date, commit, profile, the two seeds, and
    each effect and Table 3 row in both worlds), or None where none is committed."""
    return committed_record(REPLICATION_RECORD)


def _excludes_zero(lo: float, hi: float) -> int:
    """+1 when the interval (lo, hi) lies above 0, -1 below, 0 when it holds 0 or is
    undefined."""
    return 1 if lo > 0 else -1 if hi < 0 else 0


def replication(book: dict[str, float], again: dict[str, float]) -> str:
    """Whether an effect replicates: ``book`` and ``again`` are its estimate and interval
    (``delta``, ``low``, ``high``) in the book's world and in the replication's. An effect
    the book decided (interval excludes 0) is :data:`REPLICATED` when the replication's
    interval excludes 0 on the same side, :data:`REVERSED` when on the other side, else
    :data:`SAME_SIGN` or :data:`OTHER_SIGN` by its estimate's sign (an undefined estimate:
    other sign); one the book did not decide is :data:`NOT_DECIDED`."""
    side = _excludes_zero(book["low"], book["high"])
    if side == 0:
        return NOT_DECIDED
    again_side = _excludes_zero(again["low"], again["high"])
    if again_side:
        return REPLICATED if again_side == side else REVERSED
    return SAME_SIGN if side * again["delta"] > 0 else OTHER_SIGN


def _estimate(r: dict[str, float], unit: str) -> str:
    if not all(math.isfinite(r[k]) for k in ("delta", "low", "high")):
        return "undefined"
    return f"{r['delta']:+.1f} ({r['low']:.1f} to {r['high']:.1f}){unit}"


def replication_table(record: dict[str, Any]) -> pd.DataFrame:
    """One row per effect of the record: chapter, comparison, the estimate with its 95 %
    interval in the book's world and in the replication's (F1 points, or F1 points per px
    for chapter 13's costs), and :func:`replication`."""
    rows = []
    for e in record["effects"]:
        unit = " /px" if e["chapter"] == "13" else ""
        rows.append({"chapter": e["chapter"], "comparison": e["comparison"],
                     f"book, seed {record['book_seed']}": _estimate(e["book"], unit),
                     f"replication, seed {record['replicate_seed']}":
                         _estimate(e["replicate"], unit),
                     "replicates?": replication(e["book"], e["replicate"])})
    return pd.DataFrame(rows)


def table3_replication(record: dict[str, Any]) -> pd.DataFrame:
    """Table 3's F1 (%) with its 95 % interval per row in the two worlds of the record."""
    return pd.DataFrame([{"method": r["method"],
                          f"book, seed {record['book_seed']}": r["book"],
                          f"replication, seed {record['replicate_seed']}": r["replicate"]}
                         for r in record["table3"]])


def replication_words(record: dict[str, Any] | None, params: Params) -> str:
    """What the record says in one paragraph: when and at which commit it ran, on which
    profile and seeds, how many of the effects the book decided replicate, keep their sign
    undecided, or reverse; and whether this build is the record's profile."""
    if record is None:
        return ("No replication is recorded yet (`make replicate` writes "
                f"`{REPLICATION_RECORD}`): read a decided row as this world's answer only.")
    verdicts = [replication(e["book"], e["replicate"]) for e in record["effects"]]
    decided_n = sum(v != NOT_DECIDED for v in verdicts)
    words = (f"`make replicate` ran the whole study again on a world drawn with master seed "
             f"{record['replicate_seed']} instead of {record['book_seed']} ({record['profile']}"
             f" profile, {record['date']}, commit {record['commit']}; no choice of the study "
             f"ever read that world). Of the {decided_n} effects the book's world decided, "
             f"{verdicts.count(REPLICATED)} replicated (decided again, same side), "
             f"{verdicts.count(SAME_SIGN)} kept their sign without deciding, "
             f"{verdicts.count(OTHER_SIGN)} turned sign without deciding and "
             f"{verdicts.count(REVERSED)} reversed.")
    if params.profile != record["profile"]:
        words += (f" This build is the {params.profile} profile, so its own rows above are not"
                  " the record's book column.")
    return words
