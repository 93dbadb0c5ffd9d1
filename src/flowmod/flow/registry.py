"""Flow estimators' common ground: errors, image reading, flow resizing, the base class and the
registry (``get_estimator(name, **options)``).

Every estimator turns two (H, W, 3) uint8 BGR images (as cv2.imread gives) into (H, W, 2)
float32 flow in pixels, frame 1 -> frame 2. ``scale`` (all image methods): compute on images
resized by this factor, then resize the flow back, multiplying u and v by the size ratios.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, Literal

import cv2
import numpy as np

# --------------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------------


class FlowFileError(ValueError):
    """A flow file (.npy or .flo) is corrupt, truncated or of the wrong shape (names the file)."""


class ImageError(FileNotFoundError):
    """Images are missing or cannot be decoded (names the first few and the count)."""


class MissingWeightsError(FileNotFoundError):
    """A network method has no trained weights; the message says which file to put where."""


class NotSyntheticError(ValueError):
    """The ``gt`` method was asked for on a dataroot that is not a generated world."""


# --------------------------------------------------------------------------------------------
# images and flow resizing
# --------------------------------------------------------------------------------------------


#: What libjpeg says of data it decodes anyway (OpenCV only prints it): a corrupt image.
_DECODER_WARNING = re.compile(r"(Corrupt JPEG data|Premature end of JPEG|Invalid JPEG|"
                              r"Bogus|Warning: unknown JFIF)[^\n]*")
_STDERR = threading.Lock()


def decode(path: str | os.PathLike[str], flags: int = cv2.IMREAD_COLOR
           ) -> tuple[np.ndarray | None, str | None]:
    """``cv2.imread(path, flags)`` and the decoder's first complaint (libjpeg's "Corrupt
    JPEG data ..." warnings go to the process's stderr, which is captured meanwhile and
    passed on otherwise unchanged); None where it had none."""
    with _STDERR, tempfile.TemporaryFile() as cap:
        sys.stderr.flush()
        saved = os.dup(2)
        try:
            os.dup2(cap.fileno(), 2)
            img = cv2.imread(str(path), flags)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        cap.seek(0)
        said = cap.read().decode(errors="replace")
    found = _DECODER_WARNING.search(said)
    rest = _DECODER_WARNING.sub("", said).strip()
    if rest:
        print(rest, file=sys.stderr)
    return img, found.group(0).strip() if found else None


def read_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read an image as cv2.imread does: (H, W, 3) uint8 BGR; :class:`ImageError` if it is
    missing, cannot be decoded, or decodes with the decoder's warnings (corrupt data)."""
    img, warning = decode(path)
    if img is None:
        what = "missing" if not Path(path).is_file() else "cannot be decoded"
        raise ImageError(f"image {what}: {path}")
    if warning:
        raise ImageError(f"image corrupt ({warning}): {path}; restore the file from the data set")
    return img


def check_pair(img1: np.ndarray, img2: np.ndarray) -> None:
    for name, img in (("img1", img1), ("img2", img2)):
        if not (isinstance(img, np.ndarray) and img.ndim == 3 and img.shape[2] == 3):
            raise ValueError(
                f"{name} must be an (H, W, 3) BGR image, got {getattr(img, 'shape', img)}"
            )
        if img.dtype != np.uint8:
            raise ValueError(f"{name} must be uint8 (as cv2.imread gives), got {img.dtype}")
    if img1.shape != img2.shape:
        raise ValueError(f"images differ in size: {img1.shape} vs {img2.shape}")


