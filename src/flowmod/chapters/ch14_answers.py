"""Chapter 14, the book's answers at a glance: every paired effect the chapters report on
the test scenes or Table 4's set, one row each with its interval over scenes and training
seeds and whether it decides (the landing page shows the table and its forest plot).

Reads what chapters 07, 10 and 11 read (their published predictions); computes nothing new.
"""

from __future__ import annotations

import numpy as np
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
        for (_, r), (lo, hi) in zip(table.iterrows(), table.attrs["ci_points"], strict=True):
            rows.append({"chapter": chapter, "question": QUESTIONS[chapter],
                         "comparison": r["comparison"], "ΔF1 (points)": r["ΔF1 (points)"],
                         "low": lo, "high": hi,
                         "95% CI, scenes and seeds (points)": r[
                             "95% CI, scenes and seeds (points)"],
                         "interval counts": r.get("interval counts", common.COUNTS_SEEDS),
                         "verdict": r["verdict"],
                         "p (two-sided)": two_sided(r["replicates with A <= B (%)"] / 100),
                         "scenes": r["scenes"]})
    out = pd.DataFrame(rows, columns=EFFECT_COLUMNS)
    out["Holm, all effects"] = np.where(holm(out["p (two-sided)"].to_numpy(float)),
                                        "decided", "not decided")
    return out


def two_sided(share: float) -> float:
    """The bootstrap's two-sided p-value from the share of its replicates with A <= B:
    2 min(share, 1 - share), at most 1 (NaN stays NaN)."""
    return float(min(1.0, 2 * min(share, 1 - share))) if np.isfinite(share) else float("nan")


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


def answers(eff: pd.DataFrame) -> pd.DataFrame:
    """The landing page's table: one row per question, its effects in words, one line each
    (``name: +1.2 (-0.5 to 2.9), decided``, joined by HTML line breaks), the share decided,
    how many stay decided after Holm's correction over all the book's effects, the
    chapter."""
    out = []
    for chapter, g in eff.groupby("chapter", sort=True):
        parts = [f"{r['comparison']}: {r['ΔF1 (points)']:+.1f} "
                 f"({r['95% CI, scenes and seeds (points)']})"
                 + verdict_words(r["verdict"])
                 + (" [scenes only]" if r.get("interval counts") == common.COUNTS_SCENES
                    else "")
                 for _, r in g.iterrows()]
        out.append({"question": g["question"].iloc[0],
                    "answer (ΔF1 points, 95 % interval over scenes and seeds)": "<br>".join(parts),
                    "decided": f"{int(g['verdict'].map(decided).sum())} of {len(g)}",
                    "Holm, all effects": f"{int((g['Holm, all effects'] == 'decided').sum())}",
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
