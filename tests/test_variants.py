"""Chapter 10: the classifier on other inputs (residual flow, flow + static-world flow,
images, images + flow): composing them, flipping them, the context crops on the smoke world,
the nodes of the graph and the scores built from them."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from flowmod import crops, dag, evaluate, metrics, pipeline
from flowmod.artefacts import CheckpointError
from flowmod.chapters import ch10_inputs as ch10
from flowmod.chapters import common
from flowmod.crops import hflip
from flowmod.extensions import context, inputs
from flowmod.model import load_model, motion_resnet18, predict
from flowmod.params import ProfileError, load_profile
from flowmod.train import TrainingError, train_model


def _parts(n: int = 5, s: int = 8, seed: int = 0):
    rng = np.random.default_rng(seed)
    flow = rng.normal(0, 5, (n, 2, s, s)).astype(np.float16)
    static = rng.normal(0, 5, (n, 2, s, s)).astype(np.float16)
    images = rng.integers(0, 256, (n, 6, s, s), dtype=np.uint8)
    return flow, static, images


def test_compose_stacks_each_input_as_documented():
    flow, static, images = _parts()
    f, st = flow.astype(np.float32), static.astype(np.float32)
    img = (images.astype(np.float32) / 255 - 0.5) / 0.25
    np.testing.assert_array_equal(inputs.compose("flow", flow), f)
    np.testing.assert_array_equal(inputs.compose("residual", flow, static), f - st)
    np.testing.assert_array_equal(inputs.compose("flow+static", flow, static),
                                  np.concatenate([f, st], 1))
    np.testing.assert_allclose(inputs.compose("images", images=images), img, rtol=1e-6)
    both = inputs.compose("images+flow", flow, images=images)
    assert both.shape == (5, 8, 8, 8) and both.dtype == np.float32
    np.testing.assert_array_equal(both[:, :2], f)
    assert -2.0 <= both[:, 2:].min() and both[:, 2:].max() <= 2.0
    for name, v in inputs.VARIANTS.items():
        x = inputs.compose(name, flow, static, images)
        assert x.shape[1] == v.channels, name
    with pytest.raises(ValueError, match="needs \\['static'\\]"):
        inputs.compose("residual", flow)


def test_inputs_compose_per_batch_and_check_lengths():
    flow, static, images = _parts(n=7)
    x = inputs.Inputs("flow+static", flow, static)
    assert x.shape == (7, 4, 8, 8) and len(x) == 7
    idx = np.array([1, 4, 6])
    np.testing.assert_array_equal(x[idx], inputs.compose("flow+static", flow[idx], static[idx]))
    np.testing.assert_array_equal(x[2:4], inputs.compose("flow+static", flow[2:4],
                                                           static[2:4]))
    with pytest.raises(ValueError, match="different lengths"):
        inputs.Inputs("residual", flow, static[:6])


def test_flip_negates_the_horizontal_flow_components_of_each_input():
    flow, static, images = _parts(n=2)
    for name, v in inputs.VARIANTS.items():
        x = inputs.compose(name, flow, static, images)
        y = hflip(x, v.negate)
        np.testing.assert_array_equal(hflip(y, v.negate), x)
        for c in range(v.channels):
            sign = -1 if c in v.negate else 1
            np.testing.assert_array_equal(y[:, c], sign * x[:, c, :, ::-1])
    # the flip of flow+static is the input of the flipped flow and flipped static flow
    np.testing.assert_array_equal(
        hflip(inputs.compose("flow+static", flow, static), (0, 2)),
        inputs.compose("flow+static", hflip(flow.astype(np.float32)),
                         hflip(static.astype(np.float32))))
    t = torch.from_numpy(inputs.compose("images+flow", flow, images=images))
    assert torch.equal(hflip(t, (0,)), torch.from_numpy(hflip(t.numpy(), (0,))))


def test_models_of_other_channel_counts_train_save_and_load(tmp_path):
    rng = np.random.default_rng(0)
    n, s = 48, 32
    flow = rng.normal(0, 1, (n, 2, s, s)).astype(np.float16)
    static = rng.normal(0, 1, (n, 2, s, s)).astype(np.float16)
    y = (np.arange(n) % 2).astype(int)
    flow[y == 1, 0] += 3  # the movers' flow differs from the static world's
    x = inputs.Inputs("flow+static", flow, static)
    df = pd.DataFrame({"label": y})
    h = train_model(x, df, x, df, tmp_path, epochs=2, batch_size=16, progress=False,
                    device="cpu", amp=None, in_channels=4, flip_negate=(0, 2))
    assert len(h) == 2
    model = load_model(tmp_path / "best.pt", in_channels=None)
    assert model.conv1.in_channels == 4
    with pytest.raises(CheckpointError, match=r"\(64, 4, 7, 7\).*\(64, 2, 7, 7\)"):
        load_model(tmp_path / "best.pt")  # the paper's 2-channel input: refused, named
    assert predict(model, x, device="cpu").shape == (n,)
    ck = torch.load(tmp_path / "last.pt", weights_only=True)
    assert ck["config"]["channels"] == 4 and ck["config"]["flip_negate"] == [0, 2]
    # a 2-channel split where 4 channels are trained is refused, naming the shape
    with pytest.raises(TrainingError, match=r"\(N, 4, S, S\)"):
        train_model(x, df, flow, df, tmp_path / "b", epochs=1, progress=False, device="cpu",
                    in_channels=4)
    assert motion_resnet18(6)(torch.zeros(2, 6, 32, 32)).shape == (2, 1)


def test_extension_parameters_are_checked():
    with pytest.raises(ProfileError, match="extension_methods"):
        load_profile("smoke", extension_methods=["farneback"])
    with pytest.raises(ProfileError, match="twice"):
        load_profile("smoke", extension_inputs=["residual", "residual"])
    with pytest.raises(ProfileError, match="extension_inputs"):
        load_profile("smoke", extension_inputs=["optical"])
    p = load_profile("smoke", extension_inputs=[], error_kinds=["noise"])
    assert not [n for n in pipeline.nodes(p) if pipeline.GRAPH.stage(n).chapter == "10"]
    # chapter 13's pull reads the still-world flow: its context nodes stay, nothing else
    pulled = load_profile("smoke", extension_inputs=[], error_kinds=["pull"])
    assert {n.stage for n in pipeline.nodes(pulled)
            if pipeline.GRAPH.stage(n).chapter == "10"} == {"context"}
    # without inputs, any methods are fine: nothing of chapter 10 exists
    load_profile("smoke", extension_inputs=[], extension_methods=["farneback"])


def test_chapter10_nodes_and_their_inputs():
    p = load_profile("smoke", extension_inputs=["residual", "images"],
                     extension_methods=["dis"], extension_seeds=2, folds=1)
    ten = [str(n) for n in pipeline.nodes(p) if pipeline.GRAPH.stage(n).chapter == "10"]
    assert ten == ["context[keyframe]", "context[general]", "xtrain[dis/residual/s0]",
                   "xtrain[dis/residual/s1]", "xtrain[images/s0]", "xtrain[images/s1]",
                   "xevaluate[dis/residual]", "xevaluate[images]"]
    assert pipeline.inputs(dag.Node("xtrain", None, "images/s0"), p) == (
        dag.Node("context", None, "keyframe"),)
    assert dag.Node("crops", "dis", "general") in pipeline.inputs(
        dag.Node("xevaluate", "dis", "residual"), p)
    assert str(pipeline.node_dir(p, dag.Node("xtrain", None, "images/s1"))).endswith(
        "extensions/models/images/s1")


# --- on the smoke world (chapter 10 built by the smoke_built fixture) -------------------------


def test_context_crops_match_the_flow_crops_objects_images_and_geometry(smoke_built):
    p = smoke_built
    static, images, idx = ch10.context_split(p, "train")
    x, cidx = common.open_crops(p, "gt", "train")
    assert idx["ann_token"].equals(cidx["ann_token"])
    assert static.shape == x.shape and images.shape == (len(x), 6, *x.shape[2:])
    # the image channels are the crops of the two frames' JPEGs in the flow crop's window
    pairs = pd.read_parquet(pipeline.published(p, dag.Node("select")) / "pairs.parquet")
    row = pairs.set_index("pair_id").loc[idx["pair_id"].iloc[0]]
    box = idx[list(crops.BOX_COLUMNS)].to_numpy(float)[:1]
    for k, col in enumerate(("path_1", "path_2")):
        want = crops.crop_image(context.read_image(p.dataroot_path / row[col]), box,
                                p.crop_size, p.crop_scale)[0].transpose(2, 0, 1)
        np.testing.assert_array_equal(images[0, 3 * k:3 * k + 3], want)
    # the static world explains the exact flow of still vehicles, not that of movers
    t = ch10.static_explains(x, static, idx["label"].to_numpy()).set_index("vehicles")
    moved = np.median(np.abs(np.asarray(x, np.float32)), axis=(1, 2, 3)) > 0.5
    assert moved.sum() >= 5
    still = ch10.static_explains(x[moved], static[moved], idx["label"].to_numpy()[moved])
    assert still.set_index("vehicles").loc["still", "residual / flow"] < 0.1
    assert t.loc["moving", "residual (px)"] > 3 * t.loc["still", "residual (px)"]


def test_deployed_static_world_explains_still_vehicles_less_exactly_than_the_oracle(
        smoke_built):
    """The static world a car could compute (flat ground, the target at its 2D box's ground
    contact) removes most of a still vehicle's exact flow, less exactly than the annotated
    3D boxes do; movers keep theirs. ``residual-deployed`` stacks flow minus it."""
    p = smoke_built
    ctx = pipeline.published(p, dag.Node("context", None, "keyframe"))
    flows = pipeline.published(p, dag.Node("crops", "gt", "keyframe"))
    x, idx = crops.read_crops(flows, "f0")
    oracle = context.read_context(ctx, "f0")[0]
    deployed, _, didx = context.read_context(ctx, "f0", "ground")
    assert didx["ann_token"].equals(idx["ann_token"]) and deployed.shape == x.shape
    assert not np.array_equal(deployed, oracle)
    moved = np.median(np.abs(np.asarray(x, np.float32)), axis=(1, 2, 3)) > 0.5
    labels = idx["label"].to_numpy()[moved]
    car = ch10.static_explains(x[moved], deployed[moved], labels).set_index("vehicles")
    box = ch10.static_explains(x[moved], oracle[moved], labels).set_index("vehicles")
    assert car.loc["still", "objects"] >= 5
    assert car.loc["still", "residual / flow"] < 0.5
    assert box.loc["still", "residual (px)"] < car.loc["still", "residual (px)"]
    assert car.loc["moving", "residual (px)"] > car.loc["still", "residual (px)"]
    xs, _ = inputs.split_inputs("residual-deployed", ctx, flows, "f0")
    np.testing.assert_allclose(xs[np.arange(4)], np.asarray(x[:4], np.float32)
                               - np.asarray(deployed[:4], np.float32))


def test_context_refuses_a_corrupt_image(smoke_built, tmp_path):
    p = smoke_built
    pairs = pd.read_parquet(pipeline.published(p, dag.Node("select")) / "pairs.parquet")
    objects = crops.part_objects(pipeline.published(p, dag.Node("select")), "keyframe")
    root = tmp_path / "root"
    bad = root / pairs["path_1"].iloc[0]
    bad.parent.mkdir(parents=True)
    bad.write_bytes(b"not a jpeg")
    one = objects[objects["pair_id"] == pairs["pair_id"].iloc[0]]
    with pytest.raises(crops.CropsError, match=str(bad.name)):
        context.image_crops(one, pairs, root, 32, 3.0)


def test_chapter10_scores_are_those_of_its_predictions(smoke_built):
    p = smoke_built
    assert ch10.built(p) == inputs.chains(p) == [("gt", "residual"), ("dis", "residual"),
                                                     (None, "images")]
    rows = ch10.rows(p)
    assert rows == [("gt", "flow"), ("gt", "residual"), ("dis", "flow"), ("dis", "residual"),
                    (None, "images")]
    table = ch10.table(p, rows)
    assert len(table) == len(rows) == 5
    assert table["input"].tolist() == ["flow", "residual [oracle: annotated-box depth]", "flow",
                                       "residual [oracle: annotated-box depth]",
                                       "images [untuned recipe]"]
    for (m, v), r in zip(rows, table.to_dict("records"), strict=True):
        d = ch10.predictions(p, m, v, "test")
        f1 = np.mean([metrics.seed_summary(d["label"].to_numpy(), pr[None],
                                            d["scene"].to_numpy())["f1"]
                      for pr in evaluate.seed_probs(d)])
        assert r["F1 (%)"] == round(100 * f1, 1)
        assert r["channels"] == inputs.VARIANTS[v].channels
    comp = ch10.comparisons(p, "general", rows)
    assert len(comp) == 3 and comp["comparison"].iloc[-1] == "images [untuned recipe] - gt: flow"
    # the test split's objects are those of Table 3
    xd = ch10.predictions(p, "dis", "residual", "test")
    assert xd["ann_token"].equals(ch10.predictions(p, "dis", "flow", "test")["ann_token"])


def test_chapter10_shows_only_what_was_built_with_these_parameters(smoke_built):
    p = smoke_built
    # other training settings: the built models are not the ones asked for
    other = p.model_copy(update={"epochs": p.epochs + 1, "extension_build": False})
    assert ch10.built(other) == []
    pipeline.build(other, ["10"])  # without extension_build: trains nothing
    assert ch10.built(other) == []
    assert "make extensions" in ch10.headline(other, ch10.comparisons(other))
    # the same settings: everything is current
    assert ch10.built(p.model_copy(update={"extension_build": False})) == inputs.chains(p)


def test_a_chapter_that_shows_what_is_built_reruns_when_more_is_built(smoke_built, tmp_path):
    """Chapter 10 without extension_build shows the chains built: its executed copy must not
    be reused once more (or fewer) of them exist, though no parameter changed."""
    from flowmod import environment, runner

    nb = next(n for n in runner.notebooks() if n.stem.startswith("10"))
    p = smoke_built.model_copy(update={"extension_build": False})
    values = runner.notebook_parameters(nb, p)
    device = environment.device_info("cpu")
    built = runner.notebook_fingerprint(nb, values, p, device)
    elsewhere = p.model_copy(update={"run_dir": str(tmp_path / "runs")})  # nothing built there
    assert [n for n in pipeline.expected(elsewhere) if pipeline.expected(elsewhere)[n] is None] == []
    assert runner.notebook_fingerprint(nb, values, elsewhere, device) != built
    assert runner.notebook_fingerprint(nb, values, p, device) == built


def test_chapter10_tags_every_input_whose_static_world_reads_annotated_boxes():
    """Where an input's static-world flow takes its depth from the annotated 3D boxes the
    table row says oracle; the deployed one says what it idealises; inputs with images say
    their recipe is the raw flow's, untuned for them; the raw flow no tag."""
    assert ch10.input_label("residual") == "residual [oracle: annotated-box depth]"
    assert ch10.input_label("flow+static") == "flow+static [oracle: annotated-box depth]"
    assert ch10.input_label("residual-deployed") == (
        "residual-deployed [idealised: exact poses, flat ground, annotated 2D box]")
    assert [ch10.input_label(v) for v in ("flow", "images", "images+flow")] == [
        "flow", "images [untuned recipe]", "images+flow [untuned recipe]"]


