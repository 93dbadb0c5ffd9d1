"""The classifier of the paper (Sec. IV-B): a 2-channel ResNet18 with one output logit.

torchvision ``resnet18(weights=None)`` (trained from scratch) with ``conv1`` taking the two
flow channels (u, v) and ``fc`` giving one logit; ``sigmoid(logit) > 0.5`` means moving.
The new ``conv1`` and ``fc`` keep PyTorch's default initialisation, as in the original code.
``width`` narrows every stage (64: the paper's; the demo trains a narrower one, see the
differences page).
The extensions of chapter 10 use the same network with other input channels
(``in_channels``: flow + static-world flow, image crops, ...); :func:`load_model` reads the
channel count from the checkpoint.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from flowmod.artefacts import CheckpointError, state_dict_mismatch
from flowmod.environment import resolve_device
from flowmod.metrics import sigmoid

#: Parameters of torchvision's resnet18 (3 input channels, 1000 classes).
RESNET18_PARAMS = 11_689_512

#: How the flow channels of a crop are scaled before the network sees them (the recipe's
#: ``crop_input``): ``raw`` px as stored (the paper); ``centred``: each crop's median (per
#: channel, over its S x S pixels) subtracted, so the window's background, mostly static
#: world, reads about 0 and the ego motion's flow at that place in the frame cancels;
#: ``clipped``: values limited to +-:data:`CLIP_PX`; ``log``: sign(x) log(1 + |x|);
#: ``centred-log``: centred, then log.
INPUT_MODES = ("raw", "centred", "clipped", "log", "centred-log")
#: The bound of the ``clipped`` input, px (the far vehicles' flow is a few px to tens).
CLIP_PX = 50.0


def scale_input(x: torch.Tensor, mode: str, channels: Sequence[int] = (0, 1)) -> torch.Tensor:
    """The input ``mode`` (:data:`INPUT_MODES`) of crops ``x`` (B, C, S, S), px: the flow
    ``channels`` scaled, the others as they are; a new tensor (``x`` is never changed)."""
    if mode not in INPUT_MODES:
        raise ValueError(f"input mode {mode!r}: use one of {', '.join(INPUT_MODES)}")
    idx = list(channels)
    if mode == "raw" or not idx:
        return x
    out = x.clone()
    f = out[:, idx].float()
    if mode in ("centred", "centred-log"):
        f = f - f.flatten(2).median(dim=2).values[..., None, None]
    if mode == "clipped":
        f = f.clamp(-CLIP_PX, CLIP_PX)
    if mode in ("log", "centred-log"):
        f = torch.sign(f) * torch.log1p(f.abs())
    out[:, idx] = f.to(out.dtype)
    return out


def _scale_hook(module: nn.Module, args: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor]:
    mode = INPUT_MODES[int(module.input_mode)]
    return (scale_input(args[0], mode, module.input_channels.tolist()),)


def motion_resnet18(in_channels: int = 2, width: int = 64, input_mode: str = "raw",
                    flow_channels: Sequence[int] = (0, 1)) -> nn.Module:
    """ResNet18 for (B, C, S, S) crops -> (B, 1) logits (any S >= 32; C = 2: flow u, v).

    ``width``: channels of the first stage (64: the paper's network; its stages have
    width, 2, 4 and 8 x width channels). Depth, blocks and strides are ResNet18's.
    ``input_mode`` (:data:`INPUT_MODES`, other than ``raw``): the network scales its
    ``flow_channels`` itself (:func:`scale_input`, a forward pre-hook), and its state_dict
    records how (buffers ``input_mode``, ``input_channels``), so every reader of the
    weights (training, evaluation, ``flowmod.predict``) feeds it stored crops alike."""
    if in_channels < 1 or width < 1:
        raise ValueError(f"in_channels and width must be >= 1, got {in_channels}, {width}")
    if input_mode not in INPUT_MODES:
        raise ValueError(f"input mode {input_mode!r}: use one of {', '.join(INPUT_MODES)}")
    from torchvision.models import resnet18  # here: torchvision's import costs ~1 s

    m = resnet18(weights=None)
    if width != 64:
        _narrow(m, width)
    m.conv1 = nn.Conv2d(in_channels, width, kernel_size=7, stride=2, padding=3, bias=False)
    m.fc = nn.Linear(m.fc.in_features, 1)
    if input_mode != "raw":
        bad = [c for c in flow_channels if not 0 <= c < in_channels]
        if bad:
            raise ValueError(f"flow channels {bad} outside the input's {in_channels}")
        m.register_buffer("input_mode", torch.tensor(INPUT_MODES.index(input_mode)))
        m.register_buffer("input_channels", torch.tensor(list(flow_channels), dtype=torch.long))
        m.register_forward_pre_hook(_scale_hook)
    return m


def input_mode_of(model: nn.Module) -> str:
    """The input scaling a network applies (:data:`INPUT_MODES`; ``raw`` without one)."""
    code = getattr(model, "input_mode", None)
    return "raw" if code is None else INPUT_MODES[int(code)]


def _narrow(m: nn.Module, width: int) -> None:
    """Give ResNet18 ``m`` stages of width, 2, 4, 8 x ``width`` channels (the layout and
    initialisation of torchvision's, whose state_dict keys it keeps)."""
    from torchvision.models.resnet import BasicBlock  # here: ~1 s to import

    m.bn1 = nn.BatchNorm2d(width)
    planes = [width, 2 * width, 4 * width, 8 * width]
    inplanes = width
    for k, p in enumerate(planes, start=1):
        stride = 1 if k == 1 else 2
        down = None if stride == 1 and inplanes == p else nn.Sequential(
            nn.Conv2d(inplanes, p, kernel_size=1, stride=stride, bias=False), nn.BatchNorm2d(p))
        setattr(m, f"layer{k}", nn.Sequential(BasicBlock(inplanes, p, stride, down),
                                              BasicBlock(p, p)))
        inplanes = p
    m.fc = nn.Linear(8 * width, 1000)
    for mod in m.modules():
        if isinstance(mod, nn.Conv2d):
            nn.init.kaiming_normal_(mod.weight, mode="fan_out", nonlinearity="relu")
        elif isinstance(mod, nn.BatchNorm2d):
            nn.init.ones_(mod.weight)
            nn.init.zeros_(mod.bias)


def count_parameters(model: nn.Module) -> int:
    """Number of parameters (trainable or not; buffers excluded)."""
    return sum(p.numel() for p in model.parameters())


def _state_dict_of(obj: object, path: Path) -> dict[str, torch.Tensor]:
    """A state_dict from a saved object: a state_dict, or a training checkpoint's 'model'."""
    if isinstance(obj, dict) and "model" in obj and isinstance(obj["model"], dict):
        obj = obj["model"]
    if not isinstance(obj, dict) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise CheckpointError(
            f"{path}: not a state_dict (got {type(obj).__name__}); expected the output of "
            "torch.save(model.state_dict()) or a flowmod training checkpoint (last.pt)"
        )
    keys = list(obj)
    if keys and all(k.startswith("module.") for k in keys):  # saved from DataParallel
        obj = {k.removeprefix("module."): v for k, v in obj.items()}
    return obj


def _input_scaling(state: dict[str, torch.Tensor], path: Path) -> tuple[str, list[int]]:
    """(input mode, flow channels) a checkpoint's network was trained with (raw: none)."""
    code, chans = state.get("input_mode"), state.get("input_channels")
    if code is None:
        return "raw", [0, 1]
    if code.numel() != 1 or not 0 <= int(code) < len(INPUT_MODES) or chans is None:
        raise CheckpointError(f"{path}: input_mode {code.tolist()} is not one of "
                              f"{len(INPUT_MODES)} known input scalings; retrain the model")
    return INPUT_MODES[int(code)], [int(c) for c in chans.reshape(-1).tolist()]


def check_state_dict(state: dict[str, torch.Tensor], model: nn.Module, source: str) -> None:
    """Raise :class:`CheckpointError` listing missing/unexpected keys and shape mismatches."""
    problems = state_dict_mismatch(state, model.state_dict())
    if problems:
        raise CheckpointError(
            f"{source}: not a checkpoint of motion_resnet18 (ResNet18, 1 logit); "
            + problems
        )


def load_model(path: str | os.PathLike[str], device: str | torch.device = "cpu",
               in_channels: int | None = 2) -> nn.Module:
    """motion_resnet18 with the weights of ``path`` (state_dict or last.pt), in eval mode.

    ``in_channels``: the input channels the caller will feed (2: flow crops); None takes
    them from the checkpoint (chapter 10's models of other inputs). Raises
    :class:`CheckpointError` naming the file and the mismatching keys/shapes when the
    checkpoint belongs to another architecture or input.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model checkpoint not found: {path}")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many kinds for a damaged file
        raise CheckpointError(
            f"{path}: not a readable checkpoint ({type(e).__name__}: "
            f"{(str(e).splitlines() or ['empty file'])[0]}); "
            "the file may be cut short or not a model: copy it again or retrain") from None
    state = _state_dict_of(obj, path)
    conv1 = state.get("conv1.weight")
    shaped = conv1 is not None and conv1.ndim == 4
    if in_channels is None:
        in_channels = int(conv1.shape[1]) if shaped else 2
    with torch.device("meta"):  # no initialisation (0.1 s a model): every tensor is loaded
        model = motion_resnet18(in_channels, int(conv1.shape[0]) if shaped else 64,
                                *_input_scaling(state, path))
    check_state_dict(state, model, str(path))
    like = model.state_dict()
    model.load_state_dict({k: v.to(like[k].dtype) for k, v in state.items()}, assign=True)
    return model.to(resolve_device(device)).eval()


# --- predictions -----------------------------------------------------------------------------


def _batches(n: int, batch_size: int) -> Iterable[slice]:
    for a in range(0, n, batch_size):
        yield slice(a, min(a + batch_size, n))


def predict_logits(
    model: nn.Module, x: Any, batch_size: int = 256, device: str | torch.device = "auto",
    amp: str | None = None,
) -> np.ndarray:
    """Logits (N,) float64 for crops x: (N, C, S, S) (float16 memmap or any array), pixels.

    Runs in eval mode under ``torch.inference_mode`` (no flips, no augmentation); the model's
    train/eval mode is restored afterwards. ``amp``: None, 'bf16' or 'fp16' autocast.
    """
    dev = resolve_device(device)
    was_training = model.training
    model.eval()
    out = np.empty(len(x), dtype=np.float64)
    dtype = _amp_dtype(amp)
    try:
        with torch.inference_mode():
            for sl in _batches(len(x), batch_size):
                xb = torch.from_numpy(np.array(x[sl]))  # a copy in the stored dtype: fewer bytes
                xb = xb.to(dev, non_blocking=True).float()  # to move; converted there
                xb = xb.contiguous(memory_format=torch.channels_last)
                with torch.autocast(dev.type, dtype=dtype, enabled=dtype is not None):
                    logits = model(xb)
                out[sl] = logits.float().reshape(-1).cpu().numpy()
    finally:
        model.train(was_training)
    return out


def predict(
    model: nn.Module, x: Any, batch_size: int = 256, device: str | torch.device = "auto",
    amp: str | None = None,
) -> np.ndarray:
    """Probabilities of 'moving' (N,) float64 for crops x: (N, C, S, S), pixels."""
    z = predict_logits(model, x, batch_size=batch_size, device=device, amp=amp)
    return sigmoid(z)



def _amp_dtype(amp: str | None) -> torch.dtype | None:
    if amp in (None, "none", False):
        return None
    if amp == "bf16":
        return torch.bfloat16
    if amp == "fp16":
        return torch.float16
    raise ValueError(f"amp={amp!r}: use None, 'bf16' or 'fp16'")

