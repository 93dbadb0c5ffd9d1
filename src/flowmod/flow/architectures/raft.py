"""RAFT through torchvision's architectures: :func:`build_raft` (never downloads),
:func:`raft_flow` (normalisation and padding around the network), the files torchvision
caches for each, and the princeton-vl checkpoint layout mapped to torchvision's and back."""

from __future__ import annotations

import os
import re
from collections.abc import Mapping

from torch import Tensor, nn

from flowmod.artefacts import CheckpointError
from flowmod.flow.architectures.checkpoints import strip_prefix
from flowmod.flow.architectures.padding import pad_to_multiple, unpad

RAFT_ARCHS = ("raft_large", "raft_small")
#: torchvision's RAFT pools the correlation 3 times: the padded input needs 8 * 16 px a side.
RAFT_MIN_SIZE = 128


def build_raft(arch: str) -> nn.Module:
    """An untrained torchvision RAFT (``raft_large`` or ``raft_small``); never downloads."""
    from torchvision.models import optical_flow

    if arch not in RAFT_ARCHS:
        raise ValueError(f"unknown RAFT architecture {arch!r}; known: {', '.join(RAFT_ARCHS)}")
    return getattr(optical_flow, arch)(weights=None, progress=False)


def raft_flow(model: nn.Module, img1: Tensor, img2: Tensor, num_flow_updates: int = 12) -> Tensor:
    """Flow in pixels (B, 2, H, W) for RGB images (B, 3, H, W) with values in [0, 255].

    Inputs are scaled to [-1, 1], padded (replicate) to multiples of 8 (and to at least
    128 px, the smallest size torchvision's correlation pyramid accepts), and the flow of the
    last update is cropped back to (H, W), so pixel (y, x) of the output belongs to pixel
    (y, x) of ``img1``.
    """
    x1 = img1 * (2.0 / 255.0) - 1.0
    x2 = img2 * (2.0 / 255.0) - 1.0
    x1, pads = pad_to_multiple(x1, 8, min_size=RAFT_MIN_SIZE)
    x2, _ = pad_to_multiple(x2, 8, min_size=RAFT_MIN_SIZE)
    preds = model(x1, x2, num_flow_updates=num_flow_updates)
    return unpad(preds[-1], pads)


def torchvision_weight_files(arch: str) -> list[tuple[str, str]]:
    """``[(enum member name, file name), ...]`` torchvision would cache for ``arch``, preferred
    first (the KITTI fine-tuned large model first: the paper used KITTI-trained weights)."""
    from torchvision.models.optical_flow import Raft_Large_Weights, Raft_Small_Weights

    enum = Raft_Large_Weights if arch == "raft_large" else Raft_Small_Weights
    members = list(enum)
    members.sort(key=lambda m: _RAFT_PREFERENCE.index(m.name) if m.name in _RAFT_PREFERENCE else 99)
    return [(f"{enum.__name__}.{m.name}", os.path.basename(m.url)) for m in members]


_RAFT_PREFERENCE = (
    "C_T_SKHT_K_V1",
    "C_T_SKHT_K_V2",
    "C_T_SKHT_V2",
    "C_T_SKHT_V1",
    "C_T_V2",
    "C_T_V1",
)


_ORIG_UPDATE = {
    "encoder.convc1": "motion_encoder.convcorr1.0",
    "encoder.convc2": "motion_encoder.convcorr2.0",
    "encoder.convf1": "motion_encoder.convflow1.0",
    "encoder.convf2": "motion_encoder.convflow2.0",
    "encoder.conv": "motion_encoder.conv.0",
    "gru.convz1": "recurrent_block.convgru1.convz",
    "gru.convr1": "recurrent_block.convgru1.convr",
    "gru.convq1": "recurrent_block.convgru1.convq",
    "gru.convz2": "recurrent_block.convgru2.convz",
    "gru.convr2": "recurrent_block.convgru2.convr",
    "gru.convq2": "recurrent_block.convgru2.convq",
    "gru.convz": "recurrent_block.convgru1.convz",  # raft_small: one 3x3 ConvGRU
    "gru.convr": "recurrent_block.convgru1.convr",
    "gru.convq": "recurrent_block.convgru1.convq",
    "flow_head.conv1": "flow_head.conv1",
    "flow_head.conv2": "flow_head.conv2",
}
# torchvision -> original; raft_small's single ConvGRU has no 1/2 suffix in the original
_TV_UPDATE = {v: k for k, v in _ORIG_UPDATE.items() if not k.startswith("gru.") or k[-1] in "12"}
_TV_UPDATE_SMALL = {
    v: k for k, v in _ORIG_UPDATE.items() if not k.startswith("gru.") or k[-1] > "9"
}
_ENCODERS = {"fnet": "feature_encoder", "cnet": "context_encoder"}
_BLOCK = re.compile(r"^(layer\d+\.\d+)\.(conv|norm)(\d+)\.(.+)$")
_TV_BLOCK = re.compile(r"^(layer\d+\.\d+)\.convnormrelu(\d+)\.([01])\.(.+)$")


def is_original_raft(sd: Mapping[str, Tensor]) -> bool:
    """True for the princeton-vl layout (``[module.]fnet.*``, ``update_block.gru.*``...)."""
    keys = strip_prefix(sd).keys()
    return any(k.startswith(("fnet.", "cnet.")) for k in keys)


