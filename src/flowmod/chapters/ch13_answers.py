"""Chapter 13, the book's answers at a glance: every paired effect the chapters report on
the test scenes or Table 4's set, one row each with its interval over scenes and training
seeds and whether it decides (the landing page shows the table and its forest plot).

Reads what chapters 07, 10 and 11 read (their published predictions); computes nothing new.
"""

from __future__ import annotations

import pandas as pd

from flowmod.chapters import ch07_evaluation as ch07
from flowmod.chapters import ch10_inputs as ch10
from flowmod.chapters import ch11_all_distances as ch11
from flowmod.chapters import common
from flowmod.chapters.common import decided, verdict_words
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
                  "95% CI, scenes and seeds (points)", "verdict", "scenes"]


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
        for (_, r), (lo, hi) in zip(table.iterrows(), table.attrs["ci_points"], strict=True):
            rows.append({"chapter": chapter, "question": QUESTIONS[chapter],
                         "comparison": r["comparison"], "ΔF1 (points)": r["ΔF1 (points)"],
                         "low": lo, "high": hi,
                         "95% CI, scenes and seeds (points)": r[
                             "95% CI, scenes and seeds (points)"],
                         "verdict": r["verdict"], "scenes": r["scenes"]})
    return pd.DataFrame(rows, columns=EFFECT_COLUMNS)


def answers(eff: pd.DataFrame) -> pd.DataFrame:
    """The landing page's table: one row per question, its effects in words, one line each
    (``name: +1.2 (-0.5 to 2.9), decided``, joined by HTML line breaks), the share decided,
    the chapter."""
    out = []
    for chapter, g in eff.groupby("chapter", sort=True):
        parts = [f"{r['comparison']}: {r['ΔF1 (points)']:+.1f} "
                 f"({r['95% CI, scenes and seeds (points)']})"
                 + verdict_words(r["verdict"])
                 for _, r in g.iterrows()]
        out.append({"question": g["question"].iloc[0],
                    "answer (ΔF1 points, 95 % interval over scenes and seeds)": "<br>".join(parts),
                    "decided": f"{int(g['verdict'].map(decided).sum())} of {len(g)}",
                    "chapter": chapter})
    return pd.DataFrame(out)


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
