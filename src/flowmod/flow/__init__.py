"""Optical flow: estimators behind one interface, flow files, accuracy metrics, the flow stage.

    est = get_estimator("dis", preset="medium", scale=0.5)
    flow = est.estimate(img1, img2)   # img: (H, W, 3) uint8 BGR as cv2.imread gives
                                      # flow: (H, W, 2) float32, pixels, frame1 -> frame2

Modules: :mod:`~flowmod.flow.registry` (base class, registry, image I/O),
:mod:`~flowmod.flow.estimators` (gt, dis, farneback), :mod:`~flowmod.flow.networks` (raft,
raft_small, fastflownet over :mod:`~flowmod.flow.architectures`), :mod:`~flowmod.flow.store` (files),
:mod:`~flowmod.flow.metrics` (EPE, Fl-all, colour coding), :mod:`~flowmod.flow.stage` (the
stage of chapter 03).
"""

from flowmod.flow import estimators, networks  # noqa: F401  (register the methods)
from flowmod.flow.metrics import (
    box_bias,
    boxes_mask,
    endpoint_error,
    epe,
    fl_all,
    flow_metrics,
    flow_to_color,
)
from flowmod.flow.networks import estimator_options
from flowmod.flow.registry import (
    FlowEstimator,
    FlowFileError,
    ImageError,
    MissingWeightsError,
    NotSyntheticError,
    available_methods,
    get_estimator,
    read_image,
    register_estimator,
    resize_flow,
)
from flowmod.flow.stage import (
    FlowFiles,
    FlowReader,
    check_images,
    clip_pairs,
    compute_flow,
    figure_pair,
    flow_root,
    kept_pairs,
)
from flowmod.flow.store import (
    load_flow_npy,
    load_stored_flow,
    read_flo,
    save_flow_npy,
    store_flow,
    write_flo,
)

__all__ = [
    "FlowEstimator",
    "FlowFiles",
    "FlowReader",
    "clip_pairs",
    "figure_pair",
    "kept_pairs",
    "FlowFileError",
    "ImageError",
    "MissingWeightsError",
    "NotSyntheticError",
    "available_methods",
    "check_images",
    "compute_flow",
    "flow_root",
    "box_bias",
    "boxes_mask",
    "endpoint_error",
    "epe",
    "estimator_options",
    "fl_all",
    "flow_metrics",
    "flow_to_color",
    "get_estimator",
    "load_stored_flow",
    "load_flow_npy",
    "read_flo",
    "read_image",
    "register_estimator",
    "resize_flow",
    "save_flow_npy",
    "store_flow",
    "write_flo",
]
