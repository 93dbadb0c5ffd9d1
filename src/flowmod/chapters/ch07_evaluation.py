"""Chapter 07's backend: Table 3, the paired comparisons, the original protocol's number."""

from __future__ import annotations

from itertools import combinations
from typing import Any

import numpy as np
import pandas as pd

from flowmod import evaluate, pipeline
from flowmod.chapters.common import (
    breakdown,
    comparison_table,
    decided,
    difference_words,
    headline_method,
    results,
    verdict_words,
)
from flowmod.dag import Node
from flowmod.evaluate import paired, read_scores, scored_crops, seed_probs
from flowmod.extensions import flowerrors
from flowmod.metrics import group_mean_bootstrap, interval, protocol_comparison
from flowmod.metrics import table3 as metrics_table3
from flowmod.params import Params


def original_vs_clean(params: Params, method: str) -> dict[str, Any]:
    """The published original-protocol comparison of ``method``
    (:func:`flowmod.evaluate.original_protocol`)."""
    return read_scores(pipeline.published(params, Node("evaluate", method)), "original")


def table3(params: Params) -> pd.DataFrame:
    """Table 3 of this build: one row per flow method (the classifiers, mean over training
    seeds with their range) and one per geometric baseline on the same flow, with the
    95 % interval over scenes and seeds and what it resamples."""
    rows = [{"method": f"ResNet18 on {m} flow", **results(params, m, "test")[1]}
            for m in params.flow_methods]
    rows += [{"method": f"ResNet18 on {m} flow, {RAW_LABEL}", **results(params, m, "raw")[1]}
             for m in raw_methods(params)]
    rows += [{"method": f"geometric residual, {m} flow", **results(params, m, "baseline")[1]}
             for m in params.flow_methods]
    return metrics_table3(rows)


#: How Table 3 names the models trained on the paper's raw input beside the chosen recipe.
RAW_LABEL = "the paper's raw input"


def raw_methods(params: Params) -> list[str]:
    """The flow methods whose classifier is also trained on the paper's raw input
    (``raw_input_methods``), in the profile's order."""
    return [m for m in params.flow_methods if m in (params.raw_input_methods or [])]


def comparisons(params: Params) -> pd.DataFrame:
    """Paired comparisons of the classifiers on the same test objects: every pair of flow
    methods (earlier minus later in the profile's order), the exact flow against each
    estimate first; then each classifier against the geometric rule on the same flow (an
    oracle: it reads the annotated 3D boxes), which has no training noise; then, for
    ``raw_input_methods``, the chosen input scaling against the paper's raw input (one
    model a fold, seeded as the chosen recipe's seed 0)."""
    preds = {m: results(params, m, "test")[0] for m in params.flow_methods}
    rows = {}
    for a, b in combinations(params.flow_methods, 2):
        rows[f"{a} - {b}"] = paired(preds[a], preds[b], f"{a} and {b}", seed=params.seed)
    for m in params.flow_methods:
        rows[f"{m}: classifier - oracle rule"] = paired(
            preds[m], results(params, m, "baseline")[0], f"{m}'s classifier and rule",
            seed=params.seed)
    for m in raw_methods(params):
        rows[f"{m}: {params.input_scaling} input - raw input"] = paired(
            preds[m], results(params, m, "raw")[0], f"{m}'s two recipes", seed=params.seed)
    return comparison_table(rows)


def answer(table: pd.DataFrame) -> str:
    """The paired comparisons (:func:`comparisons`) in words, each with its interval over
    scenes and training seeds and whether it decides (the interval excludes 0)."""
    out = []
    for _, row in table.iterrows():
        words = difference_words(row)
        if decided(row["verdict"]):
            words += f", decided: {'the first' if row['verdict'] == 'A better' else 'the second'}"
            words += " is better"
        out.append(f"{row['comparison']}: {words}")
    return "; ".join(out) + "."


