"""Selection of frame pairs and target vehicles over the official nuscenes-devkit (Table 1).

The same code runs on the synthetic world and on real nuScenes (v1.0-mini, v1.0-trainval).

Keyframe set (the paper): consecutive CAM_FRONT keyframes of scenes whose description has no
item equal to night, rain or lightning; in each pair, vehicles of the seven Table-1 categories
with visibility token '4' (80-100 %), all 8 box corners in front of the camera and inside the
image (``BoxVisibility.ALL``), at a distance in [min_distance, max_distance], and the same
instance qualifying in both frames. Distance (``distance_mode``): ``ego`` = 3D norm from the
ego-pose origin of the frame to the box centre (the original code's definition), ``camera`` =
from the camera centre. 2D box = min/max of the 8 projected corners (equal to the devkit's
``export_2d_annotations_as_json`` box for fully visible boxes).

Generalisation set (the paper's section IV-D): in held-out scenes, every CAM_FRONT frame
(keyframes and sweeps) paired with the frame ``general_interval`` frames later; boxes from
the devkit's interpolated 3D boxes; near vehicles included; the paper's label is that of the
closest previous keyframe.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from pyquaternion import Quaternion

from flowmod import dag, labels, world
from flowmod.artefacts import atomic_path
from flowmod.params import Params
from flowmod.progress import bar

if TYPE_CHECKING:  # the devkit is imported where it is used (1-2 s: matplotlib, sklearn)
    from nuscenes.nuscenes import NuScenes

TABLES = (
    "attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map",
    "sample", "sample_annotation", "sample_data", "scene", "sensor", "visibility",
)
CAMERA = "CAM_FRONT"
SPLITS = ("train", "val", "test")

class SelectionError(ValueError):
    """Bad or empty input to the selection; the message names the thing and the fix."""


# --- input checks ------------------------------------------------------------------------

def check_dataroot(dataroot: str | Path, version: str) -> Path:
    """Check that ``dataroot/version`` holds the 13 nuScenes tables, before loading anything."""
    root = Path(dataroot)
    if not root.is_dir():
        raise SelectionError(
            f"dataroot {root} does not exist: give the folder that holds samples/, sweeps/ and "
            f"{version}/ (for the synthetic world, set synthetic: true to generate it)"
        )
    vdir = root / version
    if not vdir.is_dir():
        found = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("v"))
        raise SelectionError(
            f"version folder {vdir} not found; version folders in {root}: {found or 'none'} "
            "(set the `version` parameter to one of them)"
        )
    missing = [t for t in TABLES if not (vdir / f"{t}.json").is_file()]
    if missing:
        raise SelectionError(f"{vdir} lacks tables: {', '.join(missing)} (.json)")
    return vdir


def open_nuscenes(dataroot: str | Path, version: str) -> NuScenes:
    """Load the devkit's ``NuScenes`` after :func:`check_dataroot` (quietly). The last one
    loaded is reused while no table file of the version changed (size and mtime)."""
    vdir = check_dataroot(dataroot, version)
    stamp = tuple((f.name, f.stat().st_size, f.stat().st_mtime_ns)
                  for f in sorted(vdir.glob("*.json")))
    return _load_nuscenes(str(Path(dataroot).resolve()), version, stamp)


def as_nuscenes(nusc_or_dataroot: Any, version: str) -> NuScenes:
    """``nusc_or_dataroot`` itself when it is a loaded ``NuScenes``, else
    :func:`open_nuscenes` of that dataroot."""
    if isinstance(nusc_or_dataroot, (str, os.PathLike)):
        return open_nuscenes(nusc_or_dataroot, version)
    return nusc_or_dataroot


@lru_cache(maxsize=1)
def _load_nuscenes(dataroot: str, version: str, stamp: tuple) -> NuScenes:
    from nuscenes.nuscenes import NuScenes  # here: the devkit costs ~1 s to import

    return NuScenes(version=version, dataroot=dataroot, verbose=False)


def check_images(dataroot: str | Path, paths: Iterable[str]) -> list[str]:
    """Relative image paths under ``dataroot`` that do not exist (in the given order)."""
    root = Path(dataroot)
    return [p for p in dict.fromkeys(paths) if not (root / p).is_file()]


# --- scenes ------------------------------------------------------------------------------

def description_items(description: str) -> list[str]:
    """``"Night, after rain, peds"`` -> ``["night", "after rain", "peds"]``."""
    return [s.strip().lower() for s in description.split(",") if s.strip()]


def scene_table(nusc) -> pd.DataFrame:
    """One row per scene: scene, token, description, n_samples, has_sweeps, excluded_by."""
    rows = []
    for sc in nusc.scene:
        first = nusc.get("sample", sc["first_sample_token"])
        sd = nusc.get("sample_data", first["data"][CAMERA])
        nxt = nusc.get("sample_data", sd["next"]) if sd["next"] else None
        rows.append({
            "scene": sc["name"], "scene_token": sc["token"], "log_token": sc["log_token"],
            "description": sc["description"],
            "n_samples": sc["nbr_samples"],
            "has_sweeps": bool(nxt is not None and not nxt["is_key_frame"]),
        })
    return pd.DataFrame(rows)


def filter_scenes(scenes: pd.DataFrame, exclude: Iterable[str]) -> pd.DataFrame:
    """Add ``excluded_by``: the first description item found in ``exclude`` (``""`` = kept).

    Whole items are matched, so "after rain" is kept while "rain" is excluded.
    """
    bad = {e.strip().lower() for e in exclude}
    out = scenes.copy()
    out["excluded_by"] = [
        next((item for item in description_items(d) if item in bad), "")
        for d in out["description"]
    ]
    return out


def _group_members(scenes: Iterable[str], groups: dict[str, str] | None
                   ) -> tuple[list[str], dict[str, list[str]], list[str]]:
    """(sorted scenes, group -> its scenes, sorted group names); without ``groups`` each
    scene is its own group."""
    scenes = sorted(scenes)
    members: dict[str, list[str]] = {}
    for s in scenes:
        members.setdefault((groups or {}).get(s, s), []).append(s)
    return scenes, members, sorted(members)


def split_scenes(
    scenes: list[str], fractions: list[float], seed: int, prefer_test: Iterable[str] = (),
    groups: dict[str, str] | None = None,
) -> dict[str, str]:
    """Assign each scene to train / val / test, seeded, keeping every *group* of scenes
    (``groups``: scene -> group, e.g. its log) in one split; without groups each scene is
    its own group.

    Split sizes are counted in scenes (at least one scene each in val and test when there
    are three or more groups). Groups holding a scene of ``prefer_test`` (those that carry
    sweeps, for the generalisation stage) fill the test split first; when every scene is
    preferred (real nuScenes) this is a plain shuffle.
    """
    rng = np.random.default_rng(seed)
    scenes, members, names = _group_members(scenes, groups)
    n = len(scenes)
    n_test = int(round(fractions[2] * n))
    n_val = int(round(fractions[1] * n))
    if len(names) >= 3:
        n_test, n_val = max(n_test, 1), max(n_val, 1)
    preferred = set(prefer_test)
    first = [g for g in names if preferred & set(members[g])]
    rest = [g for g in names if g not in set(first)]
    order = list(rng.permutation(first)) + list(rng.permutation(rest))
    out = {s: "train" for s in scenes}
    test: list[str] = []
    for g in order:
        if sum(len(members[x]) for x in test) >= n_test:
            break
        test.append(g)
    remaining = list(rng.permutation([g for g in names if g not in set(test)]))
    val: list[str] = []
    for g in remaining:
        if sum(len(members[x]) for x in val) >= n_val or len(val) == len(remaining) - 1:
            break
        val.append(g)
    for g in val:
        out.update({s: "val" for s in members[g]})
    for g in test:
        out.update({s: "test" for s in members[g]})
    return out


def assign_folds(
    scenes: list[str], folds: int, val_share: float, seed: int, spread: Iterable[str] = (),
    groups: dict[str, str] | None = None,
) -> dict[str, tuple[int, bool]]:
    """Cross-validation over scenes: each scene's fold (0 .. folds-1) and whether it is a
    validation scene (when its fold is not the one being tested). Returns scene -> (fold, val).

    Every *group* of scenes (``groups``: scene -> group, e.g. its log) stays in one fold.
    Groups holding a scene of ``spread`` (scenes with sweeps) are dealt out first, so that
    every fold gets its share of them; each group goes to the fold with the fewest scenes so
    far (ties: the lower fold). In each fold a seeded ``val_share`` of its groups (at least
    one where the fold has two or more) are validation scenes: fold k's model trains on the
    other folds' remaining scenes, chooses its epoch on their validation scenes and is scored
    once on fold k.
    """
    rng = np.random.default_rng(seed)
    scenes, members, names = _group_members(scenes, groups)
    if len(names) < folds:
        raise SelectionError(
            f"folds={folds} but the kept scenes form only {len(names)} independent group(s): "
            "use fewer folds or more scenes")
    preferred = set(spread)
    first = [g for g in names if preferred & set(members[g])]
    rest = [g for g in names if g not in set(first)]
    sizes = [0] * folds
    of_fold: dict[int, list[str]] = {k: [] for k in range(folds)}
    for g in [*rng.permutation(first), *rng.permutation(rest)]:
        k = int(np.argmin(sizes))
        of_fold[k].append(str(g))
        sizes[k] += len(members[g])
    out: dict[str, tuple[int, bool]] = {}
    for k, gs in of_fold.items():
        n_val = max(1, int(round(val_share * len(gs)))) if len(gs) >= 2 else 0
        val = set(rng.permutation(gs)[:n_val]) if n_val else set()
        out.update({s: (k, g in val) for g in gs for s in members[g]})
    return out


def fold_roles(df: pd.DataFrame, fold: int, folds: int) -> np.ndarray:
    """The role (``train``, ``val``, ``test``) of each row of ``df`` (scenes, pairs or
    objects with columns split, fold, val_scene) for the model of ``fold``. One fold is the
    paper's single split (the ``split`` column); with cross-validation fold k tests its own
    scenes and validates on the other folds' validation scenes."""
    if folds == 1:
        return df["split"].astype(str).to_numpy()
    k = df["fold"].to_numpy()
    return np.where(k == fold, "test", np.where(df["val_scene"].to_numpy(bool), "val", "train"))


