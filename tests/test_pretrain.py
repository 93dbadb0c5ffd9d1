"""FastFlowNet's pretraining recipe (flowmod.flow.pretrain): the multi-scale loss, the
schedule, the batches. Hand-made tensors; seconds."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import pandas as pd
import pytest
import torch
import torch.nn.functional as F

from flowmod.artefacts import file_digest
from flowmod.environment import simd_path
from flowmod.flow import pretrain as pt
from flowmod.flow.architectures import FastFlowNet, fastflownet_inputs
from flowmod.flow.selftrain import HeldOut
from flowmod.params import load_profile
from flowmod.paths import repo_root


def test_level_target_averages_valid_pixels_and_needs_half_of_a_cell():
    gt = torch.zeros(1, 2, 8, 8)
    gt[:, 0, :4, :4] = 4.0  # u = 4 px in the top-left 4 x 4 cell
    valid = torch.ones(1, 1, 8, 8)
    valid[:, :, :4, :4] = 0
    valid[:, :, 0, 0] = 1  # 1 of 16 valid: that cell is invalid at level 2
    flow, ok = pt.level_target(gt, valid, 2)
    assert flow.shape == (1, 2, 2, 2) and ok.tolist() == [[[[0.0, 1.0], [1.0, 1.0]]]]
    assert flow[0, 0, 0, 0] == pytest.approx(4.0), "the mean over the valid pixels"
    assert flow[0, 0, 1, 1] == 0.0


def test_pyramid_loss_is_zero_for_the_exact_flow_and_weights_the_levels():
    h, w = 64, 64
    gt = torch.zeros(1, 2, h, w)
    gt[:, 0] = 3.0
    gt[:, 1] = -4.0  # EPE of a zero prediction: 5 px everywhere
    valid = torch.ones(1, 1, h, w)
    exact = [torch.stack([torch.full((1, h >> k, w >> k), 3.0 / 20),
                          torch.full((1, h >> k, w >> k), -4.0 / 20)], 1) for k in pt.LEVELS]
    loss, parts = pt.pyramid_loss(exact, gt, valid, (1, 1, 1, 1, 1))
    assert float(loss) == pytest.approx(0.0, abs=0.01) and parts["epe2"] < 0.01
    zero = [torch.zeros_like(f) for f in exact]
    loss, parts = pt.pyramid_loss(zero, gt, valid, (1.0, 0.5, 0.25, 0.25, 0.25))
    assert parts["epe2"] == pytest.approx(5.0, abs=1e-4)
    assert float(loss) == pytest.approx(5.0 * 2.25, abs=1e-3)


def test_rate_halves_at_each_milestone():
    r = pt.Recipe(lr=4e-4, milestones=(10, 20), gamma=0.5)
    assert [pt.learning_rate(r, s) for s in (0, 9, 10, 19, 20, 99)] == pytest.approx(
        [4e-4, 4e-4, 2e-4, 2e-4, 1e-4, 1e-4])


@dataclass
class Pairs:
    """Two hand-made pairs of 128 x 192 frames with a known flow (u = column index) and one
    far box each (x 150-170, y 100-120 px)."""

    scale: float = 0.5
    focus_depth: tuple[float, float] = (20.0, 80.0)

    pairs: pd.DataFrame = field(default_factory=lambda: pd.DataFrame(
        {"sd_token_1": ["a", "b"], "sd_token_2": ["c", "d"], "gap": [1, 6]}))

    def load(self, i: int):
        h, w = 128, 192
        img = np.zeros((h, w, 3), np.uint8)
        img[..., 0] = np.arange(w, dtype=np.uint8)[None, :]
        flow = np.zeros((h, w, 2), np.float32)
        flow[..., 0] = np.arange(w)[None, :] + 1000 * "ab".index(self.pairs.sd_token_1.iloc[i])
        flow[..., 1] = 7.0
        return {"img1": img, "img2": img.copy(), "flow": flow, "valid": np.ones((h, w), bool),
                "boxes": np.array([[150.0, 100.0, 170.0, 120.0]], np.float32)}


def test_batches_are_drawn_from_seed_and_step_and_flips_negate_u():
    r = pt.Recipe(batch=8, crop=(64, 128), flip_p=0.5, seed=3)
    a, b = pt.draw_batch(Pairs(), r, 5), pt.draw_batch(Pairs(), r, 5)
    assert all(torch.equal(a[k], b[k]) for k in a), "a function of (seed, step)"
    assert not torch.equal(a["img1"], pt.draw_batch(Pairs(), r, 6)["img1"])
    assert a["img1"].shape == (8, 3, 64, 128) and a["gt"].shape == (8, 2, 64, 128)
    for k in range(8):
        u, img = a["gt"][k, 0], a["img1"][k, 0]
        flipped = bool(u[0, 0] > u[0, -1] or u[0, 0] < 0)
        if flipped:  # mirrored: the image's columns run backwards and u changes sign
            assert img[0, 0] > img[0, -1] and (u <= 0).all()
        else:
            assert img[0, 0] < img[0, -1] and (u >= 0).all()
        assert (a["gt"][k, 1] == 7.0).all(), "v is kept"
    flips = [bool(a["img1"][k, 0, 0, 0] > a["img1"][k, 0, 0, -1]) for k in range(8)]
    assert any(flips) and not all(flips)
    none = pt.draw_batch(Pairs(), replace(r, flip_p=0.0), 5)
    assert all(none["img1"][k, 0, 0, 0] < none["img1"][k, 0, 0, -1] for k in range(8))


def test_focused_windows_hold_a_far_box_whose_pixels_weigh_more():
    r = pt.Recipe(batch=16, crop=(64, 128), seed=2, focus_p=1.0, box_weight=9.0)
    b = pt.draw_batch(Pairs(), r, 0)
    heavy = (b["weight"] == 10.0).sum(dim=(1, 2, 3))
    assert (heavy == 400).all(), "every window holds the whole 20 x 20 box, weighted 1 + 9"
    assert set(b["weight"].unique().tolist()) == {1.0, 10.0}
    plain = pt.draw_batch(Pairs(), replace(r, focus_p=0.0), 0)
    assert (plain["weight"] == 10.0).sum(dim=(1, 2, 3)).lt(400).any(), "random windows miss it"
    same = pt.draw_batch(Pairs(), replace(r, focus_p=0.0, box_weight=0.0), 0)
    assert torch.equal(same["img1"], plain["img1"]), "the weight does not move the windows"
    assert (same["weight"] == 1.0).all()


def test_window_origin_holds_the_box_or_centres_on_a_larger_one():
    rng = np.random.default_rng(0)
    box = np.array([150.0, 100.0, 170.0, 120.0])
    for _ in range(50):
        y, x = pt.window_origin(rng, (128, 192), (64, 128), box)
        assert y <= 100 and y + 64 >= 120 and x <= 150 and x + 128 >= 170
        assert 0 <= y <= 64 and 0 <= x <= 64
    big = np.array([10.0, 0.0, 190.0, 128.0])  # wider and taller than the window
    assert pt.window_origin(rng, (128, 192), (64, 128), big) == (32, 36)
    seen = {pt.window_origin(rng, (128, 192), (64, 128), None) for _ in range(200)}
    assert min(y for y, _ in seen) < 8 and max(x for _, x in seen) > 56, "uniform without a box"


def test_box_weights_follow_the_window_and_the_loss_weighs_cells_by_them():
    wt = pt.box_weight_map(np.array([[10.0, 20.0, 14.0, 22.0]]), (8, 8), (18, 8), 4.0)
    assert wt.sum() == 64 + 4 * 2 * 4 and (wt[2:4, 2:6] == 5.0).all() and wt[0, 0] == 1.0
    h = w = 64
    gt = torch.zeros(1, 2, h, w)
    gt[:, 0, :32] = 20.0  # the top half moves 20 px, the bottom half stays
    zero = [torch.zeros(1, 2, h >> k, w >> k) for k in pt.LEVELS]
    valid = torch.ones(1, 1, h, w)
    plain, parts = pt.pyramid_loss(zero, gt, valid, (1, 0, 0, 0, 0))
    same, _ = pt.pyramid_loss(zero, gt, valid, (1, 0, 0, 0, 0), torch.full((1, 1, h, w), 3.0))
    top = torch.ones(1, 1, h, w)
    top[:, :, :32] = 3.0
    heavy, parts_w = pt.pyramid_loss(zero, gt, valid, (1, 0, 0, 0, 0), top)
    assert float(plain) == pytest.approx(10.0, abs=1e-3) and float(same) == pytest.approx(10.0, abs=1e-3)
    assert float(heavy) == pytest.approx(15.0, abs=1e-3), "3 x 20 px + 1 x 0 px over 4"
    assert parts_w["epe2"] == pytest.approx(parts["epe2"]), "the reported EPE is unweighted"


def test_box_ids_follow_the_window_and_the_flip():
    ids = pt.box_id_map(np.array([[10.0, 20.0, 14.0, 22.0], [12.0, 21.0, 13.0, 26.0]]),
                        (8, 8), (18, 8))
    assert (ids[2:4, 2:4] == 1).all() and (ids[3:8, 4:5] == 2).all(), "later boxes on top"
    assert (ids[2, 4:6] == 1).all() and ids[2, 6] == 0 and (ids > 0).sum() == 8 + 5 - 1
    b = pt.draw_batch(Pairs(), pt.Recipe(batch=16, crop=(64, 128), seed=2, focus_p=1.0,
                                         box_weight=9.0, flip_p=0.5), 0)
    assert b["box_id"].dtype == torch.int64
    assert torch.equal(b["box_id"] == 1, b["weight"] == 10.0), "flipped with the weights"
    assert ((b["box_id"] == 1).sum(dim=(1, 2, 3)) == 400).all()


def test_box_mean_loss_is_the_length_of_each_box_s_mean_error():
    """Scatter inside a box cancels; the mean is over valid pixels; every box of every
    image counts once; without a box the loss is 0."""
    gt, flow = torch.zeros(2, 2, 4, 4), torch.zeros(2, 2, 4, 4)
    ids, valid = torch.zeros(2, 1, 4, 4, dtype=torch.int64), torch.ones(2, 1, 4, 4)
    ids[0, 0, :2, :2] = 1  # image 0, box 1: scatter only (+3, -3, +3, -3 in u)
    flow[0, 0, :2, :2] = torch.tensor([[3.0, -3.0], [3.0, -3.0]])
    ids[0, 0, 2:, 2:] = 2  # image 0, box 2: shifted (0, 4), one pixel invalid and wrong
    flow[0, 1, 2:, 2:] = 4.0
    flow[0, 0, 3, 3], valid[0, 0, 3, 3] = 100.0, 0.0
    ids[1, 0, 1:3, 1:3] = 1  # image 1, box 1: shifted (3, 0) over 4 px, (6, 0) on one
    flow[1, 0, 1:3, 1:3] = torch.tensor([[3.0, 3.0], [3.0, 15.0]])
    loss = pt.box_mean_loss(flow, gt, valid, ids)
    assert float(loss) == pytest.approx((0.0 + 4.0 + 6.0) / 3, abs=1e-3)
    flow[0, 0, 0, 0] = 7.0  # off the truth outside any box (id 0): not counted
    ids[0, 0, 0, 0] = 0
    assert float(pt.box_mean_loss(flow, gt, valid, ids)) == pytest.approx(
        (1.0 + 4.0 + 6.0) / 3, abs=1e-3)
    assert float(pt.box_mean_loss(flow, gt, valid, torch.zeros_like(ids))) == 0.0
    one = torch.zeros(1, 2, 8, 8, requires_grad=True)
    mask = torch.zeros(1, 1, 8, 8, dtype=torch.int64)
    mask[..., 2:4, 2:4] = 1
    pt.box_mean_loss(one, torch.ones(1, 2, 8, 8), torch.ones(1, 1, 8, 8), mask).backward()
    assert (one.grad[..., 2:4, 2:4] < 0).all() and (one.grad[..., :2, :] == 0).all()


def test_the_recipe_s_box_mean_weight_reaches_the_step_s_loss():
    m, batch = FastFlowNet(), pt.draw_batch(Pairs(), pt.Recipe(batch=1, crop=(64, 128),
                                                                focus_p=1.0), 0)
    opt = torch.optim.SGD(m.parameters(), lr=0.0)
    plain = pt.train_step(m, opt, batch, pt.Recipe(), 0)
    heavy = pt.train_step(m, opt, batch, pt.Recipe(box_mean_weight=2.0), 0)
    assert "box_mean" not in plain and heavy["box_mean"] > 1.0
    assert heavy["loss"] == pytest.approx(plain["loss"] + 2.0 * heavy["box_mean"], rel=1e-5)


def test_full_res_loss_scores_the_upsampled_flow_at_every_pixel():
    torch.manual_seed(0)
    coarse = torch.randn(1, 2, 16, 16)  # a level-2 output, px / 20
    gt = 20 * F.interpolate(coarse, size=(64, 64), mode="bilinear", align_corners=False)
    valid = torch.ones(1, 1, 64, 64)
    levels = [coarse, *[torch.zeros(1, 2, 64 >> k, 64 >> k) for k in pt.LEVELS[1:]]]
    exact, parts = pt.pyramid_loss(levels, gt, valid, (1, 0, 0, 0, 0), full_res=True)
    cells, _ = pt.pyramid_loss(levels, gt, valid, (1, 0, 0, 0, 0))
    assert float(exact) < 0.01 and parts["epe2"] < 0.01, "what inference upsamples is exact"
    assert float(cells) > 1.0, "cell means of the upsampled field are not its cells"
    gt = torch.zeros(1, 2, 64, 64)
    gt[:, 0, 5, 5] = 10.0  # one pixel moves, inside a 4 x 4 cell
    weight = torch.ones(1, 1, 64, 64)
    weight[:, :, 5, 5] = 3.0
    zero = [torch.zeros(1, 2, 64 >> k, 64 >> k) for k in pt.LEVELS]
    one, _ = pt.pyramid_loss(zero, gt, valid, (1, 0, 0, 0, 0), weight, full_res=True)
    assert float(one) == pytest.approx(30.0 / (4095 + 3), abs=2e-3), "weighted per pixel"
    m, batch = FastFlowNet(), pt.draw_batch(Pairs(), pt.Recipe(batch=1, crop=(64, 128)), 0)
    opt = torch.optim.SGD(m.parameters(), lr=0.0)
    a = pt.train_step(m, opt, batch, pt.Recipe(), 0)["epe2"]
    b = pt.train_step(m, opt, batch, pt.Recipe(full_res=True), 0)["epe2"]
    assert a != b, "the recipe's full_res reaches the loss (a linear flow: barely)"


def test_a_phase_with_ema_passes_on_the_average_of_its_weights(tmp_path):
    r = pt.Recipe(batch=2, crop=(64, 128), lr=1e-3)
    w = [pt.train(r, Pairs(), tmp_path / f"raw{n}", n, None, False)[0].state_dict()
         for n in (1, 2)]
    avg, _ = pt.train(replace(r, ema=0.5), Pairs(), tmp_path / "avg", 2, None, False)
    assert all(torch.allclose(avg.state_dict()[k], (w[0][k] + w[1][k]) / 2, atol=1e-6)
               for k in w[0]), "first step copied, second averaged with decay 0.5"
    assert not all(torch.equal(avg.state_dict()[k], w[1][k]) for k in w[0])
    state = torch.load(tmp_path / "avg" / "last.pt", weights_only=True)
    assert all(torch.equal(pt.phase_result(state)[k], avg.state_dict()[k]) for k in w[0])
    assert all(torch.equal(state["model"][k], w[1][k]) for k in w[0]), "training as without"
    pt.train(replace(r, ema=0.5), Pairs(), tmp_path / "resumed", 1, None, False)
    again, _ = pt.train(replace(r, ema=0.5), Pairs(), tmp_path / "resumed", 2, None, False)
    assert all(torch.equal(again.state_dict()[k], avg.state_dict()[k]) for k in w[0])


def test_a_phase_may_start_from_its_predecessor_rounded_to_float16(tmp_path):
    one = pt.Recipe(batch=2, crop=(64, 128), steps=1, lr=1e-3)
    two = replace(one, seed=7, lr=0.0)  # a step at rate 0 keeps the weights it starts from
    first = pt.run_schedule((one,), Pairs(), tmp_path / "a", 1, None, progress=False)
    plain = pt.run_schedule((one, two), Pairs(), tmp_path / "b", 2, None, progress=False)
    half = pt.run_schedule((one, replace(two, init_float16=True)), Pairs(), tmp_path / "c",
                           2, None, progress=False)
    ref = first.state_dict()
    assert all(torch.equal(plain.state_dict()[k], ref[k]) for k in ref)
    assert all(torch.equal(half.state_dict()[k], ref[k].half().float()) for k in ref)
    assert not all(torch.equal(half.state_dict()[k], ref[k]) for k in ref)


def test_later_phases_continue_from_published_weights_as_from_scratch(tmp_path):
    one = pt.Recipe(batch=2, crop=(64, 128), steps=2, lr=1e-3, eval_every=1, scale=1.0)
    two = replace(one, seed=7, steps=1, lr=5e-4, init_float16=True, scale=0.5)
    d = Pairs().load(1)
    held = HeldOut([d["img1"]], [d["img2"]], [d["flow"]], [d["valid"]], [d["boxes"]], ["s"])
    out = tmp_path / "weights"
    pt.run_schedule((one,), Pairs(), tmp_path / "a", 2, held, progress=False)
    first = pt.publish((one,), tmp_path / "a", out, "f" * 64, held)
    prior = pt.shipped_phases((one, two), out)
    assert prior[0] == 1 and prior[1]["sha256"] == first["sha256"]
    init = pt.load_half(out / "weights.pt").state_dict()
    cont = pt.run_schedule((one, two), Pairs(), tmp_path / "b", 3, held, progress=False,
                           start=(1, init))
    assert not (tmp_path / "b" / "phase1").exists(), "the published phase is not retrained"
    whole = pt.run_schedule((one, two), Pairs(), tmp_path / "c", 3, held, progress=False)
    assert all(torch.equal(cont.state_dict()[k], whole.state_dict()[k])
               for k in whole.state_dict()), "bit-identical to the schedule from scratch"
    m = pt.publish((one, two), tmp_path / "b", out, "f" * 64, held, prior=prior)
    assert m["steps"] == 3 and [c["step"] for c in m["validation"]["curve"]] == [0, 1, 2, 3]
    assert first["scale"] == 1.0 and m["scale"] == 0.5, "the last phase's scale"
    assert [c.get("val_scale") for c in m["validation"]["curve"]] == [None, 1.0, 1.0, 0.5]
    at_half = pt.score_model(pt.load_half(out / "weights.pt"), held, 0.5)
    assert m["validation"]["final_float16"]["epe"] == pytest.approx(at_half["epe"])
    assert m["continued_from"]["phases"] == 1 and m["continued_from"]["sha256"] == first["sha256"]
    assert m["first_losses"] == first["first_losses"] and len(m["training_curve"]) == 2
    assert m["train_seconds"] > first["train_seconds"]
    with pytest.raises(pt.PretrainError, match="not made by the first phases"):
        pt.shipped_phases((replace(one, lr=1e-2), two), out)
    (out / "weights.pt").write_bytes(b"edited")
    with pytest.raises(pt.PretrainError, match="sha256 differs"):
        pt.shipped_phases((one, two), out)


def test_a_later_phase_starts_from_the_weights_the_previous_one_ended_with(tmp_path):
    one = pt.Recipe(batch=2, crop=(64, 128), steps=2, lr=1e-3)
    two = replace(one, seed=7, steps=2, lr=5e-4, focus_p=1.0, box_weight=4.0, min_gap=6)
    first = pt.run_schedule((one, two), Pairs(), tmp_path / "a", 2, None, progress=False)
    both = pt.run_schedule((one, two), Pairs(), tmp_path / "b", 3, None, progress=False)
    by_hand, _ = pt.train(two, pt.phase_data(Pairs(), two), tmp_path / "c", 1, None, False,
                          first.state_dict())
    assert all(torch.equal(both.state_dict()[k], by_hand.state_dict()[k])
               for k in both.state_dict())
    assert torch.load(tmp_path / "b" / "phase2" / "last.pt", weights_only=True)["step"] == 1
    state, rows = pt.phase_histories((one, two), tmp_path / "b")
    assert [r["step"] for r in rows] == [1, 2, 3], "steps count from the schedule's start"
    assert pt.phase_data(Pairs(), replace(two, scale=1.0)).scale == 1.0, "its own scale"
    with pytest.raises(pt.PretrainError, match="at least one step"):
        pt.run_schedule((one, two), Pairs(), tmp_path / "d", 0, None, progress=False)


def test_the_pair_cache_keeps_each_scale_apart(smoke_world, tmp_path):
    """A phase at another scale reads the frames again at its scale (images, exact flow in px
    of that scale, boxes), never the files decoded at another."""
    root, version = smoke_world
    frames = pt.scene_frames(root, version)
    pairs = pt.training_pairs(frames, dict.fromkeys(frames, "train"), 1, 1000).head(1)
    half = pt.PairCache(pairs, root, version, 0.5, tmp_path)
    a = half.load(0)
    quarter = pt.phase_data(half, pt.Recipe(scale=0.25))
    b = quarter.load(0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scale-0.25", "scale-0.5"]
    assert b["img1"].shape[:2] == tuple(round(s / 2) for s in a["img1"].shape[:2])
    assert b["boxes"] * 2 == pytest.approx(a["boxes"])
    ok = b["valid"] & a["valid"][::2, ::2]
    ratio = np.abs(b["flow"][ok]).mean() / np.abs(a["flow"][::2, ::2][ok]).mean()
    assert ratio == pytest.approx(0.5, abs=0.05), "px of the frames at that scale"
    again = quarter.load(0)
    assert all(np.array_equal(again[k], b[k]) for k in b), "read back from its cache"


def test_a_phase_with_min_gap_trains_only_on_pairs_that_far_apart():
    data = pt.phase_data(Pairs(), pt.Recipe(min_gap=6, focus_depth=(30.0, 70.0)))
    assert data.pairs["sd_token_1"].tolist() == ["b"] and data.focus_depth == (30.0, 70.0)
    assert len(pt.phase_data(Pairs(), pt.Recipe()).pairs) == 2, "min_gap 1: every pair"
    b = pt.draw_batch(data, pt.Recipe(batch=6, crop=(64, 128), flip_p=0.0), 0)
    assert (b["gt"][:, 0] >= 1000).all(), "every window comes from the pair 6 frames apart"
    with pytest.raises(pt.PretrainError, match="min_gap 7 leaves no training pair"):
        pt.phase_data(Pairs(), pt.Recipe(min_gap=7))


def test_a_step_lowers_the_loss_on_its_batch_and_levels_match_forward():
    torch.manual_seed(0)
    model = FastFlowNet()
    r = pt.Recipe(batch=2, crop=(64, 128), lr=1e-3)
    batch = pt.draw_batch(Pairs(), r, 0)
    x1, x2 = fastflownet_inputs(batch["img1"], batch["img2"])
    with torch.no_grad():
        levels = model.levels(x1, x2)
        assert torch.equal(levels[0], model(x1, x2)), "forward is the finest level"
        assert [lv.shape[-1] for lv in levels] == [32, 16, 8, 4, 2]
    opt = torch.optim.Adam(model.parameters(), lr=r.lr)
    first = pt.train_step(model, opt, batch, r, 0)["loss"]
    for step in range(1, 6):
        last = pt.train_step(model, opt, batch, r, step)["loss"]
    assert last < first


@pytest.mark.slow
def test_prepare_reads_the_world_where_it_was_generated(tmp_path):
    """``make flownet`` once failed before its first step: the world is generated in
    ``<dataroot>/worlds/<id>/`` and was then looked for at the dataroot itself."""
    recipe = replace(pt.Recipe(), world_scenes=2, world_keyframes=3, world_vehicles=4,
                     val_every=2, eval_pairs=1, start_stride=8)
    fp, root = pt.ensure_world(recipe, tmp_path / "pretrain", progress=False)
    assert root.parent == tmp_path / "pretrain" / "worlds"
    assert (root / "v1.0-synth" / "scene.json").is_file() and len(fp) == 64
    world_fp, data, heldout = pt.prepare(recipe, tmp_path / "pretrain", tmp_path / "work",
                                         progress=False)
    assert world_fp == fp and len(data.pairs) > 0 and len(heldout.img1) == 1


def test_loss_curve_averages_blocks_of_steps():
    rows = [{"step": s, "loss": float(s), "epe2": 2.0 * s} for s in range(1, 251)]
    got = pt.loss_curve(rows, every=100)
    assert [r["step"] for r in got] == [100, 200, 250]
    assert got[0]["loss"] == pytest.approx(50.5) and got[2]["epe2"] == pytest.approx(451.0)


def test_training_starts_from_the_seeded_initial_network():
    r = pt.Recipe(seed=5)
    a, b = pt.initial_model(r), pt.initial_model(r)
    other = pt.initial_model(replace(r, seed=6))
    assert all(torch.equal(a.state_dict()[k], b.state_dict()[k]) for k in a.state_dict())
    assert not all(torch.equal(a.state_dict()[k], other.state_dict()[k])
                   for k in a.state_dict())


# --- the shipped weights (weights/fastflownet_synth) -----------------------------------------------

SHIPPED = repo_root() / pt.WEIGHTS_DIR


@pytest.fixture(scope="module")
def manifest() -> dict:
    f = SHIPPED / "manifest.json"
    assert f.is_file(), f"{f} is missing: `make flownet` makes it (the weights ship with the code)"
    return json.loads(f.read_text())


def test_shipped_weights_are_the_recorded_float16_file_of_the_current_schedule(manifest):
    w = SHIPPED / "weights.pt"
    assert file_digest(w) == manifest["sha256"], "weights.pt is not the file the manifest hashed"
    assert w.stat().st_size <= 10 * 2**20
    state = torch.load(w, map_location="cpu", weights_only=True)
    assert {v.dtype for v in state.values()} == {torch.float16}
    assert set(state) == set(FastFlowNet().state_dict())
    # a recipe field added since (its default: what the phases did) is read at its default
    made = [{**asdict(pt.Recipe()), **r} for r in manifest["schedule"]]
    assert json.loads(json.dumps(made)) == json.loads(json.dumps(
        [asdict(p) for p in pt.SCHEDULE])), (
        "the schedule changed since the weights were made: `make flownet` remakes them")
    assert set(manifest["schedule"][0]) <= set(asdict(pt.Recipe())), "no field was dropped"
    assert manifest["steps"] == sum(p.steps for p in pt.SCHEDULE), "they end the schedule"
    assert manifest["world"]["fingerprint"] and len(manifest["world"]["fingerprint"]) == 64
    val = manifest["validation"]
    assert [c["step"] for c in val["curve"]][:2] == [0, pt.SCHEDULE[0].eval_every]
    assert val["curve"][-1]["step"] == manifest["steps"]


@pytest.mark.slow
def test_shipped_weights_reproduce_their_check_on_the_smoke_world(manifest, smoke_world,
                                                                  tmp_path):
    """The recipe's first steps from scratch give the recorded losses, and the shipped
    weights the recorded errors on the smoke world's pairs."""
    data = smoke_world[0].parents[1]
    smoke = load_profile("smoke", dataroot=str(data), n_jobs=1, run_dir=str(tmp_path / "runs"))
    threads = torch.get_num_threads()
    got = pt.smoke_check(pt.SCHEDULE[0], SHIPPED / "weights.pt", smoke, tmp_path / "check",
                         manifest["scale"])
    assert torch.get_num_threads() == threads, "the check leaves the thread count as it was"
    path = simd_path()
    if path not in manifest["check"]:
        pytest.skip(f"no smoke-world check recorded for numpy's SIMD path {path} "
                    "(`python -m flowmod.flow.pretrain --check-only` on such a machine adds it)")
    want = manifest["check"][path]
    # the check ran on this very smoke world (its content; the world's generator code is
    # in the world's name, so a generator edit that draws the same world passes)
    assert got["world"] == want["world"] and got["steps"] == want["steps"]
    assert want["scale"] == pt.SCHEDULE[-1].scale, "scored at the scale the weights run at"
    assert got["first_losses"] == pytest.approx(want["first_losses"], rel=1e-6, abs=0)
    for k in ("epe", "epe_boxes", "fl_all"):
        assert got["weights"][k] == pytest.approx(want["weights"][k], rel=1e-4), k


