"""Chapter 13's backend: which flow errors decide motion detection.

The experiment (stages ``elevels``, ``etrain``, ``eevaluate``,
:mod:`flowmod.extensions.flowerrors`): the exact flow degraded by one kind of error at a
time, at levels matched to the same mean end-point error, and the classifier trained anew on
each; every arm scored paired against the exact-flow arm on the same test objects. Then the
real methods' errors in the same terms (:func:`error_profile`), placed on the experiment's
curves (:func:`predictions`) and set against their Table 3 differences.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from flowmod import pipeline
from flowmod.chapters.common import committed_record, comparison_table, results
from flowmod.crops import BOX_COLUMNS, read_crops
from flowmod.dag import Node
from flowmod.evaluate import paired, seed_probs
from flowmod.extensions.context import read_context
from flowmod.extensions.flowerrors import (
    EXACT,
    KINDS,
    arm_key,
    arms,
    box_masks,
    read_arm,
    read_levels,
)
from flowmod.flow.finetune import FINETUNE_RECORD
from flowmod.metrics import interval, scene_bootstrap
from flowmod.params import Params

#: Each kind of error in words (the chapter's tables and sentences).
KIND_WORDS = {
    "noise": "white noise in the box",
    "resolution": "lost resolution (cell means)",
    "pull": "movers' motion pulled toward the still world",
    "scale": "a global scale error",
    "outliers": "sparse large outliers",
    "ring": "white noise around the box only",
}
#: Movers whose exact box-mean motion is below this (px) give no direction to resolve along.
MIN_MOTION = 0.25


def built(p: Params) -> list[str]:
    """The arm keys (:func:`flowmod.extensions.flowerrors.arm_key`) whose predictions and
    models are current."""
    return [arm_key(*a) for a in arms(p) if pipeline.built(p, Node("eevaluate", "gt", arm_key(*a)))]


def arm_predictions(p: Params, key: str) -> pd.DataFrame:
    """One arm's test predictions (``prob``) with each object's realised end-point error
    in its box and ring (``epe_box``, ``epe_ring``, px)."""
    return read_arm(pipeline.published(p, Node("eevaluate", "gt", key)))


def _level(p: Params, kind: str) -> dict[str, Any]:
    """The ``levels.json`` of a kind's ``elevels`` node."""
    return read_levels(pipeline.published(p, Node("elevels", "gt", kind)))


def _region(kind: str) -> str:
    """Where a kind's error is measured: ``epe_ring`` for the ring kind, else ``epe_box``."""
    return f"epe_{KINDS[kind].region}"


def levels_table(p: Params, done: list[str]) -> pd.DataFrame:
    """Per built arm: the kind, the target error, the level matched on the calibration
    objects (and whether the kind reached it), and the error it realised on the scored
    objects in the box and in the ring (mean and median over objects, px)."""
    rows = []
    for key in done:
        kind, t = key.partition("/")[::2]
        if kind == EXACT:
            continue
        lv, d = _level(p, kind), arm_predictions(p, key)
        rows.append({"kind": KIND_WORDS[kind], "target (px)": lv["targets"][int(t)],
                     "level": round(lv["levels"][int(t)], 3), "of": lv["unit"],
                     "reached": "yes" if lv["reached"][int(t)] else "no (largest level)",
                     "box mean (px)": round(d["epe_box"].mean(), 2),
                     "box median (px)": round(d["epe_box"].median(), 2),
                     "ring mean (px)": round(d["epe_ring"].mean(), 2),
                     "ring median (px)": round(d["epe_ring"].median(), 2)})
    return pd.DataFrame(rows)


def effects(p: Params, done: list[str]) -> pd.DataFrame:
    """Each degraded arm minus the exact-flow arm on the same objects (F1 points, paired
    over scenes: :func:`flowmod.chapters.common.comparison_table`), with the arm's kind,
    target and realised error where its kind is measured (``error (px)``)."""
    if EXACT not in done:
        return pd.DataFrame()
    ref = arm_predictions(p, EXACT)
    rows, meta = {}, []
    for key in done:
        if key == EXACT:
            continue
        kind, t = key.partition("/")[::2]
        d = arm_predictions(p, key)
        rows[f"{KIND_WORDS[kind]}, target {t} - exact flow"] = paired(
            d, ref, f"the {key} arm and the exact-flow arm", seed=p.seed)
        meta.append({"kind": kind, "target": int(t), "error (px)": float(d[_region(kind)].mean()),
                     "delta": 100 * rows[next(reversed(rows))]["delta_f1"]})
    if not rows:
        return pd.DataFrame()
    table = comparison_table(rows)
    return pd.concat([pd.DataFrame(meta), table], axis=1).assign(
        ci_lo=[c[0] for c in table.attrs["ci_points"]],
        ci_hi=[c[1] for c in table.attrs["ci_points"]])


