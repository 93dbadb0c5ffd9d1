"""Paper preprocessing (Sec. III-C): flow crops around each vehicle's 2D box.

For every object: a square of side ``max(w, h)`` about the box centre, its side multiplied by
``scale`` (3 in the paper), edge padding (``cv2.BORDER_REPLICATE``) where it leaves the frame,
crop, bilinear resize (``cv2.resize`` ``INTER_LINEAR``) to ``S x S``. Flow values are kept as
they are (pixels of the flow grid; not rescaled by the resize), as in the paper.

Window convention (documented choice; the original code used ``floor``/``ceil`` bounds with an
inclusive end, which gives windows 1-2 px larger and sometimes not square): pixel ``i`` covers
``[i, i + 1)``; the window is ``n = max(1, round(scale * max(w, h)))`` pixels on each side,
starting at ``round(c - n / 2)`` (halves rounded up) for the box centre ``c``.

Artefacts (``build_crops``): ``<out_dir>/<method>/<split>.npy``, an ``(N, 2, S, S)`` float16
array (channel 0 = u, 1 = v, pixels), and ``<split>.parquet``, the objects' rows in the same
order. :func:`open_crops` opens both and checks that they agree.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np
import pandas as pd

from flowmod.artefacts import atomic_path, is_up_to_date, manifest_path, mark_done

#: Bump when the crop geometry or the file layout changes (invalidates built crops).
CROPS_VERSION = 1
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
    x0 = _round_half_up(cx - n / 2)
    y0 = _round_half_up(cy - n / 2)
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


def hflip(x: T) -> T:
    """Horizontal flip of flow crops, on a copy: mirror the width axis and negate u.

    x: (..., 2, S, S) numpy array or torch tensor (channel 0 = u). The input is never
    modified (the original code flipped a view in place and corrupted its cached crops).
    Applying it twice gives the input back exactly.
    """
    if isinstance(x, np.ndarray):
        out = x[..., ::-1].copy()
        np.negative(out[..., 0, :, :], out=out[..., 0, :, :])
        return out  # type: ignore[return-value]
    import torch

    if isinstance(x, torch.Tensor):
        out_t = torch.flip(x, dims=(-1,))  # torch.flip always copies
        out_t[..., 0, :, :].neg_()
        return out_t  # type: ignore[return-value]
    raise TypeError(f"hflip expects a numpy array or a torch tensor, got {type(x).__name__}")


# --- I/O: building and opening the crop artefacts -------------------------------------------


def _load_flow(flow_dir: Path, method: str, pair_id: str) -> np.ndarray:
    """One pair's flow, (H, W, 2) float32 pixels (via :func:`flowmod.flow.load_flow`)."""
    from flowmod.flow import load_flow

    try:
        return load_flow(flow_dir, method, pair_id)
    except FileNotFoundError:
        path = Path(flow_dir) / method / f"{pair_id}.npy"
        raise CropsError(
            f"flow file missing: {path} (run the flow stage for method {method!r}; crops cannot "
            "be rebuilt once full-frame flow was deleted)"
        ) from None


def crop_paths(out_dir: str | os.PathLike[str], method: str, split: str) -> tuple[Path, Path]:
    """``(<out_dir>/<method>/<split>.npy, <out_dir>/<method>/<split>.parquet)``."""
    d = Path(out_dir) / method
    return d / f"{split}.npy", d / f"{split}.parquet"


def _split_hash(
    objects: pd.DataFrame, method: str, size: int, scale: float, image_size: tuple[int, int],
    flow_dir: Path,
) -> str:
    """Parameters + identity of the split's objects (+ the flow index's stat, if present)."""
    h = hashlib.sha256()
    flow_index = Path(flow_dir) / method / "index.parquet"
    stamp = None
    if flow_index.is_file():
        st = flow_index.stat()
        stamp = [st.st_size, st.st_mtime_ns]
    meta = {
        "version": CROPS_VERSION, "method": method, "size": int(size), "scale": float(scale),
        "image_size": list(image_size), "columns": list(map(str, objects.columns)),
        "flow_index": stamp,
    }
    h.update(json.dumps(meta, sort_keys=True).encode())
    h.update(pd.util.hash_pandas_object(objects, index=False).to_numpy().tobytes())
    return h.hexdigest()[:16]


def _check_objects(objects: pd.DataFrame) -> None:
    need = {"pair_id", "split", *BOX_COLUMNS}
    missing = sorted(need - set(objects.columns))
    if missing:
        raise CropsError(f"objects table lacks columns {missing} (have {list(objects.columns)})")


