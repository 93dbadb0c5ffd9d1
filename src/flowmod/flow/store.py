"""Flow on disk: Middlebury .flo, .npy (float16/float32, atomic), storage at a reduced scale.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np

from flowmod.artefacts import atomic_path
from flowmod.flow.registry import FlowFileError

FLO_MAGIC = 202021.25


def check_flow(flow: np.ndarray, what: str = "flow") -> None:
    if not (isinstance(flow, np.ndarray) and flow.ndim == 3 and flow.shape[2] == 2):
        raise ValueError(f"{what} must be an (H, W, 2) array, got {getattr(flow, 'shape', flow)}")


def write_flo(path: str | os.PathLike[str], flow: np.ndarray) -> None:
    """Write (H, W, 2) flow in the Middlebury .flo format (little-endian float32), atomically."""
    check_flow(flow)
    h, w = flow.shape[:2]
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.array([FLO_MAGIC], "<f4").tofile(f)
        np.array([w, h], "<i4").tofile(f)
        np.ascontiguousarray(flow, dtype="<f4").tofile(f)


def read_flo(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a Middlebury .flo file -> (H, W, 2) float32; :class:`FlowFileError` if invalid."""
    data = Path(path).read_bytes()
    if len(data) < 12 or np.frombuffer(data[:4], "<f4")[0] != np.float32(FLO_MAGIC):
        raise FlowFileError(f"{path}: not a .flo file (magic number 202021.25 missing)")
    w, h = (int(x) for x in np.frombuffer(data[4:12], "<i4"))
    if w <= 0 or h <= 0 or len(data) != 12 + 8 * w * h:
        raise FlowFileError(
            f"{path}: corrupt .flo file ({w}x{h} needs {12 + 8 * max(w * h, 0)} bytes, "
            f"has {len(data)})"
        )
    return np.frombuffer(data[12:], "<f4").reshape(h, w, 2).astype(np.float32)


def save_flow_npy(path: str | os.PathLike[str], flow: np.ndarray, dtype: str = "float16") -> None:
    """Save (H, W, 2) flow as .npy of ``dtype`` (float16 / float32), atomically.

    For float16, values beyond its range (+-65504 px: only invalid pixels, e.g. points that
    pass behind the camera) are clipped instead of becoming inf.
    """
    check_flow(flow)
    with atomic_path(path) as tmp:
        np.save(tmp, as_stored(flow, dtype), allow_pickle=False)


def load_flow_npy(path: str | os.PathLike[str]) -> np.ndarray:
    """Load a .npy flow -> (H, W, 2) float32; :class:`FlowFileError` naming a bad file."""
    try:
        arr = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise
    except Exception as e:  # noqa: BLE001 - truncated, garbage, pickled...: name the file
        raise FlowFileError(
            f"{path}: corrupt or truncated flow file ({type(e).__name__}: {e})"
        ) from e
    if arr.ndim != 3 or arr.shape[2] != 2:
        raise FlowFileError(f"{path}: expected an (H, W, 2) flow, found shape {arr.shape}")
    return arr.astype(np.float32)


def npy_header(path: Path) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """(shape, fortran_order, dtype, data offset) from a .npy header, without reading data."""
    fmt = np.lib.format
    with open(path, "rb") as f:
        version = fmt.read_magic(f)
        if version == (1, 0):
            shape, fortran, dt = fmt.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, fortran, dt = fmt.read_array_header_2_0(f)
        else:
            raise ValueError(f"unsupported .npy version {version}")
        return tuple(shape), bool(fortran), np.dtype(dt), f.tell()


def npy_ok(path: Path, dtype: str, like: tuple[int | None, ...] = (None, None, 2)) -> bool:
    """True if ``path`` is a complete .npy of a ``dtype`` array shaped ``like`` (None: any
    length; default an (H, W, 2) flow), checked from its header and file size."""
    try:
        shape, fortran, dt, offset = npy_header(path)
        size = path.stat().st_size
    except Exception:  # noqa: BLE001 - anything unreadable is simply not done
        return False
    return (
        dt == np.dtype(dtype)
        and len(shape) == len(like)
        and all(n is None or n == k for n, k in zip(like, shape, strict=True))
        and not fortran
        and size == offset + math.prod(shape) * dt.itemsize
    )


def full_shape(stored: tuple[int, ...], store_scale: float) -> tuple[int, int]:
    """(H, W) of the image whose flow was stored at ``store_scale`` with shape ``stored``."""
    return int(round(stored[0] / store_scale)), int(round(stored[1] / store_scale))


def valid_path(path: str | os.PathLike[str]) -> Path:
    """Where the valid mask of the flow file ``path`` is kept (``<stem>.valid.npy``)."""
    p = Path(path)
    return p.with_name(p.stem + ".valid.npy")


