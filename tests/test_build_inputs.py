"""Chapter 10's classifier stages (:mod:`flowmod.extensions.inputs`): ``xtrain`` and
``xevaluate`` built on hand-made published inputs (quick: no world, no training).

The inputs are written by hand into a smoke-profile run folder under the library's own file
names (:func:`flowmod.extensions.context.paths` for the ``context`` node's static-world flow,
deployable static-world flow, image crops and index; :func:`flowmod.crops.crop_paths` for a
method's flow crops), each node with a manifest, so that the real stage graph
(``pipeline.GRAPH``) reads them. Every array holds values exact in float16, so the expected
inputs are computed here by hand with numpy: which objects play which role for which fold's
model, which channels in which order, and their values.

* ``xtrain``: the trainer (``train_seed``) is replaced by a recorder, so the test sees the
  exact training and validation inputs, rows and settings the node hands it.
* ``xevaluate``: the ``xtrain`` nodes are published with hand-made (untrained, seeded)
  networks; the predictions table must hold, per row, the probability of its own fold's
  network on the input composed here by hand.
"""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest
from conftest import shared_scope
from handmade import node_folder

from flowmod import pipeline
from flowmod.crops import crop_paths
from flowmod.dag import Node
from flowmod.evaluate import read_frame
from flowmod.extensions import context, inputs
from flowmod.params import load_profile

#: Crop size (the network needs >= 32), folds, rows per stored split.
S, FOLDS, PER_SPLIT = 32, 3, 4
#: The general set's rows, by fold (in stored order: mixed; modulo the run's folds).
GENERAL_FOLDS = [2, 0, 1, 0, 2, 1]


def _params(root, folds=FOLDS, **kw):
    """The smoke profile in ``root`` with chapter 10's every input on dis."""
    return load_profile("smoke", run_dir=str(root / "runs"), folds=folds,
                        extension_methods=["dis"], extension_inputs=list(inputs.EXTENSION_INPUTS),
                        **kw)


def _px(rng, shape):
    """Flow-like values exact in float16 (eighths of a px, |x| <= 5)."""
    return (rng.integers(-40, 41, shape) / 8).astype(np.float16)


