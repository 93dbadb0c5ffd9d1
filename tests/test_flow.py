"""flowmod.flow and flowmod.flow.architectures: estimators, networks' plumbing, the cached stage, metrics.

No trained network weights exist here: the network tests check shapes, padding, scaling and
key layouts with random or hand-set weights and never claim accuracy for them. DIS and
Farneback are checked for accuracy on textured synthetic pairs with known flow.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import types
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import torch

from flowmod import flow as fl
from flowmod.flow import architectures as fn


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """The networks here run on one thread (the test machine is shared), and the thread
    count is restored afterwards: a module-level setting changed it for whichever test
    happened to import this module first (test_crops does, without xdist)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# --------------------------------------------------------------------------------------------
# synthetic pairs
# --------------------------------------------------------------------------------------------


def texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """(h, w, 3) uint8 BGR with detail at several scales."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for s in (2, 4, 8, 16, 32):
        n = rng.random((h // s + 3, w // s + 3)).astype(np.float32)
        up = cv2.resize(n, ((w // s + 3) * s, (h // s + 3) * s), interpolation=cv2.INTER_CUBIC)
        img += up[s : s + h, s : s + w] / np.sqrt(s)
    img = (img - img.min()) / (img.max() - img.min()) * 235 + 10
    return np.dstack([img, np.roll(img, 5, 1), 255 - img]).astype(np.uint8)


def affine_pair(h: int, w: int, a: np.ndarray, t: tuple[float, float], seed: int = 0):
    """img2 = img1 moved by x -> a @ (x - c) + c + t (c: image centre); returns img1, img2, gt."""
    m = 40
    big = texture(h + 2 * m, w + 2 * m, seed)
    c = np.array([m + (w - 1) / 2, m + (h - 1) / 2])
    fwd = np.hstack([a, (c + np.asarray(t) - a @ c)[:, None]]).astype(np.float64)
    moved = cv2.warpAffine(big, fwd, (w + 2 * m, h + 2 * m), flags=cv2.INTER_CUBIC,
                           borderMode=cv2.BORDER_REFLECT)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.stack([xs + m, ys + m], -1)
    gt = (pts @ fwd[:, :2].T + fwd[:, 2]) - pts
    crop = (slice(m, m + h), slice(m, m + w))
    return big[crop], moved[crop], gt.astype(np.float32)


def inner(shape, margin: int = 12) -> np.ndarray:
    mask = np.zeros(shape[:2], bool)
    mask[margin:-margin, margin:-margin] = True
    return mask


SHIFT = affine_pair(150, 200, np.eye(2), (3.0, -2.0))
AFFINE = affine_pair(150, 200, np.array([[1.012, 0.006], [-0.006, 1.012]]), (1.5, -1.0), seed=1)


# --------------------------------------------------------------------------------------------
# classical estimators: real accuracy
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("method", "opts", "tol_shift", "tol_affine"),
    [
        ("dis", {"preset": "ultrafast"}, 0.4, 0.5),  # measured 0.14, 0.18
        ("dis", {"preset": "fast"}, 0.3, 0.5),  # 0.08, 0.20
        ("dis", {"preset": "medium"}, 0.1, 0.2),  # 0.02, 0.05
        ("farneback", {}, 0.1, 0.2),  # 0.00, 0.04
    ],
)
def test_classical_recover_known_flow(method, opts, tol_shift, tol_affine):
    est = fl.get_estimator(method, **opts)
    for (img1, img2, gt), tol in ((SHIFT, tol_shift), (AFFINE, tol_affine)):
        flow = est.estimate(img1, img2)
        assert flow.shape == gt.shape and flow.dtype == np.float32
        assert fl.epe(flow, gt, mask=inner(gt.shape)) < tol


@pytest.mark.parametrize("method", ["dis", "farneback"])
def test_classical_flow_reads_frames_as_bgr(method):
    """Frames are BGR (as cv2.imread gives them): gray weighs R (channel 2) 0.299 and B
    (channel 0) 0.114. A texture moving right in R and another moving left in B: the flow
    follows R. Read as RGB, B would weigh 0.299 and the flow would point left."""
    a1, a2, _ = affine_pair(120, 160, np.eye(2), (3.0, 0.0), seed=2)
    b1, b2, _ = affine_pair(120, 160, np.eye(2), (-3.0, 0.0), seed=3)
    img1 = np.dstack([b1[..., 0], np.full(b1.shape[:2], 128, np.uint8), a1[..., 0]])
    img2 = np.dstack([b2[..., 0], np.full(b2.shape[:2], 128, np.uint8), a2[..., 0]])
    u = fl.get_estimator(method).estimate(img1, img2)[..., 0][inner((120, 160))]
    assert np.median(u) > 1.0, np.median(u)


def test_scale_option_returns_full_size_flow_in_full_size_pixels():
    img1, img2, gt = SHIFT
    flow = fl.get_estimator("dis", preset="medium", scale=0.5).estimate(img1, img2)
    assert flow.shape == gt.shape
    assert fl.epe(flow, gt, mask=inner(gt.shape, 16)) < 0.5
    np.testing.assert_allclose(np.median(flow[inner(gt.shape, 16)], axis=0), [3.0, -2.0], atol=0.2)


def test_resize_flow_multiplies_by_size_ratios():
    f = np.ones((10, 20, 2), np.float32)
    g = fl.resize_flow(f, (30, 80))
    assert g.shape == (30, 80, 2)
    np.testing.assert_allclose(g[..., 0], 4.0)
    np.testing.assert_allclose(g[..., 1], 3.0)


def test_registry_and_input_checks():
    assert {"gt", "dis", "farneback", "raft", "raft_small", "fastflownet"} <= set(
        fl.available_methods()
    )
    with pytest.raises(ValueError, match="unknown flow method 'nope'"):
        fl.get_estimator("nope")
    with pytest.raises(TypeError, match="'dis'"):
        fl.get_estimator("dis", bogus=1)
    with pytest.raises(ValueError, match="preset"):
        fl.get_estimator("dis", preset="slow")
    est = fl.get_estimator("dis")
    with pytest.raises(ValueError, match="uint8"):
        est.estimate(SHIFT[0].astype(np.float32), SHIFT[1])
    with pytest.raises(ValueError, match="differ in size"):
        est.estimate(SHIFT[0], SHIFT[1][:-1])


# --------------------------------------------------------------------------------------------
# FastFlowNet
# --------------------------------------------------------------------------------------------


def test_correlation_matches_direct_loop():
    g = torch.Generator().manual_seed(0)
    f1 = torch.randn(2, 3, 6, 7, generator=g)
    f2 = torch.randn(2, 3, 6, 7, generator=g)
    r = 4
    ref = torch.zeros(2, 81, 6, 7)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            k = (dy + r) * 9 + (dx + r)
            for y in range(6):
                for x in range(7):
                    if 0 <= y + dy < 6 and 0 <= x + dx < 7:
                        ref[:, k, y, x] = (f1[:, :, y, x] * f2[:, :, y + dy, x + dx]).sum(1) / 3
    out = fn.correlation(f1, f2, 4)
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6)
    sub = fn.correlation(f1, f2, 4, fn.FFN_CORR_INDEX)
    assert sub.shape[1] == 53
    torch.testing.assert_close(sub, out.index_select(1, torch.tensor(fn.FFN_CORR_INDEX)))


def test_fastflownet_state_dict_layout():
    sd = fn.FastFlowNet().state_dict()
    assert len(sd) == 104
    shapes = {k: tuple(v.shape) for k, v in sd.items()}
    assert shapes["pconv1_1.0.weight"] == (16, 3, 3, 3)
    assert shapes["pconv2_1.0.weight"] == (32, 16, 3, 3)
    assert shapes["pconv3_3.0.weight"] == (64, 64, 3, 3)
    assert shapes["rconv2.0.weight"] == (32, 32, 3, 3)
    assert shapes["rconv6.0.weight"] == (32, 64, 3, 3)
    assert shapes["up3.weight"] == (2, 2, 4, 4) and "up6.bias" in shapes
    assert shapes["decoder2.conv1.0.weight"] == (96, 87, 3, 3)
    assert shapes["decoder6.conv3.0.weight"] == (96, 32, 3, 3)  # groups=3
    assert shapes["decoder5.conv6.0.weight"] == (32, 64, 3, 3)
    assert shapes["decoder4.conv7.weight"] == (2, 32, 3, 3)


def test_warp_moves_features_by_the_flow():
    x = torch.zeros(1, 1, 8, 9)
    x[0, 0, 4, 6] = 1.0
    flow = torch.zeros(1, 2, 8, 9)
    flow[:, 0], flow[:, 1] = 2.0, 1.0  # sample x at (col + 2, row + 1)
    out = fn.warp(x, flow)
    assert out[0, 0, 3, 4] == pytest.approx(1.0)
    assert out.sum() == pytest.approx(1.0)


@pytest.mark.parametrize("legacy", [False, True])
def test_fastflownet_checkpoint_in_official_layout_loads(tmp_path, legacy):
    torch.manual_seed(0)
    model = fn.FastFlowNet().eval()
    path = tmp_path / "fastflownet_ft_kitti.pth"
    torch.save(model.state_dict(), path, _use_new_zipfile_serialization=not legacy)
    est = fl.get_estimator("fastflownet", weights=path, device="cpu")
    assert est.weights_source == str(path)
    img1, img2 = SHIFT[0][:97, :131], SHIFT[1][:97, :131]  # odd sizes: resized to 128 x 192
    flow = est.estimate(img1, img2)
    assert flow.shape == (97, 131, 2) and flow.dtype == np.float32 and np.isfinite(flow).all()
    x1 = torch.from_numpy(img1).permute(2, 0, 1)[None].float()
    x2 = torch.from_numpy(img2).permute(2, 0, 1)[None].float()
    with torch.inference_mode():
        ref = fn.fastflownet_flow(model, x1, x2)[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(flow, ref, atol=1e-5)
    # a DataParallel ("module.") checkpoint loads too
    torch.save({f"module.{k}": v for k, v in model.state_dict().items()}, tmp_path / "dp.pth")
    fl.get_estimator("fastflownet", weights=tmp_path / "dp.pth", device="cpu")


def test_mismatched_checkpoint_fails_naming_file_and_keys(tmp_path):
    sd = fn.FastFlowNet().state_dict()
    del sd["decoder3.conv7.bias"]
    sd["rconv2.0.weight"] = torch.zeros(32, 16, 3, 3)
    sd["extra.weight"] = torch.zeros(1)
    path = tmp_path / "bad.pth"
    torch.save(sd, path)
    with pytest.raises(fn.CheckpointError) as e:
        fl.get_estimator("fastflownet", weights=path, device="cpu")
    msg = str(e.value)
    for part in (str(path), "decoder3.conv7.bias", "extra.weight", "rconv2.0.weight"):
        assert part in msg
    # a RAFT-large file given to raft_small
    big = tmp_path / "raft_large.pth"
    torch.save(fn.build_raft("raft_large").state_dict(), big)
    with pytest.raises(fn.CheckpointError, match="raft_large.pth.*shape mismatches"):
        fl.get_estimator("raft_small", weights=big, device="cpu")
    # not a checkpoint at all
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a torch file")
    with pytest.raises(fn.CheckpointError, match="junk.pth"):
        fl.get_estimator("fastflownet", weights=junk, device="cpu")


def _hand_set_fastflownet(bu: float, bv: float) -> fn.FastFlowNet:
    """All weights zero except decoder2's last bias: flow2 = (bu, bv) px/20 everywhere."""
    m = fn.FastFlowNet()
    with torch.no_grad():
        for p in m.parameters():
            p.zero_()
        m.decoder2.conv7.bias.copy_(torch.tensor([bu, bv]))
    return m.eval()


