"""The evaluation stages (chapters 07 and 08): each trained classifier scored on the test split
and on the generalisation set, the geometric baseline, Table 3 and Table 4, failure reasons.
Scores come from :mod:`flowmod.metrics`; predictions from :mod:`flowmod.model`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from flowmod.metrics import apply_threshold, bootstrap_f1_ci, fit_threshold, metrics
from flowmod.model import predict, resolve_device

# --- the stages (chapters 07 and 08) -------------------------------------------------------


def predict_split(model_file: Any, crops_folder: Any, split: str, device: Any = "auto"
                  ) -> pd.DataFrame:
    """The split's objects (crop index order) with ``prob``: the model in ``model_file``
    (a best.pt) applied to the split's crops in ``crops_folder``."""
    from flowmod.crops import read_crops
    from flowmod.model import load_model

    model = load_model(model_file, resolve_device(device))
    x, df = read_crops(crops_folder, split)
    return df.assign(prob=predict(model, x, device=device))


def score(df: pd.DataFrame, label_col: str = "label", seed: int = 0) -> dict[str, Any]:
    """Whole-set metrics of ``df.prob`` against ``df[label_col]``, with a bootstrap 95 % CI."""
    y, p = df[label_col].to_numpy(), df["prob"].to_numpy()
    return {**metrics(y, p), "ci": bootstrap_f1_ci(y, p, seed=seed)}


def geometric_baseline(pairs: pd.DataFrame, objects: pd.DataFrame, load_flow: Any,
                       seed: int = 0) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The residual baseline on one method's flow (``load_flow(pair_id)``): threshold on the
    static-world residual (m/s, :mod:`flowmod.geometry`) fitted on train, scored on test."""
    from flowmod import geometry

    key = objects[objects["set"] == "keyframe"]
    sub = key[key["split"].isin(["train", "test"])].reset_index(drop=True)
    res = geometry.residual_scores(sub, pairs, load_flow)
    sub = pd.concat([sub, res], axis=1)
    train = sub[sub["split"] == "train"]
    t = fit_threshold(train["residual_speed"], train["label"])
    test = sub[sub["split"] == "test"].assign(
        prob=lambda d: apply_threshold(d["residual_speed"], t).astype(float))
    return test, {**score(test, seed=seed), "threshold_m_s": t}


def _write(folder: Any, frames: Mapping[str, pd.DataFrame], scores: Mapping[str, Any]) -> None:
    from flowmod.artefacts import atomic_path, write_json

    for name, df in frames.items():
        with atomic_path(folder / f"{name}.parquet") as tmp:
            df.to_parquet(tmp, index=False)
    for name, s in scores.items():
        write_json(folder / f"{name}.json", s)


def run(params: Any) -> dict[str, tuple[pd.DataFrame, dict[str, Any]]]:
    """Build every stale ``evaluate[<method>]`` node (:mod:`flowmod.dag`): the model chosen on
    validation scored once on the test split, and the geometric baseline on the same flow.
    Files: ``test.parquet`` + ``scores.json`` (the model), ``baseline.parquet`` +
    ``baseline.json``. Returns ``{method: (predictions, scores)}`` of the model."""
    from flowmod import dag
    from flowmod.flow import FlowReader

    out = {}
    for m in params.flow_methods:
        b = dag.begin(params, dag.Node("evaluate", m))
        if not b.up_to_date:
            q = b.params
            preds = predict_split(b.input_dir(dag.Node("train", m)) / "best.pt",
                                  b.input_dir(dag.Node("crops", m, "keyframe")), "test",
                                  q.device)
            sel = b.input_dir(dag.Node("select"))
            base, base_s = geometric_baseline(
                pd.read_parquet(sel / "pairs.parquet"), pd.read_parquet(sel / "objects.parquet"),
                FlowReader(params, m, "keyframe").load, seed=q.seed)
            d = b.start(fresh=True)
            _write(d, {"test": preds, "baseline": base},
                   {"scores": {"split": "test", **score(preds, seed=q.seed)}, "baseline": base_s})
            b.publish(n=len(preds))
        out[m] = results(params, m, "test")
    return out


def run_general(params: Any) -> dict[str, pd.DataFrame]:
    """Build every stale ``generalise[<method>]`` node: each model (chosen on validation in
    chapter 06) applied to the generalisation crops, without retraining. Returns
    ``{method: predictions}``."""
    from flowmod import dag

    out = {}
    for m in params.flow_methods:
        b = dag.begin(params, dag.Node("generalise", m))
        if not b.up_to_date:
            preds = predict_split(b.input_dir(dag.Node("train", m)) / "best.pt",
                                  b.input_dir(dag.Node("crops", m, "general")), "general",
                                  b.params.device)
            _write(b.start(fresh=True), {"general": preds}, {})
            b.publish(n=len(preds))
        out[m] = results(params, m, "general")[0]
    return out


def results(params: Any, method: str, name: str = "test") -> tuple[pd.DataFrame, dict[str, Any]]:
    """Published predictions and scores: ``name`` = ``test`` (the model on the test split),
    ``baseline`` (the geometric baseline) or ``general`` (scores empty)."""
    import json

    from flowmod import dag

    node = dag.Node("generalise" if name == "general" else "evaluate", method)
    folder = dag.published(params, node)
    preds = pd.read_parquet(folder / f"{name}.parquet")
    js = folder / ("scores.json" if name == "test" else f"{name}.json")
    return preds, (json.loads(js.read_text()) if js.is_file() else {})


def table4(preds: Mapping[str, pd.DataFrame]) -> pd.DataFrame:
    """Table 4 per flow method, scored against the paper's label (the previous keyframe
    pair's eq.-1 label) and, where the data set knows it, the true per-frame label."""
    rows = []
    for m, df in preds.items():
        for name, col in (("paper rule (previous keyframe)", "label"),
                          ("true label at the frame", "true_label")):
            if col not in df or (df[col] < 0).all():
                continue
            d = df[df[col] >= 0]
            s = metrics(d[col], d["prob"])
            rows.append({"method": m, "scored against": name, "n": s["n"],
                         "F1 (%)": round(100 * s["f1"], 1),
                         "Precision (%)": round(100 * s["precision"], 1),
                         "Recall (%)": round(100 * s["recall"], 1)})
    return pd.DataFrame(rows)


def failure_reasons(df: pd.DataFrame, threshold: float = 0.5, speed_threshold: float = 2.0,
                    scale: float = 3.0) -> pd.DataFrame:
    """Tag each wrong prediction with the paper's two failure reasons.

    ``unclear flow``: remote (> 50 m) or slow (speed within 1 m/s of the threshold);
    ``other objects in the crop``: another object's box overlaps this object's crop window
    (the tripled square). Adds columns wrong, unclear_flow, crowded.
    """
    from flowmod.crops import crop_windows

    out = df.copy()
    out["wrong"] = (out["prob"] > threshold).astype(int) != out["label"]
    out["unclear_flow"] = (out["distance"] > 50) | ((out["speed"] - speed_threshold).abs() < 1)
    crowded = np.zeros(len(out), dtype=bool)
    boxes = out[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float)
    win = crop_windows(boxes, scale)
    for _, idx in out.groupby("pair_id").indices.items():
        for i in idx:
            x0, y0, n = win[i]
            others = boxes[[j for j in idx if j != i]]
            if len(others):
                crowded[i] = bool(((others[:, 0] < x0 + n) & (others[:, 2] > x0)
                                   & (others[:, 1] < y0 + n) & (others[:, 3] > y0)).any())
    out["crowded"] = crowded
    return out
