"""Paper preprocessing (Sec. III-C): flow crops around each vehicle's 2D box.

For every object: a square of side ``max(w, h)`` about the box centre, its side multiplied by
``scale`` (3 in the paper), edge padding (``cv2.BORDER_REPLICATE``) where it leaves the frame,
crop, bilinear resize (``cv2.resize`` ``INTER_LINEAR``) to ``S x S``. Flow values are kept as
they are (pixels of the flow grid; not rescaled by the resize), as in the paper.

Window convention (documented choice; the original code used ``floor``/``ceil`` bounds with an
inclusive end, which gives windows 1-2 px larger and sometimes not square): box coordinates
are continuous, with pixel ``i``'s centre at ``i`` (it covers ``[i - 0.5, i + 0.5)``), as the
projection of the 3D corners through the camera matrix gives them. The window is
``n = max(1, round(scale * max(w, h)))`` pixels on each side, the ``n`` pixels whose span is
centred on the box centre ``c`` (to the nearest pixel): first pixel ``round(c - (n - 1) / 2)``,
halves rounded up. On a flow grid stored at scale ``s``, box coordinates map as
``(x + 0.5) * s - 0.5`` (the centres of the reduced pixels).

Artefacts (``build_crops``): ``<out_dir>/<split>.npy``, an ``(N, 2, S, S)`` float16 array
(channel 0 = u, 1 = v, pixels), and ``<split>.parquet``, the objects' rows in the same order.
:func:`read_crops` opens both and checks that they agree.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np
import pandas as pd

from flowmod import dag, geometry
from flowmod.artefacts import atomic_path, fingerprint, read_manifest, write_json
from flowmod.dag import StageParams
from flowmod.flow import FlowReader, compute_flow, estimator_options, flow_root
from flowmod.flow.stage import DIGESTS, FlowFiles, pair_files, pool_config, world_identity
from flowmod.flow.store import npy_ok, roundtrip
from flowmod.geometry import GRID, box_samples
from flowmod.params import Params
from flowmod.progress import bar
from flowmod.select import PARTS, WIDE, fold_roles, objects_node, read_table

#: The nuScenes CAM_FRONT image size (width, height) in which object boxes are given.
IMAGE_SIZE = (1600, 900)
BOX_COLUMNS = ("xmin", "ymin", "xmax", "ymax")

T = TypeVar("T")


class CropsError(ValueError):
    """Crop artefacts are missing, inconsistent or cannot be built; the message names files."""


# --- geometry (pure) ------------------------------------------------------------------------


def _round_half_up(a: np.ndarray) -> np.ndarray:
    return np.floor(a + 0.5).astype(np.int64)


def crop_windows(boxes: np.ndarray, scale: float = 3.0) -> np.ndarray:
    """Square crop windows for boxes.

    boxes: (N, 4) xmin, ymin, xmax, ymax, pixels. Returns (N, 3) int64 ``x0, y0, n``: the
    window covers columns ``x0 .. x0 + n - 1`` and rows ``y0 .. y0 + n - 1`` (may leave the
    frame; those pixels are edge-replicated).
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    if not np.isfinite(b).all():
        bad = np.flatnonzero(~np.isfinite(b).all(axis=1))[:5].tolist()
        raise CropsError(f"boxes contain NaN/inf (rows {bad}...)")
    w = b[:, 2] - b[:, 0]
    h = b[:, 3] - b[:, 1]
    if (w < 0).any() or (h < 0).any():
        bad = np.flatnonzero((w < 0) | (h < 0))[:5].tolist()
        raise CropsError(f"boxes with xmax < xmin or ymax < ymin (rows {bad}...)")
    n = np.maximum(1, _round_half_up(scale * np.maximum(w, h)))
    cx = (b[:, 0] + b[:, 2]) / 2
    cy = (b[:, 1] + b[:, 3]) / 2
    x0 = _round_half_up(cx - (n - 1) / 2)
    y0 = _round_half_up(cy - (n - 1) / 2)
    return np.stack([x0, y0, n], axis=1)


def crop_boxes(flow: np.ndarray, boxes: np.ndarray, size: int, scale: float = 3.0) -> np.ndarray:
    """Crops of one frame's flow around its boxes.

    flow: (H, W, 2) pixels (any float dtype); boxes: (N, 4) xyxy in pixels of that grid.
    Returns (N, 2, S, S) float32 with S = ``size`` (u, v unchanged by the resize).
    """
    flow = np.ascontiguousarray(flow, dtype=np.float32)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise CropsError(f"flow must be (H, W, 2), got {flow.shape}")
    return crop_image(flow, boxes, size, scale).transpose(0, 3, 1, 2)


