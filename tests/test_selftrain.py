"""Chapter 12: FastFlowNet trained here from scratch: its losses, its batches, resuming, the
published weights as an ordinary ``fastflownet`` checkpoint, and the stage's nodes."""

from __future__ import annotations

import json
import time

import cv2
import numpy as np
import pandas as pd
import pytest
import torch

from flowmod import dag, pipeline
from flowmod.chapters import ch12_self_trained_flow as ch12
from flowmod.flow import selftrain
from flowmod.flow.networks import FastFlowNetFlow
from flowmod.params import ProfileError, load_profile


def _texture(h: int = 64, w: int = 96, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w, 3)).astype(np.float32), (0, 0), 1.5)
    return img


def _t(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(img.transpose(2, 0, 1)).float()[None]


def test_photometric_loss_is_lowest_at_the_true_motion_and_ignores_exposure():
    img1 = _texture()
    d = (3.0, -2.0)  # the content moves by d: img2(p) = img1(p - d)
    m = np.float32([[1, 0, d[0]], [0, 1, d[1]]])
    img2 = cv2.warpAffine(img1, m, (img1.shape[1], img1.shape[0]),
                          borderMode=cv2.BORDER_REFLECT)
    a, b = _t(img1), _t(img2)

    def loss(flow, b=b):
        f = torch.tensor(flow, dtype=torch.float32).view(1, 2, 1, 1).expand(1, 2, 64, 96)
        return selftrain.photometric_loss(a, b, f.contiguous(), smooth=0.0)[0].item()

    true = loss(d)
    assert true < 0.5 * loss((0.0, 0.0))
    assert true < loss((4.0, -2.0)) and true < loss((3.0, -1.0))
    brighter = torch.clamp(1.3 * b + 12.0, 0, 255)  # another exposure: census does not mind
    assert loss(d, brighter) < 0.5 * loss((0.0, 0.0), brighter)


def test_supervised_loss_and_inside_mask():
    flow = torch.zeros(1, 2, 4, 5)
    gt = torch.zeros(1, 2, 4, 5)
    gt[:, 0] = 3.0
    gt[:, 1] = 4.0  # 5 px off everywhere
    valid = torch.ones(1, 1, 4, 5)
    valid[..., 0] = 0
    loss, parts = selftrain.supervised_loss(flow, gt, valid)
    assert abs(loss.item() - 5.0) < 1e-3 and abs(parts["epe"] - 5.0) < 1e-3
    out = torch.zeros(1, 2, 4, 5)
    out[:, 0, :, 3:] = 2.0  # columns 3 and 4 move right by 2: 5 and 6 are outside
    m = selftrain.inside(out)[0, 0]
    assert m[:, :3].all() and not m[:, 3:].any()


def test_second_order_smoothness_is_zero_on_affine_flow_and_stops_at_edges():
    """Second order: a constant or linearly growing flow (a zoom) costs nothing, a kink
    does; measured on the 1/4 grid in its pixels; an image edge on the kink waives it."""
    h, w = 32, 48
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32),
                            torch.arange(w, dtype=torch.float32), indexing="ij")
    img = torch.full((1, 3, h, w), 100.0)
    zoom = torch.stack((0.1 * xs, 0.05 * ys))[None]
    assert selftrain.second_order_smoothness(zoom + 3.0, img).item() == pytest.approx(0, abs=1e-6)
    kink = torch.stack((8.0 * (xs >= 24).float(), torch.zeros_like(xs)))[None]
    # on the 1/4 grid (12 columns) a 2 px step: |d2| = 2 at the 2 columns beside it, out of
    # 10 centres and 2 channels, none in y: (2 x 2 / 10 / 2 + 0) / 2
    assert selftrain.second_order_smoothness(kink, img).item() == pytest.approx(0.1, rel=1e-5)
    edge = img.clone()
    edge[..., 24:] = 200.0
    assert selftrain.second_order_smoothness(kink, edge).item() < 1e-6, "an edge waives it"


