"""Profiles: load and validate the parameters of a run.

A profile (``params/<name>.yaml``) is a flat mapping of parameter names to values. The same
names are the papermill parameters of the notebooks: each notebook declares the subset it uses
in its ``parameters`` cell, and :func:`validate` checks a (partial) mapping before any work.

Errors name the key, the value given and what is allowed, e.g.::

    ProfileError: params/demo.yaml: min_distance=80.0 must be < max_distance=70.0
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import pandas as pd
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from flowmod.paths import repo_root

#: Table 1 of the paper: the seven target vehicle categories (official nuScenes names).
TABLE1_CATEGORIES = [
    "vehicle.car",
    "vehicle.emergency.ambulance",
    "vehicle.emergency.police",
    "vehicle.truck",
    "vehicle.bus.bendy",
    "vehicle.bus.rigid",
    "vehicle.construction",
]

FLOW_METHODS = ("gt", "dis", "farneback", "raft", "raft_small", "fastflownet")


class ProfileError(ValueError):
    """A profile or a notebook parameter is invalid; the message names the key and the fix."""


class Params(BaseModel):
    """Every parameter of the study, with its unit and allowed range.

    Defaults are the ``demo`` profile's values, so a notebook run without a profile behaves
    like the embedded default.
    """

    model_config = ConfigDict(extra="forbid", strict=False, validate_default=True)

    # --- run ---------------------------------------------------------------------------
    profile: str = Field("demo", description="profile name; artefacts go to runs/<profile>/")
    seed: int = Field(0, ge=0, description="master seed for every random choice")
    run_dir: str = Field("runs/demo", description="stage artefacts (relative to the repo root)")
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="torch device")
    force: bool = Field(False, description="recompute stages whose outputs are up to date")

    # --- data --------------------------------------------------------------------------
    dataroot: str | None = Field("data/demo", description="nuScenes-format data root")
    version: str = Field("v1.0-synth", description="table folder under dataroot, e.g. v1.0-mini")
    synthetic: bool = Field(True, description="build the synthetic world when dataroot is absent")
    world_scenes: int = Field(40, ge=1, le=2000, description="synthetic world: number of scenes")
    world_keyframes: int = Field(20, ge=2, le=60, description="keyframes (2 Hz) per scene")
    world_sweep_scenes: int = Field(4, ge=0, description="scenes that also get ~12 Hz sweeps")
    world_vehicles: int = Field(28, ge=1, le=200, description="vehicles per scene (mean)")

    # --- selection (Table 1) -----------------------------------------------------------
    categories: list[str] = Field(default_factory=lambda: list(TABLE1_CATEGORIES))
    min_distance: float = Field(30.0, ge=0.0, description="m, nearest target vehicle")
    max_distance: float = Field(70.0, gt=0.0, description="m, farthest target vehicle")
    distance_mode: Literal["ego", "camera"] = Field(
        "ego", description="distance from the ego-pose origin (paper code) or the camera"
    )
    visibility_tokens: list[Literal["1", "2", "3", "4"]] = Field(
        default_factory=lambda: ["4"], description="nuScenes visibility bins ('4' = 80-100 %)"
    )
    exclude_descriptions: list[str] = Field(
        default_factory=lambda: ["night", "rain", "lightning"],
        description="drop scenes with a comma-separated description item equal to one of these",
    )
    split_fractions: list[float] = Field(
        default_factory=lambda: [0.7, 0.15, 0.15], description="train, val, test (by scene)"
    )
    missing_images: Literal["error", "skip"] = Field("error", description="on missing JPEGs")

    # --- labels ------------------------------------------------------------------------
    speed_threshold: float = Field(2.0, gt=0.0, description="m/s; moving if speed >= this")

    # --- generalisation ----------------------------------------------------------------
    general_interval: int = Field(4, ge=1, le=12, description="camera frames between the pair")
    general_min_distance: float = Field(0.0, ge=0.0, description="m, near vehicles included")
    general_max_distance: float = Field(100.0, gt=0.0, description="m, farthest vehicle")
    general_max_scenes: int = Field(4, ge=0, description="held-out scenes used (0 = none)")

    # --- optical flow ------------------------------------------------------------------
    flow_methods: list[Literal[FLOW_METHODS]] = Field(  # type: ignore[valid-type]
        default_factory=lambda: ["gt", "dis", "farneback"]
    )
    flow_scale: float = Field(0.5, gt=0.0, le=1.0, description="image scale at which flow is computed and stored")
    dis_preset: Literal["ultrafast", "fast", "medium"] = Field("medium")
    flow_dtype: Literal["float16", "float32"] = Field("float16")
    raft_weights: str | None = Field(None, description="path to RAFT weights (.pth)")
    raft_small_weights: str | None = Field(None, description="path to RAFT-small weights")
    fastflownet_weights: str | None = Field(None, description="path to FastFlowNet weights")
    n_jobs: int = Field(2, ge=1, le=64, description="parallel CPU workers")

    # --- crops and learning (Table 2) --------------------------------------------------
    crop_size: int = Field(64, ge=16, le=512, description="px, side of the resized crop (224)")
    crop_scale: float = Field(3.0, ge=1.0, le=10.0, description="crop side / box side")
    epochs: int = Field(8, ge=1, le=500)
    batch_size: int = Field(128, ge=1, le=4096)
    lr: float = Field(0.01, gt=0.0, le=10.0)
    momentum: float = Field(0.9, ge=0.0, lt=1.0)
    weight_decay: float = Field(0.01, ge=0.0)
    step_size: int = Field(10, ge=1, description="StepLR step, epochs")
    gamma: float = Field(0.5, gt=0.0, le=1.0, description="StepLR factor")
    hflip_p: float = Field(0.5, ge=0.0, le=1.0, description="training-only horizontal flip")
    num_workers: int = Field(0, ge=0, le=64, description="DataLoader workers")

    @model_validator(mode="after")
    def _cross_checks(self) -> Params:
        if self.min_distance >= self.max_distance:
            raise ValueError(
                f"min_distance={self.min_distance} must be < max_distance={self.max_distance}"
            )
        if len(self.split_fractions) != 3 or any(f < 0 for f in self.split_fractions):
            raise ValueError(
                f"split_fractions={self.split_fractions} must be three non-negative numbers "
                "(train, val, test)"
            )
        if abs(sum(self.split_fractions) - 1.0) > 1e-6:
            raise ValueError(f"split_fractions={self.split_fractions} must sum to 1")
        if not self.categories:
            raise ValueError("categories is empty: give at least one nuScenes category name")
        if not self.dataroot:
            raise ValueError(
                "dataroot is required: set it in the profile or pass DATAROOT=/path/to/nuscenes "
                "(the folder that holds samples/, sweeps/ and the version folder)"
            )
        if self.general_min_distance >= self.general_max_distance:
            raise ValueError(
                f"general_min_distance={self.general_min_distance} must be < "
                f"general_max_distance={self.general_max_distance}"
            )
        if self.world_sweep_scenes > self.world_scenes:
            raise ValueError(
                f"world_sweep_scenes={self.world_sweep_scenes} must be <= "
                f"world_scenes={self.world_scenes}"
            )
        return self

    # --- paths ---------------------------------------------------------------------------
    def path(self, value: str) -> Path:
        """Resolve a path parameter against the repository root (absolute paths unchanged)."""
        p = Path(value).expanduser()
        return p if p.is_absolute() else repo_root() / p

    @property
    def run_path(self) -> Path:
        return self.path(self.run_dir)

    @property
    def dataroot_path(self) -> Path:
        assert self.dataroot  # checked by the validator
        return self.path(self.dataroot)


def _format_error(err: ValidationError, source: str) -> str:
    lines = []
    for e in err.errors():
        key = ".".join(str(x) for x in e["loc"]) or "(profile)"
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            allowed = ", ".join(sorted(Params.model_fields))
            lines.append(f"unknown key {key!r}; allowed keys: {allowed}")
        elif e["loc"]:
            lines.append(f"{key}={e.get('input')!r}: {msg}")
        else:
            lines.append(msg)
    return f"{source}: " + "; ".join(lines)


def validate(values: dict[str, Any], source: str = "parameters") -> Params:
    """Validate a (possibly partial) mapping of parameters; missing keys take defaults.

    Raises :class:`ProfileError` naming every bad key and what is allowed.
    """
    try:
        return Params.model_validate(values)
    except ValidationError as err:
        raise ProfileError(_format_error(err, source)) from None


def profile_path(name_or_path: str | Path) -> Path:
    """``"demo"`` -> ``<repo>/params/demo.yaml``; a path to a YAML file is returned as is."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml"):
        return p if p.is_absolute() else Path.cwd() / p
    return repo_root() / "params" / f"{name_or_path}.yaml"


