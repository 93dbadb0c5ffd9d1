"""Chapter 11's backend: the classifier trained on all distances, against the paper's."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from flowmod import pipeline
from flowmod.chapters import ch08_generalisation, common
from flowmod.chapters.common import breakdown, comparison_table, results
from flowmod.crops import part_splits
from flowmod.dag import Node
from flowmod.evaluate import paired, scored, seed_probs
from flowmod.metrics import CI_COLUMN, false_alarm_rate, metrics
from flowmod.params import Params
from flowmod.select import read_table
from flowmod.train import extension_parts

#: Distance bins of the chapter's breakdowns (m): chapter 08's, Table 4's range and beyond.
EDGES = ch08_generalisation.DISTANCE_EDGES


def built(params: Params) -> list[str]:
    """The methods of ``wide_methods`` whose predictions, models, crops and selection are
    current (:meth:`flowmod.dag.Graph.built`)."""
    return [m for m in params.wide_methods if pipeline.built(params, Node("wgeneralise", m))]


def training_summary(params: Params) -> pd.DataFrame:
    """One row per training set and split: pairs, objects, moving share, distance range."""
    rows = []
    for name, node in ((f"paper: {band(params)} keyframes", "select"), ("all distances", "wide")):
        d = pipeline.published(params, Node(node))
        pairs, obj = (pd.read_parquet(d / f"{k}.parquet") for k in ("pairs", "objects"))
        for split in part_splits("wide", params.folds):
            o, pp = obj[obj["split"] == split], pairs[pairs["split"] == split]
            rows.append({"training set": name, "split": split, "pairs": len(pp),
                         "of them sweep pairs": int((pp["set"] == "sweep").sum()),
                         "objects": len(o), "moving (%)": round(100 * o["label"].mean(), 1),
                         "distance (m)": f"{o['distance'].min():.0f}-"
                                         f"{o['distance'].max():.0f}"})
    return pd.DataFrame(rows)


def near_counts(params: Params) -> dict[str, float]:
    """How many vehicles nearer than ``min_distance`` (and of them moving) the all-distances
    training set (train and val) and Table 4's set hold: what removing the filter can teach
    and where it is tested. NaN without chapter 11 (``wide_methods`` empty)."""
    keys = ("train", "train_moving", "general", "general_moving")
    if not params.wide_methods:
        return {f"wide_near_{k}": float("nan") for k in keys}
    out = {}
    for name, node in (("train", "wide"), ("general", "general")):
        obj = read_table(pipeline.published(params, Node(node)), "objects")
        near = obj[(obj["distance"] < params.min_distance)
                   & (obj["distance"] <= params.general_max_distance)]
        out[f"wide_near_{name}"] = float(len(near))
        out[f"wide_near_{name}_moving"] = float(near["label"].sum())
    return out


def predictions(params: Params, method: str, split: str, wide: bool) -> pd.DataFrame:
    """Published predictions (``prob_s<k>`` per seed) of ``method``'s classifiers on
    ``split`` (``general`` or ``test``): trained on all distances (``wide``) or the paper's
    (chapters 07 and 08)."""
    if not wide:
        return results(params, method, split)[0]
    folder = pipeline.published(params, Node("wgeneralise", method))
    return pd.read_parquet(folder / f"{split}.parquet")


def band(params: Params) -> str:
    """The paper's training band of this run: ``30-70 m`` (min_distance, max_distance)."""
    return f"{params.min_distance:g}-{params.max_distance:g} m"


def label(params: Params, method: str, wide: bool) -> str:
    """A row's name: ``dis (30-70 m)`` (the paper's training: :func:`band`) or ``dis (all
    distances)``."""
    return f"{method} ({'all distances' if wide else band(params)})"


def table4(params: Params, done: list[str]) -> pd.DataFrame:
    """Table 4 of every method of ``wide_methods``, with a row per method of ``done``
    trained on all distances beside the paper's (:func:`flowmod.chapters.ch08_generalisation.table4`: the
    paper's range scored against the paper's label and the true one, and the vehicles beyond
    it apart)."""
    preds = {label(params, m, w): predictions(params, m, "general", w)
             for m in params.wide_methods for w in (False, True) if not w or m in done}
    return ch08_generalisation.table4(preds, params.general_max_distance)


