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

``--steps`` runs the other steps of issue 38's ablation instead, each one factor changed
from the demo's recipe (:data:`STEPS`: network width, epochs, crop size, and the world's
true labels for training, a diagnostic only a synthetic world allows), paired on (method,
fold, seed) with the recipe's own models of the same run, validation rows only. Each model's
chosen epoch is scored on its validation rows against the annotated labels (the book's
target) and against the world's true labels. ``--record`` then writes
``benchmarks/ablation_steps.json``, which chapter 06 shows with each step's paired effect
and its interval over the (method, fold, seed) units.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

from flowmod import pipeline
from flowmod.artefacts import write_json
from flowmod.crops import fold_crops
from flowmod.dag import Node
from flowmod.metrics import metrics
from flowmod.model import INPUT_MODES, load_model, predict
from flowmod.params import ProfileError, load_profile, parse_overrides
from flowmod.paths import repo_root
from flowmod.train import TrainSettings, train_model

#: The rule that picks the recipe, fixed before any run (and quoted by chapter 06).
RULE = ("the input scaling with the highest mean validation F1 over every method's folds and "
        "seeds")


def _overrides(pairs: list[str]) -> dict:
    """``--set key=value`` items as a dict (:func:`flowmod.params.parse_overrides`); a bad
    item ends the run with its one-line message."""
    try:
        return parse_overrides(pairs)
    except ProfileError as e:
        raise SystemExit(f"{e} (e.g. --set epochs=12)") from None


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


#: Issue 38's other steps: name -> variant -> (training overrides, profile overrides of the
#: crops, training label column). The first variant of every step is the demo's recipe.
STEPS: dict[str, dict[str, tuple[dict, dict, str]]] = {
    "recipe": {"the demo's (log input, width 32, 8 epochs, 40 px)": ({}, {}, "label")},
    "network width": {"64 (the paper's ResNet18)": ({"width": 64}, {}, "label")},
    "epochs": {"16 (the rate lowered every 6)": ({"epochs": 16, "step_size": 6}, {}, "label")},
    "crop size": {"64 px": ({}, {"crop_size": 64}, "label")},
    "training labels": {"the world's true label (diagnostic)": ({}, {}, "true_label")},
}


def _crops_folder(p, method: str) -> Path:
    """The published keyframe crops of ``method`` under ``p``, built if missing (a crop
    size other than the demo's is built beside it; the demo's is kept as a variant)."""
    node = Node("crops", method, "keyframe")
    if not pipeline.current(p, node):
        pipeline.build(p, ["05"], progress=True)
    return pipeline.published(p, node)


def _scores(out: Path, val_x, val_df: pd.DataFrame) -> dict:
    """Validation F1 of the chosen epoch's weights against both label sets."""
    prob = predict(load_model(out / "best.pt"), val_x, device="cpu")
    row = {"val_f1": metrics(val_df["label"].to_numpy(), prob)["f1"]}
    if "true_label" in val_df:
        row["val_f1_true"] = metrics(val_df["true_label"].to_numpy(), prob)["f1"]
    return row


def run_steps(methods: list[str], seeds: int, steps: list[str]) -> pd.DataFrame:
    """One row per (step, variant, method, fold, seed): validation F1s of the chosen epoch."""
    base = load_profile("demo")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for step in ["recipe", *[x for x in steps if x != "recipe"]]:
            for variant, (over, crops_over, label) in STEPS[step].items():
                p = load_profile("demo", flow_methods=methods, **crops_over) if crops_over \
                    else base
                for m in methods:
                    folder = _crops_folder(p, m)
                    for k in range(p.folds):
                        train = fold_crops(folder, p.folds, k, "train")
                        val = fold_crops(folder, p.folds, k, "val")
                        for j in range(seeds):
                            t0 = time.perf_counter()
                            out = Path(tmp) / f"{step}-{m}-{k}-{j}"
                            h = train_model(*train, *val, out, TrainSettings.of(p),
                                            seed=p.seed + k + 100 * j, progress=False,
                                            resume=False, label_col=label, **over)
                            rows.append({"step": step, "variant": variant, "method": m,
                                         "fold": k, "seed": j, **_scores(out, *val),
                                         "epoch": h.attrs["best_epoch"],
                                         "seconds": time.perf_counter() - t0})
                            print(rows[-1], flush=True)
    return pd.DataFrame(rows)


