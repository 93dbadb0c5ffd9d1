"""Chapter 10's backend: the classifier on other inputs, against the paper's raw flow."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from flowmod import pipeline
from flowmod.chapters import common
from flowmod.chapters.common import comparison_table, results
from flowmod.crops import gather_fold
from flowmod.dag import Node
from flowmod.evaluate import fold_of, paired, scored, seed_probs
from flowmod.extensions.context import read_context
from flowmod.extensions.inputs import VARIANTS, chains
from flowmod.metrics import ci_text, sd_cells, seed_summary, span
from flowmod.params import Params
from flowmod.select import SPLITS
from flowmod.train import extension_parts


def built(params: Params) -> list[tuple[str | None, str]]:
    """The chains whose predictions, models and context crops are current
    (:meth:`flowmod.dag.Graph.built`: made from what is published now, with ``params``)."""
    return [c for c in chains(params) if pipeline.built(params, Node("xevaluate", *c))]


def predictions(params: Params, method: str | None, variant: str, split: str) -> pd.DataFrame:
    """Published predictions (``prob_s<k>`` per seed) of one chain on ``test`` or
    ``general``; ``variant`` ``flow`` reads the paper's models (chapters 07 and 08)."""
    if variant == "flow":
        return results(params, method, "test" if split == "test" else "general")[0]
    folder = pipeline.published(params, Node("xevaluate", method, variant))
    return pd.read_parquet(folder / f"{split}.parquet")


def rows(params: Params) -> list[tuple[str | None, str]]:
    """Rows of the chapter's table: per extension method the raw flow (the paper's models)
    and its built inputs, then the image-only input."""
    done = built(params)
    rows: list[tuple[str | None, str]] = []
    for m in params.extension_methods:
        rows += [(m, "flow")] + [(mm, v) for mm, v in done if mm == m]
    return rows + [(mm, v) for mm, v in done if mm is None]


def table(params: Params, rows_of: list[tuple[str | None, str]] | None = None,
          split: str = "test") -> pd.DataFrame:
    """Method x input x F1 on the keyframe test split (``split="test"``) or on the
    generalisation set within Table 4's range (``"general"``): mean over training seeds,
    their range and SD, the 95 % interval of the mean over scenes and seeds, precision and
    recall.
    ``rows_of``: the chains (default :func:`rows`)."""
    out = []
    for m, v in (rows(params) if rows_of is None else rows_of):
        d = scored(predictions(params, m, v, split), split, params.general_max_distance)
        s = seed_summary(d["label"].to_numpy(), seed_probs(d), d["scene"].to_numpy(),
                         seed=params.seed, folds=fold_of(d))
        out.append({"flow method": m or "-", "input": input_label(v),
                    "channels": VARIANTS[v].channels,
                     "F1 (%)": round(100 * s["f1"], 1),
                     f"{s['unit']}s (%)": span(s["f1_min"], s["f1_max"]),
                     **sd_cells(s),
                     "95% CI, scenes and seeds (%)": ci_text(s["ci"], s["n_scenes"]),
                     "P (%)": round(100 * s["precision"], 1),
                     "R (%)": round(100 * s["recall"], 1)})
    return pd.DataFrame(out)


def comparisons(params: Params, split: str = "test",
                rows_of: list[tuple[str | None, str]] | None = None) -> pd.DataFrame:
    """Each input minus the raw flow of the same method (the image-only input: minus the raw
    flow of the first extension method), paired on the same objects and scenes, with the
    per-seed differences (:func:`flowmod.metrics.paired_comparison`)."""
    out = {}
    for m, v in (rows(params) if rows_of is None else rows_of):
        if v == "flow":
            continue
        ref = reference(params, m)
        a = scored(predictions(params, m, v, split), split, params.general_max_distance)
        b = scored(predictions(params, ref, "flow", split), split, params.general_max_distance)
        out[comparison_name(params, m, v)] = paired(a, b, f"{m}/{v} and {ref}/flow",
                                                    params.seed)
    return comparison_table(out)


def reference(params: Params, method: str | None) -> str:
    """The raw-flow classifier an input of ``method`` is compared with: the same method's,
    or for an input without flow (``method`` None) the first extension method's."""
    return method or params.extension_methods[0]


def comparison_name(params: Params, method: str | None, variant: str) -> str:
    """The row name of a chain in :func:`comparisons`: ``dis: residual [oracle: ...] - dis:
    flow``, ``images - gt: flow`` (the input by :func:`input_label`)."""
    return (f"{method + ': ' if method else ''}{input_label(variant)} - "
            f"{reference(params, method)}: flow")


def inputs_table() -> pd.DataFrame:
    """The classifier inputs: name, channels, what they hold, channels a flip negates."""
    return pd.DataFrame([{"input": v.name, "channels": v.channels, "holds": v.doc,
                          "negated by a flip": ", ".join(map(str, v.negate)) or "-"}
                         for v in VARIANTS.values()])


def context_split(params: Params, split: str) -> tuple[np.ndarray, np.ndarray, pd.DataFrame]:
    """The published context crops of one stored split, or of a role (``train``, ``val``,
    ``test``; with cross-validation fold 0's): (static, images, index)."""
    part = "general" if split == "general" else "keyframe"
    folder = pipeline.published(params, Node("context", None, part))
    if split not in SPLITS:
        return read_context(folder, split)

    def read(s: str) -> tuple[list[Any], pd.DataFrame]:
        static, images, df = read_context(folder, s)
        return [static, images], df
    (static, images), df = gather_fold(read, params.folds, 0, split)
    return static, images, df


