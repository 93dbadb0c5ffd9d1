"""Flow accuracy (end-point error, KITTI Fl-all, box masks) and the colour coding of flow."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from flowmod.flow.store import check_flow


def flow_to_color(flow: np.ndarray, max_flow: float | None = None, bgr: bool = False) -> np.ndarray:
    """Colour-code flow (H, W, 2) -> (H, W, 3) uint8 RGB (BGR if ``bgr``), Middlebury wheel.

    Uses ``torchvision.utils.flow_to_image``; saturation is normalised by the largest
    magnitude, or by ``max_flow`` pixels (larger vectors clipped) for comparable images.
    """
    import torch
    from torchvision.utils import flow_to_image

    check_flow(flow)
    f = np.nan_to_num(flow.astype(np.float32))
    h, w = f.shape[:2]
    if max_flow is not None:
        if not max_flow > 0:
            raise ValueError(f"max_flow={max_flow} must be > 0 (pixels)")
        mag = np.linalg.norm(f, axis=2, keepdims=True)
        f = f * np.minimum(1.0, max_flow / np.maximum(mag, 1e-9))
        ref = np.zeros((h, 1, 2), np.float32)
        ref[..., 0] = max_flow  # one extra column fixes the normalisation
        f = np.concatenate([f, ref], axis=1)
    img = flow_to_image(torch.from_numpy(f).permute(2, 0, 1)).permute(1, 2, 0).numpy()[:, :w]
    return np.ascontiguousarray(img[..., ::-1] if bgr else img)


# --------------------------------------------------------------------------------------------
# metrics
# --------------------------------------------------------------------------------------------


def _magnitude(v: np.ndarray) -> np.ndarray:
    """(H, W) float32 length of the (H, W, 2) vectors ``v``: the two planes squared and
    added, bit for bit numpy's sum over the last axis (which is slow on a 2-long axis)."""
    sq = np.square(v.astype(np.float32))
    return np.sqrt(sq[..., 0] + sq[..., 1])


def endpoint_error(flow: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-pixel end-point error (H, W) float32, pixels."""
    check_flow(flow)
    check_flow(gt, "gt")
    if flow.shape != gt.shape:
        raise ValueError(f"flow {flow.shape} and gt {gt.shape} differ in shape")
    return _magnitude(flow.astype(np.float32) - gt.astype(np.float32))


def _select(
    shape: tuple[int, ...], valid: np.ndarray | None, mask: np.ndarray | None
) -> np.ndarray:
    sel = np.ones(shape[:2], bool)
    for m in (valid, mask):
        if m is not None:
            if m.shape != shape[:2]:
                raise ValueError(f"mask shape {m.shape} != flow shape {shape[:2]}")
            sel &= m.astype(bool)
    return sel


def epe(
    flow: np.ndarray,
    gt: np.ndarray,
    valid: np.ndarray | None = None,
    mask: np.ndarray | None = None,
) -> float:
    """Mean end-point error (pixels) over pixels that are ``valid`` and in ``mask`` (both (H, W)
    bool, None = all); NaN if no pixel is selected."""
    err = endpoint_error(flow, gt)
    sel = _select(flow.shape, valid, mask)
    return float(err[sel].mean()) if sel.any() else float("nan")


def fl_all(
    flow: np.ndarray,
    gt: np.ndarray,
    valid: np.ndarray | None = None,
    mask: np.ndarray | None = None,
) -> float:
    """KITTI Fl-all in percent (0-100): share of selected pixels whose end-point error is
    > 3 px AND > 5 % of the true flow magnitude; NaN if no pixel is selected."""
    err = endpoint_error(flow, gt)
    mag = _magnitude(gt)
    outlier = (err > 3.0) & (err > 0.05 * mag)
    sel = _select(flow.shape, valid, mask)
    return float(100.0 * outlier[sel].mean()) if sel.any() else float("nan")


def boxes_mask(boxes: np.ndarray | Sequence[Sequence[float]], shape: tuple[int, ...]) -> np.ndarray:
    """(H, W) bool mask of the pixels inside any of the (N, 4) boxes xmin, ymin, xmax, ymax
    (pixels, inclusive; a pixel is inside when its centre (col, row) is); clipped to the image."""
    h, w = shape[:2]
    mask = np.zeros((h, w), bool)
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    for xmin, ymin, xmax, ymax in b:
        c0, c1 = max(0, math.ceil(xmin)), min(w - 1, math.floor(xmax))
        r0, r1 = max(0, math.ceil(ymin)), min(h - 1, math.floor(ymax))
        if c1 >= c0 and r1 >= r0:
            mask[r0 : r1 + 1, c0 : c1 + 1] = True
    return mask


def box_bias(
    flow: np.ndarray,
    gt: np.ndarray,
    valid: np.ndarray | None,
    boxes: np.ndarray | Sequence[Sequence[float]],
) -> float:
    """The mean over ``boxes`` (N, 4) of the length (px) of each box's mean error: the error
    of ``flow`` (H, W, 2) px against ``gt`` averaged over the box's valid pixels first, so
    scatter about the truth cancels and what is left is the motion the flow adds to, or
    takes from, the whole vehicle (chapter 13: what the classifier reads). Boxes without a
    valid pixel are skipped; NaN if none is left."""
    err = (np.asarray(flow, np.float64) - gt).reshape(-1, 2)
    ok = np.ones(err.shape[0], bool) if valid is None else np.asarray(valid).reshape(-1)
    out = []
    for box in np.asarray(boxes, dtype=np.float64).reshape(-1, 4):
        sel = boxes_mask(box[None], flow.shape).reshape(-1) & ok
        if sel.any():
            out.append(float(np.hypot(*err[sel].mean(axis=0))))
    return float(np.mean(out)) if out else float("nan")


def flow_metrics(
    flow: np.ndarray,
    gt: np.ndarray,
    valid: np.ndarray | None = None,
    boxes: np.ndarray | None = None,
) -> dict[str, float]:
    """EPE (px) and Fl-all (%) overall and, with ``boxes`` (N, 4), inside the boxes, with
    the boxes' :func:`box_bias` (px)."""
    out = {"epe": epe(flow, gt, valid), "fl_all": fl_all(flow, gt, valid)}
    if boxes is not None:
        m = boxes_mask(boxes, flow.shape)
        out["epe_boxes"] = epe(flow, gt, valid, m)
        out["fl_all_boxes"] = fl_all(flow, gt, valid, m)
        out["bias_boxes"] = box_bias(flow, gt, valid, boxes)
    return out