@pytest.mark.parametrize(("h", "w", "scale"), [(150, 200, 1.0), (97, 131, 1.0), (150, 200, 0.5),
                                               (97, 131, 0.5)])
@pytest.mark.parametrize("on_device", [False, True])
def test_fastflownet_output_scaling_chain(h, w, scale, on_device):
    """Host resizing (OpenCV) and device resizing (torch, what a GPU runs) scale the flow
    alike; ``on_device`` forces the device path on the CPU."""
    est = fl.get_estimator("fastflownet", model=_hand_set_fastflownet(0.1, -0.05),
                           device="cpu", scale=scale)
    est.device_resize = on_device
    img = texture(h, w)
    flow = est.estimate_batch([img], [img])[0]
    assert flow.shape == (h, w, 2) and flow.dtype == np.float32
    hs, ws = round(h * scale), round(w * scale)
    h64, w64 = 64 * -(-hs // 64), 64 * -(-ws // 64)
    # x20, times the 64-multiple resize ratio, times the `scale` resize ratio
    np.testing.assert_allclose(flow[..., 0], 20 * 0.1 * (ws / w64) * (w / ws), rtol=1e-5)
    np.testing.assert_allclose(flow[..., 1], 20 * -0.05 * (hs / h64) * (h / hs), rtol=1e-5)


def test_fastflownet_random_weights_equivariances():
    """Random weights, no accuracy claim: batch == single; a common brightness offset changes
    nothing (the per-channel mean is subtracted)."""
    torch.manual_seed(1)
    est = fl.get_estimator("fastflownet", model=fn.FastFlowNet(), device="cpu", batch_size=2)
    a1, a2, _ = SHIFT
    b1, b2, _ = AFFINE
    single = [est.estimate(a1, a2), est.estimate(b1, b2)]
    batch = est.estimate_batch([a1, b1], [a2, b2])
    for s, b in zip(single, batch, strict=True):
        np.testing.assert_allclose(s, b, atol=1e-4)
    est.scale, est.device_resize = 0.5, True  # frames and flow resized by torch, as on a GPU
    on_device = est.estimate_batch([a1, b1], [a2, b2])
    est.device_resize = False
    on_host = est.estimate_batch([a1, b1], [a2, b2])
    for d, h in zip(on_device, on_host, strict=True):
        assert d.shape == h.shape == a1.shape[:2] + (2,)
        assert np.abs(d - h).mean() < 0.1 * np.abs(h).mean() + 1e-3  # interpolation only
    est.scale = 1.0
    brighter = est.estimate(a1 + np.uint8(9), a2 + np.uint8(9))  # textures stay in 10..245
    np.testing.assert_allclose(brighter, single[0], atol=1e-3 * max(1.0, np.abs(single[0]).max()))


# --------------------------------------------------------------------------------------------
# RAFT
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("arch", ["raft_large", "raft_small"])
def test_raft_original_key_mapping_round_trips(arch):
    sd = fn.build_raft(arch).state_dict()
    orig = fn.raft_torchvision_to_original(sd)
    assert fn.is_original_raft(orig) and not fn.is_original_raft(sd)
    shapes = {k: tuple(v.shape) for k, v in orig.items()}
    if arch == "raft_large":
        assert len(orig) == len(sd) + 10  # cnet layer2.0 / layer3.0 norm3 == downsample.1
        assert shapes["module.fnet.conv1.weight"] == (64, 3, 7, 7)
        assert shapes["module.cnet.layer2.0.norm3.running_mean"] == (96,)
        assert shapes["module.cnet.layer3.0.downsample.1.weight"] == (128,)
        assert shapes["module.update_block.encoder.convc1.weight"] == (256, 324, 1, 1)
        assert shapes["module.update_block.gru.convq2.weight"] == (128, 384, 5, 1)
        assert shapes["module.update_block.mask.2.weight"] == (576, 256, 1, 1)
        assert shapes["module.fnet.layer1.1.conv2.weight"] == (64, 64, 3, 3)
    else:
        assert shapes["module.fnet.layer1.0.conv3.weight"] == (32, 8, 1, 1)
        assert shapes["module.update_block.gru.convz.weight"] == (96, 242, 3, 3)
        assert shapes["module.update_block.encoder.convc1.weight"] == (96, 196, 1, 1)
    back = fn.raft_original_to_torchvision(orig)
    assert list(back) == list(sd) or set(back) == set(sd)
    for k, v in sd.items():
        assert torch.equal(back[k], v), k
    # without the DataParallel prefix and without the duplicated norms it maps the same
    plain = {k[len("module.") :]: v for k, v in orig.items() if ".norm3." not in k}
    assert set(fn.raft_original_to_torchvision(plain)) == set(sd)


def _zero_raft_small(b: tuple[float, float]) -> torch.nn.Module:
    """All weights zero except the flow head's last bias: each update adds b (1/8 res)."""
    m = fn.build_raft("raft_small")
    with torch.no_grad():
        for p in m.parameters():
            p.zero_()
        m.update_block.flow_head.conv2.bias.copy_(torch.tensor(b))
    return m.eval()


def test_raft_loads_original_checkpoint_and_hand_set_flow(tmp_path):
    model = _zero_raft_small((0.25, -0.125))
    path = tmp_path / "raft-small.pth"
    torch.save(fn.raft_torchvision_to_original(model.state_dict()), path)
    est = fl.get_estimator("raft_small", weights=path, device="cpu", num_flow_updates=3)
    img = texture(75, 101)  # odd: padded to 80 x 104, cropped back
    flow = est.estimate(img, img)
    assert flow.shape == (75, 101, 2)
    # flow = 8 (upsampling) * 3 updates * b, everywhere
    np.testing.assert_allclose(flow[..., 0], 6.0, rtol=1e-5)
    np.testing.assert_allclose(flow[..., 1], -3.0, rtol=1e-5)
    half = fl.get_estimator("raft_small", weights=path, device="cpu", num_flow_updates=3,
                            scale=0.5).estimate(img, img)
    np.testing.assert_allclose(half[..., 0], 6.0 * 101 / 50, rtol=1e-5)  # 101 -> 50 px wide


class _EchoRAFT(torch.nn.Module):
    """A stand-in network whose 'flow' is the first image's R and G inputs: shows where each
    output pixel comes from."""

    def forward(self, img1, img2, num_flow_updates=12):
        assert img1.shape[-2] % 8 == 0 and img1.shape[-1] % 8 == 0
        return [img1[:, :2]]


@pytest.mark.parametrize(("h", "w"), [(900, 1600), (97, 131)])
def test_raft_unpadding_keeps_coordinates(h, w):
    img = np.full((h, w, 3), 40, np.uint8)
    y0, x0 = h // 2, w - 3
    img[y0, x0, 2] = 250  # a red dot (BGR) near the right edge
    est = fl.get_estimator("raft", model=_EchoRAFT(), device="cpu")
    flow = est.estimate(img, img)
    assert flow.shape == (h, w, 2)
    assert np.unravel_index(np.argmax(flow[..., 0]), (h, w)) == (y0, x0)
    np.testing.assert_allclose(flow[..., 0], img[..., 2] * (2 / 255) - 1, atol=1e-6)
    x = torch.zeros(1, 3, h, w)
    padded, pads = fn.pad_to_multiple(x, 8)
    assert padded.shape[-2] % 8 == 0 and padded.shape[-1] % 8 == 0
    assert fn.unpad(padded, pads).shape == x.shape
    if h == 900:
        assert padded.shape[-2] == 904 and pads[2:] == (2, 2)


def test_raft_random_weights_shape_and_batch():
    """Random weights (no accuracy claim): odd sizes come back at full size; batch == single."""
    torch.manual_seed(2)
    est = fl.get_estimator("raft_small", model=fn.build_raft("raft_small"), device="cpu",
                           num_flow_updates=2, batch_size=2)
    a1, a2 = SHIFT[0][:75, :101], SHIFT[1][:75, :101]
    b1, b2 = AFFINE[0][:75, :101], AFFINE[1][:75, :101]
    single = [est.estimate(a1, a2), est.estimate(b1, b2)]
    batch = est.estimate_batch([a1, b1], [a2, b2])
    for s, b in zip(single, batch, strict=True):
        assert s.shape == (75, 101, 2) and np.isfinite(s).all()
        np.testing.assert_allclose(s, b, atol=1e-3)


@pytest.mark.parametrize(
    ("method", "param"),
    [("raft", "raft_weights"), ("raft_small", "raft_small_weights"),
     ("fastflownet", "fastflownet_weights")],
)
def test_networks_refuse_without_weights(tmp_path, monkeypatch, method, param):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    with pytest.raises(fl.MissingWeightsError) as e:
        fl.get_estimator(method, device="cpu")
    msg = str(e.value)
    assert param in msg and str(tmp_path / "torch" / "hub" / "checkpoints") in msg
    assert "random weights" in msg
    with pytest.raises(fl.MissingWeightsError, match="nothere.pth"):
        fl.get_estimator(method, weights=tmp_path / "nothere.pth", device="cpu")


def test_raft_weights_found_in_torch_home_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    name = dict(fn.torchvision_weight_files("raft_small"))["Raft_Small_Weights.C_T_V2"]
    cache = tmp_path / "hub" / "checkpoints"
    cache.mkdir(parents=True)
    torch.save(_zero_raft_small((0.5, 0.5)).state_dict(), cache / name)
    est = fl.get_estimator("raft_small", device="cpu", num_flow_updates=1)
    assert est.weights_source == str(cache / name)
    np.testing.assert_allclose(est.estimate(SHIFT[0][:40, :48], SHIFT[1][:40, :48]), 4.0)
    assert fn.torchvision_weight_files("raft_large")[0][0] == "Raft_Large_Weights.C_T_SKHT_K_V1"


# --------------------------------------------------------------------------------------------
# the stage runner
# --------------------------------------------------------------------------------------------


def make_dataroot(root: Path, n: int = 4, size=(60, 80)) -> pd.DataFrame:
    rows = []
    for i in range(n):
        img1, img2, _ = affine_pair(*size, np.eye(2), (1.0 + i, -1.0), seed=10 + i)
        p1, p2 = f"samples/CAM_FRONT/f{i}a.jpg", f"samples/CAM_FRONT/f{i}b.jpg"
        (root / p1).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / p1), img1, [cv2.IMWRITE_JPEG_QUALITY, 95])
        cv2.imwrite(str(root / p2), img2, [cv2.IMWRITE_JPEG_QUALITY, 95])
        rows.append({
            "pair_id": f"p{i}", "scene": "synth-0000", "split": "train", "set": "keyframe",
            "sd_token_1": f"t{i}a", "sd_token_2": f"t{i}b", "path_1": p1, "path_2": p2,
            "timestamp_1": 1_000_000 * i, "timestamp_2": 1_000_000 * i + 500_000,
        })  # fmt: skip
    return pd.DataFrame(rows)


