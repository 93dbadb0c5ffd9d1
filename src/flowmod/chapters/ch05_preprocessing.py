"""Chapter 05's backend: the crops each stage published, and what keeping crops saves."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from flowmod import pipeline
from flowmod.chapters.common import flow_reader
from flowmod.crops import IMAGE_SIZE, CropsError, crop_paths, part_splits, samples_path
from flowmod.dag import Node
from flowmod.flow import flow_to_color
from flowmod.params import Params
from flowmod.select import PARTS, Selection

#: Crops of each class the gallery shows.
GALLERY = 8


def folders(p: Params) -> dict[str, dict[str, Path]]:
    """``{method: {part: published crops folder}}`` of the paper's two parts."""
    return {m: {part: pipeline.published(p, Node("crops", m, part)) for part in PARTS}
            for m in p.flow_methods}


def run_summary(p: Params) -> pd.DataFrame:
    """One row per method and split: objects, crop size and where they are published."""
    rows = []
    for m, parts in folders(p).items():
        for part, folder in parts.items():
            for split in part_splits(part, p.folds):
                n = int(np.load(crop_paths(folder, split)[0], mmap_mode="r").shape[0])
                rows.append({"method": m, "split": split, "objects": n,
                             "crop (px)": p.crop_size,
                             "folder": str(folder.relative_to(p.run_path))})
    return pd.DataFrame(rows)


def storage_table(p: Params) -> pd.DataFrame:
    """Disk used per item: crops per object vs full-frame flow per pair, for each method."""
    rows = []
    for m, parts in folders(p).items():
        npys = [crop_paths(parts[part], split)[0]
                for part in PARTS for split in part_splits(part, p.folds)]
        n_obj = sum(int(np.load(f, mmap_mode="r").shape[0]) for f in npys)
        crop_bytes = sum(f.stat().st_size for f in npys)
        sample_bytes = sum(samples_path(parts[part], split).stat().st_size
                           for part in PARTS for split in part_splits(part, p.folds))
        flows = [r.path(pid) for part in PARTS
                 for r in [flow_reader(p, m, part)] for pid in r.index["pair_id"]]
        flow_bytes = sum(f.stat().st_size for f in flows)
        rows.append({
            "method": m, "objects": n_obj, "crops total (MB)": crop_bytes / 1e6,
            "per object (kB)": crop_bytes / max(n_obj, 1) / 1e3,
            "flow samples per object (kB)": sample_bytes / max(n_obj, 1) / 1e3,
            "flow pairs": len(flows),
            "flow total (MB)": flow_bytes / 1e6,
            "flow per pair (MB)": flow_bytes / max(len(flows), 1) / 1e6,
            "original: float32 flow per pair (MB)": IMAGE_SIZE[0] * IMAGE_SIZE[1] * 2 * 4 / 1e6,
        })
    return pd.DataFrame(rows).round(2)


def median_mover(sel: Selection, among: Sequence[str] | None = None) -> tuple[pd.Series, pd.Series]:
    """A moving keyframe vehicle of median box width and its pair's row (for the figure of
    the preprocessing steps); only in the pairs ``among`` if given (those with stored flow)."""
    obj = sel.objects[(sel.objects["set"] == "keyframe") & (sel.objects["label"] == 1)]
    if among is not None:
        obj = obj[obj["pair_id"].isin(list(among))]
    if not len(obj):
        raise CropsError("no moving keyframe vehicle among the pairs with stored flow")
    width = (obj["xmax"] - obj["xmin"]).to_numpy()
    row = obj.iloc[int(np.argsort(width)[len(obj) // 2])]
    return row, sel.pairs.set_index("pair_id").loc[row.pair_id]


def crop_color(crop: np.ndarray) -> np.ndarray:
    """A (2, S, S) flow crop in the flow-colour code (S, S, 3)
    (:func:`flowmod.flow.metrics.flow_to_color`, channels last)."""
    return flow_to_color(np.moveaxis(crop, 0, -1))
