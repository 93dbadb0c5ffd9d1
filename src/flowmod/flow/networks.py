"""Flow networks as estimators: RAFT (torchvision ``raft_large`` / ``raft_small``) and
FastFlowNet (:mod:`flowmod.flow.architectures`), always with trained weights.

Network methods never run from random weights: without a weights file they raise
:class:`MissingWeightsError` saying which file to put where. torch is imported lazily.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from flowmod.environment import resolve_device
from flowmod.flow.registry import (
    FlowEstimator,
    MissingWeightsError,
    check_pair,
    register_estimator,
    resize_flow,
    resize_image,
)
from flowmod.flowweights import CATALOG, WEIGHTS_PARAM
from flowmod.params import FILE_DEFAULTS

if TYPE_CHECKING:
    import torch

    from flowmod.params import Params


def _nets() -> Any:
    """:mod:`flowmod.flow.architectures`, imported on first use: it imports torch, which the CPU
    methods (and a Ray worker running them) never need."""
    from flowmod.flow import architectures as nets  # lazy: torch is heavy (see the docstring)

    return nets

class _NetworkEstimator(FlowEstimator):
    """A torch network; ``weights``: a checkpoint path or an in-memory state_dict.

    ``model`` (an already-loaded ``nn.Module``) bypasses the weights search: for tests and
    timing only.
    """

    cpu_bound = False
    file_options = ("weights",)
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
        #: resize frames and flow on the device (CUDA): the host path's OpenCV resizing
        #: made ``scale`` < 1 slower than 1 on a GPU
        self.device_resize = self.device.type == "cuda"

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
            check_pair(a, b)
        run = self._run_scaled if self.device_resize and self.scale != 1.0 else self._run_resized
        groups: dict[tuple[int, ...], list[int]] = {}
        for i, a in enumerate(img1s):
            groups.setdefault(a.shape, []).append(i)
        out: list[np.ndarray | None] = [None] * len(img1s)
        for idx in groups.values():
            for s in range(0, len(idx), self.batch_size):
                chunk = idx[s : s + self.batch_size]
                flows = run([img1s[i] for i in chunk], [img2s[i] for i in chunk])
                for i, f in zip(chunk, flows, strict=True):
                    out[i] = f
        return out  # type: ignore[return-value]

    def _run_resized(self, img1s: Sequence[np.ndarray], img2s: Sequence[np.ndarray]
                     ) -> list[np.ndarray]:
        """One batch of same-size frames, resized on the host (OpenCV: INTER_AREA down,
        INTER_LINEAR for the flow back up): frames (H, W, 3) uint8 BGR, flows (H, W, 2) px."""
        flows = self._run([resize_image(a, self.scale) for a in img1s],
                          [resize_image(b, self.scale) for b in img2s])
        return [resize_flow(f, a.shape[:2]) for f, a in zip(flows, img1s, strict=True)]

    def _run_scaled(self, img1s: Sequence[np.ndarray], img2s: Sequence[np.ndarray]
                    ) -> list[np.ndarray]:
        """As :meth:`_run_resized` with both resizings on the device (area down, bilinear
        up, as OpenCV's INTER_AREA and INTER_LINEAR)."""
        import torch
        from torch.nn import functional as F  # noqa: N812

        hh, ww = img1s[0].shape[:2]
        h, w = max(1, round(hh * self.scale)), max(1, round(ww * self.scale))
        mode = "area" if self.scale < 1.0 else "bilinear"

        def small(imgs: Sequence[np.ndarray]) -> torch.Tensor:
            x = torch.from_numpy(np.stack(imgs)).to(self.device).permute(0, 3, 1, 2).float()
            return F.interpolate(x, size=(h, w), mode=mode)

        with torch.inference_mode():
            flow = self._flow_tensor(small(img1s), small(img2s)).float()
            full = F.interpolate(flow, size=(hh, ww), mode="bilinear", align_corners=False)
            full[:, 0] *= ww / w
            full[:, 1] *= hh / h
        return list(full.permute(0, 2, 3, 1).cpu().numpy())

    def options(self) -> dict[str, Any]:
        return {"scale": self.scale, "weights": self.weights_source}


def _missing_weights(method: str, param: str, what: str, cache_files: Sequence[str]) -> str:
    cache = _nets().hub_checkpoint_dir()
    return (
        f"{method} needs trained weights and none were found (flow is never computed from "
        f"random weights). Either set the parameter {param} to {what}, or put "
        f"{cache_files[0]} into {cache}/ (the folder is $TORCH_HOME/hub/checkpoints; "
        f"also looked for: {', '.join(cache_files[1:]) or '-'})."
    )


@register_estimator
class RAFTFlow(_NetworkEstimator):
    """RAFT (torchvision ``raft_large``); 20 flow updates by default, as the original RAFT demo
    and MotionDetection code run it (RAFT.forward's own default is 12).

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
        num_flow_updates: int = 20,
        device: Any = "auto",
        scale: float = 1.0,
        batch_size: int | None = None,
        model: Any = None,
    ) -> None:
        self.num_flow_updates = int(num_flow_updates)
        super().__init__(weights, device=device, scale=scale, batch_size=batch_size, model=model)

    def _build_and_load(self, weights: Any) -> Any:
        fn = _nets()
        model = fn.build_raft(self.arch)
        files = fn.torchvision_weight_files(self.arch)
        if weights is None:
            weights = next((f for f in cache_files(self.name) if f.is_file()), None)
            if weights is None:
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
        rgb = [2, 1, 0]  # cv2 gives BGR; RAFT was trained on RGB
        return _nets().raft_flow(self.model, img1[:, rgb], img2[:, rgb], self.num_flow_updates)

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
    """FastFlowNet (:class:`flowmod.flow.architectures.FastFlowNet`) with the official checkpoints.

    Weights: ``weights`` (path or state_dict), else one of the official file names
    (``fastflownet_ft_kitti.pth`` first) in the TORCH_HOME hub cache.
    """

    name = "fastflownet"
    weights_param = "fastflownet_weights"

    def _build_and_load(self, weights: Any) -> Any:
        fn = _nets()
        model = fn.FastFlowNet()
        if weights is None:
            weights = next((f for f in cache_files(self.name) if f.is_file()), None)
            if weights is None:
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
        return _nets().fastflownet_flow(self.model, img1, img2)


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
        value = getattr(params, WEIGHTS_PARAM[method], None)
        # null: the cache file the network would find, named, so that the pool keys it by
        # content (``file_options``) like a given file; None when there is none
        opts["weights"] = params.path(value) if value else cached_weights(method)
        opts["device"] = params.device
        if method != "fastflownet":
            opts["num_flow_updates"] = params.raft_iters
    return opts




def cache_files(method: str) -> list[Path]:
    """The files ``method`` looks for in ``$TORCH_HOME/hub/checkpoints/``, preferred first
    (its :data:`flowmod.flowweights.CATALOG` entry's names, or torchvision's for its
    architecture)."""
    fn, entry = _nets(), CATALOG[method]
    names = list(entry.cache_names) or [
        f for _, f in fn.torchvision_weight_files(entry.torchvision_arch)]
    return [fn.hub_checkpoint_dir() / n for n in names]


def weights_file(params: Params, method: str) -> Path | None:
    """The weight file a network ``method`` would load under ``params``: its ``*_weights``
    parameter when that file exists, else the first cache file present; None if neither."""
    value = getattr(params, WEIGHTS_PARAM[method])
    if value:
        given = params.path(value)
        return given if given.is_file() else None
    return cached_weights(method)


def cached_weights(method: str) -> Path | None:
    """The first of :func:`cache_files` present (what the network loads with weights null)."""
    return next((f for f in cache_files(method) if f.is_file()), None)


# a null *_weights parameter stands for the cached file: its content enters fingerprints
FILE_DEFAULTS.update({param: partial(cached_weights, m) for m, param in WEIGHTS_PARAM.items()})


def planned_methods(params: Params) -> tuple[list[str], list[str]]:
    """``flow_methods`` plus each of ``flow_networks`` whose weights are present, and one line
    per network saying whether it was added (the file) or not (where to put one)."""
    methods, notes = list(params.flow_methods), []
    for m in params.flow_networks:
        if m in methods:
            continue
        found = weights_file(params, m)
        if found:
            methods.append(m)
            notes.append(f"flow_networks: {m} added to flow_methods (weights {found})")
        elif getattr(params, WEIGHTS_PARAM[m]):
            notes.append(f"flow_networks: {m} left out: {WEIGHTS_PARAM[m]}="
                         f"{getattr(params, WEIGHTS_PARAM[m])} is not a file")
        else:
            where = cache_files(m)[0]
            notes.append(f"flow_networks: {m} left out: no weights (set "
                         f"{WEIGHTS_PARAM[m]}, or put {where.name} into {where.parent}/; "
                         "`make weights` fetches RAFT's)")
    return methods, notes
