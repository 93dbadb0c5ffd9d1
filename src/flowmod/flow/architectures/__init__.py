"""Optical-flow networks in plain PyTorch, one architecture per file, and their weights' files.

:mod:`flowmod.flow` imports this package lazily, so that the CPU methods never pay for
importing torch:

* :mod:`.fastflownet`: :class:`FastFlowNet` (Kong et al., ICRA 2021) and
  :func:`fastflownet_flow`, the input normalisation, resizing and output scaling around it;
* :mod:`.raft`: torchvision's RAFT (:func:`build_raft`, :func:`raft_flow`) and the
  princeton-vl checkpoint layout mapped to torchvision's and back
  (:func:`raft_original_to_torchvision`, :func:`raft_torchvision_to_original`);
* :mod:`.checkpoints`: where weights are looked up (:func:`hub_checkpoint_dir`),
  :func:`read_checkpoint` (``torch.load(weights_only=True)``) and :func:`load_weights` (a
  strict load that names the file and the first mismatching keys);
* :mod:`.padding`: :func:`pad_to_multiple` and :func:`unpad`.

Conventions: image tensors are (B, 3, H, W) float; flow tensors are (B, 2, H, W) with channel
0 = u (x, to the right) and 1 = v (y, down), in pixels of the image they refer to.
"""

from __future__ import annotations

from flowmod.artefacts import CheckpointError
from flowmod.flow.architectures.checkpoints import (
    hub_checkpoint_dir,
    load_weights,
    read_checkpoint,
    strip_prefix,
)
from flowmod.flow.architectures.fastflownet import (
    FFN_CHECKPOINT_NAMES,
    FFN_CORR_INDEX,
    FFN_DIV_FLOW,
    FFN_DIV_SIZE,
    FastFlowNet,
    FFNDecoder,
    channel_shuffle,
    correlation,
    fastflownet_flow,
    fastflownet_inputs,
    warp,
)
from flowmod.flow.architectures.padding import Pads, pad_to_multiple, unpad
from flowmod.flow.architectures.raft import (
    RAFT_ARCHS,
    RAFT_MIN_SIZE,
    build_raft,
    is_original_raft,
    raft_flow,
    raft_original_to_torchvision,
    raft_torchvision_to_original,
    torchvision_weight_files,
)

__all__ = [
    "FFN_CHECKPOINT_NAMES", "FFN_CORR_INDEX", "FFN_DIV_FLOW", "FFN_DIV_SIZE", "RAFT_ARCHS",
    "RAFT_MIN_SIZE", "CheckpointError", "FFNDecoder", "FastFlowNet", "Pads", "build_raft",
    "channel_shuffle", "correlation", "fastflownet_flow", "fastflownet_inputs",
    "hub_checkpoint_dir", "is_original_raft", "load_weights", "pad_to_multiple", "raft_flow",
    "raft_original_to_torchvision", "raft_torchvision_to_original", "read_checkpoint",
    "strip_prefix", "torchvision_weight_files", "unpad", "warp",
]
