"""The exact flow's fast path (issue 49, item 3) against the formulation it replaced.

``flowmod.world.truth.flow_between`` works in row blocks, renders each frame once for
consecutive pairs and fills undefined pixels from a window; the reference below is the
whole-frame code it replaced (commit 2950711), verbatim but for names. Tolerance: none. The
flow (float32 px) and the valid mask must be equal bit for bit on every pixel, so the
crops read from them are equal too.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from flowmod.crops import pair_crops
from flowmod.world import geometry as wg
from flowmod.world import render as wr
from flowmod.world import truth


def _reference_fill(flow: np.ndarray, defined: np.ndarray) -> np.ndarray:
    """The replaced ``fill_undefined``: the whole frame's Euclidean feature transform."""
    flow = np.asarray(flow, dtype=np.float64)
    if defined.all():
        return flow.astype(np.float32)
    if not defined.any():
        return np.zeros(flow.shape, np.float32)
    iy, ix = distance_transform_edt(~defined, return_distances=False, return_indices=True)
    return flow[iy, ix].astype(np.float32)


def _reference_flow(geo, t1: float, t2: float) -> tuple[np.ndarray, np.ndarray]:
    """The replaced ``flow_between``: two fresh renders, the whole frame at once."""
    f1 = wr.render(geo, t1, textured=False)
    f2 = wr.render(geo, t2, textured=False)
    H, W = wg.H_IMG, wg.W_IMG
    K = f1.K

    def T(R, t):
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = R, t
        return m

    T_w1 = T(f1.R_wc, f1.c)
    T_2w = np.linalg.inv(T(f2.R_wc, f2.c))
    P2 = K @ np.eye(3, 4)

    def A(motion):
        return P2 @ T_2w @ motion @ T_w1

    rays = wg.pixel_rays(K)
    rho = f1.invz.ravel().astype(np.float64)
    sid = f1.sid.ravel()
    a0 = A(np.eye(4))
    p = a0[:, :3] @ rays + a0[:, 3:4] * rho[None, :]
    counts = np.bincount(sid, minlength=wg.SID_AGENT0 + len(geo.agents))
    for i in range(len(geo.agents)):
        s = wg.SID_AGENT0 + i
        if counts[s] == 0:
            continue
        R1, c1 = geo.agent_pose(i, t1)
        R2, c2 = geo.agent_pose(i, t2)
        motion = T(R2, c2) @ np.linalg.inv(T(R1, c1))
        idx = np.flatnonzero(sid == s)
        ai = A(motion)
        p[:, idx] = ai[:, :3] @ rays[:, idx] + ai[:, 3:4] * rho[None, idx]
    z = p[2]
    front = z > 1e-9
    zs = np.where(front, z, 1.0)
    u2 = p[0] / zs
    v2 = p[1] / zs
    vv, uu = np.divmod(np.arange(H * W), W)
    du, dv = u2 - uu, v2 - vv
    iz_pt = np.where(front, rho / zs, 0.0)
    defined = (front & (iz_pt <= 1.0 / truth.NEAR_FLOW_M)
               & (np.hypot(du, dv) <= truth.MAX_FLOW_PX))
    inside = defined & (u2 >= -0.5) & (u2 <= W - 0.5) & (v2 >= -0.5) & (v2 <= H - 0.5)
    ui = np.clip(np.round(np.where(defined, u2, 0.0)), 0, W - 1).astype(np.int64)
    vi = np.clip(np.round(np.where(defined, v2, 0.0)), 0, H - 1).astype(np.int64)
    tgt = vi * W + ui
    iz_buf = f2.invz.ravel()[tgt].astype(np.float64)
    sid_buf = f2.sid.ravel()[tgt]
    same = sid_buf == sid
    occluded = np.where(same, iz_buf > iz_pt * 1.02 + 6e-4, iz_buf > iz_pt * 1.003 + 1e-5)
    valid = inside & ~occluded
    flow = np.stack([du, dv], axis=1).reshape(H, W, 2)
    return _reference_fill(flow, defined.reshape(H, W)), valid.reshape(H, W)


def _pairs(root, version, n_scenes: int = 2) -> list[tuple[object, float, float]]:
    """(geometry, t1, t2) of the first scenes' consecutive keyframes, in order (as the flow
    stage meets them: each frame shared by two pairs), and one pair backwards in time."""
    key = truth._world_key(root, version)
    out = []
    for si, sc in enumerate(truth.load_world(*key)["scenes"][:n_scenes]):
        geo = truth._geometry(*key, si)
        ts = [(f["ts"] - sc["t0_us"]) / 1e6 for f in sc["frames"]]
        out += [(geo, a, b) for a, b in zip(ts[:-1], ts[1:], strict=True)]
    return [*out, (out[0][0], out[1][2], out[0][1])]


