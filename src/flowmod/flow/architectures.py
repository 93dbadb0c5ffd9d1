"""Optical-flow networks in plain PyTorch: FastFlowNet, RAFT weight handling, padding.

This module holds the network side of :mod:`flowmod.flow` (which imports it lazily, so that the
CPU methods never pay for importing torch):

* :class:`FastFlowNet`: Kong et al., ICRA 2021, written from the layer specification in
  DESIGN.md section 5 with the layer names and shapes of the official checkpoints (plain
  state_dicts, 104 keys), and a plain-PyTorch :func:`correlation` (no compiled ops).
* :func:`fastflownet_flow` and :func:`raft_flow`: the input normalisation, resizing / padding
  and output scaling around each network, so the models see exactly what they were trained on.
* RAFT weights: :func:`raft_original_to_torchvision` / :func:`raft_torchvision_to_original`
  map the princeton-vl checkpoint layout (``module.fnet.*``, ``module.update_block.*``) to the
  layout of ``torchvision.models.optical_flow.raft_large`` / ``raft_small`` and back.
* :func:`read_checkpoint` and :func:`load_weights`: ``torch.load(weights_only=True)`` of a file
  (zip or legacy format) and a strict load that names the file and the first mismatching keys.

Conventions: image tensors are (B, 3, H, W) float; flow tensors are (B, 2, H, W) with channel
0 = u (x, to the right) and 1 = v (y, down), in pixels of the image they refer to.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from flowmod.artefacts import CheckpointError, state_dict_mismatch

# --------------------------------------------------------------------------------------------
# padding (RAFT needs H, W divisible by 8)
# --------------------------------------------------------------------------------------------

Pads = tuple[int, int, int, int]  # left, right, top, bottom


def pad_to_multiple(
    x: Tensor, multiple: int = 8, mode: str = "replicate", min_size: int = 0
) -> tuple[Tensor, Pads]:
    """Pad the last two dims of ``x`` (B, C, H, W) up to multiples of ``multiple`` (and at
    least ``min_size``).

    The padding is split evenly (the odd pixel goes to the right / bottom), as RAFT's own
    ``InputPadder`` does for Sintel; returns the padded tensor and (left, right, top, bottom).
    """
    h, w = x.shape[-2:]
    ph = max(min_size - h, (-h) % multiple)
    pw = max(min_size - w, (-w) % multiple)
    ph, pw = ph + (-(h + ph)) % multiple, pw + (-(w + pw)) % multiple
    pads = (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2)
    if ph == 0 and pw == 0:
        return x, pads
    return F.pad(x, pads, mode=mode), pads


def unpad(x: Tensor, pads: Pads) -> Tensor:
    """Undo :func:`pad_to_multiple` on the last two dims (the original project forgot this)."""
    left, right, top, bottom = pads
    h, w = x.shape[-2:]
    return x[..., top : h - bottom, left : w - right]


# --------------------------------------------------------------------------------------------
# FastFlowNet
# --------------------------------------------------------------------------------------------

#: The 53 of the 81 (dy-major) displacements of radius 4 that FastFlowNet keeps.
FFN_CORR_INDEX: tuple[int, ...] = (
    0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 21, 22, 23, 24, 26, 28, 29, 30, 31, 32, 33, 34,
    36, 38, 39, 40, 41, 42, 44, 46, 47, 48, 49, 50, 51, 52, 54, 56, 57, 58, 59, 60, 62, 64,
    66, 68, 70, 72, 74, 76, 78, 80,
)  # fmt: skip

#: FastFlowNet's flow unit: the network predicts flow / 20.
FFN_DIV_FLOW = 20.0
#: FastFlowNet's input sides are resized to multiples of this.
FFN_DIV_SIZE = 64
#: Scale of the upsampled flow (units px/20 at 1/4 resolution) into pixels of levels 5..2.
_FFN_WARP_SCALE = {5: 0.625, 4: 1.25, 3: 2.5, 2: 5.0}

#: Official checkpoint file names, in the order they are looked for (KITTI first: the paper's).
FFN_CHECKPOINT_NAMES = (
    "fastflownet_ft_kitti.pth",
    "fastflownet_ft_mix.pth",
    "fastflownet_ft_sintel.pth",
    "fastflownet_things3d.pth",
    "fastflownet_chairs.pth",
)


def correlation(
    f1: Tensor,
    f2: Tensor,
    max_displacement: int = 4,
    displacements: Sequence[int] | None = None,
) -> Tensor:
    """Local cost volume between feature maps, in plain PyTorch.

    ``f1``, ``f2``: (B, C, H, W). Channel ``k = (dy + r) * (2r + 1) + (dx + r)`` (dy-major) of
    the result is ``sum_c f1[:, c, y, x] * f2[:, c, y + dy, x + dx] / C``, with ``f2`` zero
    outside the image. ``displacements`` picks a subset of the channel indices (computing only
    those equals ``index_select`` of the full volume). Returns (B, D, H, W).
    """
    b, c, h, w = f1.shape
    r = max_displacement
    d = 2 * r + 1
    idx = range(d * d) if displacements is None else displacements
    # channels last: each displacement's sum over channels runs along contiguous memory
    # (about 3x faster on a CPU than summing over the channel dimension of (B, C, H, W))
    a = f1.permute(0, 2, 3, 1).contiguous()
    f2p = F.pad(f2, (r, r, r, r)).permute(0, 2, 3, 1).contiguous()
    out = f1.new_empty(b, len(idx), h, w)
    for k, i in enumerate(idx):
        oy, ox = divmod(int(i), d)  # offsets into the padded map = (dy + r, dx + r)
        out[:, k] = (a * f2p[:, oy : oy + h, ox : ox + w, :]).sum(-1)
    return out / c


def warp(x: Tensor, flow: Tensor) -> Tensor:
    """Sample ``x`` (B, C, H, W) at ``(x + u, y + v)``: bilinear, zeros outside, corners aligned.

    ``flow``: (B, 2, H, W) in pixels of ``x``.
    """
    b, _, h, w = x.shape
    ys = torch.arange(h, device=x.device, dtype=x.dtype).view(1, h, 1)
    xs = torch.arange(w, device=x.device, dtype=x.dtype).view(1, 1, w)
    gx = (xs + flow[:, 0]) * (2.0 / max(w - 1, 1)) - 1.0
    gy = (ys + flow[:, 1]) * (2.0 / max(h - 1, 1)) - 1.0
    grid = torch.stack((gx, gy), dim=-1)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=True)


def _conv_lrelu(cin: int, cout: int, stride: int = 1, groups: int = 1) -> nn.Sequential:
    """3x3 convolution (with bias) + LeakyReLU(0.1); keys ``<name>.0.weight/bias``."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride, 1, groups=groups, bias=True),
        nn.LeakyReLU(0.1, inplace=True),
    )


