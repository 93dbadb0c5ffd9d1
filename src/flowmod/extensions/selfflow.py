"""Beyond the paper (chapter 12): FastFlowNet trained here from scratch, as a stage.

The training itself (losses, batches, held-out scoring) is :mod:`flowmod.flow.selftrain`;
this module declares the ``selfflow[<mode>]`` nodes (``selfflow_modes``: ``photometric``,
``supervised``, ``finetune``), built only with ``selfflow_build`` (``make selfflow``). The
chapter's tables are in :mod:`flowmod.chapters.ch12_self_trained_flow`.
"""

from __future__ import annotations

import functools
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from flowmod import dag, world
from flowmod.artefacts import atomic_path, save_checkpoint, write_json
from flowmod.flow.networks import FastFlowNetFlow
from flowmod.select import read_table


def build(b: dag.Build, progress: bool) -> dict[str, Any]:
    """Build one ``selfflow[<mode>]`` node: FastFlowNet trained on fold 0's training-scene
    pairs (``finetune``: from ``selfflow_init``, photometrically, on its test scenes' pairs,
    as a user would adapt the weights to their own unlabelled frames), its curve on
    validation-scene pairs, and scored once on test-scene pairs at the end: ``weights.pt``
    (a FastFlowNet state_dict), ``history.csv`` and ``eval.json`` (the network's and the
    baselines' metrics on the validation and on the test pairs)."""
    from flowmod.flow.selftrain import (  # torch: imported where the network trains
        FramePairs,
        SelfFlowError,
        baselines,
        cache_gt,
        fold0_pairs,
        held_out,
        heldout_pairs,
        sample_pairs,
        score_model,
        train_flow,
        validation_pairs,
    )

    q, mode = b.params, str(b.node.part)
    root = q.dataroot_path
    synthetic = world.is_synthetic(root, q.version)
    if mode == "supervised" and not synthetic:
        raise SelfFlowError(
            f"selfflow_modes has 'supervised', but {root} ({q.version}) is not a generated "
            "world: there is no exact flow to supervise with; use selfflow_modes=[photometric]")
    sel = b.input_dir(dag.Node("select"))
    pairs = read_table(sel, "pairs")
    role = "test" if mode == "finetune" else "train"
    train = sample_pairs(fold0_pairs(pairs, q.folds, role), q.selfflow_pairs, (q.seed, 0))
    val = validation_pairs(pairs, q.selfflow_eval_pairs, q.seed, q.folds)
    test = heldout_pairs(pairs, q.selfflow_eval_pairs, q.seed, q.folds)
    if train.empty or val.empty or test.empty:
        raise SelfFlowError(f"no training ({len(train)}), validation ({len(val)}) or test "
                            f"({len(test)}) pair in chapter 02's selection: run chapter 02 "
                            "first")
    init = init_weights(q) if mode == "finetune" else None  # before any work
    work = b.start(fresh=q.force)
    gt_files = (cache_gt(train, root, q.version, q.flow_scale, work / "gt", progress)
                if mode == "supervised" else None)
    data = FramePairs([(root / r.path_1, root / r.path_2) for r in train.itertuples()],
                      q.flow_scale, gt_files)
    objects = read_table(sel, "objects")
    val_data = held_out(val, objects, root, q.version, synthetic)
    model, hist = train_flow(
        data, mode, work, iters=q.selfflow_iters, batch=q.selfflow_batch, lr=q.selfflow_lr,
        crop=q.selfflow_crop, smooth=q.selfflow_smooth, seed=q.seed,
        evaluate=functools.partial(score_model, data=val_data, scale=q.flow_scale),
        eval_every=q.selfflow_eval_every, progress=progress,
        desc=f"train fastflownet ({mode})", device=q.device, init=init,
        window=q.selfflow_window,
        warmup=q.selfflow_warmup if mode == "photometric" else 0)
    save_checkpoint({k: v.cpu() for k, v in model.state_dict().items()}, work / WEIGHTS)
    with atomic_path(work / HISTORY) as tmp:
        hist.to_csv(tmp, index=False)
    test_data = held_out(test, objects, root, q.version, synthetic)  # read once, at the end
    final = {k[len("val_"):]: v for k, v in hist.iloc[-1].items() if k.startswith("val_")}
    write_json(work / EVALUATION, {
        "mode": mode, "steps": int(hist["step"].iloc[-1]),
        "seconds_per_step": float(hist["seconds"].median()),
        "train_pairs": len(train), "train_scenes": sorted(train["scene"].unique()),
        "val_pairs": len(val), "heldout_pairs": len(test),
        "validation": {"fastflownet": final,
                       "baselines": baselines(val_data, q.flow_scale)},
        "fastflownet": score_model(model, test_data, q.flow_scale),
        "baselines": baselines(test_data, q.flow_scale)})
    shutil.rmtree(work / "gt", ignore_errors=True)
    (work / "last.pt").unlink(missing_ok=True)
    return {"mode": mode, "steps": int(hist["step"].iloc[-1])}