def protocols(params: Params) -> pd.DataFrame:
    """Per method: the clean F1 (best validation epoch, whole test split) and what the
    original code's protocol reports for the same models (epoch chosen on the test split,
    stills thinned 1 of 2, F1 averaged per batch), means over training seeds, and
    original minus clean."""
    rows = []
    for m in params.flow_methods:
        r = original_vs_clean(params, m)
        rows.append({"method": m, "clean F1 (%)": round(100 * r["clean"], 1),
                     "original protocol F1 (%)": round(100 * r["original"], 1),
                     "original - clean (points)": round(100 * r["original_minus_clean"], 1)})
    return pd.DataFrame(rows)


#: How many test frames with their predictions the chapter shows (Figure 2).
EXAMPLES = 4


#: Chapter 07's distance bins (m): Table 1's band in 10 m steps.
DISTANCE_BINS = [30, 40, 50, 60, 70.01]


def by_distance(preds: dict[str, pd.DataFrame]) -> dict[str, pd.DataFrame]:
    """Per method, F1 per distance bin (:data:`DISTANCE_BINS`) with its interval over scenes
    and seeds and the objects in each bin (:func:`~flowmod.chapters.common.breakdown`)."""
    return {m: breakdown(df, "distance", DISTANCE_BINS) for m, df in preds.items()}


