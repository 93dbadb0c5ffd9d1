"""Beyond the paper (chapter 10): the same ResNet18 on other inputs than the raw flow crop.

Inputs (channels, in this order; ``S x S`` crops of the paper's window):

=============== == =====================================================================
``flow``         2 the paper's input: the flow crop (u, v), px
``residual``     2 flow minus the static-world flow of the window (ego motion removed), px
``flow+static``  4 the flow crop, then the static-world flow (u, v, u_s, v_s), px
``images``       6 no flow: RGB of frame 1 and frame 2 in the window, standardised
``images+flow``  8 the flow crop, then the six image channels
=============== == =====================================================================

Image channels are standardised as ``(x / 255 - 0.5) / 0.25``. A horizontal flip (training
augmentation) mirrors every channel and negates the horizontal flow components.

Stages (:mod:`flowmod.dag`): ``xtrain[<method>/<input>/s<k>]`` trains one seed with the
paper's Table 2 settings on the keyframe train split (epoch chosen on validation), like
``train``; ``xevaluate[<method>/<input>]`` applies its seeds to the test split and the
generalisation set. The ``images`` input uses no flow: its nodes have no method
(``xtrain[images/s0]``). Scores, intervals over scenes and paired differences against the
raw flow of the same method are computed from the published predictions (:func:`table`,
:func:`comparisons`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from flowmod.context import read_context
from flowmod.crops import read_crops
from flowmod.evaluate import paired, scored, seed_probs
from flowmod.evaluate import results as flow_results
from flowmod.metrics import comparison_table, seed_summary


@dataclass(frozen=True)
class Variant:
    """One classifier input: which artefacts it stacks and how many channels result."""

    name: str
    channels: int
    flow: bool
    static: bool
    images: bool
    #: channels negated by a horizontal flip (horizontal flow components)
    negate: tuple[int, ...]
    doc: str


VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("flow", 2, True, False, False, (0,), "raw flow (the paper)"),
    Variant("residual", 2, True, True, False, (0,), "flow minus static-world flow"),
    Variant("flow+static", 4, True, True, False, (0, 2), "flow and static-world flow"),
    Variant("images", 6, False, False, True, (), "the two images, no flow"),
    Variant("images+flow", 8, True, False, True, (0,), "flow and the two images"),
)}
#: The inputs chapter 10 can train (``flow`` is the paper's, trained in chapter 06).
EXTENSION_INPUTS = tuple(v for v in VARIANTS if v != "flow")


def standardise_images(images: np.ndarray) -> np.ndarray:
    """uint8 image channels -> float32 ``(x / 255 - 0.5) / 0.25``."""
    return (np.asarray(images, np.float32) / 255.0 - 0.5) / 0.25


def compose(variant: str, flow: np.ndarray | None = None, static: np.ndarray | None = None,
            images: np.ndarray | None = None) -> np.ndarray:
    """The input of ``variant`` for a batch: (B, C, S, S) float32 from flow (B, 2, S, S) px,
    static (B, 2, S, S) px and images (B, 6, S, S) uint8 (those the variant uses)."""
    v = VARIANTS[variant]
    need = {"flow": (v.flow, flow), "static": (v.static, static), "images": (v.images, images)}
    missing = [k for k, (used, arr) in need.items() if used and arr is None]
    if missing:
        raise ValueError(f"input {variant!r} needs {missing}")
    f = np.asarray(flow, np.float32) if v.flow else None
    if variant == "flow":
        return f  # type: ignore[return-value]
    if variant == "residual":
        return f - np.asarray(static, np.float32)  # type: ignore[operator]
    if variant == "flow+static":
        return np.concatenate([f, np.asarray(static, np.float32)], axis=1)  # type: ignore[list-item]
    img = standardise_images(images)  # type: ignore[arg-type]
    return img if variant == "images" else np.concatenate([f, img], axis=1)  # type: ignore[list-item]


class Inputs:
    """A split's input for one variant, composed per batch from the memory-mapped artefacts
    (nothing is stacked on disk): ``x[indices]`` -> (B, C, S, S) float32; ``shape``,
    ``len``. What :func:`flowmod.train.train_model` and :func:`flowmod.model.predict` read."""

    def __init__(self, variant: str, flow: Any = None, static: Any = None,
                 images: Any = None) -> None:
        self.variant = variant
        self.parts = {"flow": flow, "static": static, "images": images}
        first = next(a for a in (flow, static, images) if a is not None)
        n, _, s, _ = first.shape
        lens = {k: len(a) for k, a in self.parts.items() if a is not None}
        if len(set(lens.values())) != 1:
            raise ValueError(f"input {variant!r}: parts of different lengths {lens}")
        self.shape = (n, VARIANTS[variant].channels, s, s)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, idx: Any) -> np.ndarray:
        return compose(self.variant, **{k: None if a is None else np.asarray(a[idx])
                                        for k, a in self.parts.items()})


# --- reading a split -------------------------------------------------------------------------

def _same_objects(a: pd.DataFrame, b: pd.DataFrame, what: str) -> None:
    if len(a) != len(b) or not a["ann_token"].reset_index(drop=True).equals(
            b["ann_token"].reset_index(drop=True)):
        raise ValueError(f"{what}: the flow crops and the context crops hold other objects "
                         f"({len(a)} and {len(b)} rows); rebuild chapter 10's context stage")


def split_inputs(variant: str, context_folder: Any, crops_folder: Any, split: str
                 ) -> tuple[Inputs, pd.DataFrame]:
    """(inputs, index) of one split for ``variant``: the context node's arrays and, for an
    input with flow, the flow crops of the method's crops node (same objects, checked)."""
    static, images, df = read_context(context_folder, split)
    v = VARIANTS[variant]
    flow = None
    if v.flow:
        flow, fdf = read_crops(crops_folder, split)
        _same_objects(fdf, df, f"{split} split of {crops_folder}")
    return Inputs(variant, flow, static if v.static else None,
                  images if v.images else None), df