def build_crops(
    objects: pd.DataFrame,
    flow_dir: str | os.PathLike[str],
    method: str,
    out_dir: str | os.PathLike[str],
    *,
    size: int,
    scale: float = 3.0,
    image_size: tuple[int, int] = IMAGE_SIZE,
    force: bool = False,
    progress: bool = True,
    checkpoint_every: int = 200,
) -> dict[str, Path]:
    """Crop every object of ``objects`` from its pair's flow; one artefact pair per split.

    objects: one row per (pair, vehicle) with pair_id, split and the box (xmin, ymin, xmax,
    ymax in pixels of ``image_size`` = (width, height)); if a flow file has another
    resolution (flow computed at a reduced scale), boxes are scaled to its grid and the flow
    values are used as stored. Non-finite flow values (invalid pixels) become 0.

    Writes ``<out_dir>/<method>/<split>.npy`` (N, 2, S, S) float16 (filled through a
    memmap under a temporary name, renamed when complete) and ``<split>.parquet`` (the
    objects' rows, sorted by pair_id, in array order). Each flow file is read once. A split
    whose outputs are up to date (same size, scale, method, objects, flow index) is skipped;
    an interrupted split resumes from its last checkpoint (every ``checkpoint_every`` pairs).
    Returns ``{split: path of the .npy}``.
    """
    _check_objects(objects)
    flow_dir = Path(flow_dir)
    out: dict[str, Path] = {}
    for split in sorted(objects["split"].astype(str).unique()):
        sel = objects[objects["split"].astype(str) == split]
        # Stable sort by pair: each pair's rows are contiguous, its flow is read once.
        df = sel.sort_values("pair_id", kind="mergesort").reset_index(drop=True)
        out[split] = _build_split(
            df, flow_dir, method, Path(out_dir), split, size=size, scale=scale,
            image_size=image_size, force=force, progress=progress,
            checkpoint_every=checkpoint_every,
        )
    return out


def _build_split(
    df: pd.DataFrame, flow_dir: Path, method: str, out_dir: Path, split: str, *, size: int,
    scale: float, image_size: tuple[int, int], force: bool, progress: bool,
    checkpoint_every: int,
) -> Path:
    from tqdm.auto import tqdm

    npy, index = crop_paths(out_dir, method, split)
    phash = _split_hash(df, method, size, scale, image_size, flow_dir)
    if not force and is_up_to_date(npy, phash) and is_up_to_date(index, phash):
        return npy
    npy.parent.mkdir(parents=True, exist_ok=True)
    partial = npy.with_name(f".{split}.partial.npy")
    state_file = npy.with_name(f".{split}.progress.json")
    shape = (len(df), 2, size, size)

    pair_ids = df["pair_id"].astype(str).to_numpy()
    starts = np.flatnonzero(np.r_[True, pair_ids[1:] != pair_ids[:-1]]) if len(df) else []
    bounds = list(zip(starts, list(starts[1:]) + [len(df)], strict=True))

    done, n_nonfinite = 0, 0
    arr = None
    if not force and partial.is_file() and state_file.is_file():
        try:
            state = json.loads(state_file.read_text())
            if state.get("params_hash") == phash:
                arr = np.lib.format.open_memmap(partial, mode="r+")
                if arr.shape != shape or arr.dtype != np.float16:
                    arr = None
                else:
                    done = int(state["pairs_done"])
                    n_nonfinite = int(state.get("nonfinite", 0))
        except (OSError, ValueError, KeyError):
            arr = None
    if arr is None:
        arr = np.lib.format.open_memmap(partial, mode="w+", dtype=np.float16, shape=shape)
        done, n_nonfinite = 0, 0
        state_file.unlink(missing_ok=True)

    boxes_all = df[list(BOX_COLUMNS)].to_numpy(dtype=np.float64)
    flow_shape = [image_size[1], image_size[0]]
    last_ckpt = time.monotonic()
    bar = tqdm(
        total=len(bounds), initial=done, desc=f"crops {method}/{split}", unit="pair",
        disable=not progress,
    )
    try:
        for k in range(done, len(bounds)):
            a, b = bounds[k]
            flow = _load_flow(flow_dir, method, pair_ids[a])
            bad = ~np.isfinite(flow)
            if bad.any():
                n_nonfinite += int(bad.sum())
                flow = np.where(bad, np.float32(0), flow)
            boxes = boxes_all[a:b].copy()
            fh, fw = flow.shape[:2]
            flow_shape = [fh, fw]
            if (fw, fh) != tuple(image_size):
                sx, sy = fw / image_size[0], fh / image_size[1]
                if abs(fh - sx * image_size[1]) > 1.5:  # more than rounding of a rescale
                    raise CropsError(
                        f"flow of pair {pair_ids[a]} is {fw}x{fh} (WxH), not the "
                        f"{image_size[0]}x{image_size[1]} image (or a rescaled copy): padded "
                        "flow not unpadded? (RAFT pads 900 rows to 904)"
                    )
                boxes[:, [0, 2]] *= sx
                boxes[:, [1, 3]] *= sy
            arr[a:b] = crop_boxes(flow, boxes, size, scale)
            bar.update(1)
            due = bool(checkpoint_every) and (k + 1 - done) % checkpoint_every == 0
            if due or time.monotonic() - last_ckpt > 60:
                arr.flush()
                _write_state(state_file, phash, k + 1, n_nonfinite)
                last_ckpt = time.monotonic()
    finally:
        bar.close()
    arr.flush()
    del arr
    with atomic_path(index) as tmp:
        df.to_parquet(tmp, index=False)
    os.replace(partial, npy)
    state_file.unlink(missing_ok=True)
    info: dict[str, Any] = {
        "method": method, "split": split, "size": size, "scale": scale, "rows": len(df),
        "pairs": len(bounds), "nonfinite_flow_values_zeroed": n_nonfinite,
        "flow_shape": flow_shape,
    }
    mark_done(index, phash, **info)
    mark_done(npy, phash, **info)
    return npy


