"""Chapter 09's backend: where the classifiers are blind, and whether the flow or the
classifier loses the slow movers along the line of sight, the classifier and the oracle
rule compared at equal false-alarm rates (:func:`flowmod.extensions.blind_spots.matched_effect`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from flowmod.evaluate import seed_probs
from flowmod.extensions import blind_spots
from flowmod.params import Params

#: The cell chapter 09 answers on: movers within 30 degrees of the line of sight at 2-3 m/s.
SLOW_RADIAL = {"angle": (0.0, blind_spots.RADIAL_MAX_ANGLE), "speed": (2.0, 3.0)}


def rule_margin(df: pd.DataFrame, baseline: pd.DataFrame, summary: dict[str, Any]
                ) -> np.ndarray:
    """(N,) the oracle rule's score on each row of ``df`` (by ``ann_token``): its residual
    speed minus the threshold its fold fitted on its training scenes (m/s; ``summary``: the
    baseline's record, ``thresholds_m_s`` per fold), so that one threshold, 0, gives the
    rule's own calls in every fold and any other moves them all alike."""
    b = baseline.set_index("ann_token").reindex(df["ann_token"])
    thr = np.asarray(summary.get("thresholds_m_s") or [summary["threshold_m_s"]], float)
    fold = b["fold"].to_numpy(int) if len(thr) > 1 else np.zeros(len(b), int)
    return b["residual_speed"].to_numpy(float) - thr[fold]


def slow_radial(params: Params, df: pd.DataFrame, baseline: tuple[pd.DataFrame, dict],
                method: str) -> dict[str, Any]:
    """The slow radial movers of ``df`` (a method's test predictions with
    :func:`~flowmod.extensions.blind_spots.motion_geometry`): the classifier and the rule at
    their own operating points (``own``, :func:`~flowmod.extensions.blind_spots.cell_effect`)
    with each one's false-alarm rate (%), and at each other's (``at_rule``, ``at_clf``;
    ``baseline``: the rule's published predictions and record, :func:`rule_margin`);
    their words (``own_words``, ``matched_words``); the scores for the ROC figure."""
    probs = seed_probs(df)
    calls = blind_spots.rule_calls(df, baseline[0])
    score = rule_margin(df, *baseline)
    clf = np.atleast_2d(probs).mean(axis=0)
    labels = df["label"].to_numpy()
    own = blind_spots.cell_effect(df, probs, calls, seed=params.seed, **SLOW_RADIAL)
    far_rule = blind_spots.false_alarm_rate(calls, labels)
    far_clf = blind_spots.false_alarm_rate(clf > 0.5, labels)
    at = {key: blind_spots.matched_effect(df, clf, score, far=far, seed=params.seed,
                                          **SLOW_RADIAL)
          for key, far in (("at_rule", far_rule), ("at_clf", far_clf))}
    return {"own": own, "far_rule": 100 * far_rule, "far_clf": 100 * far_clf, **at,
            "own_words": blind_spots.slow_radial_words(own, method, 100 * far_clf,
                                                       100 * far_rule),
            "matched_words": blind_spots.matched_words(own, at["at_rule"], at["at_clf"],
                                                       method),
            "scores": {"classifier": clf, "oracle rule": score}, "labels": labels,
            "cell": blind_spots.in_cell(df, **SLOW_RADIAL)}