def loaded(res: pd.DataFrame, pool: Path, pair_id: str, store_scale: float = 1.0) -> np.ndarray:
    """The flow of one pair from compute_flow's result rows."""
    return fl.load_stored_flow(pool / res.set_index("pair_id").loc[pair_id, "file"], store_scale)


KW = {"version": "v1.0-synth", "world": "w0", "n_jobs": 1, "progress": False}


def test_compute_flow_writes_resumes_and_survives_a_kill(tmp_path):
    root, pool = tmp_path / "data", tmp_path / "pool"
    pairs = make_dataroot(root)
    kw = {"dataroot": root, **KW}
    first = fl.compute_flow(pairs, "dis", pool, preset="fast", **kw)
    assert first["computed"].all() and list(first["pair_id"]) == list(pairs["pair_id"])
    assert list(first.columns) == ["pair_id", "key", "file", "seconds", "shape", "computed"]
    assert (first["seconds"] > 0).all() and list(first["shape"].iloc[0]) == [60, 80, 2]
    files = {r.pair_id: pool / r.file for r in first.itertuples()}
    arr = np.load(files["p1"])
    assert arr.dtype == np.float16 and arr.shape == (60, 80, 2)
    direct = fl.get_estimator("dis", preset="fast").estimate(
        fl.read_image(root / pairs.path_1[1]), fl.read_image(root / pairs.path_2[1]))
    np.testing.assert_allclose(loaded(first, pool, "p1"), direct, atol=0.01)

    stats = {p: (p.stat().st_mtime_ns, p.stat().st_ino) for p in files.values()}
    again = fl.compute_flow(pairs, "dis", pool, preset="fast", **kw)
    assert not again["computed"].any()
    assert {p: (p.stat().st_mtime_ns, p.stat().st_ino) for p in files.values()} == stats
    pd.testing.assert_frame_equal(again.drop(columns="computed"), first.drop(columns="computed"))

    # simulated kill: p1 only got as far as a temporary file, p2 was left truncated
    files["p1"].unlink()
    (files["p1"].parent / ".p1.abc123.tmp.npy").write_bytes(b"\x93NUMPY partial")
    data = files["p2"].read_bytes()
    files["p2"].write_bytes(data[: len(data) // 2])
    with pytest.raises(fl.FlowFileError, match=files["p2"].name):
        fl.load_stored_flow(files["p2"])
    resumed = fl.compute_flow(pairs, "dis", pool, preset="fast", **kw)
    assert set(resumed.loc[resumed["computed"], "pair_id"]) == {"p1", "p2"}
    assert not list(pool.rglob(".*tmp*"))
    assert loaded(resumed, pool, "p2").shape == (60, 80, 2)

    # other options live beside: the first files stay, and switching back costs nothing
    changed = fl.compute_flow(pairs, "dis", pool, preset="medium", dtype="float32", **kw)
    assert changed["computed"].all() and set(changed["key"]) == set(first["key"])
    assert changed["file"].str.split("/").str[0].nunique() == 1
    assert np.load(pool / changed["file"].iloc[0]).dtype == np.float32
    back = fl.compute_flow(pairs, "dis", pool, preset="fast", **kw)
    assert not back["computed"].any()


def test_a_pool_file_changed_in_place_is_computed_again_not_reused(tmp_path):
    """Issue 53: a pool file zeroed in place (header kept: it is complete) was reused, so a
    crops rebuild published all-zero crops. The pool records each file's sha256 when it
    is written; a file whose content differs is computed again (only that one), and files
    of a pool that recorded no digests are trusted as before."""

    root, pool = tmp_path / "data", tmp_path / "pool"
    pairs = make_dataroot(root, n=3)
    kw = {"dataroot": root, **KW}
    first = fl.compute_flow(pairs, "dis", pool, preset="fast", **kw)
    files = {r.pair_id: pool / r.file for r in first.itertuples()}
    good = files["p1"].read_bytes()
    log = (files["p1"].parent / fl.stage.TIMINGS).read_text().splitlines()
    assert [json.loads(x)["sha256"] for x in log] == [
        hashlib.sha256(files[p].read_bytes()).hexdigest() for p in first["pair_id"]]
    st = files["p1"].stat()
    header = len(good) - 60 * 80 * 2 * 2
    files["p1"].write_bytes(good[:header] + bytes(len(good) - header))
    os.utime(files["p1"], ns=(st.st_atime_ns, st.st_mtime_ns))
    assert fl.stage.altered(files["p1"].parent, list(first["key"]), fl.stage.FlowFiles()) == {
        first.set_index("pair_id").loc["p1", "key"]}
    again = fl.compute_flow(pairs, "dis", pool, preset="fast", **kw)
    assert list(again.loc[again["computed"], "pair_id"]) == ["p1"]
    assert files["p1"].read_bytes() == good
    # a pool written before digests were logged: its files are trusted
    (files["p1"].parent / fl.stage.TIMINGS).write_text(
        "".join(json.dumps({"key": k, "seconds": 0.1}) + "\n" for k in first["key"]))
    files["p2"].write_bytes(files["p2"].read_bytes()[:header] + bytes(len(good) - header))
    assert not fl.compute_flow(pairs, "dis", pool, preset="fast", **kw)["computed"].any()


def test_the_exact_flow_is_keyed_by_the_worlds_description_not_its_annotations(tmp_path):
    """gt reads only the world's own description (synth_world.json): an edited annotation
    leaves its pair keys alone, an edited description changes them all; image methods keep
    the data's fingerprint (their keys are their images)."""
    from flowmod import dag
    from flowmod.params import WORLD_FILE, validate

    vdir = tmp_path / "data" / "v1.0-synth"
    vdir.mkdir(parents=True)
    (vdir / WORLD_FILE).write_text('{"scenes": []}')
    (vdir / "sample_annotation.json").write_text("[]")
    p = validate({"dataroot": str(tmp_path / "data"), "version": "v1.0-synth",
                  "run_dir": str(tmp_path / "runs"), "synthetic": False})
    q = dag.StageParams(p, dag.Node("flow", "gt", "keyframe"))
    gt = fl.stage.world_identity(q, "gt", "world-A")
    assert gt == fl.stage.world_identity(q, "gt", "world-B") != "world-A"
    assert fl.stage.world_identity(q, "dis", "world-A") == "world-A"
    (vdir / "sample_annotation.json").write_text('[{"token": "a"}]')
    assert fl.stage.world_identity(q, "gt", "world-A") == gt
    (vdir / WORLD_FILE).write_text('{"scenes": [{}]}')
    assert fl.stage.world_identity(q, "gt", "world-A") != gt


def test_a_pool_folder_is_named_by_its_estimators_code(tmp_path):
    """Code as an input, one level down: the flow files of a method are kept under the
    digest of the estimator's code, so an edited estimator never reuses old flow."""
    from flowmod import codedigest

    cfg = fl.stage.options_config("dis", "float16", 1.0, {})
    assert cfg["code"] == codedigest.code_id("flowmod.flow.estimators")
    assert fl.stage.options_config("raft", "float16", 1.0, {"weights": None})["code"] == (
        codedigest.code_id("flowmod.flow.networks"))


def test_pair_keys_follow_the_data_not_the_pair_id(tmp_path):
    """Another world (seed, dataroot content), other tokens or other image files never match."""
    root = tmp_path / "data"
    pairs = make_dataroot(root, n=2)
    keys = fl.stage.pair_keys(pairs, root, "world-A")
    assert len(set(keys)) == 2
    assert fl.stage.pair_keys(pairs, root, "world-B") != keys, "another world"
    # the same files and version name, another world's content: other keys
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    assert fl.stage.pair_keys(pairs, copy, "world-A") == keys, "a copy of the same world"
    assert fl.stage.pair_keys(pairs, copy, "world-C") != keys
    other_tokens = pairs.assign(sd_token_1=["x", "y"])
    assert fl.stage.pair_keys(other_tokens, root, "world-A") != keys, "other frames"
    img = root / pairs.path_2[0]
    img.write_bytes(img.read_bytes() + b"\0")  # another image file behind the same name
    changed = fl.stage.pair_keys(pairs, root, "world-A")
    assert changed[0] != keys[0] and changed[1] == keys[1]
    img.unlink()
    with pytest.raises(fl.ImageError, match="image missing"):
        fl.stage.pair_keys(pairs, root, "world-A")


def test_image_methods_key_each_pair_by_its_two_images_only(tmp_path):
    """DIS reads only a pair's two images: another world fingerprint (one annotation
    edited) recomputes nothing, and an image whose content changed (same size) recomputes
    exactly the pair that reads it; ``gt`` reads the world, and recomputes all (issue 41)."""
    root, pool = tmp_path / "data", tmp_path / "pool"
    pairs = make_dataroot(root)
    kw = {**KW, "dataroot": root, "preset": "fast"}
    first = fl.compute_flow(pairs, "dis", pool, **kw)
    edited = fl.compute_flow(pairs, "dis", pool, **{**kw, "world": "w0-one-box-edited"})
    assert not edited["computed"].any() and list(edited["key"]) == list(first["key"])
    img = root / pairs.path_1[2]
    data = bytearray(img.read_bytes())
    data[-40] ^= 0x01  # one bit of the entropy-coded data: same size, other content
    img.write_bytes(bytes(data))
    again = fl.compute_flow(pairs, "dis", pool, **kw)
    assert list(again.loc[again["computed"], "pair_id"]) == ["p2"]
    assert (pool / again["file"].iloc[0]).parent.joinpath(".image-digests.json").is_file()
    keys = fl.stage.pair_keys(pairs, root, "w0", by_images=True)
    assert keys == list(again["key"]) and fl.stage.pair_keys(pairs, root, "w9", True) == keys
    assert fl.stage.pair_keys(pairs, root, "w0") != fl.stage.pair_keys(pairs, root, "w9")


def test_compute_flow_parallel_matches_direct(tmp_path):
    root = tmp_path / "data"
    pairs = make_dataroot(root, n=3)
    kw = {**KW, "n_jobs": 2}
    res = fl.compute_flow(pairs, "farneback", tmp_path / "pool", dataroot=root, dtype="float32",
                          **kw)
    assert res["computed"].all()
    for r in pairs.itertuples():
        direct = fl.get_estimator("farneback").estimate(
            fl.read_image(root / r.path_1), fl.read_image(root / r.path_2))
        np.testing.assert_allclose(loaded(res, tmp_path / "pool", r.pair_id), direct, atol=1e-4)


def test_compute_flow_reports_bad_images_before_starting(tmp_path):
    root = tmp_path / "data"
    pairs = make_dataroot(root)
    (root / pairs.path_2[0]).write_bytes(b"")
    data = (root / pairs.path_1[3]).read_bytes()
    (root / pairs.path_1[3]).write_bytes(data[: len(data) // 2])
    with pytest.raises(fl.ImageError) as e:
        fl.compute_flow(pairs, "dis", tmp_path / "pool", dataroot=root, **KW)
    msg = str(e.value)
    assert "2 of 8 images" in msg and pairs.path_2[0] in msg and pairs.path_1[3] in msg
    assert "truncated" in msg and "empty" in msg
    assert not list((tmp_path / "pool").rglob("*.npy"))


def test_a_jpeg_whose_data_is_corrupt_but_whose_end_survives_is_refused(tmp_path, capfd):
    """Zeroed bytes in the middle of a JPEG keep its end marker, and OpenCV decodes it with
    only libjpeg's "Corrupt JPEG data" on stderr: that warning makes it corrupt (issue 41)."""
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 255, (90, 160, 3), dtype=np.uint8), (5, 5), 0)
    data = bytearray(cv2.imencode(".jpg", img)[1].tobytes())
    good, bad = tmp_path / "good.jpg", tmp_path / "bad.jpg"
    good.write_bytes(bytes(data))
    data[len(data) // 3 : len(data) // 3 + 200] = bytes(200)
    bad.write_bytes(bytes(data))
    assert bad.read_bytes().endswith(b"\xff\xd9") and cv2.imread(str(bad)) is not None
    assert "Corrupt JPEG data" in capfd.readouterr().err  # what OpenCV alone gives
    assert fl.read_image(good).shape == (90, 160, 3)
    with pytest.raises(fl.ImageError, match=r"image corrupt \(Corrupt JPEG data.*bad.jpg"):
        fl.read_image(bad)
    with pytest.raises(fl.ImageError, match=r"1 of 2 images.*bad.jpg \(corrupt: Corrupt JPEG"):
        fl.check_images([good, bad])
    assert "Corrupt JPEG" not in capfd.readouterr().err  # said once, in the error


def test_compute_flow_network_batches(tmp_path):
    root = tmp_path / "data"
    pairs = make_dataroot(root, n=3, size=(50, 70))
    res = fl.compute_flow(pairs, "fastflownet", tmp_path / "pool", dataroot=root, **KW,
                          model=_hand_set_fastflownet(0.05, 0.0), device="cpu", batch_size=2)
    assert res["computed"].all()
    f = loaded(res, tmp_path / "pool", "p2")
    np.testing.assert_allclose(f[..., 0], 20 * 0.05 * 70 / 128, rtol=1e-3)


def test_new_weights_at_the_same_path_never_reuse_the_old_weights_flow(tmp_path):
    """The pool once keyed network flow by the weights' path: `make flownet` then `make
    book` reused the flow of the replaced weights (their sha256 now enters the pool)."""
    root, pool, w = tmp_path / "data", tmp_path / "pool", tmp_path / "w.pt"
    pairs = make_dataroot(root, n=2, size=(50, 70))
    torch.save(_hand_set_fastflownet(0.05, 0.0).state_dict(), w)
    kw = {"dataroot": root, **KW, "weights": str(w), "device": "cpu"}
    old = fl.compute_flow(pairs, "fastflownet", pool, **kw)
    assert fl.compute_flow(pairs, "fastflownet", pool, **kw)["computed"].sum() == 0
    torch.save(_hand_set_fastflownet(0.10, 0.0).state_dict(), w)  # new weights, same path
    new = fl.compute_flow(pairs, "fastflownet", pool, **kw)
    assert new["computed"].all()
    ratio = loaded(new, pool, "p1")[..., 0] / loaded(old, pool, "p1")[..., 0]
    np.testing.assert_allclose(ratio, 2.0, rtol=1e-3)


def test_null_weights_stand_for_the_cached_checkpoint_they_load(tmp_path, monkeypatch):
    """``fastflownet_weights: null`` loads the first checkpoint found in the torch hub cache:
    the flow node's fingerprint and the pool key that file's content, so a checkpoint
    replaced in the cache, or a preferred one added, never gets the old flow."""
    from flowmod import dag
    from flowmod.flow.networks import cache_files, estimator_options
    from flowmod.params import load_profile

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    p = load_profile("smoke", run_dir=str(tmp_path / "runs"), fastflownet_weights=None)
    node = dag.Node("flow", "fastflownet", "keyframe")
    assert dag.values(p, node)["fastflownet_weights"] is None, "nothing cached: as before"
    assert estimator_options(p, "fastflownet")["weights"] is None
    preferred, other = cache_files("fastflownet")[:2]
    other.parent.mkdir(parents=True)
    torch.save(_hand_set_fastflownet(0.05, 0.0).state_dict(), other)
    first = dag.values(p, node)["fastflownet_weights"]
    opts = estimator_options(p, "fastflownet")
    assert opts["weights"] == other and first == {"sha256": fl.stage.file_digest(other)}
    root, pool = tmp_path / "data", tmp_path / "pool"
    pairs = make_dataroot(root, n=2, size=(50, 70))
    kw = {**KW, "dataroot": root, **opts, "device": "cpu"}
    old = fl.compute_flow(pairs, "fastflownet", pool, **kw)
    torch.save(_hand_set_fastflownet(0.10, 0.0).state_dict(), other)  # replaced in the cache
    assert dag.values(p, node)["fastflownet_weights"] != first
    new = fl.compute_flow(pairs, "fastflownet", pool, **kw)
    assert new["computed"].all()
    ratio = loaded(new, pool, "p1")[..., 0] / loaded(old, pool, "p1")[..., 0]
    np.testing.assert_allclose(ratio, 2.0, rtol=1e-3)
    torch.save(_hand_set_fastflownet(0.20, 0.0).state_dict(), preferred)  # a preferred one
    assert estimator_options(p, "fastflownet")["weights"] == preferred
    assert dag.values(p, node)["fastflownet_weights"] == {
        "sha256": fl.stage.file_digest(preferred)}


def test_gt_estimator_passes_its_world_and_returns_float32_and_bool(tmp_path, monkeypatch):
    """GTFlow asks the world of its own dataroot and version, at scale 1, and returns the
    flow as float32 and the mask as bool whatever the world hands back."""
    seen = []
    world = types.ModuleType("flowmod.world.truth")
    world.is_synthetic = lambda dataroot, version: seen.append(("is", dataroot, version)) or True

    def gt_flow(dataroot, version, t1, t2):
        seen.append(("gt", dataroot, version, t1, t2))
        return np.full((2, 3, 2), 1.5, np.float64).tolist(), np.array([[1, 0, 2]] * 2)

    world.gt_flow = gt_flow
    monkeypatch.setitem(sys.modules, "flowmod.world.truth", world)
    est = fl.get_estimator("gt", dataroot=tmp_path / "w", version="v1.0-x")
    assert est.scale == 1.0 and est.options() == {"dataroot": str(tmp_path / "w"),
                                                  "version": "v1.0-x"}
    flow, valid = est.estimate_tokens("a", "b")
    assert flow.dtype == np.float32 and flow.shape == (2, 3, 2) and (flow == 1.5).all()
    assert valid.dtype == bool and valid.tolist() == [[True, False, True]] * 2
    assert seen == [("is", str(tmp_path / "w"), "v1.0-x"),
                    ("gt", str(tmp_path / "w"), "v1.0-x", "a", "b")]
    with pytest.raises(TypeError, match=r"^gt works from sample_data tokens, not images: use "
                                        r"estimate_tokens\(sd_token_1, sd_token_2\) or "
                                        r"compute_flow\(\)$"):
        est.estimate(SHIFT[0], SHIFT[1])
    world.gt_flow = lambda *a: (np.full((2, 3, 2), np.nan), np.ones((2, 3), bool))
    with pytest.raises(ValueError, match=r"^gt flow a -> b has non-finite values$"):
        est.estimate_tokens("a", "b")
    world.is_synthetic = lambda dataroot, version: False
    with pytest.raises(fl.NotSyntheticError, match=r"is not one \(flowmod.world.is_synthetic is "
                                                   r"False\): drop 'gt' from flow_methods for "
                                                   r"real nuScenes data$"):
        fl.get_estimator("gt", dataroot=tmp_path / "w", version="v1.0-x")


def test_classical_estimators_defaults_and_presets():
    """DIS and Farneback at their documented defaults (scale 1; Farneback 5 levels, a 15 px
    window, no Gaussian unless asked); DIS computes with the preset it names."""
    dis = fl.get_estimator("dis")
    assert dis.options() == {"preset": "medium", "scale": 1.0}
    far = fl.get_estimator("farneback")
    assert far.options() == {"scale": 1.0, "pyr_scale": 0.5, "levels": 5, "winsize": 15,
                             "iterations": 3, "poly_n": 5, "poly_sigma": 1.2, "flags": 0}
    assert fl.get_estimator("farneback", gaussian=True).options()["flags"] == \
        cv2.OPTFLOW_FARNEBACK_GAUSSIAN
    with pytest.raises(ValueError, match="allowed: ultrafast, fast, medium$"):
        fl.get_estimator("dis", preset="slow")
    img1, img2, _ = SHIFT
    g1, g2 = (cv2.cvtColor(i, cv2.COLOR_BGR2GRAY) for i in (img1, img2))
    for name, preset in (("ultrafast", cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST),
                         ("medium", cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)):
        want = cv2.DISOpticalFlow_create(preset).calc(g1, g2, None)
        got = fl.get_estimator("dis", preset=name).estimate(img1, img2)
        np.testing.assert_array_equal(got, want)


def test_gt_method_works_from_tokens(tmp_path, monkeypatch):
    calls = []

    def gt_flow(dataroot, version, t1, t2):
        calls.append((t1, t2))
        flow = np.full((6, 8, 2), float(len(t1)), np.float32)
        flow[0, 0] = 7.0
        valid = np.ones((6, 8), bool)
        valid[0, 0] = False  # e.g. the point leaves the image
        return flow, valid

    world = types.ModuleType("flowmod.world.truth")
    world.is_synthetic = lambda dataroot, version: Path(dataroot).name == "synth"
    world.gt_flow = gt_flow
    monkeypatch.setitem(sys.modules, "flowmod.world.truth", world)
    pairs = make_dataroot(tmp_path / "synth", n=2)
    res = fl.compute_flow(pairs, "gt", tmp_path / "pool", dataroot=tmp_path / "synth", **KW)
    assert res["computed"].all() and calls == [("t0a", "t0b"), ("t1a", "t1b")]
    f = loaded(res, tmp_path / "pool", "p1")
    assert f.shape == (6, 8, 2) and f[0, 0, 0] == 7 and f[1, 1, 0] == 3
    valid = fl.stage.load_stored_valid(tmp_path / "pool" / res["file"].iloc[1])
    assert valid.shape == (6, 8) and not valid[0, 0] and valid[1:].all(), "the mask is stored"
    with pytest.raises(TypeError, match="tokens"):
        fl.get_estimator("gt", dataroot=tmp_path / "synth", version="v").estimate(
            SHIFT[0], SHIFT[1])
    make_dataroot(tmp_path / "real", n=2)
    with pytest.raises(fl.NotSyntheticError, match="not one"):
        fl.compute_flow(pairs, "gt", tmp_path / "pool2", dataroot=tmp_path / "real", **KW)


# --------------------------------------------------------------------------------------------
# metrics, files, colours
# --------------------------------------------------------------------------------------------


def test_epe_and_fl_all_on_hand_made_arrays():
    gt = np.zeros((4, 4, 2), np.float32)
    gt[0, :, 0] = 100.0  # top row moves 100 px right
    flow = gt.copy()
    flow[1, 1] = (3.0, 4.0)  # error 5 on a still pixel: outlier
    flow[0, 2] = (104.0, 0.0)  # error 4 > 3 px but < 5 % of 100: not an outlier
    flow[3, 3] = (0.0, 2.0)  # error 2: not an outlier
    assert fl.epe(flow, gt) == pytest.approx((5 + 4 + 2) / 16)
    assert fl.fl_all(flow, gt) == pytest.approx(100 / 16)
    valid = np.ones((4, 4), bool)
    valid[1, 1] = False
    assert fl.epe(flow, gt, valid) == pytest.approx(6 / 15)
    assert fl.fl_all(flow, gt, valid) == 0.0
    box = fl.boxes_mask(np.array([[0.6, 0.2, 2.0, 1.5]]), gt.shape)  # cols 1-2, row 1
    assert box.sum() == 2 and box[1, 1] and box[1, 2]
    assert fl.epe(flow, gt, mask=box) == pytest.approx(2.5)
    assert fl.fl_all(flow, gt, mask=box) == pytest.approx(50.0)
    assert np.isnan(fl.epe(flow, gt, valid, fl.boxes_mask(np.array([[1, 1, 1, 1]]), gt.shape)))
    clipped = fl.boxes_mask([[-5, -5, 1, 100]], gt.shape)
    assert clipped.sum() == 8
    m = fl.flow_metrics(flow, gt, valid, boxes=np.array([[0, 0, 3, 3]]))
    assert m["epe"] == m["epe_boxes"] and m["fl_all_boxes"] == 0.0


# --- mutation-testing kills: thresholds, keys, dtypes and empty selections ---------------


def test_fl_all_thresholds_are_strict_and_use_the_true_magnitude():
    """KITTI's outlier: error > 3 px and > 5 % of |gt|; both strict, |gt| the Euclidean
    norm (a negative component counts as its square)."""
    gt = np.zeros((1, 6, 2), np.float32)
    gt[0, :, 0] = (0, 0, -100, -100, -100, 0)
    flow = gt.copy()
    flow[0, 0] = (3.0, 0.0)  # error exactly 3 on a still pixel: not an outlier
    flow[0, 1] = (3.5, 0.0)  # error 3.5 on a still pixel: an outlier
    flow[0, 2] = (-105.0, 0.0)  # error exactly 5 % of 100 (and > 3): not an outlier
    flow[0, 3] = (-106.0, 0.0)  # error 6 > 5 % of 100: an outlier
    flow[0, 4] = (-104.0, 0.0)  # error 4: > 3 px but < 5 %: not an outlier
    assert fl.fl_all(flow, gt) == pytest.approx(100 * 2 / 6)
    err = fl.endpoint_error(flow, gt)
    assert err.dtype == np.float32 and err.shape == (1, 6)
    np.testing.assert_allclose(err[0], [3, 3.5, 5, 6, 4, 0])


def test_box_bias_averages_the_error_over_each_box_before_its_length():
    """Scatter inside a box cancels, a shift of the whole box does not; invalid pixels are
    left out; boxes count alike whatever their size; no box with a valid pixel is NaN."""
    gt = np.zeros((4, 6, 2), np.float32)
    flow = gt.copy()
    flow[0, 0], flow[0, 1] = (1.0, 0.0), (-1.0, 0.0)  # box A: scatter only, EPE 1
    flow[2:4, 3:6] = (0.0, -2.0)  # box B (3 x 2 px): the whole vehicle shifted 2 px
    flow[3, 5] = (50.0, 50.0)  # ... but this pixel is invalid
    valid = np.ones((4, 6), bool)
    valid[3, 5] = False
    boxes = np.array([[0, 0, 1, 0], [3, 2, 5, 3]])
    assert fl.box_bias(flow, gt, valid, boxes) == pytest.approx((0.0 + 2.0) / 2)
    assert fl.box_bias(flow, gt, valid, boxes[:1]) == pytest.approx(0.0)
    assert fl.epe(flow, gt, valid, fl.boxes_mask(boxes[:1], gt.shape)) == pytest.approx(1.0)
    assert fl.box_bias(flow, gt, None, boxes[1:]) > 10  # the outlier counts when valid
    flow[1, 0] = (0.0, 3.0)  # box A grown to two rows: (1 - 1 + 0 + 0, 3) / 4 px
    assert fl.box_bias(flow, gt, valid, [[0, 0, 1, 1]]) == pytest.approx(0.75)
    assert np.isnan(fl.box_bias(flow, gt, valid, [[5, 3, 5, 3]]))
    assert np.isnan(fl.box_bias(flow, gt, valid, np.zeros((0, 4))))


def test_flow_metrics_keys_masks_and_empty_selections():
    """``flow_metrics`` reports each metric under its name, the valid mask in every metric
    and the boxes in the box metrics; an empty selection is NaN without a warning."""
    import warnings

    gt = np.zeros((4, 4, 2), np.float32)
    flow = gt.copy()
    flow[0, 0] = (10.0, 0.0)  # an outlier outside the box, kept valid
    flow[3, 3] = (0.0, 8.0)  # an outlier outside the box, marked invalid
    flow[2, 1] = (0.0, 4.0)  # an outlier inside the box
    valid = np.ones((4, 4), bool)
    valid[3, 3] = False
    boxes = np.array([[1, 1, 2, 2], [3.2, 0.2, 3.4, 0.4]])  # 2x2 pixels; one with no pixel
    m = fl.flow_metrics(flow, gt, valid, boxes=boxes)
    assert set(m) == {"epe", "fl_all", "epe_boxes", "fl_all_boxes", "bias_boxes"}
    assert m["epe"] == pytest.approx(14 / 15) and m["fl_all"] == pytest.approx(200 / 15)
    assert m["epe_boxes"] == pytest.approx(1.0) and m["fl_all_boxes"] == pytest.approx(25.0)
    assert m["bias_boxes"] == pytest.approx(1.0)  # (0, 4) over the box's 4 pixels
    assert set(fl.flow_metrics(flow, gt)) == {"epe", "fl_all"}
    none = np.zeros((4, 4), bool)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(fl.epe(flow, gt, none)) and np.isnan(fl.fl_all(flow, gt, none))
    with pytest.raises(ValueError, match="^gt must be"):
        fl.epe(flow, gt[..., 0])


def test_boxes_mask_edges_one_pixel_boxes_and_boxes_outside():
    """A box one pixel wide marks that pixel; a box left of or above the image marks
    nothing; several boxes are all marked; the mask is boolean."""
    shape = (5, 6, 2)
    one = fl.boxes_mask([[1, 2, 1, 2]], shape)
    assert one.dtype == bool and one.sum() == 1 and one[2, 1]
    assert fl.boxes_mask([[-10, 1, -3, 3]], shape).sum() == 0
    assert fl.boxes_mask([[1, -10, 3, -3]], shape).sum() == 0
    two = fl.boxes_mask(np.array([[0, 0, 1, 0], [4, 3, 5, 4]]), shape)
    assert two.sum() == 2 + 4 and two[0, :2].all() and two[3:5, 4:6].all()


def test_flow_to_color_fixed_scale_clips_and_keeps_shorter_vectors():
    """With ``max_flow``: a vector longer than it gets the colour of one of exactly that
    length; a shorter one the colour it has beside a vector of that length; ``max_flow``
    must be > 0 and may be below 1 px."""
    flow = np.zeros((1, 3, 2), np.float32)
    flow[0, 0] = (16.0, 0.0)
    flow[0, 1] = (4.0, 0.0)
    ref = flow.copy()
    ref[0, 0] = (8.0, 0.0)
    a, b = fl.flow_to_color(flow, max_flow=8.0), fl.flow_to_color(ref)
    np.testing.assert_array_equal(a, b)
    small = np.zeros((1, 2, 2), np.float32)
    small[0, 0] = (0.8, 0.0)
    small_ref = small.copy()
    small_ref[0, 0] = (0.5, 0.0)
    small_ref[0, 1] = (0.0, 0.0)
    np.testing.assert_array_equal(fl.flow_to_color(small, max_flow=0.5)[0, 0],
                                  fl.flow_to_color(small_ref)[0, 0])
    with pytest.raises(ValueError, match="max_flow=0"):
        fl.flow_to_color(flow, max_flow=0)


def test_flo_round_trip_and_bad_magic(tmp_path):
    flow = np.random.default_rng(0).normal(size=(7, 5, 2)).astype(np.float32)
    fl.write_flo(tmp_path / "a.flo", flow)
    assert (tmp_path / "a.flo").read_bytes()[:4] == b"PIEH"  # 202021.25 as float32
    assert (tmp_path / "a.flo").stat().st_size == 12 + 7 * 5 * 8
    np.testing.assert_array_equal(fl.read_flo(tmp_path / "a.flo"), flow)
    (tmp_path / "bad.flo").write_bytes(b"FLOW" + (tmp_path / "a.flo").read_bytes()[4:])
    with pytest.raises(fl.FlowFileError, match="bad.flo.*magic"):
        fl.read_flo(tmp_path / "bad.flo")
    (tmp_path / "short.flo").write_bytes((tmp_path / "a.flo").read_bytes()[:-8])
    with pytest.raises(fl.FlowFileError, match="short.flo"):
        fl.read_flo(tmp_path / "short.flo")


def test_npy_io_rejects_corrupt_and_pickled(tmp_path):
    flow = np.ones((3, 4, 2), np.float32)
    fl.save_flow_npy(tmp_path / "a.npy", flow)
    assert np.load(tmp_path / "a.npy").dtype == np.float16
    assert fl.load_flow_npy(tmp_path / "a.npy").dtype == np.float32
    (tmp_path / "junk.npy").write_bytes(os.urandom(64))
    with pytest.raises(fl.FlowFileError, match="junk.npy"):
        fl.load_flow_npy(tmp_path / "junk.npy")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(fl.FlowFileError, match="obj.npy"):
        fl.load_flow_npy(tmp_path / "obj.npy")
    np.save(tmp_path / "wrong.npy", np.zeros((3, 4)))
    with pytest.raises(fl.FlowFileError, match="wrong.npy"):
        fl.load_flow_npy(tmp_path / "wrong.npy")


def test_flow_to_color():
    flow = np.zeros((5, 6, 2), np.float32)
    img = fl.flow_to_color(flow)
    assert img.shape == (5, 6, 3) and img.dtype == np.uint8
    assert (img == 255).all()  # no motion is white
    flow[2, 3] = (4.0, 0.0)
    a = fl.flow_to_color(flow, max_flow=8.0)
    flow[0, 0] = (8.0, 0.0)
    b = fl.flow_to_color(flow, max_flow=8.0)
    np.testing.assert_array_equal(a[2, 3], b[2, 3])  # a fixed scale: same vector, same colour
    rgb, bgr = fl.flow_to_color(flow), fl.flow_to_color(flow, bgr=True)
    np.testing.assert_array_equal(bgr, rgb[..., ::-1])


def test_estimator_options_from_a_profile(tmp_path):
    from flowmod.params import validate

    p = validate({"flow_scale": 0.5, "dis_preset": "fast", "device": "cpu",
                  "fastflownet_weights": str(tmp_path / "ffn.pth")})
    assert fl.estimator_options(p, "dis") == {"scale": 0.5, "preset": "fast"}
    assert fl.estimator_options(p, "gt") == {}
    opts = fl.estimator_options(p, "fastflownet")
    assert opts["weights"] == tmp_path / "ffn.pth" and opts["device"] == "cpu"
    assert fl.estimator_options(p, "raft")["weights"] is None
    fl.get_estimator("dis", **fl.estimator_options(p, "dis"))


def test_float16_flow_is_clipped_not_inf(tmp_path):
    flow = np.zeros((4, 5, 2), np.float32)
    flow[1, 2] = [1e6, -1e6]
    fl.save_flow_npy(tmp_path / "f.npy", flow, "float16")
    back = fl.load_flow_npy(tmp_path / "f.npy")
    assert np.isfinite(back).all() and back[1, 2, 0] == 65504.0 and back[1, 2, 1] == -65504.0


def test_flow_stored_at_reduced_scale_loads_at_full_size(tmp_path):
    root, pool = tmp_path / "data", tmp_path / "pool"
    pairs = make_dataroot(root, n=2)
    kw = {"dataroot": root, "dtype": "float32", **KW}
    res = fl.compute_flow(pairs, "farneback", pool, store_scale=0.5, **kw)
    assert list(res["shape"].iloc[0]) == [60, 80, 2], "the index records the full size"
    assert np.load(pool / res["file"].iloc[0]).shape == (30, 40, 2), "a quarter of the disk"
    full = loaded(res, pool, "p0", 0.5)
    assert full.shape == (60, 80, 2)
    direct = fl.get_estimator("farneback").estimate(
        fl.read_image(root / pairs.path_1[0]), fl.read_image(root / pairs.path_2[0]))
    # values stay in full-image pixels: a smooth flow survives the round trip
    assert np.median(np.abs(full - direct)) < 0.1
    assert abs(float(full[..., 0].mean()) - float(direct[..., 0].mean())) < 0.1
    again = fl.compute_flow(pairs, "farneback", pool, store_scale=0.5, **kw)
    assert not again["computed"].any()
    other = fl.compute_flow(pairs, "farneback", pool, store_scale=1.0, **kw)
    assert other["computed"].all(), "another scale is another cache"
    with pytest.raises(ValueError, match="store_scale"):
        fl.compute_flow(pairs, "farneback", pool, store_scale=0.0, **kw)


@pytest.mark.parametrize("scale,dtype", [(1.0, "float16"), (0.5, "float16"), (0.5, "float32")])
def test_roundtrip_equals_storing_and_loading(tmp_path, scale, dtype):
    """The in-memory round trip (used on new frames) gives what the file would, bit for bit."""
    rng = np.random.default_rng(1)
    flow = rng.normal(0, 20, (60, 80, 2)).astype(np.float32)
    fl.store_flow(tmp_path / "f.npy", flow, dtype, scale)
    np.testing.assert_array_equal(fl.store.roundtrip(flow, dtype, scale),
                                  fl.load_stored_flow(tmp_path / "f.npy", scale))
    valid = rng.random((60, 80)) > 0.3  # with a mask (gt): invalid values never leak in
    fl.store_flow(tmp_path / "g.npy", flow, dtype, scale, valid=valid)
    np.testing.assert_array_equal(fl.store.roundtrip(flow, dtype, scale, valid),
                                  fl.load_stored_flow(tmp_path / "g.npy", scale))
    if scale != 1.0:
        assert not np.array_equal(fl.store.roundtrip(flow, dtype, scale, valid),
                                  fl.store.roundtrip(flow, dtype, scale))


def test_flow_metric_errors_name_both_shapes():
    from flowmod.flow import metrics as fm

    a, b = np.zeros((4, 5, 2), np.float32), np.zeros((4, 6, 2), np.float32)
    with pytest.raises(ValueError, match=r"^flow \(4, 5, 2\) and gt \(4, 6, 2\) differ in shape$"):
        fm.endpoint_error(a, b)
    with pytest.raises(ValueError, match=r"^mask shape \(4, 4\) != flow shape \(4, 5\)$"):
        fl.flow_metrics(a, a, np.ones((4, 4), bool))


def test_endpoint_error_is_the_length_of_the_difference_to_the_bit():
    """The two planes squared and added: the same float32 bits as numpy's sum over the last
    axis (the stored accuracy rows and chapter 03's table do not move with the speed-up)."""
    from flowmod.flow.metrics import endpoint_error, fl_all

    rng = np.random.default_rng(3)
    a, b = (rng.normal(0, 7, (45, 80, 2)).astype(np.float32) for _ in range(2))
    d = a - b
    assert np.array_equal(endpoint_error(a, b), np.sqrt((d**2).sum(axis=2)))
    err, mag = np.sqrt((d**2).sum(axis=2)), np.sqrt((b**2).sum(axis=2))
    assert fl_all(a, b) == float(100.0 * ((err > 3.0) & (err > 0.05 * mag)).mean())