def test_chapter10_headline_asks_the_profiles_questions_in_order():
    """The headline reports each input of ``extension_inputs`` in the profile's order (fixed
    in advance, not the best by test F1) against the raw flow of the main method, with its
    paired interval; the static-world input is named as the oracle it is."""
    from flowmod.params import load_profile

    p = load_profile("smoke")  # extension_inputs [residual, images], methods [gt, dis]
    paired = pd.DataFrame({
        "comparison": ["gt: residual [oracle: annotated-box depth] - gt: flow",
                       "dis: residual [oracle: annotated-box depth] - dis: flow",
                       "images [untuned recipe] - gt: flow"],
        "ΔF1 (points)": [9.0, -1.0, 5.0],
        "95% CI, scenes and seeds (points)": ["2.0 to 15.0", "-3.0 to 1.0", "1.0 to 9.0"]})
    assert ch10.headline(p, paired) == (
        "against the raw dis flow, paired on the test scenes: residual" + ch10.ORACLE_NOTE
        + " -1.0 F1 points (95 % interval over scenes and training seeds -3.0 to 1.0); images "
        "(no flow; against gt flow) +5.0 F1 points (95 % interval over scenes and training "
        "seeds 1.0 to 9.0)")
    swapped = ch10.headline(p.model_copy(update={"extension_inputs": ["images", "residual"]}),
                            paired)
    assert swapped.index("images") < swapped.index("residual")
    assert "make extensions" in ch10.headline(p, paired.iloc[:1])