def with_folds(df: pd.DataFrame, scenes: pd.DataFrame) -> pd.DataFrame:
    """``df`` (pairs or objects, column scene) with its scenes' ``fold`` and ``val_scene``."""
    if not len(df):
        return df
    by = scenes.set_index("scene")
    return df.assign(fold=df["scene"].map(by["fold"]).astype(int),
                     val_scene=df["scene"].map(by["val_scene"]).astype(bool))


def _scene_split(p: Params, kept: pd.DataFrame, unit: str) -> pd.DataFrame:
    """(split, fold, val_scene) per kept scene: the paper's single seeded split (folds 1) or
    the cross-validation folds (split ``f<k>``)."""
    groups = dict(zip(kept["scene"], kept["scene" if unit == "scene" else "log_token"],
                      strict=True))
    sweeps = kept.loc[kept["has_sweeps"], "scene"]
    if p.folds == 1:
        split = split_scenes(list(kept["scene"]), p.split_fractions, p.seed,
                             prefer_test=sweeps, groups=groups)
        empty = [s for s in SPLITS if s not in set(split.values())]
        if empty:
            raise SelectionError(
                f"split(s) {empty} got no scene: {len(kept)} kept scenes in "
                f"{len(set(groups.values()))} {unit}(s) cannot fill train, val and test "
                f"(split_fractions={p.split_fractions}); use more scenes or other fractions")
        return pd.DataFrame({"split": split, "fold": 0,
                             "val_scene": {s: v == "val" for s, v in split.items()}})
    f_train, f_val, _ = p.split_fractions
    folds = assign_folds(list(kept["scene"]), p.folds, f_val / max(f_train + f_val, 1e-9),
                         p.seed, spread=sweeps, groups=groups)
    return pd.DataFrame({"split": {s: f"f{k}" for s, (k, _) in folds.items()},
                         "fold": {s: k for s, (k, _) in folds.items()},
                         "val_scene": {s: v for s, (_, v) in folds.items()}})


