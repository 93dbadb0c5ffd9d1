"""A geometric baseline without learning: flow residual against a static-world prediction.

If a vehicle were still, the flow at its pixels would be fully explained by the camera's own
motion: back-project a pixel with its depth, move it from camera 1 to camera 2 through the
global frame, project it again. The residual between the measured flow and that prediction
is the vehicle's own image motion; scaled by depth / focal length / time it approximates the
vehicle's speed across the line of sight (m/s). A threshold on it, tuned on the training
split, is the baseline's classifier.

The same prediction over a whole crop window (:func:`static_flow_crop`, depth from the
annotated boxes, the ground plane or a far plane: :func:`scene_depth`) is the static-world
flow that an ego-motion-compensated classifier input subtracts (per object:
:func:`flowmod.crops.static_crops`).

Inputs come from ``pairs.parquet`` (``intrinsic`` 3x3, ``cam2global_1/2`` 4x4, row-major
lists) and ``objects.parquet`` (2D box; the annotated 3D box: global centre, size (w, l, h),
rotation (w, x, y, z)), so no devkit table is read here (pyquaternion, a devkit
dependency, turns the rotation into a matrix).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd


def camera_rays(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(3, N) camera-frame rays with z = 1 through the pixels xy (N, 2) px: a ray times a
    depth (m) is the point at that depth."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return np.linalg.solve(K, np.stack([xy[:, 0], xy[:, 1], np.ones(len(xy))]))


def static_flow(
    xy: np.ndarray, depth: np.ndarray, K: np.ndarray, cam2global_1: np.ndarray,
    cam2global_2: np.ndarray,
) -> np.ndarray:
    """Flow (N, 2) px that static points would have from frame 1 to frame 2.

    xy: (N, 2) pixel coordinates in frame 1; depth: (N,) camera-z depth in m; K: (3, 3);
    cam2global_*: (4, 4) camera-to-global transforms of the two frames.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    depth = np.asarray(depth, dtype=np.float64)
    rays = camera_rays(xy, K)
    p_cam1 = np.vstack([rays * depth, np.ones(len(depth))])  # (4, N)
    p_cam2 = np.linalg.solve(cam2global_2, cam2global_1 @ p_cam1)
    proj = K @ p_cam2[:3]
    xy2 = (proj[:2] / proj[2]).T
    return xy2 - xy


def pair_cameras(row: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K (3, 3), cam2global_1 (4, 4), cam2global_2 (4, 4)) of a pairs.parquet row."""
    return (np.asarray(row["intrinsic"], dtype=float).reshape(3, 3),
            np.asarray(row["cam2global_1"], dtype=float).reshape(4, 4),
            np.asarray(row["cam2global_2"], dtype=float).reshape(4, 4))


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a unit quaternion (w, x, y, z) (the nuScenes convention)."""
    from pyquaternion import Quaternion

    return Quaternion(np.asarray(q, dtype=np.float64)).rotation_matrix


def ray_box_depth(xy: np.ndarray, K: np.ndarray, center_cam: np.ndarray, size_wlh: np.ndarray,
                  rot_cam: np.ndarray) -> np.ndarray:
    """Camera-z depth (m) where the ray through each pixel first meets a 3D box, NaN where
    it misses.

    xy: (N, 2) px; K: (3, 3); the box in camera coordinates: centre (3,) m, size (w, l, h) m
    (nuScenes: x along the length, y across, z up in the box frame) and rotation (3, 3).
    """
    rays = camera_rays(xy, K)
    half = np.array([size_wlh[1], size_wlh[0], size_wlh[2]], dtype=np.float64) / 2
    o = rot_cam.T @ (-np.asarray(center_cam, dtype=np.float64))  # camera origin, box frame
    d = rot_cam.T @ rays  # (3, N)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half[:, None] - o[:, None]) / d
        t2 = (half[:, None] - o[:, None]) / d
    t1 = np.where(np.isnan(t1), -np.inf, t1)
    t2 = np.where(np.isnan(t2), np.inf, t2)
    t_near = np.minimum(t1, t2).max(axis=0)
    t_far = np.maximum(t1, t2).min(axis=0)
    hit = (t_far >= np.maximum(t_near, 0.0)) & (t_near > 0)
    return np.where(hit, t_near, np.nan)  # rays have z = 1: the ray parameter is the depth