def test_warmup_distance_is_l1_and_ssim_and_the_loss_says_which_it_used():
    a = _t(_texture())
    assert selftrain.warmup_distance(a, a).abs().max().item() < 1e-6
    darker = 0.5 * a
    d = selftrain.warmup_distance(a, darker)
    l1 = 0.15 * (0.5 * a).mean().item() / 255.0
    assert d.mean().item() > l1, "SSIM adds its share to the L1's"
    f = torch.zeros(1, 2, 64, 96)
    warm = selftrain.photometric_loss(a, darker, f, 0.0, warm=True)
    cold = selftrain.photometric_loss(a, darker, f, 0.0, warm=False)
    assert warm[1]["warm-up"] == 1.0 and cold[1]["warm-up"] == 0.0
    assert warm[1]["photometric"] != pytest.approx(cold[1]["photometric"], rel=1e-3)
    # the warm-up distance also finds the true motion
    img1 = _texture()
    img2 = cv2.warpAffine(img1, np.float32([[1, 0, 3], [0, 1, -2]]), (96, 64),
                          borderMode=cv2.BORDER_REFLECT)

    def loss(u, v):
        g = torch.tensor([u, v], dtype=torch.float32).view(1, 2, 1, 1).expand(1, 2, 64, 96)
        return selftrain.photometric_loss(_t(img1), _t(img2), g.contiguous(), 0.0,
                                          warm=True)[0].item()
    assert loss(3.0, -2.0) < 0.5 * loss(0.0, 0.0)


@pytest.fixture(scope="module")
def pairs_data(smoke_built):
    """Four keyframe pairs of the smoke world's training scenes, with their exact flow, at
    the smoke profile's flow_scale."""
    p = smoke_built
    sel = pd.read_parquet(pipeline.published(p, dag.Node("select")) / "pairs.parquet")
    train = selftrain.fold0_pairs(sel, p.folds, "train").head(4)
    return p, train


def _data(p, train, tmp_path, gt: bool = True) -> selftrain.FramePairs:
    root = p.dataroot_path
    files = (selftrain.cache_gt(train, root, p.version, p.flow_scale, tmp_path / "gt", False)
             if gt else None)
    return selftrain.FramePairs([(root / r.path_1, root / r.path_2)
                                 for r in train.itertuples()], p.flow_scale, files)


def test_batches_are_drawn_from_seed_and_step(pairs_data, tmp_path):
    p, train = pairs_data
    data = _data(p, train, tmp_path)
    img, flow, valid = data.load(0)[0], data.load(0)[2], data.load(0)[3]
    assert img.shape[:2] == flow.shape[:2] == valid.shape
    assert img.shape[0] == round(900 * p.flow_scale)
    a = selftrain.draw_batch(data, 3, 0, 2, (64, 128))
    b = selftrain.draw_batch(data, 3, 0, 2, (64, 128))
    c = selftrain.draw_batch(data, 4, 0, 2, (64, 128))
    assert a["img1"].shape == (2, 3, 64, 128) and a["gt"].shape == (2, 2, 64, 128)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(a["img1"], c["img1"])
    with pytest.raises(selftrain.SelfFlowError, match="selfflow_crop.*larger"):
        selftrain.draw_batch(data, 0, 0, 1, (1024, 2048))
    # whole frames resized: the picture and its exact flow shrink together
    f = selftrain.draw_batch(data, 3, 0, 2, (64, 128), "frame")
    whole = selftrain.draw_batch(data, 3, 0, 2, img.shape[:2], "frame")
    assert f["img1"].shape == (2, 3, 64, 128) and f["gt"].shape == (2, 2, 64, 128)
    ratio = 128 / img.shape[1]
    big = whole["gt"][0, 0][whole["valid"][0, 0] > 0].abs().mean().item()
    small = f["gt"][0, 0][f["valid"][0, 0] > 0].abs().mean().item()
    assert small == pytest.approx(ratio * big, rel=0.15), "u scales with the width"
    assert whole["img1"].shape[-2:] == img.shape[:2]
    with pytest.raises(selftrain.SelfFlowError, match="selfflow_window='tile'"):
        selftrain.draw_batch(data, 0, 0, 1, (64, 128), "tile")


