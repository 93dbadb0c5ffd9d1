"""Padding to a multiple of a side (RAFT needs H, W divisible by 8) and back."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor

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