# --- frames and boxes --------------------------------------------------------------------

def camera_frames(nusc, scene_token: str, keyframes_only: bool) -> list[dict]:
    """The scene's CAM_FRONT sample_data records in time order."""
    sc = nusc.get("scene", scene_token)
    first = nusc.get("sample", sc["first_sample_token"])
    sd = nusc.get("sample_data", first["data"][CAMERA])
    frames = []
    while True:
        if sd["is_key_frame"] or not keyframes_only:
            frames.append(sd)
        if not sd["next"]:
            break
        sd = nusc.get("sample_data", sd["next"])
    return frames


def box_2d(corners_img: np.ndarray) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) px from projected corners ``(2 or 3, 8)``."""
    return (float(corners_img[0].min()), float(corners_img[1].min()),
            float(corners_img[0].max()), float(corners_img[1].max()))


@dataclass(frozen=True)
class Candidate:
    """A vehicle that qualifies in one frame."""

    ann_token: str
    category: str
    distance: float
    box: tuple[float, float, float, float]
    center: tuple[float, float, float]
    #: (w, l, h) m and the global orientation quaternion (w, x, y, z) at this frame's time
    size: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)


def qualifying_boxes(
    nusc, sd: dict, categories: set[str], min_d: float, max_d: float, distance_mode: str,
    visibility: set[str] | None,
) -> dict[str, Candidate]:
    """Instances of ``sd``'s frame that pass Table 1: instance token -> :class:`Candidate`.

    ``visibility`` None skips the visibility check. Boxes come from the devkit
    (``get_sample_data`` with ``BoxVisibility.ALL``: all corners in front and inside the image;
    interpolated for sweeps).
    """
    from nuscenes.utils.geometry_utils import BoxVisibility, view_points

    _, boxes, K = nusc.get_sample_data(sd["token"], box_vis_level=BoxVisibility.ALL)
    if not boxes:
        return {}
    cam2global = camera_to_global(nusc, sd)
    if distance_mode == "camera":
        origin = cam2global[:3, 3]
    else:
        origin = np.asarray(nusc.get("ego_pose", sd["ego_pose_token"])["translation"], float)
    out: dict[str, Candidate] = {}
    for box in boxes:
        if box.name not in categories:
            continue
        ann = nusc.get("sample_annotation", box.token)
        if visibility is not None and ann["visibility_token"] not in visibility:
            continue
        # the box's global centre at this frame's time (interpolated for sweeps)
        center = cam2global[:3, :3] @ box.center + cam2global[:3, 3]
        dist = float(np.linalg.norm(center - origin))
        if not (min_d <= dist <= max_d):
            continue
        corners = view_points(box.corners(), K, normalize=True)
        rot = Quaternion(matrix=cam2global[:3, :3]) * box.orientation
        out[ann["instance_token"]] = Candidate(
            ann["token"], box.name, dist, box_2d(corners), tuple(center.tolist()),
            tuple(float(x) for x in box.wlh), tuple(float(x) for x in rot.elements),
        )
    return out


def frame_boxes(nusc, sd: dict) -> list[dict]:
    """Every annotated object of ``sd``'s frame (any category, any visibility) that has a
    corner in front of the camera and inside the image: instance token, category and the
    2D box of its corners in front of the camera, clipped to the image (px)."""
    from nuscenes.utils.geometry_utils import BoxVisibility, view_points

    _, boxes, K = nusc.get_sample_data(sd["token"], box_vis_level=BoxVisibility.ANY)
    w, h = sd["width"], sd["height"]
    out = []
    for box in boxes:
        c = box.corners()
        front = c[:, c[2] > 0.1]
        if front.shape[1] == 0:
            continue
        x0, y0, x1, y1 = box_2d(view_points(front, K, normalize=True))
        out.append({"instance_token": nusc.get("sample_annotation", box.token)["instance_token"],
                    "category": box.name, "xmin": max(x0, 0.0), "ymin": max(y0, 0.0),
                    "xmax": min(x1, w - 1.0), "ymax": min(y1, h - 1.0)})
    return out


def frame_boxes_3d(nusc, sd_token: str) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every annotated box of a camera frame (any category) in the global frame, at the
    frame's time (the devkit interpolates sweeps between keyframes): (centre (3,) m, size
    (w, l, h) m, rotation quaternion (w, x, y, z)). The occluders of the static-world flow
    (:func:`flowmod.crops.static_crops`)."""
    return [(np.asarray(b.center, float), np.asarray(b.wlh, float),
             np.asarray(b.orientation.elements, float)) for b in nusc.get_boxes(sd_token)]