def test_training_resumes_where_it_stopped_and_learns(pairs_data, tmp_path):
    p, train = pairs_data
    data = _data(p, train, tmp_path)
    kw = dict(iters=6, batch=1, lr=1e-3, crop=(64, 128), smooth=0.05, seed=0, progress=False)
    straight, h1 = selftrain.train_flow(data, "supervised", tmp_path / "a", **kw)
    part, _ = selftrain.train_flow(data, "supervised", tmp_path / "b", stop_after=3, **kw)
    assert (tmp_path / "b" / "last.pt").is_file()
    resumed, h2 = selftrain.train_flow(data, "supervised", tmp_path / "b", **kw)
    for k, v in straight.state_dict().items():
        torch.testing.assert_close(resumed.state_dict()[k], v, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(h1["loss"], h2["loss"], rtol=1e-5)
    assert list(h2["step"]) == [1, 2, 3, 4, 5, 6]
    # with an evaluation: step 0 scores the untrained network, then every eval_every steps
    calls = []

    def evaluate(model):
        calls.append(sum(float(v.abs().sum()) for v in model.state_dict().values()))
        return {"epe": float(len(calls))}
    _, h3 = selftrain.train_flow(data, "supervised", tmp_path / "e", evaluate=evaluate,
                                 eval_every=4, **kw)
    assert list(h3["step"]) == [0, 1, 2, 3, 4, 5, 6]
    assert h3["val_epe"].tolist()[:1] + h3["val_epe"].dropna().tolist()[1:] == [1.0, 2.0, 3.0]
    assert list(h3.dropna(subset=["val_epe"])["step"]) == [0, 4, 6]
    assert np.isnan(h3["loss"].iloc[0]) and calls[0] != calls[1]
    with pytest.raises(selftrain.SelfFlowError, match="exact flow"):
        selftrain.train_flow(_data(p, train, tmp_path, gt=False), "supervised",
                             tmp_path / "c", **kw)
    with pytest.raises(selftrain.SelfFlowError, match="multiples of 64"):
        selftrain.train_flow(data, "photometric", tmp_path / "d", **{**kw, "crop": (60, 128)})


def test_published_weights_are_a_fastflownet_checkpoint_with_the_recorded_error(smoke_built):
    p = smoke_built
    assert ch12.built(p) == ["photometric", "supervised", "finetune"]
    for mode in ch12.built(p):
        hist, ev = ch12.results(p, mode)
        assert ev["steps"] == p.selfflow_iters == len(hist) - 1  # and step 0
        assert hist["step"].iloc[0] == 0 and not np.isnan(hist["val_epe"].iloc[0])
        est = FastFlowNetFlow(ch12.weights_path(p, mode), device="cpu", scale=p.flow_scale)
        sel = pipeline.published(p, dag.Node("select"))
        pairs = pd.read_parquet(sel / "pairs.parquet")
        test = selftrain.heldout_pairs(pairs, p.selfflow_eval_pairs, p.seed, p.folds)
        h = selftrain.held_out(test, pd.read_parquet(sel / "objects.parquet"),
                               p.dataroot_path, p.version, True)
        again = selftrain.score(est.estimate, h)
        assert again["epe"] == pytest.approx(ev["fastflownet"]["epe"], rel=1e-4)
        # the curve and the choice are on the validation scenes' pairs, not the test pairs
        val = selftrain.validation_pairs(pairs, p.selfflow_eval_pairs, p.seed, p.folds)
        assert not set(val["scene"]) & set(test["scene"])
        hv = selftrain.held_out(val, pd.read_parquet(sel / "objects.parquet"),
                                p.dataroot_path, p.version, True)
        on_val = selftrain.score(est.estimate, hv)["epe"]
        assert hist["val_epe"].dropna().iloc[-1] == pytest.approx(on_val, rel=1e-4)
        assert ev["validation"]["fastflownet"]["epe"] == pytest.approx(on_val, rel=1e-4)
        assert set(ev["baselines"]) == {"zero flow", "farneback", "dis (medium)"}
    t = ch12.epe_table(p, ch12.built(p))
    assert list(t["method"]) == ["zero flow", "farneback", "dis (medium)",
                                 "fastflownet (photometric)", "fastflownet (supervised)",
                                 "fastflownet (finetune)"]
    head = ch12.headline(p, ch12.built(p))
    assert "against DIS's" in head and "the zero flow's" in head
    assert not (pipeline.node_dir(p, dag.Node("selfflow", None, "supervised")) / "gt").exists()


def test_selfflow_nodes_parameters_and_gate(smoke_built, tmp_path):
    demo = load_profile("demo")
    assert [str(n) for n in pipeline.nodes(demo, ["12"])] == [
        "shipped", "selfflow[photometric]", "selfflow[supervised]", "selfflow[finetune]"]
    assert not demo.selfflow_build, "the default book shows the shipped weights; make selfflow"
    assert pipeline.gate(dag.Node("selfflow", None, "photometric")) == "selfflow_build"
    assert load_profile("paper", dataroot="/x").selfflow_modes == ["photometric"]
    with pytest.raises(ProfileError, match="selfflow_crop.*multiples of 64"):
        load_profile("demo", selfflow_crop=[250, 448])
    fresh = load_profile("smoke", run_dir=str(tmp_path / "runs"))
    with pytest.raises(dag.MissingInput, match="selfflow_build=true.*make selfflow"):
        pipeline.published(fresh, dag.Node("selfflow", None, "photometric"))
    # more steps asked for, not built: the status names the make target; nothing is shown
    more = smoke_built.model_copy(update={"selfflow_iters": 5, "selfflow_build": False})
    pipeline.build(more, ["12"])  # without selfflow_build: trains nothing
    assert ch12.built(more) == []
    assert pipeline.format_status(more).splitlines()[-1].endswith(
        "chapter 12's 3 (flow networks) only with selfflow_build: make selfflow")
    assert "make selfflow" in ch12.headline(more, [])
    info = json.loads((pipeline.node_dir(smoke_built, dag.Node("selfflow", None, "photometric"))
                       / "manifest.json").read_text())
    assert info["params"]["selfflow_iters"] == 2 and info["params"]["flow_scale"] == 0.5


def test_seconds_per_pair_time_the_estimator_not_the_scoring(monkeypatch):
    n, flow = 3, np.zeros((8, 12, 2), np.float32)
    data = selftrain.HeldOut([np.zeros((8, 12, 3), np.uint8)] * n,
                             [np.zeros((8, 12, 3), np.uint8)] * n, [flow + 1.0] * n,
                             [np.ones((8, 12), bool)] * n, [np.zeros((0, 4))] * n)
    real = selftrain.flow_metrics

    def slow_metrics(*args):
        time.sleep(0.1)
        return real(*args)
    monkeypatch.setattr(selftrain, "flow_metrics", slow_metrics)
    out = selftrain.score(lambda a, b: flow, data)
    assert out["epe"] == pytest.approx(np.sqrt(2.0), rel=1e-5)
    assert out["seconds_per_pair"] < 0.05, "the scoring's time is not the estimator's"


def test_the_shipped_stage_scores_the_weights_once_on_held_out_pairs(smoke_built):
    """Chapter 12's numbers on this book's world come from the ``shipped`` node, not from
    the chapter: its table and per-pair errors are the network's and DIS's on the pairs
    drawn with the seed (equal to scoring them directly), and its example holds the first
    pair's flows at full size."""
    p = smoke_built
    table, errors = ch12.held_out_check(p)
    assert table["method"].tolist() == ["zero flow", "farneback", "dis (medium)", ch12.SHIPPED]
    assert table["EPE in boxes 95% CI over scenes"].str.endswith("scenes: too few)").all()
    sel = pipeline.published(p, dag.Node("select"))
    pairs = pd.read_parquet(sel / "pairs.parquet")
    pick = selftrain.sample_pairs(pairs[pairs["set"] == "keyframe"], p.selfflow_eval_pairs,
                                  (p.seed, 12))
    assert errors["pair_id"].tolist() == pick["pair_id"].tolist()
    data = selftrain.held_out(pick, pd.read_parquet(sel / "objects.parquet"), p.dataroot_path,
                              p.version, synthetic=True)
    net = FastFlowNetFlow(p.path(p.shipped_weights), device="cpu", scale=p.flow_scale)
    rows, _ = selftrain.pair_metrics(net.estimate, data)
    assert errors[ch12.SHIPPED].tolist() == pytest.approx([r["epe_boxes"] for r in rows])
    want = selftrain.mean_metrics(rows)
    row = table.set_index("method").loc[ch12.SHIPPED]
    assert (row["EPE (px)"], row["EPE in boxes (px)"]) == (round(want["epe"], 2),
                                                         round(want["epe_boxes"], 2))
    img, flows, valid = ch12.shipped_example(p)
    assert set(flows) == {"exact", "dis (medium)", ch12.SHIPPED}
    assert flows["exact"].shape == (*img.shape[:2], 2) == (*valid.shape, 2)
    assert np.abs(flows["exact"] - data.gt[0]).max() < 0.05 * np.abs(data.gt[0]).max() + 0.01


def test_the_papers_observation_is_answered_with_paired_numbers(smoke_built):
    """Chapter 12 compares the shipped network's chain with DIS's; the smoke profile has no
    fastflownet chain, so the exact flow's stands in for it."""
    from flowmod.chapters import ch07_evaluation as ch07
    from flowmod.chapters import common

    p = smoke_built
    errors = pd.DataFrame({"scene": ["a", "a", "b", "c"], ch12.SHIPPED: [3.0, 2.0, 4.0, np.nan],
                           "dis (medium)": [1.0, 0.0, 2.0, 1.0]})
    assert ch12.observation(p, errors) == {}, "no fastflownet chain in the smoke profile"
    obs = ch12.observation(p, errors, methods=("gt", "dis"))
    assert obs["epe_boxes_minus_dis"] == {"diff": 2.0, "ci": (2.0, 2.0), "verdict": "A better",
                                          "scenes": 2}, "scene c has no defined difference"
    want = ch07.comparisons(p).set_index("comparison").loc["gt - dis"]
    assert obs["test"]["ΔF1 (points)"] == want["ΔF1 (points)"]
    assert obs["test"]["95% CI, scenes and seeds (points)"] == want["95% CI, scenes and seeds (points)"]
    general = common.results(p, "dis", "general")[0]
    assert obs["general"]["objects"] == (general["distance"] <= p.general_max_distance).sum()
    words = ch12.observation_words(obs)
    assert "less accurate than DIS's (+2.00 px" in words and "on Table 4" in words
    assert "over 2 scenes +2.00 to +2.00" in words
    mixed = ch12.observation(p, errors.assign(**{"dis (medium)": [6.0, 0.0, 2.0, 1.0]}),
                             methods=("gt", "dis"))
    lo, hi = mixed["epe_boxes_minus_dis"]["ci"]
    assert lo < 0 < hi and mixed["epe_boxes_minus_dis"]["verdict"] == "undecided"
    # the verdict in words: the paper's observation repeats only where both differences are
    # decided and the classifiers' goes against the flows' accuracy
    row = {"ΔF1 (points)": 4.0, "95% CI, scenes and seeds (points)": "1.0 to 7.0",
           "verdict": "A better", "detectable (points)": 3.0}
    worse = {"diff": 2.0, "ci": (1.0, 3.0), "verdict": "A better", "scenes": 3}
    decided = {"epe_boxes_minus_dis": worse, "test": row, "general": row}
    assert "observation repeats" in ch12.observation_words(decided)
    better = {"diff": -1.0, "ci": (-2.0, -0.5), "verdict": "B better", "scenes": 3}
    assert "does not repeat" in ch12.observation_words({**decided, "epe_boxes_minus_dis": better})
    tie = {"diff": -0.01, "ci": (-0.3, 0.3), "verdict": "undecided", "scenes": 3}
    words = ch12.observation_words({**decided, "epe_boxes_minus_dis": tie})
    assert "not told apart from DIS's" in words and "neither repeated nor contradicted" in words
    assert "cannot tell" in ch12.observation_words(
        {**decided, "test": {**row, "verdict": "undecided"}})
    assert "unknown" in ch12.observation_words({**decided, "epe_boxes_minus_dis": None})
    assert "cannot answer" in ch12.observation_words({})


def test_group_mean_bootstrap_resamples_whole_scenes_and_skips_undefined_values():
    from flowmod.metrics import group_mean_bootstrap

    reps = group_mean_bootstrap([1.0, 1.0, 1.0, 5.0, np.nan], ["a", "a", "a", "b", "b"], n=400)
    # a replicate draws scenes, not pairs: with a twice, 1.0; b twice, 5.0; one each, 2.0
    assert set(np.round(reps, 6)) == {1.0, 2.0, 5.0}
    assert np.isnan(group_mean_bootstrap([np.nan], ["a"], n=3)).all()
    with pytest.raises(ValueError, match="groups has 1 values but values has 2"):
        group_mean_bootstrap([1.0, 2.0], ["a"])


def test_finetune_starts_from_its_weights_and_trains_on_the_test_scenes(smoke_built, tmp_path):
    """The finetune mode: the step-0 network is ``selfflow_init`` (its validation error is
    that file's), it trains photometrically on fold 0's test scenes (a user's own unlabelled
    frames), and only its node reads ``selfflow_init``."""
    from flowmod.extensions.selfflow import init_weights
    from flowmod.flow import pretrain
    from flowmod.paths import repo_root

    p = smoke_built
    hist, ev = ch12.results(p, "finetune")
    shipped = p.path(p.selfflow_init)
    assert shipped == repo_root() / pretrain.WEIGHTS_DIR / "weights.pt"
    sel = pipeline.published(p, dag.Node("select"))
    pairs = pd.read_parquet(sel / "pairs.parquet")
    val = selftrain.validation_pairs(pairs, p.selfflow_eval_pairs, p.seed, p.folds)
    hv = selftrain.held_out(val, pd.read_parquet(sel / "objects.parquet"), p.dataroot_path,
                            p.version, True)
    start = FastFlowNetFlow(shipped, device="cpu", scale=p.flow_scale)
    assert hist["val_epe"].iloc[0] == pytest.approx(selftrain.score(start.estimate, hv)["epe"],
                                                    rel=1e-4), "step 0 is the shipped network"
    scratch = ch12.results(p, "photometric")[0]
    assert hist["val_epe"].iloc[0] != pytest.approx(scratch["val_epe"].iloc[0], rel=1e-3)
    assert {"photometric", "smoothness"} <= set(hist.columns), "the photometric loss"
    # its pairs are the test scenes' (and the photometric network's the training scenes')
    test_scenes = set(selftrain.fold0_pairs(pairs, p.folds, "test")["scene"])
    assert ev["train_scenes"] and set(ev["train_scenes"]) <= test_scenes
    assert not set(ch12.results(p, "photometric")[1]["train_scenes"]) & test_scenes
    assert dag.reads(dag.Node("selfflow", None, "finetune")).count("selfflow_init") == 1
    assert "selfflow_init" not in dag.reads(dag.Node("selfflow", None, "photometric"))
    missing = p.model_copy(update={"selfflow_init": str(tmp_path / "none.pt"),
                                   "run_dir": str(tmp_path / "runs")})
    with pytest.raises(selftrain.SelfFlowError, match="selfflow_init=.*none.pt.*make flownet"):
        init_weights(dag.StageParams(missing, dag.Node("selfflow", None, "finetune")))


def test_world_words_compare_the_errors_at_the_precision_they_show():
    row = {"Fl-all (%)": 30.0, "Fl-all in boxes (%)": 9.0, "s / pair": 0.1}
    table = pd.DataFrame([{"method": ch12.SHIPPED, "EPE (px)": 10.3, "EPE in boxes (px)": 1.504,
                           **row},
                          {"method": "dis (medium)", "EPE (px)": 13.2,
                           "EPE in boxes (px)": 1.51, **row}])
    words = ch12.world_words(table, 16)
    assert "10.3 px over the frame, lower than DIS's 13.2 px" in words
    assert "1.5 px inside the far vehicles' boxes, equal to DIS's 1.5 px" in words


def test_the_landing_sentence_gives_the_held_out_difference_with_its_interval():
    """The landing page quoted the shipped weights' box error beside DIS's without an
    interval (issue 39): the paired difference and its interval over scenes come with it,
    flagged when too few scenes are resampled."""
    errors = pd.DataFrame({"scene": [f"s{i // 2}" for i in range(24)],
                           ch12.SHIPPED: [1.0 + 0.1 * (i % 3) for i in range(24)],
                           "dis (medium)": [1.5] * 24})
    d = ch12.box_difference(errors, seed=0)
    assert d["scenes"] == 12 and d["diff"] == pytest.approx(-0.4)
    assert d["ci"][1] < 0 and d["verdict"] == "B better"
    table = pd.DataFrame({"method": [ch12.SHIPPED, "dis (medium)"],
                          "EPE in boxes (px)": [1.1, 1.5]})
    m = {"steps": 10, "train_seconds": 3600.0}
    text = ch12.shipped_headline(m, table, {}, d)
    assert f"(paired per pair {d['diff']:+.2f} px, 95 % interval over scenes " \
           f"{d['ci'][0]:+.2f} to {d['ci'][1]:+.2f}, decided)" in text
    few = ch12.box_difference(errors.iloc[:4], seed=0)
    assert "(2 scenes: too few)" in ch12.shipped_headline(m, table, {}, few)
    assert ch12.box_difference(None) is None
