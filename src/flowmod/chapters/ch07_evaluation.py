"""Chapter 07's backend: Table 3, the paired comparisons, the original protocol's number."""

from __future__ import annotations

from itertools import combinations
from typing import Any

import numpy as np
import pandas as pd

from flowmod.chapters.common import difference_words, headline_method, read_json, results
from flowmod.dag import Node
from flowmod.evaluate import paired
from flowmod.metrics import comparison_table
from flowmod.metrics import table3 as metrics_table3
from flowmod.params import Params


def original_vs_clean(params: Params, method: str) -> dict[str, Any]:
    """The published original-protocol comparison of ``method``
    (:func:`flowmod.evaluate.original_protocol`)."""
    return read_json(params, Node("evaluate", method), "original.json")


def table3(params: Params) -> pd.DataFrame:
    """Table 3 of this build: one row per flow method (the classifiers, mean over training
    seeds with their range) and one per geometric baseline on the same flow, with the
    95 % interval over scenes and seeds and what it resamples."""
    rows = [{"method": f"ResNet18 on {m} flow", **results(params, m, "test")[1]}
            for m in params.flow_methods]
    rows += [{"method": f"geometric residual, {m} flow", **results(params, m, "baseline")[1]}
             for m in params.flow_methods]
    return metrics_table3(rows)


def comparisons(params: Params) -> pd.DataFrame:
    """Paired comparisons of the classifiers on the same test objects: every pair of flow
    methods (earlier minus later in the profile's order), the exact flow against each
    estimate first; then each classifier against the geometric rule on the same flow (an
    oracle: it reads the annotated 3D boxes), which has no training noise."""
    preds = {m: results(params, m, "test")[0] for m in params.flow_methods}
    rows = {}
    for a, b in combinations(params.flow_methods, 2):
        da, db = preds[a], preds[b]
        if not da["ann_token"].equals(db["ann_token"]):
            raise ValueError(f"{a} and {b} were scored on different objects")
        rows[f"{a} - {b}"] = paired(da, db, f"{a} and {b}", seed=params.seed)
    for m in params.flow_methods:
        rows[f"{m}: classifier - oracle rule"] = paired(
            preds[m], results(params, m, "baseline")[0], f"{m}'s classifier and rule",
            seed=params.seed)
    return comparison_table(rows)


def answer(table: pd.DataFrame) -> str:
    """The paired comparisons (:func:`comparisons`) in words, each with its interval over
    scenes and training seeds and whether it decides (the interval excludes 0)."""
    out = []
    for _, row in table.iterrows():
        words = difference_words(row)
        if row["verdict"] != "undecided":
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


def numbers(params: Params) -> dict[str, Any]:
    """The numbers chapter 07 records for the book's other pages and the tests: per method
    the classifiers' mean test F1 (%), the baseline's, the objects and scenes scored, the
    headline method (the first estimated flow of the profile) and the protocol gap."""
    out: dict[str, Any] = {}
    gaps = []
    for m in params.flow_methods:
        s = results(params, m, "test")[1]
        out[f"test_f1_{m}"] = round(100 * s["f1"], 1)
        out[f"test_f1_min_{m}"] = round(100 * s["f1_min"], 1)
        out[f"test_f1_max_{m}"] = round(100 * s["f1_max"], 1)
        out[f"test_seed_sd_{m}"] = round(100 * s.get("seed_sd", float("nan")), 1)
        out[f"baseline_f1_{m}"] = round(100 * results(params, m, "baseline")[1]["f1"], 1)
        gaps.append(original_vs_clean(params, m)["original_minus_clean"])
        out["n_test"], out["n_test_scenes"] = s["n"], s["n_scenes"]
        out["seeds"] = s["seeds"]
        out["training_seeds"] = s.get("training_seeds", 1)
        out["chance_f1"] = round(100 * s.get("always_moving_f1", float("nan")), 1)
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
               protocol_gap=round(100 * float(np.mean(gaps)), 1))
    return out