def crop_image(image: np.ndarray, boxes: np.ndarray, size: int, scale: float = 3.0) -> np.ndarray:
    """The paper's crop of any (H, W, C) array around each box: (N, S, S, C), image's dtype.

    The frame is padded once (edge replication) by the largest margin any window needs, then
    each window is a slice of it; if that padding would more than quadruple the frame (very
    near, very large boxes) the windows are gathered with clipped indices instead (same
    values, less memory). Each window is resized bilinearly (cv2 INTER_LINEAR) to S x S.
    """
    size = int(size)
    if size < 1:
        raise CropsError(f"size must be >= 1, got {size}")
    win = crop_windows(boxes, scale)
    H, W, C = image.shape
    out = np.empty((len(win), size, size, C), dtype=image.dtype)
    if len(win) == 0:
        return out
    x0, y0, n = win[:, 0], win[:, 1], win[:, 2]
    margin = int(max(0, -x0.min(), -y0.min(), (x0 + n).max() - W, (y0 + n).max() - H))
    if (H + 2 * margin) * (W + 2 * margin) <= 4 * H * W:
        src = image
        if margin:
            src = cv2.copyMakeBorder(
                image, margin, margin, margin, margin, cv2.BORDER_REPLICATE
            )
        for i, (x, y, k) in enumerate(win.tolist()):
            patch = src[y + margin : y + margin + k, x + margin : x + margin + k]
            out[i] = _resize(patch, size)
    else:
        for i, (x, y, k) in enumerate(win.tolist()):
            rows = np.clip(np.arange(y, y + k), 0, H - 1)
            cols = np.clip(np.arange(x, x + k), 0, W - 1)
            out[i] = _resize(image[np.ix_(rows, cols)], size)
    return out


def _resize(patch: np.ndarray, size: int) -> np.ndarray:
    """(n, n, C) -> (S, S, C), bilinear (cv2 INTER_LINEAR)."""
    return cv2.resize(patch, (size, size), interpolation=cv2.INTER_LINEAR).reshape(
        size, size, patch.shape[2])


def hflip(x: T, negate: Sequence[int] = (0,)) -> T:
    """Horizontal flip of crops, on a copy: mirror the width axis and negate the channels
    ``negate`` (the horizontal flow components: u of the flow crops, channel 0).

    x: (..., C, S, S) numpy array or torch tensor. The input is never modified (the original
    code flipped a view in place and corrupted its cached crops). Applying it twice gives
    the input back exactly.
    """
    if isinstance(x, np.ndarray):
        out = x[..., ::-1].copy()
        for c in negate:
            np.negative(out[..., c, :, :], out=out[..., c, :, :])
        return out  # type: ignore[return-value]
    import torch

    if isinstance(x, torch.Tensor):
        out_t = torch.flip(x, dims=(-1,))  # torch.flip always copies
        for c in negate:
            out_t[..., c, :, :].neg_()
        return out_t  # type: ignore[return-value]
    raise TypeError(f"hflip expects a numpy array or a torch tensor, got {type(x).__name__}")


# --- I/O: building and opening the crop artefacts -------------------------------------------


def samples_path(out_dir: str | os.PathLike[str], split: str) -> Path:
    """``<out_dir>/<split>.samples.npy``: (N, G * G, 2) float32, the flow at each object's box
    lattice (:func:`flowmod.geometry.box_samples`), rows as in the crops."""
    return Path(out_dir) / f"{split}.samples.npy"


def read_samples(folder: str | os.PathLike[str], split: str) -> np.ndarray:  # pragma: no mutate block
    """The flow samples of a split's objects (see :func:`samples_path`)."""
    path = samples_path(folder, split)
    if not path.is_file():
        raise CropsError(f"flow samples missing: {path}; rebuild the crops (chapter 05)")
    return np.load(path, allow_pickle=False)


def crop_paths(out_dir: str | os.PathLike[str], split: str) -> tuple[Path, Path]:
    """``(<out_dir>/<split>.npy, <out_dir>/<split>.parquet)``."""
    d = Path(out_dir)
    return d / f"{split}.npy", d / f"{split}.parquet"


def _split_hash(objects: pd.DataFrame, size: int, scale: float, image_size: tuple[int, int]) -> str:  # pragma: no mutate block
    """Identity of a split's build (for resuming a partial one): its rows and the geometry."""
    meta = {"size": int(size), "scale": float(scale),
            "image_size": list(image_size), "columns": list(map(str, objects.columns))}
    h = hashlib.sha256(json.dumps(meta, sort_keys=True).encode())
    h.update(pd.util.hash_pandas_object(objects, index=False).to_numpy().tobytes())
    return h.hexdigest()[:16]


def _check_objects(objects: pd.DataFrame) -> None:  # pragma: no mutate block
    need = {"pair_id", "split", *BOX_COLUMNS}
    missing = sorted(need - set(objects.columns))
    if missing:
        raise CropsError(f"objects table lacks columns {missing} (have {list(objects.columns)})")


