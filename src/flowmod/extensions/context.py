"""The other inputs of chapter 10 (beyond the paper), per object and in the order of its flow
crops: the static-world flow of its crop window and the two camera images of that window.

* ``<split>.static.npy``: (N, 2, S, S) float16 px, the flow a static world would produce in
  the object's crop window from the two camera poses and calibrations, with depth from every
  annotated 3D box of the first frame where a ray meets one, else the ground plane, else a
  far plane (:func:`flowmod.crops.static_crops`; all of which real nuScenes has too). The
  flow crop minus it is the ego-motion-compensated (residual) input.
* ``<split>.deployed.npy``: (N, 2, S, S) float16 px, the same with what a car could know
  (:func:`flowmod.geometry.deployed_depth`): no 3D box, the flat ground, and the target at
  its 2D box's ground-contact depth.
* ``<split>.images.npy``: (N, 6, S, S) uint8, RGB of frame 1 then RGB of frame 2 in the same
  window (the window of the flow crop, cut from the full-resolution images and resized the
  same way: :func:`flowmod.crops.crop_image`).
* ``<split>.parquet``: the objects' rows, in array order (that of the flow crops:
  :func:`flowmod.crops.split_objects`).

The stage is ``context[<part>]`` (:data:`STAGE`), one node per part (keyframe splits,
generalisation set); it reads no flow, so every flow method shares it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from flowmod import dag
from flowmod.artefacts import atomic_path
from flowmod.crops import (
    STATIC_DEPTHS,
    CropsError,
    crop_image,
    part_objects,
    part_splits,
    split_objects,
    static_crops,
)
from flowmod.params import Params
from flowmod.progress import bar
from flowmod.select import PARTS, frame_boxes_3d, objects_node, open_nuscenes, read_table

#: Files of one split: static-world flow crops (annotated-box depth; deployable depth),
#: image crops, index.
STATIC, DEPLOYED, IMAGES = "static", "deployed", "images"
#: The static-world flow a ``depth`` of :func:`read_context` names: ``boxes`` (annotated 3D
#: boxes, an oracle) or ``ground`` (the 2D box's ground contact, deployable).
DEPTHS = dict(zip(STATIC_DEPTHS, (STATIC, DEPLOYED), strict=True))


def read_image(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a camera JPEG; :class:`CropsError` naming the file if it is
    missing or cannot be decoded."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR) if Path(path).is_file() else None
    if img is None:
        raise CropsError(f"camera image {path} is missing or not a readable image: restore it "
                         "from the data set (or regenerate the world: make data)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def image_crops(objects: pd.DataFrame, pairs: pd.DataFrame, dataroot: Path, size: int,
                scale: float, progress: bool = False) -> np.ndarray:
    """(N, 6, S, S) uint8: RGB of frame 1 and of frame 2 in each object's crop window
    (``scale`` x its frame-1 box, the flow crop's window), rows as ``objects``. Each pair's
    two images are read once."""
    out = np.empty((len(objects), 6, size, size), np.uint8)
    p = pairs.set_index("pair_id")
    boxes = objects[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float)
    groups = objects.groupby("pair_id", sort=False).indices
    for pid, rows in bar(groups.items(), total=len(groups), desc="image crops", unit="pair",
                         disable=not progress):
        row = p.loc[pid]
        for k, col in enumerate(("path_1", "path_2")):
            img = read_image(Path(dataroot) / row[col])
            out[rows, 3 * k:3 * k + 3] = crop_image(img, boxes[rows], size, scale).transpose(
                0, 3, 1, 2)
    return out


def paths(folder: str | os.PathLike[str], split: str) -> dict[str, Path]:
    """The files of one split: ``static``, ``deployed``, ``images`` (.npy) and ``index``
    (.parquet)."""
    d = Path(folder)
    return {**{k: d / f"{split}.{k}.npy" for k in (STATIC, DEPLOYED, IMAGES)},
            "index": d / f"{split}.parquet"}


def build_split(objects: pd.DataFrame, pairs: pd.DataFrame, dataroot: Path, out: Path,
                split: str, size: int, scale: float, frame_boxes: Any = None,
                progress: bool = False) -> int:
    """Write the three files of one split (each atomically); returns its number of rows."""
    df = split_objects(objects, split)
    f = paths(out, split)
    static = static_crops(df, pairs, size, scale, frame_boxes=frame_boxes,
                          depths=tuple(DEPTHS), progress=progress)
    images = image_crops(df, pairs, dataroot, size, scale, progress=progress)
    for name, arr in ((STATIC, static["boxes"].astype(np.float16)),
                      (DEPLOYED, static["ground"].astype(np.float16)), (IMAGES, images)):
        with atomic_path(f[name]) as tmp:
            np.save(tmp, arr, allow_pickle=False)
    with atomic_path(f["index"]) as tmp:
        df.to_parquet(tmp, index=False)
    return len(df)


def read_context(folder: str | os.PathLike[str], split: str, depth: str = "boxes"
                 ) -> tuple[np.ndarray, np.ndarray, pd.DataFrame]:
    """(static (N, 2, S, S) float16 px, images (N, 6, S, S) uint8, index) of one split,
    memory-mapped; the static-world flow with ``depth`` :data:`DEPTHS` (``boxes``: annotated,
    ``ground``: deployable). :class:`CropsError` naming the file when one is missing or they
    disagree."""
    f = paths(folder, split)
    for path in f.values():
        if not path.is_file():
            raise CropsError(f"context artefact missing: {path}; run chapter 10's stages "
                             "(python -m flowmod.runner --only 10 --set extension_build=true)")
    static = np.load(f[DEPTHS[depth]], mmap_mode="r", allow_pickle=False)
    images = np.load(f[IMAGES], mmap_mode="r", allow_pickle=False)
    df = pd.read_parquet(f["index"])
    if not (static.shape[0] == images.shape[0] == len(df)) or static.shape[1] != 2 \
            or images.shape[1] != 6:
        raise CropsError(f"{folder}: {split} files disagree (static {static.shape}, images "
                         f"{images.shape}, index {len(df)} rows); rebuild with force=true")
    return static, images, df


def build(b: dag.Build, progress: bool) -> dict[str, Any]:
    """Build one ``context[<part>]`` node: static-world flow and image crops of the part's
    objects, the occluders from the devkit's boxes of each pair's first frame."""
    q, part = b.params, b.node.part
    sel = b.input_dir(objects_node(part))
    objects = part_objects(sel, part)
    pairs = read_table(sel, "pairs")
    pairs = pairs[pairs["pair_id"].isin(set(objects["pair_id"]))]
    nusc = open_nuscenes(q.dataroot_path, q.version)
    boxes = {str(r.pair_id): frame_boxes_3d(nusc, r.sd_token_1)
             for r in bar(pairs.itertuples(), total=len(pairs), desc="annotated boxes",
                          unit="pair", disable=not progress)}
    work = b.start(fresh=True)
    rows = {s: build_split(objects, pairs, q.dataroot_path, work, s, q.crop_size, q.crop_scale,
                           boxes, progress) for s in part_splits(part, q.folds)}
    return {"rows": rows, "boxes": sum(len(v) for v in boxes.values())}


def _pulled(p: Params) -> bool:
    """Chapter 13 pulls the exact flow toward the still-world flow (its ``pull`` kind)."""
    return "pull" in p.error_kinds and "gt" in p.flow_methods


#: Chapter 10's static-world flow and image crops, one node per part (no flow method).
STAGE = dag.Stage("context", 2, "10", "extensions/context/{part}",
                  "static-world flow and image crops of every object",
                  nodes=lambda p: ([dag.Node("context", None, part) for part in PARTS]
                                   if p.extension_inputs or _pulled(p) else []),
                  inputs=lambda n, p: (dag.Node("world"), objects_node(n.part)), build=build,
                  outputs=("{split}.parquet", "{split}.static.npy", "{split}.deployed.npy",
                           "{split}.images.npy"))