def resize_flow(flow: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize ``flow`` (h, w, 2) to ``size`` = (H, W), bilinear; u *= W / w, v *= H / h."""
    h, w = flow.shape[:2]
    hh, ww = size
    if (h, w) == (hh, ww):
        return flow.astype(np.float32, copy=False)
    out = cv2.resize(flow.astype(np.float32, copy=False), (ww, hh), interpolation=cv2.INTER_LINEAR)
    out[..., 0] *= ww / w
    out[..., 1] *= hh / h
    return out


def _scaled_size(shape: tuple[int, ...], scale: float) -> tuple[int, int]:
    return max(1, round(shape[0] * scale)), max(1, round(shape[1] * scale))


def resize_image(img: np.ndarray, scale: float) -> np.ndarray:
    if scale == 1.0:
        return img
    h, w = _scaled_size(img.shape, scale)
    interp = cv2.INTER_AREA if scale < 1.0 else cv2.INTER_LINEAR
    return cv2.resize(img, (w, h), interpolation=interp)


# --------------------------------------------------------------------------------------------
# estimators
# --------------------------------------------------------------------------------------------


class FlowEstimator:
    """Base class: ``estimate(img1, img2) -> (H, W, 2) float32`` flow in pixels, 1 -> 2.

    Class attributes: ``name`` (registry key), ``inputs`` ("images", or "tokens" for methods
    that work from sample_data tokens), ``cpu_bound`` (the stage runner parallelises pairs over
    processes; otherwise it runs batches sequentially).
    """

    name: ClassVar[str] = ""
    #: Bump when a change of the estimator's code changes its flow (invalidates cached files).
    code_version: ClassVar[int] = 1
    inputs: ClassVar[Literal["images", "tokens"]] = "images"
    cpu_bound: ClassVar[bool] = True
    #: Options naming a file (weights) whose content the flow depends on: a pool keys them
    #: by their sha256 as well as their name.
    file_options: ClassVar[tuple[str, ...]] = ()
    #: Files of the data's version folder that a token method reads (its pairs' keys hold
    #: their digests, not the whole data set's identity).
    world_files: ClassVar[tuple[str, ...]] = ()

    def __init__(self, scale: float = 1.0) -> None:
        if not (0.0 < float(scale) <= 4.0):
            raise ValueError(f"{self.name}: scale={scale} must be in (0, 4]")
        self.scale = float(scale)

    # subclasses implement this on (already rescaled) images
    def _estimate(self, img1: np.ndarray, img2: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def estimate(self, img1: np.ndarray, img2: np.ndarray) -> np.ndarray:
        """Flow (H, W, 2) float32 in pixels from (H, W, 3) uint8 BGR ``img1`` to ``img2``."""
        check_pair(img1, img2)
        flow = self._estimate(resize_image(img1, self.scale), resize_image(img2, self.scale))
        return resize_flow(flow, img1.shape[:2])

    def estimate_batch(
        self, img1s: Sequence[np.ndarray], img2s: Sequence[np.ndarray]
    ) -> list[np.ndarray]:
        """``[estimate(a, b) for a, b in zip(img1s, img2s)]``; networks batch this."""
        if len(img1s) != len(img2s):
            raise ValueError(f"{len(img1s)} first images but {len(img2s)} second images")
        return [self.estimate(a, b) for a, b in zip(img1s, img2s, strict=True)]

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={describe_option(v)}" for k, v in self.options().items())
        return f"{type(self).__name__}({opts})"

    def options(self) -> dict[str, Any]:
        """The options that change the result (recorded beside the cache)."""
        return {"scale": self.scale}


REGISTRY: dict[str, type[FlowEstimator]] = {}


def register_estimator(cls: type[FlowEstimator]) -> type[FlowEstimator]:
    """Class decorator: make ``cls`` available as ``get_estimator(cls.name)``."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    REGISTRY[cls.name] = cls
    return cls


def available_methods() -> list[str]:
    """Registered method names."""
    return sorted(REGISTRY)


def get_estimator(name: str, **options: Any) -> FlowEstimator:
    """Build the estimator ``name`` with ``options`` (see the module docstring)."""
    if name not in REGISTRY:
        raise ValueError(f"unknown flow method {name!r}; known: {', '.join(available_methods())}")
    try:
        return REGISTRY[name](**options)
    except TypeError as e:
        if "argument" in str(e):
            raise TypeError(f"flow method {name!r}: {e}") from e
        raise


def _gray(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)



def describe_option(v: Any) -> Any:
    if isinstance(v, Mapping):
        return "<state_dict>"
    if isinstance(v, (str, int, float, bool)) or v is None:
        return v
    return str(v)