def build_crops(
    objects: pd.DataFrame,
    load_flow: Callable[[str], np.ndarray] | None,
    out_dir: str | os.PathLike[str],
    *,
    pair_items: PairItems | None = None,
    size: int,
    scale: float = 3.0,
    splits: Sequence[str] | None = None,
    image_size: tuple[int, int] = IMAGE_SIZE,
    progress: bool = True,
    checkpoint_every: int = 200,
    label: str = "crops",
) -> dict[str, dict[str, Any]]:  # pragma: no mutate block
    """Crop every object of ``objects`` from its pair's flow; one artefact pair per split.

    objects: one row per (pair, vehicle) with pair_id, split and the box (xmin, ymin, xmax,
    ymax in pixels of ``image_size`` = (width, height)); ``load_flow(pair_id)`` -> (H, W, 2)
    flow in pixels (if it has another resolution, boxes are scaled to its grid and the flow
    values are used as they are). Non-finite flow values become 0 (and are counted).
    ``pair_items`` instead gives each pair's crops already made (:data:`PairItems`, e.g.
    from the per-pair files of crops mode, :class:`PairCrops`).

    Writes ``<out_dir>/<split>.npy`` (N, 2, S, S) float16 (filled through a memmap under a
    temporary name, renamed when complete) and ``<split>.parquet`` (the objects' rows, sorted
    by pair_id, in array order) for every split of ``splits`` (default: those present; a
    split without objects gets an empty array). Each flow is read once. A split already
    complete in ``out_dir`` is kept; an interrupted split resumes from its last checkpoint
    (every ``checkpoint_every`` pairs). Returns ``{split: build info}``.
    """
    _check_objects(objects)
    if pair_items is None:
        if load_flow is None:
            raise ValueError("build_crops needs load_flow or pair_items")
        get = load_flow

        def pair_items(pid: str, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, int,
                                                              list[int]]:
            return pair_crops(get(pid), boxes, size, scale, image_size, pid)
    out: dict[str, dict[str, Any]] = {}
    names = list(splits) if splits is not None else sorted(objects["split"].astype(str).unique())
    for split in names:
        df = split_objects(objects, split)
        out[split] = _build_split(
            df, pair_items, Path(out_dir), split, size=size, scale=scale,
            image_size=image_size, progress=progress, checkpoint_every=checkpoint_every,
            label=label,
        )
    return out


#: ``pair_items(pair_id, boxes (n, 4)) -> (crops (n, 2, S, S), samples (n, G*G, 2),
#: non-finite flow values zeroed, flow (H, W))``: one pair's share of a split.
PairItems = Callable[[str, np.ndarray], tuple[np.ndarray, np.ndarray, int, list[int]]]


#: An annotated 3D box in the global frame: (centre (3,) m, size (w, l, h) m, rotation
#: quaternion (w, x, y, z)).
GlobalBox = tuple[np.ndarray, np.ndarray, np.ndarray]


#: Depth of the static world in :func:`static_crops`: ``boxes``, the annotated 3D boxes (an
#: oracle), or ``ground``, the target's 2D box on the flat ground (what a car could compute).
STATIC_DEPTHS = ("boxes", "ground")


def _pair_geometry(pair: Any, boxes3d: Sequence[GlobalBox]) -> tuple[Any, ...]:
    """One pair's cameras (K, frame-1 and frame-2 camera-to-global) and its annotated boxes
    in frame 1's camera, those in front of it: [(centre, wlh, rotation)]."""
    K, T1, T2 = geometry.pair_cameras(pair)
    inside = [geometry.box_in_camera(T1, c, q) + (np.asarray(wlh, float),)
              for c, wlh, q in boxes3d]
    return K, T1, T2, [(c, wlh, rot) for c, rot, wlh in inside if c[2] > 0]


def _own_box(o: Any, T1: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The object's own annotated box in frame 1's camera (when no frame boxes are given)."""
    c, rot = geometry.box_in_camera(T1, np.array([o.center_x, o.center_y, o.center_z]),
                                    np.array([o.qw, o.qx, o.qy, o.qz]))
    return [(c, np.array([o.size_w, o.size_l, o.size_h]), rot)]


def static_crops(objects: pd.DataFrame, pairs: pd.DataFrame, size: int, scale: float,
                 ground_z: float = 0.0,
                 frame_boxes: Mapping[str, Sequence[GlobalBox]] | None = None,
                 depths: Sequence[str] = ("boxes",), progress: bool = False
                 ) -> dict[str, np.ndarray]:
    """For each of ``depths`` (:data:`STATIC_DEPTHS`), (N, 2, S, S) float32 px:
    :func:`flowmod.geometry.static_flow_crop` for every object of ``objects`` (rows of
    objects.parquet, in their order) in its pair's crop window (``scale`` x the box;
    edge-padded outside the frame like the flow crops), on the ground ``z = ground_z``
    (global; 0 on the generated world and in nuScenes, whose ego poses lie on the ground):
    the crop the ego-motion-compensated input subtracts. Depth ``boxes``: the annotated 3D
    boxes ``frame_boxes[pair_id]`` (every box of the pair's first frame, global:
    :func:`flowmod.select.frame_boxes_3d`) where given, else the object's own box only;
    ``ground``: no 3D box, the target at its 2D box's ground contact
    (:func:`flowmod.geometry.deployed_depth`). Each pair's cameras are read once."""
    unknown = sorted(set(depths) - set(STATIC_DEPTHS))
    if unknown:
        raise ValueError(f"unknown static-world depth {unknown}; known: {list(STATIC_DEPTHS)}")
    p = pairs.set_index("pair_id")
    box2d = objects[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float)
    wins = crop_windows(box2d, scale)
    out = {d: np.empty((len(objects), 2, size, size), np.float32) for d in depths}
    cams: dict[str, tuple[Any, ...]] = {}
    rows = zip(objects.itertuples(index=False), wins, strict=True)
    for i, (o, win) in enumerate(bar(rows, total=len(objects), desc="static-world crops",
                                     unit="object", disable=not progress)):
        pid = str(o.pair_id)
        if pid not in cams:
            cams[pid] = _pair_geometry(p.loc[pid], (frame_boxes or {}).get(pid, ()))
        K, T1, T2, boxes = cams[pid]
        own = frame_boxes is None or pid not in frame_boxes
        for d in depths:
            if d == "ground":
                out[d][i] = geometry.static_flow_crop(win, size, K, T1, T2, [], ground_z,
                                                      image_size=IMAGE_SIZE, box2d=box2d[i])
                continue
            out[d][i] = geometry.static_flow_crop(win, size, K, T1, T2,
                                                  _own_box(o, T1) if own else boxes, ground_z,
                                                  image_size=IMAGE_SIZE)
    return out