def _replicates(p: Params, key: str) -> np.ndarray:
    """(n,) scene-bootstrap F1 replicates of one arm (the same draws for every arm)."""
    d = arm_predictions(p, key)
    return scene_bootstrap(d["label"].to_numpy(), seed_probs(d), d["scene"].to_numpy(),
                           seed=p.seed)


def slope_through_origin(err: np.ndarray, loss: np.ndarray, reps: np.ndarray
                         ) -> tuple[float, float, float]:
    """(slope, lo, hi): the least-squares slope through the origin of ``loss`` (L,) against
    ``err`` (L,) px, and the 95 % interval of the slopes of the replicates ``reps`` (L, n)
    (NaN replicates left out; NaN when none is defined)."""
    err = np.asarray(err, float)
    slope = float(err @ np.asarray(loss, float) / (err @ err))
    draws = (err @ np.asarray(reps, float)) / (err @ err)
    draws = draws[np.isfinite(draws)]
    lo, hi = interval(draws) if draws.size else (float("nan"), float("nan"))
    return slope, float(lo), float(hi)


def costs(p: Params, eff: pd.DataFrame) -> pd.DataFrame:
    """Per kind: the F1 points lost per px of realised end-point error
    (:func:`slope_through_origin` over its levels), with its 95 % interval from the same
    scene resamples for every arm (the exact arm's too), and whether it excludes 0."""
    if eff.empty:
        return pd.DataFrame()
    ref = _replicates(p, EXACT)
    rows = []
    for kind, g in eff.groupby("kind", sort=False):
        err = g["error (px)"].to_numpy()
        reps = np.stack([100 * (ref - _replicates(p, arm_key(kind, t))) for t in g["target"]])
        slope, lo, hi = slope_through_origin(err, -g["delta"].to_numpy(), reps)
        rows.append({"kind": kind, "error": KIND_WORDS[kind],
                     "F1 points lost per px": round(slope, 1),
                     "95% CI": f"{lo:.1f} to {hi:.1f}", "ci_lo": lo, "ci_hi": hi,
                     "decided": "yes" if lo > 0 or hi < 0 else "no",
                     "levels": len(g), "largest error (px)": round(float(err.max()), 2)})
    return pd.DataFrame(rows).sort_values("F1 points lost per px", ascending=False,
                                          ignore_index=True)


# --- the real methods' errors in the same terms ----------------------------------------------


def error_profile(flow: np.ndarray, exact: np.ndarray, still: np.ndarray, box: np.ndarray
                  ) -> pd.DataFrame:
    """Per object, a flow method's error in the experiment's terms; flow, exact and still
    (the still-world flow of the window) (N, 2, S, S) px, box (N, S, S) bool. Columns (px):
    ``epe_box``, ``epe_ring`` (mean end-point error in the box, around it); ``scatter``
    (mean distance of the box's errors from their box mean: what white noise makes);
    ``bias`` (length of the box-mean error); ``lost`` (the part of the box-mean error that
    points against the mover's own motion, exact minus still-world flow: what the pull
    makes; 0 for objects with less than :data:`MIN_MOTION` of motion); ``apparent``
    (length of the box-mean flow minus the still-world flow: the motion a still vehicle
    seems to have); ``motion`` (the same of the exact flow)."""
    w = box[:, None].astype(np.float32)
    npx = np.maximum(box.sum((1, 2)), 1)[:, None]
    err = flow - exact
    epe = np.linalg.norm(err, axis=1)
    bias = (err * w).sum((2, 3)) / npx
    motion = ((exact - still) * w).sum((2, 3)) / npx
    norm = np.linalg.norm(motion, axis=1)
    unit = motion / np.maximum(norm, 1e-9)[:, None]
    against = np.where(norm >= MIN_MOTION, np.maximum(-(bias * unit).sum(1), 0.0), 0.0)
    ring = ~box
    return pd.DataFrame({
        "epe_box": (epe * box).sum((1, 2)) / npx[:, 0],
        "epe_ring": (epe * ring).sum((1, 2)) / np.maximum(ring.sum((1, 2)), 1),
        "scatter": (np.linalg.norm(err - bias[:, :, None, None], axis=1) * box).sum((1, 2))
        / npx[:, 0],
        "bias": np.linalg.norm(bias, axis=1), "lost": against,
        "apparent": np.linalg.norm(((flow - still) * w).sum((2, 3)) / npx, axis=1),
        "motion": norm})


