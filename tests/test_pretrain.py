"""FastFlowNet's pretraining recipe (flowmod.flow.pretrain): the multi-scale loss, the
schedule, the batches. Hand-made tensors; seconds."""

from __future__ import annotations

import json
from dataclasses import asdict, replace

import numpy as np
import pandas as pd
import pytest
import torch

from flowmod.artefacts import file_digest
from flowmod.flow import pretrain as pt
from flowmod.flow.architectures import FastFlowNet, fastflownet_inputs
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


class Pairs:
    """Two hand-made pairs of 128 x 192 frames with a known flow (u = column index)."""

    pairs = pd.DataFrame({"sd_token_1": ["a", "b"], "sd_token_2": ["c", "d"]})

    def load(self, i: int):
        h, w = 128, 192
        img = np.zeros((h, w, 3), np.uint8)
        img[..., 0] = np.arange(w, dtype=np.uint8)[None, :]
        flow = np.zeros((h, w, 2), np.float32)
        flow[..., 0] = np.arange(w)[None, :] + 1000 * i
        flow[..., 1] = 7.0
        return img, img.copy(), flow, np.ones((h, w), bool)


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


def test_shipped_weights_are_the_recorded_float16_file_of_the_current_recipe(manifest):
    w = SHIPPED / "weights.pt"
    assert file_digest(w) == manifest["sha256"], "weights.pt is not the file the manifest hashed"
    assert w.stat().st_size <= 10 * 2**20
    state = torch.load(w, map_location="cpu", weights_only=True)
    assert {v.dtype for v in state.values()} == {torch.float16}
    assert set(state) == set(FastFlowNet().state_dict())
    assert manifest["recipe"] == json.loads(json.dumps(asdict(pt.Recipe()))), (
        "the recipe changed since the weights were made: `make flownet` remakes them")
    assert manifest["steps"] == pt.Recipe().steps, "the shipped weights end the schedule"
    assert manifest["world"]["fingerprint"] and len(manifest["world"]["fingerprint"]) == 64
    val = manifest["validation"]
    assert [c["step"] for c in val["curve"]][:2] == [0, pt.Recipe().eval_every]
    assert val["curve"][-1]["step"] == manifest["steps"]


@pytest.mark.slow
def test_shipped_weights_reproduce_their_check_on_the_smoke_world(manifest, smoke_world,
                                                                  tmp_path):
    """The recipe's first steps from scratch give the recorded losses, and the shipped
    weights the recorded errors on the smoke world's pairs."""
    data = smoke_world[0].parents[1]
    smoke = load_profile("smoke", dataroot=str(data), n_jobs=1)
    threads = torch.get_num_threads()
    got = pt.smoke_check(pt.Recipe(), SHIPPED / "weights.pt", smoke, tmp_path / "check")
    assert torch.get_num_threads() == threads, "the check leaves the thread count as it was"
    want = manifest["check"]
    assert got["world_id"] == want["world_id"] and got["steps"] == want["steps"]
    assert got["first_losses"] == pytest.approx(want["first_losses"], rel=1e-6, abs=0)
    for k in ("epe", "epe_boxes", "fl_all"):
        assert got["weights"][k] == pytest.approx(want["weights"][k], rel=1e-4), k