def test_the_check_is_recorded_for_both_simd_paths_and_each_is_kept(manifest, monkeypatch):
    """The smoke world's bytes differ between numpy's AVX-512 and AVX2 paths (this project's
    machines have either), so the shipped manifest holds a check for each, and recording one
    path's keeps the other's."""
    assert set(manifest["check"]) == {"avx512", "avx2"}
    a, b = manifest["check"]["avx512"], manifest["check"]["avx2"]
    assert a["world"] != b["world"] and a["steps"] == b["steps"] == pt.CHECK_STEPS
    assert b["weights"]["epe_boxes"] == pytest.approx(a["weights"]["epe_boxes"], rel=0.05)
    m = pt.with_check({"sha256": "x", "check": {"avx512": a}}, {"new": 1}, "avx2")
    assert m == {"sha256": "x", "check": {"avx512": a, "avx2": {"new": 1}}}
    assert pt.with_check(m, {"newer": 2}, "avx512")["check"] == {"avx512": {"newer": 2},
                                                                  "avx2": {"new": 1}}
    assert pt.pinned_simd_path() == simd_path()
    monkeypatch.setattr(pt, "simd_path", lambda: None)
    with pytest.raises(pt.PretrainError, match="neither AVX-512 nor AVX2 on this CPU"):
        pt.pinned_simd_path()


