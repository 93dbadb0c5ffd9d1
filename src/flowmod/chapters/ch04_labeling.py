"""Chapter 04's backend: the equation-1 labels of the keyframe set beside the devkit's and
(on the synthetic world) the true views of motion, the speed histogram's bins and the
examples near the threshold, with the numbers the chapter glues."""

from __future__ import annotations

import numpy as np
import pandas as pd

from flowmod import labels
from flowmod.params import Params
from flowmod.select import Selection

#: Bins of the speed histogram (m/s): 0 to 25 m/s in steps of 0.5 m/s.
SPEED_BINS = np.arange(0.0, 25.5, 0.5)
#: How many examples near the threshold the chapter shows (one row of the figure).
NEAR_EXAMPLES = 6
#: The columns of the examples' table.
NEAR_COLUMNS = ["pair_id", "category", "distance", "speed", "label", "attribute", "box_speed"]


def keyframe_objects(sel: Selection) -> pd.DataFrame:
    """The selected target vehicles of the keyframe set, with their labels."""
    return sel.objects[sel.objects["set"] == "keyframe"]


def speeds(key: pd.DataFrame) -> dict[str, pd.Series]:
    """Speed by equation 1 (m/s) of the moving and of the still vehicles."""
    return {"moving": key.loc[key["label"] == 1, "speed"],
            "still": key.loc[key["label"] == 0, "speed"]}


def moving_fraction(key: pd.DataFrame) -> float:
    """Share (%) of the vehicles labelled moving, one decimal."""
    return round(100 * float(key["label"].mean()), 1)


def box_agreement(key: pd.DataFrame) -> float:
    """:func:`flowmod.labels.box_agreement` (%), one decimal."""
    return round(labels.box_agreement(key), 1)


def true_agreement(key: pd.DataFrame) -> float:
    """Share (%) of the vehicles whose equation-1 label is their true label at frame 1's
    time (synthetic world only), two decimals."""
    return round(100 * float((key["label"] == key["true_label"]).mean()), 2)


def near_threshold(params: Params, key: pd.DataFrame, threshold: float) -> pd.DataFrame:
    """Up to :data:`NEAR_EXAMPLES` vehicles near the threshold, nearest first
    (:func:`flowmod.labels.near_threshold`, drawn with the profile's seed)."""
    return labels.near_threshold(key, threshold, n=NEAR_EXAMPLES, seed=params.seed)


def near_titles(near: pd.DataFrame) -> list[str]:
    """Each example's title: its speed (m/s) and distance (m)."""
    return [f"{s:.2f} m/s, {d:.0f} m" for s, d in zip(near["speed"], near["distance"],
                                                       strict=True)]