def read_profile(name_or_path: str | Path) -> dict[str, Any]:
    """Read a profile YAML as a plain dict (not yet validated)."""
    p = profile_path(name_or_path)
    if not p.is_file():
        known = ", ".join(sorted(x.stem for x in (repo_root() / "params").glob("*.yaml")))
        raise ProfileError(f"profile {str(name_or_path)!r} not found at {p}; known: {known}")
    data = yaml.safe_load(p.read_text()) or {}
    if not isinstance(data, dict):
        raise ProfileError(f"{p}: a profile must be a mapping of parameter names to values")
    return data


def load_profile(name_or_path: str | Path, **overrides: Any) -> Params:
    """Read and validate a profile, with optional overrides (e.g. ``epochs=2``)."""
    data = read_profile(name_or_path)
    data.update(overrides)
    return validate(data, source=str(profile_path(name_or_path)))


def from_notebook(namespace: dict[str, Any]) -> Params:
    """Validate the parameters a notebook declared (its globals that are Params fields)."""
    values = {k: namespace[k] for k in Params.model_fields if k in namespace}
    return validate(values, source="notebook parameters")


def subset_hash(p: Params, keys: list[str] | tuple[str, ...]) -> str:
    """A short stable hash of the named parameters (for up-to-date checks of a stage)."""
    import hashlib
    import json

    blob = json.dumps({k: getattr(p, k) for k in sorted(keys)}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["epochs=2", "flow_methods=[dis]"]`` -> ``{"epochs": 2, "flow_methods": ["dis"]}``."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ProfileError(f"override {item!r} must look like key=value")
        out[key.strip()] = yaml.safe_load(raw) if raw.strip() else None
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m flowmod.params PROFILE``: validate a profile and print it."""
    import argparse
    import sys

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("profile", help="profile name (params/<name>.yaml) or path")
    args = ap.parse_args(argv)
    try:
        p = load_profile(args.profile)
    except ProfileError as e:
        print(f"ProfileError: {e}", file=sys.stderr)
        return 2
    print(yaml.safe_dump(p.model_dump(), sort_keys=False), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


def describe(p: Params) -> pd.DataFrame:
    """The parameters as a table: name, value, description (for the book)."""
    rows = []
    for name, field in Params.model_fields.items():
        rows.append(
            {"parameter": name, "value": getattr(p, name), "description": field.description or ""}
        )
    return pd.DataFrame(rows)
