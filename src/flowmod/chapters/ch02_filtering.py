"""Chapter 02's backend: Table 1 and what each step of the selection keeps."""

from __future__ import annotations

import numpy as np
import pandas as pd

from flowmod.params import Params
from flowmod.select import CAMERA, Selection

#: Width (m) of the bins of the selected vehicles' distance histogram.
DISTANCE_BIN = 2.5
#: How many example frames of the selection the chapter shows.
EXAMPLES = 4


def distance_bins(params: Params) -> np.ndarray:
    """Bins of the distance histogram (m): the selected band, in :data:`DISTANCE_BIN` steps."""
    return np.arange(params.min_distance, params.max_distance + DISTANCE_BIN, DISTANCE_BIN)


def table1(p: Params) -> pd.DataFrame:
    """Table 1 of the paper, regenerated from the parameters."""
    vis_bins = {"1": "0-40 %", "2": "40-60 %", "3": "60-80 %", "4": "80-100 %"}
    return pd.DataFrame([
        {"setting": "Target categories", "description": "\n".join(p.categories)},
        {"setting": "Distance", "description": f"{p.min_distance:g} m - {p.max_distance:g} m"
                                               f" ({p.distance_mode} origin)"},
        {"setting": "Visibility",
         "description": ", ".join(vis_bins[v] for v in sorted(p.visibility_tokens))},
        {"setting": "Sensor", "description": CAMERA},
        {"setting": "Excluded scenes",
         "description": ", ".join(p.exclude_descriptions) or "none"},
    ])


def step_counts(sel: Selection) -> pd.DataFrame:
    """How many scenes, pairs and objects survive each step of the selection."""
    sc, pairs, obj = sel.scenes, sel.pairs, sel.objects
    rows = [("scenes in the data set", len(sc))]
    for reason, n in sc.loc[sc["excluded_by"] != "", "excluded_by"].value_counts().items():
        rows.append((f"scenes excluded: '{reason}'", int(n)))
    rows += [
        ("scenes kept", int((sc["excluded_by"] == "").sum())),
        ("keyframe pairs with a target vehicle", int((pairs["set"] == "keyframe").sum())),
        ("target vehicles in keyframe pairs", int((obj["set"] == "keyframe").sum())),
        ("generalisation scenes", int(pairs.loc[pairs["set"] == "general", "scene"].nunique())),
        ("generalisation pairs", int((pairs["set"] == "general").sum())),
        ("generalisation objects", int((obj["set"] == "general").sum())),
    ]
    return pd.DataFrame(rows, columns=["step", "count"])


def distance_groups(objects: pd.DataFrame) -> dict[str, pd.Series]:
    """Keyframe targets' distances (m) by the unit the models are scored on: each split
    present, as ``split`` (``f0``, ``f1``, ... with cross-validation; train/val/test with
    one split), in their order of appearance sorted by name."""
    key = objects[objects["set"] == "keyframe"]
    return {str(s): key.loc[key["split"] == s, "distance"]
            for s in sorted(key["split"].unique())}


def distance_words(groups: dict[str, pd.Series]) -> str:
    """What the distance histogram shows, from its data: each group's count, range and
    median (m)."""
    parts = [f"{name}: {len(d)} vehicles, {d.min():.1f}-{d.max():.1f} m, median "
             f"{d.median():.1f} m" for name, d in groups.items() if len(d)]
    empty = [name for name, d in groups.items() if not len(d)]
    text = "; ".join(parts) + "."
    return text + (f" No vehicle in {', '.join(empty)}." if empty else "")