def reduce(flow: np.ndarray, store_scale: float, valid: np.ndarray | None = None,
           check: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Flow (H, W, 2) px at ``store_scale`` of its size, values kept in pixels of the full
    image: areas averaged (cv2 INTER_AREA); with a ``valid`` mask (H, W) bool, valid pixels
    only where a reduced pixel covers any (invalid values never leak into valid ones), and
    the reduced mask (valid where at least half of the area is). Returns (flow, mask).
    ``check``: refuse a scale from which the full size cannot be recovered (a stored file
    records only the scale)."""
    flow = np.asarray(flow, np.float32)
    if store_scale == 1.0:
        return flow, valid
    h, w = flow.shape[:2]
    size = (max(1, int(round(h * store_scale))), max(1, int(round(w * store_scale))))
    if check and full_shape(size, store_scale) != (h, w):
        raise ValueError(f"store_scale={store_scale} cannot store a {h}x{w} flow so that its "
                         "size is recovered; use a scale like 0.5 or 0.25")
    area = cv2.resize(flow, size[::-1], interpolation=cv2.INTER_AREA)
    if valid is None:
        return area, None
    m = np.asarray(valid, np.float32)
    cover = cv2.resize(m, size[::-1], interpolation=cv2.INTER_AREA)
    num = cv2.resize(flow * m[..., None], size[::-1], interpolation=cv2.INTER_AREA)
    with np.errstate(divide="ignore", invalid="ignore"):
        area = np.where(cover[..., None] > 0, num / cover[..., None], area)
    return area.astype(np.float32), cover >= 0.5


def restore(stored: np.ndarray, store_scale: float,
            size: tuple[int, int] | None = None) -> np.ndarray:
    """Stored flow back at full image size (bilinear; ``size`` (H, W), else recovered from
    the scale), float32, pixels."""
    stored = np.asarray(stored, np.float32)
    if store_scale == 1.0 and size is None:
        return stored
    h, w = size or full_shape(stored.shape, store_scale)
    return cv2.resize(stored, (w, h), interpolation=cv2.INTER_LINEAR)


def as_stored(flow: np.ndarray, dtype: str) -> np.ndarray:
    """Flow cast to the storage dtype; for float16, values beyond its range (+-65504 px) are
    clipped instead of becoming inf."""
    if dtype not in ("float16", "float32"):
        raise ValueError(f"dtype={dtype!r}; allowed: float16, float32")
    if dtype == "float16":
        big = float(np.finfo(np.float16).max)
        flow = np.clip(flow, -big, big)
    return np.ascontiguousarray(flow, dtype=dtype)


def roundtrip(flow: np.ndarray, dtype: str = "float16", store_scale: float = 1.0,
              valid: np.ndarray | None = None) -> np.ndarray:
    """What :func:`load_stored_flow` returns for ``flow`` stored by :func:`store_flow` (with
    its ``valid`` mask, if any), without the file: the same reduction, dtype and
    restoration, bit for bit (for any image size: the restoration goes back to ``flow``'s
    own size)."""
    small = as_stored(reduce(flow, store_scale, valid, check=False)[0], dtype)
    return restore(small, store_scale, size=flow.shape[:2])


def store_flow(path: str | os.PathLike[str], flow: np.ndarray, dtype: str = "float16",
               store_scale: float = 1.0, valid: np.ndarray | None = None) -> None:
    """Save flow (H, W, 2) px at ``store_scale`` of its size (:func:`reduce`), values kept in
    pixels of the full image, so :func:`load_stored_flow` can restore the full size; with a
    ``valid`` mask the mask is stored too, before the flow, so a complete flow file always
    has its mask."""
    small, mask = reduce(flow, store_scale, valid)
    if mask is not None:
        with atomic_path(valid_path(path)) as tmp:
            np.save(tmp, np.asarray(mask, dtype=bool), allow_pickle=False)
    save_flow_npy(path, small, dtype)


def load_stored_valid(path: str | os.PathLike[str], store_scale: float = 1.0
                      ) -> np.ndarray | None:
    """The valid mask stored beside the flow file ``path`` at full image size (nearest
    neighbour), or None when the method has none (estimated flow)."""
    vp = valid_path(path)
    if not vp.is_file():
        return None
    m = np.load(vp, allow_pickle=False)
    if store_scale == 1.0:
        return m
    h, w = full_shape(m.shape, store_scale)
    return cv2.resize(m.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)


def load_stored_flow(path: str | os.PathLike[str], store_scale: float = 1.0) -> np.ndarray:
    """A flow file written by :func:`store_flow`: (H, W, 2) float32, pixels of the full image,
    frame 1 -> 2 (bilinearly restored to full size when stored at a reduced scale)."""
    return restore(load_flow_npy(path), store_scale)