def method_errors(p: Params, method: str) -> pd.DataFrame:
    """:func:`error_profile` of ``method``'s keyframe crops against the exact flow's, on
    every scored object (every fold's test rows), with label and scene."""
    out = []
    folders = {m: pipeline.published(p, Node("crops", m, "keyframe")) for m in (method, "gt")}
    ctx = pipeline.published(p, Node("context", None, "keyframe"))
    for k in range(p.folds):
        split = f"f{k}" if p.folds > 1 else "test"
        x, df = read_crops(folders[method], split)
        g, gdf = read_crops(folders["gt"], split)
        still, _, cdf = read_context(ctx, split, "boxes")
        if not (df["ann_token"].equals(gdf["ann_token"]) and df["ann_token"].equals(cdf["ann_token"])):
            raise ValueError(f"{method}, {split}: its crops, the exact flow's and the "
                             "still-world flow's hold other objects")
        box = box_masks(df[list(BOX_COLUMNS)].to_numpy(np.float64), x.shape[-1], p.crop_scale)
        t = error_profile(np.asarray(x, np.float32), np.asarray(g, np.float32),
                          np.asarray(still, np.float32), box)
        out.append(t.assign(label=df["label"].to_numpy(), scene=df["scene"].to_numpy()))
    return pd.concat(out, ignore_index=True)


#: The profile's components, each with the kind of the experiment that makes that error.
COMPONENTS = {"scatter": "noise", "lost": "pull", "bias": "scale", "epe_ring": "ring"}


def profiles(p: Params) -> pd.DataFrame:
    """Per estimated flow method: its error profile's means over the scored objects (px),
    the apparent motion of still vehicles and of movers (medians, px), and its Table 3
    difference from the exact flow (exact minus method, F1 points, chapter 07's paired
    comparison over scenes and seeds)."""
    if not pipeline.built(p, Node("evaluate", "gt")):
        return pd.DataFrame()
    ref = results(p, "gt", "test")[0]
    rows = []
    for m in [m for m in p.flow_methods if m != "gt" and pipeline.built(p, Node("evaluate", m))]:
        t = method_errors(p, m)
        cmp = paired(ref, results(p, m, "test")[0], f"gt and {m}", seed=p.seed)
        rows.append({"method": m, **{c: float(t[c].mean()) for c in
                                     ("epe_box", "epe_ring", "scatter", "bias", "lost")},
                     "apparent, still (px)": float(t.loc[t["label"] == 0, "apparent"].median()),
                     "apparent, movers (px)": float(t.loc[t["label"] == 1, "apparent"].median()),
                     "measured": 100 * cmp["delta_f1"], "measured_lo": 100 * cmp["ci"][0],
                     "measured_hi": 100 * cmp["ci"][1]})
    return pd.DataFrame(rows)


def predictions(prof: pd.DataFrame, cost: pd.DataFrame) -> pd.DataFrame:
    """Per method, its Table 3 loss against the exact flow (measured, F1 points, with its
    interval) beside two predictions from the experiment's costs per px: by its box
    end-point error alone, priced as white noise (``by end-point error``), and by its
    profile, each component priced by the kind that makes it (:data:`COMPONENTS`;
    ``by profile``). A kind the experiment did not run prices nothing (NaN)."""
    if prof.empty:
        return pd.DataFrame(columns=["method", "measured", "by end-point error", "by profile"])
    price = dict(zip(cost["kind"], cost["F1 points lost per px"], strict=True)) if len(cost) else {}
    out = prof[["method", "measured", "measured_lo", "measured_hi"]].copy()
    out["by end-point error"] = prof["epe_box"] * price.get("noise", np.nan)
    out["by profile"] = sum(prof[c] * price.get(k, np.nan) for c, k in COMPONENTS.items())
    return out


# --- the answer in words ------------------------------------------------------------------------


def _cost_words(r: Any) -> str:
    return f"{KIND_WORDS[r['kind']]} ({r['F1 points lost per px']:.1f}, {r['95% CI']})"


#: The kinds whose error is the absence of a vehicle's own motion (what the label reads).
MOTION_KINDS = frozenset({"pull"})