# --- the stages --------------------------------------------------------------------------------

def plan(params: Any) -> list[tuple[str | None, str]]:
    """The (method, input) chains of chapter 10 (:func:`flowmod.dag.extension_chains`)."""
    from flowmod import dag

    return dag.extension_chains(params)


def run(params: Any, progress: bool = True) -> dict[tuple[str | None, str], Any]:
    """Build chapter 10's stale context crops, and when ``extension_build`` is on every seed
    of every chain, then its predictions (otherwise no model is trained). Returns
    ``{(method, input): published xevaluate folder or None}``."""
    from flowmod import context, dag, train

    if not params.extension_inputs:
        return {}
    context.run(params, progress=progress)  # cheap (seconds): the chapter always shows it
    for m, v in plan(params):
        if params.extension_build:
            for k, part in enumerate(dag.seed_parts(params)):
                b = dag.begin(params, dag.Node("xtrain", m, f"{v}/{part}"))
                if b.up_to_date:
                    continue
                ctx = b.input_dir(dag.Node("context", None, "keyframe"))
                crops_dir = b.input_dir(dag.Node("crops", m, "keyframe")) if m else None
                (tx, tdf), (vx, vdf) = (split_inputs(v, ctx, crops_dir, s) for s in
                                        ("train", "val"))
                q = b.params
                h = train.train_node(
                    b, tx, tdf, vx, vdf, k, f"train {m + ' ' if m else ''}{v} seed {q.seed + k}",
                    progress, in_channels=VARIANTS[v].channels, flip_negate=VARIANTS[v].negate)
                b.publish(best_epoch=int(h.attrs["best_epoch"]),
                          best_f1=float(h.attrs["best_f1"]), seed=q.seed + k, amp=q.amp,
                          input=v, channels=VARIANTS[v].channels)
            _evaluate(params, m, v)
    done = built(params)
    return {c: dag.node_dir(params, _xnode(*c)) if c in done else None for c in plan(params)}