def test_chapter_12_describes_every_phase_of_the_schedule(manifest):
    from flowmod.chapters import ch12_self_trained_flow as ch12

    t = ch12.recipe_table(manifest).set_index("")["shipped weights"]
    assert t["schedule"].endswith("; 4000 steps") and "3500" in t["schedule"]
    assert t["phase 2"].startswith("5000 more steps from the previous phase's weights")
    assert "share 0.75" in t["phase 2"] and "20-80 m" in t["phase 2"] and "21x" in t["phase 2"]
    assert len([k for k in t.index if k.startswith("phase")]) == len(pt.SCHEDULE) - 1
    assert "only the pairs" not in t["phase 2"] and "41x" not in t["phase 2"]
    assert t["phase 4"].endswith("only the pairs 4 to 6 frames apart (keyframes: 6)")
    assert t["phase 5"].endswith("only the pairs 6 frames apart (keyframes: 6)")
    assert t["phase 6"].startswith("4000 more steps from the previous phase's weights as "
                                   "published (float16)")
    assert "flow upsampled to every pixel" in t["phase 6"] and "(decay 0.999)" in t["phase 6"]
    assert "upsampled" not in t["phase 5"] and "average" not in t["phase 5"]
    assert t["phase 8"].endswith("frames read at scale 0.75 (before: 0.5)")
    starts = np.cumsum([0] + [p.steps for p in pt.SCHEDULE])
    assert ch12.scale_changes(manifest) == [
        (int(starts[k]), p.scale) for k, p in enumerate(pt.SCHEDULE)
        if k and p.scale != pt.SCHEDULE[k - 1].scale] == [(29000, 0.75)]
    from flowmod.report import viz

    fig = viz.pretrain_curves(*ch12.curves(manifest), manifest["validation"]["baselines"],
                              ch12.scale_changes(manifest))
    for ax in fig.axes:  # each panel marks where the frames grew
        assert [list(ln.get_xdata()) for ln in ax.lines if ln.get_linestyle() == ":"
                and ln.get_color() == "0.5"] == [[29000, 29000]]
        assert "frames at 0.75" in [t.get_text() for t in ax.texts]
    v = ch12.validation_table(manifest).set_index("method")["frame scale"]
    assert v["dis (medium)"] == v.iloc[-1] == manifest["scale"] == pt.SCHEDULE[-1].scale
    assert v["fastflownet, step 0 (untrained)"] == pt.SCHEDULE[0].scale
    at = {s: load_profile("demo", flow_scale=s) for s in (manifest["scale"], 0.5)}
    assert "not validated" not in ch12.shipped_note(at[manifest["scale"]], manifest)
    assert "at scale 0.75; this profile computes flow at 0.5" in ch12.shipped_note(at[0.5],
                                                                                 manifest)
    assert "scale" not in t["phase 7"], "a phase at its predecessor's scale says nothing"
    assert t["phase 7"].startswith("4000 more steps from the previous phase's weights as "
                                   "published (float16) (a fresh Adam 5e-05,")