def _write_state(path: Path, phash: str, pairs_done: int, nonfinite: int) -> None:
    with atomic_path(path) as tmp:
        state = {"params_hash": phash, "pairs_done": pairs_done, "nonfinite": nonfinite}
        tmp.write_text(json.dumps(state))


def open_crops(
    out_dir: str | os.PathLike[str], method: str, split: str
) -> tuple[np.memmap, pd.DataFrame]:
    """Open a split's crops read-only: ``(x, index)``.

    x: (N, 2, S, S) float16 memmap, pixels; index: the objects' rows in the same order.
    Raises :class:`CropsError` naming both files if either is missing or they disagree.
    """
    npy, index = crop_paths(out_dir, method, split)
    for p in (npy, index):
        if not p.is_file():
            raise CropsError(
                f"crop artefact missing: {p} (pair: {npy.name} + {index.name}); "
                "run build_crops (stage 05) for this method"
            )
    x = np.load(npy, mmap_mode="r", allow_pickle=False)
    df = pd.read_parquet(index)
    check_crops(x, df, npy, index)
    return x, df


def check_crops(
    x: Any, df: pd.DataFrame, npy: str | os.PathLike[str] = "<array>",
    index: str | os.PathLike[str] = "<index>",
) -> None:
    """Raise :class:`CropsError` unless x is (N, 2, S, S) and the index has N rows."""
    shape = tuple(getattr(x, "shape", ()))
    if len(shape) != 4 or shape[1] != 2 or shape[2] != shape[3]:
        raise CropsError(f"{npy}: crops must be (N, 2, S, S), got shape {shape}")
    if shape[0] != len(df):
        raise CropsError(
            f"crop index and array disagree: {index} has {len(df)} rows but {npy} has "
            f"{shape[0]} crops (shape {shape}); rebuild the crops (build_crops(force=True))"
        )


def crops_manifest(out_dir: str | os.PathLike[str], method: str, split: str) -> dict[str, Any]:
    """The build record of a split (rows, pairs, size, zeroed flow values...), or {}."""
    m = manifest_path(crop_paths(out_dir, method, split)[0])
    return json.loads(m.read_text()) if m.is_file() else {}


# --- the stage (notebook 05) ----------------------------------------------------------------


def crops_dir(params: Any) -> Path:
    """``<run_dir>/crops``."""
    return params.run_path / "crops"


def stage_objects(objects: pd.DataFrame) -> pd.DataFrame:
    """Objects with the generalisation set as its own split ``general`` (keyframe objects keep
    train / val / test)."""
    out = objects.copy()
    out.loc[out["set"] == "general", "split"] = "general"
    return out


def run(params: Any, objects: pd.DataFrame, progress: bool = True) -> dict[str, dict[str, Path]]:
    """Crops of every object for each flow method of the profile: ``{method: {split: npy}}``."""
    from flowmod.flow import flow_dir

    obj = stage_objects(objects)
    return {
        m: build_crops(obj, flow_dir(params), m, crops_dir(params), size=params.crop_size,
                       scale=params.crop_scale, force=params.force, progress=progress)
        for m in params.flow_methods
    }


def storage_table(params: Any) -> pd.DataFrame:
    """Disk used per item: crops per object vs full-frame flow per pair, for each method."""
    from flowmod.flow import flow_dir

    rows = []
    for m in params.flow_methods:
        npys = sorted((crops_dir(params) / m).glob("*.npy"))
        n_obj = sum(int(np.load(p, mmap_mode="r").shape[0]) for p in npys)
        crop_bytes = sum(p.stat().st_size for p in npys)
        flows = list((flow_dir(params) / m).glob("*.npy"))
        flow_bytes = sum(p.stat().st_size for p in flows)
        rows.append({
            "method": m, "objects": n_obj, "crops total (MB)": crop_bytes / 1e6,
            "per object (kB)": crop_bytes / max(n_obj, 1) / 1e3, "flow pairs": len(flows),
            "flow total (MB)": flow_bytes / 1e6,
            "flow per pair (MB)": flow_bytes / max(len(flows), 1) / 1e6,
            "original: float32 flow per pair (MB)": IMAGE_SIZE[0] * IMAGE_SIZE[1] * 2 * 4 / 1e6,
        })
    return pd.DataFrame(rows).round(2)
