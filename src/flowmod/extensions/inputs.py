"""Beyond the paper (chapter 10): the same ResNet18 on other inputs than the raw flow crop.

Inputs (channels, in this order; ``S x S`` crops of the paper's window):

=============== == =====================================================================
``flow``         2 the paper's input: the flow crop (u, v), px
``residual``     2 flow minus the static-world flow of the window (ego motion removed), px;
                   depth from the annotated 3D boxes (an oracle a car does not have)
``residual-deployed``
                 2 the same with the depth a car could assume: flat ground, the target
                   at its 2D box's ground contact (ego poses are odometry)
``flow+static``  4 the flow crop, then the static-world flow (u, v, u_s, v_s), px
``images``       6 no flow: RGB of frame 1 and frame 2 in the window, standardised
``images+flow``  8 the flow crop, then the six image channels
=============== == =====================================================================

Image channels are standardised as ``(x / 255 - 0.5) / 0.25``. A horizontal flip (training
augmentation) mirrors every channel and negates the horizontal flow components.

Stages (:data:`XTRAIN`, :data:`XEVALUATE`): ``xtrain[<method>/<input>/s<k>]`` trains one
seed with the paper's Table 2 settings on the keyframe train split (epoch chosen on
validation), like ``train``; ``xevaluate[<method>/<input>]`` applies its seeds to the test
split and the generalisation set. The ``images`` input uses no flow: its nodes have no
method (``xtrain[images/s0]``). The chapter's tables are in
:mod:`flowmod.chapters.ch10_inputs`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from flowmod import dag
from flowmod.crops import SplitReader, gather_fold, read_crops
from flowmod.evaluate import predict_splits, scored_rows
from flowmod.extensions.context import read_context
from flowmod.params import Params
from flowmod.select import PARTS
from flowmod.train import MODEL_OUTPUTS, extension_parts, seed_index, train_seed


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
    #: the static-world flow's depth (:data:`flowmod.extensions.context.DEPTHS`)
    depth: str = "boxes"

    @property
    def flow_channels(self) -> tuple[int, ...]:
        """The channels that hold flow, px (what the recipe's ``input_scaling`` scales)."""
        return tuple(range(4 if self.name == "flow+static" else 2)) if self.flow else ()


VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("flow", 2, True, False, False, (0,), "raw flow (the paper)"),
    Variant("residual", 2, True, True, False, (0,), "flow minus static-world flow"),
    Variant("residual-deployed", 2, True, True, False, (0,),
            "flow minus static-world flow, target depth from its 2D box", depth="ground"),
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
    if variant in ("residual", "residual-deployed"):
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
    """(inputs, index) of one stored split for ``variant``: the context node's arrays and,
    for an input with flow, the flow crops of the method's crops node (same objects,
    checked)."""
    v = VARIANTS[variant]
    static, images, df = read_context(context_folder, split, v.depth)
    flow = None
    if v.flow:
        flow, fdf = read_crops(crops_folder, split)
        _same_objects(fdf, df, f"{split} split of {crops_folder}")
    return Inputs(variant, flow, static if v.static else None,
                  images if v.images else None), df


def _reader(variant: str, context_folder: Any, crops_folder: Any) -> SplitReader:
    """A :data:`flowmod.crops.SplitReader` of the input's parts (flow, static, images)."""
    def read(split: str) -> tuple[list[Any], pd.DataFrame]:
        x, df = split_inputs(variant, context_folder, crops_folder, split)
        return [x.parts[k] for k in ("flow", "static", "images")], df
    return read


def _inputs(variant: str, arrays: list[Any], df: pd.DataFrame) -> tuple[Inputs, pd.DataFrame]:
    flow, static, images = arrays
    return Inputs(variant, flow, static, images), df


def fold_inputs(variant: str, context_folder: Any, crops_folder: Any, folds: int, fold: int,
                role: str, part: str = "keyframe") -> tuple[Inputs, pd.DataFrame]:
    """(inputs, index) of the objects that play ``role`` for the model of ``fold``
    (:func:`flowmod.crops.gather_fold`)."""
    return _inputs(variant, *gather_fold(_reader(variant, context_folder, crops_folder),
                                         folds, fold, role, part))


def scored_inputs(variant: str, context_folder: Any, crops_folder: Any, folds: int,
                  part: str) -> tuple[Inputs, pd.DataFrame]:
    """(inputs, index) of every object a chain's models are scored on in ``part``
    (:func:`flowmod.evaluate.scored_rows`)."""
    return _inputs(variant, *scored_rows(_reader(variant, context_folder, crops_folder),
                                         folds, part))


# --- the stages --------------------------------------------------------------------------------

def chains(p: Params) -> list[tuple[str | None, str]]:
    """The (flow method, input) chains of chapter 10: every extension method with every
    input that holds flow, and the input without flow (``images``) once, method None."""
    return [(m, v) for v in p.extension_inputs
            for m in (p.extension_methods if v != "images" else [None])]


def chain_key(method: str | None, variant: str) -> str:
    """``method/input`` (``images`` alone): the key of a chain's nodes."""
    return "/".join(x for x in (method, variant) if x)


def _chain(node: dag.Node) -> tuple[str | None, str]:
    """(method, input) of an ``xtrain`` (part ``<input>/s<k>``) or ``xevaluate`` node."""
    return node.method, str(node.part).split("/")[0]


def build_xtrain(b: dag.Build, progress: bool) -> dict[str, Any]:
    """Build one ``xtrain[<method>/<input>/s<k>]`` node: the classifier on that input of the
    keyframe train/val split, Table 2 settings, epoch chosen on validation."""
    m, v = _chain(b.node)
    ctx = b.input_dir(dag.Node("context", None, "keyframe"))
    crops_dir = b.input_dir(dag.Node("crops", m, "keyframe")) if m else None
    train, val = (fold_inputs(v, ctx, crops_dir, b.params.folds, seed_index(b.node), role)
                  for role in ("train", "val"))
    info = train_seed(b, train, val, progress, f"{m + ' ' if m else ''}{v}",
                      in_channels=VARIANTS[v].channels, flip_negate=VARIANTS[v].negate,
                      flow_channels=VARIANTS[v].flow_channels)
    return {**info, "input": v, "channels": VARIANTS[v].channels}


def build_xevaluate(b: dag.Build, progress: bool) -> dict[str, Any]:
    """Build one ``xevaluate[<method>/<input>]`` node: the chain's models on their test rows
    and the generalisation set (``test.parquet``, ``general.parquet``; ``prob_s<k>`` per
    seed, or ``prob`` by each row's fold)."""
    m, v = _chain(b.node)
    splits = {}
    for split, part in (("test", "keyframe"), ("general", "general")):
        crops_dir = b.input_dir(dag.Node("crops", m, part)) if m else None
        splits[split] = scored_inputs(v, b.input_dir(dag.Node("context", None, part)),
                                      crops_dir, b.params.folds, part)
    predict_splits(b, "xtrain", chain_key(m, v), splits, in_channels=None)
    return {"seeds": b.params.extension_seeds, "input": v}


def _xtrain_inputs(node: dag.Node, p: Params) -> tuple[dag.Node, ...]:
    m = node.method
    return ((dag.Node("crops", m, "keyframe"),) if m else ()) + (
        dag.Node("context", None, "keyframe"),)


def _xevaluate_inputs(node: dag.Node, p: Params) -> tuple[dag.Node, ...]:
    m, v = _chain(node)
    models = tuple(dag.Node("xtrain", m, f"{v}/{k}") for k in extension_parts(p))
    flow = tuple(dag.Node("crops", m, part) for part in PARTS) if m else ()
    return (*models, *flow, *(dag.Node("context", None, part) for part in PARTS))


#: Chapter 10: one seed of a classifier on another input (``make extensions``).
XTRAIN = dag.Stage(
    "xtrain", 1, "10", "extensions/models/{key}", "a classifier on another input",
    nodes=lambda p: [dag.Node("xtrain", m, f"{v}/{k}") for m, v in chains(p)
                     for k in extension_parts(p)],
    inputs=_xtrain_inputs, build=build_xtrain, gate="extension_build", outputs=MODEL_OUTPUTS,
    parallel=True)
#: Chapter 10: a chain's seeds on the test split and the generalisation set.
XEVALUATE = dag.Stage(
    "xevaluate", 1, "10", "extensions/metrics/{key}", "its test and generalisation predictions",
    nodes=lambda p: [dag.Node("xevaluate", m, v) for m, v in chains(p)],
    inputs=_xevaluate_inputs, build=build_xevaluate, gate="extension_build",
    outputs=("test.parquet", "general.parquet"))