def _index(split, folds):
    """A stored split's objects: fold, validation scene, label, token."""
    if split == "general":
        fold = np.array(GENERAL_FOLDS) % folds
    elif split.startswith("f"):
        fold = np.full(PER_SPLIT, int(split[1:]))
    else:
        fold = np.zeros(PER_SPLIT, int)
    n = len(fold)
    return pd.DataFrame({"ann_token": [f"{split}-{i}" for i in range(n)],
                         "scene": [f"scene-{split}-{i % 2}" for i in range(n)],
                         "split": split, "fold": fold, "val_scene": np.arange(n) % 2 == 1,
                         "label": (np.arange(n) // 2) % 2, "distance": 40.0 + np.arange(n)})


def _splits(part, folds):
    if part == "general":
        return ["general"]
    return [f"f{k}" for k in range(folds)] if folds > 1 else ["train", "val", "test"]


def _make_inputs(p, seed=0):
    """Publish context[keyframe], context[general], crops[dis/keyframe], crops[dis/general];
    returns {split: {flow, static, deployed, images, index}} (the arrays as float32 / uint8)."""
    rng = np.random.default_rng(seed)
    data = {}
    for part in ("keyframe", "general"):
        ctx = node_folder(p, Node("context", None, part))
        crops = node_folder(p, Node("crops", "dis", part))
        for split in _splits(part, p.folds):
            df = _index(split, p.folds)
            n = len(df)
            arr = {"flow": _px(rng, (n, 2, S, S)), "static": _px(rng, (n, 2, S, S)),
                   "deployed": _px(rng, (n, 2, S, S)),
                   "images": rng.integers(0, 256, (n, 6, S, S), dtype=np.uint8)}
            f = context.paths(ctx, split)
            for name in (context.STATIC, context.DEPLOYED, context.IMAGES):
                np.save(f[name], arr[name])
            df.to_parquet(f["index"], index=False)
            npy, idx = crop_paths(crops, split)
            np.save(npy, arr["flow"])
            df.to_parquet(idx, index=False)
            data[split] = {**{k: a.astype(np.float32) if a.dtype == np.float16 else a
                              for k, a in arr.items()}, "index": df}
    return data


def _by_hand(variant, d):
    """The classifier's input composed by hand: (N, C, S, S) float32."""
    img = (d["images"].astype(np.float32) / 255 - 0.5) / 0.25
    return {"residual": lambda: d["flow"] - d["static"],
            "residual-deployed": lambda: d["flow"] - d["deployed"],
            "flow+static": lambda: np.concatenate([d["flow"], d["static"]], axis=1),
            "images": lambda: img,
            "images+flow": lambda: np.concatenate([d["flow"], img], axis=1)}[variant]()


def _rows(data, splits, keep):
    """The hand-made rows of ``splits`` (in order) that ``keep(index)`` selects, as
    ({array: stacked}, index)."""
    parts = []
    for s in splits:
        m = keep(data[s]["index"]).to_numpy()
        parts.append({k: (v[m].reset_index(drop=True) if k == "index" else v[m])
                      for k, v in data[s].items()})
    return ({k: np.concatenate([q[k] for q in parts]) for k in parts[0] if k != "index"},
            pd.concat([q["index"] for q in parts], ignore_index=True))


@pytest.fixture(scope=shared_scope)
def world(tmp_path_factory):
    """Three folds of hand-made published context and dis crops."""
    p = _params(tmp_path_factory.mktemp("xinputs"))
    return p, _make_inputs(p)


# --- xtrain ---------------------------------------------------------------------------------

#: Per input: (method, parts its input holds, channels, channels a flip negates, flow channels)
CHAINS = {"residual": ("dis", {"flow", "static"}, 2, (0,), (0, 1)),
          "residual-deployed": ("dis", {"flow", "static"}, 2, (0,), (0, 1)),
          "flow+static": ("dis", {"flow", "static"}, 4, (0, 2), (0, 1, 2, 3)),
          "images": (None, {"images"}, 6, (), ()),
          "images+flow": ("dis", {"flow", "images"}, 8, (0,), (0, 1))}


def _recorder(monkeypatch):
    """Replace the trainer by one that records what it is given; returns the records."""
    seen = []

    def train_seed(b, train, val, progress, what, **kw):
        seen.append({"train": train, "val": val, "progress": progress, "what": what, **kw})
        return {"best_epoch": 3, "seed": 17}

    monkeypatch.setattr(inputs, "train_seed", train_seed)
    return seen


def _check_given(x, df, variant, want_x, want_df, parts):
    """``(x, df)``: the rows ``want_df`` with the input ``want_x`` and exactly ``parts``."""
    assert df["ann_token"].tolist() == want_df["ann_token"].tolist(), variant
    assert x.variant == variant and len(x) == len(want_df)
    assert x.shape == (len(want_df), *want_x.shape[1:])
    assert {k for k, a in x.parts.items() if a is not None} == parts, variant
    got = x[np.arange(len(x))]
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, want_x)


@pytest.mark.parametrize("variant", list(CHAINS))
def test_xtrain_trains_on_the_other_folds_training_rows_and_validates_on_their_val_scenes(
        world, monkeypatch, variant):
    """xtrain[<m>/<input>/f1] hands the trainer, for fold 1's model, the train-scene rows of
    folds 0 and 2 and their validation-scene rows, each composed as the input says, with its
    channels, flip and flow channels; its manifest fields add the input and channels."""
    p, data = world
    m, parts, channels, negate, flow_channels = CHAINS[variant]
    seen = _recorder(monkeypatch)
    b = pipeline.GRAPH.begin(p, Node("xtrain", m, f"{variant}/f1"))
    info = inputs.build_xtrain(b, True)
    assert info == {"best_epoch": 3, "seed": 17, "input": variant, "channels": channels}
    (got,) = seen
    assert got["what"] == (f"dis {variant}" if m else variant)
    assert got["progress"] is True
    assert (got["in_channels"], got["flip_negate"], got["flow_channels"]) == (
        channels, negate, flow_channels)
    for role, val in (("train", False), ("val", True)):
        want, df = _rows(data, ["f0", "f2"], lambda d, v=val: d["val_scene"] == v)
        _check_given(*got[role], variant, _by_hand(variant, want), df, parts)


def test_xtrain_with_one_split_reads_the_stored_train_and_val_splits(tmp_path, monkeypatch):
    """Without cross-validation, seed 1's model trains on the whole ``train`` split and
    validates on the ``val`` split (the test split unread)."""
    p = _params(tmp_path, folds=1, extension_seeds=2)
    data = _make_inputs(p, seed=1)
    seen = _recorder(monkeypatch)
    inputs.build_xtrain(pipeline.GRAPH.begin(p, Node("xtrain", "dis", "residual/s1")), False)
    (got,) = seen
    assert got["progress"] is False
    for role in ("train", "val"):
        _check_given(*got[role], "residual", _by_hand("residual", data[role]),
                     data[role]["index"], {"flow", "static"})


# --- reading one split ----------------------------------------------------------------------


def test_split_inputs_reads_the_context_index_and_its_depth(world):
    """A split's input and index: the context node's rows; residual-deployed subtracts the
    deployable static world, residual the annotated-box one; images read no crops."""
    p, data = world
    ctx = pipeline.GRAPH.node_dir(p, Node("context", None, "keyframe"))
    crops = pipeline.GRAPH.node_dir(p, Node("crops", "dis", "keyframe"))
    for variant in ("residual", "residual-deployed"):
        x, df = inputs.split_inputs(variant, ctx, crops, "f2")
        pd.testing.assert_frame_equal(df, data["f2"]["index"])
        np.testing.assert_array_equal(x[np.arange(PER_SPLIT)], _by_hand(variant, data["f2"]))
    x, df = inputs.split_inputs("images", ctx, "no crops here", "f0")
    np.testing.assert_array_equal(x[np.arange(PER_SPLIT)], _by_hand("images", data["f0"]))


def _other_crops(p, folder, split, tokens):
    """Flow crops of ``split`` whose index holds ``tokens``."""
    rng = np.random.default_rng(5)
    npy, idx = crop_paths(folder, split)
    np.save(npy, _px(rng, (len(tokens), 2, S, S)))
    df = _index(split, p.folds).iloc[:len(tokens)].assign(ann_token=tokens)
    df.to_parquet(idx, index=False)


@pytest.mark.parametrize("tokens", [["f0-0", "f0-1", "f0-X", "f0-3"], ["f0-0", "f0-1", "f0-2"]],
                         ids=["other-object", "fewer-rows"])
def test_flow_crops_of_other_objects_than_the_context_are_refused(world, tmp_path, tokens):
    """Flow crops that hold another object (or fewer rows) than the context split are one
    ValueError naming the split, the folder and both row counts."""
    p, _ = world
    ctx = pipeline.GRAPH.node_dir(p, Node("context", None, "keyframe"))
    _other_crops(p, tmp_path, "f0", tokens)
    msg = (f"f0 split of {tmp_path}: the flow crops and the context crops hold other objects "
           f"({len(tokens)} and {PER_SPLIT} rows); rebuild chapter 10's context stage")
    with pytest.raises(ValueError, match=f"^{re.escape(msg)}$"):
        inputs.split_inputs("residual", ctx, tmp_path, "f0")
    x, _ = inputs.split_inputs("images", ctx, tmp_path, "f0")  # no flow: not read
    assert len(x) == PER_SPLIT


# --- xevaluate ------------------------------------------------------------------------------


def _publish_models(p, m, variant):
    """Publish the chain's xtrain nodes, each with a network of its own (one seeded network,
    its first convolution and output bias changed per part); returns {part: network}."""
    import torch

    from flowmod.model import motion_resnet18
    from flowmod.train import extension_parts, model_file

    torch.manual_seed(7)
    net = motion_resnet18(inputs.VARIANTS[variant].channels, width=4).eval()
    base = {k: v.clone() for k, v in net.state_dict().items()}
    nets = {}
    for k, part in enumerate(extension_parts(p)):
        state = {**base, "conv1.weight": base["conv1.weight"] * (1 + 0.5 * k),
                 "fc.bias": base["fc.bias"] - 0.4 * k}
        node = Node("xtrain", m, f"{variant}/{part}")
        torch.save(state, model_file(node_folder(p, node, amp="off")))
        nets[part] = state
    return net, nets


def _probs(net, state, x):
    """The probabilities of ``net`` with weights ``state`` on ``x``."""
    from flowmod.model import predict

    net.load_state_dict(state)
    return predict(net, x, device="cpu")


def _check_table(got, want):
    """``got`` holds ``want``'s rows and columns, its probabilities to 1e-6, and they spread."""
    assert got.columns.tolist() == want.columns.tolist()
    probs = [c for c in want.columns if c.startswith("prob")]
    pd.testing.assert_frame_equal(got.drop(columns=probs), want.drop(columns=probs))
    for c in probs:
        np.testing.assert_allclose(got[c], want[c], rtol=0, atol=1e-6, err_msg=c)
        assert np.ptp(want[c]) > 1e-3, "the hand-made models tell the rows apart"


def test_xevaluate_scores_every_row_with_its_own_fold_s_model(tmp_path):
    """xevaluate[dis/images+flow] (two folds) publishes test.parquet (fold 0's keyframe
    rows, then fold 1's) and general.parquet (the general set's rows of fold 0, then of fold
    1), each row with the probability of its own fold's 8-channel model on the input
    composed by hand; its manifest records the seeds and the input."""
    p = _params(tmp_path, folds=2)
    data = _make_inputs(p, seed=3)
    net, nets = _publish_models(p, "dis", "images+flow")
    folder = pipeline.GRAPH.build_node(p, Node("xevaluate", "dis", "images+flow"))
    for name, splits in (("test", ["f0", "f1"]), ("general", ["general"])):
        frames = []
        for k in range(2):
            want, df = _rows(data, splits, lambda d, k=k: d["fold"] == k)
            frames.append(df.assign(prob=_probs(net, nets[f"f{k}"],
                                                _by_hand("images+flow", want))))
        _check_table(read_frame(folder, name), pd.concat(frames, ignore_index=True))
    rec = pipeline.GRAPH.recorded(p, Node("xevaluate", "dis", "images+flow"))
    assert (rec["seeds"], rec["input"]) == (1, "images+flow")


def test_xevaluate_of_the_images_scores_the_test_split_and_general_set_with_each_seed(
        tmp_path):
    """Without cross-validation, xevaluate[images] (no flow method, no crops) gives every
    row of the test split and of the general set each seed's probability (``prob_s0``,
    ``prob_s1``; ``prob`` = seed 0's) on the standardised image crops."""
    p = _params(tmp_path, folds=1, extension_seeds=2)
    data = _make_inputs(p, seed=2)
    net, nets = _publish_models(p, None, "images")
    folder = pipeline.GRAPH.build_node(p, Node("xevaluate", None, "images"))
    for name in ("test", "general"):
        x = _by_hand("images", data[name])
        probs = {f"prob_{s}": _probs(net, nets[s], x) for s in ("s0", "s1")}
        want = data[name]["index"].assign(**probs, prob=probs["prob_s0"])
        _check_table(read_frame(folder, name), want)
    rec = pipeline.GRAPH.recorded(p, Node("xevaluate", None, "images"))
    assert (rec["seeds"], rec["input"]) == (2, "images")


def test_fold_inputs_of_the_general_set_are_its_rows_of_the_fold(world):
    """On the general part, the rows a fold's model is tested on are the general set's rows
    of that fold's scenes, in stored order; on the keyframe part, the fold's own split."""
    p, data = world
    ctx, crops = (pipeline.GRAPH.node_dir(p, Node(s, m, "general"))
                  for s, m in (("context", None), ("crops", "dis")))
    x, df = inputs.fold_inputs("flow+static", ctx, crops, FOLDS, 2, "test", part="general")
    want, want_df = _rows(data, ["general"], lambda d: d["fold"] == 2)
    assert df["ann_token"].tolist() == ["general-0", "general-4"]
    _check_given(x, df, "flow+static", _by_hand("flow+static", want), want_df,
                 {"flow", "static"})
    ctx, crops = (pipeline.GRAPH.node_dir(p, Node(s, m, "keyframe"))
                  for s, m in (("context", None), ("crops", "dis")))
    x, df = inputs.fold_inputs("residual", ctx, crops, FOLDS, 1, "test")
    _check_given(x, df, "residual", _by_hand("residual", data["f1"]), data["f1"]["index"],
                 {"flow", "static"})
