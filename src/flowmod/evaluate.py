"""The evaluation stages (chapters 07 and 08): each trained classifier scored on the test split
and on the generalisation set, the geometric baseline, the scores of a predictions table.
Scores come from :mod:`flowmod.metrics`; predictions from :mod:`flowmod.model`. Chapter 08's
analysis of the generalisation predictions (Table 4, failure reasons) is its backend's
(:mod:`flowmod.chapters.ch08_generalisation`)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from flowmod import dag, geometry
from flowmod.artefacts import atomic_path, write_json
from flowmod.crops import (
    SplitReader,
    concat_arrays,
    crops_reader,
    gather_fold,
    read_crops,
    read_samples,
)
from flowmod.environment import resolve_device
from flowmod.metrics import (
    apply_threshold,
    fit_threshold,
    metrics,
    paired_comparison,
    paper_protocol_f1,
    seed_summary,
    thin_still,
)
from flowmod.params import Params
from flowmod.select import read_table
from flowmod.train import (
    EPOCH_PROBS,
    RAW,
    model_file,
    part_index,
    part_seed,
    raw_nodes,
    records_test,
    seed_parts,
)

#: The original code's batch size (Table 2), over which its per-batch F1 was averaged: the
#: original protocol is replayed with it whatever batch this study's models trained with.
ORIGINAL_BATCH = 128

# --- the stages (chapters 07 and 08) -------------------------------------------------------


def models_of(b: dag.Build, stage: str, method: str) -> list[tuple[str, Path, str | None]]:
    """(part, best.pt, amp) of every training seed among a node's inputs of ``stage``
    (``train``, ``xtrain`` or ``wtrain``) for ``method`` (``method/input`` for ``xtrain``,
    ``method/raw`` for the raw-input models of ``train``)."""
    out = []
    for name, rec in b.inputs.items():
        if name.startswith(f"{stage}[{method}/"):
            part = name[len(f"{stage}[{method}/"):-1]
            if "/" in part:  # a model of a longer key (train[dis/raw/f0] for "dis")
                continue
            amp = rec.get("amp", "off")
            out.append((part, model_file(b.input_dir(dag.Node(stage, method, part))),
                        None if amp in (None, "off") else amp))
    return sorted(out)


def predict_models(models: list[tuple[str, Any, str | None]], x: Any, df: pd.DataFrame,
                   device: Any = "auto", in_channels: int | None = 2, folds: int = 1
                   ) -> pd.DataFrame:
    """``df`` (the rows of ``x``: (N, C, S, S)) with the models' probabilities (models:
    part, best.pt, amp); ``in_channels`` as :func:`flowmod.model.load_model` (None: the
    checkpoint's). Each model predicts in the precision it was trained and selected in.
    Seeds (one split): ``prob_<part>`` of every model on every row and ``prob`` = the
    first's (the single model the figures show). Cross-validation (``folds`` > 1): each row
    predicted by the models of its fold (``df.fold``), which never saw it: ``prob`` alone
    with one model a fold; with several training seeds a fold (parts ``f<k>s<j>``),
    ``prob_s<j>`` by the seed-j models and ``prob`` = ``prob_s0``."""
    from flowmod.model import load_model, predict  # torch: only where models predict

    if folds > 1:
        return df.assign(**_fold_probs(models, x, df, device, in_channels))
    probs = {}
    for part, path, amp in models:
        model = load_model(path, resolve_device(device), in_channels)
        probs[f"prob_{part}"] = predict(model, x, device=device, amp=amp)
    return df.assign(**probs, prob=probs[f"prob_{models[0][0]}"])


def _fold_probs(models: list[tuple[str, Any, str | None]], x: Any, df: pd.DataFrame,
                device: Any, in_channels: int | None) -> dict[str, np.ndarray]:
    """Cross-validation: per training seed j, every row's probability by its fold's seed-j
    model (``prob`` with one seed a fold, else ``prob_s<j>`` and ``prob``)."""
    from flowmod.model import load_model, predict

    fold = df["fold"].to_numpy()
    seeds = sorted({part_seed(part) for part, _, _ in models})
    out = {j: np.full(len(df), np.nan) for j in seeds}
    for part, path, amp in models:
        rows = np.flatnonzero(fold == part_index(part))
        if rows.size:
            model = load_model(path, resolve_device(device), in_channels)
            out[part_seed(part)][rows] = predict(model, x[rows], device=device, amp=amp)
    if len(seeds) == 1:
        return {"prob": out[seeds[0]]}
    return {**{f"prob_s{j}": out[j] for j in seeds}, "prob": out[seeds[0]]}


def scored_rows(read: SplitReader, folds: int, part: str = "keyframe"
                ) -> tuple[list[Any], pd.DataFrame]:
    """Every row a node's models are scored on, each fold's test rows in turn
    (:func:`flowmod.crops.gather_fold`): the test split, or with cross-validation every
    scene of the part, fold by fold."""
    got = [gather_fold(read, folds, k, "test", part) for k in range(folds)]
    if len(got) == 1:
        return got[0]
    return concat_arrays(a for a, _ in got), pd.concat([df for _, df in got], ignore_index=True)


def scored_crops(folder: Any, folds: int, part: str = "keyframe") -> tuple[Any, pd.DataFrame]:
    """``(x, index)`` of :func:`scored_rows` for a crops node."""
    arrays, df = scored_rows(crops_reader(folder), folds, part)
    return arrays[0], df


def seed_columns(df: pd.DataFrame) -> list[str]:
    """The per-seed probability columns of a predictions table."""
    cols = [c for c in df.columns if c.startswith("prob_s") and c[6:].isdigit()]
    return sorted(cols, key=lambda c: int(c[6:]))


def seed_probs(df: pd.DataFrame) -> np.ndarray:
    """(S, N) probabilities of every training seed (``prob`` alone if there are none)."""
    cols = seed_columns(df) or ["prob"]
    return df[cols].to_numpy(dtype=np.float64).T


def scored(df: pd.DataFrame, split: str, max_distance: float) -> pd.DataFrame:
    """The objects a split is scored on: all of the test split; of the generalisation set
    those within ``max_distance`` (Table 4's row, the paper's label)."""
    return df if split == "test" else df[df["distance"] <= max_distance]


def paired(a: pd.DataFrame, b: pd.DataFrame, what: str, seed: int = 0) -> dict[str, Any]:
    """:func:`flowmod.metrics.paired_comparison` of ``a``'s models minus ``b``'s (two
    predictions tables of the same objects, per-seed ``prob_s<k>``); :class:`ValueError`
    naming ``what`` if they hold different objects."""
    if not a["ann_token"].reset_index(drop=True).equals(b["ann_token"].reset_index(drop=True)):
        raise ValueError(f"{what} were scored on different objects")
    return paired_comparison(a["label"].to_numpy(), seed_probs(a), seed_probs(b),
                             a["scene"].to_numpy(), seed=seed, folds=fold_of(a))


def fold_of(df: pd.DataFrame) -> np.ndarray | None:
    """The fold of each row of a cross-validated predictions table whose rows span several
    folds (None for one split, or rows of one fold: one set of models scored them)."""
    if "fold" not in df or df["fold"].nunique() < 2:
        return None
    return df["fold"].to_numpy()


def score(df: pd.DataFrame, label_col: str = "label", seed: int = 0) -> dict[str, Any]:
    """Scores of ``df``'s models against ``df[label_col]``: per seed (or per fold), their
    mean (pooled over folds) and range, the interval of the F1 with whole scenes resampled
    (:func:`seed_summary`)."""
    return seed_summary(df[label_col].to_numpy(), seed_probs(df), df["scene"].to_numpy(),
                        instances=df.get("instance_token"), seed=seed, folds=fold_of(df))


def original_protocol(df: pd.DataFrame, epoch_probs: list[np.ndarray],
                      batch_size: int = ORIGINAL_BATCH, parts: list[str] | None = None
                      ) -> dict[str, Any]:
    """What the original code would report for each model: the best over epochs (the epoch
    chosen on the reported set) of F1 averaged per batch (of the original's 128, whatever
    batch the models trained with) on its test rows with still
    objects thinned 1 of 2; beside the clean number (best validation epoch, whole set).
    ``epoch_probs``: per model, (epochs, N) probabilities saved during training, on every
    row of ``df`` (seeds) or on its fold's rows in order (cross-validation); ``parts``: the
    models' training parts (default: the k-th is fold k's, or seed k's)."""
    fold = fold_of(df)
    y_all = df["label"].to_numpy().astype(np.int64)
    if fold is None:  # every seed on every row
        clean = [metrics(y_all, p)["f1"] for p in seed_probs(df)]
        units = [(y_all, ep) for ep in epoch_probs]
    else:  # each fold's model on its own rows
        names = parts or [f"f{k}" for k in range(len(epoch_probs))]
        cols = seed_columns(df)
        clean, units = [], []
        for part, ep in zip(names, epoch_probs, strict=True):
            rows = fold == part_index(part)
            prob = df[cols[part_seed(part)] if cols else "prob"].to_numpy()
            clean.append(metrics(y_all[rows], prob[rows])["f1"])
            units.append((y_all[rows], ep))
    original = []
    for y, ep in units:
        keep = thin_still(y)
        original.append(max(paper_protocol_f1(y[keep], e[keep], batch_size) for e in ep))
    return {"clean": float(np.nanmean(clean)), "original": float(np.nanmean(original)),
            "original_minus_clean": float(np.nanmean(original) - np.nanmean(clean)),
            "per_seed_clean": clean, "per_seed_original": original,
            "models": "folds" if fold is not None else "seeds"}


def geometric_baseline(pairs: pd.DataFrame, crops_folder: Any, seed: int = 0, folds: int = 1
                       ) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The residual baseline on one method's flow, from the flow samples stored with its
    crops (``crops_folder``: a published crops node of the keyframe part): threshold on the
    static-world residual (m/s, :mod:`flowmod.geometry`) fitted on each fold's (or the
    split's) training rows, scored on its test rows."""
    def read(split: str) -> tuple[list[Any], pd.DataFrame]:
        return [read_samples(crops_folder, split)], read_crops(crops_folder, split)[1]

    tests, thresholds = [], []
    for k in range(folds):
        part = {}
        for role in ("train", "test"):
            (smp,), sub = gather_fold(read, folds, k, role)
            sub = sub.reset_index(drop=True)
            part[role] = pd.concat([sub, geometry.residual_scores(sub, pairs, smp)], axis=1)
        t = fit_threshold(part["train"]["residual_speed"], part["train"]["label"])
        thresholds.append(t)
        tests.append(part["test"].assign(
            prob=lambda d, t=t: apply_threshold(d["residual_speed"], t).astype(float)))
    test = pd.concat(tests, ignore_index=True)
    return test, {**score(test, seed=seed), "threshold_m_s": float(np.mean(thresholds)),
                  "thresholds_m_s": thresholds}


def write_frames(folder: Path, frames: Mapping[str, pd.DataFrame],
                 scores: Mapping[str, Any]) -> None:  # pragma: no mutate block
    """``<name>.parquet`` per table and ``<name>.json`` per score record (each atomically)."""
    for name, df in frames.items():
        with atomic_path(folder / f"{name}.parquet") as tmp:
            df.to_parquet(tmp, index=False)
    for name, s in scores.items():
        write_json(folder / f"{name}.json", s)


def read_frame(folder: Path, name: str) -> pd.DataFrame:
    """One predictions table (``<name>.parquet``) of a scoring node: ``test``, ``raw``,
    ``baseline``, ``general``... (:func:`write_frames`' one reader)."""
    return pd.read_parquet(Path(folder) / f"{name}.parquet")


def read_scores(folder: Path, name: str) -> dict[str, Any]:
    """One score record (``<name>.json``) of a scoring node (``scores`` for the test
    predictions, ``original`` for the original protocol); {} where it has none."""
    f = Path(folder) / f"{name}.json"
    return json.loads(f.read_text()) if f.is_file() else {}


def predict_splits(b: dag.Build, stage: str, key: str,
                   splits: Mapping[str, tuple[Any, pd.DataFrame]],
                   in_channels: int | None = 2) -> dict[str, pd.DataFrame]:  # pragma: no mutate block
    """The one predictor of a node's models: every model of the node's inputs of ``stage``
    for ``key`` on each split's (x, index) (:func:`predict_models`: every seed on every row,
    or each row by its fold's model), written as ``<split>.parquet`` into the building
    folder. Returns the tables."""
    models = models_of(b, stage, key)
    frames = {split: predict_models(models, x, df, b.params.device, in_channels,
                                    b.params.folds)
              for split, (x, df) in splits.items()}
    write_frames(b.start(fresh=True), frames, {})
    return frames


def build_evaluate(b: dag.Build, progress: bool) -> dict[str, Any]:  # pragma: no mutate block
    """Build one ``evaluate[<method>]`` node: every model (chosen on validation) scored once
    on its test rows (``test.parquet`` + ``scores.json``: the test split, or every scene by
    its fold's model), the raw-input models on the same rows when the method has them
    (``raw.parquet`` + ``.json``), the geometric baseline on the same flow
    (``baseline.parquet`` + ``.json``), and the original protocol from the probabilities
    seed 0's models saved during training (``original.json``)."""
    q, m = b.params, b.node.method
    crops_dir = b.input_dir(dag.Node("crops", m, "keyframe"))
    x, rows = scored_crops(crops_dir, q.folds)
    preds = predict_splits(b, "train", m, {"test": (x, rows)})["test"]
    frames, scores = {}, {"scores": {"split": "test", **score(preds, seed=q.seed)}}
    raw = models_of(b, "train", f"{m}/{RAW}")
    if raw:
        frames["raw"] = predict_models(raw, x, rows, q.device, 2, q.folds)
        scores["raw"] = {"split": "test", "input_scaling": "raw",
                         **score(frames["raw"], seed=q.seed)}
    frames["baseline"], scores["baseline"] = geometric_baseline(
        read_table(b.input_dir(dag.Node("select")), "pairs"), crops_dir,
        seed=q.seed, folds=q.folds)
    models = models_of(b, "train", m)
    replayed = [(p, path) for p, path, _ in models if records_test(p)]
    scores["original"] = original_protocol(
        preds, [np.load(path.parent / EPOCH_PROBS) for _, path in replayed],
        parts=[p for p, _ in replayed])
    write_frames(b.dir, frames, scores)
    return {"n": len(preds), "seeds": len(models), "raw_models": len(raw)}


def build_generalise(b: dag.Build, progress: bool) -> dict[str, Any]:  # pragma: no mutate block
    """Build one ``generalise[<method>]`` node: the models (chosen on validation in chapter
    06) on the generalisation crops, without retraining (``general.parquet``; with
    cross-validation each scene by its fold's model)."""
    m = b.node.method
    folder = b.input_dir(dag.Node("crops", m, "general"))
    preds = predict_splits(b, "train", m,
                           {"general": scored_crops(folder, b.params.folds, "general")})
    return {"n": len(preds["general"])}


def _models(p: Params, method: str) -> tuple[dag.Node, ...]:
    return tuple(dag.Node("train", method, k) for k in seed_parts(p))


def _evaluated_models(p: Params, method: str) -> tuple[dag.Node, ...]:
    """The models ``evaluate[<method>]`` scores: the recipe's, then the raw-input ones."""
    return _models(p, method) + tuple(raw_nodes(p, method))


#: Chapter 07: the classifiers on the test split.
EVALUATE = dag.Stage(
    "evaluate", 6, "07", "metrics/{method}/test", "test predictions, baseline, scores",
    nodes=lambda p: [dag.Node("evaluate", m) for m in p.flow_methods],
    inputs=lambda n, p: (*_evaluated_models(p, n.method),
                         dag.Node("crops", n.method, "keyframe"), dag.Node("select")),
    build=build_evaluate,
    outputs=("test.parquet", "scores.json", "raw.parquet", "raw.json", "baseline.parquet",
             "baseline.json", "original.json"))
#: Chapter 08: the classifiers on the generalisation set.
GENERALISE = dag.Stage(
    "generalise", 3, "08", "metrics/{method}/general", "generalisation predictions",
    nodes=lambda p: [dag.Node("generalise", m) for m in p.flow_methods],
    inputs=lambda n, p: (*_models(p, n.method), dag.Node("crops", n.method, "general"),
                         dag.Node("general")),
    build=build_generalise, outputs=("general.parquet",))
