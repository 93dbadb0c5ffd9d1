"""The evaluation stages (chapters 07 and 08): each trained classifier scored on the test split
and on the generalisation set, the geometric baseline, Table 3 and Table 4, failure reasons.
Scores come from :mod:`flowmod.metrics`; predictions from :mod:`flowmod.model`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from flowmod.metrics import (
    apply_threshold,
    fit_threshold,
    metrics,
    paper_protocol_f1,
    seed_summary,
    thin_still,
)
from flowmod.metrics import table3 as metrics_table3
from flowmod.model import predict, resolve_device

# --- the stages (chapters 07 and 08) -------------------------------------------------------


def models_of(b: Any, stage: str, method: str) -> list[tuple[str, Any, str | None]]:
    """(part, best.pt, amp) of every training seed among a node's inputs of ``stage``
    (``train``, or chapter 11's ``wtrain``) for ``method``."""
    from flowmod import dag

    out = []
    for name, rec in b.inputs.items():
        if name.startswith(f"{stage}[{method}/"):
            part = name[len(f"{stage}[{method}/"):-1]
            amp = rec.get("amp", "off")
            out.append((part, b.input_dir(dag.Node(stage, method, part)) / "best.pt",
                        None if amp in (None, "off") else amp))
    return sorted(out)


def predict_seeds(models: list[tuple[str, Any, str | None]], crops_folder: Any, split: str,
                  device: Any = "auto") -> pd.DataFrame:
    """The split's objects (crop index order) with ``prob_<part>`` of every model (in the
    precision it was trained and selected in) and ``prob`` = the first seed's (the single
    model the figures show)."""
    from flowmod.crops import read_crops

    x, df = read_crops(crops_folder, split)
    return predict_models(models, x, df, device)


def predict_models(models: list[tuple[str, Any, str | None]], x: Any, df: pd.DataFrame,
                   device: Any = "auto", in_channels: int | None = 2) -> pd.DataFrame:
    """``df`` (the rows of ``x``: (N, C, S, S)) with ``prob_<part>`` of every model (part,
    best.pt, amp) and ``prob`` = the first's; ``in_channels`` as
    :func:`flowmod.model.load_model` (None: the checkpoint's)."""
    from flowmod.model import load_model

    probs = {}
    for part, path, amp in models:
        model = load_model(path, resolve_device(device), in_channels)
        probs[f"prob_{part}"] = predict(model, x, device=device, amp=amp)
    return df.assign(**probs, prob=probs[f"prob_{models[0][0]}"])


def seed_columns(df: pd.DataFrame) -> list[str]:
    """The per-seed probability columns of a predictions table."""
    return sorted(c for c in df.columns if c.startswith("prob_s"))


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
    from flowmod.metrics import paired_comparison

    if not a["ann_token"].reset_index(drop=True).equals(b["ann_token"].reset_index(drop=True)):
        raise ValueError(f"{what} were scored on different objects")
    return paired_comparison(a["label"].to_numpy(), seed_probs(a), seed_probs(b),
                             a["scene"].to_numpy(), seed=seed)


def score(df: pd.DataFrame, label_col: str = "label", seed: int = 0) -> dict[str, Any]:
    """Scores of ``df``'s models against ``df[label_col]``: per seed, their mean and range,
    the interval of the mean F1 with whole scenes resampled (:func:`seed_summary`)."""
    return seed_summary(df[label_col].to_numpy(), seed_probs(df), df["scene"].to_numpy(),
                        instances=df.get("instance_token"), seed=seed)


def original_protocol(df: pd.DataFrame, epoch_probs: list[np.ndarray], batch_size: int = 128
                      ) -> dict[str, Any]:
    """What the original code would report for each seed: the best over epochs (the epoch
    chosen on the reported set) of F1 averaged per batch on the test split with still
    objects thinned 1 of 2; beside the clean number (best validation epoch, whole split).
    ``epoch_probs``: per seed, (epochs, N) probabilities saved during training."""
    y = df["label"].to_numpy().astype(np.int64)
    keep = thin_still(y)
    clean = [metrics(y, p)["f1"] for p in seed_probs(df)]
    original = [max(paper_protocol_f1(y[keep], e[keep], batch_size) for e in ep)
                for ep in epoch_probs]
    return {"clean": float(np.mean(clean)), "original": float(np.mean(original)),
            "original_minus_clean": float(np.mean(original) - np.mean(clean)),
            "per_seed_clean": clean, "per_seed_original": original}


def geometric_baseline(pairs: pd.DataFrame, crops_folder: Any, seed: int = 0
                       ) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The residual baseline on one method's flow, from the flow samples stored with its
    crops (``crops_folder``: a published crops node of the keyframe part): threshold on the
    static-world residual (m/s, :mod:`flowmod.geometry`) fitted on train, scored on test."""
    from flowmod import geometry
    from flowmod.crops import read_crops, read_samples

    frames, samples = [], []
    for split in ("train", "test"):
        frames.append(read_crops(crops_folder, split)[1])
        samples.append(read_samples(crops_folder, split))
    sub = pd.concat(frames, ignore_index=True)
    res = geometry.residual_scores(sub, pairs, np.concatenate(samples))
    sub = pd.concat([sub, res], axis=1)
    train = sub[sub["split"] == "train"]
    t = fit_threshold(train["residual_speed"], train["label"])
    test = sub[sub["split"] == "test"].assign(
        prob=lambda d: apply_threshold(d["residual_speed"], t).astype(float))
    return test.reset_index(drop=True), {**score(test, seed=seed), "threshold_m_s": t}


def _write(folder: Any, frames: Mapping[str, pd.DataFrame], scores: Mapping[str, Any]) -> None:
    from flowmod.artefacts import atomic_path, write_json

    for name, df in frames.items():
        with atomic_path(folder / f"{name}.parquet") as tmp:
            df.to_parquet(tmp, index=False)
    for name, s in scores.items():
        write_json(folder / f"{name}.json", s)


def run(params: Any) -> dict[str, tuple[pd.DataFrame, dict[str, Any]]]:
    """Build every stale ``evaluate[<method>]`` node (:mod:`flowmod.dag`): every training
    seed's model (chosen on validation) scored once on the test split, the geometric
    baseline on the same flow, and the original protocol from the probabilities saved during
    training. Files: ``test.parquet`` + ``scores.json`` (the models), ``baseline.parquet``
    + ``baseline.json``, ``original.json``. Returns ``{method: (predictions, scores)}``."""
    from flowmod import dag
    from flowmod.train import EPOCH_PROBS

    out = {}
    for m in params.flow_methods:
        b = dag.begin(params, dag.Node("evaluate", m))
        if not b.up_to_date:
            q = b.params
            models = models_of(b, "train", m)
            preds = predict_seeds(models, b.input_dir(dag.Node("crops", m, "keyframe")),
                                  "test", q.device)
            base, base_s = geometric_baseline(
                pd.read_parquet(b.input_dir(dag.Node("select")) / "pairs.parquet"),
                b.input_dir(dag.Node("crops", m, "keyframe")), seed=q.seed)
            epochs = [np.load(path.parent / EPOCH_PROBS) for _, path, _ in models]
            batch = int(b.inputs[f"train[{m}/{models[0][0]}]"]["params"]["batch_size"])
            _write(b.start(fresh=True), {"test": preds, "baseline": base},
                   {"scores": {"split": "test", **score(preds, seed=q.seed)},
                    "baseline": base_s, "original": original_protocol(preds, epochs, batch)})
            b.publish(n=len(preds), seeds=len(models))
        out[m] = results(params, m, "test")
    return out


def run_general(params: Any) -> dict[str, pd.DataFrame]:
    """Build every stale ``generalise[<method>]`` node: every seed's model (chosen on
    validation in chapter 06) applied to the generalisation crops, without retraining.
    Returns ``{method: predictions}``."""
    from flowmod import dag

    out = {}
    for m in params.flow_methods:
        b = dag.begin(params, dag.Node("generalise", m))
        if not b.up_to_date:
            preds = predict_seeds(models_of(b, "train", m),
                                  b.input_dir(dag.Node("crops", m, "general")), "general",
                                  b.params.device)
            _write(b.start(fresh=True), {"general": preds}, {})
            b.publish(n=len(preds))
        out[m] = results(params, m, "general")[0]
    return out


def results(params: Any, method: str, name: str = "test") -> tuple[pd.DataFrame, dict[str, Any]]:
    """Published predictions and scores: ``name`` = ``test`` (the models on the test split),
    ``baseline`` (the geometric baseline) or ``general`` (scores empty)."""
    import json

    from flowmod import dag

    node = dag.Node("generalise" if name == "general" else "evaluate", method)
    folder = dag.published(params, node)
    preds = pd.read_parquet(folder / f"{name}.parquet")
    js = folder / ("scores.json" if name == "test" else f"{name}.json")
    return preds, (json.loads(js.read_text()) if js.is_file() else {})


def original_vs_clean(params: Any, method: str) -> dict[str, Any]:
    """The published original-protocol comparison of ``method`` (see
    :func:`original_protocol`)."""
    import json

    from flowmod import dag

    return json.loads((dag.published(params, dag.Node("evaluate", method))
                       / "original.json").read_text())


def table4(preds: Mapping[str, pd.DataFrame], max_distance: float) -> pd.DataFrame:
    """Table 4 per flow method (mean over training seeds, with their range): the paper's
    range (distance <= ``max_distance``) scored against the paper's label (the previous
    keyframe pair's eq.-1 label) and, where the data set knows it, the true label at the
    frame; then the vehicles beyond that range, apart."""
    rows = []
    for m, df in preds.items():
        for rng, d0 in ((f"0-{max_distance:g} m (Table 4)", df[df["distance"] <= max_distance]),
                        (f"beyond {max_distance:g} m", df[df["distance"] > max_distance])):
            for name, col in (("paper rule (previous keyframe)", "label"),
                              ("true label at the frame", "true_label")):
                if len(d0) == 0 or col not in d0 or (d0[col] < 0).all():
                    continue
                d = d0[d0[col] >= 0]
                s = seed_summary(d[col].to_numpy(), seed_probs(d), d["scene"].to_numpy(),
                                 instances=d.get("instance_token"))
                rows.append({"method": m, "vehicles": rng, "scored against": name,
                             "objects": s["n"], "scenes": s["n_scenes"],
                             "F1 (%)": round(100 * s["f1"], 1),
                             "seed range (%)": f"{100 * s['f1_min']:.1f}-"
                                               f"{100 * s['f1_max']:.1f}",
                             "P (%)": round(100 * s["precision"], 1),
                             "R (%)": round(100 * s["recall"], 1),
                             "F1 95% CI, scenes (%)": f"{100 * s['ci'][0]:.1f}-"
                                                      f"{100 * s['ci'][1]:.1f}"})
    return pd.DataFrame(rows)


def failure_reasons(df: pd.DataFrame, boxes: pd.DataFrame, threshold: float = 0.5,
                    speed_threshold: float = 2.0, scale: float = 3.0) -> pd.DataFrame:
    """Tag each wrong prediction with the paper's two failure reasons.

    ``unclear flow``: remote (> 50 m) or slow (speed within 1 m/s of the threshold);
    ``other objects in the crop``: the box of any other annotated object of the frame (any
    category, any visibility: ``boxes`` with pair_id, instance_token and the 2D box)
    overlaps this object's crop window (the tripled square). Adds columns wrong,
    unclear_flow, crowded.
    """
    from flowmod.crops import crop_windows

    out = df.copy()
    out["wrong"] = (out["prob"] > threshold).astype(int) != out["label"]
    out["unclear_flow"] = (out["distance"] > 50) | ((out["speed"] - speed_threshold).abs() < 1)
    crowded = np.zeros(len(out), dtype=bool)
    win = crop_windows(out[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float), scale)
    by_pair = {pid: g for pid, g in boxes.groupby("pair_id")}
    for i, (pid, inst) in enumerate(zip(out["pair_id"], out["instance_token"], strict=True)):
        g = by_pair.get(pid)
        if g is None:
            continue
        others = g.loc[g["instance_token"] != inst, ["xmin", "ymin", "xmax", "ymax"]].to_numpy()
        x0, y0, n = win[i]
        crowded[i] = bool(((others[:, 0] < x0 + n) & (others[:, 2] > x0)
                           & (others[:, 1] < y0 + n) & (others[:, 3] > y0)).any())
    out["crowded"] = crowded
    return out


# --- chapter 07's tables ---------------------------------------------------------------------

def table3(params: Any) -> pd.DataFrame:
    """Table 3 of this build: one row per flow method (the classifiers, mean over training
    seeds with their range) and one per geometric baseline on the same flow, with the
    scene-level 95 % interval and what it resamples."""
    rows = [{"method": f"ResNet18 on {m} flow", **results(params, m, "test")[1]}
            for m in params.flow_methods]
    rows += [{"method": f"geometric residual, {m} flow", **results(params, m, "baseline")[1]}
             for m in params.flow_methods]
    return metrics_table3(rows)


def comparisons(params: Any) -> pd.DataFrame:
    """Paired comparisons of the classifiers on the same test objects: every pair of flow
    methods (earlier minus later in the profile's order), the exact flow against each
    estimate first."""
    from itertools import combinations

    from flowmod.metrics import comparison_table, paired_comparison

    preds = {m: results(params, m, "test")[0] for m in params.flow_methods}
    rows = {}
    for a, b in combinations(params.flow_methods, 2):
        da, db = preds[a], preds[b]
        if not da["ann_token"].equals(db["ann_token"]):
            raise ValueError(f"{a} and {b} were scored on different objects")
        rows[f"{a} - {b}"] = paired_comparison(da["label"].to_numpy(), seed_probs(da),
                                               seed_probs(db), da["scene"].to_numpy(),
                                               seed=params.seed)
    return comparison_table(rows)


def protocols(params: Any) -> pd.DataFrame:
    """Per method: the clean F1 (best validation epoch, whole test split) and what the
    original code's protocol reports for the same models (epoch chosen on the test split,
    stills thinned 1 of 2, F1 averaged per batch), means over training seeds, and
    original minus clean."""
    rows = []
    for m in params.flow_methods:
        r = original_vs_clean(params, m)
        rows.append({"method": m, "clean F1 (%)": round(100 * r["clean"], 1),
                     "original protocol F1 (%)": round(100 * r["original"], 1),
                     "original - clean (points)": round(100 * r["original_minus_clean"], 1)})
    return pd.DataFrame(rows)


def chapter07_numbers(params: Any) -> dict[str, Any]:
    """The numbers chapter 07 records for the book's other pages and the tests: per method
    the classifiers' mean test F1 (%), the baseline's, the objects and scenes scored, the
    headline method (the first estimated flow of the profile) and the protocol gap."""
    out: dict[str, Any] = {}
    gaps = []
    for m in params.flow_methods:
        s = results(params, m, "test")[1]
        out[f"test_f1_{m}"] = round(100 * s["f1"], 1)
        out[f"test_f1_min_{m}"] = round(100 * s["f1_min"], 1)
        out[f"test_f1_max_{m}"] = round(100 * s["f1_max"], 1)
        out[f"baseline_f1_{m}"] = round(100 * results(params, m, "baseline")[1]["f1"], 1)
        gaps.append(original_vs_clean(params, m)["original_minus_clean"])
        out["n_test"], out["n_test_scenes"] = s["n"], s["n_scenes"]
        out["seeds"] = s["seeds"]
    head = next((m for m in params.flow_methods if m != "gt"), params.flow_methods[0])
    s = results(params, head, "test")[1]
    out.update(headline_method=head, headline_f1=round(100 * s["f1"], 1),
               headline_precision=round(100 * s["precision"], 1),
               headline_recall=round(100 * s["recall"], 1),
               headline_ci_lo=round(100 * s["ci"][0], 1), headline_ci_hi=round(100 * s["ci"][1], 1),
               headline_baseline_f1=out[f"baseline_f1_{head}"],
               protocol_gap=round(100 * float(np.mean(gaps)), 1))
    return out


def chapter08_numbers(params: Any, table: pd.DataFrame) -> dict[str, Any]:
    """The numbers chapter 08 records: Table 4's F1 per method (paper's range, both
    labels), the objects scored, and the headline method's F1."""
    out: dict[str, Any] = {}
    t4 = table[table["vehicles"].str.endswith("(Table 4)")]
    for r in t4.to_dict("records"):
        key = "paper" if r["scored against"].startswith("paper") else "true"
        out[f"general_f1_{r['method']}_{key}"] = r["F1 (%)"]
    paper = t4[t4["scored against"].str.startswith("paper")]
    out["n_general"] = int(paper["objects"].iloc[0]) if len(paper) else 0
    head = next((m for m in params.flow_methods if m != "gt"), params.flow_methods[0])
    out["headline_general_f1"] = out.get(f"general_f1_{head}_paper", float("nan"))
    beyond = table[~table["vehicles"].str.endswith("(Table 4)")
                   & table["scored against"].str.startswith("paper")]
    for r in beyond.to_dict("records"):
        out[f"beyond_f1_{r['method']}"] = r["F1 (%)"]
    return out