def box_in_camera(cam2global: np.ndarray, center_global: np.ndarray, q_global: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A global box pose as (centre (3,), rotation (3, 3)) in a camera with ``cam2global``."""
    g2c = np.linalg.inv(cam2global)
    c = g2c[:3, :3] @ np.asarray(center_global, dtype=np.float64) + g2c[:3, 3]
    return c, g2c[:3, :3] @ quaternion_matrix(q_global)


#: Side of the lattice of points sampled over each 2D box (the flow samples stored with the
#: crops, read by the baseline).
GRID = 9


def box_lattice(box: np.ndarray, grid: int = GRID) -> np.ndarray:
    """(grid * grid, 2) pixel coordinates of a regular lattice over a box xmin, ymin, xmax,
    ymax (corners included), row by row."""
    x0, y0, x1, y1 = np.asarray(box, dtype=np.float64)
    gx, gy = np.meshgrid(np.linspace(x0, x1, grid), np.linspace(y0, y1, grid))
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def box_samples(flow: np.ndarray, boxes: np.ndarray, grid: int = GRID) -> np.ndarray:
    """Flow (N, grid * grid, 2) float32 px at the lattice of each box (nearest pixel,
    clipped to the image): what the baseline needs of a flow field, per object."""
    flow = np.asarray(flow)
    h, w = flow.shape[:2]
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    out = np.empty((len(b), grid * grid, 2), np.float32)
    for i, box in enumerate(b):
        xy = box_lattice(box, grid)
        x = np.clip(np.rint(xy[:, 0]).astype(int), 0, w - 1)
        y = np.clip(np.rint(xy[:, 1]).astype(int), 0, h - 1)
        out[i] = flow[y, x]
    return out


def box_residual(
    samples: np.ndarray, box: np.ndarray, center_global: np.ndarray, K: np.ndarray,
    cam2global_1: np.ndarray, cam2global_2: np.ndarray, dt_s: float,
    size_wlh: np.ndarray | None = None, q_global: np.ndarray | None = None,
) -> tuple[float, float]:
    """Residual of the measured flow on a vehicle against the flow it would have if still.

    samples: (G * G, 2) px, the measured flow at :func:`box_lattice` of the 2D box (xmin,
    ymin, xmax, ymax px); the annotated 3D box at frame 1: global centre (3,) m, size (w, l,
    h) m and global rotation (w, x, y, z). Keeps the lattice points whose ray meets the 3D
    box, each at the depth where it does (:func:`ray_box_depth`), so every sample lies on
    the vehicle at its true depth. Without size/rotation (or if no ray hits) it falls back
    to the box centre's depth at the lattice point nearest the centre. Returns (median
    residual in px, the residual converted to m/s across the line of sight at the vehicle's
    median depth).
    """
    samples = np.asarray(samples, dtype=np.float64)
    grid = int(round(np.sqrt(len(samples))))
    xy = box_lattice(box, grid)
    c_cam, r_cam = (box_in_camera(cam2global_1, center_global, q_global)
                    if q_global is not None else (None, None))
    depth = (ray_box_depth(xy, K, c_cam, np.asarray(size_wlh, dtype=np.float64), r_cam)
             if size_wlh is not None and c_cam is not None else np.full(len(xy), np.nan))
    hit = np.isfinite(depth)
    if not hit.any():
        c = np.linalg.solve(cam2global_1, np.append(np.asarray(center_global, dtype=float), 1.0))
        mid = len(xy) // 2
        xy, depth, samples = xy[mid:mid + 1], np.array([float(c[2])]), samples[mid:mid + 1]
    else:
        xy, depth, samples = xy[hit], depth[hit], samples[hit]
    res = samples - static_flow(xy, depth, K, cam2global_1, cam2global_2)
    res_px = float(np.linalg.norm(np.median(res, axis=0)))
    return res_px, res_px * float(np.median(depth)) / float(K[0, 0]) / dt_s


#: The object columns :func:`residual_scores` reads (size and rotation only where present).
_RESIDUAL_COLUMNS = {"box": ("xmin", "ymin", "xmax", "ymax"),
                     "center": ("center_x", "center_y", "center_z"),
                     "size": ("size_w", "size_l", "size_h"), "q": ("qw", "qx", "qy", "qz")}


def residual_scores(objects: pd.DataFrame, pairs: pd.DataFrame, samples: np.ndarray
                    ) -> pd.DataFrame:
    """Residuals for every object: columns residual_px and residual_speed (m/s).

    samples: (N, G * G, 2) flow at each object's box lattice (:func:`box_samples`, stored
    with the crops), in ``objects``' row order.
    """
    if len(samples) != len(objects):
        raise ValueError(f"{len(samples)} flow samples for {len(objects)} objects")
    p = pairs.set_index("pair_id")
    col = {c: objects[list(cs)].to_numpy(float) for c, cs in _RESIDUAL_COLUMNS.items()
           if set(cs) <= set(objects.columns)}
    with_box = (np.isfinite(col["size"][:, 0]) if "size" in col and "q" in col
                else np.zeros(len(objects), bool))
    out = np.zeros((len(objects), 2))
    for pair_id, idx in objects.groupby("pair_id", sort=False).indices.items():
        row = p.loc[pair_id]
        K, T1, T2 = pair_cameras(row)
        dt = (row["timestamp_2"] - row["timestamp_1"]) / 1e6
        for i in idx:
            box = with_box[i]
            out[i] = box_residual(samples[i], col["box"][i], col["center"][i], K, T1, T2, dt,
                                  col["size"][i] if box else None, col["q"][i] if box else None)
    return pd.DataFrame(out, columns=["residual_px", "residual_speed"], index=objects.index)


# --- the static world over a crop window (ego-motion-compensated input) --------------------

#: Depth (m) given to rays that meet neither an annotated box nor the ground (the sky,
#: the horizon): far enough that only the camera's rotation moves them.
FAR_DEPTH = 1000.0

#: :func:`scene_depth`'s sources: where each ray's depth came from.
BOX, GROUND, FAR = 0, 1, 2


def plane_depth(xy: np.ndarray, K: np.ndarray, cam2global: np.ndarray, z_plane: float
                ) -> np.ndarray:
    """Camera-z depth (m) where the ray through each pixel meets the horizontal global plane
    ``z = z_plane`` (the ground), NaN where it does not (parallel, or behind the camera).

    xy: (N, 2) px; K: (3, 3); cam2global: (4, 4)."""
    rays = camera_rays(xy, K)
    dz = (cam2global[:3, :3] @ rays)[2]  # global height change per metre of depth
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (z_plane - cam2global[2, 3]) / dz
    return np.where(np.isfinite(s) & (s > 0), s, np.nan)


def scene_depth(
    xy: np.ndarray, K: np.ndarray, cam2global: np.ndarray,
    boxes: list[tuple[np.ndarray, np.ndarray, np.ndarray]], ground_z: float,
    far: float = FAR_DEPTH,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth (N,) m of the nearest surface the ray through each pixel meets: an annotated 3D
    box (``boxes``: (centre (3,), size (w, l, h), rotation (3, 3)) in camera coordinates,
    :func:`box_in_camera`), else the ground plane ``z = ground_z`` (global), else ``far``;
    and (N,) int8 of :data:`BOX`, :data:`GROUND`, :data:`FAR` saying which."""
    depth = plane_depth(xy, K, cam2global, ground_z)
    source = np.where(np.isfinite(depth), GROUND, FAR).astype(np.int8)
    depth = np.where(np.isfinite(depth), depth, np.inf)
    for centre, size_wlh, rot in boxes:
        d = ray_box_depth(xy, K, centre, np.asarray(size_wlh, dtype=np.float64), rot)
        nearer = np.isfinite(d) & (d < depth)
        depth[nearer], source[nearer] = d[nearer], BOX
    return np.where(np.isfinite(depth), depth, far), source


