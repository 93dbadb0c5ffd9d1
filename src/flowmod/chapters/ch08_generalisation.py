"""Chapter 08's backend: Table 4 and its numbers, F1 by distance and speed, the paper's two
failure reasons and their examples (chapter 11 reads :func:`table4` for its models)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from flowmod.chapters.common import breakdown, headline_method, results
from flowmod.crops import crop_windows
from flowmod.evaluate import fold_of, seed_probs
from flowmod.metrics import CI_COLUMN, ci_text, points, sd_cells, seed_summary, span
from flowmod.params import Params

#: Distance bins of the F1-by-distance figure (m): 10 m steps, Table 4's range and beyond.
DISTANCE_EDGES = (0, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100.01)
#: Speed bins of the F1-by-speed figure (m/s): either side of the paper's 2 m/s threshold.
SPEED_EDGES = (0, 1, 2, 3, 5, 10, 40)
#: Wrong predictions of each kind the failure figure shows, in one row.
FAILURE_EXAMPLES = 3
#: Columns of the failure figure: both kinds of wrong prediction in one row.
FAILURE_COLUMNS = 2 * FAILURE_EXAMPLES
#: The scene clip: width of each half of a frame (px) and frames per second.
CLIP_WIDTH, CLIP_FPS = 640, 6


def predictions(params: Params) -> dict[str, pd.DataFrame]:
    """``{method: generalisation predictions}`` of the paper's classifiers."""
    return {m: results(params, m, "general")[0] for m in params.flow_methods}


def table(params: Params, preds: dict[str, pd.DataFrame] | None = None) -> pd.DataFrame:
    """Table 4 of this build (:func:`table4` at ``general_max_distance``) of ``preds``
    (default: :func:`predictions`)."""
    return table4(predictions(params) if preds is None else preds,
                  params.general_max_distance)


def by_distance(preds: dict[str, pd.DataFrame]) -> dict[str, pd.DataFrame]:
    """Per method, F1 per distance bin (:data:`DISTANCE_EDGES`) with its interval over
    scenes and seeds and the objects in each bin (:func:`~flowmod.chapters.common.breakdown`)."""
    return {m: breakdown(df, "distance", list(DISTANCE_EDGES)) for m, df in preds.items()}


def by_speed(preds: dict[str, pd.DataFrame]) -> dict[str, pd.DataFrame]:
    """Per method, F1 per speed bin (:data:`SPEED_EDGES`), as :func:`by_distance`."""
    return {m: breakdown(df, "speed", list(SPEED_EDGES)) for m, df in preds.items()}


def numbers(params: Params, table: pd.DataFrame) -> dict[str, Any]:
    """The numbers chapter 08 records: Table 4's F1 per method (paper's range, both
    labels), the objects scored, and the headline method's F1 with its interval (text) and
    the F1 of calling every vehicle moving on the same objects."""
    out: dict[str, Any] = {}
    t4 = table[table["vehicles"].str.endswith("(Table 4)")]
    for r in t4.to_dict("records"):
        key = "paper" if r["scored against"].startswith("paper") else "true"
        out[f"general_f1_{r['method']}_{key}"] = r["F1 (%)"]
    paper = t4[t4["scored against"].str.startswith("paper")]
    out["n_general"] = int(paper["objects"].iloc[0]) if len(paper) else 0
    head = headline_method(params)
    out["headline_general_f1"] = out.get(f"general_f1_{head}_paper", float("nan"))
    row = paper[paper["method"] == head]
    out["headline_general_ci"] = (str(row["F1 95% CI, scenes and seeds (%)"].iloc[0])
                                  if len(row) else "undefined")
    out["headline_general_chance"] = (float(row["always moving F1 (%)"].iloc[0]) if len(row)
                                      else float("nan"))
    beyond = table[~table["vehicles"].str.endswith("(Table 4)")
                   & table["scored against"].str.startswith("paper")]
    for r in beyond.to_dict("records"):
        out[f"beyond_f1_{r['method']}"] = r["F1 (%)"]
    return out