def init_weights(q: Any) -> Any:
    """The file ``selfflow_init`` names (the finetune mode's start), or one clear line."""
    from flowmod.flow.selftrain import SelfFlowError

    path = q.path(q.selfflow_init)
    if not path.is_file():
        raise SelfFlowError(f"selfflow_init={q.selfflow_init}: no such file ({path}); "
                            "`make flownet` makes the shipped weights, or name another "
                            "FastFlowNet state_dict")
    return path


def build_shipped(b: dag.Build, progress: bool) -> dict[str, Any]:
    """Build the ``shipped`` node: the FastFlowNet weights ``shipped_weights`` names beside
    the zero flow, Farneback and DIS (:func:`flowmod.flow.selftrain.reference_estimators`)
    on ``selfflow_eval_pairs`` keyframe pairs of this book's world drawn with the seed
    (scenes the weights never saw and no recipe of theirs was chosen on: their held-out
    test set). Writes ``world.parquet`` (per method: EPE and Fl-all over the frame and in
    the far vehicles' boxes, s/pair), ``pairs.parquet`` (per pair and method: its id,
    scene, first frame, EPE over the frame and in the boxes, px) and ``example.npz`` (the
    first pair's exact, DIS and network flow, float16, and its valid mask); empty tables
    on data without exact flow (real nuScenes: nothing to measure against)."""
    from flowmod.flow.selftrain import (
        DIS_PRESET,
        SHIPPED,
        SelfFlowError,
        held_out,
        mean_metrics,
        pair_metrics,
        reference_estimators,
        sample_pairs,
    )

    q = b.params
    weights = q.path(q.shipped_weights)
    if not weights.is_file():
        raise SelfFlowError(f"shipped_weights={q.shipped_weights}: no such file ({weights}); "
                            "`make flownet` makes the shipped weights")
    work = b.start(fresh=True)
    if not world.is_synthetic(q.dataroot_path, q.version):
        _write_shipped(work, pd.DataFrame(), pd.DataFrame(), {})
        return {"pairs": 0, "exact_flow": False}
    sel = b.input_dir(dag.Node("select"))
    pairs = read_table(sel, "pairs")
    pick = sample_pairs(pairs[pairs["set"] == "keyframe"], q.selfflow_eval_pairs, (q.seed, 12))
    data = held_out(pick, read_table(sel, "objects"), q.dataroot_path,
                    q.version, synthetic=True)
    ests = {**reference_estimators(q.flow_scale),
            SHIPPED: FastFlowNetFlow(weights, device=q.device, scale=q.flow_scale).estimate}
    flows: dict[str, np.ndarray] = {}
    table, per_pair = [], []
    for name, est in ests.items():
        rows, seconds = pair_metrics(_keep_first(est, flows, name), data)
        table.append({"method": name, **mean_metrics(rows),
                      "seconds_per_pair": seconds / len(rows)})
        per_pair += [{"pair_id": r.pair_id, "scene": r.scene, "path_1": r.path_1,
                      "method": name, "epe": m["epe"], "epe_boxes": m["epe_boxes"]}
                     for r, m in zip(pick.itertuples(), rows, strict=True)]
    example = {"exact": data.gt[0], "valid": data.valid[0],
               **{k: flows[k] for k in (f"dis ({DIS_PRESET})", SHIPPED)}}
    _write_shipped(work, pd.DataFrame(table), pd.DataFrame(per_pair), example)
    return {"pairs": len(pick), "exact_flow": True}


