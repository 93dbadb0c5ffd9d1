"""Beyond the paper: what flow cannot see (the geometry of a vehicle's motion seen from the
camera, F1 and recall broken down by it, and the image signal that motion produces).

A vehicle's velocity splits into a *radial* part, along the line of sight from the camera
(it changes the vehicle's distance, so only the size of its box changes in the image) and a
*lateral* part, across it (the box moves across the image). Over a keyframe gap of ``dt``
seconds, at distance ``Z`` metres, with focal length ``f`` px:

* lateral speed ``v``: the box moves by about ``f v dt / Z`` px;
* radial speed ``v`` on a vehicle ``W`` m wide: its width changes by about
  ``f W (1 / (Z - v dt) - 1 / Z)`` px, i.e. ``f W v dt / Z**2`` to first order.

At 50 m and 2 m/s that is 25 px against 1 px: slow radial movers are where flow is blind.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from flowmod.metrics import breakdown as _breakdown


def motion_geometry(objects: pd.DataFrame, pairs: pd.DataFrame) -> pd.DataFrame:
    """Objects with the geometry of their motion seen from frame 1's camera: ``radial_speed``
    and ``lateral_speed`` (m/s, ground plane; radial positive away from the camera),
    ``motion_angle`` (degrees between the velocity and the line of sight, 0 = straight
    away or towards, 90 = across) and ``box_width_px``."""
    cam = pairs.set_index("pair_id")["cam2global_1"].map(
        lambda m: np.asarray(m, dtype=np.float64).reshape(4, 4)[:3, 3])
    origin = np.stack(objects["pair_id"].map(cam).to_numpy())
    sight = objects[["center_x", "center_y"]].to_numpy(np.float64) - origin[:, :2]
    sight /= np.maximum(np.linalg.norm(sight, axis=1, keepdims=True), 1e-9)
    v = objects[["vx", "vy"]].to_numpy(np.float64)
    radial = (v * sight).sum(axis=1)
    lateral = np.abs(v[:, 0] * sight[:, 1] - v[:, 1] * sight[:, 0])
    angle = np.degrees(np.arctan2(lateral, np.abs(radial)))
    return objects.assign(radial_speed=radial, lateral_speed=lateral, motion_angle=angle,
                          box_width_px=(objects["xmax"] - objects["xmin"]).to_numpy())


#: Movers whose motion is within this angle (deg) of the line of sight count as radial.
RADIAL_MAX_ANGLE = 30.0
#: The ``by`` of :func:`blind_spots`' speed bins over all vehicles, and over the still ones
#: and the movers along the line of sight only.
SPEED, RADIAL_SPEED = "speed (m/s)", f"speed (m/s), movers within {RADIAL_MAX_ANGLE:g} deg " \
    "of the line of sight"
SPEED_BINS = [0, 2, 3, 5, 10, 40]


def blind_spots(df: pd.DataFrame, probs: np.ndarray, groups: np.ndarray) -> pd.DataFrame:
    """F1 and recall of the moving vehicles by the angle of their motion to the line of
    sight, their speed (of all; of the radial movers, :data:`RADIAL_SPEED`), distance and
    box size (scene-level intervals, counts): one table with a ``by`` column. ``df``:
    predictions with the columns of :func:`motion_geometry`; probs: (S, N)."""
    specs = [("motion_angle", [0, 15, 30, 60, 90.01], "angle to the line of sight (deg)"),
             ("speed", SPEED_BINS, SPEED),
             ("distance", [30, 40, 50, 60, 70.01], "distance (m)"),
             ("box_width_px", [0, 20, 40, 80, 2000], "box width (px)")]
    label = df["label"].to_numpy()
    radial = (label == 0) | (df["motion_angle"].to_numpy() < RADIAL_MAX_ANGLE)
    probs, groups = np.asarray(probs), np.asarray(groups)
    out = []
    for col, bins, name in [*specs, ("speed", SPEED_BINS, RADIAL_SPEED)]:
        k = radial if name == RADIAL_SPEED else np.ones(len(df), bool)
        t = _breakdown(df[k], df["label"][k], probs[:, k], by=col, bins=bins, groups=groups[k])
        out.append(t.rename(columns={f"{col}_bin": "bin"}).assign(by=name))
    cols = ["by", "bin", "n", "n_moving", "precision", "recall", "f1", "ci_lo", "ci_hi",
            "scenes"]
    return pd.concat(out, ignore_index=True)[cols]


def physical_signal(focal_px: float, dt_s: float, distances_m=(30.0, 50.0, 70.0),
                    speed_m_s: float = 2.0, width_m: float = 1.9,
                    flow_scale: float = 1.0) -> pd.DataFrame:
    """The image signal of a ``speed_m_s`` mover over ``dt_s`` at each distance: lateral
    displacement of its box (px) and the change of its box width when it moves radially
    (px, away from the camera), in full-image pixels and at ``flow_scale``."""
    rows = []
    for z in distances_m:
        d = speed_m_s * dt_s
        lateral = focal_px * d / z
        radial = focal_px * width_m * (1 / z - 1 / (z + d))
        rows.append({"distance (m)": z, "lateral shift (px)": lateral,
                     "radial: width change (px)": radial,
                     f"lateral at flow_scale {flow_scale:g} (px)": lateral * flow_scale,
                     f"radial at flow_scale {flow_scale:g} (px)": radial * flow_scale})
    return pd.DataFrame(rows)


def recall_slow_and_fast(blind: pd.DataFrame, by: str = RADIAL_SPEED) -> tuple[float, float]:
    """Recall of the moving vehicles just above the threshold (2-3 m/s) and of those at 5
    m/s or more (NaN where a bin holds no mover), from a :func:`blind_spots` table; ``by``:
    of the movers along the line of sight (:data:`RADIAL_SPEED`) or of all (:data:`SPEED`)."""
    a = blind[blind["by"] == by].set_index("bin")

    def rec(bins: tuple[str, ...]) -> float:
        rows = a[a.index.isin(bins) & (a["n_moving"] > 0)]
        if not len(rows):
            return float("nan")
        return float((rows["recall"] * rows["n_moving"]).sum() / rows["n_moving"].sum())

    return rec(("[2, 3)",)), rec(("[5, 10)", "[10, 40)"))