def failures(params: Params, preds: pd.DataFrame, boxes: pd.DataFrame
             ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The paper's two failure reasons on ``preds`` (:func:`failure_reasons`
    with the profile's threshold and crop scale): (each reason's share among all objects
    and among the wrong predictions, the tagged rows)."""
    tagged = failure_reasons(preds, boxes, speed_threshold=params.speed_threshold,
                             scale=params.crop_scale)
    return failure_shares(tagged), tagged


#: A reason that holds for at least this share of all objects (%) cannot be told apart
#: from the objects it does not hold for: too few are left to compare with.
UNTESTABLE = 95.0


def failure_words(shares: pd.DataFrame) -> str:
    """Whether each failure reason explains the wrong predictions: one that is no commoner
    among them than among all objects (share ratio under 1.05) does not; one that holds for
    nearly every object (:data:`UNTESTABLE`) cannot be tested here; an undefined share (no
    wrong prediction) is said so."""
    out = []
    for _, r in shares.iterrows():
        a, w = r["all objects (%)"], r["wrong predictions (%)"]
        if pd.isna(w) or not a:
            out.append(f"*{r['reason']}*: undefined (no wrong prediction or no such object)")
        elif a >= UNTESTABLE:
            out.append(f"*{r['reason']}* holds for {a:.1f} % of all objects, so this world "
                       "cannot test it: nearly every crop has it, right or wrong")
        elif w / a < 1.05:
            out.append(f"*{r['reason']}* holds for {w:.1f} % of the wrong predictions and "
                       f"{a:.1f} % of all objects: no commoner among the errors, so it does "
                       "not explain them")
        else:
            out.append(f"*{r['reason']}* holds for {w:.1f} % of the wrong predictions against "
                       f"{a:.1f} % of all objects ({w / a:.1f} times as common)")
    return "; ".join(out) + "."


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
                                 folds=fold_of(d))
                rows.append({"method": m, "vehicles": rng, "scored against": name,
                             "objects": s["n"], "scenes": s["n_scenes"],
                             "F1 (%)": round(100 * s["f1"], 1),
                             f"{s['unit']} range (%)": span(s["f1_min"], s["f1_max"]),
                             "P (%)": round(100 * s["precision"], 1),
                             "R (%)": round(100 * s["recall"], 1),
                             **sd_cells(s),
                             "balanced accuracy (%)": points(s["balanced_accuracy"]),
                             "always moving F1 (%)": points(s["always_moving_f1"]),
                             CI_COLUMN: ci_text(s["ci"], s["n_scenes"])})
    return pd.DataFrame(rows)


def failure_reasons(df: pd.DataFrame, boxes: pd.DataFrame, threshold: float = 0.5,
                    speed_threshold: float = 2.0, scale: float = 3.0) -> pd.DataFrame:  # pragma: no mutate block
    """Tag each wrong prediction with the paper's two failure reasons.

    ``unclear flow``: remote (> 50 m) or slow (speed within 1 m/s of the threshold);
    ``other objects in the crop``: the box of any other annotated object of the frame (any
    category, any visibility: ``boxes`` with pair_id, instance_token and the 2D box)
    overlaps this object's crop window (the tripled square). Adds columns wrong,
    unclear_flow, crowded.
    """
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


def failure_shares(tagged: pd.DataFrame) -> pd.DataFrame:  # pragma: no mutate block
    """Share (%) of all objects and of wrong predictions with each failure reason."""
    cols = ["unclear_flow", "crowded"]
    names = {"unclear_flow": "remote or slow", "crowded": "other objects in the crop"}
    out = pd.DataFrame({
        "reason": [names[c] for c in cols],
        "all objects (%)": [100 * float(tagged[c].mean()) for c in cols],
        "wrong predictions (%)": [100 * float(tagged.loc[tagged["wrong"], c].mean())
                                  if tagged["wrong"].any() else float("nan") for c in cols],
    })
    return out.round(1)


def failure_examples(tagged: pd.DataFrame, n: int = FAILURE_EXAMPLES) -> pd.DataFrame:  # pragma: no mutate block
    """Up to ``n`` wrong predictions of each kind (remote or slow only, then crowded), with a
    ``title`` for the figure."""
    wrong = tagged[tagged["wrong"]]
    out = pd.concat([wrong[wrong["unclear_flow"] & ~wrong["crowded"]].head(n),
                     wrong[wrong["crowded"]].head(n)])
    return out.assign(title=[("crowded" if c else "remote/slow") + f", {d:.0f} m, {s:.1f} m/s"
                             for c, d, s in zip(out["crowded"], out["distance"], out["speed"],
                                                strict=True)])