def explains_method(params: Params) -> str:
    """The flow whose crops measure what the static world explains: the exact flow where the
    profile has it (the static model's own error, not the flow method's), else chapter 10's
    first method."""
    return "gt" if "gt" in params.flow_methods else params.extension_methods[0]


def static_explains(flow: np.ndarray, static: np.ndarray, labels: np.ndarray) -> pd.DataFrame:
    """How much of the flow at the vehicles the static world explains: per class (still,
    moving), the median over objects of the median flow magnitude in the box's square (the
    middle third of the crop, which is three times the box), of the residual's (flow minus
    static-world flow) there, and their ratio. flow, static: (N, 2, S, S) px; labels (N,)
    0/1."""
    s = np.asarray(flow).shape[-1]
    a, b = s // 3, s - s // 3
    f = np.asarray(flow[..., a:b, a:b], np.float32)
    r = f - np.asarray(static[..., a:b, a:b], np.float32)
    mag = np.median(np.linalg.norm(f, axis=1).reshape(len(f), -1), axis=1)
    res = np.median(np.linalg.norm(r, axis=1).reshape(len(r), -1), axis=1)
    rows = []
    for lab, name in ((0, "still"), (1, "moving")):
        k = np.asarray(labels) == lab
        rows.append({"vehicles": name, "objects": int(k.sum()),
                     "flow at the box (px)": float(np.median(mag[k])) if k.any() else np.nan,
                     "residual (px)": float(np.median(res[k])) if k.any() else np.nan,
                     "residual / flow": float(np.median(res[k] / np.maximum(mag[k], 1e-6)))
                     if k.any() else np.nan})
    return pd.DataFrame(rows)


def built_note(params: Params, done: list[tuple[str | None, str]]) -> str:
    """A line for the chapter: which chains are built, and how to build the others."""
    if not params.extension_inputs:
        return ("This profile trains no other input (`extension_inputs` is empty): the "
                "tables below hold the paper's raw-flow models only. Set it (e.g. "
                "`extension_inputs=[residual]`) and run `make extensions`.")
    todo = [c for c in chains(params) if c not in done]
    return common.built_note("Chains built", [f"{m or 'no flow'}/{v}" for m, v in done],
                             len(chains(params)), f"{len(todo) * len(extension_parts(params))} models",
                             "extension_build")


#: How a headline names the inputs whose static-world flow takes depth from the annotated
#: 3D boxes: information a car does not have.
ORACLE_NOTE = " (static world with annotated-box depth, an oracle a car does not have)"
#: How a headline names the input whose static-world flow an idealised car computes.
DEPLOYED_NOTE = (" (static world from exact ego poses, an exactly flat ground and the "
                 "target's annotated 2D box: a car with perfect odometry and detector)")


#: The tag a table row gives an input by its static-world depth (:func:`depth_note`).
TAGS = {ORACLE_NOTE: " [oracle: annotated-box depth]",
        DEPLOYED_NOTE: " [idealised: exact poses, flat ground, annotated 2D box]"}
#: The tag of the inputs with images: trained with the recipe chosen for the raw flow.
UNTUNED = " [untuned recipe]"


def input_label(variant: str) -> str:
    """An input's name in tables, tagged where its static-world flow reads annotated boxes
    (an oracle) or idealised measurements, and where it holds images (the raw flow's recipe,
    untuned for them): ``residual [oracle: annotated-box depth]``."""
    return variant + TAGS.get(depth_note(variant), "") + (UNTUNED if VARIANTS[variant].images
                                                          else "")


def depth_note(variant: str) -> str:
    """What a table or headline says of an input's static-world depth ('' without one)."""
    v = VARIANTS[variant]
    if not v.static:
        return ""
    return ORACLE_NOTE if v.depth == "boxes" else DEPLOYED_NOTE


def headline(params: Params, paired_test: pd.DataFrame) -> str:
    """One sentence for the landing page: on the main method, each input of
    ``extension_inputs`` (in the profile's order: the questions are fixed in advance, not
    picked by their test F1) minus the raw flow, paired on the test split (``paired_test``:
    :func:`comparisons` of the test split), or how to build the chapter."""
    main = next((m for m in params.extension_methods if m != "gt"), None) or (
        params.extension_methods[0] if params.extension_methods else None)
    by_name = paired_test.set_index("comparison")
    parts = []
    for v in params.extension_inputs:
        m = main if VARIANTS[v].flow else None
        if comparison_name(params, m, v) not in by_name.index:
            continue
        r = by_name.loc[comparison_name(params, m, v)]
        on = "" if m else f" (no flow; against {reference(params, m)} flow)"
        oracle = depth_note(v)
        parts.append(f"{v}{oracle}{on} {common.difference_words(r)}")
    if not parts:
        return ("not built in this run (make extensions trains them: "
                f"{len(chains(params)) * len(extension_parts(params))} models)" if params.extension_inputs else
                "not part of this profile (extension_inputs is empty)")
    return f"against the raw {main} flow, paired on the test scenes: " + "; ".join(parts)


def glue_key(method: str | None, variant: str) -> str:
    """The name chapter 10 glues a chain's numbers under: ``dis_flow_static``,
    ``none_images``."""
    return f"{method or 'none'}_{variant.replace('+', '_')}"