def contact_depth(box: np.ndarray, K: np.ndarray, cam2global: np.ndarray, ground_z: float
                  ) -> float:
    """Camera-z depth (m) of a 2D box's ground contact on a flat ground: where the ray
    through the middle of its bottom edge meets ``z = ground_z`` (global); NaN when that
    edge is at or above the horizon. box: (4,) xmin, ymin, xmax, ymax px. What a car can
    compute from a detection and its odometry: no 3D box, no depth sensor."""
    b = np.asarray(box, np.float64)
    xy = np.array([[(b[0] + b[2]) / 2.0, b[3]]])
    return float(plane_depth(xy, K, cam2global, ground_z)[0])


def deployed_depth(xy: np.ndarray, box: np.ndarray, K: np.ndarray, cam2global: np.ndarray,
                   ground_z: float, far: float = FAR_DEPTH) -> np.ndarray:
    """(N,) m: the depth a car could assume at pixels ``xy`` (N, 2): the flat ground (else
    ``far``), and inside the target's 2D ``box`` a surface facing the camera at the box's
    ground-contact depth (:func:`contact_depth`). Other vehicles are not known: ground."""
    depth, _ = scene_depth(xy, K, cam2global, [], ground_z, far)
    d = contact_depth(box, K, cam2global, ground_z)
    if np.isfinite(d):
        b = np.asarray(box, np.float64)
        inside = ((xy[:, 0] >= b[0]) & (xy[:, 0] <= b[2]) & (xy[:, 1] >= b[1])
                  & (xy[:, 1] <= b[3]))
        depth[inside] = d
    return depth


