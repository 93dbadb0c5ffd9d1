"""Chapter 03's backend: what each flow method gives, against the world's exact flow."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from flowmod import world
from flowmod.chapters import common
from flowmod.flow import FlowReader, boxes_mask, epe, fl_all
from flowmod.params import Params

#: Random pairs of each set on which the accuracy table measures every method.
ACCURACY_PAIRS = 12


def run_summary(readers: Mapping[str, Mapping[str, FlowReader]]) -> pd.DataFrame:
    """One row per method and part: pairs, median estimation seconds per pair."""
    return pd.DataFrame([
        {"method": m, "part": part, "pairs": len(r.index),
         "median s / pair": float(r.index["seconds"].median()) if len(r.index) else float("nan")}
        for m, parts in readers.items() for part, r in parts.items()])


def accuracy_table(params: Params, pairs: pd.DataFrame, objects: pd.DataFrame,
                   readers: Mapping[str, Mapping[str, FlowReader]], n_pairs: int = 20,
                   seed: int = 0) -> pd.DataFrame:
    """EPE / Fl-all against the world's exact flow, overall and inside far (keyframe set,
    min-max distance) and near (generalisation set, < min_distance) vehicle boxes, with the
    median seconds per pair; on ``n_pairs`` random pairs of each set whose flow every reader
    stores (synthetic world only).
    ``readers``: ``{method: {part: FlowReader}}``."""
    rng = np.random.default_rng(seed)
    rows = []
    for kind, dmin, dmax in (("keyframe", params.min_distance, params.max_distance),
                             ("general", 0.0, params.min_distance)):
        ids = pairs.loc[pairs["set"] == kind, "pair_id"].to_numpy()
        ids = np.array([i for i in ids if all(i in parts[kind] for parts in readers.values())])
        if len(ids) == 0:
            continue
        pick = rng.choice(ids, size=min(n_pairs, len(ids)), replace=False)
        sub = pairs.set_index("pair_id").loc[pick]
        gts = {pid: world.gt_flow(params.dataroot_path, params.version, r.sd_token_1,
                                  r.sd_token_2) for pid, r in sub.iterrows()}
        for method, parts in readers.items():
            reader = parts[kind]
            acc: dict[str, list[float]] = {"epe": [], "fl": [], "epe_box": [], "fl_box": [],
                                           "scene": []}
            for pid, (gt, valid) in gts.items():
                est = reader.load(pid)
                obj = objects[(objects["pair_id"] == pid) & objects["distance"].between(dmin, dmax)]
                mask = boxes_mask(obj[["xmin", "ymin", "xmax", "ymax"]].to_numpy(), gt.shape)
                acc["epe"].append(epe(est, gt, valid))
                acc["fl"].append(fl_all(est, gt, valid))
                if (mask & valid).any():
                    acc["epe_box"].append(epe(est, gt, valid, mask))
                    acc["fl_box"].append(fl_all(est, gt, valid, mask))
                    acc["scene"].append(sub.loc[pid, "scene"])
            secs = reader.index["seconds"]
            rows.append({
                "set": kind, "vehicles": f"{dmin:g}-{dmax:g} m", "method": method,
                "EPE all (px)": np.mean(acc["epe"]), "Fl-all (%)": np.mean(acc["fl"]),
                "EPE boxes (px)": np.mean(acc["epe_box"]) if acc["epe_box"] else np.nan,
                "EPE boxes 95% CI, scenes (px)": common.epe_ci(acc["epe_box"], acc["scene"], seed),
                "Fl-all boxes (%)": np.mean(acc["fl_box"]) if acc["fl_box"] else np.nan,
                "s / pair": float(np.nanmedian(secs)) if secs.notna().any() else np.nan,
                "pairs": len(gts),
            })
    return pd.DataFrame(rows)


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
