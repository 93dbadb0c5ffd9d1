"""Optical flow: estimator registry, the flow stage runner, flow I/O, colour coding, metrics.

Estimators (``get_estimator(name, **options)``) share one interface::

    est = get_estimator("dis", preset="medium", scale=0.5)
    flow = est.estimate(img1, img2)   # img: (H, W, 3) uint8 BGR as cv2.imread gives
                                      # flow: (H, W, 2) float32, pixels, frame1 -> frame2

=============  =======================================================  ==================
name           what                                                     options
=============  =======================================================  ==================
gt             the synthetic world's exact flow (from sample_data        dataroot, version
               tokens, not images: ``estimate_tokens``)
dis            OpenCV DIS on grayscale                                  preset, scale
farneback      OpenCV Farneback on grayscale                            scale, pyr_scale...
raft           torchvision ``raft_large`` with trained weights          weights, scale,
raft_small     torchvision ``raft_small`` with trained weights          device, batch_size,
fastflownet    FastFlowNet in plain PyTorch (:mod:`flowmod.flow_nets`)  num_flow_updates
=============  =======================================================  ==================

``scale`` (all image methods): compute on images resized by this factor, then resize the flow
back to full size, multiplying u and v by the size ratios. Network methods never run from
random weights: without a weights file they raise :class:`MissingWeightsError` saying which
file to put where.

The stage runner :func:`compute_flow` writes ``<out_dir>/<method>/<pair_id>.npy`` and
``<out_dir>/<method>/index.parquet`` (DESIGN section 2), resumable and atomic. torch is only
imported by the network methods and the colour coding.
"""

from __future__ import annotations

import concurrent.futures
import functools
import inspect
import json
import logging
import math
import os
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal

import cv2
import numpy as np
import pandas as pd

from flowmod.artefacts import atomic_path
from flowmod.environment import resolve_device

if TYPE_CHECKING:
    import torch

    from flowmod.params import Params

log = logging.getLogger(__name__)

__all__ = [
    "FlowEstimator",
    "FlowFileError",
    "ImageError",
    "MissingWeightsError",
    "NotSyntheticError",
    "available_methods",
    "boxes_mask",
    "check_images",
    "compute_flow",
    "endpoint_error",
    "epe",
    "estimator_options",
    "fl_all",
    "flow_metrics",
    "flow_to_color",
    "get_estimator",
    "load_flow",
    "load_flow_npy",
    "read_flo",
    "read_image",
    "register_estimator",
    "resize_flow",
    "save_flow_npy",
    "write_flo",
]

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


def read_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read an image as cv2.imread does: (H, W, 3) uint8 BGR; :class:`ImageError` if unusable."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        what = "missing" if not Path(path).is_file() else "cannot be decoded"
        raise ImageError(f"image {what}: {path}")
    return img


def _check_pair(img1: np.ndarray, img2: np.ndarray) -> None:
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


def _resize_image(img: np.ndarray, scale: float) -> np.ndarray:
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
    inputs: ClassVar[Literal["images", "tokens"]] = "images"
    cpu_bound: ClassVar[bool] = True

    def __init__(self, scale: float = 1.0) -> None:
        if not (0.0 < float(scale) <= 4.0):
            raise ValueError(f"{self.name}: scale={scale} must be in (0, 4]")
        self.scale = float(scale)

    # subclasses implement this on (already rescaled) images
    def _estimate(self, img1: np.ndarray, img2: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def estimate(self, img1: np.ndarray, img2: np.ndarray) -> np.ndarray:
        """Flow (H, W, 2) float32 in pixels from (H, W, 3) uint8 BGR ``img1`` to ``img2``."""
        _check_pair(img1, img2)
        flow = self._estimate(_resize_image(img1, self.scale), _resize_image(img2, self.scale))
        return resize_flow(flow, img1.shape[:2])

    def estimate_batch(
        self, img1s: Sequence[np.ndarray], img2s: Sequence[np.ndarray]
    ) -> list[np.ndarray]:
        """``[estimate(a, b) for a, b in zip(img1s, img2s)]``; networks batch this."""
        if len(img1s) != len(img2s):
            raise ValueError(f"{len(img1s)} first images but {len(img2s)} second images")
        return [self.estimate(a, b) for a, b in zip(img1s, img2s, strict=True)]

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={_describe(v)}" for k, v in self.options().items())
        return f"{type(self).__name__}({opts})"

    def options(self) -> dict[str, Any]:
        """The options that change the result (recorded beside the cache)."""
        return {"scale": self.scale}


_REGISTRY: dict[str, type[FlowEstimator]] = {}


def register_estimator(cls: type[FlowEstimator]) -> type[FlowEstimator]:
    """Class decorator: make ``cls`` available as ``get_estimator(cls.name)``."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    _REGISTRY[cls.name] = cls
    return cls


def available_methods() -> list[str]:
    """Registered method names."""
    return sorted(_REGISTRY)


def get_estimator(name: str, **options: Any) -> FlowEstimator:
    """Build the estimator ``name`` with ``options`` (see the module docstring)."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown flow method {name!r}; known: {', '.join(available_methods())}")
    try:
        return _REGISTRY[name](**options)
    except TypeError as e:
        if "argument" in str(e):
            raise TypeError(f"flow method {name!r}: {e}") from e
        raise