def step_effects(df: pd.DataFrame) -> pd.DataFrame:
    """Per step: the variant's mean validation F1 minus the recipe's, paired on (method,
    fold, seed), with a t interval over those units (few units: wide)."""
    from scipy import stats

    key = ["method", "fold", "seed"]
    ref = df[df["step"] == "recipe"].set_index(key)
    out = []
    for (step, variant), g in df[df["step"] != "recipe"].groupby(["step", "variant"],
                                                                   sort=False):
        g = g.set_index(key)
        for col, target in (("val_f1", "annotated"), ("val_f1_true", "true")):
            if col not in g:
                continue
            d = 100 * (g[col] - ref.loc[g.index, col])
            half = stats.t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / len(d) ** 0.5
            out.append({"step": step, "variant": variant, "scored against": target,
                        "units": len(d), "recipe (%)": 100 * ref.loc[g.index, col].mean(),
                        "variant (%)": 100 * g[col].mean(), "effect (points)": d.mean(),
                        "low": d.mean() - half, "high": d.mean() + half,
                        "seconds a model": g["seconds"].mean()})
    return pd.DataFrame(out).round(2)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--methods", nargs="+", default=["gt", "dis"])
    ap.add_argument("--modes", nargs="+", default=list(INPUT_MODES), choices=INPUT_MODES)
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="TrainSettings fields to replace (epochs=12, width=64)")
    ap.add_argument("--steps", nargs="*", default=None, choices=list(STEPS),
                    help="run these steps of the ablation (none given: all) instead of the "
                         "input scalings")
    ap.add_argument("--record", action="store_true",
                    help="also write benchmarks/ablation.json (ablation_steps.json with "
                         "--steps), the record chapter 06 shows")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    date = time.strftime("%Y-%m-%d")
    if args.steps is not None:
        df = run_steps(args.methods, args.seeds, args.steps or list(STEPS))
        table = step_effects(df)
        name = f"ablation-steps-{date}.json"
    else:
        modes = ["raw", *[m for m in args.modes if m != "raw"]]
        df = run(args.methods, modes, args.seeds, _overrides(args.set))
        table = summary(df)
        name = f"ablation-{date}.json"
    print(table.to_string(index=False))
    path = repo_root() / "benchmarks" / "results" / name
    write_json(path, {"date": date, "settings": args.set, "seconds": time.perf_counter() - t0,
                      "rows": df.to_dict("records"), "summary": table.to_dict("records")})
    print(f"written: {path}")
    if args.record and args.steps is not None:
        write_record(df, args.set, time.perf_counter() - t0, "ablation_steps.json",
                     effects=table.to_dict("records"))
    elif args.record:
        write_record(df, args.set, time.perf_counter() - t0)
    return 0


def choose(df: pd.DataFrame) -> str:
    """:data:`RULE` applied to the rows."""
    return str(df.groupby("mode", sort=False)["val_f1"].mean().idxmax())


def write_record(df: pd.DataFrame, settings: list[str], seconds: float,
                 name: str = "ablation.json", **extra: object) -> None:
    """``benchmarks/<name>``: what chapter 06 shows of this run."""
    import subprocess

    root = repo_root()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root,
                            capture_output=True, text=True).stdout.strip()
    record = {"date": time.strftime("%Y-%m-%d"), "commit": commit, "settings": settings,
              "seconds": round(seconds)}
    if name == "ablation.json":
        record.update(rule=RULE, choice=choose(df))
    write_json(root / "benchmarks" / name, {
        **record, **extra, "rows": df.drop(columns="seconds").to_dict("records")})


if __name__ == "__main__":
    sys.exit(main())
