"""The flowcheck stage (chapter 03): every flow method against the world's exact flow.

On ``flowcheck_pairs`` random pairs of each set (keyframe pairs: the far vehicles of Table
1; generalisation pairs: the near vehicles, up to ``min_distance``) whose flow every
method stores, one row per pair and method: the end-point error and Fl-all over the frame
and inside the set's vehicle boxes (``accuracy.parquet``). Chapter 03 aggregates the rows
into its accuracy table, chapter 09 reads the far boxes' error. Built on a generated world
only (real nuScenes has no exact flow).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from flowmod import dag
from flowmod.artefacts import atomic_path
from flowmod.flow.metrics import boxes_mask, epe, fl_all
from flowmod.flow.stage import FlowReader, flow_root
from flowmod.params import Params
from flowmod.progress import bar
from flowmod.select import PARTS, objects_node, read_selection
from flowmod.world import gt_flow, is_generated_world

#: The node's one file: one row per pair and method.
ACCURACY = "accuracy.parquet"
#: Its columns (px for end-point errors, % for Fl-all; NaN where no pixel of a box is valid).
COLUMNS = ("set", "pair_id", "scene", "method", "epe", "fl", "epe_box", "fl_box")


def read_accuracy(folder: Path) -> pd.DataFrame:
    """The rows of a published ``flowcheck`` node (:data:`COLUMNS`)."""
    return pd.read_parquet(Path(folder) / ACCURACY)


def bands(min_distance: float, max_distance: float) -> tuple[tuple[str, float, float], ...]:
    """(set, nearest, farthest m) of the vehicles whose boxes each set is scored in: the
    keyframe set's far band, the generalisation set's near vehicles (both ends included)."""
    return (("keyframe", min_distance, max_distance), ("general", 0.0, min_distance))


def pick_pairs(pairs: pd.DataFrame, kind: str, stored: list[set[str]], n: int,
               rng: np.random.Generator) -> list[str]:
    """``n`` pair ids of set ``kind`` drawn with ``rng`` (without replacement) among those
    every method stores (``stored``: each method's stored pair ids); none drawn when no
    pair qualifies."""
    ids = [i for i in pairs.loc[pairs["set"] == kind, "pair_id"]
           if all(i in s for s in stored)]
    if not ids:
        return []
    return [str(i) for i in rng.choice(ids, size=min(n, len(ids)), replace=False)]


def pair_rows(pid: str, flows: Mapping[str, np.ndarray], gt: np.ndarray, valid: np.ndarray,
              boxes: np.ndarray) -> list[dict[str, Any]]:
    """One pair's rows, per method of ``flows`` (each (H, W, 2) px): errors against ``gt``
    over the ``valid`` pixels and inside ``boxes`` ((N, 4) xmin, ymin, xmax, ymax px)."""
    mask = boxes_mask(boxes, gt.shape)
    inside = bool((mask & valid).any())
    return [{"pair_id": pid, "method": m, "epe": epe(f, gt, valid), "fl": fl_all(f, gt, valid),
             "epe_box": epe(f, gt, valid, mask) if inside else np.nan,
             "fl_box": fl_all(f, gt, valid, mask) if inside else np.nan}
            for m, f in flows.items()]


def measure(dataroot: str | Path, version: str, pairs: pd.DataFrame, objects: pd.DataFrame,
            readers: Mapping[str, Mapping[str, FlowReader]], *, min_distance: float,
            max_distance: float, n_pairs: int, seed: int, progress: bool = False
            ) -> pd.DataFrame:
    """:data:`COLUMNS` rows: per set (keyframe pairs: the vehicles from ``min_distance`` to
    ``max_distance``; generalisation pairs: from 0 to ``min_distance``, both ends included)
    ``n_pairs`` pairs drawn with ``seed`` (:func:`pick_pairs`, one stream: the keyframe set's
    draw, then the general set's), each method's flow against the world's exact flow
    (:func:`pair_rows`). ``readers``: ``{method: {part: FlowReader}}``."""
    rows, rng = [], np.random.default_rng(seed)
    by_id = pairs.set_index("pair_id")
    for kind, dmin, dmax in bands(min_distance, max_distance):
        mine = {m: parts[kind] for m, parts in readers.items()}
        ids = pick_pairs(pairs, kind, [set(r.pair_ids) for r in mine.values()], n_pairs, rng)
        near = objects[objects["distance"].between(dmin, dmax)]
        for pid in bar(ids, desc=f"flow accuracy ({kind})", disable=not progress):
            r = by_id.loc[pid]
            gt, valid = gt_flow(dataroot, version, r.sd_token_1, r.sd_token_2)
            boxes = near.loc[near["pair_id"] == pid, ["xmin", "ymin", "xmax", "ymax"]]
            rows += [{"set": kind, "scene": r.scene, **row} for row in pair_rows(
                pid, {m: rd.load(pid) for m, rd in mine.items()}, gt, valid,
                boxes.to_numpy(float))]
    return pd.DataFrame(rows, columns=list(COLUMNS))


def build(b: dag.Build, progress: bool) -> Mapping[str, Any]:
    """Build the ``flowcheck`` node: :data:`ACCURACY` (:data:`COLUMNS`, :func:`measure` on
    ``flowcheck_pairs`` pairs of each set)."""
    q = b.params
    sel = read_selection(b.input_dir(dag.Node("select")), b.input_dir(dag.Node("general")))
    readers = {m: {kind: FlowReader(b.input_dir(dag.Node("flow", m, kind)),
                                    flow_root(q.all) / m / "pool", m, kind) for kind in PARTS}
               for m in q.flow_methods}
    table = measure(q.dataroot_path, q.version, sel.pairs, sel.objects, readers,
                    min_distance=q.min_distance, max_distance=q.max_distance,
                    n_pairs=q.flowcheck_pairs, seed=q.seed, progress=progress)
    with atomic_path(b.start(fresh=True) / ACCURACY) as tmp:
        table.to_parquet(tmp, index=False)
    return {"pairs": int(table["pair_id"].nunique())}


def _nodes(p: Params) -> list[dag.Node]:
    return [dag.Node("flowcheck")] if is_generated_world(p) else []


def _inputs(n: dag.Node, p: Params) -> tuple[dag.Node, ...]:
    flows = tuple(dag.Node("flow", m, part) for m in p.flow_methods for part in PARTS)
    return (dag.Node("world"), objects_node("keyframe"), objects_node("general"), *flows)


#: The flowcheck stage: each flow method against the exact flow (generated worlds only).
STAGE = dag.Stage("flowcheck", 1, "03", "flowcheck",
                  "every flow method against the exact flow on random pairs",
                  nodes=_nodes, inputs=_inputs, build=build, outputs=(ACCURACY,))