def split_objects(objects: pd.DataFrame, split: str) -> pd.DataFrame:
    """The objects of one split in the order of its crop arrays: sorted by pair_id (stable),
    so each pair's rows are contiguous and its flow is read once."""
    sel = objects[objects["split"].astype(str) == split]
    return sel.sort_values("pair_id", kind="mergesort").reset_index(drop=True)


def pair_crops(flow: np.ndarray, boxes: np.ndarray, size: int, scale: float,
               image_size: tuple[int, int] = IMAGE_SIZE, pair_id: str = "?"
               ) -> tuple[np.ndarray, np.ndarray, int, list[int]]:
    """One pair's crops and flow samples (pure): flow (H, W, 2) px (non-finite values set
    to 0 and counted; another resolution than ``image_size`` maps the boxes onto its grid),
    boxes (n, 4) in pixels of ``image_size`` = (width, height). Returns (crops (n, 2, S, S)
    float16, samples (n, G * G, 2) float32, non-finite count, [H, W])."""
    flow = np.asarray(flow, dtype=np.float32)
    bad = ~np.isfinite(flow)
    n_bad = int(bad.sum())
    if n_bad:
        flow = np.where(bad, np.float32(0), flow)
    boxes = np.array(boxes, dtype=np.float64)
    fh, fw = flow.shape[:2]
    if (fw, fh) != tuple(image_size):
        sx, sy = fw / image_size[0], fh / image_size[1]
        if abs(fh - sx * image_size[1]) > 1.5:  # more than rounding of a rescale
            raise CropsError(
                f"flow of pair {pair_id} is {fw}x{fh} (WxH), not the "
                f"{image_size[0]}x{image_size[1]} image (or a rescaled copy): padded "
                "flow not unpadded? (RAFT pads 900 rows to 904)"
            )
        boxes[:, [0, 2]] = (boxes[:, [0, 2]] + 0.5) * sx - 0.5
        boxes[:, [1, 3]] = (boxes[:, [1, 3]] + 0.5) * sy - 0.5
    crops = crop_boxes(flow, boxes, size, scale).astype(np.float16)
    samples = box_samples(flow, boxes).astype(np.float32)
    return crops, samples, n_bad, [fh, fw]


def _resume_split(partial: Path, partial_samples: Path, state_file: Path, phash: str,
                  n: int, size: int) -> tuple[np.memmap, np.memmap, int, int]:  # pragma: no mutate block
    """The split's partial arrays and how far a killed build got (pairs done, non-finite
    values zeroed): reopened when the state matches ``phash`` and the shapes, else new."""
    shape = (n, 2, size, size)
    if partial.is_file() and state_file.is_file():
        try:
            state = json.loads(state_file.read_text())
            if state.get("params_hash") == phash:
                arr = np.lib.format.open_memmap(partial, mode="r+")
                smp = np.lib.format.open_memmap(partial_samples, mode="r+")
                if arr.shape == shape and arr.dtype == np.float16 and len(smp) == n:
                    return arr, smp, int(state["pairs_done"]), int(state.get("nonfinite", 0))
        except (OSError, ValueError, KeyError):
            pass
    arr = np.lib.format.open_memmap(partial, mode="w+", dtype=np.float16, shape=shape)
    smp = np.lib.format.open_memmap(partial_samples, mode="w+", dtype=np.float32,
                                    shape=(n, GRID * GRID, 2))
    state_file.unlink(missing_ok=True)
    return arr, smp, 0, 0


def _pair_bounds(df: pd.DataFrame) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """The rows' pair ids and each pair's [start, end) rows (rows are grouped by pair)."""
    pair_ids = df["pair_id"].astype(str).to_numpy()
    starts = list(np.flatnonzero(np.r_[True, pair_ids[1:] != pair_ids[:-1]])) if len(df) else []
    return pair_ids, list(zip(starts, starts[1:] + [len(df)], strict=False))


