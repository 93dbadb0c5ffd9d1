"""Profiles: load and validate the parameters of a run.

A profile (``params/<name>.yaml``) is a flat mapping of parameter names to values. The same
names are the papermill parameters of the notebooks: each notebook declares the subset it uses
in its ``parameters`` cell, and :func:`validate` checks a (partial) mapping before any work.

Errors name the key, the value given and what is allowed, e.g.::

    ProfileError: params/demo.yaml: min_distance=80.0 must be < max_distance=70.0
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterable
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

import pandas as pd
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from flowmod.codedigest import code_id
from flowmod.flowweights import SHIPPED_FASTFLOWNET
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
#: Version of the synthetic world's generator (:mod:`flowmod.world`): bump when it changes
#: what it writes. With the generation parameters it names the folder a world is made in.
GENERATOR_VERSION = 2
#: The module that generates a world (its code, and the code it imports, name the world).
GENERATOR_MODULE = "flowmod.world.dataset"
#: A generated world's table written by the generator (real nuScenes has none).
WORLD_FILE = "synth_world.json"
#: A generated world's manifest, beside its tables (``flowmod.world.source``).
WORLD_MANIFEST = "flowmod.manifest.json"


class ProfileError(ValueError):
    """A profile or a notebook parameter is invalid; the message names the key and the fix."""

    def _render_traceback_(self) -> list[str]:
        """What IPython shows (a notebook's kernel, so papermill too): this one line, not the
        frames through flowmod that raised it; the message says all the user needs."""
        return [f"{type(self).__name__}: {self}"]


def _field(default: Any = ..., *, read_by: tuple[str, ...] = (), role: str = "input",
           methods: tuple[str, ...] = (), file: bool = False, **kw: Any) -> Any:
    """A :class:`Params` field that also declares who reads it (the provenance declaration).

    ``read_by``: the stages whose artefacts depend on the value (their fingerprints include
    it, :mod:`flowmod.dag`); ``methods``: only for the nodes of these flow methods (or
    parts); ``file``: the value is a path whose file content (not its name) enters the
    fingerprint. ``role``:
    ``input`` (the default: read by ``read_by``), ``run`` (how to run: device, workers, force;
    never makes an artefact stale), ``location`` (where data lives: readable by every stage,
    its identity enters through the world's fingerprint) or ``plan`` (which nodes exist:
    ``flow_methods``).
    """
    if role not in ROLES:
        raise ValueError(f"role={role!r}; allowed: {ROLES}")
    extra = {"read_by": list(read_by), "role": role, "methods": list(methods), "file": file}
    if callable(default):
        return Field(default_factory=default, json_schema_extra=extra, **kw)
    return Field(default, json_schema_extra=extra, **kw)


#: For a ``file`` parameter left null: the file its reader loads instead (a network's
#: checkpoint found in the torch hub cache), or None. Registered by the module that does the
#: search (``flowmod.flow.networks``); the found file's content enters fingerprints as a
#: named file's would, so a checkpoint replaced in the cache makes its readers stale.
FILE_DEFAULTS: dict[str, Callable[[], Path | None]] = {}


#: Roles of a parameter (see :func:`_field`).
ROLES = ("input", "run", "location", "plan")

_FLOW = ("flow", "crops")  # crops too: in crops mode it computes the flow itself
_TRAIN = ("train", "xtrain", "wtrain", "etrain")  # chapters 10, 11, 14 train with Table 2 too
#: chapter 13's stages (the levels, the classifiers on degraded flow, their predictions)
_ERRORS = ("elevels", "etrain", "eevaluate")
#: every stage that splits scenes into train, validation and test
_FOLDS = ("select", "general", "wide", "crops", "context", *_TRAIN, "evaluate", "generalise",
          "xevaluate", "wgeneralise", "selfflow", "elevels", "eevaluate")


class Params(BaseModel):
    """Every parameter of the study, with its unit, allowed range and the stages that read it.

    Defaults are the ``demo`` profile's values, so a notebook run without a profile behaves
    like the embedded default. ``read_by`` (see :func:`_field`) is the one declaration of
    which stage depends on which parameter: the fingerprints of :mod:`flowmod.dag` and
    ``runner --status`` both use it, and a stage that reads an undeclared parameter fails.
    """

    model_config = ConfigDict(extra="forbid", strict=False, validate_default=True)

    # --- run ---------------------------------------------------------------------------
    profile: str = _field("demo", role="run",
                          description="profile name; artefacts go to runs/<profile>/")
    seed: int = _field(0, ge=0, read_by=("world", "select", "flowcheck", "flow", "train",
                                "evaluate", "xtrain", "wtrain", "selfflow", "shipped",
                                *_ERRORS),
                       description="master seed for every random choice")
    run_dir: str = _field("runs/demo", role="run",
                          description="stage artefacts (relative to the repo root)")
    device: Literal["auto", "cpu", "cuda"] = _field("auto", role="run",
                                                    description="torch device")
    force: bool = _field(False, role="run",
                         description="recompute stages whose outputs are up to date")

    # --- data --------------------------------------------------------------------------
    dataroot: str | None = _field("data/demo", role="location",
                                  description="nuScenes-format data root")
    version: str = _field("v1.0-synth", role="location",
                          description="table folder under dataroot, e.g. v1.0-mini")
    synthetic: bool = _field(True, role="run",
                             description="build the synthetic world when dataroot is absent")
    world_scenes: int = _field(100, ge=1, le=2000, read_by=("world",),
                               description="synthetic world: number of scenes")
    world_keyframes: int = _field(8, ge=2, le=60, read_by=("world",),
                                  description="keyframes (2 Hz) per scene")
    world_sweep_scenes: int = _field(15, ge=0, read_by=("world",),
                                     description="scenes that also get ~12 Hz sweeps (dealt "
                                                 "over the folds first)")
    world_vehicles: int = _field(28, ge=1, le=200, read_by=("world",),
                                 description="vehicles per scene (mean)")
    world_near_movers: int = _field(3, ge=0, le=20, read_by=("world",),
                                    description="vehicles driving near the ego (in view "
                                                "nearer than 30 m) a scene with sweeps gets "
                                                "besides (the generalisation set's near movers)")

    # --- selection (Table 1) -----------------------------------------------------------
    categories: list[str] = _field(lambda: list(TABLE1_CATEGORIES),
                                   read_by=("select", "general", "wide"),
                                   description="target categories (Table 1)")
    min_distance: float = _field(30.0, ge=0.0, read_by=("select", "flowcheck"),
                                 description="m, nearest target vehicle")
    max_distance: float = _field(70.0, gt=0.0, read_by=("select", "flowcheck"),
                                 description="m, farthest target vehicle")
    distance_mode: Literal["ego", "camera"] = _field(
        "ego", read_by=("select", "general", "wide"),
        description="distance from the ego-pose origin (paper code) or the camera",
    )
    visibility_tokens: list[Literal["1", "2", "3", "4"]] = _field(
        lambda: ["4"], read_by=("select", "general", "wide"),
        description="nuScenes visibility bins ('4' = 80-100 %)",
    )
    exclude_descriptions: list[str] = _field(
        lambda: ["night", "rain", "lightning"], read_by=("select",),
        description="drop scenes with a comma-separated description item equal to one of these",
    )
    split_fractions: list[float] = _field(
        lambda: [0.7, 0.15, 0.15], read_by=("select",),
        description="train, val, test (by scene)",
    )
    missing_images: Literal["error", "skip"] = _field(
        "error", read_by=("select", "general", "wide"),
        description="on missing JPEGs")

    # --- labels ------------------------------------------------------------------------
    speed_threshold: float = _field(2.0, gt=0.0,
                                    read_by=("select", "general", "difficulty", "wide"),
                                    description="m/s; moving if speed >= this")

    # --- generalisation ----------------------------------------------------------------
    general_interval: int = _field(4, ge=1, le=12, read_by=("general", "wide"),
                                   description="camera frames between the pair")
    general_min_distance: float = _field(0.0, ge=0.0, read_by=("general", "wide"),
                                         description="m, near vehicles included")
    general_max_distance: float = _field(70.0, gt=0.0, read_by=("general", "wide"),
                                         description="m, farthest vehicle of Table 4 (the "
                                                     "paper's range)")
    general_beyond_distance: float = _field(
        100.0, gt=0.0, read_by=("general",),
        description="m, vehicles from general_max_distance to this are also selected and "
                    "reported apart from Table 4 (0 = none)")
    general_max_scenes: int = _field(15, ge=0, read_by=("general",),
                                     description="held-out scenes used (0 = none)")
    general_stride: int = _field(2, ge=1, le=12, read_by=("general",),
                                 description="every n-th camera frame of a held-out scene "
                                             "starts a pair (1: every frame, as the paper)")

    # --- optical flow ------------------------------------------------------------------
    flow_methods: list[Literal[FLOW_METHODS]] = _field(  # type: ignore[valid-type]
        lambda: ["gt", "dis", "farneback", "fastflownet"], role="plan",
        description="flow methods; one chain of flow, crops, model and scores each",
    )
    flow_networks: list[Literal["raft", "raft_small", "fastflownet"]] = _field(
        list, role="plan",
        description="networks the runner adds to flow_methods when their weights are present")
    flow_scale: float = _field(0.75, gt=0.0, le=1.0, read_by=(*_FLOW, "selfflow", "shipped"),
                               description="image scale at which flow is computed and stored")
    dis_preset: Literal["ultrafast", "fast", "medium"] = _field(
        "medium", read_by=_FLOW, methods=("dis",), description="OpenCV DIS preset")
    flow_dtype: Literal["float16", "float32"] = _field("float16", read_by=_FLOW,
                                                      description="stored flow dtype")
    raft_weights: str | None = _field(None, read_by=_FLOW, methods=("raft",), file=True,
                                      description="path to RAFT weights (.pth)")
    raft_iters: int = _field(20, ge=1, le=64, read_by=_FLOW, methods=("raft", "raft_small"),
                             description="RAFT flow updates (20 in the original code)")
    raft_small_weights: str | None = _field(None, read_by=_FLOW, methods=("raft_small",),
                                            file=True,
                                            description="path to RAFT-small weights")
    fastflownet_weights: str | None = _field(
        SHIPPED_FASTFLOWNET, read_by=_FLOW, methods=("fastflownet",),
        file=True, description="path to FastFlowNet weights (default: the study's own, "
                               "pretrained on a synthetic world; null: an official "
                               "checkpoint from the torch hub cache)")
    flow_store: Literal["pairs", "crops"] = _field(
        "crops", read_by=_FLOW,
        description="pairs: keep every pair's flow; crops: keep only the objects' crops (the "
                    "crops stage computes the flow) and the flow of a few pairs for figures")
    flow_keep_pairs: int = _field(
        8, ge=1, le=1000, read_by=("flow",),
        description="crops mode: random pairs per part whose flow is kept besides the figures'")
    flowcheck_pairs: int = _field(
        12, ge=1, le=1000, read_by=("flowcheck",),
        description="chapter 03's accuracy table: random pairs of each set on which every "
                    "flow method is measured against the exact flow")
    difficulty_pairs: int = _field(
        240, ge=1, le=100000, read_by=("difficulty",),
        description="chapter 01's difficulty check: at most this many keyframe pairs (a "
                    "fixed draw) on which a naive rule reads the exact flow")
    clip_method: str | None = _field(
        None, read_by=("flow",),
        description="the flow method of chapter 08's clip (crops mode keeps the clip's flow "
                    "for it only); default: the first of flow_methods that is not gt")
    n_jobs: int = _field(2, ge=1, le=64, role="run",
                         description="parallel CPU workers: the world's scenes, the CPU flow "
                                     "methods' pairs, classifiers trained at once (one "
                                     "thread each; the same bytes as one at a time)")
    executor: Literal["local", "ray"] = _field(
        "local", role="run",
        description="where flow is computed: local processes, or a Ray cluster")
    ray_address: str = _field(
        "local", role="run", min_length=1,
        description="executor ray: local (a cluster on this machine), auto (this node's "
                    "cluster) or a head address host:port")

    # --- crops and learning (Table 2) --------------------------------------------------
    crop_size: int = _field(40, ge=16, le=512, read_by=("crops", "context"),
                            description="px, side of the resized crop (224)")
    crop_scale: float = _field(3.0, ge=1.0, le=10.0, read_by=("crops", "context", *_ERRORS),
                               description="crop side / box side")
    epochs: int = _field(8, ge=1, le=500, read_by=_TRAIN, description="training epochs")
    batch_size: int = _field(32, ge=1, le=4096, read_by=_TRAIN,
                            description="Table 2: 128 (the demo: 32)")
    lr: float = _field(0.01, gt=0.0, le=10.0, read_by=_TRAIN, description="SGD learning rate")
    momentum: float = _field(0.9, ge=0.0, lt=1.0, read_by=_TRAIN, description="SGD momentum")
    weight_decay: float = _field(0.01, ge=0.0, read_by=_TRAIN, description="SGD weight decay")
    step_size: int = _field(3, ge=1, read_by=_TRAIN,
                           description="StepLR step, epochs (Table 2: 10; the demo: 3)")
    gamma: float = _field(0.3, gt=0.0, le=1.0, read_by=_TRAIN,
                          description="StepLR factor (Table 2: 0.5; the demo: 0.3)")
    hflip_p: float = _field(0.5, ge=0.0, le=1.0, read_by=_TRAIN,
                            description="training-only horizontal flip")
    model_width: int = _field(32, ge=4, le=256, read_by=_TRAIN,
                              description="channels of the ResNet18's first stage (64: the "
                                          "paper's; the demo's 32 trains ~4x faster; stages "
                                          "have 1, 2, 4, 8 x this)")
    input_scaling: Literal["raw", "centred", "clipped", "log", "centred-log"] = _field(
        "log", read_by=_TRAIN,
        description="how the classifier scales its flow channels (raw: the paper's px; "
                    "centred: each crop's median subtracted; clipped: to +-50 px; log: "
                    "sign(x) log(1+|x|); centred-log); chosen on the validation folds")
    seeds: int = _field(3, ge=1, le=20, role="plan",
                        description="training runs per flow method and fold (the paper's "
                                    "single split: seeds seed .. seed+seeds-1; fold k: seed "
                                    "seed+k+100j for j < seeds); every interval resamples "
                                    "them with the scenes")
    extension_seeds: int = _field(
        1, ge=1, le=20, role="plan",
        description="training seeds per fold of the chains beyond the paper (chapters 10 "
                    "and 11); their intervals resample the Table 3 chains' seeds and "
                    "these")
    raw_input_methods: list[str] | None = _field(
        None, role="plan",
        description="Table 3 beside the chosen recipe: flow methods whose classifier is also "
                    "trained on the paper's raw input (px; one seed a fold, seed 0's), "
                    "scored on the same objects and compared paired; default: the exact "
                    "flow and the first estimate, none when input_scaling is raw")
    folds: int = _field(
        3, ge=1, le=10, read_by=_FOLDS,
        description="cross-validation over scenes: each fold's models train on the other "
                    "folds and are scored on its own, so every scene is a test scene; 1 = "
                    "the paper's single train/val/test split")
    amp: Literal["off", "bf16", "fp16"] = _field(
        "off", read_by=_TRAIN,
        description="mixed precision for training and every prediction of its models")
    num_workers: int = _field(0, ge=0, le=64, role="run", description="DataLoader workers")

    # --- beyond the paper (chapter 10) ---------------------------------------------------
    extension_inputs: list[Literal["residual", "residual-deployed", "flow+static", "images",
                                   "images+flow"]] = (
        _field(lambda: ["residual", "residual-deployed", "images", "images+flow"], role="plan",
               description="chapter 10: classifier inputs besides the raw flow, each trained "
                           "with Table 2 (residual = flow - static-world flow, annotated-box "
                           "depth; residual-deployed: depth from the 2D box's ground contact; "
                           "flow+static; images = the two image crops; images+flow)"))
    extension_methods: list[str] | None = _field(
        None, role="plan",
        description="chapter 10: the flow methods its flow inputs are built on; default: the "
                    "first method that is not the exact flow (a flow a car could compute)")
    extension_build: bool = _field(
        True, role="run",
        description="chapters 10 and 11 train their stale models; off: they show the ones "
                    "built (make extensions: the full matrix of inputs and methods)")

    # --- beyond the paper (chapter 11): trained on all distances --------------------------
    wide_methods: list[str] | None = _field(
        None, role="plan",
        description="chapter 11: flow methods whose classifier is also trained on every "
                    "distance from general_min_distance to general_max_distance and on "
                    "non-keyframe pairs of the training scenes; default: extension_methods; "
                    "[] = off")
    wide_sweep_stride: int = _field(
        1, ge=0, le=100, read_by=("wide",),
        description="chapter 11: every k-th camera frame of a training scene with sweeps "
                    "starts a non-keyframe pair (general_interval frames apart); 0 = none")

    # --- beyond the paper (chapter 12): FastFlowNet trained here ---------------------------
    selfflow_modes: list[Literal["photometric", "supervised", "finetune"]] = _field(
        lambda: ["photometric", "supervised", "finetune"], role="plan",
        description="chapter 12: how FastFlowNet is trained in the book: photometric "
                    "(self-supervised, from scratch), supervised by the exact flow (generated "
                    "world only) and/or finetune (photometric, from selfflow_init, on the "
                    "test scenes' frames); [] = off")
    selfflow_init: str = _field(
        SHIPPED_FASTFLOWNET, read_by=("selfflow",), methods=("finetune",),
        file=True, description="chapter 12: the FastFlowNet weights the finetune mode starts "
                               "from (default: the shipped ones)")
    selfflow_build: bool = _field(
        False, role="run",
        description="chapter 12 trains its stale networks; off: it shows the ones built "
                    "(make selfflow turns it on)")
    selfflow_iters: int = _field(300, ge=1, le=10_000_000, read_by=("selfflow",),
                                 description="chapter 12: training steps (the CPU budget)")
    selfflow_batch: int = _field(4, ge=1, le=256, read_by=("selfflow",),
                                 description="chapter 12: pairs per step")
    selfflow_lr: float = _field(3e-4, gt=0.0, le=1.0, read_by=("selfflow",),
                                description="chapter 12: Adam learning rate")
    selfflow_crop: list[int] = _field(
        lambda: [256, 448], read_by=("selfflow",), min_length=2, max_length=2,
        description="chapter 12: training input size (h, w) px at flow_scale, multiples of "
                    "64 (selfflow_window)")
    selfflow_window: Literal["frame", "crop"] = _field(
        "frame", read_by=("selfflow",),
        description="chapter 12: the network's training input: whole frames resized to "
                    "selfflow_crop (frame) or random windows of that size (crop)")
    selfflow_smooth: float = _field(2.0, ge=0.0, le=100.0, read_by=("selfflow",),
                                    description="chapter 12: weight of the second-order "
                                                "smoothness (photometric, finetune)")
    selfflow_warmup: int = _field(100, ge=0, le=10_000_000, read_by=("selfflow",),
                                  methods=("photometric",),
                                  description="chapter 12: first steps of the photometric "
                                              "mode with the L1 + SSIM distance, then census")
    selfflow_pairs: int = _field(256, ge=1, le=10_000_000, read_by=("selfflow",),
                                 description="chapter 12: training pairs (keyframe pairs of "
                                             "the train and val scenes, drawn with the seed)")
    shipped_weights: str = _field(
        SHIPPED_FASTFLOWNET, read_by=("shipped",), file=True,
        description="chapter 12: the FastFlowNet weights it scores on held-out pairs of this "
                    "book's world (default: the shipped ones)")
    selfflow_eval_pairs: int = _field(16, ge=1, le=10_000, read_by=("selfflow", "shipped"),
                                      description="chapter 12: held-out pairs (test scenes) "
                                                  "of the end-point error")
    selfflow_eval_every: int = _field(100, ge=0, le=10_000_000, read_by=("selfflow",),
                                      description="chapter 12: steps between held-out "
                                                  "evaluations (0: at the end only)")

    # --- beyond the paper (chapter 13): which flow errors decide motion detection -------------
    error_kinds: list[Literal["noise", "resolution", "pull", "scale", "outliers", "ring"]] = (
        _field(lambda: ["noise", "resolution", "pull", "scale", "outliers", "ring"],
               role="plan",
               description="chapter 13: the kinds of error put on the exact flow, one at a "
                           "time, each training the classifier anew ([] = off; pull needs "
                           "chapter 10's static-world flow, built for it)"))
    error_targets: list[float] = _field(
        lambda: [0.5, 1.0, 2.0], read_by=("elevels",), min_length=1,
        description="chapter 13: px, the mean end-point errors every kind is set to reach "
                    "(in the box; the ring kind around it), so the kinds meet at the same "
                    "error")
    error_calibration: int = _field(
        400, ge=10, le=1_000_000, read_by=("elevels",),
        description="chapter 13: objects (drawn with the seed) on which each kind's level "
                    "is matched to the targets")
    error_folds: int = _field(
        1, ge=1, le=10, role="plan",
        description="chapter 13: the first k folds train a classifier per arm (one seed a "
                    "fold); their test scenes are scored")
    error_width: int | None = _field(
        16, ge=4, le=256, read_by=("etrain",),
        description="chapter 13: the classifiers' width (None: model_width); the "
                    "experiment's exact-flow arm is trained with it too")

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
        if 0 < self.general_beyond_distance < self.general_max_distance:
            raise ValueError(
                f"general_beyond_distance={self.general_beyond_distance} must be 0 or >= "
                f"general_max_distance={self.general_max_distance}"
            )
        if self.clip_method is None:
            self.clip_method = next((m for m in self.flow_methods if m != "gt"),
                                    self.flow_methods[0] if self.flow_methods else None)
        elif self.clip_method not in self.flow_methods:
            raise ValueError(
                f"clip_method={self.clip_method!r} is not one of flow_methods="
                f"{self.flow_methods}: name one of them, or leave clip_method unset (the first "
                "method that is not gt)"
            )
        self._check_raw_input_methods()
        if len(set(self.extension_inputs)) != len(self.extension_inputs):
            raise ValueError(f"extension_inputs={self.extension_inputs} lists an input twice")
        if self.extension_methods is None:
            self.extension_methods = ([m for m in self.flow_methods if m != "gt"]
                                      or list(self.flow_methods))[:1]
        stray = [m for m in self.extension_methods if m not in self.flow_methods]
        if self.extension_inputs and (stray or not self.extension_methods):
            raise ValueError(
                f"extension_methods={self.extension_methods} must be a non-empty subset of "
                f"flow_methods={self.flow_methods} (chapter 10 builds on their crops)")
        if self.wide_methods is None:
            self.wide_methods = list(self.extension_methods)
        self._check_subset("wide_methods", "chapter 11 trains on their flow")
        if any(c <= 0 or c % 64 for c in self.selfflow_crop):
            raise ValueError(f"selfflow_crop={self.selfflow_crop}: both sides must be positive "
                             "multiples of 64 (FastFlowNet's pyramid)")
        if self.error_folds > self.folds:
            raise ValueError(f"error_folds={self.error_folds} must be <= folds={self.folds}")
        if any(t <= 0 for t in self.error_targets):
            raise ValueError(f"error_targets={self.error_targets}: every target must be > 0 px")
        if self.world_sweep_scenes > self.world_scenes:
            raise ValueError(
                f"world_sweep_scenes={self.world_sweep_scenes} must be <= "
                f"world_scenes={self.world_scenes}"
            )
        return self

    def _check_subset(self, name: str, why: str) -> None:
        """Refuse a list of flow methods (``name``) that names one not in flow_methods."""
        values = getattr(self, name)
        stray = [m for m in values if m not in self.flow_methods]
        if stray:
            raise ValueError(f"{name}={values}: {stray} not in flow_methods={self.flow_methods} "
                             f"({why}); name some of them or [] for none")

    def _check_raw_input_methods(self) -> None:
        """Resolve ``raw_input_methods``'s default and refuse what would train nothing new."""
        if self.raw_input_methods is None:
            first = [m for m in self.flow_methods if m != "gt"][:1]
            self.raw_input_methods = ([] if self.input_scaling == "raw" else
                                      [m for m in self.flow_methods if m == "gt"] + first)
        self._check_subset("raw_input_methods", "Table 3 trains on their flow")
        if self.raw_input_methods and self.input_scaling == "raw":
            raise ValueError(
                f"raw_input_methods={self.raw_input_methods} trains the paper's raw input "
                "beside input_scaling, which is raw already (the same models twice): set "
                "raw_input_methods=[]")

    # --- paths ---------------------------------------------------------------------------
    def path(self, value: str) -> Path:
        """Resolve a path parameter against the repository root (absolute paths unchanged)."""
        p = Path(value).expanduser()
        return p if p.is_absolute() else repo_root() / p

    @property
    def run_path(self) -> Path:
        return self.path(self.run_dir)

    def world_generation(self) -> dict[str, Any]:
        """What a world generated from these parameters is made from: the generator's
        version, its code (:func:`flowmod.codedigest.code_id` of the generator, so an edit
        of what it draws names another world, generated beside the old one) and the values
        of the parameters the world stage reads."""
        out: dict[str, Any] = {"generator_version": GENERATOR_VERSION,
                               "generator_code": code_id(GENERATOR_MODULE)}
        out.update({n: getattr(self, n) for n, f in Params.model_fields.items()
                    if "world" in f.json_schema_extra["read_by"]})  # type: ignore[index]
        return out

    @property
    def world_id(self) -> str:
        """16 hex digits naming the world generated from these parameters."""
        blob = json.dumps(self.world_generation(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    @property
    def dataroot_path(self) -> Path:
        """The nuScenes root the stages read. ``dataroot`` itself for real data (or with
        ``synthetic: false``), for a world's own folder (``.../worlds/<world_id>``, which
        the runner hands the notebooks) and for a world generated at the dataroot with these
        parameters; otherwise, for a world generated from the profile, its own folder
        ``<dataroot>/worlds/<world_id>``, so that the worlds of other parameters, and the
        runs reading them, never overwrite each other."""
        assert self.dataroot  # checked by the validator
        root = self.path(self.dataroot)
        vdir = root / self.version
        if not self.synthetic or root.parent.name == "worlds":
            return root
        if (vdir / "scene.json").is_file() and (
                not (vdir / WORLD_FILE).is_file()
                or _generation_at(vdir) in (None, self.world_generation())):
            return root  # real data, or a world made here (for these parameters)
        return root / "worlds" / self.world_id


def _generation_at(vdir: Path) -> dict[str, Any] | None:
    """What the world at ``vdir`` was generated from, as its manifest records it
    (:meth:`Params.world_generation`); None without a manifest."""
    m = vdir / WORLD_MANIFEST
    try:
        st = m.stat()
    except OSError:
        return None
    return _read_generation(str(m), st.st_mtime_ns, st.st_size)


@lru_cache(maxsize=16)
def _read_generation(path: str, mtime_ns: int, size: int) -> dict[str, Any] | None:
    try:
        rec = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    if "generation" in rec:
        return rec["generation"]
    old = rec.get("params")  # a manifest of an earlier layout: generated in place
    return {"generator_version": rec.get("version"), **old} if isinstance(old, dict) else None


def _format_error(err: ValidationError, source: str, overridden: Iterable[str] = ()) -> str:
    """One line naming every bad key; a key given with ``--set`` (``overridden``) is blamed
    on that option, not on the profile file (``source``)."""
    by_set, by_file = [], []
    for e in err.errors():
        key = ".".join(str(x) for x in e["loc"]) or "(profile)"
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            allowed = ", ".join(sorted(Params.model_fields))
            line = f"unknown key {key!r}; allowed keys: {allowed}"
        elif e["loc"]:
            line = f"{key}={e.get('input')!r}: {msg}"
        else:
            line = msg
        (by_set if e["loc"] and str(e["loc"][0]) in set(overridden) else by_file).append(line)
    parts = [f"--set {line}" for line in by_set]
    if by_file:
        parts.append(f"{source}: " + "; ".join(by_file))
    return "; ".join(parts)


def validate(values: dict[str, Any], source: str = "parameters",
             overridden: Iterable[str] = ()) -> Params:
    """Validate a (possibly partial) mapping of parameters; missing keys take defaults.

    Raises :class:`ProfileError` naming every bad key and what is allowed, and whether it
    came from the profile (``source``) or from an override (``overridden``: their keys).
    """
    try:
        return Params.model_validate(values)
    except ValidationError as err:
        raise ProfileError(_format_error(err, source, overridden)) from None


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
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ProfileError(f"{p}: not valid YAML{where} ({getattr(e, 'problem', None) or e}); "
                           "fix the file (a profile is a flat mapping key: value)") from None
    if not isinstance(data, dict):
        raise ProfileError(f"{p}: a profile must be a mapping of parameter names to values")
    return data


def load_profile(name_or_path: str | Path, **overrides: Any) -> Params:
    """Read and validate a profile, with optional overrides (e.g. ``epochs=2``)."""
    data = read_profile(name_or_path)
    data.update(overrides)
    return validate(data, source=str(profile_path(name_or_path)), overridden=overrides)


def from_notebook(namespace: dict[str, Any]) -> Params:
    """Validate the parameters a notebook declared (its globals that are Params fields)."""
    values = {k: namespace[k] for k in Params.model_fields if k in namespace}
    return validate(values, source="notebook parameters (papermill -p / -f, or the "
                    "parameters cell)")


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["epochs=2", "flow_methods=[dis]"]`` -> ``{"epochs": 2, "flow_methods": ["dis"]}``."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ProfileError(f"override {item!r} must look like key=value")
        try:
            out[key.strip()] = yaml.safe_load(raw) if raw.strip() else None
        except yaml.YAMLError as e:
            raise ProfileError(
                f"--set {item!r}: {raw!r} is not a YAML value ({getattr(e, 'problem', None) or e}); "
                "e.g. key=2, key=[dis,gt] or key='text'") from None
    return out


def readers_text(name: str) -> str:
    """Who reads a parameter, in words: the stages of its ``read_by`` declaration, or its
    role (run settings, the data's location, the plan of which nodes exist)."""
    meta = Params.model_fields[name].json_schema_extra
    roles = {"run": "none (how to run)", "location": "none (where the data is)",
             "plan": "which chains exist"}
    text = ", ".join(meta["read_by"]) or roles.get(meta["role"], "")
    return text + (f" (methods {', '.join(meta['methods'])})" if meta["methods"] else "")


def describe(p: Params) -> pd.DataFrame:
    """The parameters as a table: name, value, description and the stages that read it."""
    rows = []
    for name, field in Params.model_fields.items():
        rows.append({"parameter": name, "value": str(getattr(p, name)),
                     "description": field.description or "", "read by": readers_text(name)})
    return pd.DataFrame(rows)


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