def window_lattice(window: np.ndarray, size: int) -> np.ndarray:
    """(S * S, 2) image px of the pixels of an S x S crop of the square window ``x0, y0, n``
    (:func:`flowmod.crops.crop_windows`), row by row: where the bilinear resize of the
    n x n window samples it (pixel centres aligned, as cv2 ``INTER_LINEAR``)."""
    x0, y0, n = (float(v) for v in window)
    t = (np.arange(size) + 0.5) * n / size - 0.5
    gx, gy = np.meshgrid(x0 + t, y0 + t)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def static_flow_crop(
    window: np.ndarray, size: int, K: np.ndarray, cam2global_1: np.ndarray,
    cam2global_2: np.ndarray, boxes: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    ground_z: float, far: float = FAR_DEPTH, image_size: tuple[int, int] | None = None,
    box2d: np.ndarray | None = None,
) -> np.ndarray:
    """(2, S, S) float32 px: the flow a static world would have at the pixels of a crop of
    ``window``, from the two camera poses and the depth of :func:`scene_depth` (annotated
    boxes of frame 1, the ground, the far plane; all of which real nuScenes has too). The
    classifier's crop minus this is the ego-motion-compensated (residual) input.

    ``image_size`` (width, height) px: where the window leaves the frame, take the flow at
    the nearest pixel of the frame, as the flow crop's edge padding does (so the residual
    there is the frame edge's, not padding minus geometry); None: the geometry everywhere.
    ``box2d`` (4,) px: the deployable variant, depth from the target's 2D box on the flat
    ground (:func:`deployed_depth`) instead of the annotated ``boxes`` (an oracle)."""
    xy = window_lattice(window, size)
    if image_size is not None:
        xy = np.clip(xy, 0.0, [image_size[0] - 1.0, image_size[1] - 1.0])
    if box2d is not None:
        depth = deployed_depth(xy, box2d, K, cam2global_1, ground_z, far)
    else:
        depth, _ = scene_depth(xy, K, cam2global_1, boxes, ground_z, far)
    flow = static_flow(xy, depth, K, cam2global_1, cam2global_2)
    return flow.reshape(size, size, 2).transpose(2, 0, 1).astype(np.float32)

