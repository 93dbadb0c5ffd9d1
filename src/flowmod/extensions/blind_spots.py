"""Beyond the paper: what flow cannot see (the geometry of a vehicle's motion seen from the
camera, F1 and recall broken down by it, and the image signal that motion produces).

A vehicle's velocity splits into a *radial* part, along the line of sight from the camera
(it changes the vehicle's distance, so only the size of its box changes in the image) and a
*lateral* part, across it (the box moves across the image). Over a keyframe gap of ``dt``
seconds, at distance ``Z`` metres, with focal length ``f`` px:

* lateral speed ``v``: the box moves by about ``f v dt / Z`` px;
* radial speed ``v`` on a vehicle ``W`` m wide: its width changes by about
  ``f W (1 / (Z - v dt) - 1 / Z)`` px, i.e. ``f W v dt / Z**2`` to first order.

At 50 m and 2 m/s that is 25 px against 1 px: slow radial movers are where flow is blind.
"""

from __future__ import annotations

from itertools import pairwise
from typing import Any

import numpy as np
import pandas as pd

from flowmod.metrics import MIN_SCENES, group_mean_bootstrap, interval, scene_draws
from flowmod.metrics import breakdown as _breakdown


def motion_geometry(objects: pd.DataFrame, pairs: pd.DataFrame) -> pd.DataFrame:
    """Objects with the geometry of their motion seen from frame 1's camera: ``radial_speed``
    and ``lateral_speed`` (m/s, ground plane; radial positive away from the camera),
    ``motion_angle`` (degrees between the velocity and the line of sight, 0 = straight
    away or towards, 90 = across) and ``box_width_px``."""
    cam = pairs.set_index("pair_id")["cam2global_1"].map(
        lambda m: np.asarray(m, dtype=np.float64).reshape(4, 4)[:3, 3])
    origin = np.stack(objects["pair_id"].map(cam).to_numpy())
    sight = objects[["center_x", "center_y"]].to_numpy(np.float64) - origin[:, :2]
    sight /= np.maximum(np.linalg.norm(sight, axis=1, keepdims=True), 1e-9)
    v = objects[["vx", "vy"]].to_numpy(np.float64)
    radial = (v * sight).sum(axis=1)
    lateral = np.abs(v[:, 0] * sight[:, 1] - v[:, 1] * sight[:, 0])
    angle = np.degrees(np.arctan2(lateral, np.abs(radial)))
    return objects.assign(radial_speed=radial, lateral_speed=lateral, motion_angle=angle,
                          box_width_px=(objects["xmax"] - objects["xmin"]).to_numpy())


#: Movers whose motion is within this angle (deg) of the line of sight count as radial.
RADIAL_MAX_ANGLE = 30.0
#: The ``by`` of :func:`blind_spots`' speed bins over all vehicles, and over the still ones
#: and the movers along the line of sight only.
SPEED, RADIAL_SPEED = "speed (m/s)", f"speed (m/s), movers within {RADIAL_MAX_ANGLE:g} deg " \
    "of the line of sight"
SPEED_BINS = [0, 2, 3, 5, 10, 40]


def blind_spots(df: pd.DataFrame, probs: np.ndarray, groups: np.ndarray) -> pd.DataFrame:
    """F1 and recall of the moving vehicles by the angle of their motion to the line of
    sight, their speed (of all; of the radial movers, :data:`RADIAL_SPEED`), distance and
    box size (scene-level intervals, counts): one table with a ``by`` column. ``df``:
    predictions with the columns of :func:`motion_geometry`; probs: (S, N)."""
    specs = [("motion_angle", [0, 15, 30, 60, 90.01], "angle to the line of sight (deg)"),
             ("speed", SPEED_BINS, SPEED),
             ("distance", [30, 40, 50, 60, 70.01], "distance (m)"),
             ("box_width_px", [0, 20, 40, 80, 2000], "box width (px)")]
    label = df["label"].to_numpy()
    radial = (label == 0) | (df["motion_angle"].to_numpy() < RADIAL_MAX_ANGLE)
    probs, groups = np.asarray(probs), np.asarray(groups)
    out = []
    for col, bins, name in [*specs, ("speed", SPEED_BINS, RADIAL_SPEED)]:
        k = radial if name == RADIAL_SPEED else np.ones(len(df), bool)
        t = _breakdown(df[k], df["label"][k], probs[:, k], by=col, bins=bins, groups=groups[k])
        out.append(t.rename(columns={f"{col}_bin": "bin"}).assign(by=name))
    cols = ["by", "bin", "n", "n_moving", "precision", "recall", "f1", "ci_lo", "ci_hi",
            "scenes"]
    return pd.concat(out, ignore_index=True)[cols]