def _build_split(
    df: pd.DataFrame, pair_items: PairItems, out_dir: Path, split: str, *,
    size: int, scale: float, image_size: tuple[int, int], progress: bool, checkpoint_every: int,
    label: str = "crops",
) -> dict[str, Any]:  # pragma: no mutate block
    npy, index = crop_paths(out_dir, split)
    phash = _split_hash(df, size, scale, image_size)
    done_file = npy.with_name(f".{split}.done.json")
    samples_file = samples_path(out_dir, split)
    if npy.is_file() and index.is_file() and done_file.is_file() and samples_file.is_file():
        info = json.loads(done_file.read_text())
        if info.get("hash") == phash:
            return info
    out_dir.mkdir(parents=True, exist_ok=True)
    partial = npy.with_name(f".{split}.partial.npy")
    partial_samples = npy.with_name(f".{split}.samples.partial.npy")
    state_file = npy.with_name(f".{split}.progress.json")
    arr, smp, done, n_nonfinite = _resume_split(partial, partial_samples, state_file, phash,
                                                len(df), size)
    pair_ids, bounds = _pair_bounds(df)
    boxes_all = df[list(BOX_COLUMNS)].to_numpy(dtype=np.float64)
    flow_shape = [image_size[1], image_size[0]]
    last_ckpt = time.monotonic()
    with bar(total=len(bounds), initial=done, desc=f"{label}/{split}", unit="pair",
             disable=not progress) as pbar:
        for k in range(done, len(bounds)):
            a, b = bounds[k]
            crops_ab, samples_ab, bad, flow_shape = pair_items(pair_ids[a], boxes_all[a:b])
            n_nonfinite += bad
            arr[a:b] = crops_ab
            smp[a:b] = samples_ab
            pbar.update(1)
            due = bool(checkpoint_every) and (k + 1 - done) % checkpoint_every == 0
            if due or time.monotonic() - last_ckpt > 60:
                arr.flush()
                smp.flush()
                _write_state(state_file, phash, k + 1, n_nonfinite)
                last_ckpt = time.monotonic()
    arr.flush()
    smp.flush()
    del arr, smp
    with atomic_path(index) as tmp:
        df.to_parquet(tmp, index=False)
    os.replace(partial_samples, samples_file)
    os.replace(partial, npy)
    state_file.unlink(missing_ok=True)
    info: dict[str, Any] = {
        "hash": phash, "split": split, "size": size, "scale": scale, "rows": len(df),
        "pairs": len(bounds), "nonfinite_flow_values_zeroed": n_nonfinite,
        "flow_shape": flow_shape,
    }
    write_json(done_file, info)
    return info


class PairCrops(FlowFiles):  # pragma: no mutate block
    """Crops mode (``flow_store: crops``): of each pair's flow keep only its objects' crops and
    flow samples, made from the flow exactly as it would be stored and read back
    (:func:`flowmod.flow.store.roundtrip` at ``dtype`` and ``store_scale``), so that they are
    bit-identical to crops cut from stored flow files. A :func:`flowmod.flow.compute_flow`
    writer: per pair ``<key>.npy`` (n, 2, S, S) float16 (written last: complete means done),
    ``<key>.samples.npy`` (n, G * G, 2) float32 and ``<key>.json`` (non-finite flow values
    zeroed, flow shape); the pair's extra input is its boxes (n x 4 list, ``image_size``
    pixels)."""

    #: 1: crops and samples of :func:`pair_crops` from the stored-flow round trip.
    version = 1

    def __init__(self, dtype: str, store_scale: float, size: int, scale: float,
                 image_size: tuple[int, int] = IMAGE_SIZE) -> None:
        super().__init__(dtype, store_scale)
        self.size, self.scale, self.image_size = int(size), float(scale), tuple(image_size)

    def config(self) -> dict[str, Any]:
        return {"kept": "crops", "version": self.version, "size": self.size,
                "scale": self.scale, "image_size": list(self.image_size)}

    @staticmethod
    def _side(out: Path, what: str) -> Path:
        return out.with_name(f"{out.stem}.{what}")

    def write(self, out: Path, flow: np.ndarray, valid: np.ndarray | None, extra: Any) -> None:
        boxes = np.asarray(extra, dtype=np.float64).reshape(-1, 4)
        stored = roundtrip(flow, self.dtype, self.store_scale, valid)
        self.put(out, *pair_crops(stored, boxes, self.size, self.scale, self.image_size,
                                  out.stem))

    def put(self, out: Path, crops: np.ndarray, samples: np.ndarray, nonfinite: int,
            shape: Sequence[int]) -> None:
        """Write a pair's share (:data:`PairItems`) as its files (the crops last)."""
        with atomic_path(self._side(out, "samples.npy")) as tmp:
            np.save(tmp, np.asarray(samples, np.float32), allow_pickle=False)
        write_json(self._side(out, "json"), {"nonfinite": int(nonfinite),
                                             "flow_shape": [int(v) for v in shape]})
        with atomic_path(out) as tmp:
            np.save(tmp, np.asarray(crops, np.float16), allow_pickle=False)

    def remove(self, out: Path) -> None:
        """Delete a pair's files (the crops first: an incomplete pair is not complete)."""
        for f in (out, self._side(out, "samples.npy"), self._side(out, "json")):
            f.unlink(missing_ok=True)

    def complete(self, out: Path) -> bool:
        return (npy_ok(out, "float16", (None, 2, self.size, self.size))
                and self._side(out, "samples.npy").is_file()
                and self._side(out, "json").is_file())

    def shape(self, out: Path) -> list[int]:
        return [*json.loads(self._side(out, "json").read_text())["flow_shape"], 2]

    def items(self, out: Path, n: int) -> tuple[np.ndarray, np.ndarray, int, list[int]]:
        """A pair's share (:data:`PairItems`) read back from its files; ``n`` boxes expected."""
        crops = np.load(out, allow_pickle=False)
        samples = np.load(self._side(out, "samples.npy"), allow_pickle=False)
        meta = json.loads(self._side(out, "json").read_text())
        if len(crops) != n or len(samples) != n:
            raise CropsError(f"{out}: {len(crops)} crops for {n} objects; rebuild with force")
        return crops, samples, int(meta["nonfinite"]), list(meta["flow_shape"])


