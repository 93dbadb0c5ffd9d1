"""Where network weights are looked up and how a file becomes a model's weights:
``$TORCH_HOME/hub/checkpoints``, ``torch.load(weights_only=True)`` of a state_dict (zip or
legacy format) and a strict load that names the file and the first mismatching keys."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import Tensor, nn

from flowmod.artefacts import CheckpointError, state_dict_mismatch


def hub_checkpoint_dir() -> Path:
    """``$TORCH_HOME/hub/checkpoints`` (``~/.cache/torch/hub/checkpoints`` by default)."""
    return Path(torch.hub.get_dir()) / "checkpoints"


def strip_prefix(sd: Mapping[str, Tensor], prefix: str = "module.") -> dict[str, Tensor]:
    """Remove ``prefix`` (e.g. DataParallel's ``module.``) when every key has it."""
    if sd and all(k.startswith(prefix) for k in sd):
        return {k[len(prefix) :]: v for k, v in sd.items()}
    return dict(sd)




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