def breakdown(df: pd.DataFrame, by: str, bins: Any = None) -> pd.DataFrame:
    """:func:`flowmod.metrics.breakdown` of a predictions table: every training seed (F1 the
    mean over seeds), with the scene-level interval and the object count of each group."""
    from flowmod.metrics import breakdown as _breakdown

    return _breakdown(df, df["label"], seed_probs(df), by=by, bins=bins,
                      groups=df["scene"].to_numpy())


def failure_shares(tagged: pd.DataFrame) -> pd.DataFrame:
    """Share (%) of all objects and of wrong predictions with each failure reason."""
    cols = ["unclear_flow", "crowded"]
    names = {"unclear_flow": "remote or slow", "crowded": "other objects in the crop"}
    out = pd.DataFrame({
        "reason": [names[c] for c in cols],
        "all objects (%)": [100 * float(tagged[c].mean()) for c in cols],
        "wrong predictions (%)": [100 * float(tagged.loc[tagged["wrong"], c].mean())
                                  if tagged["wrong"].any() else 0.0 for c in cols],
    })
    return out.round(1)


def failure_examples(tagged: pd.DataFrame, n: int = 3) -> pd.DataFrame:
    """Up to ``n`` wrong predictions of each kind (remote or slow only, then crowded), with a
    ``title`` for the figure."""
    wrong = tagged[tagged["wrong"]]
    out = pd.concat([wrong[wrong["unclear_flow"] & ~wrong["crowded"]].head(n),
                     wrong[wrong["crowded"]].head(n)])
    return out.assign(title=[("crowded" if c else "remote/slow") + f", {d:.0f} m, {s:.1f} m/s"
                             for c, d, s in zip(out["crowded"], out["distance"], out["speed"],
                                                strict=True)])
