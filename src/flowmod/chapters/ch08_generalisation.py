"""Chapter 08's backend: Table 4's numbers."""

from __future__ import annotations

from typing import Any

import pandas as pd

from flowmod.chapters.common import headline_method, results
from flowmod.evaluate import table4
from flowmod.params import Params


def predictions(params: Params) -> dict[str, pd.DataFrame]:
    """``{method: generalisation predictions}`` of the paper's classifiers."""
    return {m: results(params, m, "general")[0] for m in params.flow_methods}


def table(params: Params) -> pd.DataFrame:
    """Table 4 of this build (:func:`flowmod.evaluate.table4`)."""
    return table4(predictions(params), params.general_max_distance)


def numbers(params: Params, table: pd.DataFrame) -> dict[str, Any]:
    """The numbers chapter 08 records: Table 4's F1 per method (paper's range, both
    labels), the objects scored, and the headline method's F1."""
    out: dict[str, Any] = {}
    t4 = table[table["vehicles"].str.endswith("(Table 4)")]
    for r in t4.to_dict("records"):
        key = "paper" if r["scored against"].startswith("paper") else "true"
        out[f"general_f1_{r['method']}_{key}"] = r["F1 (%)"]
    paper = t4[t4["scored against"].str.startswith("paper")]
    out["n_general"] = int(paper["objects"].iloc[0]) if len(paper) else 0
    head = headline_method(params)
    out["headline_general_f1"] = out.get(f"general_f1_{head}_paper", float("nan"))
    beyond = table[~table["vehicles"].str.endswith("(Table 4)")
                   & table["scored against"].str.startswith("paper")]
    for r in beyond.to_dict("records"):
        out[f"beyond_f1_{r['method']}"] = r["F1 (%)"]
    return out
