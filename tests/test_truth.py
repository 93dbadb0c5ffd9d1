"""The exact flow's fast path (issue 49, item 3) against the formulation it replaced.

``flowmod.world.truth.fill_undefined`` fills undefined pixels from a window; the reference
below is the whole-frame code it replaced (commit 2950711), verbatim but for names.
Tolerance: none, equal bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

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
    assert all(len(a) == 0 for a in truth.nearest_defined(np.ones((5, 7), bool)))


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