def _attribute(nusc, ann: dict) -> str:
    names = [nusc.get("attribute", t)["name"] for t in ann["attribute_tokens"]]
    return names[0] if names else ""


def camera_to_global(nusc, sd: dict) -> np.ndarray:
    """(4, 4) float64 transform from ``sd``'s camera frame to the global frame (m)."""
    cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
    pose = nusc.get("ego_pose", sd["ego_pose_token"])
    m = np.eye(4)
    m[:3, :3] = Quaternion(cs["rotation"]).rotation_matrix
    m[:3, 3] = cs["translation"]
    e = np.eye(4)
    e[:3, :3] = Quaternion(pose["rotation"]).rotation_matrix
    e[:3, 3] = pose["translation"]
    return e @ m


def _pair_row(nusc, pair_id: str, scene: str, split: str, kind: str, sd1: dict,
              sd2: dict) -> dict:
    cs = nusc.get("calibrated_sensor", sd1["calibrated_sensor_token"])
    return {
        "pair_id": pair_id, "scene": scene, "split": split, "set": kind,
        "sd_token_1": sd1["token"], "sd_token_2": sd2["token"],
        "path_1": sd1["filename"], "path_2": sd2["filename"],
        "timestamp_1": int(sd1["timestamp"]), "timestamp_2": int(sd2["timestamp"]),
        "sample_token_1": sd1["sample_token"], "sample_token_2": sd2["sample_token"],
        "width": int(sd1["width"]), "height": int(sd1["height"]),
        "intrinsic": np.asarray(cs["camera_intrinsic"], dtype=np.float64).ravel().tolist(),
        "cam2global_1": camera_to_global(nusc, sd1).ravel().tolist(),
        "cam2global_2": camera_to_global(nusc, sd2).ravel().tolist(),
    }