def built(params: Any) -> list[tuple[str | None, str]]:
    """The chains of :func:`plan` whose predictions, models and context crops are current
    (:func:`flowmod.dag.current`: built from what is published now, with ``params``)."""
    from flowmod import dag

    def ok(node: Any) -> bool:
        return dag.current(params, node) and all(
            ok(i) for i in dag.inputs(node, params) if i.stage in ("xtrain", "context"))

    return [c for c in plan(params) if ok(_xnode(*c))]


def _evaluate(params: Any, method: str | None, variant: str) -> None:
    """Build ``xevaluate[<method>/<input>]``: every seed on the test split and the
    generalisation set (``test.parquet``, ``general.parquet`` with ``prob_s<k>``)."""
    from flowmod import dag
    from flowmod.evaluate import _write, models_of, predict_models

    b = dag.begin(params, dag.Node("xevaluate", method, variant))
    if b.up_to_date:
        return
    # (seed part, best.pt, amp) of every seed, as chapter 07 reads them
    models = models_of(b, "xtrain", "/".join(x for x in (method, variant) if x))
    frames = {}
    for split in ("test", "general"):
        part = "general" if split == "general" else "keyframe"
        x, df = split_inputs(variant, b.input_dir(dag.Node("context", None, part)),
                             b.input_dir(dag.Node("crops", method, part)) if method else None,
                             split)
        frames[split] = predict_models(models, x, df, b.params.device, in_channels=None)
    _write(b.start(fresh=True), frames, {})
    b.publish(seeds=len(models), input=variant)


# --- the chapter's tables ---------------------------------------------------------------------

def predictions(params: Any, method: str | None, variant: str, split: str) -> pd.DataFrame:
    """Published predictions (``prob_s<k>`` per seed) of one chain on ``test`` or
    ``general``; ``variant`` ``flow`` reads the paper's models (chapters 07 and 08)."""
    from flowmod import dag

    if variant == "flow":
        return flow_results(params, method, "test" if split == "test" else "general")[0]
    folder = dag.published(params, dag.Node("xevaluate", method, variant))
    return pd.read_parquet(folder / f"{split}.parquet")


def chains(params: Any) -> list[tuple[str | None, str]]:
    """Rows of the chapter's table: per extension method the raw flow (the paper's models)
    and its built inputs, then the image-only input."""
    done = built(params)
    rows: list[tuple[str | None, str]] = []
    for m in params.extension_methods:
        rows += [(m, "flow")] + [(mm, v) for mm, v in done if mm == m]
    return rows + [(mm, v) for mm, v in done if mm is None]


def _xnode(method: str | None, variant: str) -> Any:
    from flowmod import dag

    return dag.Node("xevaluate", method, variant)


def table(params: Any, rows_of: list[tuple[str | None, str]] | None = None,
          split: str = "test") -> pd.DataFrame:
    """Method x input x F1 on the keyframe test split (``split="test"``) or on the
    generalisation set within Table 4's range (``"general"``): mean over training seeds,
    their range, the scene-level 95 % interval of the mean, precision and recall.
    ``rows_of``: the chains (default :func:`chains`)."""
    rows = []
    for m, v in (chains(params) if rows_of is None else rows_of):
        d = scored(predictions(params, m, v, split), split, params.general_max_distance)
        s = seed_summary(d["label"].to_numpy(), seed_probs(d), d["scene"].to_numpy(),
                         seed=params.seed)
        rows.append({"flow method": m or "-", "input": v, "channels": VARIANTS[v].channels,
                     "F1 (%)": round(100 * s["f1"], 1),
                     "seeds (%)": f"{100 * s['f1_min']:.1f}-{100 * s['f1_max']:.1f}",
                     "95% CI, scenes (%)": f"{100 * s['ci'][0]:.1f}-{100 * s['ci'][1]:.1f}",
                     "P (%)": round(100 * s["precision"], 1),
                     "R (%)": round(100 * s["recall"], 1)})
    return pd.DataFrame(rows)


