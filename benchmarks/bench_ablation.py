"""The classifier's input scaling, chosen on the validation folds only (issue 38).

    .venv/bin/python benchmarks/bench_ablation.py [--methods gt dis] [--modes raw centred ...]
                                                   [--seeds 2] [--set key=value ...]

Needs the demo's published crops (``make book``, or ``make run`` through chapter 05). For
every flow method, input scaling (:data:`flowmod.model.INPUT_MODES`), fold and training seed
it trains the demo's classifier (Table 2 settings of the profile, the scaling replaced) on
the fold's training rows, chooses the epoch on its validation rows (as the training stage
does) and keeps the validation F1 of that epoch. **No test row is read**: the models are
trained in a scratch folder, never published, and the fold's own scenes (its test rows) are
never opened. The validation F1 is the best over epochs, so it is optimistic by the same
selection for every scaling; the comparison between scalings is paired on (fold, seed).

Writes ``benchmarks/results/ablation-<date>.json`` and prints a table: per method and
scaling, the mean validation F1 over folds and seeds, its SD, and the mean paired difference
against ``raw`` with its SD over (fold, seed). With ``--record`` it also writes
``benchmarks/ablation.json``, the dated record chapter 06 shows (rows, the rule and its
choice: the scaling with the highest mean validation F1 over every method's folds and
seeds). Reported, never asserted.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd
import yaml

from flowmod import pipeline
from flowmod.artefacts import write_json
from flowmod.crops import fold_crops
from flowmod.dag import Node
from flowmod.model import INPUT_MODES
from flowmod.params import load_profile
from flowmod.paths import repo_root
from flowmod.train import TrainSettings, train_model

#: The rule that picks the recipe, fixed before any run (and quoted by chapter 06).
RULE = ("the input scaling with the highest mean validation F1 over every method's folds and "
        "seeds")


def _overrides(pairs: list[str]) -> dict:
    out = {}
    for item in pairs:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--set {item!r}: expected key=value, e.g. epochs=12")
        out[key.strip()] = yaml.safe_load(value)
    return out


def run(methods: list[str], modes: list[str], seeds: int, over: dict) -> pd.DataFrame:
    """One row per (method, mode, fold, seed): the validation F1 of the chosen epoch."""
    p = load_profile("demo")
    settings = TrainSettings.of(p)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for m in methods:
            folder = pipeline.published(p, Node("crops", m, "keyframe"))
            for k in range(p.folds):
                train = fold_crops(folder, p.folds, k, "train")
                val = fold_crops(folder, p.folds, k, "val")
                for j in range(seeds):
                    for mode in modes:
                        t0 = time.perf_counter()
                        out = Path(tmp) / f"{m}-{mode}-{k}-{j}"
                        h = train_model(*train, *val, out, settings, seed=p.seed + k + 100 * j,
                                        progress=False, resume=False, input_mode=mode, **over)
                        rows.append({"method": m, "mode": mode, "fold": k, "seed": j,
                                     "val_f1": h.attrs["best_f1"],
                                     "epoch": h.attrs["best_epoch"],
                                     "seconds": time.perf_counter() - t0})
                        print(rows[-1], flush=True)
    return pd.DataFrame(rows)


def summary(df: pd.DataFrame) -> pd.DataFrame:
    """Per method and mode: mean and SD of the validation F1, and the paired difference
    against raw (mean and SD over the (fold, seed) units)."""
    out = []
    for (m, mode), g in df.groupby(["method", "mode"], sort=False):
        raw = df[(df["method"] == m) & (df["mode"] == "raw")].set_index(["fold", "seed"])
        d = g.set_index(["fold", "seed"])["val_f1"] - raw["val_f1"]
        out.append({"method": m, "mode": mode, "units": len(g),
                    "val F1 (%)": round(100 * g["val_f1"].mean(), 1),
                    "SD (points)": round(100 * g["val_f1"].std(ddof=1), 1),
                    "minus raw (points)": round(100 * d.mean(), 1),
                    "SD of the difference": round(100 * d.std(ddof=1), 1)})
    return pd.DataFrame(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--methods", nargs="+", default=["gt", "dis"])
    ap.add_argument("--modes", nargs="+", default=list(INPUT_MODES), choices=INPUT_MODES)
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="TrainSettings fields to replace (epochs=12, width=64)")
    ap.add_argument("--record", action="store_true",
                    help="also write benchmarks/ablation.json, the record chapter 06 shows")
    args = ap.parse_args(argv)
    modes = ["raw", *[m for m in args.modes if m != "raw"]]
    t0 = time.perf_counter()
    df = run(args.methods, modes, args.seeds, _overrides(args.set))
    table = summary(df)
    print(table.to_string(index=False))
    date = time.strftime("%Y-%m-%d")
    path = repo_root() / "benchmarks" / "results" / f"ablation-{date}.json"
    write_json(path, {"date": date, "settings": args.set, "seconds": time.perf_counter() - t0,
                      "rows": df.to_dict("records"), "summary": table.to_dict("records")})
    print(f"written: {path}")
    if args.record:
        write_record(df, args.set, time.perf_counter() - t0)
    return 0


def choose(df: pd.DataFrame) -> str:
    """:data:`RULE` applied to the rows."""
    return str(df.groupby("mode", sort=False)["val_f1"].mean().idxmax())


def write_record(df: pd.DataFrame, settings: list[str], seconds: float) -> None:
    """``benchmarks/ablation.json``: what chapter 06 shows of this run."""
    import subprocess

    root = repo_root()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root,
                            capture_output=True, text=True).stdout.strip()
    write_json(root / "benchmarks" / "ablation.json", {
        "date": time.strftime("%Y-%m-%d"), "commit": commit, "settings": settings,
        "seconds": round(seconds), "rule": RULE, "choice": choose(df),
        "rows": df.drop(columns="seconds").to_dict("records")})


if __name__ == "__main__":
    sys.exit(main())
