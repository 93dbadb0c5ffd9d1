"""Chapter 06's backend: Table 2 and what each training seed's run chose."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pandas as pd

from flowmod import pipeline
from flowmod.chapters.common import committed_record
from flowmod.dag import Node
from flowmod.params import Params
from flowmod.paths import repo_root
from flowmod.train import read_history, seed_parts


def history(p: Params, method: str, part: str = "s0") -> pd.DataFrame:
    """The published training history of one seed of ``method`` (``attrs`` best_epoch,
    best_f1, seed)."""
    node = Node("train", method, part)
    rec = pipeline.recorded(p, node) or {}
    df = read_history(pipeline.published(p, node))
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


# --- the input scaling, chosen on validation (benchmarks/ablation.md) ------------------------

#: The dated record of the choice (written by ``benchmarks/bench_ablation.py --record``).
ABLATION_RECORD = "benchmarks/ablation.json"


def ablation_record() -> dict[str, Any]:
    """The committed record of the validation-only choice of the input scaling: date,
    commit, the rule, its choice and one row per (method, mode, fold, seed)."""
    return json.loads((repo_root() / ABLATION_RECORD).read_text())


def ablation_table(record: dict[str, Any]) -> pd.DataFrame:
    """Validation F1 (%) of the chosen epoch, per method and fold (rows) and input scaling
    (columns), then each method's mean and the mean over methods; the rule's choice is the
    column with the highest last row."""
    df = pd.DataFrame(record["rows"]).assign(val=lambda d: 100 * d["val_f1"])
    modes = list(dict.fromkeys(df["mode"]))
    folds = df.pivot_table(index=["method", "fold"], columns="mode", values="val",
                           sort=False)[modes]
    means = df.groupby(["method", "mode"], sort=False)["val"].mean().unstack()[modes]
    means.index = pd.MultiIndex.from_tuples([(m, "mean") for m in means.index])
    overall = df.groupby("mode", sort=False)["val"].mean()[modes].to_frame("all").T
    overall.index = pd.MultiIndex.from_tuples([("every method", "mean")])
    out = pd.concat([folds.rename(index=str, level=1), means, overall]).round(1)
    return out.rename_axis(index=["method", "fold"]).reset_index()


def _count(n: int, noun: str) -> str:
    """``1 fold``, ``3 folds``."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def ablation_words(record: dict[str, Any], params: Params) -> str:
    """What the record decided and whether this run follows it."""
    df = pd.DataFrame(record["rows"])
    by = df.groupby("mode", sort=False)["val_f1"].mean()
    best, raw = by.idxmax(), by.get("raw", float("nan"))
    text = (f"The rule ({record['rule']}) chose **{record['choice']}**: mean validation F1 "
            f"{100 * by[best]:.1f} % against {100 * raw:.1f} % for the raw flow, over "
            f"{_count(df['fold'].nunique(), 'fold')} x {_count(df['seed'].nunique(), 'seed')} of "
            f"{', '.join(dict.fromkeys(df['method']))} (run of {record['date']}, commit "
            f"{record['commit']}; no test row read).")
    if params.input_scaling != record["choice"]:
        text += (f" This run's profile trains with **{params.input_scaling}** instead "
                 "(its own choice, not this record's).")
    return text


# --- the other steps of the ablation (benchmarks/ablation_steps.json) -------------------------

#: The dated record of the other steps (``benchmarks/bench_ablation.py --steps --record``).
STEPS_RECORD = "benchmarks/ablation_steps.json"


def steps_record() -> dict[str, Any] | None:
    """The committed record of the ablation's other steps, or None where there is none."""
    return committed_record(STEPS_RECORD)


def steps_table(record: dict[str, Any]) -> pd.DataFrame:
    """Per step and label set scored against: the recipe's and the variant's mean validation
    F1 (%), the paired effect (points) with its 95 % t interval over the (method, fold,
    seed) units, and the seconds a model (training cost)."""
    df = pd.DataFrame(record["effects"])
    df["95% interval (points)"] = [f"{lo:+.1f} to {hi:+.1f}" for lo, hi in
                                   zip(df["low"], df["high"], strict=True)]
    df["decided"] = np.where((df["low"] > 0) | (df["high"] < 0), "yes", "no")
    cols = ["step", "variant", "scored against", "units", "recipe (%)", "variant (%)",
            "effect (points)", "95% interval (points)", "decided", "seconds a model"]
    return df[cols].round(1)


def steps_words(record: dict[str, Any]) -> str:
    """One sentence per step against the annotated labels (the book's target): its effect,
    interval and whether it is decided; the record's date and commit."""
    df = pd.DataFrame(record["effects"])
    df = df[df["scored against"] == "annotated"]
    parts = []
    for r in df.to_dict("records"):
        sign = "decided" if r["low"] > 0 or r["high"] < 0 else "not decided"
        parts.append(f"{r['step']} ({r['variant']}): {r['effect (points)']:+.1f} points "
                     f"({r['low']:+.1f} to {r['high']:+.1f}, {sign})")
    if not parts:
        return (f"The record of {record['date']} (commit {record['commit']}) holds no step "
                "scored against the annotated labels.")
    units = int(df["units"].max())
    return (f"Against the recipe, on validation rows only ({units} paired (method, fold, "
            f"seed) units each; run of {record['date']}, commit {record['commit']}): "
            + "; ".join(parts) + ".")
