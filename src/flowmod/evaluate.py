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

#: Distance bins (m) of the breakdown tables (Table 1 range 30-70 m, plus the near field).

# --- the stage (notebooks 07 and 08) ---------------------------------------------------------


def metrics_dir(params: Any) -> Any:
    """``<run_dir>/metrics``."""
    return params.run_path / "metrics"


def predictions(params: Any, method: str, split: str) -> pd.DataFrame:
    """The split's objects (crop index order) with ``prob``: the model of ``method``
    (``models/<method>/best.pt``, chosen on validation) applied to its crops."""
    from flowmod import crops, train
    from flowmod.model import load_model

    model = load_model(train.models_dir(params) / method / "best.pt", resolve_device(params.device))
    x, df = crops.open_crops(crops.crops_dir(params), method, split)
    return df.assign(prob=predict(model, x, device=params.device))


def score(df: pd.DataFrame, label_col: str = "label", seed: int = 0) -> dict[str, Any]:
    """Whole-set metrics of ``df.prob`` against ``df[label_col]``, with a bootstrap 95 % CI."""
    y, p = df[label_col].to_numpy(), df["prob"].to_numpy()
    return {**metrics(y, p), "ci": bootstrap_f1_ci(y, p, seed=seed)}


def run(params: Any, split: str = "test") -> dict[str, tuple[pd.DataFrame, dict[str, Any]]]:
    """Score each method's model on ``split``; writes ``metrics/<method>.json`` and
    ``metrics/<method>_<split>.parquet`` (predictions). Returns ``{method: (preds, scores)}``."""
    from flowmod.artefacts import atomic_path, write_json

    out = {}
    for m in params.flow_methods:
        df = predictions(params, m, split)
        s = score(df, seed=params.seed)
        write_json(metrics_dir(params) / f"{m}.json", {"split": split, **s})
        with atomic_path(metrics_dir(params) / f"{m}_{split}.parquet") as tmp:
            df.to_parquet(tmp, index=False)
        out[m] = (df, s)
    return out


def geometric_baseline(params: Any, pairs: pd.DataFrame, objects: pd.DataFrame,
                       method: str) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The residual baseline on ``method``'s flow: threshold on the static-world residual
    (m/s, :mod:`flowmod.geometry`) fitted on train, scored on test."""
    from flowmod import flow, geometry

    key = objects[objects["set"] == "keyframe"]
    sub = key[key["split"].isin(["train", "test"])].reset_index(drop=True)
    res = geometry.residual_scores(
        sub, pairs, lambda pid: flow.load_flow(flow.flow_dir(params), method, pid))
    sub = pd.concat([sub, res], axis=1)
    train = sub[sub["split"] == "train"]
    t = fit_threshold(train["residual_speed"], train["label"])
    test = sub[sub["split"] == "test"].assign(
        prob=lambda d: apply_threshold(d["residual_speed"], t).astype(float))
    return test, {**score(test, seed=params.seed), "threshold_m_s": t}


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