def comparisons(params: Any, split: str = "test",
                rows_of: list[tuple[str | None, str]] | None = None) -> pd.DataFrame:
    """Each input minus the raw flow of the same method (the image-only input: minus the raw
    flow of the first extension method), paired on the same objects and scenes, with the
    per-seed differences (:func:`flowmod.metrics.paired_comparison`)."""
    rows = {}
    for m, v in (chains(params) if rows_of is None else rows_of):
        if v == "flow":
            continue
        ref = m or params.extension_methods[0]
        a = scored(predictions(params, m, v, split), split, params.general_max_distance)
        b = scored(predictions(params, ref, "flow", split), split, params.general_max_distance)
        rows[f"{m + ': ' if m else ''}{v} - {ref}: flow"] = paired(
            a, b, f"{m}/{v} and {ref}/flow", params.seed)
    return comparison_table(rows)


def inputs_table() -> pd.DataFrame:
    """The classifier inputs: name, channels, what they hold, channels a flip negates."""
    return pd.DataFrame([{"input": v.name, "channels": v.channels, "holds": v.doc,
                          "negated by a flip": ", ".join(map(str, v.negate)) or "-"}
                         for v in VARIANTS.values()])


def context_split(params: Any, split: str) -> tuple[np.ndarray, np.ndarray, pd.DataFrame]:
    """The published context crops of one split: (static, images, index)."""
    from flowmod import dag

    part = "general" if split == "general" else "keyframe"
    return read_context(dag.published(params, dag.Node("context", None, part)), split)


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


def built_note(params: Any, done: list[tuple[str | None, str]]) -> str:
    """A line for the chapter: which chains are built, and how to build the others."""
    if not params.extension_inputs:
        return ("This profile trains no other input (`extension_inputs` is empty): the "
                "tables below hold the paper's raw-flow models only. Set it (e.g. "
                "`extension_inputs=[residual]`) and run `make extensions`.")
    from flowmod import dag

    todo = [c for c in plan(params) if c not in done]
    return dag.built_note("Chains built", [f"{m or 'no flow'}/{v}" for m, v in done],
                          len(plan(params)), f"{len(todo) * params.seeds} models",
                          "extension_build")


def headline(params: Any, test: pd.DataFrame, general: pd.DataFrame) -> str:
    """One sentence for the landing page: the best input of the main method against its
    raw flow on the test split (:func:`table`), or how to build the chapter."""
    main = next((m for m in params.extension_methods if m != "gt"), None) or (
        params.extension_methods[0] if params.extension_methods else None)

    def of(t: pd.DataFrame, v: str | None = None) -> pd.DataFrame:
        if not len(t):
            return t
        k = t["flow method"] == main
        return t[k & (t["input"] != "flow")] if v is None else t[k & (t["input"] == v)]

    rows = of(test)
    if not len(rows):
        return ("not built in this run (make extensions trains them: "
                f"{len(plan(params)) * params.seeds} models)" if params.extension_inputs else
                "not part of this profile (extension_inputs is empty)")
    best = rows.loc[rows["F1 (%)"].idxmax()]
    raw, raw_g = of(test, "flow").iloc[0], of(general, "flow").iloc[0]
    best_g = of(general, best["input"]).iloc[0]
    return (f"on {main} flow, the best other input ({best['input']}) reaches test F1 "
            f"{best['F1 (%)']:.1f} % against {raw['F1 (%)']:.1f} % on raw flow, "
            f"and {best_g['F1 (%)']:.1f} % against {raw_g['F1 (%)']:.1f} % on the "
            "generalisation set")


def glue_key(method: str | None, variant: str) -> str:
    """The name chapter 10 glues a chain's numbers under: ``dis_flow_static``,
    ``none_images``."""
    return f"{method or 'none'}_{variant.replace('+', '_')}"