def comparisons(params: Params, methods: list[str], split: str = "general") -> pd.DataFrame:
    """Trained on all distances minus the paper's training, per method, paired on the same
    objects (``general``: Table 4's range; ``test``: the keyframe test split), with the
    per-seed differences and the interval over scenes
    (:func:`flowmod.metrics.paired_comparison`)."""
    rows = {}
    for m in methods:
        a, b = (scored(predictions(params, m, split, w), split, params.general_max_distance)
                for w in (True, False))
        rows[f"{m}: all distances - {band(params)}"] = paired(
            a, b, f"{m}: the two classifiers", params.seed)
    return comparison_table(rows)


def by_distance(params: Params, methods: list[str]) -> dict[str, pd.DataFrame]:
    """F1 per distance bin (:data:`EDGES`) on the generalisation set of both classifiers of
    every method (:func:`flowmod.chapters.common.breakdown`), for one plot."""
    return {label(params, m, w): breakdown(predictions(params, m, "general", w), "distance", list(EDGES))
            for m in methods for w in (False, True)}


def near_far(params: Params, methods: list[str], near: float = 30.0) -> pd.DataFrame:
    """F1 and the share of still vehicles called moving (false alarms), means over seeds, of
    both classifiers on the generalisation set's near vehicles (< ``near`` m) and those from
    ``near`` m to Table 4's end, with the object and mover counts."""
    rows = []
    for m in methods:
        for w in (False, True):
            d = scored(predictions(params, m, "general", w), "general",
                       params.general_max_distance)
            y = d["label"].to_numpy()
            row: dict[str, Any] = {"classifier": label(params, m, w)}
            for name, k in ((f"< {near:g} m", d["distance"] < near),
                            (f"{near:g}-{params.general_max_distance:g} m",
                             d["distance"] >= near)):
                k = k.to_numpy()
                row[f"F1 {name} (%)"] = round(100 * float(np.mean(
                    [metrics(y[k], p[k])["f1"] for p in seed_probs(d)])), 1)
                row[f"still called moving {name} (%)"] = round(100 * float(np.mean(
                    [false_alarm_rate(y[k], p[k]) for p in seed_probs(d)])), 1)
                row[f"n {name}"] = int(k.sum())
                row[f"moving {name}"] = int(y[k].sum())
            rows.append(row)
    return pd.DataFrame(rows)


def built_note(params: Params, done: list[str]) -> str:
    """A line for the chapter: which methods are built, and how to build the others."""
    if not params.wide_methods:
        return ("This profile trains no classifier on all distances (`wide_methods` is "
                "empty). Set it (e.g. `wide_methods=[dis]`) and run `make extensions`.")
    todo = [m for m in params.wide_methods if m not in done]
    return common.built_note("Methods trained on all distances", done,
                             len(params.wide_methods),
                             f"{', '.join(todo)}; {len(todo) * len(extension_parts(params))} models",
                             "extension_build")


def headline(params: Params, table: pd.DataFrame, done: list[str],
             paired: pd.DataFrame | None = None) -> str:
    """One sentence for the landing page: Table 4's F1 of the main method trained on all
    distances against the paper's training (from :func:`table4`) and, with ``paired``
    (:func:`comparisons` on the generalisation set), their paired difference; or how to
    build it."""
    if not params.wide_methods:
        return "not part of this profile (wide_methods is empty)"
    main = next((m for m in done if m != "gt"), done[0] if done else None)
    if main is None:
        return ("not built in this run (make extensions trains them: "
                f"{len(params.wide_methods) * len(extension_parts(params))} models)")
    t = table[table["vehicles"].str.endswith("(Table 4)")
              & (table["scored against"] == "paper rule (previous keyframe)")].set_index(
        "method")
    wide, paper = t.loc[label(params, main, True)], t.loc[label(params, main, False)]
    return (f"trained on every distance up to {params.general_max_distance:g} m instead of "
            f"{band(params)} keyframes only, the {main} classifier reaches Table 4 F1 "
            f"{wide['F1 (%)']:.1f} % (interval over scenes and seeds {wide[CI_COLUMN]} %) "
            f"against {paper['F1 (%)']:.1f} %" + (
                f": {common.difference_words(paired.iloc[done.index(main)])}"
                if paired is not None and len(paired) == len(done) else ""))