def _keep_first(est: Any, flows: dict[str, np.ndarray], name: str) -> Any:
    """``est`` that also keeps its first pair's flow in ``flows[name]``."""
    def run(a: np.ndarray, c: np.ndarray) -> np.ndarray:
        f = est(a, c)
        flows.setdefault(name, f)
        return f
    return run


#: A ``selfflow`` node's files: the trained weights, the training history, the evaluation.
WEIGHTS, HISTORY, EVALUATION = "weights.pt", "history.csv", "eval.json"
#: The ``shipped`` node's files: its table, the per-pair errors and one pair's flows.
SHIPPED_TABLE, SHIPPED_PAIRS, SHIPPED_EXAMPLE = "world.parquet", "pairs.parquet", "example.npz"


def read_selfflow(folder: Path) -> tuple[pd.DataFrame, dict[str, Any]]:
    """A published ``selfflow`` node's training history and evaluation record."""
    return (pd.read_csv(Path(folder) / HISTORY),
            json.loads((Path(folder) / EVALUATION).read_text()))


def selfflow_weights(folder: Path) -> Path:
    """A published ``selfflow`` node's FastFlowNet weights (a ``fastflownet_weights`` value)."""
    return Path(folder) / WEIGHTS


def read_shipped(folder: Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The published ``shipped`` node's table (one row per method) and per-pair errors."""
    return (pd.read_parquet(Path(folder) / SHIPPED_TABLE),
            pd.read_parquet(Path(folder) / SHIPPED_PAIRS))


def read_shipped_example(folder: Path) -> dict[str, np.ndarray]:
    """The published ``shipped`` node's example pair: each method's flow and the valid mask."""
    with np.load(Path(folder) / SHIPPED_EXAMPLE) as z:
        return {k: z[k] for k in z.files}


def _write_shipped(folder: Any, table: pd.DataFrame, boxes: pd.DataFrame,
                   arrays: dict[str, np.ndarray]) -> None:
    """The ``shipped`` node's files, each written atomically."""
    for name, df in ((SHIPPED_TABLE, table), (SHIPPED_PAIRS, boxes)):
        with atomic_path(folder / name) as tmp:
            df.to_parquet(tmp, index=False)
    with atomic_path(folder / SHIPPED_EXAMPLE) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **{k: (v if v.dtype == bool else v.astype(np.float16))
                        for k, v in arrays.items()})


#: Chapter 12: the shipped weights on held-out pairs of this book's world (always built).
SHIPPED_STAGE = dag.Stage(
    "shipped", 2, "12", "selfflow/shipped",
    "the shipped FastFlowNet weights and the reference methods on held-out pairs",
    nodes=lambda p: [dag.Node("shipped")],
    inputs=lambda n, p: (dag.Node("world"), dag.Node("select")), build=build_shipped,
    outputs=(SHIPPED_TABLE, SHIPPED_PAIRS, SHIPPED_EXAMPLE))
#: Chapter 12: FastFlowNet trained from scratch (with ``selfflow_build``).
STAGE = dag.Stage("selfflow", 2, "12", "selfflow/{part}",
                  "FastFlowNet trained from scratch, validation and test end-point error",
                  nodes=lambda p: [dag.Node("selfflow", None, mode) for mode in p.selfflow_modes],
                  inputs=lambda n, p: (dag.Node("world"), dag.Node("select")), build=build,
                  gate="selfflow_build", outputs=(WEIGHTS, HISTORY, EVALUATION))
