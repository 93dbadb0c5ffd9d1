"""The classical estimators (OpenCV DIS and Farneback) and the synthetic world's exact flow.

=============  =======================================================  ==================
name           what                                                     options
=============  =======================================================  ==================
gt             the synthetic world's exact flow (from sample_data        dataroot, version
               tokens, not images: ``estimate_tokens``)
dis            OpenCV DIS on grayscale                                  preset, scale
farneback      OpenCV Farneback on grayscale                            scale, pyr_scale...
=============  =======================================================  ==================

The networks (``raft``, ``raft_small``, ``fastflownet``) are in :mod:`flowmod.flow.networks`.
"""

from __future__ import annotations

import os
from typing import Any, ClassVar

import cv2
import numpy as np

from flowmod.flow.registry import FlowEstimator, NotSyntheticError, register_estimator
from flowmod.params import WORLD_FILE


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

    ``estimate_tokens(sd_token_1, sd_token_2) -> (flow, valid)``: flow (H, W, 2) float32
    pixels, finite everywhere (the point's motion wherever it goes; undefined pixels take
    the nearest defined flow), and valid (H, W) bool: the point stays inside the image and
    visible (:func:`flowmod.world.gt_flow`). The flow stage stores the mask beside the flow.
    """

    name = "gt"
    inputs = "tokens"
    #: The world's own description (its annotations are never read: an edited annotation
    #: recomputes no exact flow).
    world_files = (WORLD_FILE,)
    #: 2: the world's validity convention (issue 11): finite, physical values, stored mask.
    code_version = 2

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

        return importlib.import_module("flowmod.world.truth")  # lazy: another stage, heavy import

    def estimate_tokens(self, sd_token_1: str, sd_token_2: str) -> tuple[np.ndarray, np.ndarray]:
        """Exact flow (H, W, 2) float32 px and its valid mask (H, W) bool, frame
        ``sd_token_1`` -> ``sd_token_2``."""
        flow, valid = self._world().gt_flow(self.dataroot, self.version, sd_token_1, sd_token_2)
        flow = np.asarray(flow, dtype=np.float32)
        if not np.isfinite(flow).all():
            raise ValueError(f"gt flow {sd_token_1} -> {sd_token_2} has non-finite values")
        return flow, np.asarray(valid, dtype=bool)

    def estimate(self, img1: np.ndarray, img2: np.ndarray) -> np.ndarray:
        raise TypeError(
            "gt works from sample_data tokens, not images: use estimate_tokens(sd_token_1, "
            "sd_token_2) or compute_flow()"
        )

    def options(self) -> dict[str, Any]:
        return {"dataroot": self.dataroot, "version": self.version}


