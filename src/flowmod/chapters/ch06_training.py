"""Chapter 06's backend: Table 2 and what each training seed's run chose."""

from __future__ import annotations

import numpy as np
import pandas as pd

from flowmod import pipeline
from flowmod.dag import Node
from flowmod.params import Params
from flowmod.train import seed_parts


def history(p: Params, method: str, part: str = "s0") -> pd.DataFrame:
    """The published training history of one seed of ``method`` (``attrs`` best_epoch,
    best_f1, seed)."""
    node = Node("train", method, part)
    rec = pipeline.recorded(p, node) or {}
    df = pd.read_csv(pipeline.published(p, node) / "history.csv")
    df.attrs.update(best_epoch=rec.get("best_epoch"), best_f1=rec.get("best_f1"),
                    seed=rec.get("seed"))
    return df


def histories(p: Params) -> dict[str, list[pd.DataFrame]]:
    """``{method: [history per seed]}`` of the published models."""
    return {m: [history(p, m, k) for k in seed_parts(p)] for m in p.flow_methods}


def table2(params: Params) -> pd.DataFrame:
    """Table 2 of the paper, from the parameters."""
    return pd.DataFrame([
        ("Optimizer", "Batch size", params.batch_size),
        ("Optimizer", "Algorithm", "SGD"),
        ("Optimizer", "Learning rate", params.lr),
        ("Optimizer", "Weight decay", params.weight_decay),
        ("Optimizer", "Momentum", params.momentum),
        ("Scheduler", "Schedule", "StepLR (per epoch)"),
        ("Scheduler", "Step size", params.step_size),
        ("Scheduler", "Gamma", params.gamma),
        ("Training", "Epochs", params.epochs),
        ("Training", "Horizontal flip p", params.hflip_p),
        ("Training", "Models per flow method",
         f"{params.folds * params.seeds} ({params.folds} folds x {params.seeds} seeds)"
         if params.folds > 1 else f"{params.seeds} (seeds)"),
        ("Training", "Mixed precision", params.amp),
        ("Input", "Crop size (px)", params.crop_size),
        ("Input", "Flow channels scaled", params.input_scaling),
        ("Network", "ResNet18 first-stage channels", params.model_width),
    ], columns=["Function", "Hyperparameter", "Setting"])


def mean_val_f1(histories: list[pd.DataFrame]) -> float:
    """Mean over a method's models of the validation F1 of each chosen epoch (%, 0.1)."""
    return round(100 * float(np.mean([h.attrs["best_f1"] for h in histories])), 1)


def summary(histories: dict[str, list[pd.DataFrame]]) -> pd.DataFrame:
    """One row per trained model: method, seed, chosen epoch, its validation F1 (%), the
    last epoch's training loss and the seconds of training."""
    rows = []
    for m, hs in histories.items():
        for h in hs:
            best = h.attrs["best_epoch"]
            rows.append({"method": m, "seed": h.attrs.get("seed"), "chosen epoch": best,
                         "val F1 (%)": round(100 * float(h.attrs["best_f1"]), 1),
                         "last train loss": round(float(h["train_loss"].iloc[-1]), 4),
                         "training (s)": round(float(h["seconds"].sum()), 1)})
    return pd.DataFrame(rows)
