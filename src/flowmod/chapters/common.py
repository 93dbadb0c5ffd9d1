"""What several chapters read from the published artefacts: the selection, the flow, the
crops, the classifiers' predictions and scores, and the line that says what a gate built."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from flowmod import metrics, pipeline
from flowmod.crops import fold_crops, part_of, read_crops
from flowmod.dag import Node
from flowmod.evaluate import fold_of, read_frame, read_scores, seed_probs
from flowmod.flow import FlowReader, flow_root
from flowmod.metrics import ci_text, group_mean_bootstrap, interval
from flowmod.params import Params
from flowmod.paths import repo_root
from flowmod.select import PARTS, SPLITS, Selection, read_selection
from flowmod.train import model_file


def committed_record(rel: str) -> dict[str, Any] | None:
    """A dated benchmark record a chapter shows (``rel``: its path in the repository, one of
    :data:`flowmod.runner.RECORDS`' files), or None where none is committed."""
    f = repo_root() / rel
    return json.loads(f.read_text()) if f.is_file() else None


def selection(p: Params) -> Selection:
    """The published selection (both sets, ``set`` column). :class:`flowmod.dag.MissingInput`
    names chapter 02 if it never ran."""
    return read_selection(pipeline.published(p, Node("select")),
                          pipeline.published(p, Node("general")))


def made_with(p: Params) -> dict[str, Any]:
    """The parameters that made the keyframe set (its manifest's)."""
    return (pipeline.recorded(p, Node("select")) or {})["params"]


def flow_reader(p: Params, method: str, part: str = "keyframe") -> FlowReader:
    """The published flow of ``flow[<method>/<part>]``."""
    folder = pipeline.published(p, Node("flow", method, part))
    return FlowReader(folder, flow_root(p) / method / "pool", method, part)


def flow_readers(p: Params) -> dict[str, dict[str, FlowReader]]:
    """``{method: {part: FlowReader}}`` of every published flow node of the profile."""
    return {m: {part: flow_reader(p, m, part) for part in PARTS} for m in p.flow_methods}


def open_crops(p: Params, method: str, split: str) -> tuple[Any, pd.DataFrame]:
    """The published crops of ``method``: ``(x (N, 2, S, S) float16, index)`` of a stored
    array (``general``, ``f<k>``, or a split of one fold) or of a role (``train``, ``val``,
    ``test``), with cross-validation fold 0's (:func:`flowmod.crops.fold_crops`)."""
    folder = pipeline.published(p, Node("crops", method, part_of(split)))
    if split in SPLITS:
        return fold_crops(folder, p.folds, 0, split)
    return read_crops(folder, split)


def results(p: Params, method: str, name: str = "test") -> tuple[pd.DataFrame, dict[str, Any]]:
    """Published predictions and scores of the paper's classifiers: ``name`` = ``test`` (the
    models on the test split), ``baseline`` (the geometric baseline) or ``general`` (scores
    empty)."""
    node = Node("generalise" if name == "general" else "evaluate", method)
    folder = pipeline.published(p, node)
    return read_frame(folder, name), read_scores(folder, "scores" if name == "test" else name)


def model_path(p: Params, method: str, part: str = "s0") -> Path:
    """The published ``best.pt`` of one training seed of ``method`` (state_dict of the best
    validation epoch, float16 weights)."""
    return model_file(pipeline.published(p, Node("train", method, part)))


def built_note(what: str, done: list[str], planned: int, others: str, flag: str) -> str:
    """A chapter's line on what its gate (``flag``) has built: ``{what} with these
    parameters: **d of n** (names).`` and, while some are missing, ``The other k
    ({others}) are trained by `make ...` (or this chapter with `flag=true`).``"""
    out = (f"{what} with these parameters: **{len(done)} of {planned}** "
           f"({', '.join(done) or 'none'}).")
    if len(done) < planned:
        out += (f" The other {planned - len(done)} ({others}) are trained by "
                f"`{pipeline.GATE_TARGETS[flag]}` (or this chapter with `{flag}=true`).")
    return out


def difference_words(row: Any) -> str:
    """A paired comparison's row (:func:`flowmod.metrics.comparison_table`) in words: ``+1.2
    F1 points (95 % interval over scenes and training seeds -0.5 to 2.9)``, and when it leaves the question
    open, the smallest difference these scenes would detect."""
    text = (f"{row['ΔF1 (points)']:+.1f} F1 points (95 % interval over scenes and training "
            f"seeds {row['95% CI, scenes and seeds (points)']}")
    if "verdict" in row and row["verdict"] == "inconclusive":
        text += (f"; inconclusive: these scenes would detect {row['detectable (points)']:.1f} "
                 "points or more")
    elif "verdict" in row and row["verdict"] == "equivalent":
        text += f"; equivalent: within +/-{SMALLEST_EFFECT:.0f} points"
    return text + ")"


#: The smallest difference in F1 (points) that matters, set from the paper's numbers, not
#: from this book's: a bit more than half the paper's FastFlowNet - RAFT gap (92.9 - 89.5 = 3.4 points), the
#: difference its conclusion rests on. An interval inside +/- this is "equivalent": too
#: small an effect to carry a conclusion of that kind either way.
SMALLEST_EFFECT = 2.0


def decided(verdict: str) -> bool:
    """True for a verdict whose interval excludes 0 (``A better``, ``B better``)."""
    return verdict in ("A better", "B better")


#: What an interval resamples when every trained arm has 2 or more training seeds a fold,
#: and when one has a single model a fold (its training noise is then not in the interval).
COUNTS_SEEDS, COUNTS_SCENES = "scenes and seeds", "scenes only"

#: Comparison names whose second arm is the oracle rule: it trains nothing, so its one
#: "seed" is no missing training noise.
UNTRAINED_B = ": classifier - oracle rule"


def interval_counts(name: str, row: dict[str, Any]) -> str:
    """:data:`COUNTS_SEEDS` or :data:`COUNTS_SCENES` for a paired comparison ``row``
    (:func:`flowmod.metrics.paired_comparison`: ``training_seeds`` of A and B) named
    ``name``: scenes only when a trained arm has one model a fold."""
    seeds = list(row.get("training_seeds", [1, 1]))
    if name.endswith(UNTRAINED_B):
        seeds = seeds[:1]
    return COUNTS_SEEDS if min(seeds) >= 2 else COUNTS_SCENES


def comparison_table(rows: dict[str, dict[str, Any]]) -> pd.DataFrame:
    """:func:`flowmod.metrics.comparison_table` with three verdicts: ``A better`` or ``B
    better`` (decided: the interval excludes 0), ``equivalent`` (inside +/-
    :data:`SMALLEST_EFFECT`) or ``inconclusive`` (:func:`three_verdicts`); and what each
    interval resamples (``interval counts``: :func:`interval_counts`)."""
    table = metrics.comparison_table(rows)
    table["verdict"] = [v if decided(v) else three_verdicts(ci, SMALLEST_EFFECT)
                        for v, ci in zip(table["verdict"], table.attrs["ci_points"], strict=True)]
    table.insert(3, "interval counts", [interval_counts(k, r) for k, r in rows.items()])
    return table


def verdict_words(verdict: str) -> str:
    """What a verdict adds after an interval in a sentence: ``, decided``, ``, equivalent``
    or nothing (inconclusive)."""
    return ", decided" if decided(verdict) else ", equivalent" if verdict == "equivalent" else ""


#: The three verdicts of :func:`three_verdicts`.
VERDICTS = ("decided", "equivalent", "inconclusive")


def three_verdicts(ci: tuple[float, float], delta: float) -> str:
    """The verdict on a paired effect from its interval ``ci`` = (lo, hi) and the smallest
    effect that matters ``delta`` > 0 (same unit, F1 points say): ``decided`` when the
    interval excludes 0 (lo > 0 or hi < 0, as :func:`flowmod.metrics.verdict`), else
    ``equivalent`` when it lies inside (-delta, +delta) (open: touching +/- delta is not
    inside), else ``inconclusive`` (also for an undefined interval). An interval touching
    0 does not exclude it. ValueError for delta <= 0 (or NaN) and for lo > hi."""
    if not delta > 0:
        raise ValueError(f"the smallest effect that matters must be positive, got {delta}")
    lo, hi = float(ci[0]), float(ci[1])
    if np.isnan(lo) or np.isnan(hi):
        return "inconclusive"
    if lo > hi:
        raise ValueError(f"interval ({lo}, {hi}) has its low end above its high end")
    if lo > 0 or hi < 0:
        return "decided"
    if -delta < lo and hi < delta:
        return "equivalent"
    return "inconclusive"


def headline_method(p: Params) -> str:
    """The method the book's headlines quote: the first estimated flow of the profile."""
    return next((m for m in p.flow_methods if m != "gt"), p.flow_methods[0])


def split_order(splits: Any) -> list[str]:
    """The splits present in ``splits`` in book order: train, val, test, then the folds."""
    present = {str(s) for s in splits}
    return [s for s in SPLITS if s in present] + sorted(present - set(SPLITS))


def n_scored_objects(sel: Selection, folds: int) -> int:
    """Keyframe objects Table 3 scores: the test split's, or with cross-validation every
    object (each by the model of its fold)."""
    obj = sel.objects[sel.objects["set"] == "keyframe"]
    return int((obj["split"] == "test").sum()) if folds == 1 else len(obj)


def split_sizes(sel: Selection, kind: str = "keyframe") -> pd.DataFrame:
    """Scenes, pairs, objects, moving and still objects per split (or fold: then also its
    scenes that the other folds' models validate on)."""
    pairs = sel.pairs[sel.pairs["set"] == kind]
    obj = sel.objects[sel.objects["set"] == kind]
    out = pd.DataFrame({
        "scenes": pairs.groupby("split")["scene"].nunique(),
        "pairs": pairs.groupby("split").size(),
        "objects": obj.groupby("split").size(),
        "moving": obj.groupby("split")["label"].sum(),
    }).reindex(split_order(pairs["split"])).fillna(0).astype(int)
    out["still"] = out["objects"] - out["moving"]
    out["moving %"] = (100 * out["moving"] / out["objects"].clip(lower=1)).round(1)
    if "fold" in pairs and pairs["split"].astype(str).str.startswith("f").any():
        val = pairs[pairs["val_scene"].astype(bool)].groupby("split")["scene"].nunique()
        out["val scenes"] = val.reindex(out.index).fillna(0).astype(int)
    return out


def epe_ci(values: Any, scenes: Any, seed: int) -> str:
    """The 95 % interval of a mean end-point error (px) over pairs, whole scenes resampled
    (:func:`flowmod.metrics.group_mean_bootstrap`), flagged when the scenes are too few;
    "-" without values."""
    values, scenes = list(values), list(scenes)
    if not values:
        return "-"
    ci = interval(group_mean_bootstrap(values, scenes, seed=seed))
    return ci_text(ci, len(set(scenes)), fmt=".2f")


def breakdown(df: pd.DataFrame, by: str, bins: Any = None) -> pd.DataFrame:
    """:func:`flowmod.metrics.breakdown` of a predictions table: every training seed (F1 the
    mean over seeds), with the scene-level interval and the object count of each group
    (chapters 07, 08 and 11)."""
    return metrics.breakdown(df, df["label"], seed_probs(df), by=by, bins=bins,
                             groups=df["scene"].to_numpy(), folds=fold_of(df))