def physical_signal(focal_px: float, dt_s: float, distances_m=(30.0, 50.0, 70.0),
                    speed_m_s: float = 2.0, width_m: float = 1.9,
                    flow_scale: float = 1.0) -> pd.DataFrame:
    """The image signal of a ``speed_m_s`` mover over ``dt_s`` at each distance: lateral
    displacement of its box (px) and the change of its box width when it moves radially
    (px, away from the camera), in full-image pixels and at ``flow_scale``."""
    rows = []
    for z in distances_m:
        d = speed_m_s * dt_s
        lateral = focal_px * d / z
        radial = focal_px * width_m * (1 / z - 1 / (z + d))
        rows.append({"distance (m)": z, "lateral shift (px)": lateral,
                     "radial: width change (px)": radial,
                     f"lateral at flow_scale {flow_scale:g} (px)": lateral * flow_scale,
                     f"radial at flow_scale {flow_scale:g} (px)": radial * flow_scale})
    return pd.DataFrame(rows)


def recall_slow_and_fast(blind: pd.DataFrame, by: str = RADIAL_SPEED) -> tuple[float, float]:
    """Recall of the moving vehicles just above the threshold (2-3 m/s) and of those at 5
    m/s or more (NaN where a bin holds no mover), from a :func:`blind_spots` table; ``by``:
    of the movers along the line of sight (:data:`RADIAL_SPEED`) or of all (:data:`SPEED`)."""
    a = blind[blind["by"] == by].set_index("bin")

    def rec(bins: tuple[str, ...]) -> float:
        rows = a[a.index.isin(bins) & (a["n_moving"] > 0)]
        if not len(rows):
            return float("nan")
        return float((rows["recall"] * rows["n_moving"]).sum() / rows["n_moving"].sum())

    return rec(("[2, 3)",)), rec(("[5, 10)", "[10, 40)"))


#: :func:`speed_angle_table`'s bins: the angle of the motion to the line of sight (deg) and
#: the speed of the movers (m/s, from the threshold up).
ANGLE_BINS, MOVER_SPEED_BINS = [0.0, 30.0, 60.0, 90.01], [2.0, 3.0, 5.0, 40.0]
#: Fewer movers than this in a cell, and its recalls are not compared in words.
MIN_MOVERS = 100


def _bin_names(edges: list[float]) -> list[str]:
    """"lo-hi" of consecutive edges (the angle's last edge, 90.01, named 90)."""
    return [f"{a:g}-{90.0 if b == 90.01 else b:g}" for a, b in pairwise(edges)]


def in_cell(df: pd.DataFrame, angle: tuple[float, float], speed: tuple[float, float]
             ) -> np.ndarray:
    """(N,) the movers whose motion angle (deg) and speed (m/s) each lie in ``[lo, hi)``."""
    a, s = df["motion_angle"].to_numpy(), df["speed"].to_numpy()
    return ((df["label"].to_numpy() == 1) & (a >= angle[0]) & (a < angle[1])
            & (s >= speed[0]) & (s < speed[1]))


