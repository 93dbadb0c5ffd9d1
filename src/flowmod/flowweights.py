"""The flow networks' weights, one entry each, like a torchvision weights enum: which flow
method they serve, the parameter that names their file, where they are looked up (the file
this repository ships, trained here, with its manifest; or the files of the torch hub
cache), and how to get them. Every other module asks this one.

The shipped weights' manifest (``manifest.json`` beside ``weights.pt``) holds their recipe,
the pretraining world's fingerprint, the steps, the validation errors and the file's sha256
(written by ``make flownet``, :mod:`flowmod.flow.pretrain`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from flowmod.paths import repo_root

#: The files of a shipped weights folder: the float16 state_dict and its manifest.
WEIGHTS_NAME, MANIFEST_NAME = "weights.pt", "manifest.json"


@dataclass(frozen=True)
class FlowWeights:
    """One network's weights. ``shipped``: the repository folder of weights trained here
    (``weights.pt`` and ``manifest.json``), or None; ``cache_names``: the files looked for
    in ``$TORCH_HOME/hub/checkpoints``, preferred first (empty: torchvision's own names for
    ``torchvision_arch``); ``download``: the torchvision enum member ``make weights``
    fetches; ``how``: how a user gets them, in words."""

    method: str
    param: str
    how: str
    shipped: str | None = None
    cache_names: tuple[str, ...] = ()
    torchvision_arch: str | None = None
    download: str | None = None

    @property
    def shipped_file(self) -> str | None:
        """The shipped ``weights.pt`` relative to the repository (the parameter's default)."""
        return None if self.shipped is None else f"{self.shipped}/{WEIGHTS_NAME}"

    def manifest(self) -> dict[str, Any] | None:
        """The shipped weights' manifest, or None where nothing is shipped or it is missing."""
        if self.shipped is None:
            return None
        f = repo_root() / self.shipped / MANIFEST_NAME
        return json.loads(f.read_text()) if f.is_file() else None

    def is_shipped(self, path: str | Path) -> bool:
        """Whether ``path`` (absolute, or relative to the repository) is the shipped file."""
        if self.shipped_file is None:
            return False
        p = Path(path)
        p = p if p.is_absolute() else repo_root() / p
        return p.resolve() == (repo_root() / self.shipped_file).resolve()


#: FastFlowNet trained by this study on a synthetic world of its own (``make flownet``); an
#: official checkpoint copied into the hub cache serves with ``fastflownet_weights: null``.
FASTFLOWNET_SYNTH = FlowWeights(
    method="fastflownet", param="fastflownet_weights", shipped="weights/fastflownet_synth",
    cache_names=("fastflownet_ft_kitti.pth", "fastflownet_ft_mix.pth",
                 "fastflownet_ft_sintel.pth", "fastflownet_things3d.pth",
                 "fastflownet_chairs.pth"),
    how="shipped (make flownet trains them again); or copy an official checkpoint "
        "(checkpoints/ of https://github.com/ltkong218/FastFlowNet) into the hub cache and "
        "set fastflownet_weights: null")
#: RAFT (large), KITTI fine-tuned: the paper's choice of KITTI weights.
RAFT_LARGE = FlowWeights(
    method="raft", param="raft_weights", torchvision_arch="raft_large",
    download="C_T_SKHT_K_V1", how="make weights downloads them through torchvision (internet)")
#: RAFT small: its only published weights.
RAFT_SMALL = FlowWeights(
    method="raft_small", param="raft_small_weights", torchvision_arch="raft_small",
    download="C_T_V2", how="make weights downloads them through torchvision (internet)")

#: Every network's weights by flow method.
CATALOG: dict[str, FlowWeights] = {w.method: w for w in (RAFT_LARGE, RAFT_SMALL,
                                                        FASTFLOWNET_SYNTH)}
#: The parameter that names each network's weight file.
WEIGHTS_PARAM: dict[str, str] = {m: w.param for m, w in CATALOG.items()}
#: The shipped FastFlowNet file (the default of every parameter that names FastFlowNet
#: weights).
SHIPPED_FASTFLOWNET: str = FASTFLOWNET_SYNTH.shipped_file or ""
#: Its folder (relative to the repository root), where ``make flownet`` writes them.
SHIPPED_FASTFLOWNET_DIR: str = FASTFLOWNET_SYNTH.shipped or ""
#: The shipped weights' row name in chapter 12's tables.
SHIPPED_ROW = "fastflownet (shipped)"
#: The DIS preset that chapter 12 compares the network with (chapter 03's CPU default).
SHIPPED_DIS_PRESET = "medium"
