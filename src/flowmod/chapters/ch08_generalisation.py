"""Chapter 08's backend: Table 4's numbers."""

from __future__ import annotations

from typing import Any

import pandas as pd

from flowmod.chapters.common import headline_method, results
from flowmod.evaluate import failure_reasons, failure_shares, table4
from flowmod.params import Params


def predictions(params: Params) -> dict[str, pd.DataFrame]:
    """``{method: generalisation predictions}`` of the paper's classifiers."""
    return {m: results(params, m, "general")[0] for m in params.flow_methods}


def table(params: Params) -> pd.DataFrame:
    """Table 4 of this build (:func:`flowmod.evaluate.table4`)."""
    return table4(predictions(params), params.general_max_distance)


def numbers(params: Params, table: pd.DataFrame) -> dict[str, Any]:
    """The numbers chapter 08 records: Table 4's F1 per method (paper's range, both
    labels), the objects scored, and the headline method's F1 with its interval (text) and
    the F1 of calling every vehicle moving on the same objects."""
    out: dict[str, Any] = {}
    t4 = table[table["vehicles"].str.endswith("(Table 4)")]
    for r in t4.to_dict("records"):
        key = "paper" if r["scored against"].startswith("paper") else "true"
        out[f"general_f1_{r['method']}_{key}"] = r["F1 (%)"]
    paper = t4[t4["scored against"].str.startswith("paper")]
    out["n_general"] = int(paper["objects"].iloc[0]) if len(paper) else 0
    head = headline_method(params)
    out["headline_general_f1"] = out.get(f"general_f1_{head}_paper", float("nan"))
    row = paper[paper["method"] == head]
    out["headline_general_ci"] = (str(row["F1 95% CI, scenes and seeds (%)"].iloc[0])
                                  if len(row) else "undefined")
    out["headline_general_chance"] = (float(row["always moving F1 (%)"].iloc[0]) if len(row)
                                      else float("nan"))
    beyond = table[~table["vehicles"].str.endswith("(Table 4)")
                   & table["scored against"].str.startswith("paper")]
    for r in beyond.to_dict("records"):
        out[f"beyond_f1_{r['method']}"] = r["F1 (%)"]
    return out


def failures(params: Params, preds: pd.DataFrame, boxes: pd.DataFrame
             ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The paper's two failure reasons on ``preds`` (:func:`flowmod.evaluate.failure_reasons`
    with the profile's threshold and crop scale): (each reason's share among all objects
    and among the wrong predictions, the tagged rows)."""
    tagged = failure_reasons(preds, boxes, speed_threshold=params.speed_threshold,
                             scale=params.crop_scale)
    return failure_shares(tagged), tagged


def failure_words(shares: pd.DataFrame) -> str:
    """Whether each failure reason explains the wrong predictions: one that is no commoner
    among them than among all objects (share ratio under 1.05) does not; an undefined share
    (no wrong prediction) is said so."""
    out = []
    for _, r in shares.iterrows():
        a, w = r["all objects (%)"], r["wrong predictions (%)"]
        if pd.isna(w) or not a:
            out.append(f"*{r['reason']}*: undefined (no wrong prediction or no such object)")
        elif w / a < 1.05:
            out.append(f"*{r['reason']}* holds for {w:.1f} % of the wrong predictions and "
                       f"{a:.1f} % of all objects: no commoner among the errors, so it does "
                       "not explain them")
        else:
            out.append(f"*{r['reason']}* holds for {w:.1f} % of the wrong predictions against "
                       f"{a:.1f} % of all objects ({w / a:.1f} times as common)")
    return "; ".join(out) + "."