def pair_boxes(objects: pd.DataFrame) -> dict[str, list[list[float]]]:
    """``{pair_id: boxes}`` in the objects' order within each pair (the order
    :func:`build_crops` keeps); a pair's objects must all be in one split."""
    spread = objects.groupby("pair_id")["split"].nunique()
    if (spread > 1).any():
        raise CropsError(f"pairs with objects in several splits: {list(spread[spread > 1].index[:5])}")
    return {str(pid): g[list(BOX_COLUMNS)].to_numpy(np.float64).tolist()
            for pid, g in objects.groupby("pair_id", sort=False)}


def make_writer(q: StageParams | Params) -> PairCrops:  # pragma: no mutate block
    """Crops mode's writer under the parameters of ``q``."""
    return PairCrops(q.flow_dtype, q.flow_scale, q.crop_size, q.crop_scale)


def pool_root(q: StageParams | Params, method: str) -> Path:  # pragma: no mutate block
    """``<run>/crops/<method>/pool``: crops mode's per-pair files of every option."""
    return q.run_path / "crops" / method / "pool"


def crops_pool(q: StageParams | Params, method: str) -> Path:  # pragma: no mutate block
    """The folder of crops mode's per-pair files for ``method`` under the options of ``q``
    (``<run>/crops/<method>/pool/<options fingerprint>``)."""
    config = pool_config(method, q.flow_dtype, q.flow_scale, estimator_options(q, method),
                         make_writer(q))
    return pool_root(q, method) / fingerprint(config)


#: A crops-mode node's record of where each pair's rows are (:func:`pool_table`).
POOL_KEYS = "pool_keys.parquet"


def unreferenced_pools(p: Params, variants: bool) -> list[Path]:
    """The crops stage's garbage: crops mode's pool folders of other options than ``p``'s
    (another geometry, flow option or dtype; the nodes themselves keep their arrays; with
    ``flow_store: pairs`` no pool is read). A method with a build in progress keeps its
    folders. ``variants``: no difference (a kept variant holds its own arrays)."""
    out: list[Path] = []
    for root in sorted((p.run_path / "crops").glob("*/pool")):
        m = root.parent.name
        if any(root.parent.glob(".*.building-*")):
            continue
        keep = crops_pool(p, m) if p.flow_store == "crops" and m in p.flow_methods else None
        out += [d for d in sorted(root.iterdir()) if d.is_dir() and d != keep]
    return out


def pool_table(folder: Path, files: Mapping[str, str], writer: PairCrops,
               pool: Path) -> pd.DataFrame:  # pragma: no mutate block
    """Per pair of a crops node built in crops mode: its per-pair file (relative to the
    pool), split, first row and number of rows in the split's arrays, non-finite count and
    flow shape; written as ``<folder>/pool_keys.parquet`` so that the per-pair files can go
    once the node is published and be restored from it (:func:`restore_pool`)."""
    rows = []
    for npy in sorted(folder.glob("*.parquet")):
        if npy.name == POOL_KEYS:
            continue
        split = npy.stem
        ids = pd.read_parquet(npy, columns=["pair_id"])["pair_id"].astype(str).to_numpy()
        # a split's rows are sorted by pair: each pair's rows are one contiguous block
        uniq, first, count = np.unique(ids, return_index=True, return_counts=True)
        for pid, start, n in zip(uniq, first, count, strict=True):
            meta = json.loads(writer._side(pool / files[pid], "json").read_text())
            rows.append({"pair_id": str(pid), "file": files[pid], "split": split,
                         "start": int(start), "n": int(n),
                         "nonfinite": int(meta["nonfinite"]),
                         "flow_h": int(meta["flow_shape"][0]), "flow_w": int(meta["flow_shape"][1])})
    table = pd.DataFrame(rows, columns=["pair_id", "file", "split", "start", "n", "nonfinite",
                                        "flow_h", "flow_w"])
    with atomic_path(folder / POOL_KEYS) as tmp:
        table.to_parquet(tmp, index=False)
    return table


def restore_pool(pool: Path, files: Iterable[str], writer: PairCrops,
                 sources: Iterable[Path]) -> int:  # pragma: no mutate block
    """Write back the per-pair files of ``files`` (relative to ``pool``) that are not
    complete but whose rows a crops node in ``sources`` (published or kept variant, with a
    :func:`pool_table`) holds: a rebuild reuses them instead of computing their flow.
    Returns the number of pairs restored."""
    want = {f for f in files if not writer.complete(pool / f)}
    done = 0
    for src in sources:
        if not want or not (src / POOL_KEYS).is_file():
            continue
        table = pd.read_parquet(src / POOL_KEYS)
        table = table[table["file"].isin(want)]
        for split, rows in table.groupby("split"):
            x, _ = read_crops(src, str(split))
            samples = read_samples(src, str(split))
            for r in rows.itertuples():
                sl = slice(r.start, r.start + r.n)
                writer.put(pool / r.file, x[sl], samples[sl], r.nonfinite, [r.flow_h, r.flow_w])
                want.discard(r.file)
                done += 1
    return done