def _gray(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


@register_estimator
class DISFlow(FlowEstimator):
    """OpenCV Dense Inverse Search on grayscale; ``preset`` ultrafast / fast / medium."""

    name = "dis"
    PRESETS: ClassVar[dict[str, int]] = {
        "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
        "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
        "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
    }

    def __init__(self, preset: str = "medium", scale: float = 1.0) -> None:
        super().__init__(scale)
        if preset not in self.PRESETS:
            raise ValueError(f"dis: preset={preset!r}; allowed: {', '.join(self.PRESETS)}")
        self.preset = preset

    def _estimate(self, img1: np.ndarray, img2: np.ndarray) -> np.ndarray:
        # a fresh object per pair: a reused DIS instance carries state between calls, and
        # its results would then depend on the order in which pairs were computed
        dis = cv2.DISOpticalFlow_create(self.PRESETS[self.preset])
        return dis.calc(_gray(img1), _gray(img2), None)

    def options(self) -> dict[str, Any]:
        return {"preset": self.preset, "scale": self.scale}


@register_estimator
class FarnebackFlow(FlowEstimator):
    """OpenCV Farneback on grayscale (pyramid of 5 levels, 15 px window by default)."""

    name = "farneback"

    def __init__(
        self,
        scale: float = 1.0,
        pyr_scale: float = 0.5,
        levels: int = 5,
        winsize: int = 15,
        iterations: int = 3,
        poly_n: int = 5,
        poly_sigma: float = 1.2,
        gaussian: bool = False,
    ) -> None:
        super().__init__(scale)
        self.params = {
            "pyr_scale": float(pyr_scale),
            "levels": int(levels),
            "winsize": int(winsize),
            "iterations": int(iterations),
            "poly_n": int(poly_n),
            "poly_sigma": float(poly_sigma),
            "flags": cv2.OPTFLOW_FARNEBACK_GAUSSIAN if gaussian else 0,
        }

    def _estimate(self, img1: np.ndarray, img2: np.ndarray) -> np.ndarray:
        return cv2.calcOpticalFlowFarneback(_gray(img1), _gray(img2), None, **self.params)

    def options(self) -> dict[str, Any]:
        return {"scale": self.scale, **self.params}


@register_estimator
class GTFlow(FlowEstimator):
    """The synthetic world's exact flow, from sample_data tokens (``flowmod.world.gt_flow``).

    ``estimate_tokens(sd_token_1, sd_token_2) -> (H, W, 2) float32`` pixels. Pixels whose
    flow the world marks invalid (leaving the image, occluded in frame 2) keep the flow of
    their surface; non-finite values are set to 0. Use ``flowmod.world.gt_flow`` directly when
    the valid mask is needed (evaluation).
    """

    name = "gt"
    inputs = "tokens"

    def __init__(self, dataroot: str | os.PathLike[str], version: str) -> None:
        super().__init__(1.0)
        self.dataroot = str(dataroot)
        self.version = version
        world = self._world()
        if not world.is_synthetic(self.dataroot, self.version):
            raise NotSyntheticError(
                f"gt flow exists only for a generated world, and {self.dataroot} "
                f"({self.version}) is not one (flowmod.world.is_synthetic is False): drop 'gt' "
                "from flow_methods for real nuScenes data"
            )

    @staticmethod
    def _world() -> Any:
        import importlib

        return importlib.import_module("flowmod.world")  # lazy: another stage, heavy import

    def estimate_tokens(self, sd_token_1: str, sd_token_2: str) -> np.ndarray:
        """Exact flow (H, W, 2) float32, pixels, from frame ``sd_token_1`` to ``sd_token_2``."""
        flow, _valid = self._world().gt_flow(self.dataroot, self.version, sd_token_1, sd_token_2)
        flow = np.asarray(flow, dtype=np.float32)
        return np.where(np.isfinite(flow), flow, np.float32(0.0))

    def estimate(self, img1: np.ndarray, img2: np.ndarray) -> np.ndarray:
        raise TypeError(
            "gt works from sample_data tokens, not images: use estimate_tokens(sd_token_1, "
            "sd_token_2) or compute_flow()"
        )

    def options(self) -> dict[str, Any]:
        return {"dataroot": self.dataroot, "version": self.version}


# --- networks -------------------------------------------------------------------------------


class _NetworkEstimator(FlowEstimator):
    """A torch network; ``weights``: a checkpoint path or an in-memory state_dict.

    ``model`` (an already-loaded ``nn.Module``) bypasses the weights search: for tests and
    timing only.
    """

    cpu_bound = False
    weights_param: ClassVar[str] = ""

    def __init__(
        self,
        weights: str | os.PathLike[str] | Mapping[str, Any] | None = None,
        *,
        device: Any = "auto",
        scale: float = 1.0,
        batch_size: int | None = None,
        model: Any = None,
    ) -> None:
        super().__init__(scale)
        self.device = resolve_device(device)
        self.batch_size = int(batch_size or (4 if self.device.type == "cuda" else 1))
        if model is not None:
            self.weights_source = "<model given>"
        else:
            model = self._build_and_load(weights)
        self.model = model.to(self.device).eval()

    def _build_and_load(self, weights: Any) -> Any:
        raise NotImplementedError

    def _flow_tensor(self, img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) float BGR in [0, 255] -> (B, 2, H, W) flow in pixels."""
        raise NotImplementedError

    def _estimate(self, img1: np.ndarray, img2: np.ndarray) -> np.ndarray:
        return self._run([img1], [img2])[0]

    def _run(self, img1s: Sequence[np.ndarray], img2s: Sequence[np.ndarray]) -> list[np.ndarray]:
        import torch

        def to_tensor(imgs: Sequence[np.ndarray]) -> torch.Tensor:
            x = torch.from_numpy(np.stack(imgs)).to(self.device)
            return x.permute(0, 3, 1, 2).float()

        with torch.inference_mode():
            flow = self._flow_tensor(to_tensor(img1s), to_tensor(img2s))
        return list(flow.permute(0, 2, 3, 1).float().cpu().numpy())

    def estimate_batch(
        self, img1s: Sequence[np.ndarray], img2s: Sequence[np.ndarray]
    ) -> list[np.ndarray]:
        """Flows for many pairs; same-size pairs run ``batch_size`` at a time."""
        if len(img1s) != len(img2s):
            raise ValueError(f"{len(img1s)} first images but {len(img2s)} second images")
        for a, b in zip(img1s, img2s, strict=True):
            _check_pair(a, b)
        small1 = [_resize_image(a, self.scale) for a in img1s]
        small2 = [_resize_image(b, self.scale) for b in img2s]
        groups: dict[tuple[int, ...], list[int]] = {}
        for i, a in enumerate(small1):
            groups.setdefault(a.shape, []).append(i)
        out: list[np.ndarray | None] = [None] * len(img1s)
        for idx in groups.values():
            for s in range(0, len(idx), self.batch_size):
                chunk = idx[s : s + self.batch_size]
                flows = self._run([small1[i] for i in chunk], [small2[i] for i in chunk])
                for i, f in zip(chunk, flows, strict=True):
                    out[i] = resize_flow(f, img1s[i].shape[:2])
        return out  # type: ignore[return-value]

    def options(self) -> dict[str, Any]:
        return {"scale": self.scale, "weights": self.weights_source}


def _missing_weights(method: str, param: str, what: str, cache_files: Sequence[str]) -> str:
    from flowmod.flow_nets import hub_checkpoint_dir

    cache = hub_checkpoint_dir()
    return (
        f"{method} needs trained weights and none were found (flow is never computed from "
        f"random weights). Either set the parameter {param} to {what}, or put "
        f"{cache_files[0]} into {cache}/ (the folder is $TORCH_HOME/hub/checkpoints; "
        f"also looked for: {', '.join(cache_files[1:]) or '-'})."
    )


@register_estimator
class RAFTFlow(_NetworkEstimator):
    """RAFT (torchvision ``raft_large``); 12 flow updates by default.

    Weights: ``weights`` (path to a torchvision state_dict .pth or an original princeton-vl
    checkpoint, mapped by key), else the torchvision file in the TORCH_HOME hub cache
    (``Raft_Large_Weights.C_T_SKHT_K_V1`` preferred: KITTI fine-tuned).
    """

    name = "raft"
    arch: ClassVar[str] = "raft_large"
    weights_param = "raft_weights"

    def __init__(
        self,
        weights: str | os.PathLike[str] | Mapping[str, Any] | None = None,
        *,
        num_flow_updates: int = 12,
        device: Any = "auto",
        scale: float = 1.0,
        batch_size: int | None = None,
        model: Any = None,
    ) -> None:
        self.num_flow_updates = int(num_flow_updates)
        super().__init__(weights, device=device, scale=scale, batch_size=batch_size, model=model)

    def _build_and_load(self, weights: Any) -> Any:
        from flowmod import flow_nets as fn

        model = fn.build_raft(self.arch)
        files = fn.torchvision_weight_files(self.arch)
        if weights is None:
            for _enum, fname in files:
                p = fn.hub_checkpoint_dir() / fname
                if p.is_file():
                    weights = p
                    break
            else:
                what = (
                    f"a .pth file (a torchvision state_dict such as {files[0][1]} of "
                    f"{files[0][0]}, or an original princeton-vl RAFT checkpoint"
                    + (
                        " such as raft-kitti.pth)"
                        if self.arch == "raft_large"
                        else " raft-small.pth)"
                    )
                )
                raise MissingWeightsError(
                    _missing_weights(self.name, self.weights_param, what, [f for _, f in files])
                )
        if isinstance(weights, Mapping):
            sd, source = fn.strip_prefix(weights), "the given state_dict"
            self.weights_source = "<state_dict>"
        else:
            path = Path(weights).expanduser()
            if not path.is_file():
                raise MissingWeightsError(
                    f"{self.name}: weights file not found: {path} (parameter "
                    f"{self.weights_param}; expected a torchvision {self.arch} state_dict such "
                    f"as {files[0][1]} or an original RAFT checkpoint)"
                )
            sd, source = fn.read_checkpoint(path), f"weights file {path}"
            self.weights_source = str(path)
        if fn.is_original_raft(sd):
            try:
                sd = fn.raft_original_to_torchvision(sd)
            except fn.CheckpointError as e:
                raise fn.CheckpointError(f"{source}: {e}") from e
            source += " (original RAFT layout, keys mapped to torchvision)"
        return fn.load_weights(model, sd, source)

    def _flow_tensor(self, img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
        from flowmod.flow_nets import raft_flow

        rgb = [2, 1, 0]  # cv2 gives BGR; RAFT was trained on RGB
        return raft_flow(self.model, img1[:, rgb], img2[:, rgb], self.num_flow_updates)

    def options(self) -> dict[str, Any]:
        return {**super().options(), "num_flow_updates": self.num_flow_updates}


@register_estimator
class RAFTSmallFlow(RAFTFlow):
    """RAFT small (torchvision ``raft_small``); parameter ``raft_small_weights``."""

    name = "raft_small"
    arch = "raft_small"
    weights_param = "raft_small_weights"


@register_estimator
class FastFlowNetFlow(_NetworkEstimator):
    """FastFlowNet (:class:`flowmod.flow_nets.FastFlowNet`) with the official checkpoints.

    Weights: ``weights`` (path or state_dict), else one of the official file names
    (``fastflownet_ft_kitti.pth`` first) in the TORCH_HOME hub cache.
    """

    name = "fastflownet"
    weights_param = "fastflownet_weights"

    def _build_and_load(self, weights: Any) -> Any:
        from flowmod import flow_nets as fn

        model = fn.FastFlowNet()
        if weights is None:
            for fname in fn.FFN_CHECKPOINT_NAMES:
                if (fn.hub_checkpoint_dir() / fname).is_file():
                    weights = fn.hub_checkpoint_dir() / fname
                    break
            else:
                what = (
                    "an official FastFlowNet checkpoint (checkpoints/fastflownet_ft_kitti.pth of "
                    "the FastFlowNet repository, KITTI fine-tuned as in the paper)"
                )
                raise MissingWeightsError(
                    _missing_weights(self.name, self.weights_param, what, fn.FFN_CHECKPOINT_NAMES)
                )
        if isinstance(weights, Mapping):
            self.weights_source = "<state_dict>"
            return fn.load_weights(model, fn.strip_prefix(weights), "the given state_dict")
        path = Path(weights).expanduser()
        if not path.is_file():
            raise MissingWeightsError(
                f"{self.name}: weights file not found: {path} (parameter {self.weights_param}; "
                "expected an official checkpoint such as fastflownet_ft_kitti.pth)"
            )
        self.weights_source = str(path)
        return fn.load_weights(model, fn.read_checkpoint(path), f"weights file {path}")

    def _flow_tensor(self, img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
        from flowmod.flow_nets import fastflownet_flow

        return fastflownet_flow(self.model, img1, img2)


def estimator_options(params: Params, method: str) -> dict[str, Any]:
    """The ``get_estimator``/``compute_flow`` options of ``method`` from a profile.

    ``gt`` gets none here (``compute_flow`` passes dataroot and version itself).
    """
    if method == "gt":
        return {}
    opts: dict[str, Any] = {"scale": params.flow_scale}
    if method == "dis":
        opts["preset"] = params.dis_preset
    elif method in ("raft", "raft_small", "fastflownet"):
        param = {"raft": "raft_weights", "raft_small": "raft_small_weights"}.get(
            method, "fastflownet_weights"
        )
        value = getattr(params, param, None)
        opts["weights"] = params.path(value) if value else None
        opts["device"] = params.device
    return opts


# --------------------------------------------------------------------------------------------
# flow files
# --------------------------------------------------------------------------------------------

FLO_MAGIC = 202021.25
#: While computing, the index is rewritten this often (s), so timings survive an interruption.
INDEX_WRITE_SECONDS = 30.0


def _check_flow(flow: np.ndarray, what: str = "flow") -> None:
    if not (isinstance(flow, np.ndarray) and flow.ndim == 3 and flow.shape[2] == 2):
        raise ValueError(f"{what} must be an (H, W, 2) array, got {getattr(flow, 'shape', flow)}")


def write_flo(path: str | os.PathLike[str], flow: np.ndarray) -> None:
    """Write (H, W, 2) flow in the Middlebury .flo format (little-endian float32), atomically."""
    _check_flow(flow)
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
    _check_flow(flow)
    if dtype not in ("float16", "float32"):
        raise ValueError(f"dtype={dtype!r}; allowed: float16, float32")
    if dtype == "float16":
        big = float(np.finfo(np.float16).max)
        flow = np.clip(flow, -big, big)
    with atomic_path(path) as tmp:
        np.save(tmp, np.ascontiguousarray(flow, dtype=dtype), allow_pickle=False)


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


def _npy_header(path: Path) -> tuple[tuple[int, ...], bool, np.dtype, int]:
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


def _npy_ok(path: Path, dtype: str) -> bool:
    """True if ``path`` is a complete .npy of an (H, W, 2) ``dtype`` array (header + size)."""
    try:
        shape, fortran, dt, offset = _npy_header(path)
        size = path.stat().st_size
    except Exception:  # noqa: BLE001 - anything unreadable is simply not done
        return False
    return (
        dt == np.dtype(dtype)
        and len(shape) == 3
        and shape[2] == 2
        and not fortran
        and size == offset + math.prod(shape) * dt.itemsize
    )


def full_shape(stored: tuple[int, ...], store_scale: float) -> tuple[int, int]:
    """(H, W) of the image whose flow was stored at ``store_scale`` with shape ``stored``."""
    return int(round(stored[0] / store_scale)), int(round(stored[1] / store_scale))


def store_flow(path: str | os.PathLike[str], flow: np.ndarray, dtype: str = "float16",
               store_scale: float = 1.0) -> None:
    """Save flow (H, W, 2) px at ``store_scale`` of its size (area-averaged), values kept in
    pixels of the full image, so :func:`load_flow` can restore the full size."""
    if store_scale != 1.0:
        h, w = flow.shape[:2]
        size = (int(round(h * store_scale)), int(round(w * store_scale)))
        if min(size) < 1 or full_shape(size, store_scale) != (h, w):
            raise ValueError(f"store_scale={store_scale} cannot store a {h}x{w} flow so that its "
                             "size is recovered; use a scale like 0.5 or 0.25")
        flow = cv2.resize(np.asarray(flow, np.float32), size[::-1], interpolation=cv2.INTER_AREA)
    save_flow_npy(path, flow, dtype)


def _store_scale(folder: Path) -> float:
    """The store_scale recorded in a method folder's config.json (1.0 if none)."""
    cfg = folder / "config.json"
    if not cfg.is_file():
        return 1.0
    return float(_read_config(str(cfg), cfg.stat().st_mtime_ns).get("store_scale", 1.0))


@functools.lru_cache(maxsize=64)
def _read_config(path: str, mtime_ns: int) -> dict[str, Any]:
    return json.loads(Path(path).read_text())


def load_flow(out_dir: str | os.PathLike[str], method: str, pair_id: str) -> np.ndarray:
    """Flow of one pair written by :func:`compute_flow`: (H, W, 2) float32, pixels of the full
    image, frame 1 -> 2 (bilinearly restored to full size when stored at a reduced scale)."""
    folder = Path(out_dir) / method
    flow = load_flow_npy(folder / f"{pair_id}.npy")
    scale = _store_scale(folder)
    if scale == 1.0:
        return flow
    h, w = full_shape(flow.shape, scale)
    return cv2.resize(flow, (w, h), interpolation=cv2.INTER_LINEAR)


# --------------------------------------------------------------------------------------------
# colour coding
# --------------------------------------------------------------------------------------------


def flow_to_color(flow: np.ndarray, max_flow: float | None = None, bgr: bool = False) -> np.ndarray:
    """Colour-code flow (H, W, 2) -> (H, W, 3) uint8 RGB (BGR if ``bgr``), Middlebury wheel.

    Uses ``torchvision.utils.flow_to_image``; saturation is normalised by the largest
    magnitude, or by ``max_flow`` pixels (larger vectors clipped) for comparable images.
    """
    import torch
    from torchvision.utils import flow_to_image

    _check_flow(flow)
    f = np.nan_to_num(flow.astype(np.float32))
    h, w = f.shape[:2]
    if max_flow is not None:
        if not max_flow > 0:
            raise ValueError(f"max_flow={max_flow} must be > 0 (pixels)")
        mag = np.linalg.norm(f, axis=2, keepdims=True)
        f = f * np.minimum(1.0, max_flow / np.maximum(mag, 1e-9))
        ref = np.zeros((h, 1, 2), np.float32)
        ref[..., 0] = max_flow  # one extra column fixes the normalisation
        f = np.concatenate([f, ref], axis=1)
    img = flow_to_image(torch.from_numpy(f).permute(2, 0, 1)).permute(1, 2, 0).numpy()[:, :w]
    return np.ascontiguousarray(img[..., ::-1] if bgr else img)


# --------------------------------------------------------------------------------------------
# metrics
# --------------------------------------------------------------------------------------------


def endpoint_error(flow: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-pixel end-point error (H, W) float32, pixels."""
    _check_flow(flow)
    _check_flow(gt, "gt")
    if flow.shape != gt.shape:
        raise ValueError(f"flow {flow.shape} and gt {gt.shape} differ in shape")
    d = flow.astype(np.float32) - gt.astype(np.float32)
    return np.sqrt((d**2).sum(axis=2))


def _select(
    shape: tuple[int, ...], valid: np.ndarray | None, mask: np.ndarray | None
) -> np.ndarray:
    sel = np.ones(shape[:2], bool)
    for m in (valid, mask):
        if m is not None:
            if m.shape != shape[:2]:
                raise ValueError(f"mask shape {m.shape} != flow shape {shape[:2]}")
            sel &= m.astype(bool)
    return sel


def epe(
    flow: np.ndarray,
    gt: np.ndarray,
    valid: np.ndarray | None = None,
    mask: np.ndarray | None = None,
) -> float:
    """Mean end-point error (pixels) over pixels that are ``valid`` and in ``mask`` (both (H, W)
    bool, None = all); NaN if no pixel is selected."""
    err = endpoint_error(flow, gt)
    sel = _select(flow.shape, valid, mask)
    return float(err[sel].mean()) if sel.any() else float("nan")


def fl_all(
    flow: np.ndarray,
    gt: np.ndarray,
    valid: np.ndarray | None = None,
    mask: np.ndarray | None = None,
) -> float:
    """KITTI Fl-all in percent (0-100): share of selected pixels whose end-point error is
    > 3 px AND > 5 % of the true flow magnitude; NaN if no pixel is selected."""
    err = endpoint_error(flow, gt)
    mag = np.sqrt((gt.astype(np.float32) ** 2).sum(axis=2))
    outlier = (err > 3.0) & (err > 0.05 * mag)
    sel = _select(flow.shape, valid, mask)
    return float(100.0 * outlier[sel].mean()) if sel.any() else float("nan")


def boxes_mask(boxes: np.ndarray | Sequence[Sequence[float]], shape: tuple[int, ...]) -> np.ndarray:
    """(H, W) bool mask of the pixels inside any of the (N, 4) boxes xmin, ymin, xmax, ymax
    (pixels, inclusive; a pixel is inside when its centre (col, row) is); clipped to the image."""
    h, w = shape[:2]
    mask = np.zeros((h, w), bool)
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    for xmin, ymin, xmax, ymax in b:
        c0, c1 = max(0, math.ceil(xmin)), min(w - 1, math.floor(xmax))
        r0, r1 = max(0, math.ceil(ymin)), min(h - 1, math.floor(ymax))
        if c1 >= c0 and r1 >= r0:
            mask[r0 : r1 + 1, c0 : c1 + 1] = True
    return mask


def flow_metrics(
    flow: np.ndarray,
    gt: np.ndarray,
    valid: np.ndarray | None = None,
    boxes: np.ndarray | None = None,
) -> dict[str, float]:
    """EPE (px) and Fl-all (%) overall and, with ``boxes`` (N, 4), inside the boxes."""
    out = {"epe": epe(flow, gt, valid), "fl_all": fl_all(flow, gt, valid)}
    if boxes is not None:
        m = boxes_mask(boxes, flow.shape)
        out["epe_boxes"] = epe(flow, gt, valid, m)
        out["fl_all_boxes"] = fl_all(flow, gt, valid, m)
    return out


# --------------------------------------------------------------------------------------------
# the stage runner
# --------------------------------------------------------------------------------------------

_JPEG_SOI, _JPEG_EOI = b"\xff\xd8", b"\xff\xd9"
_PNG_SIG = b"\x89PNG\r\n\x1a\n"


def _image_problem(path: Path) -> str | None:
    """None if ``path`` looks like a complete, decodable image, else what is wrong."""
    try:
        size = path.stat().st_size
    except OSError:
        return "missing"
    if size == 0:
        return "empty"
    try:
        with open(path, "rb") as f:
            head = f.read(8)
            f.seek(max(0, size - 64))
            tail = f.read()
    except OSError as e:
        return f"unreadable ({e.strerror})"
    if head.startswith(_JPEG_SOI) and _JPEG_EOI not in tail:
        return "truncated JPEG (no end marker)"
    if head.startswith(_PNG_SIG) and b"IEND" not in tail:
        return "truncated PNG (no IEND chunk)"
    if cv2.imread(str(path), cv2.IMREAD_REDUCED_GRAYSCALE_8) is None:
        return "cannot be decoded"
    return None


def check_images(paths: Sequence[str | os.PathLike[str]], n_jobs: int = 2, show: int = 5) -> None:
    """Check that every image exists and decodes; :class:`ImageError` listing the first
    ``show`` bad files (with the reason) and their count."""
    unique = list(dict.fromkeys(Path(p) for p in paths))
    with concurrent.futures.ThreadPoolExecutor(max(1, n_jobs)) as pool:
        problems = [
            (p, why) for p, why in zip(unique, pool.map(_image_problem, unique), strict=True) if why
        ]
    if problems:
        first = "; ".join(f"{p} ({why})" for p, why in problems[:show])
        more = f" and {len(problems) - show} more" if len(problems) > show else ""
        raise ImageError(
            f"{len(problems)} of {len(unique)} images are missing or corrupt: {first}{more}"
        )


def _describe(v: Any) -> Any:
    if isinstance(v, Mapping):
        return "<state_dict>"
    if isinstance(v, (str, int, float, bool)) or v is None:
        return v
    return str(v)


_NOT_CONFIG = ("device", "batch_size", "model", "dataroot", "version")


def _config(cls: type[FlowEstimator], dtype: str, options: Mapping[str, Any]) -> dict[str, Any]:
    """What the cached flows depend on: method, dtype and the options with their defaults."""
    extra = {"dataroot": None, "version": None} if cls.inputs == "tokens" else {}
    try:
        bound = inspect.signature(cls).bind(**extra, **options)
    except TypeError as e:
        raise TypeError(f"flow method {cls.name!r}: {e}") from None
    bound.apply_defaults()
    opts = {k: _describe(v) for k, v in sorted(bound.arguments.items()) if k not in _NOT_CONFIG}
    return {"method": cls.name, "dtype": dtype, "options": opts, "format": 1}


def _one_image_pair(
    est: FlowEstimator, pid: str, path1: str, path2: str, out: Path, storage: tuple[str, float],
    threads: int,
) -> tuple[str, float, tuple[int, ...]]:
    """Worker: read, estimate, save one pair; returns (pair_id, seconds, shape)."""
    if threads:
        cv2.setNumThreads(threads)
    img1, img2 = read_image(path1), read_image(path2)
    t0 = time.perf_counter()
    flow = est.estimate(img1, img2)
    seconds = time.perf_counter() - t0
    store_flow(out, flow, *storage)
    return pid, seconds, flow.shape


def _one_token_pair(
    est: FlowEstimator, pid: str, tok1: str, tok2: str, out: Path, storage: tuple[str, float],
    threads: int,
) -> tuple[str, float, tuple[int, ...]]:
    """Worker for token methods (``gt``)."""
    if threads:
        cv2.setNumThreads(threads)
    t0 = time.perf_counter()
    flow = est.estimate_tokens(tok1, tok2)  # type: ignore[attr-defined]
    seconds = time.perf_counter() - t0
    store_flow(out, flow, *storage)
    return pid, seconds, flow.shape


def _batched(
    est: FlowEstimator, jobs: list[tuple[str, str, str, Path]], storage: tuple[str, float]
) -> Iterator[tuple[str, float, tuple[int, ...]]]:
    """Sequential batches for networks; the next batch's images load in a thread meanwhile."""
    bs = max(1, getattr(est, "batch_size", 1))
    chunks = [jobs[i : i + bs] for i in range(0, len(jobs), bs)]

    def load(chunk: list[tuple[str, str, str, Path]]) -> list[tuple[np.ndarray, np.ndarray]]:
        return [(read_image(a), read_image(b)) for _, a, b, _ in chunk]

    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        nxt = pool.submit(load, chunks[0]) if chunks else None
        for i, chunk in enumerate(chunks):
            assert nxt is not None
            imgs = nxt.result()
            nxt = pool.submit(load, chunks[i + 1]) if i + 1 < len(chunks) else None
            t0 = time.perf_counter()
            flows = est.estimate_batch([a for a, _ in imgs], [b for _, b in imgs])
            seconds = (time.perf_counter() - t0) / len(chunk)
            for (pid, _, _, out), flow in zip(chunk, flows, strict=True):
                store_flow(out, flow, *storage)
                yield pid, seconds, flow.shape


def _read_index(path: Path) -> pd.DataFrame | None:
    if not path.is_file():
        return None
    try:
        df = pd.read_parquet(path)
    except Exception as e:  # noqa: BLE001 - a bad index is rebuilt from the files
        log.warning("ignoring unreadable flow index %s (%s)", path, e)
        return None
    return df if "pair_id" in df.columns else None


def _write_index(
    path: Path, rows: Mapping[str, dict[str, Any]], order: Sequence[str]
) -> pd.DataFrame:
    known = set(order)
    ids = [p for p in order if p in rows] + [p for p in rows if p not in known]
    df = pd.DataFrame(
        {
            "pair_id": ids,
            "seconds": [float(rows[p]["seconds"]) for p in ids],
            "shape": [[int(x) for x in rows[p]["shape"]] for p in ids],
            "file": [f"{p}.npy" for p in ids],
        }
    )
    with atomic_path(path) as tmp:
        df.to_parquet(tmp, index=False)
    return df


def compute_flow(
    pairs: pd.DataFrame,
    method: str,
    out_dir: str | os.PathLike[str],
    *,
    dataroot: str | os.PathLike[str],
    version: str,
    dtype: str = "float16",
    n_jobs: int = 2,
    progress: bool = True,
    force: bool = False,
    store_scale: float = 1.0,
    **options: Any,
) -> pd.DataFrame:
    """Flow of every pair of ``pairs`` (rows of pairs.parquet) with ``method``.

    ``store_scale`` < 1 stores each flow at that fraction of the image size (values still in
    full-image pixels; :func:`load_flow` restores the size): 0.5 needs a quarter of the disk.

    Writes ``<out_dir>/<method>/<pair_id>.npy`` ((H, W, 2) ``dtype``, pixels, frame 1 -> 2)
    and ``<out_dir>/<method>/index.parquet`` (pair_id, seconds = estimation time per pair,
    shape, file name in that folder), both atomically. Resumable: pairs whose .npy is complete
    (header, dtype and size checked) are not recomputed; temporary and truncated files are.
    A change of method options or dtype (recorded in ``config.json``), or ``force``, deletes
    the folder's flows first. Images (``path_1``, ``path_2`` relative to ``dataroot``) are
    checked before any work. CPU methods run pairs in ``n_jobs`` processes; networks run
    sequential batches. Returns the index rows of ``pairs`` plus ``computed`` (bool, this
    call). One run per method folder at a time.
    """
    if method not in _REGISTRY:
        raise ValueError(f"unknown flow method {method!r}; known: {', '.join(available_methods())}")
    if dtype not in ("float16", "float32"):
        raise ValueError(f"dtype={dtype!r}; allowed: float16, float32")
    cls = _REGISTRY[method]
    need = [
        "pair_id",
        *(("sd_token_1", "sd_token_2") if cls.inputs == "tokens" else ("path_1", "path_2")),
    ]
    missing_cols = [c for c in need if c not in pairs.columns]
    if missing_cols:
        raise ValueError(f"pairs lacks column(s) {missing_cols} needed by method {method!r}")
    ids = [str(p) for p in pairs["pair_id"]]
    dup = pd.Series(ids)[pd.Series(ids).duplicated()].unique().tolist()
    if dup:
        raise ValueError(f"duplicate pair_id in pairs: {dup[:5]}")
    bad = [p for p in ids if not p or "/" in p or "\\" in p or p.startswith(".")]
    if bad:
        raise ValueError(f"pair_id values must be plain file names: {bad[:5]}")

    folder = Path(out_dir) / method
    folder.mkdir(parents=True, exist_ok=True)
    index_path = folder / "index.parquet"
    config_path = folder / "config.json"
    if not 0.0 < store_scale <= 1.0:
        raise ValueError(f"store_scale={store_scale}; allowed: 0 < store_scale <= 1")
    config = {**_config(cls, dtype, options), "store_scale": float(store_scale)}
    storage = (dtype, float(store_scale))
    old_config = None
    if config_path.is_file():
        try:
            old_config = json.loads(config_path.read_text())
        except (OSError, json.JSONDecodeError):
            old_config = None
    stale = force or (old_config is not None and old_config != config)
    for tmp in folder.glob(".*.tmp*"):  # left by an interrupted run
        tmp.unlink(missing_ok=True)
    if stale:
        log.warning(
            "flow/%s: %s; deleting its cached flows",
            method,
            "forced" if force else f"options changed ({old_config} -> {config})",
        )
        for f in folder.glob("*.npy"):
            f.unlink()
        index_path.unlink(missing_ok=True)
    if stale or old_config is None:
        with atomic_path(config_path) as tmp:
            tmp.write_text(json.dumps(config, indent=2, sort_keys=True) + "\n")

    rows: dict[str, dict[str, Any]] = {}
    old = _read_index(index_path)
    if old is not None:
        for r in old.itertuples(index=False):
            if (folder / f"{r.pair_id}.npy").is_file():
                rows[str(r.pair_id)] = {"seconds": r.seconds, "shape": list(r.shape)}
    done = set()
    for pid in ids:
        f = folder / f"{pid}.npy"
        if _npy_ok(f, dtype):
            done.add(pid)
            if pid not in rows:  # finished before the index was last written
                stored = _npy_header(f)[0]
                rows[pid] = {"seconds": float("nan"),
                             "shape": [*full_shape(stored, store_scale), *stored[2:]]}
        else:
            rows.pop(pid, None)
    todo = pairs[[pid not in done for pid in ids]]

    root = Path(dataroot)
    if len(todo) and cls.inputs == "images":
        paths = [root / p for p in (*todo["path_1"], *todo["path_2"])]
        check_images(paths, n_jobs=n_jobs)

    computed: set[str] = set()
    if len(todo):
        if cls.inputs == "tokens":
            est = cls(dataroot=dataroot, version=version, **options)  # type: ignore[call-arg]
        else:
            est = cls(**options)
        parallel = est.cpu_bound and n_jobs > 1 and len(todo) > 1
        threads = 1 if parallel else 0
        results: Iterator[tuple[str, float, tuple[int, ...]]] | Any
        if cls.inputs == "tokens":
            calls = [
                (
                    _one_token_pair,
                    (
                        est,
                        str(r.pair_id),
                        r.sd_token_1,
                        r.sd_token_2,
                        folder / f"{r.pair_id}.npy",
                        storage,
                        threads,
                    ),
                )
                for r in todo.itertuples(index=False)
            ]
        else:
            calls = [
                (
                    _one_image_pair,
                    (
                        est,
                        str(r.pair_id),
                        str(root / r.path_1),
                        str(root / r.path_2),
                        folder / f"{r.pair_id}.npy",
                        storage,
                        threads,
                    ),
                )
                for r in todo.itertuples(index=False)
            ]
        if parallel:
            from joblib import Parallel, delayed

            results = Parallel(n_jobs=n_jobs, return_as="generator_unordered")(
                delayed(fn)(*args) for fn, args in calls
            )
        elif est.cpu_bound:
            results = (fn(*args) for fn, args in calls)
        else:
            jobs = [(a[1], a[2], a[3], a[4]) for _, a in calls]
            results = _batched(est, jobs, storage)

        from tqdm import tqdm

        last_write = time.monotonic()
        with tqdm(total=len(todo), desc=f"flow {method}", unit="pair", disable=not progress) as bar:
            for pid, seconds, shape in results:
                rows[pid] = {"seconds": seconds, "shape": list(shape)}
                computed.add(pid)
                bar.update(1)
                if time.monotonic() - last_write > INDEX_WRITE_SECONDS:  # if interrupted
                    _write_index(index_path, rows, ids)
                    last_write = time.monotonic()
    index = _write_index(index_path, rows, ids)
    out = index[index["pair_id"].isin(set(ids))].reset_index(drop=True)
    out["computed"] = out["pair_id"].isin(computed)
    return out


# --------------------------------------------------------------------------------------------
# the stage (notebook 03)
# --------------------------------------------------------------------------------------------

def flow_dir(params: Params) -> Path:
    """``<run_dir>/flow``."""
    return params.run_path / "flow"


def run(params: Params, pairs: pd.DataFrame, progress: bool = True) -> dict[str, pd.DataFrame]:
    """Flow of every pair for each method of ``params.flow_methods``; cached and resumable.

    Returns ``{method: index}`` (pair_id, seconds, shape, file, computed).
    """
    out = {}
    for method in params.flow_methods:
        out[method] = compute_flow(
            pairs, method, flow_dir(params), dataroot=params.dataroot_path,
            version=params.version, dtype=params.flow_dtype, n_jobs=params.n_jobs,
            progress=progress, force=params.force, store_scale=params.flow_scale,
            **estimator_options(params, method),
        )
    return out


def accuracy_table(
    params: Params, pairs: pd.DataFrame, objects: pd.DataFrame, indexes: dict[str, pd.DataFrame],
    n_pairs: int = 20, seed: int = 0,
) -> pd.DataFrame:
    """EPE / Fl-all against the world's exact flow, overall and inside far (keyframe set,
    min-max distance) and near (generalisation set, < min_distance) vehicle boxes, with the
    median seconds per pair; on ``n_pairs`` random pairs of each set (synthetic world only)."""
    from flowmod import world

    rng = np.random.default_rng(seed)
    rows = []
    for kind, dmin, dmax in (("keyframe", params.min_distance, params.max_distance),
                             ("general", 0.0, params.min_distance)):
        ids = pairs.loc[pairs["set"] == kind, "pair_id"].to_numpy()
        if len(ids) == 0:
            continue
        pick = rng.choice(ids, size=min(n_pairs, len(ids)), replace=False)
        sub = pairs.set_index("pair_id").loc[pick]
        gts = {pid: world.gt_flow(params.dataroot_path, params.version, r.sd_token_1,
                                  r.sd_token_2) for pid, r in sub.iterrows()}
        for method in indexes:
            acc: dict[str, list[float]] = {"epe": [], "fl": [], "epe_box": [], "fl_box": []}
            for pid, (gt, valid) in gts.items():
                est = load_flow(flow_dir(params), method, pid)
                obj = objects[(objects["pair_id"] == pid) & objects["distance"].between(dmin, dmax)]
                mask = boxes_mask(obj[["xmin", "ymin", "xmax", "ymax"]].to_numpy(), gt.shape)
                acc["epe"].append(epe(est, gt, valid))
                acc["fl"].append(fl_all(est, gt, valid))
                if (mask & valid).any():
                    acc["epe_box"].append(epe(est, gt, valid, mask))
                    acc["fl_box"].append(fl_all(est, gt, valid, mask))
            secs = indexes[method]["seconds"]
            rows.append({
                "set": kind, "vehicles": f"{dmin:g}-{dmax:g} m", "method": method,
                "EPE all (px)": np.mean(acc["epe"]), "Fl-all (%)": np.mean(acc["fl"]),
                "EPE boxes (px)": np.mean(acc["epe_box"]) if acc["epe_box"] else np.nan,
                "Fl-all boxes (%)": np.mean(acc["fl_box"]) if acc["fl_box"] else np.nan,
                "s / pair": float(np.nanmedian(secs)) if secs.notna().any() else np.nan,
                "pairs": len(gts),
            })
    return pd.DataFrame(rows)


def box_flow_magnitude(objects: pd.DataFrame, load: Any, inner: float = 0.6) -> np.ndarray:
    """Median flow magnitude (px) over the central ``inner`` fraction of each object's box.

    ``load(pair_id) -> (H, W, 2)``; each pair's flow is read once.
    """
    out = np.full(len(objects), np.nan)
    for pid, idx in objects.groupby("pair_id", sort=False).indices.items():
        f = load(pid)
        mag = np.linalg.norm(f.astype(np.float32), axis=-1)
        for i in idx:
            o = objects.iloc[i]
            cx, cy = (o.xmin + o.xmax) / 2, (o.ymin + o.ymax) / 2
            hw, hh = (o.xmax - o.xmin) * inner / 2, (o.ymax - o.ymin) * inner / 2
            y0, y1 = int(max(cy - hh, 0)), int(min(cy + hh, mag.shape[0] - 1)) + 1
            x0, x1 = int(max(cx - hw, 0)), int(min(cx + hw, mag.shape[1] - 1)) + 1
            out[i] = float(np.median(mag[y0:y1, x0:x1]))
    return out