def channel_shuffle(x: Tensor, groups: int) -> Tensor:
    """(B, G*K, H, W) -> interleave the G groups' channels (ShuffleNet)."""
    b, c, h, w = x.shape
    return x.view(b, groups, c // groups, h, w).transpose(1, 2).reshape(b, c, h, w)


class FFNDecoder(nn.Module):
    """FastFlowNet's flow decoder: 87 -> 96 -> 3 x 96 (grouped, shuffled) -> 64 -> 32 -> 2."""

    def __init__(self, in_channels: int = 87, groups: int = 3) -> None:
        super().__init__()
        self.groups = groups
        self.conv1 = _conv_lrelu(in_channels, 96)
        self.conv2 = _conv_lrelu(96, 96, groups=groups)
        self.conv3 = _conv_lrelu(96, 96, groups=groups)
        self.conv4 = _conv_lrelu(96, 96, groups=groups)
        self.conv5 = _conv_lrelu(96, 64)
        self.conv6 = _conv_lrelu(64, 32)
        self.conv7 = nn.Conv2d(32, 2, 3, 1, 1)

    def forward(self, x: Tensor) -> Tensor:
        x = self.conv1(x)
        for conv in (self.conv2, self.conv3, self.conv4):
            x = conv(x)
            if self.groups > 1:
                x = channel_shuffle(x, self.groups)
        return self.conv7(self.conv6(self.conv5(x)))


class FastFlowNet(nn.Module):
    """FastFlowNet (Kong, Shen, Yang, ICRA 2021) in plain PyTorch.

    ``forward(img1, img2)``: normalised images (B, 3, H, W) with H, W multiples of 64 (see
    :func:`fastflownet_flow` for the preprocessing) -> ``flow2`` (B, 2, H/4, W/4) in units of
    pixels / 20 at the 1/4 resolution of the input.
    """

    def __init__(self, groups: int = 3) -> None:
        super().__init__()
        self.groups = groups
        self.pconv1_1 = _conv_lrelu(3, 16, 2)
        self.pconv1_2 = _conv_lrelu(16, 16)
        self.pconv2_1 = _conv_lrelu(16, 32, 2)
        self.pconv2_2 = _conv_lrelu(32, 32)
        self.pconv2_3 = _conv_lrelu(32, 32)
        self.pconv3_1 = _conv_lrelu(32, 64, 2)
        self.pconv3_2 = _conv_lrelu(64, 64)
        self.pconv3_3 = _conv_lrelu(64, 64)
        self.rconv2 = _conv_lrelu(32, 32)
        self.rconv3 = _conv_lrelu(64, 32)
        self.rconv4 = _conv_lrelu(64, 32)
        self.rconv5 = _conv_lrelu(64, 32)
        self.rconv6 = _conv_lrelu(64, 32)
        self.up3 = nn.ConvTranspose2d(2, 2, 4, 2, 1)
        self.up4 = nn.ConvTranspose2d(2, 2, 4, 2, 1)
        self.up5 = nn.ConvTranspose2d(2, 2, 4, 2, 1)
        self.up6 = nn.ConvTranspose2d(2, 2, 4, 2, 1)
        self.decoder2 = FFNDecoder(87, groups)
        self.decoder3 = FFNDecoder(87, groups)
        self.decoder4 = FFNDecoder(87, groups)
        self.decoder5 = FFNDecoder(87, groups)
        self.decoder6 = FFNDecoder(87, groups)
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
                nn.init.kaiming_normal_(m.weight)
                nn.init.zeros_(m.bias)

    def pyramid(self, x: Tensor) -> list[Tensor]:
        """Feature levels 2..6 of (B, 3, H, W): 32 ch at 1/4, then 64 ch at 1/8 ... 1/64."""
        x = self.pconv1_2(self.pconv1_1(x))
        f2 = self.pconv2_3(self.pconv2_2(self.pconv2_1(x)))
        f3 = self.pconv3_3(self.pconv3_2(self.pconv3_1(f2)))
        f4 = F.avg_pool2d(f3, 2, 2)
        f5 = F.avg_pool2d(f4, 2, 2)
        f6 = F.avg_pool2d(f5, 2, 2)
        return [f2, f3, f4, f5, f6]

    def forward(self, img1: Tensor, img2: Tensor) -> Tensor:
        return self.levels(img1, img2)[0]

    def levels(self, img1: Tensor, img2: Tensor) -> list[Tensor]:
        """The flow of every decoder level, finest first: ``[flow2, ..., flow6]``, level
        ``l`` (B, 2, H / 2^l, W / 2^l), each in units of pixels of the input / 20 (what a
        multi-scale loss supervises; :meth:`forward` returns ``flow2``)."""
        h, w = img1.shape[-2:]
        if h % FFN_DIV_SIZE or w % FFN_DIV_SIZE:
            raise ValueError(
                f"FastFlowNet.forward needs sides that are multiples of {FFN_DIV_SIZE}, got "
                f"{h}x{w}: use fastflownet_flow(), which resizes"
            )
        b = img1.shape[0]
        feats = self.pyramid(torch.cat((img1, img2), 0))  # one pass for both images
        f1 = {lvl: f[:b] for lvl, f in zip(range(2, 7), feats, strict=True)}
        f2 = {lvl: f[b:] for lvl, f in zip(range(2, 7), feats, strict=True)}
        rconv = {2: self.rconv2, 3: self.rconv3, 4: self.rconv4, 5: self.rconv5, 6: self.rconv6}
        up = {3: self.up3, 4: self.up4, 5: self.up5, 6: self.up6}
        dec = {
            2: self.decoder2, 3: self.decoder3, 4: self.decoder4, 5: self.decoder5,
            6: self.decoder6,
        }  # fmt: skip

        flow = f1[6].new_zeros(b, 2, *f1[6].shape[-2:])
        out: list[Tensor] = []
        for lvl in (6, 5, 4, 3, 2):
            target = f2[lvl]
            if lvl < 6:
                flow = up[lvl + 1](flow)  # coarser flow at this level, still in px/20 units
                target = warp(target, flow * _FFN_WARP_SCALE[lvl])
            cost = correlation(f1[lvl], target, 4, FFN_CORR_INDEX)
            x = torch.cat((cost, rconv[lvl](f1[lvl]), flow), 1)
            flow = dec[lvl](x) + flow  # level 6 starts from zero flow: plain prediction
            out.insert(0, flow)
        return out


def fastflownet_inputs(img1: Tensor, img2: Tensor) -> tuple[Tensor, Tensor]:
    """FastFlowNet's input for BGR images (B, 3, H, W) in [0, 255]: /255, minus the
    per-channel mean over both images, bilinear resize to the next multiples of 64."""
    h, w = img1.shape[-2:]
    x1, x2 = img1 / 255.0, img2 / 255.0
    mean = torch.cat((x1, x2), dim=2).mean(dim=(2, 3), keepdim=True)
    x1, x2 = x1 - mean, x2 - mean
    hh = FFN_DIV_SIZE * -(-h // FFN_DIV_SIZE)
    ww = FFN_DIV_SIZE * -(-w // FFN_DIV_SIZE)
    if (hh, ww) != (h, w):
        x1 = F.interpolate(x1, size=(hh, ww), mode="bilinear", align_corners=False)
        x2 = F.interpolate(x2, size=(hh, ww), mode="bilinear", align_corners=False)
    return x1, x2


def fastflownet_flow(model: FastFlowNet, img1: Tensor, img2: Tensor) -> Tensor:
    """Flow in pixels (B, 2, H, W) for BGR images (B, 3, H, W) with values in [0, 255].

    As the official demo: /255, minus the per-channel mean over both images, bilinear resize
    (align_corners=False) to multiples of 64, network, upsample its 1/4-resolution output to
    that size, x20, resize back to (H, W) with u, v multiplied by the size ratios.
    """
    h, w = img1.shape[-2:]
    x1, x2 = fastflownet_inputs(img1, img2)
    hh, ww = x1.shape[-2:]
    out = model(x1, x2)
    flow = FFN_DIV_FLOW * F.interpolate(out, size=(hh, ww), mode="bilinear", align_corners=False)
    if (hh, ww) != (h, w):
        flow = F.interpolate(flow, size=(h, w), mode="bilinear", align_corners=False)
        flow = flow * torch.tensor([w / ww, h / hh], dtype=flow.dtype, device=flow.device).view(
            1, 2, 1, 1
        )
    return flow


# --------------------------------------------------------------------------------------------
# RAFT (torchvision architectures)
# --------------------------------------------------------------------------------------------

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


def hub_checkpoint_dir() -> Path:
    """``$TORCH_HOME/hub/checkpoints`` (``~/.cache/torch/hub/checkpoints`` by default)."""
    return Path(torch.hub.get_dir()) / "checkpoints"


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


def strip_prefix(sd: Mapping[str, Tensor], prefix: str = "module.") -> dict[str, Tensor]:
    """Remove ``prefix`` (e.g. DataParallel's ``module.``) when every key has it."""
    if sd and all(k.startswith(prefix) for k in sd):
        return {k[len(prefix) :]: v for k, v in sd.items()}
    return dict(sd)


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


# --------------------------------------------------------------------------------------------
# checkpoints
# --------------------------------------------------------------------------------------------


def read_checkpoint(path: str | os.PathLike[str]) -> dict[str, Tensor]:
    """Read a state_dict with ``torch.load(weights_only=True)`` (zip or legacy format).

    Unwraps ``{"state_dict": ...}`` / ``{"model": ...}`` containers and a ``module.`` prefix.
    Raises :class:`FileNotFoundError` or :class:`CheckpointError` naming the file.
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"weights file not found: {path}")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling problem: name the file
        raise CheckpointError(
            f"cannot read weights file {path}: {type(e).__name__}: {e}".splitlines()[0]
        ) from e
    for key in ("state_dict", "model", "model_state_dict"):
        if isinstance(obj, Mapping) and isinstance(obj.get(key), Mapping):
            obj = obj[key]
    if not isinstance(obj, Mapping) or not all(isinstance(v, Tensor) for v in obj.values()):
        raise CheckpointError(f"weights file {path} does not hold a state_dict of tensors")
    return strip_prefix(obj)


def load_weights(model: nn.Module, sd: Mapping[str, Tensor], source: str) -> nn.Module:
    """Strictly load ``sd`` into ``model``, or raise :class:`CheckpointError` that names
    ``source`` and the first missing, unexpected and wrongly shaped keys."""
    own = model.state_dict()
    sd = dict(sd)
    for k in own:  # BatchNorm counters are absent from some old checkpoints: harmless
        if k.endswith("num_batches_tracked") and k not in sd:
            sd[k] = own[k]
    problems = state_dict_mismatch(sd, own)
    if problems:
        raise CheckpointError(
            f"{source} does not match the {type(model).__name__} architecture "
            f"({len(sd)} keys in the file, {len(own)} in the model): {problems}"
        )
    model.load_state_dict(sd, strict=True)
    return model