def by_category(preds: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """F1 per vehicle category, one block of rows per method."""
    return pd.concat({m: breakdown(df, "category") for m, df in preds.items()},
                     names=["method"]).reset_index(0)


def protocol_scores(preds: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """The same predictions scored four ways per method (whole set, per batch of the
    original's 128, stills thinned 1 of 2, both: :func:`flowmod.metrics.protocol_comparison`)."""
    return pd.concat({m: protocol_comparison(df["label"], df["prob"], evaluate.ORIGINAL_BATCH)
                      for m, df in preds.items()}, names=["method"]).reset_index(0)


def numbers(params: Params) -> dict[str, Any]:
    """The numbers chapter 07 records for the book's other pages and the tests: per method
    the classifiers' mean test F1 (%), the baseline's, the objects and scenes scored, the
    headline method (the first estimated flow of the profile) and the protocol gap (the
    mean over methods, and its range over every model: ``protocol_gap_range``)."""
    out: dict[str, Any] = {}
    gaps: list[float] = []
    per_model: list[float] = []
    for m in params.flow_methods:
        s = results(params, m, "test")[1]
        out[f"test_f1_{m}"] = round(100 * s["f1"], 1)
        out[f"test_f1_min_{m}"] = round(100 * s["f1_min"], 1)
        out[f"test_f1_max_{m}"] = round(100 * s["f1_max"], 1)
        out[f"test_seed_sd_{m}"] = round(100 * s.get("seed_sd", float("nan")), 1)
        out[f"baseline_f1_{m}"] = round(100 * results(params, m, "baseline")[1]["f1"], 1)
        gaps.append(original_vs_clean(params, m)["original_minus_clean"])
        per_model += protocol_gaps(original_vs_clean(params, m))
        out["n_test"], out["n_test_scenes"] = s["n"], s["n_scenes"]
        out["seeds"] = s["seeds"]
        out["training_seeds"] = s.get("training_seeds", 1)
        out["chance_f1"] = round(100 * s["always_moving_f1"], 1)
        out["scored_by"] = (f"pooled over {s['seeds']} cross-validation folds, each scene "
                            "scored by the models that never saw it, the mean of "
                            f"{s.get('training_seeds', 1)} training seeds a fold"
                            if s.get("unit") == "fold" else
                            f"mean of {s['seeds']} training seeds")
    head = headline_method(params)
    s = results(params, head, "test")[1]
    out.update(headline_method=head, headline_f1=round(100 * s["f1"], 1),
               headline_precision=round(100 * s["precision"], 1),
               headline_recall=round(100 * s["recall"], 1),
               headline_ci_lo=round(100 * s["ci"][0], 1), headline_ci_hi=round(100 * s["ci"][1], 1),
               headline_baseline_f1=out[f"baseline_f1_{head}"],
               protocol_gap=round(100 * float(np.mean(gaps)), 1),
               protocol_gap_range=(f"{100 * np.nanmin(per_model):.1f} to "
                                   f"{100 * np.nanmax(per_model):.1f} points over the "
                                   f"{len(per_model)} models"),
               bootstrap_draws=bootstrap_draws())
    return out


def protocol_gaps(rec: dict[str, Any]) -> list[float]:
    """Each model's original-protocol F1 minus its clean F1 (fractions), from
    :func:`original_vs_clean`'s record (``per_seed_original``, ``per_seed_clean``)."""
    return [float(o - c) for o, c in zip(rec["per_seed_original"], rec["per_seed_clean"],
                                         strict=True)]


def bootstrap_draws() -> int:
    """Replicates behind every interval of the book: the default of
    :func:`flowmod.metrics.scene_bootstrap` (and of the paired comparisons, which use it)."""
    import inspect

    from flowmod.metrics import paired_comparison, scene_bootstrap

    n = inspect.signature(scene_bootstrap).parameters["n"].default
    if inspect.signature(paired_comparison).parameters["n"].default != n:
        raise ValueError("the paired comparisons and Table 3 bootstrap different replicates")
    return int(n)


# --- why one flow method's classifier trails another's: the flow error in and around the box ---


def box_masks(df: pd.DataFrame, size: int, scale: float) -> np.ndarray:
    """(N, S, S) bool: the pixels of each object's crop (the paper's window, ``scale`` times
    the box's longer side, resized to S x S) that lie inside its 2D box, for the objects
    of ``df`` (:func:`flowmod.extensions.flowerrors.box_masks`, the one definition)."""
    return flowerrors.box_masks(df[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float), size, scale)


def crop_errors(params: Params, method: str, reference: str = "gt") -> pd.DataFrame:
    """Per scored object (the rows of Table 3, in its order): the end-point error (px of the
    flow grid) of ``method``'s flow crop against ``reference``'s (the exact flow) inside the
    object's box (``epe_box``) and in the rest of the window around it (``epe_around``)."""
    folder = {m: pipeline.published(params, Node("crops", m, "keyframe"))
              for m in (method, reference)}
    xm, dm = scored_crops(folder[method], params.folds)
    xr, dr = scored_crops(folder[reference], params.folds)
    if not dm["ann_token"].reset_index(drop=True).equals(dr["ann_token"].reset_index(drop=True)):
        raise ValueError(f"{method} and {reference} crops hold different objects")
    err = np.linalg.norm(np.asarray(xm, np.float32) - np.asarray(xr, np.float32), axis=1)
    inside = box_masks(dm, err.shape[-1], params.crop_scale)
    box = (err * inside).sum((1, 2)) / np.maximum(inside.sum((1, 2)), 1)
    around = (err * ~inside).sum((1, 2)) / np.maximum((~inside).sum((1, 2)), 1)
    return dm[["ann_token", "scene", "label", "distance", "speed"]].assign(
        epe_box=box, epe_around=around).reset_index(drop=True)


def _right(params: Params, method: str, objects: pd.Series) -> np.ndarray:
    """(N,) whether the seed-mean probability of ``method``'s classifiers is on the right
    side of 0.5 for each object of ``objects`` (ann_tokens of Table 3's objects, in the
    order wanted); ValueError if one has no prediction."""
    df = results(params, method, "test")[0]
    right = pd.Series((seed_probs(df).mean(axis=0) > 0.5).astype(int)
                      == df["label"].to_numpy(), index=df["ann_token"].to_numpy())
    missing = ~objects.isin(right.index)
    if missing.any():
        raise ValueError(f"{method}'s test predictions lack {int(missing.sum())} of the "
                         "objects its crops hold")
    return right.loc[objects.to_numpy()].to_numpy()


def error_explanation(params: Params, a: str, b: str) -> pd.DataFrame:
    """Method ``a`` against ``b`` on the same objects: the median crop error inside the box
    and around it (px; means are ruled by the few windows on near road) and the share of
    objects whose error is larger with ``a`` than with ``b`` (%, 50 when neither is worse),
    with its interval over scenes; then both classifiers' accuracy (seed-mean probability)
    by thirds of ``a``'s error around the box (the thirds' edges in px)."""
    ea, eb = crop_errors(params, a), crop_errors(params, b)
    rows = []
    for col, name in (("epe_box", "flow error inside the box, median (px)"),
                      ("epe_around", "flow error around the box, median (px)")):
        worse = (ea[col] > eb[col]).astype(float) + 0.5 * (ea[col] == eb[col])
        lo, hi = interval(group_mean_bootstrap(worse, ea["scene"], seed=params.seed))
        rows.append({"quantity": name, a: round(float(ea[col].median()), 2),
                     b: round(float(eb[col].median()), 2),
                     f"objects where {a} errs more (%)": round(100 * float(worse.mean()), 1),
                     "95% CI over scenes (%)": f"{100 * lo:.1f}-{100 * hi:.1f}"})
    ra, rb = _right(params, a, ea["ann_token"]), _right(params, b, ea["ann_token"])
    edges = np.quantile(ea["epe_around"], [0, 1 / 3, 2 / 3, 1])
    third = np.clip(np.searchsorted(edges, ea["epe_around"], side="right") - 1, 0, 2)
    for k in range(3):
        sel = third == k
        rows.append({"quantity": f"classifier accuracy (%), {a}'s error around the box "
                                 f"{edges[k]:.1f}-{edges[k + 1]:.1f} px ({int(sel.sum())} "
                                 "objects)",
                     a: round(100 * float(ra[sel].mean()), 1),
                     b: round(100 * float(rb[sel].mean()), 1),
                     f"objects where {a} errs more (%)": "",
                     "95% CI over scenes (%)": ""})
    return pd.DataFrame(rows)


def network_pair(params: Params) -> tuple[str, str] | None:
    """(network flow method, DIS) for :func:`error_explanation` when the profile has both
    and the exact flow to measure them against; else None."""
    nets = [m for m in params.flow_methods if m not in ("gt", "dis", "farneback")]
    if not nets or not {"gt", "dis"} <= set(params.flow_methods):
        return None
    return nets[0], "dis"


def explanation_words(table: pd.DataFrame, a: str, b: str) -> str:
    """:func:`error_explanation` in words (every number from the table)."""
    share = f"objects where {a} errs more (%)"
    box, around = table.iloc[0], table.iloc[1]
    acc = table.iloc[2:]
    gaps = [f"{r[a]:.1f} against {r[b]:.1f} %" for _, r in acc.iterrows()]
    return (f"Inside the box, {a}'s flow errs more than {b}'s on {box[share]:.1f} % of the "
            f"objects (95 % over scenes {box['95% CI over scenes (%)']} %; medians "
            f"{box[a]:.2f} and {box[b]:.2f} px); around the box, on {around[share]:.1f} % "
            f"({around['95% CI over scenes (%)']} %; medians {around[a]:.2f} and "
            f"{around[b]:.2f} px). By thirds of {a}'s error around the box, from the smallest, "
            f"the classifiers are right for {', '.join(gaps)} of the objects ({a} against {b}).")


def network_section(params: Params) -> tuple[pd.DataFrame, str]:
    """Chapter 07's explanation of the network row: (:func:`error_explanation` of
    :func:`network_pair`, its words); an empty table and a sentence saying why without a
    network beside DIS and the exact flow."""
    pair = network_pair(params)
    if pair is None:
        return (pd.DataFrame(columns=["quantity"]),
                "This profile has no network flow beside DIS and the exact flow.")
    table = error_explanation(params, *pair)
    return table, explanation_words(table, *pair)


def landing_words(table: pd.DataFrame, params: Params) -> dict[str, str]:
    """What the landing page quotes of the paired comparisons (:func:`comparisons`): the
    headline method's classifier against the oracle rule on its flow and, when the profile
    has the exact flow, the exact flow against the headline method; each in words with its
    interval over scenes and seeds, and whether it decides."""
    head = headline_method(params)
    rows = table.set_index("comparison")

    def words(name: str) -> str:
        if name not in rows.index:
            return "not in this profile"
        row = rows.loc[name]
        return difference_words(row) + verdict_words(row["verdict"])

    return {"headline_vs_oracle": words(f"{head}: classifier - oracle rule"),
            "exact_vs_headline": words(f"gt - {head}")}