def test_a_new_record_re_executes_the_chapters_that_could_show_it(smoke_built, tmp_path,
                                                                  monkeypatch):
    """Chapter 06 shows committed ablation records: its fingerprint holds their content, so
    a new or changed record re-executes it instead of reusing its copy; a chapter that shows
    none keeps its copy."""
    from flowmod import environment, runner

    nb = next(n for n in runner.notebooks() if n.stem.startswith("06"))
    values = runner.notebook_parameters(nb, smoke_built)
    device = environment.device_info("cpu")
    before = runner.notebook_fingerprint(nb, values, smoke_built, device)
    rec = tmp_path / "record.json"
    monkeypatch.setattr(runner, "RECORDS", {"06": (*runner.RECORDS["06"], str(rec))})
    absent = runner.notebook_fingerprint(nb, values, smoke_built, device)
    rec.write_text('{"rows": []}')
    changed = runner.notebook_fingerprint(nb, values, smoke_built, device)
    assert len({before, absent, changed}) == 3
    rec.write_text('{"rows": [1]}')
    assert runner.notebook_fingerprint(nb, values, smoke_built, device) not in (absent, changed)
    other = next(n for n in runner.notebooks() if n.stem.startswith("07"))  # shows no record
    v7 = runner.notebook_parameters(other, smoke_built)
    fp7 = runner.notebook_fingerprint(other, v7, smoke_built, device)
    rec.write_text('{"rows": [2]}')
    assert runner.notebook_fingerprint(other, v7, smoke_built, device) == fp7