def test_exact_flow_fast_path_equals_the_reference_bit_for_bit(smoke_world):
    """Every pixel's flow and validity equal the replaced code's on the smoke world's
    consecutive keyframe pairs and one backward pair (agents in them), and so do the crops
    of every agent's box; a second call (frames from the render cache) gives the same."""
    root, version = smoke_world
    truth._depth_frame.cache_clear()
    seen_agents = 0
    for geo, t1, t2 in _pairs(root, version):
        ref_flow, ref_valid = _reference_flow(geo, t1, t2)
        flow, valid = truth.flow_between(geo, t1, t2)
        assert flow.dtype == np.float32 and flow.shape == ref_flow.shape
        assert np.array_equal(valid, ref_valid), f"valid differs on {(valid != ref_valid).sum()} px"
        diff = np.abs(flow - ref_flow)
        assert np.array_equal(flow, ref_flow), f"flow differs: max {diff.max()} px"
        fr = wr.render(geo, t1, textured=False)
        boxes = [(u.min(), v.min(), u.max() + 1, v.max() + 1)
                 for s in np.unique(fr.sid[fr.sid >= wg.SID_AGENT0])
                 for v, u in [np.nonzero(fr.sid == s)]]
        if boxes:
            b = np.asarray(boxes, np.float64)
            assert np.array_equal(pair_crops(flow, b, 40, 3.0)[0],
                                  pair_crops(ref_flow, b, 40, 3.0)[0])
        seen_agents += len(boxes) > 0
        again = truth.flow_between(geo, t1, t2)
        assert np.array_equal(again[0], flow) and np.array_equal(again[1], valid)
    assert seen_agents >= 3


def test_flow_between_fills_undefined_pixels_like_the_reference(smoke_world):
    """A pair whose flow is undefined somewhere (the ground near the camera passes behind
    it): the filled values equal the whole-frame feature transform's."""
    root, version = smoke_world
    key = truth._world_key(root, version)
    for si, sc in enumerate(truth.load_world(*key)["scenes"]):
        geo = truth._geometry(*key, si)
        ts = [(f["ts"] - sc["t0_us"]) / 1e6 for f in sc["frames"]]
        f1, f2 = truth._depth_frame(geo, ts[0]), truth._depth_frame(geo, ts[-1])
        pg = truth._pair_geometry(geo, f1, f2, ts[0], ts[-1])
        n = wg.H_IMG * wg.W_IMG
        flow, defined, valid = np.empty((n, 2), np.float32), np.empty(n, bool), np.empty(n, bool)
        truth._flow_rows(pg, 0, wg.H_IMG, flow, defined, valid)
        defined = defined.reshape(wg.H_IMG, wg.W_IMG)
        if not defined.all():
            flow = flow.reshape(wg.H_IMG, wg.W_IMG, 2)
            assert np.array_equal(truth.fill_undefined(flow, defined),
                                  _reference_fill(flow, defined))
            assert np.array_equal(truth.flow_between(geo, ts[0], ts[-1])[0],
                                  _reference_flow(geo, ts[0], ts[-1])[0])
            return
    pytest.fail("no pair of the smoke world has undefined flow: the fill is not exercised")


@pytest.mark.parametrize("seed", range(4))
def test_nearest_defined_equals_the_whole_frame_feature_transform(seed):
    """The window (the undefined pixels' bounding box grown by 1 px) gives scipy's
    whole-map answer, its choice among equidistant pixels included: random boxes, speckle
    and bands on maps of any size."""
    rng = np.random.default_rng(seed)
    for _ in range(60):
        H, W = rng.integers(20, 160, size=2)
        undefined = np.zeros((H, W), bool)
        for _ in range(rng.integers(1, 5)):
            y, x = rng.integers(0, H), rng.integers(0, W)
            undefined[y : y + rng.integers(1, 50), x : x + rng.integers(1, 50)] = True
        if rng.random() < 0.5:
            undefined |= rng.random((H, W)) < rng.choice([0.01, 0.3, 0.8])
        if rng.random() < 0.3:
            undefined[-rng.integers(1, H):] = True  # a band at the bottom, as the ground's
        if undefined.all() or not undefined.any():
            continue
        iy, ix = distance_transform_edt(undefined, return_distances=False, return_indices=True)
        ys, xs = np.nonzero(undefined)
        got = truth.nearest_defined(~undefined)
        for a, b in zip(got, (ys, xs, iy[ys, xs], ix[ys, xs]), strict=True):
            np.testing.assert_array_equal(a, b)
    # nothing undefined: four empty index arrays, integer like the others (float indices
    # raise even when empty)
    assert all(len(a) == 0 and a.dtype == np.int64
               for a in truth.nearest_defined(np.ones((5, 7), bool)))


def test_fill_undefined_equals_the_whole_frame_fill():
    """Random flow (float64, as the exact flow's arithmetic) with undefined bands, boxes,
    speckle, none and all: the same float32 values as the replaced fill."""
    rng = np.random.default_rng(7)
    flow = rng.normal(0, 50, (90, 160, 2))
    undefined = np.zeros((90, 160), bool)
    undefined[70:], undefined[20:45, 100:130] = True, True
    masks = [undefined, undefined | (rng.random((90, 160)) < 0.2),
             np.zeros((90, 160), bool), np.ones((90, 160), bool)]
    for und in masks:
        got = truth.fill_undefined(flow, ~und)
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, _reference_fill(flow, ~und))