def answer(cost: pd.DataFrame) -> str:
    """The chapter's answer in one sentence: which kinds of error cost the classifier F1
    points per px of end-point error measurably (the interval above 0), how little the
    others cost (their intervals' span), and what that says of the paper's RAFT/FastFlowNet
    result (as this world shows it)."""
    if len(cost) < 2:
        return "Too few kinds of error were built to compare their costs"
    dear = cost[cost["ci_lo"] > 0]
    rest = cost[~(cost["ci_lo"] > 0)]
    if dear.empty:
        return (f"No kind of error costs the classifier measurably at these errors (F1 "
                f"points per px, every 95 % interval between {cost['ci_lo'].min():.1f} and "
                f"{cost['ci_hi'].max():.1f}): in this world the end-point error, whatever "
                "its kind, does not decide the classifier")
    why = ("whether the error erases a vehicle's own motion, not its size"
           if set(dear["kind"]) <= MOTION_KINDS else "its kind, not its size")
    words = (f"Per pixel of end-point error, only {'; '.join(map(_cost_words, dear.to_dict('records')))}"
             f" costs the classifier measurably (F1 points per px, 95 % interval)")
    if len(rest):
        words += (f"; the other {len(rest)} kinds ({', '.join(KIND_WORDS[k] for k in rest['kind'])})"
                  f" cost nothing these scenes resolve, every interval contains 0 (from "
                  f"{rest['ci_lo'].min():.1f} to {rest['ci_hi'].max():.1f})")
    return (words + f". What decides is {why}: a more accurate flow (the paper's RAFT) can "
            "make the weaker classifier when its little error falls on the vehicles' own "
            "motion. This is what this world shows, not a measurement on real nuScenes")


def _pairs_agree(x: np.ndarray, y: np.ndarray) -> tuple[int, int]:
    """(agreeing, all) pairs of methods that ``x`` and ``y`` order alike (ties: not)."""
    n = len(x)
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    return sum(np.sign(x[i] - x[j]) * np.sign(y[i] - y[j]) > 0 for i, j in pairs), len(pairs)


def prediction_words(pred: pd.DataFrame, prof: pd.DataFrame) -> str:
    """How well each predictor orders the methods' measured Table 3 losses (pairs of
    methods ordered alike), and what orders them: the box end-point error itself, its
    price as white noise, the profile, the apparent motion of still vehicles."""
    if len(pred) < 2:
        return "fewer than two estimated flow methods were built, so nothing can be ordered"
    measured = pred["measured"].to_numpy(float)
    cand = {"their box end-point error": prof["epe_box"].to_numpy(float),
            "the experiment's price of their profile": pred["by profile"].to_numpy(float),
            "the apparent motion they give still vehicles": prof["apparent, still (px)"]
            .to_numpy(float)}
    parts = []
    for name, v in cand.items():
        k, n = _pairs_agree(v, measured)
        parts.append(f"{name} orders {k} of {n} pairs of methods as Table 3 does")
    return "; ".join(parts) + (f" (with {len(pred)} methods, a weak test: read it as a "
                               "pointer, not a finding)")


# --- what the notebook shows ------------------------------------------------------------------


def built_note(p: Params, done: list[str]) -> str:
    """A line for the chapter: how many arms are built, or why the profile has none."""
    planned = [arm_key(*a) for a in arms(p)]
    if not planned:
        return ("This profile runs no flow-error experiment: it needs the exact flow (`gt` "
                "in `flow_methods`, a generated world's) and at least one kind in "
                "`error_kinds`.")
    out = f"Arms built with these parameters: **{len(done)} of {len(planned)}**."
    missing = [k for k in planned if k not in done]
    return out + (f" Not built: {', '.join(missing)}." if missing else "")


def scope_table(p: Params, done: list[str]) -> pd.DataFrame:
    """What the experiment trained and scores: arms, folds, width, test scenes, objects,
    movers."""
    d = arm_predictions(p, EXACT) if EXACT in done else pd.DataFrame(
        columns=["scene", "label"])
    return pd.DataFrame([{
        "arms (models a fold)": len(done), "folds trained": p.error_folds,
        "network width": p.error_width or p.model_width,
        "Table 3's width": p.model_width, "test scenes": d["scene"].nunique(),
        "test objects": len(d), "of them moving": int(d["label"].sum()),
        "interval counts": "scenes only"}])


