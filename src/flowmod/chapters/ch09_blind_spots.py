"""Chapter 09's backend: where the classifiers are blind, and whether the flow or the
classifier loses the slow movers along the line of sight, the classifier and the oracle
rule compared at equal false-alarm rates (:func:`flowmod.extensions.blind_spots.matched_effect`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from flowmod import pipeline, world
from flowmod.chapters.common import results
from flowmod.dag import Node
from flowmod.evaluate import seed_probs
from flowmod.extensions import blind_spots
from flowmod.flow.accuracy import read_accuracy
from flowmod.metrics import ci_text, group_mean_bootstrap, interval
from flowmod.params import Params
from flowmod.select import Selection

#: The columns of the moving test vehicles' summary.
MOTION_COLUMNS = ["distance", "speed", "radial_speed", "lateral_speed", "motion_angle"]
#: The distance (m) of the signal table's glued radial width change: the band's middle.
SIGNAL_DISTANCE = 50.0


def main_method(params: Params) -> str:
    """The chapter's main method: the first flow method that is not ``gt`` (or ``gt``)."""
    return next((m for m in params.flow_methods if m != "gt"), params.flow_methods[0])


def shown_methods(params: Params) -> list[str]:
    """The methods whose classifiers the chapter breaks down: ``gt`` and the main one."""
    return [m for m in params.flow_methods if m in ("gt", main_method(params))]


def test_geometry(params: Params, sel: Selection) -> dict[str, pd.DataFrame]:
    """``{method: test predictions}`` of :func:`shown_methods`, each object with the geometry
    of its motion (:func:`~flowmod.extensions.blind_spots.motion_geometry`)."""
    return {m: blind_spots.motion_geometry(results(params, m)[0], sel.pairs)
            for m in shown_methods(params)}


def moving_summary(df: pd.DataFrame) -> pd.DataFrame:
    """Count, mean, spread and quantiles of :data:`MOTION_COLUMNS` over the movers of
    ``df``, one row per column."""
    moving = df[df["label"] == 1]
    return moving[MOTION_COLUMNS].describe().T.reset_index(names="moving vehicles")


def blind_tables(preds: dict[str, pd.DataFrame]) -> dict[str, pd.DataFrame]:
    """Per method, F1 and recall by angle, speed, distance and box width
    (:func:`~flowmod.extensions.blind_spots.blind_spots`, scenes as the resampled unit)."""
    return {m: blind_spots.blind_spots(df, seed_probs(df), df["scene"].to_numpy())
            for m, df in preds.items()}


def blind_table(blind: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """:func:`blind_tables` as one table, a ``method`` column first."""
    return pd.concat(blind, names=["method"]).reset_index(level=0)


def recall_numbers(blind: dict[str, pd.DataFrame], main: str) -> dict[str, float]:
    """The glued recalls (%) of the slow (2-3 m/s) and fast radial movers of every method
    (``recall_slow_<m>``, ``recall_fast_<m>``) and of the main one (``headline_recall_*``)."""
    out = {}
    for m, t in blind.items():
        slow, fast = blind_spots.recall_slow_and_fast(t)
        for key, value in (("slow", slow), ("fast", fast)):
            out[f"recall_{key}_{m}"] = round(100 * float(value), 1)
            if m == main:
                out[f"headline_recall_{key}"] = round(100 * float(value), 1)
    return out


#: The speeds (m/s) of the slow and the fast radial movers, as
#: :func:`~flowmod.extensions.blind_spots.recall_slow_and_fast` bins them.
SLOW, FAST = (2.0, 3.0), (5.0, 40.0)


def recall_interval(df: pd.DataFrame, speeds: tuple[float, float], seed: int = 0
                    ) -> tuple[float, float, int]:
    """(lo, hi) 95 % interval over scenes of the recall (a fraction) of the radial movers
    of ``df`` (motion within ``RADIAL_MAX_ANGLE`` of the line of sight) with speed in
    [lo, hi) m/s, each mover's hit the share of the training seeds that call it moving
    (whole scenes resampled, the seeds' calls kept as they are), and the scenes it
    resamples; NaN without such a mover."""
    k = ((df["label"] == 1) & (df["motion_angle"] < blind_spots.RADIAL_MAX_ANGLE)
         & (df["speed"] >= speeds[0]) & (df["speed"] < speeds[1])).to_numpy()
    hits = (seed_probs(df)[:, k] > 0.5).mean(axis=0)
    scenes = df["scene"].to_numpy()[k]
    lo, hi = interval(group_mean_bootstrap(hits, scenes, seed=seed))
    return lo, hi, int(len(np.unique(scenes)))


def recall_intervals(df: pd.DataFrame, seed: int = 0) -> dict[str, str]:
    """The glued intervals of the main method's slow and fast radial recalls
    (``headline_recall_slow_ci``, ``headline_recall_fast_ci``: "lo-hi" %, over scenes,
    flagged where too few)."""
    out = {}
    for key, speeds in (("slow", SLOW), ("fast", FAST)):
        lo, hi, n = recall_interval(df, speeds, seed)
        out[f"headline_recall_{key}_ci"] = ci_text((lo, hi), n)
    return out


def speed_angle(df: pd.DataFrame, baseline: pd.DataFrame) -> pd.DataFrame:
    """Recall by angle and speed of the classifier (mean over seeds) beside the oracle rule
    (``baseline``: its published predictions), :func:`~flowmod.extensions.blind_spots.speed_angle_table`."""
    return blind_spots.speed_angle_table(df, seed_probs(df),
                                         blind_spots.rule_calls(df, baseline))


def signal_table(params: Params, pairs: pd.DataFrame) -> pd.DataFrame:
    """The image signal of a slow mover (:func:`~flowmod.extensions.blind_spots.physical_signal`)
    at the keyframe pairs' median focal length (px) and time gap (s), and at ``flow_scale``."""
    key = pairs[pairs["set"] == "keyframe"]
    focal = float(np.median([k[0] for k in key["intrinsic"]]))  # f_x
    dt = float(np.median(key["timestamp_2"] - key["timestamp_1"])) / 1e6  # us -> s
    return blind_spots.physical_signal(focal, dt, flow_scale=params.flow_scale)


def radial_px(signal: pd.DataFrame, distance: float = SIGNAL_DISTANCE) -> float:
    """The radial mover's box width change (px, full resolution) at ``distance`` (m)."""
    row = signal[signal["distance (m)"] == distance]
    return round(float(row["radial: width change (px)"].iloc[0]), 2)


def far_flow_error(params: Params) -> pd.DataFrame | None:
    """:func:`far_box_error` of chapter 03's ``flowcheck`` node (:mod:`flowmod.flow.accuracy`);
    None off the synthetic world."""
    if not world.is_synthetic(params.dataroot_path, params.version):
        return None
    return far_box_error(read_accuracy(pipeline.published(params, Node("flowcheck"))))


def far_box_error(rows: pd.DataFrame) -> pd.DataFrame:
    """Each method's mean end-point error (px) and Fl-all (%) inside the far boxes of the
    keyframe pairs of ``rows`` (the ``flowcheck`` node's) that have a valid pixel in one, in
    the methods' order."""
    far = rows[rows["set"] == "keyframe"].dropna(subset=["epe_box"])
    out = far.groupby("method", sort=False)[["epe_box", "fl_box"]].mean().reset_index()
    return out.rename(columns={"epe_box": "EPE boxes (px)", "fl_box": "Fl-all boxes (%)"})


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
