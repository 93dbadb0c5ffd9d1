"""FastFlowNet (Kong et al., ICRA 2021), written from the layer specification in DESIGN.md
section 5 with the layer names and shapes of the official checkpoints (plain state_dicts,
104 keys), with a plain-PyTorch :func:`correlation` (no compiled ops), and
:func:`fastflownet_flow`: the input normalisation, resizing and output scaling around it."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from flowmod.flowweights import FASTFLOWNET_SYNTH

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

#: Official checkpoint file names, in the order they are looked for (KITTI first: the
#: paper's): the weights catalog's.
FFN_CHECKPOINT_NAMES = FASTFLOWNET_SYNTH.cache_names


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
