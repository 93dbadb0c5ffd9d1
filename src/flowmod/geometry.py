"""A geometric baseline without learning: flow residual against a static-world prediction.

If a vehicle were still, the flow at its pixels would be fully explained by the camera's own
motion: back-project a pixel with its depth, move it from camera 1 to camera 2 through the
global frame, project it again. The residual between the measured flow and that prediction
is the vehicle's own image motion; scaled by depth / focal length / time it approximates the
vehicle's speed across the line of sight (m/s). A threshold on it, tuned on the training
split, is the baseline's classifier.

Inputs come from ``pairs.parquet`` (``intrinsic`` 3x3, ``cam2global_1/2`` 4x4, row-major
lists) and ``objects.parquet`` (2D box, global box centre), so no devkit is needed here.
"""

from __future__ import annotations

import numpy as np
import pandas as pd


def static_flow(
    xy: np.ndarray, depth: np.ndarray, K: np.ndarray, cam2global_1: np.ndarray,
    cam2global_2: np.ndarray,
) -> np.ndarray:
    """Flow (N, 2) px that static points would have from frame 1 to frame 2.

    xy: (N, 2) pixel coordinates in frame 1; depth: (N,) camera-z depth in m; K: (3, 3);
    cam2global_*: (4, 4) camera-to-global transforms of the two frames.
    """
    xy = np.asarray(xy, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    ones = np.ones(len(xy))
    rays = np.linalg.solve(K, np.stack([xy[:, 0], xy[:, 1], ones]))  # (3, N), z = 1
    p_cam1 = np.vstack([rays * depth, ones])  # (4, N)
    p_cam2 = np.linalg.solve(cam2global_2, cam2global_1 @ p_cam1)
    proj = K @ p_cam2[:3]
    xy2 = (proj[:2] / proj[2]).T
    return xy2 - xy


def _sample(flow: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Nearest-pixel flow values (N, 2) at ``xy`` (N, 2), clipped to the image."""
    h, w = flow.shape[:2]
    x = np.clip(np.rint(xy[:, 0]).astype(int), 0, w - 1)
    y = np.clip(np.rint(xy[:, 1]).astype(int), 0, h - 1)
    return flow[y, x].astype(np.float64)


def box_residual(
    flow: np.ndarray, box: np.ndarray, center_global: np.ndarray, K: np.ndarray,
    cam2global_1: np.ndarray, cam2global_2: np.ndarray, dt_s: float, grid: int = 7,
    inner: float = 0.6,
) -> tuple[float, float]:
    """Residual of the measured flow inside a box against the static prediction.

    flow: (H, W, 2) px; box: (4,) xmin, ymin, xmax, ymax px; center_global: (3,) m. Samples a
    ``grid`` x ``grid`` lattice over the central ``inner`` fraction of the box (to stay on the
    vehicle), all at the depth of the box centre. Returns (median residual in px, the
    residual converted to m/s across the line of sight).
    """
    x0, y0, x1, y1 = np.asarray(box, dtype=np.float64)
    cx, cy, hw, hh = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) * inner / 2, (y1 - y0) * inner / 2
    gx, gy = np.meshgrid(np.linspace(cx - hw, cx + hw, grid), np.linspace(cy - hh, cy + hh, grid))
    xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
    c = np.linalg.solve(cam2global_1, np.append(np.asarray(center_global, dtype=float), 1.0))
    depth = float(c[2])
    pred = static_flow(xy, np.full(len(xy), depth), K, cam2global_1, cam2global_2)
    res = _sample(flow, xy) - pred
    res_px = float(np.linalg.norm(np.median(res, axis=0)))
    return res_px, res_px * depth / float(K[0, 0]) / dt_s


def residual_scores(
    objects: pd.DataFrame, pairs: pd.DataFrame, load_flow, grid: int = 7
) -> pd.DataFrame:
    """Residuals for every object: columns residual_px and residual_speed (m/s).

    ``load_flow(pair_id) -> (H, W, 2)`` reads a pair's flow; each flow is read once.
    """
    p = pairs.set_index("pair_id")
    out = np.zeros((len(objects), 2))
    for pair_id, idx in objects.groupby("pair_id", sort=False).indices.items():
        row = p.loc[pair_id]
        flow = load_flow(pair_id)
        K = np.asarray(row["intrinsic"], dtype=float).reshape(3, 3)
        T1 = np.asarray(row["cam2global_1"], dtype=float).reshape(4, 4)
        T2 = np.asarray(row["cam2global_2"], dtype=float).reshape(4, 4)
        dt = (row["timestamp_2"] - row["timestamp_1"]) / 1e6
        for i in idx:
            o = objects.iloc[i]
            out[i] = box_residual(
                flow, o[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float),
                o[["center_x", "center_y", "center_z"]].to_numpy(float), K, T1, T2, dt, grid,
            )
    return pd.DataFrame(out, columns=["residual_px", "residual_speed"], index=objects.index)
