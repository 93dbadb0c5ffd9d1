"""Chapter 03's backend: what each flow method gives, against the world's exact flow."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from flowmod import pipeline
from flowmod.chapters import common
from flowmod.dag import Node
from flowmod.flow import FlowReader
from flowmod.flow.accuracy import bands, read_accuracy
from flowmod.params import Params


def run_summary(readers: Mapping[str, Mapping[str, FlowReader]]) -> pd.DataFrame:
    """One row per method and part: pairs, median estimation seconds per pair."""
    return pd.DataFrame([
        {"method": m, "part": part, "pairs": len(r.index),
         "median s / pair": float(r.index["seconds"].median()) if len(r.index) else float("nan")}
        for m, parts in readers.items() for part, r in parts.items()])


def accuracy_rows(params: Params) -> pd.DataFrame:
    """The published ``flowcheck`` node's rows (:mod:`flowmod.flow.accuracy`: per pair and
    method, against the exact flow)."""
    return read_accuracy(pipeline.published(params, Node("flowcheck")))


def accuracy_table(params: Params, rows: pd.DataFrame,
                   readers: Mapping[str, Mapping[str, FlowReader]]) -> pd.DataFrame:
    """EPE / Fl-all against the world's exact flow, overall and inside far (keyframe set,
    min-max distance) and near (generalisation set, up to min_distance) vehicle boxes (means
    over the ``flowcheck`` node's pairs, ``rows``; boxes: over the pairs with a valid pixel in
    one, with a scene-level interval), and the median seconds per pair of every stored pair
    (``readers``: ``{method: {part: FlowReader}}``)."""
    out = []
    for kind, dmin, dmax in bands(params.min_distance, params.max_distance):
        for method, parts in readers.items():
            mine = rows[(rows["set"] == kind) & (rows["method"] == method)]
            if mine.empty:
                continue
            box = mine.dropna(subset=["epe_box"])
            secs = parts[kind].index["seconds"]
            out.append({
                "set": kind, "vehicles": f"{dmin:g}-{dmax:g} m", "method": method,
                "EPE all (px)": mine["epe"].mean(), "Fl-all (%)": mine["fl"].mean(),
                "EPE boxes (px)": box["epe_box"].mean() if len(box) else np.nan,
                "EPE boxes 95% CI, scenes (px)": common.epe_ci(box["epe_box"], box["scene"],
                                                               params.seed),
                "Fl-all boxes (%)": box["fl_box"].mean() if len(box) else np.nan,
                "s / pair": float(np.nanmedian(secs)) if secs.notna().any() else np.nan,
                "pairs": int(mine["pair_id"].nunique()),
            })
    return pd.DataFrame(out)


def box_flow_magnitude(objects: pd.DataFrame, load: Any, inner: float = 0.6) -> np.ndarray:
    """Median flow magnitude (px) over the central ``inner`` fraction of each object's box.

    ``load(pair_id) -> (H, W, 2)``; each pair's flow is read once.
    """
    out = np.full(len(objects), np.nan)
    for pid, idx in objects.groupby("pair_id", sort=False).indices.items():
        f = load(pid)
        mag = np.linalg.norm(f.astype(np.float32), axis=-1)
        for i in idx:
            o = objects.iloc[i]
            cx, cy = (o.xmin + o.xmax) / 2, (o.ymin + o.ymax) / 2
            hw, hh = (o.xmax - o.xmin) * inner / 2, (o.ymax - o.ymin) * inner / 2
            y0, y1 = int(max(cy - hh, 0)), int(min(cy + hh, mag.shape[0] - 1)) + 1
            x0, x1 = int(max(cx - hw, 0)), int(min(cx + hw, mag.shape[1] - 1)) + 1
            out[i] = float(np.median(mag[y0:y1, x0:x1]))
    return out