def _crops_from_flow(q: StageParams, method: str, part: str, pairs: pd.DataFrame,
                     objects: pd.DataFrame, world: str, progress: bool,
                     sources: Sequence[Path] = ()) -> tuple[PairItems, dict[str, str], int]:  # pragma: no mutate block
    """Crops mode: compute each pair's flow (local or Ray executor, as the flow stage) and
    keep its crops (:class:`PairCrops`) in ``<run>/crops/<method>/pool``, after restoring
    the pairs that a node of ``sources`` holds (:func:`restore_pool`). Returns the
    :data:`PairItems` that read them back, ``{pair_id: file}`` and the number of pairs whose
    flow was computed."""
    boxes = pair_boxes(objects)
    pairs = pairs[pairs["pair_id"].astype(str).isin(boxes)]
    writer, pool = make_writer(q), pool_root(q, method)
    extras = {str(pid): boxes[str(pid)] for pid in pairs["pair_id"]}
    planned = pair_files(pairs, method, q.dataroot_path, world, q.flow_dtype, q.flow_scale,
                         writer, extras, digests=pool / DIGESTS, **estimator_options(q, method))
    if not q.force:
        restore_pool(pool, planned.values(), writer, sources)
    idx = compute_flow(pairs, method, pool, dataroot=q.dataroot_path, version=q.version,
                       world=world, dtype=q.flow_dtype, n_jobs=q.n_jobs, progress=progress,
                       force=q.force, store_scale=q.flow_scale, label=f"flow+crops {method}/{part}",
                       executor=q.executor, ray_address=q.ray_address, writer=writer,
                       extras=extras, **estimator_options(q, method))
    files = dict(zip(idx["pair_id"].astype(str), idx["file"], strict=True))

    def items(pid: str, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, list[int]]:
        return writer.items(pool / files[pid], len(b))

    return items, files, int(idx["computed"].sum())


def _write_state(path: Path, phash: str, pairs_done: int, nonfinite: int) -> None:  # pragma: no mutate block
    with atomic_path(path) as tmp:
        state = {"params_hash": phash, "pairs_done": pairs_done, "nonfinite": nonfinite}
        tmp.write_text(json.dumps(state))


def read_crops(folder: str | os.PathLike[str], split: str) -> tuple[np.memmap, pd.DataFrame]:  # pragma: no mutate block
    """Open a split's crops in ``folder`` read-only: ``(x, index)``.

    x: (N, 2, S, S) float16 memmap, pixels; index: the objects' rows in the same order.
    Raises :class:`CropsError` naming both files if either is missing or they disagree.
    """
    npy, index = crop_paths(folder, split)
    for p in (npy, index):
        if not p.is_file():
            raise CropsError(
                f"crop artefact missing: {p} (pair: {npy.name} + {index.name}); "
                "run the crops stage (chapter 05) for this method"
            )
    x = np.load(npy, mmap_mode="r", allow_pickle=False)
    df = pd.read_parquet(index)
    check_crops(x, df, npy, index)
    return x, df


def check_crops(
    x: Any, df: pd.DataFrame, npy: str | os.PathLike[str] = "<array>",
    index: str | os.PathLike[str] = "<index>",
) -> None:  # pragma: no mutate block
    """Raise :class:`CropsError` unless x is (N, 2, S, S) and the index has N rows."""
    shape = tuple(getattr(x, "shape", ()))
    if len(shape) != 4 or shape[1] != 2 or shape[2] != shape[3]:
        raise CropsError(f"{npy}: crops must be (N, 2, S, S), got shape {shape}")
    if shape[0] != len(df):
        raise CropsError(
            f"crop index and array disagree: {index} has {len(df)} rows but {npy} has "
            f"{shape[0]} crops (shape {shape}); rebuild the crops (build_crops(force=True))"
        )


#: The parts of the crops stage (chapter 11's part ``wide``: the training set at every
#: distance, with ``extension_build``).
CROP_PARTS = ("keyframe", "general", WIDE)


def part_splits(part: str, folds: int) -> tuple[str, ...]:
    """The arrays a crops part is stored in: the generalisation set in one (``general``);
    the keyframe and wide parts by split (``train``, ``val``, ``test``; the wide part has no
    test) or, with cross-validation, by fold (``f0`` .. ``f<folds-1>``)."""
    if part == "general":
        return ("general",)
    if folds > 1:
        return tuple(f"f{k}" for k in range(folds))
    return ("train", "val", "test") if part == "keyframe" else ("train", "val")


#: Reads one stored array set: split -> (arrays aligned with the index (None: absent), index)
SplitReader = Callable[[str], tuple[list[Any], pd.DataFrame]]


def crops_reader(folder: str | os.PathLike[str]) -> SplitReader:
    """The :data:`SplitReader` of a crops node: ``[x (N, 2, S, S)], index``."""
    def read(split: str) -> tuple[list[Any], pd.DataFrame]:
        x, df = read_crops(folder, split)
        return [x], df
    return read


def take_rows(arrays: list[Any], keep: np.ndarray) -> list[Any]:
    """The rows ``keep`` (bool mask) of each array (None stays None), in memory."""
    return [None if a is None else np.asarray(a[keep]) for a in arrays]


def concat_arrays(parts: Iterable[list[Any]]) -> list[Any]:
    """Position by position, the concatenation of several array lists (None stays None)."""
    return [None if cols[0] is None else np.concatenate(cols)
            for cols in zip(*parts, strict=True)]


