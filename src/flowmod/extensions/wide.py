"""Beyond the paper (chapter 11): the classifier trained without the paper's strict filtering.

The paper trains on keyframe pairs with vehicles 30-70 m away and then meets near vehicles
and non-keyframe pairs only at test time (Table 4); its section V expects that "the
performance might dramatically enhance if the model is trained with" them. Here the same
ResNet18, with the same Table 2 settings, is trained on every vehicle of the training scenes
from ``general_min_distance`` to ``general_max_distance`` (the generalisation range) and on
the non-keyframe pairs of those scenes where they have sweeps, then applied to the same
held-out generalisation set as Table 4 and to the paper's keyframe test split.

Stages (chapter 11; its tables are in :mod:`flowmod.chapters.ch11_all_distances`):

- ``wide``: the training set (:func:`flowmod.select.select_wide`) of the train and val
  scenes: ``pairs.parquet``, ``objects.parquet`` (``set`` keyframe or sweep);
- ``flow[<method>/wide]`` (``flow_store: pairs`` only) and ``crops[<method>/wide]``: the
  flow and crops stages on it (splits train and val);
- ``wtrain[<method>/s<k>]``: one training seed, epoch chosen on the wide validation split;
- ``wgeneralise[<method>]``: every seed on the generalisation set (``general.parquet``) and
  the keyframe test split (``test.parquet``), ``prob_s<k>`` per seed.

The selection is always built (seconds); flow, crops, models and predictions only with
``extension_build`` (on in the demo; ``make extensions`` adds the exact flow).
"""

from __future__ import annotations

from typing import Any

from flowmod import dag
from flowmod.crops import fold_crops
from flowmod.evaluate import predict_splits, scored_crops
from flowmod.select import PARTS, WIDE, open_nuscenes, read_table, select_wide, write_tables
from flowmod.train import MODEL_OUTPUTS, extension_parts, recipe, seed_index, train_seed

# --- the stages --------------------------------------------------------------------------------

def build_wide(b: dag.Build, progress: bool) -> dict[str, Any]:
    """Build the ``wide`` node: chapter 11's training selection (``pairs``, ``objects``)."""
    scenes = read_table(b.input_dir(dag.Node("select")), "scenes")
    q = b.params
    pairs, objects = select_wide(q, scenes, open_nuscenes(q.dataroot_path, q.version), progress)
    write_tables(b.start(fresh=True), {"pairs": pairs, "objects": objects})
    return {"rows": len(objects), "pairs": len(pairs),
            "sweep_pairs": int((pairs["set"] == "sweep").sum())}


def build_wtrain(b: dag.Build, progress: bool) -> dict[str, Any]:
    """Build one ``wtrain[<method>/s<k>]`` node: the classifier on the wide crops, epoch
    chosen on the wide validation split."""
    m, folds, k = b.node.method, b.params.folds, seed_index(b.node)
    folder = b.input_dir(dag.Node("crops", m, WIDE))
    info = train_seed(b, fold_crops(folder, folds, k, "train", WIDE),
                      fold_crops(folder, folds, k, "val", WIDE), progress, f"{m} all distances")
    return {**info, "recipe": recipe(b, m, WIDE)}


def build_wgeneralise(b: dag.Build, progress: bool) -> dict[str, Any]:
    """Build ``wgeneralise[<method>]``: every seed on the generalisation crops and on the
    keyframe test split (``general.parquet``, ``test.parquet``)."""
    m = b.node.method
    splits = {split: scored_crops(b.input_dir(dag.Node("crops", m, part)), b.params.folds, part)
              for split, part in (("general", "general"), ("test", "keyframe"))}
    frames = predict_splits(b, "wtrain", m, splits)
    return {"seeds": b.params.extension_seeds, "general": len(frames["general"]),
            "test": len(frames["test"])}


#: Chapter 11: the training selection at every distance (always built: seconds).
WIDE_STAGE = dag.Stage(
    "wide", 1, "11", "extensions/wide/select",
    "training pairs and objects at every distance, sweeps too",
    nodes=lambda p: [dag.Node("wide")] if p.wide_methods else [],
    inputs=lambda n, p: (dag.Node("world"), dag.Node("select")), build=build_wide,
    outputs=("pairs.parquet", "objects.parquet"))
#: Chapter 11: one fold's (or seed's) classifier trained on all distances (extension_build).
WTRAIN = dag.Stage(
    "wtrain", 1, "11", "extensions/wide/models/{method}/{part}",
    "a classifier trained on all distances",
    nodes=lambda p: [dag.Node("wtrain", m, k) for m in p.wide_methods for k in extension_parts(p)],
    inputs=lambda n, p: (dag.Node("crops", n.method, WIDE),), build=build_wtrain,
    gate="extension_build", outputs=MODEL_OUTPUTS, parallel=True)
#: Chapter 11: its seeds on the generalisation set and the keyframe test split.
WGENERALISE = dag.Stage(
    "wgeneralise", 1, "11", "extensions/wide/metrics/{method}",
    "its generalisation and test predictions",
    nodes=lambda p: [dag.Node("wgeneralise", m) for m in p.wide_methods],
    inputs=lambda n, p: (*(dag.Node("wtrain", n.method, k) for k in extension_parts(p)),
                         *(dag.Node("crops", n.method, part) for part in PARTS),
                         dag.Node("general")),
    build=build_wgeneralise, gate="extension_build", outputs=("general.parquet", "test.parquet"))
