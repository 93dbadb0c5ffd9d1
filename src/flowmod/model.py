"""The classifier of the paper (Sec. IV-B): a 2-channel ResNet18 with one output logit.

torchvision ``resnet18(weights=None)`` (trained from scratch) with ``conv1`` taking the two
flow channels (u, v) and ``fc`` giving one logit; ``sigmoid(logit) > 0.5`` means moving.
The new ``conv1`` and ``fc`` keep PyTorch's default initialisation, as in the original code.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

from flowmod.artefacts import CheckpointError, state_dict_mismatch
from flowmod.environment import resolve_device

#: Parameters of torchvision's resnet18 (3 input channels, 1000 classes).
RESNET18_PARAMS = 11_689_512


def motion_resnet18() -> nn.Module:
    """ResNet18 for (B, 2, S, S) flow crops -> (B, 1) logits (any S >= 32)."""
    from torchvision.models import resnet18

    m = resnet18(weights=None)
    m.conv1 = nn.Conv2d(2, 64, kernel_size=7, stride=2, padding=3, bias=False)
    m.fc = nn.Linear(m.fc.in_features, 1)
    return m


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


def check_state_dict(state: dict[str, torch.Tensor], model: nn.Module, source: str) -> None:
    """Raise :class:`CheckpointError` listing missing/unexpected keys and shape mismatches."""
    problems = state_dict_mismatch(state, model.state_dict())
    if problems:
        raise CheckpointError(
            f"{source}: not a checkpoint of motion_resnet18 (2-channel ResNet18, 1 logit); "
            + problems
        )


def load_model(path: str | os.PathLike[str], device: str | torch.device = "cpu") -> nn.Module:
    """motion_resnet18 with the weights of ``path`` (state_dict or last.pt), in eval mode.

    Raises :class:`CheckpointError` naming the file and the mismatching keys/shapes when the
    checkpoint belongs to another architecture.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model checkpoint not found: {path}")
    obj = torch.load(path, map_location="cpu", weights_only=True)
    state = _state_dict_of(obj, path)
    model = motion_resnet18()
    check_state_dict(state, model, str(path))
    model.load_state_dict(state)
    return model.to(resolve_device(device)).eval()