def gather_fold(read: SplitReader, folds: int, fold: int, role: str, part: str = "keyframe"
                ) -> tuple[list[Any], pd.DataFrame]:
    """The rows of a node's arrays (stored by :func:`part_splits`, read by ``read``) that
    play ``role`` (``train``, ``val``, ``test``) for the model of ``fold``
    (:func:`flowmod.select.fold_roles`). One fold reads the split as it is (memmaps);
    cross-validation gathers the rows of the other folds' arrays into memory (train, val) or
    reads the fold's own (test). The generalisation part is one array set: with
    cross-validation, its rows of the fold's scenes."""
    if part == "general":
        arrays, df = read("general")
        if folds == 1:
            return arrays, df
        keep = df["fold"].to_numpy() == fold
        return take_rows(arrays, keep), df[keep].reset_index(drop=True)
    if folds == 1:
        return read(role)
    if role == "test":
        return read(f"f{fold}")
    parts, dfs = [], []
    for k in range(folds):
        if k != fold:
            arrays, df = read(f"f{k}")
            keep = fold_roles(df, fold, folds) == role
            parts.append(take_rows(arrays, keep))
            dfs.append(df[keep])
    return concat_arrays(parts), pd.concat(dfs, ignore_index=True)


def fold_crops(folder: str | os.PathLike[str], folds: int, fold: int, role: str,
               part: str = "keyframe") -> tuple[Any, pd.DataFrame]:
    """``(x (N, 2, S, S), index)``: the flow crops of a crops node that play ``role`` for the
    model of ``fold`` (:func:`gather_fold`)."""
    arrays, df = gather_fold(crops_reader(folder), folds, fold, role, part)
    return arrays[0], df


def part_of(split: str) -> str:
    """The crops part holding ``split`` (``general`` or ``keyframe``)."""
    return "general" if split == "general" else "keyframe"


def part_objects(folder: Path, part: str) -> pd.DataFrame:
    """The objects of a selection node's folder (``select`` for the keyframe part,
    ``general``), each with its split (``general`` for the generalisation set)."""
    objects = read_table(folder, "objects")
    if part == "general":
        objects = objects.assign(split="general")
    if not len(objects):
        objects = pd.DataFrame(columns=["pair_id", "split", *BOX_COLUMNS])
    return objects


def build(b: dag.Build, progress: bool) -> Mapping[str, Any]:  # pragma: no mutate block
    """Build one ``crops[<method>/<part>]`` node: the crops of the part's objects, split by
    split, from the published flow of the same part (``flow_store: pairs``) or computed here
    pair by pair (crops mode; the per-pair files go once the node is published)."""
    q, m, part = b.params, b.node.method, b.node.part
    objects = part_objects(b.input_dir(objects_node(part)), part)
    load, items, files, computed = None, None, {}, None
    work = b.start(fresh=q.force)
    if q.flow_store == "crops":
        pairs = read_table(b.input_dir(objects_node(part)), "pairs")
        # a pair of the same boxes may be in another part's node too (never restored from
        # a node whose files are not what it published)
        sources = [d for other in CROP_PARTS
                   for d in dag.results(b.other(dag.Node("crops", m, other)))
                   if dag.damage(d, read_manifest(d / "manifest.json"),
                                 dag.digest_cache(q.all)) is None]
        items, files, computed = _crops_from_flow(
            q, m, part, pairs, objects,
            world_identity(q, m, b.inputs["world"]["fingerprint"]), progress, sources)
    else:
        load = FlowReader(b.input_dir(dag.Node("flow", m, part)),
                          flow_root(q) / m / "pool", m, part).load
    splits = part_splits(part, q.folds)
    info = build_crops(objects, load, work, pair_items=items, size=q.crop_size,
                       scale=q.crop_scale, splits=splits, progress=progress, label=f"crops {m}")
    if files:
        writer, pool = make_writer(q), pool_root(q, m)
        pool_table(work, files, writer, pool)
        # the published arrays hold every pair's rows: the per-pair files go
        b.after_publish(lambda: [writer.remove(pool / f) for f in files.values()])
    return {"splits": info, "rows": sum(i["rows"] for i in info.values()),
            "flow_computed": computed}


def _inputs(node: dag.Node, p: Params) -> tuple[dag.Node, ...]:
    # crops mode computes the flow itself: the kept flow (figures) is not its input
    if p.flow_store == "pairs":
        return (dag.Node("flow", node.method, node.part), objects_node(node.part))
    return (dag.Node("world"), objects_node(node.part))


def _nodes(p: Params) -> list[dag.Node]:
    return ([dag.Node("crops", m, part) for m in p.flow_methods for part in PARTS]
            + [dag.Node("crops", m, WIDE) for m in p.wide_methods])


#: The crops stage (chapter 05; chapter 11's part with extension_build).
STAGE = dag.Stage("crops", 4, "05", "crops/{method}/{part}", "flow crops around every object",
                  nodes=_nodes, inputs=_inputs, build=build,
                  parts={WIDE: ("11", "extension_build")},
                  outputs=("{split}.npy", "{split}.parquet", "{split}.samples.npy", POOL_KEYS),
                  garbage=unreferenced_pools)