def effects_view(eff: pd.DataFrame) -> pd.DataFrame:
    """:func:`effects` as the chapter shows it."""
    if eff.empty:
        return eff
    cols = ["comparison", "error (px)", "ΔF1 (points)", "95% CI, scenes and seeds (points)",
            "verdict", "scenes", "objects"]
    return eff[cols].rename(columns={"95% CI, scenes and seeds (points)":
                                     "95% CI, scenes only (points)"})


def costs_view(cost: pd.DataFrame) -> pd.DataFrame:
    """:func:`costs` as the chapter shows it."""
    return cost.drop(columns=["kind", "ci_lo", "ci_hi"]) if len(cost) else cost


def profile_view(prof: pd.DataFrame, pred: pd.DataFrame) -> pd.DataFrame:
    """The real methods' profiles (px) beside their measured and predicted Table 3 losses
    (F1 points, exact minus method)."""
    if prof.empty:
        return prof
    out = prof.rename(columns={"epe_box": "EPE box (px)", "epe_ring": "EPE ring (px)",
                               "scatter": "scatter (px)", "bias": "bias (px)",
                               "lost": "against motion (px)"})
    out["Table 3 loss (points)"] = [f"{m:.1f} ({lo:.1f} to {hi:.1f})" for m, lo, hi in
                                    prof[["measured", "measured_lo", "measured_hi"]].to_numpy()]
    out["priced as noise (points)"] = pred["by end-point error"].to_numpy()
    out["priced by profile (points)"] = pred["by profile"].to_numpy()
    return out.drop(columns=["measured", "measured_lo", "measured_hi"])


# --- the answer used once: a FastFlowNet fine-tune (benchmarks/finetune.json) ---------------

#: The fine-tune's weights in the record, in the chapter's words.
FINETUNE_ARMS = {"shipped": "the shipped weights",
                 "control": "control: the same steps without the term",
                 "box_mean": "fine-tuned on the box-mean error"}


def finetune_record() -> dict[str, Any] | None:
    """The committed record of ``make flownet-finetune`` (:mod:`flowmod.flow.finetune`), or
    None where none is committed."""
    return committed_record(FINETUNE_RECORD)


def finetune_table(record: dict[str, Any]) -> pd.DataFrame:
    """Each weights' mean validation scores on the pretraining world's pairs: box bias and
    box end-point error (px), frame end-point error (px)."""
    means = record["validation"]["means"]
    return pd.DataFrame([{"weights": FINETUNE_ARMS[k], "box bias (px)": means[k]["bias_boxes"],
                          "box EPE (px)": means[k]["epe_boxes"], "EPE (px)": means[k]["epe"]}
                         for k in FINETUNE_ARMS if k in means])


def _signed(d: dict[str, float], unit: str = "px") -> str:
    return f"{d['mean']:+.3f} {unit} ({d['lo']:+.3f} to {d['hi']:+.3f})"


def finetune_words(record: dict[str, Any] | None) -> str:
    """The fine-tune's outcome in one sentence: adopted or not, the term's effect on the
    mean box bias against the control and on the box end-point error against the shipped
    weights, with their intervals over the validation scenes."""
    if record is None:
        return ("No fine-tune is recorded yet (`make flownet-finetune` writes "
                f"`{FINETUNE_RECORD}`)")
    d, box = record["decision"]["differences"], record["recipes"]["box_mean"]
    scenes = len(set(record["validation"]["pair_scenes"]))
    outcome = ("was adopted" if record["decision"]["adopt"]
               else "was not adopted (the shipped weights stay the default)")
    return (f"A fine-tune of the shipped FastFlowNet with a loss on each far box's mean error "
            f"({box['steps']} steps, the term weighted {box['box_mean_weight']:g}) {outcome}: "
            f"against a control trained the same steps without the term, it changed the "
            f"mean box bias by {_signed(d['bias_vs_control'])}, and against the shipped "
            f"weights the box end-point error by {_signed(d['epe_boxes_vs_shipped'])}; 95 % "
            f"intervals over the {scenes} validation scenes of the pretraining world, "
            f"none of the book's{_finetune_reading(d['bias_vs_control'])}")


def _finetune_reading(d: dict[str, float]) -> str:
    """What the term's effect on the box bias against the control says, by its interval."""
    if d["hi"] < 0:
        return ". The term lowered the bias beyond what the same training does without it"
    if d["lo"] > 0:
        return ". The term raised the bias against the same training without it"
    return (". A loss on the box's mean flow, on its own, did not lower the bias this chapter "
            "prices beyond what the same training does without it")
