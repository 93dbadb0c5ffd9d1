"""Motion labels: velocity by the paper's equation 1, and the devkit's views of motion.

Equation 1 of the paper is a forward difference of an instance's global position between the
two keyframes of a pair, over the samples' timestamps::

    velocity = (position_2 - position_1) / (timestamp_2 - timestamp_1)      [m/s]

An object is *moving* (label 1) when ``|velocity| >= threshold`` (2 m/s), else *still* (0).
We use the 3D norm (the vertical component of nuScenes annotations is near zero). Alongside,
the devkit's ``box_velocity`` (a centred difference over the previous and next annotations)
and the annotators' attribute (vehicle.moving / stopped / parked) give two independent views,
compared in :func:`agreement_table`.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

US_PER_S = 1_000_000


def velocity(
    pos1: np.ndarray, pos2: np.ndarray, t1_us: np.ndarray | int, t2_us: np.ndarray | int
) -> np.ndarray:
    """Equation 1: ``(pos2 - pos1) / (t2 - t1)``.

    pos1, pos2: (N, 3) or (3,) global positions, m; t1_us, t2_us: timestamps, integer
    microseconds. Returns velocities in m/s with pos's shape.
    """
    dt = (np.asarray(t2_us, dtype=np.float64) - np.asarray(t1_us, dtype=np.float64)) / US_PER_S
    if np.any(dt <= 0):
        raise ValueError("timestamps must increase from frame 1 to frame 2 (microseconds)")
    pos1, pos2 = np.asarray(pos1, dtype=np.float64), np.asarray(pos2, dtype=np.float64)
    return (pos2 - pos1) / (dt[..., None] if np.ndim(dt) else dt)


def speed(v: np.ndarray) -> np.ndarray:
    """``|v|``, m/s, over the last axis."""
    return np.linalg.norm(np.asarray(v, dtype=np.float64), axis=-1)


def motion_label(speeds: np.ndarray, threshold: float = 2.0) -> np.ndarray:
    """1 (moving) where ``speed >= threshold`` (m/s), else 0 (still); NaN speeds -> -1."""
    s = np.asarray(speeds, dtype=np.float64)
    return np.where(np.isnan(s), -1, s >= threshold).astype(np.int8)


def attribute_motion(attribute: str) -> str:
    """Reduce a nuScenes attribute name to ``moving`` / ``stopped`` / ``parked`` / ``other``."""
    for key in ("moving", "stopped", "parked"):
        if attribute.endswith("." + key):
            return key
    return "other"


def agreement_table(objects: pd.DataFrame) -> pd.DataFrame:
    """Confusion of the eq.-1 label with the devkit attribute and the box_velocity label.

    Rows: label (still / moving); columns: attribute moving / stopped / parked / other and the
    box_velocity label (``box: still`` / ``box: moving`` / ``box: n/a``). Counts of objects.
    """
    lab = objects["label"].map({0: "still", 1: "moving"}).rename("label")
    attr = objects["attribute"].map(attribute_motion).rename("attribute")
    box = pd.Series(
        np.where(objects["box_speed"].isna(), "box: n/a",
                 np.where(objects["box_label"] == 1, "box: moving", "box: still")),
        index=objects.index, name="box_velocity",
    )
    t1 = pd.crosstab(lab, attr)
    t2 = pd.crosstab(lab, box)
    cols1 = [c for c in ("moving", "stopped", "parked", "other") if c in t1.columns]
    cols2 = [c for c in ("box: moving", "box: still", "box: n/a") if c in t2.columns]
    return pd.concat([t1[cols1], t2[cols2]], axis=1).fillna(0).astype(int)


def box_agreement(objects: pd.DataFrame) -> float:
    """Share (%) of objects whose eq.-1 label equals the devkit box_velocity label, among
    those the devkit can give one for."""
    valid = objects["box_label"] >= 0
    return 100.0 * float((objects.loc[valid, "label"] == objects.loc[valid, "box_label"]).mean())


def true_agreement(objects: pd.DataFrame) -> pd.DataFrame:
    """Synthetic world only: eq.-1 label vs the true label at frame 1's time (counts)."""
    if "true_label" not in objects:
        raise KeyError("objects have no true_label column (only a synthetic world knows it)")
    lab = objects["label"].map({0: "still", 1: "moving"}).rename("eq. 1 label")
    true = objects["true_label"].map({0: "still", 1: "moving"}).rename("true label")
    return pd.crosstab(lab, true)


def near_threshold(objects: pd.DataFrame, threshold: float, width: float = 0.5,
                   n: int = 6, seed: int = 0) -> pd.DataFrame:
    """Up to ``n`` objects with ``|speed - threshold| < width`` (m/s), nearest first."""
    near = objects[(objects["speed"] - threshold).abs() < width]
    near = near.sample(min(len(near), 4 * n), random_state=seed)
    return near.assign(gap=(near["speed"] - threshold).abs()).nsmallest(n, "gap")