def raft_original_to_torchvision(sd: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """Map an original RAFT state_dict (``module.fnet.conv1.weight``...) to torchvision names.

    Residual blocks: ``convK``/``normK`` -> ``convnormreluK.0``/``.1``; the block's extra norm
    (``norm3`` of a residual, ``norm4`` of a bottleneck block) is the same module as
    ``downsample.1`` and is dropped (or renamed, if ``downsample.1`` is absent). Encoders:
    ``conv1``/``norm1``/``conv2`` -> ``convnormrelu.0``/``convnormrelu.1``/``conv``. Update
    block: ``encoder.convc1`` -> ``motion_encoder.convcorr1.0`` ..., ``gru.convz1`` ->
    ``recurrent_block.convgru1.convz`` ..., ``mask.0``/``mask.2`` -> ``mask_predictor``.
    """
    sd = strip_prefix(sd)
    # the number of convolutions per residual block tells which norm is the downsample's
    nconv: dict[str, int] = {}
    for k in sd:
        enc, _, rest = k.partition(".")
        m = _BLOCK.match(rest)
        if enc in _ENCODERS and m and m.group(2) == "conv":
            key = f"{enc}.{m.group(1)}"
            nconv[key] = max(nconv.get(key, 0), int(m.group(3)))
    out: dict[str, Tensor] = {}
    for k, v in sd.items():
        enc, _, rest = k.partition(".")
        if enc in _ENCODERS:
            tv = _ENCODERS[enc]
            m = _BLOCK.match(rest)
            if rest.startswith("conv1."):
                out[f"{tv}.convnormrelu.0.{rest[6:]}"] = v
            elif rest.startswith("norm1."):
                out[f"{tv}.convnormrelu.1.{rest[6:]}"] = v
            elif rest.startswith("conv2."):
                out[f"{tv}.conv.{rest[6:]}"] = v
            elif m:
                block, kind, num, param = m.group(1), m.group(2), int(m.group(3)), m.group(4)
                if kind == "norm" and num > nconv.get(f"{enc}.{block}", 0):
                    alias = f"{enc}.{block}.downsample.1.{param}"
                    if alias not in sd:
                        out[f"{tv}.{block}.downsample.1.{param}"] = v
                    continue
                out[f"{tv}.{block}.convnormrelu{num}.{0 if kind == 'conv' else 1}.{param}"] = v
            else:  # layerX.Y.downsample.*
                out[f"{tv}.{rest}"] = v
        elif enc == "update_block":
            if rest.startswith("mask.0."):
                out[f"mask_predictor.convrelu.0.{rest[7:]}"] = v
            elif rest.startswith("mask.2."):
                out[f"mask_predictor.conv.{rest[7:]}"] = v
            else:
                mod, _, param = rest.rpartition(".")
                if mod not in _ORIG_UPDATE:
                    raise CheckpointError(f"unknown key in an original RAFT checkpoint: {k}")
                out[f"update_block.{_ORIG_UPDATE[mod]}.{param}"] = v
        else:
            raise CheckpointError(f"unknown key in an original RAFT checkpoint: {k}")
    return out


def raft_torchvision_to_original(
    sd: Mapping[str, Tensor], prefix: str = "module."
) -> dict[str, Tensor]:
    """Inverse of :func:`raft_original_to_torchvision`, in the layout of the princeton-vl
    checkpoints (``module.`` prefix from DataParallel; the downsample norm also stored under its
    block name ``norm3``/``norm4``, as the original modules register it twice)."""
    nconv: dict[str, int] = {}
    for k in sd:
        enc, _, rest = k.partition(".")
        m = _TV_BLOCK.match(rest)
        if m:
            key = f"{enc}.{m.group(1)}"
            nconv[key] = max(nconv.get(key, 0), int(m.group(2)))
    inv_enc = {v: k for k, v in _ENCODERS.items()}
    sep_gru = any(k.startswith("update_block.recurrent_block.convgru2.") for k in sd)
    update_map = _TV_UPDATE if sep_gru else _TV_UPDATE_SMALL
    out: dict[str, Tensor] = {}
    for k, v in sd.items():
        enc, _, rest = k.partition(".")
        if enc in inv_enc:
            o = inv_enc[enc]
            m = _TV_BLOCK.match(rest)
            if rest.startswith("convnormrelu.0."):
                out[f"{o}.conv1.{rest[15:]}"] = v
            elif rest.startswith("convnormrelu.1."):
                out[f"{o}.norm1.{rest[15:]}"] = v
            elif rest.startswith("conv."):
                out[f"{o}.conv2.{rest[5:]}"] = v
            elif m:
                block, num, sub, param = m.group(1), m.group(2), m.group(3), m.group(4)
                out[f"{o}.{block}.{'conv' if sub == '0' else 'norm'}{num}.{param}"] = v
            else:
                out[f"{o}.{rest}"] = v
                dm = re.match(r"^(layer\d+\.\d+)\.downsample\.1\.(.+)$", rest)
                if dm:  # the same norm module, registered under the block's name too
                    out[
                        f"{o}.{dm.group(1)}.norm{nconv[f'{enc}.{dm.group(1)}'] + 1}.{dm.group(2)}"
                    ] = v
        elif enc == "update_block":
            mod, _, param = rest.rpartition(".")
            if mod not in update_map:
                raise CheckpointError(f"unknown key in a torchvision RAFT state_dict: {k}")
            out[f"update_block.{update_map[mod]}.{param}"] = v
        elif enc == "mask_predictor":
            if rest.startswith("convrelu.0."):
                out[f"update_block.mask.0.{rest[11:]}"] = v
            elif rest.startswith("conv."):
                out[f"update_block.mask.2.{rest[5:]}"] = v
            else:
                raise CheckpointError(f"unknown key in a torchvision RAFT state_dict: {k}")
        else:
            raise CheckpointError(f"unknown key in a torchvision RAFT state_dict: {k}")
    return {prefix + k: v for k, v in out.items()}