def keyframe_set(
    nusc, scenes: pd.DataFrame, p: Params, progress: bool = True,
    distances: tuple[float, float] | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Pairs of consecutive keyframes and their target vehicles (labels by equation 1).

    ``scenes`` has columns scene, scene_token, split; ``distances`` (m, default
    ``(min_distance, max_distance)``). Returns (pairs, objects).
    """
    cats, vis = set(p.categories), set(p.visibility_tokens)
    near, far = distances or (p.min_distance, p.max_distance)
    pair_rows, obj_rows = [], []
    for sc in bar(scenes.itertuples(), total=len(scenes), desc="keyframe pairs",
                   disable=not progress):
        frames = camera_frames(nusc, sc.scene_token, keyframes_only=True)
        quals = [qualifying_boxes(nusc, sd, cats, near, far, p.distance_mode, vis)
                 for sd in frames]
        for i in range(len(frames) - 1):
            sd1, sd2 = frames[i], frames[i + 1]
            common = [inst for inst in quals[i] if inst in quals[i + 1]]
            if not common:
                continue
            pair_id = f"{sc.scene}-k{i:03d}"
            pair_rows.append(_pair_row(nusc, pair_id, sc.scene, sc.split, "keyframe", sd1, sd2))
            s1 = nusc.get("sample", sd1["sample_token"])
            s2 = nusc.get("sample", sd2["sample_token"])
            for inst in common:
                c1, c2 = quals[i][inst], quals[i + 1][inst]
                a1 = nusc.get("sample_annotation", c1.ann_token)
                a2 = nusc.get("sample_annotation", c2.ann_token)
                v = labels.velocity(a1["translation"], a2["translation"],
                                    s1["timestamp"], s2["timestamp"])
                obj_rows.append(_object_row(nusc, pair_id, sc, "keyframe", inst, c1, a1, v, p))
    return pd.DataFrame(pair_rows), pd.DataFrame(obj_rows)


def _object_row(nusc, pair_id, sc, kind, inst, c: Candidate, ann: dict, v, p: Params) -> dict:
    box_v = nusc.box_velocity(ann["token"])
    box_speed = float(np.linalg.norm(box_v)) if np.all(np.isfinite(box_v)) else float("nan")
    spd = float(labels.speed(v))
    return {
        "pair_id": pair_id, "scene": sc.scene, "split": sc.split, "set": kind,
        "instance_token": inst, "ann_token": ann["token"], "category": c.category,
        "distance": c.distance, "visibility": ann["visibility_token"],
        "center_x": c.center[0], "center_y": c.center[1], "center_z": c.center[2],
        "xmin": c.box[0], "ymin": c.box[1], "xmax": c.box[2], "ymax": c.box[3],
        "size_w": c.size[0], "size_l": c.size[1], "size_h": c.size[2],
        "qw": c.rotation[0], "qx": c.rotation[1], "qy": c.rotation[2], "qz": c.rotation[3],
        "vx": float(v[0]), "vy": float(v[1]), "vz": float(v[2]), "speed": spd,
        "label": int(labels.motion_label(spd, p.speed_threshold)),
        "attribute": _attribute(nusc, ann), "box_speed": box_speed,
        "box_label": int(labels.motion_label(box_speed, p.speed_threshold)),
    }


def general_set(
    nusc, scenes: pd.DataFrame, p: Params, progress: bool = True, *,
    far: float | None = None, stride: int = 1, sweeps_only: bool = False,
    kind: str = "general",
) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """The generalisation manifest: frame pairs ``general_interval`` apart in held-out scenes.

    Objects: Table-1 vehicles in frame 1 (interpolated devkit boxes, all corners visible,
    distance from general_min_distance to general_max_distance, the paper's range, and on to
    general_beyond_distance for a separate breakdown; the previous keyframe's visibility
    token), present in the previous and next keyframes. ``label`` follows the paper (the
    eq.-1 label of the previous keyframe pair); ``speed`` and ``label`` are those of that
    keyframe pair. Boxes: every annotated object of each pair's frame 1
    (:func:`frame_boxes`), for the failure analysis. Returns (pairs, objects, boxes).

    Chapter 11 reuses it for the non-keyframe pairs of training scenes: ``far`` (m, default
    the farther of general_max_distance and general_beyond_distance), every ``stride``-th
    camera frame starting a pair, ``sweeps_only`` (frame 1 a sweep), ``kind`` (the ``set``
    column and pair-id letter).
    """
    cats, vis = set(p.categories), set(p.visibility_tokens)
    if far is None:
        far = max(p.general_max_distance, p.general_beyond_distance)
    pair_rows, obj_rows, box_rows = [], [], []
    for sc in bar(scenes.itertuples(), total=len(scenes), desc=f"{kind} pairs",
                   disable=not progress):
        frames = camera_frames(nusc, sc.scene_token, keyframes_only=False)
        for i in range(0, len(frames) - p.general_interval, stride):
            sd1, sd2 = frames[i], frames[i + p.general_interval]
            if sweeps_only and sd1["is_key_frame"]:
                continue
            nxt = nusc.get("sample", sd1["sample_token"])  # a sweep points to the NEXT sample
            prev = nxt if sd1["is_key_frame"] else (
                nusc.get("sample", nxt["prev"]) if nxt["prev"] else None)
            if prev is None or not prev["next"]:
                continue
            after = nusc.get("sample", prev["next"])
            quals = qualifying_boxes(nusc, sd1, cats, p.general_min_distance, far,
                                     p.distance_mode, None)
            prev_anns = {nusc.get("sample_annotation", t)["instance_token"]: t
                         for t in prev["anns"]}
            after_anns = {nusc.get("sample_annotation", t)["instance_token"]: t
                          for t in after["anns"]}
            pair_id = f"{sc.scene}-{kind[0]}{i:04d}"
            rows = []
            for inst, c in quals.items():
                if inst not in prev_anns or inst not in after_anns:
                    continue
                a_prev = nusc.get("sample_annotation", prev_anns[inst])
                if a_prev["visibility_token"] not in vis:
                    continue
                a_after = nusc.get("sample_annotation", after_anns[inst])
                v = labels.velocity(a_prev["translation"], a_after["translation"],
                                    prev["timestamp"], after["timestamp"])
                rows.append(_object_row(nusc, pair_id, sc, kind, inst, c, a_prev, v, p))
            if rows:
                pair_rows.append(_pair_row(nusc, pair_id, sc.scene, sc.split, kind, sd1, sd2))
                obj_rows.extend(rows)
                box_rows.extend({"pair_id": pair_id, **b} for b in frame_boxes(nusc, sd1))
    return pd.DataFrame(pair_rows), pd.DataFrame(obj_rows), pd.DataFrame(box_rows)


# --- the stage ---------------------------------------------------------------------------

@dataclass
class Selection:
    """The stage's outputs: pairs and objects of both sets, and the scene table."""

    pairs: pd.DataFrame
    objects: pd.DataFrame
    scenes: pd.DataFrame
    #: every annotated object of the generalisation pairs' frame 1 (failure analysis)
    boxes: pd.DataFrame = field(default_factory=pd.DataFrame)


def _add_true_speed(objects: pd.DataFrame, pairs: pd.DataFrame, p: Params) -> pd.DataFrame:
    """For a synthetic world: the true speed at frame 1's time and its label."""
    t1 = pairs.set_index("pair_id")["timestamp_1"]
    true = [
        float(labels.speed(world.true_velocity(p.dataroot_path, p.version, inst, int(t1[pid]))))
        for inst, pid in zip(objects["instance_token"], objects["pair_id"], strict=True)
    ]
    objects = objects.copy()
    objects["true_speed"] = true
    objects["true_label"] = labels.motion_label(np.asarray(true), p.speed_threshold)
    return objects


def _missing_images(p: Params, pairs: pd.DataFrame, objects: pd.DataFrame
                    ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Drop pairs whose images are missing (``missing_images: skip``) or raise (``error``)."""
    missing = check_images(p.dataroot_path, list(pairs["path_1"]) + list(pairs["path_2"]))
    if not missing:
        return pairs, objects
    msg = f"{len(missing)} image files are missing under {p.dataroot_path}, e.g. {missing[:3]}"
    if p.missing_images == "error":
        raise SelectionError(msg + " (set missing_images: skip to drop their pairs)")
    bad = pairs["path_1"].isin(missing) | pairs["path_2"].isin(missing)
    pairs = pairs[~bad].reset_index(drop=True)
    return pairs, objects[objects["pair_id"].isin(pairs["pair_id"])].reset_index(drop=True)


def _finish(p: Params, pairs: pd.DataFrame, objects: pd.DataFrame
            ) -> tuple[pd.DataFrame, pd.DataFrame]:
    pairs, objects = _missing_images(p, pairs, objects)
    if world.is_synthetic(p.dataroot_path, p.version) and len(objects):
        objects = _add_true_speed(objects, pairs, p)
    return pairs, objects


def select_keyframes(p: Params, nusc=None, progress: bool = True) -> Selection:
    """The paper's keyframe set and the scene split (no caching; see :func:`run`)."""
    nusc = nusc or open_nuscenes(p.dataroot_path, p.version)
    scenes = filter_scenes(scene_table(nusc), p.exclude_descriptions)
    kept = scenes[scenes["excluded_by"] == ""]
    if kept.empty:
        raise SelectionError(
            f"all {len(scenes)} scenes were excluded by their descriptions "
            f"({sorted(set(scenes['excluded_by']))}); change exclude_descriptions"
        )
    # Consecutive scenes of one nuScenes drive share places and parked cars: split by log.
    # A generated world's scenes are independent of each other: split by scene.
    unit = "scene" if world.is_synthetic(p.dataroot_path, p.version) else "log"
    split = _scene_split(p, kept, unit)
    scenes["split"] = scenes["scene"].map(split["split"]).fillna("excluded")
    scenes["fold"] = scenes["scene"].map(split["fold"]).fillna(-1).astype(int)
    scenes["val_scene"] = scenes["scene"].map(split["val_scene"]).fillna(False).astype(bool)
    scenes["split_unit"] = unit
    kept = scenes[scenes["split"] != "excluded"]
    pairs, objects = keyframe_set(nusc, kept, p, progress)
    if objects.empty:
        raise SelectionError(
            f"no vehicle passed Table 1 in {len(kept)} scenes: check categories "
            f"{p.categories}, distance [{p.min_distance}, {p.max_distance}] m and visibility "
            f"{p.visibility_tokens}"
        )
    pairs, objects = _finish(p, pairs, objects)
    return Selection(with_folds(pairs, scenes), with_folds(objects, scenes), scenes)


def held_out(scenes: pd.DataFrame, folds: int) -> pd.DataFrame:
    """The scenes a model is scored on: the test split (one fold), every kept scene
    (cross-validation: each by the model of its own fold)."""
    return scenes[scenes["split"] == "test"] if folds == 1 else scenes[scenes["fold"] >= 0]


def select_general(p: Params, scenes: pd.DataFrame, nusc=None, progress: bool = True
                   ) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """The generalisation set over the held-out scenes of ``scenes`` (the keyframe stage's
    scene table with its split): test scenes with sweeps, at most ``general_max_scenes``.
    Returns (pairs, objects, boxes of every annotated object in frame 1)."""
    chosen = held_out(scenes, p.folds)
    chosen = chosen[chosen["has_sweeps"]]
    # folds take turns, so that every fold's model meets non-keyframe pairs
    turn = chosen.groupby("fold").cumcount()
    chosen = chosen.assign(_turn=turn).sort_values(["_turn", "fold"], kind="stable").drop(
        columns="_turn").head(p.general_max_scenes)
    if chosen.empty:
        return pd.DataFrame(), pd.DataFrame(), pd.DataFrame()
    nusc = nusc or open_nuscenes(p.dataroot_path, p.version)
    pairs, objects, boxes = general_set(nusc, chosen, p, progress, stride=p.general_stride)
    pairs, objects = _finish(p, pairs, objects)
    pairs, objects = with_folds(pairs, scenes), with_folds(objects, scenes)
    return pairs, objects, boxes[boxes["pair_id"].isin(pairs["pair_id"])].reset_index(drop=True)


def select_wide(p: Params, scenes: pd.DataFrame, nusc=None, progress: bool = True
                ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Chapter 11's training set (the paper's strict filtering removed): in the train and
    val scenes of ``scenes`` (the keyframe stage's scene table), the consecutive keyframe
    pairs with Table-1 vehicles at every distance of the generalisation range
    (general_min_distance to general_max_distance, eq.-1 labels), and, in scenes with
    sweeps, the pairs ``general_interval`` camera frames apart whose first frame is a sweep,
    every ``wide_sweep_stride``-th frame (0: none), labelled like the generalisation set.
    Columns as the keyframe set; ``set`` is ``keyframe`` or ``sweep``. Returns (pairs,
    objects)."""
    train = scenes[scenes["split"].isin(["train", "val"])] if p.folds == 1 else scenes[
        scenes["fold"] >= 0]  # cross-validation: every scene trains the other folds' models
    if train.empty:
        raise SelectionError("no train or val scene in the scene table: run chapter 02")
    nusc = nusc or open_nuscenes(p.dataroot_path, p.version)
    kp, ko = keyframe_set(nusc, train, p, progress,
                          distances=(p.general_min_distance, p.general_max_distance))
    frames_p, frames_o = [kp], [ko]
    swept = train[train["has_sweeps"]]
    if p.wide_sweep_stride and len(swept):
        sp, so, _ = general_set(nusc, swept, p, progress, far=p.general_max_distance,
                                stride=p.wide_sweep_stride, sweeps_only=True, kind="sweep")
        frames_p.append(sp)
        frames_o.append(so)
    objects = pd.concat([f for f in frames_o if len(f)] or [pd.DataFrame()], ignore_index=True)
    if objects.empty or (p.folds == 1 and not {"train", "val"} <= set(objects["split"])):
        raise SelectionError(
            f"the all-distances training set has no vehicle in the train or val split "
            f"(distance {p.general_min_distance:g}-{p.general_max_distance:g} m): check "
            "general_min_distance / general_max_distance")
    pairs = pd.concat([f for f in frames_p if len(f)], ignore_index=True)
    pairs, objects = _finish(p, pairs, objects)
    return with_folds(pairs, scenes), with_folds(objects, scenes)


def select(p: Params, progress: bool = True) -> Selection:
    """Both sets at once, uncached: keyframe pairs and objects, then the generalisation set
    appended (``set`` column); the scene table."""
    nusc = open_nuscenes(p.dataroot_path, p.version)
    sel = select_keyframes(p, nusc, progress)
    gp, go, _ = select_general(p, sel.scenes, nusc, progress)
    return Selection(pd.concat([sel.pairs, gp], ignore_index=True),
                     pd.concat([sel.objects, go], ignore_index=True), sel.scenes)


def read_table(folder: Path, name: str) -> pd.DataFrame:
    """One table (``pairs``, ``objects``, ``scenes``, ``boxes``) of a selection node's folder
    (``select``, ``general``, ``wide``): the one reader of the files :func:`write_tables`
    writes."""
    return pd.read_parquet(Path(folder) / f"{name}.parquet")


def write_tables(d: Path, frames: dict[str, pd.DataFrame]) -> None:
    """Write ``{name: table}`` as ``<d>/<name>.parquet`` (each atomically)."""
    for key, df in frames.items():
        with atomic_path(d / f"{key}.parquet") as tmp:
            df.to_parquet(tmp, index=False)


def build_select(b: dag.Build, progress: bool) -> Mapping[str, Any]:
    """Build the ``select`` node: the keyframe set and the scene split (``pairs``,
    ``objects``, ``scenes`` tables)."""
    q = b.params
    sel = select_keyframes(q, open_nuscenes(q.dataroot_path, q.version), progress)
    write_tables(b.start(fresh=True), {"pairs": sel.pairs, "objects": sel.objects,
                                       "scenes": sel.scenes})
    return {"rows": len(sel.objects), "pairs": len(sel.pairs)}


def build_general(b: dag.Build, progress: bool) -> Mapping[str, Any]:
    """Build the ``general`` node: the generalisation set (``pairs``, ``objects`` and the
    ``boxes`` of every annotated object in frame 1)."""
    q = b.params
    scenes = read_table(b.input_dir(dag.Node("select")), "scenes")
    gp, go, gb = select_general(q, scenes, open_nuscenes(q.dataroot_path, q.version), progress)
    write_tables(b.start(fresh=True), {"pairs": gp, "objects": go, "boxes": gb})
    return {"rows": len(go), "pairs": len(gp)}


#: The two parts of the flow and crops stages: the paper's keyframe pairs and the
#: generalisation pairs.
PARTS = ("keyframe", "general")
#: Chapter 11's part of the flow and crops stages: the training set at every distance.
WIDE = "wide"


def objects_node(part: str | None) -> dag.Node:
    """The selection node holding a flow or crops part's pairs and objects: ``select``
    (keyframe), ``wide`` (chapter 11's part) or ``general``."""
    return {None: dag.Node("select"), "keyframe": dag.Node("select"),
            WIDE: dag.Node("wide")}.get(part, dag.Node("general"))


#: The keyframe set and the scene split (chapter 02).
SELECT = dag.Stage("select", 3, "02", "select", "Table-1 keyframe pairs and objects, scene split",
                   nodes=lambda p: [dag.Node("select")],
                   inputs=lambda n, p: (dag.Node("world"),), build=build_select,
                   outputs=("pairs.parquet", "objects.parquet", "scenes.parquet"))
#: The generalisation set (chapter 02).
GENERAL = dag.Stage("general", 3, "02", "general",
                    "generalisation pairs and objects (held-out scenes)",
                    nodes=lambda p: [dag.Node("general")],
                    inputs=lambda n, p: (dag.Node("world"), dag.Node("select")),
                    build=build_general,
                    outputs=("pairs.parquet", "objects.parquet", "boxes.parquet"))


def read_selection(select_dir: Path, general_dir: Path) -> Selection:
    """The published selection (both sets, ``set`` column) from the folders of the
    ``select`` and ``general`` nodes."""
    frames = {}
    for name, d in (("select", select_dir), ("general", general_dir)):
        frames[name] = {k: read_table(d, k) for k in ("pairs", "objects", "scenes", "boxes")
                        if (Path(d) / f"{k}.parquet").is_file()}
    key, gen = frames["select"], frames["general"]
    return Selection(pd.concat([key["pairs"], gen["pairs"]], ignore_index=True),
                     pd.concat([key["objects"], gen["objects"]], ignore_index=True),
                     key["scenes"], gen.get("boxes", pd.DataFrame()))