def _hits(probs: np.ndarray, rule: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per mover of ``k``: the share of training seeds whose classifier found it (``probs``
    (S, N)) and the oracle rule's hit (``rule`` (N,)), both 0-1."""
    probs = np.atleast_2d(np.asarray(probs, float))
    return (probs[:, k] > 0.5).mean(axis=0), (np.asarray(rule, float)[k] > 0.5).astype(float)


def speed_angle_table(df: pd.DataFrame, probs: np.ndarray, rule: np.ndarray) -> pd.DataFrame:
    """Recall of the moving vehicles by the angle of their motion to the line of sight
    (:data:`ANGLE_BINS`) and by speed (:data:`MOVER_SPEED_BINS`), for the classifier
    (``probs`` (S, N): the mean over training seeds) beside the oracle rule on the same flow
    (``rule`` (N,): its 0/1 call; the rule reads the annotated 3D boxes). ``df``:
    :func:`motion_geometry` rows with ``label``, ``speed`` (m/s) and ``scene``. One row per
    cell with movers: the movers, their scenes, both recalls (%)."""
    rows = []
    for a_name, angle in zip(_bin_names(ANGLE_BINS), pairwise(ANGLE_BINS), strict=True):
        for s_name, speed in zip(_bin_names(MOVER_SPEED_BINS), pairwise(MOVER_SPEED_BINS),
                                 strict=True):
            k = in_cell(df, angle, speed)
            if not k.any():
                continue
            clf, hit = _hits(probs, rule, k)
            rows.append({"angle to the line of sight (deg)": a_name, "speed (m/s)": s_name,
                         "movers": int(k.sum()), "scenes": int(df["scene"][k].nunique()),
                         "classifier recall (%)": round(100 * float(clf.mean()), 1),
                         "oracle rule recall (%)": round(100 * float(hit.mean()), 1)})
    return pd.DataFrame(rows, columns=["angle to the line of sight (deg)", "speed (m/s)",
                                       "movers", "scenes", "classifier recall (%)",
                                       "oracle rule recall (%)"])


def cell_effect(df: pd.DataFrame, probs: np.ndarray, rule: np.ndarray, angle: tuple[float, float],
                speed: tuple[float, float], seed: int = 0) -> dict[str, Any]:
    """The movers of one angle x speed cell (deg, m/s; lower bounds included): the cell,
    their number and scenes, the classifier's recall (mean over seeds), the oracle rule's,
    and the rule minus the classifier (points) with its 95 % interval over scenes (per
    mover: the rule's hit minus the share of seeds that found it;
    :func:`flowmod.metrics.group_mean_bootstrap`)."""
    k = in_cell(df, angle, speed)
    clf, hit = _hits(probs, rule, k)
    lo, hi = interval(group_mean_bootstrap(hit - clf, df["scene"].to_numpy()[k], seed=seed))
    return {"angle": tuple(angle), "speed": tuple(speed),
            "movers": int(k.sum()), "scenes": int(df["scene"][k].nunique()),
            "classifier": 100 * float(clf.mean()) if k.any() else float("nan"),
            "rule": 100 * float(hit.mean()) if k.any() else float("nan"),
            "rule_minus_classifier": 100 * float((hit - clf).mean()) if k.any() else float("nan"),
            "ci": (100 * lo, 100 * hi)}


def _cell_words(e: dict[str, Any]) -> str:
    """``at 2-3 m/s within 30 degrees of the line of sight``, from a :func:`cell_effect`."""
    (a0, a1), (s0, s1) = e["angle"], e["speed"]
    where = f"within {a1:g} degrees of" if a0 == 0 else f"at {a0:g}-{a1:g} degrees to"
    return f"at {s0:g}-{s1:g} m/s {where} the line of sight"


def slow_radial_words(e: dict[str, Any], method: str, far_clf: float | None = None,
                      far_rule: float | None = None) -> str:
    """:func:`cell_effect` of the slow movers along the line of sight in words, at each
    one's own operating point; with their false-alarm rates (%, ``far_clf``, ``far_rule``)
    said beside, because recalls at different false-alarm rates are not comparable (the
    verdict is :func:`matched_words`')."""
    if not e["movers"]:
        return f"This run has no mover {_cell_words(e)}."
    lo, hi = e["ci"]
    text = (f"Of the {e['movers']} movers {_cell_words(e)} "
            f"({e['scenes']} scenes), the classifier on {method} flow recalls "
            f"{e['classifier']:.1f} % and the oracle rule on the same flow "
            f"{e['rule']:.1f} % at their own operating points (rule minus classifier "
            f"{e['rule_minus_classifier']:+.1f} points, 95 % interval over scenes {lo:+.1f} "
            f"to {hi:+.1f}" + (f", {e['scenes']} scenes: too few" if e["scenes"] < MIN_SCENES
                               else "") + ")")
    if far_clf is None or far_rule is None:
        return text + "."
    return text + (f"; but the rule calls {far_rule:.1f} % of the still vehicles moving and "
                   f"the classifier {far_clf:.1f} %, so these two recalls are not comparable.")


def crossing_words(table: pd.DataFrame) -> str:
    """Whether this run's movers cross the line of sight often enough to compare directions
    (:data:`MIN_MOVERS` at 60-90 degrees), in words, from a :func:`speed_angle_table`."""
    last = _bin_names(ANGLE_BINS)[-1]
    cross = table[table["angle to the line of sight (deg)"] == last]
    n = int(cross["movers"].sum())
    if n >= MIN_MOVERS:
        return (f"{n} movers cross the line of sight at {last} degrees: the table compares "
                "directions at equal speed.")
    return (f"Only {n} of the movers cross the line of sight at {last} degrees (fewer than "
            f"{MIN_MOVERS}): too few to say how direction itself matters; the table compares "
            "speeds within the movers along the line of sight.")


def rule_calls(df: pd.DataFrame, baseline: pd.DataFrame) -> np.ndarray:
    """(N,) the oracle rule's 0/1 call on each row of ``df`` (by ``ann_token``) from its
    published predictions (``baseline``: the evaluate node's ``baseline`` table); NaN where
    the rule has no row."""
    return baseline.set_index("ann_token")["prob"].reindex(df["ann_token"]).to_numpy(float)


# --- matched operating points ---------------------------------------------------------------


def false_alarm_rate(calls: np.ndarray, labels: np.ndarray,
                     weights: np.ndarray | None = None) -> float:
    """Share (0-1) of the still vehicles (``labels`` 0) that ``calls`` (0/1) call moving,
    each object weighted by ``weights`` (None: 1); NaN without a still vehicle."""
    still = np.asarray(labels) == 0
    w = np.ones(len(still)) if weights is None else np.asarray(weights, float)
    total = w[still].sum()
    return float((w[still] * (np.asarray(calls, float)[still] > 0.5)).sum() / total) if total \
        else float("nan")


def threshold_at(scores: np.ndarray, labels: np.ndarray, far: float,
                 weights: np.ndarray | None = None) -> float:
    """The lowest score threshold whose calls (``score > threshold``) give the still
    vehicles a false-alarm rate of at most ``far`` (0-1): the highest-scoring stills are the
    false alarms, and the threshold sits on the highest still left out, so the recall at
    that rate is the most any threshold allows (the ROC curve's, Neyman-Pearson's)."""
    still = np.asarray(labels) == 0
    sc = np.asarray(scores, float)[still]
    w = np.ones(len(sc)) if weights is None else np.asarray(weights, float)[still]
    order = np.argsort(-sc, kind="stable")
    share = np.cumsum(w[order]) / max(w.sum(), 1e-12)
    k = int(np.searchsorted(share, far + 1e-12, side="right"))  # stills allowed above it
    return float(sc[order][k]) if k < len(sc) else float("-inf")


def _recall(scores: np.ndarray, cell: np.ndarray, t: float, w: np.ndarray) -> float:
    """Weighted share of the movers of ``cell`` whose score exceeds ``t``."""
    total = w[cell].sum()
    return float((w[cell] * (scores[cell] > t)).sum() / total) if total else float("nan")


def matched_effect(df: pd.DataFrame, clf_score: np.ndarray, rule_score: np.ndarray,
                   angle: tuple[float, float], speed: tuple[float, float], far: float,
                   seed: int = 0, n: int = 2000) -> dict[str, Any]:
    """The movers of one angle x speed cell recalled by the classifier (``clf_score``: its
    seed-mean probability) and by the oracle rule (``rule_score``: its residual speed, m/s)
    when each calls the same share ``far`` (0-1) of all still test vehicles moving: each
    threshold set on the stills, the recalls (%) and the rule minus the classifier (points)
    with its 95 % interval over scenes (each replicate draws the scenes and sets both
    thresholds again on its stills)."""
    k = in_cell(df, angle, speed)
    labels = df["label"].to_numpy()
    clf, rule = np.asarray(clf_score, float), np.asarray(rule_score, float)

    def recalls(w: np.ndarray) -> tuple[float, float]:
        return (_recall(clf, k, threshold_at(clf, labels, far, w), w),
                _recall(rule, k, threshold_at(rule, labels, far, w), w))

    c, r = recalls(np.ones(len(df)))
    scenes, idx = np.unique(df["scene"].to_numpy(), return_inverse=True)
    draws = scene_draws(len(scenes), n, seed)
    diffs = np.array([np.subtract(*recalls(d[idx])[::-1]) for d in draws])
    lo, hi = interval(diffs)
    return {"angle": tuple(angle), "speed": tuple(speed), "far": 100 * far,
            "movers": int(k.sum()), "scenes": int(df["scene"][k].nunique()),
            "classifier": 100 * c, "rule": 100 * r, "rule_minus_classifier": 100 * (r - c),
            "ci": (100 * lo, 100 * hi)}


def matched_words(own: dict[str, Any], at_rule: dict[str, Any], at_clf: dict[str, Any],
                  method: str) -> str:
    """Chapter 09's answer on one cell: the recalls at each one's own operating point are not
    comparable when their false-alarm rates differ, so the verdict comes from the two
    matched comparisons (:func:`matched_effect` at the rule's and at the classifier's
    false-alarm rate): the flow carries motion the classifier loses only if the rule wins at
    both; the classifier reads the flow as well as the rule if neither interval excludes 0
    or the classifier wins at both."""
    if not own["movers"]:
        return f"This run has no mover {_cell_words(own)}."
    parts = []
    for e, whose in ((at_rule, "the rule's"), (at_clf, "the classifier's")):
        lo, hi = e["ci"]
        parts.append(f"at {whose} false-alarm rate ({e['far']:.1f} % of still vehicles called "
                     f"moving) the classifier recalls {e['classifier']:.1f} % and the rule "
                     f"{e['rule']:.1f} % (rule minus classifier "
                     f"{e['rule_minus_classifier']:+.1f} points, 95 % interval over scenes "
                     f"{lo:+.1f} to {hi:+.1f})")
    wins = [e["ci"][0] > 0 for e in (at_rule, at_clf)]
    loses = [e["ci"][1] < 0 for e in (at_rule, at_clf)]
    if all(wins):
        end = ("the rule finds movers the classifier misses at either rate: the slow radial "
               "motion is in the flow and the classifier loses part of it.")
    elif any(wins):
        end = ("the rule wins at one rate only: whether the classifier loses motion the flow "
               "carries depends on the operating point.")
    elif all(loses):
        end = "the classifier finds more of them than the rule at either rate."
    else:
        end = ("at equal false-alarm rates these scenes do not tell the two apart (neither "
               "interval excludes 0).")
    small = f" ({own['scenes']} scenes: too few)" if own["scenes"] < MIN_SCENES else ""
    return (f"Compared at equal false-alarm rates on {method} flow, the {own['movers']} "
            f"movers {_cell_words(own)}{small}: " + "; ".join(parts) + "; " + end)
