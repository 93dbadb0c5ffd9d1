"""FastFlowNet pretrained here, supervised, on a synthetic world of its own.

The paper's flow networks were trained supervised on synthetic data (FlyingChairs, Things)
before they met real frames. No such weights can be had offline, so this module makes the
study's own: FastFlowNet (:class:`flowmod.flow.architectures.FastFlowNet`) trained from scratch on
the exact flow of a *pretraining world*, a generated world of its own seed and size that
shares no scene with the book's worlds (the book's every scene can then be a test scene).

The recipe (:class:`Recipe`, recorded in the manifest) in short: frame pairs 1 to
``max_gap`` camera frames apart (12 Hz sweeps and keyframes) of the world's training
scenes, read at ``scale`` (the book's ``flow_scale``); random ``crop`` windows, a random
horizontal flip; the multi-scale end-point error of every decoder level against the exact
flow over its valid pixels (:func:`pyramid_loss`); Adam with the rate halved at fixed
steps (so weights stopped at any step are what the same recipe gives at that step);
gradient norm clipped. Every ``eval_every`` steps: end-point error on keyframe pairs of the
validation scenes, overall and inside the far (Table-1, 30-70 m) vehicles' boxes, beside
DIS. The batch of step ``i`` is drawn with ``(seed, i)``; a killed run resumes from
``last.pt``.

The shipped weights come from :data:`SCHEDULE`: phases of such recipes, each later phase
starting from the weights its predecessor ended with (later phases place most or all windows
on, and weight the loss in, the boxes of far agents, :func:`flowmod.world.agent_boxes`, and
the last ones train only on pairs ``min_gap`` or more frames apart; a phase may score its
finest level per pixel on the upsampled flow, ``full_res``, pass on a moving average of its
weights, ``ema``, and start from its predecessor's weights rounded to float16 as published,
``init_float16``, and read the frames at a scale of its own, ``scale``: the published
weights are scored, and meant to run, at the last phase's). Phase ``k`` trains in
``<work>/phase<k>/``. ``--from-shipped`` takes the
phases the published weights hold as done (their manifest's schedule, sha256 and world must
match) and trains the later ones from that file: with ``init_float16`` on the first of them,
bit-identical to the whole schedule from scratch.

``python -m flowmod.flow.pretrain`` (``make flownet``) generates the world, trains, and
publishes ``weights/fastflownet_synth/``: ``weights.pt`` (float16 state_dict, an ordinary
``fastflownet_weights`` file) and ``manifest.json`` (recipe, world fingerprint, steps, the
validation curve, the final validation errors of the published float16 weights, sha256,
where and how long it ran).
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F
from torch import Tensor
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from flowmod.artefacts import atomic_path, file_digest, fingerprint, write_json
from flowmod.environment import simd_path, torch_threads
from flowmod.flow.architectures import FFN_DIV_FLOW, FastFlowNet, fastflownet_inputs
from flowmod.flow.estimators import GTFlow
from flowmod.flow.registry import read_image, resize_flow
from flowmod.flow.selftrain import HeldOut, baselines, held_out, score_model
from flowmod.flowweights import (
    MANIFEST_NAME,
    SHIPPED_FASTFLOWNET_DIR,
    WEIGHTS_NAME,
)
from flowmod.params import Params, load_profile, validate
from flowmod.paths import repo_root
from flowmod.progress import bar
from flowmod.select import (
    camera_frames,
    filter_scenes,
    keyframe_set,
    open_nuscenes,
    scene_table,
)
from flowmod.world import agent_boxes, world_fingerprint
from flowmod.world import ensure_world as ensure_world_data

#: Where the shipped weights live (relative to the repository root).
WEIGHTS_DIR = SHIPPED_FASTFLOWNET_DIR
#: Decoder levels of :meth:`FastFlowNet.levels`, finest first.
LEVELS = (2, 3, 4, 5, 6)
#: Steps between resumable checkpoints.
CHECKPOINT_EVERY = 100


class PretrainError(ValueError):
    """Bad input to the pretraining; the message names the thing and the fix."""


@dataclass(frozen=True)
class Recipe:
    """Everything the shipped weights depend on besides the code."""

    world_seed: int = 1000
    world_scenes: int = 32
    world_keyframes: int = 10
    world_vehicles: int = 28
    #: every ``val_every``-th scene (sorted by name) is a validation scene
    val_every: int = 4
    scale: float = 0.5
    max_gap: int = 6
    #: the phase trains on the pairs at least this many camera frames apart (keyframe pairs,
    #: what the book scores, are 6 apart)
    min_gap: int = 1
    #: a training pair starts every ``start_stride``-th camera frame
    start_stride: int = 4
    batch: int = 4
    crop: tuple[int, int] = (256, 448)
    lr: float = 3e-4
    #: steps at which the rate is multiplied by ``gamma`` (sized so that the whole schedule,
    #: :attr:`steps`, fits one working session on 2 CPU cores, ~1.1 s a step)
    milestones: tuple[int, ...] = (2_000, 3_000, 3_500)
    #: the schedule's length: ``make flownet`` trains to it
    steps: int = 4_000
    gamma: float = 0.5
    clip: float = 1.0
    #: loss weights of levels 2..6 (means over valid pixels, px of the input)
    level_weights: tuple[float, ...] = (1.0, 0.5, 0.25, 0.25, 0.25)
    flip_p: float = 0.5
    eval_every: int = 1000
    eval_pairs: int = 24
    seed: int = 0
    threads: int = 2
    #: share of windows placed so that a box of :attr:`focus_depth` lies inside (0: none)
    focus_p: float = 0.0
    #: extra loss weight of the pixels inside those boxes (0: every valid pixel alike)
    box_weight: float = 0.0
    #: agents whose median depth (m) is in this range make the boxes (the far vehicles')
    focus_depth: tuple[float, float] = (20.0, 80.0)
    #: the finest level's loss on its flow upsampled (bilinearly, as at inference) to the
    #: window's pixels against the exact flow of each pixel, instead of on cell means
    full_res: bool = False
    #: decay of an exponential moving average of the weights, updated every step; the
    #: phase's result (validated, passed on, published) is the average (0: the weights)
    ema: float = 0.0
    #: the phase starts from its predecessor's weights rounded to float16, as published
    init_float16: bool = False
    #: weight of :func:`box_mean_loss`, the error of each far box's mean flow (0: none)
    box_mean_weight: float = 0.0

    def world_params(self, dataroot: str) -> Any:
        """The :class:`flowmod.params.Params` of the pretraining world (sweeps everywhere)."""
        return validate({
            "profile": "pretrain", "dataroot": dataroot, "seed": self.world_seed,
            "world_scenes": self.world_scenes, "world_keyframes": self.world_keyframes,
            "world_sweep_scenes": self.world_scenes, "world_vehicles": self.world_vehicles,
            "flow_scale": self.scale}, source="pretraining recipe")


#: The shipped weights' schedule. Phase 1 learns flow from scratch on random windows; every
#: later phase starts from its predecessor's weights (a fresh optimiser) and turns to what
#: the study measures: windows that hold a far (20-80 m) agent's box and those boxes' pixels
#: weighted up in the loss (phase 2: 3 windows in 4, x21; phases 3-5: every window, x41);
#: phases 4 and 5 on the pairs as far apart as keyframes (4-6, then 6 frames), at lower rates;
#: phase 6 (pairs 4-6 apart) from the published float16 file, its finest level scored per
#: pixel after upsampling, passing on a moving average of its weights; phase 7 the same at
#: half the rate (phase 6's validation error still fell at every evaluation); phase 8 the
#: same on frames read at 0.75 (the book's ``flow_scale`` since; at 0.5 a far vehicle is a
#: handful of the network's quarter-resolution cells, and phase 7 had stopped improving).
SCHEDULE: tuple[Recipe, ...] = (
    Recipe(),
    Recipe(seed=1, steps=5_000, lr=2e-4, milestones=(3_000, 4_000, 4_500), eval_every=500,
           focus_p=0.75, box_weight=20.0),
    Recipe(seed=2, steps=4_000, lr=2e-4, milestones=(2_500, 3_250, 3_750), eval_every=500,
           focus_p=1.0, box_weight=40.0),
    Recipe(seed=3, steps=4_000, lr=1e-4, milestones=(2_000, 3_000, 3_500), eval_every=500,
           focus_p=1.0, box_weight=40.0, min_gap=4),
    Recipe(seed=4, steps=4_000, lr=5e-5, milestones=(2_000, 3_000, 3_500), eval_every=500,
           focus_p=1.0, box_weight=40.0, min_gap=6),
    Recipe(seed=5, steps=4_000, lr=1e-4, milestones=(2_000, 3_000, 3_500), eval_every=500,
           focus_p=1.0, box_weight=40.0, min_gap=4, full_res=True, ema=0.999,
           init_float16=True),
    Recipe(seed=6, steps=4_000, lr=5e-5, milestones=(2_000, 3_000, 3_500), eval_every=500,
           focus_p=1.0, box_weight=40.0, min_gap=4, full_res=True, ema=0.999,
           init_float16=True),
    Recipe(seed=7, steps=3_000, lr=1e-4, milestones=(1_500, 2_250, 2_750), eval_every=500,
           focus_p=1.0, box_weight=40.0, min_gap=4, full_res=True, ema=0.999,
           init_float16=True, scale=0.75),
    Recipe(seed=8, steps=4_000, lr=1e-4, milestones=(2_000, 3_000, 3_500), eval_every=500,
           focus_p=1.0, box_weight=40.0, min_gap=4, full_res=True, ema=0.999,
           init_float16=True, scale=0.75),
)


# --- the loss (a pure function of tensors) ------------------------------------------------------

def level_target(gt: Tensor, valid: Tensor, level: int) -> tuple[Tensor, Tensor]:
    """The exact flow (B, 2, H, W) px and its valid mask (B, 1, H, W) at decoder ``level``
    (H / 2^level): the mean over each cell's valid pixels; a cell is valid where more than
    half of its pixels are."""
    k = 2 ** level
    v = valid.float()
    share = F.avg_pool2d(v, k, k)
    flow = F.avg_pool2d(gt * v, k, k) / share.clamp(min=1e-6)
    return flow, (share > 0.5).float()


def level_error(flow: Tensor, gt: Tensor, valid: Tensor, level: int, full_res: bool
                ) -> tuple[Tensor, Tensor, int]:
    """End-point error (px of the input) of decoder output ``flow`` (units px / 20) at
    ``level`` against the exact flow ``gt`` (B, 2, H, W) px: per cell of the level (against
    :func:`level_target`), or with ``full_res`` per pixel of the flow upsampled bilinearly to
    (H, W). Returns (error, valid mask, cell side px), each (B, 1, ., .)."""
    if full_res:
        up = F.interpolate(flow, size=gt.shape[-2:], mode="bilinear", align_corners=False)
        target, ok, side = gt, valid.float(), 1
    else:
        (target, ok), up, side = level_target(gt, valid, level), flow, 2 ** level
    err = torch.sqrt(((FFN_DIV_FLOW * up - target) ** 2).sum(1, keepdim=True) + 1e-6)
    return err, ok, side


def pyramid_loss(levels: Sequence[Tensor], gt: Tensor, valid: Tensor,
                 weights: Sequence[float], pixel_weight: Tensor | None = None,
                 full_res: bool = False) -> tuple[Tensor, dict[str, float]]:
    """Weighted sum over decoder levels (finest first, units px / 20) of the mean end-point
    error, px of the input, over valid cells (with ``full_res``, the finest level's over
    valid pixels, :func:`level_error`); with ``pixel_weight`` (B, 1, H, W) a weighted mean
    (each cell weighted by its pixels' mean weight). Returns (loss, {"epe2": the finest
    level's unweighted EPE})."""
    loss, parts = gt.new_zeros(()), {}
    for lvl, flow, w in zip(LEVELS, levels, weights, strict=True):
        err, ok, side = level_error(flow, gt, valid, lvl, full_res and lvl == LEVELS[0])
        cell = ok if pixel_weight is None else ok * F.avg_pool2d(pixel_weight, side)
        loss = loss + w * (err * cell).sum() / cell.sum().clamp(min=1e-6)
        if lvl == LEVELS[0]:
            parts["epe2"] = float((err * ok).sum().detach() / ok.sum().clamp(min=1.0))
    return loss, parts


def box_mean_loss(flow: Tensor, gt: Tensor, valid: Tensor, box_id: Tensor) -> Tensor:
    """The mean over the boxes in ``box_id`` (B, 1, H, W) int64, 0 outside any box, k > 0
    inside the window's k-th) of the length (px) of the box's mean error: ``flow`` (B, 2,
    H, W) px against ``gt`` averaged over the box's ``valid`` pixels (what
    :func:`flowmod.flow.metrics.box_bias` measures). Zero without a box."""
    B, _, H, W = gt.shape
    k = int(box_id.max()) + 1
    slot = (box_id + k * torch.arange(B, device=gt.device).view(B, 1, 1, 1)).view(-1)
    keep = valid.view(-1) > 0
    err = (flow - gt).permute(0, 2, 3, 1).reshape(-1, 2)[keep]
    sums = gt.new_zeros(B * k, 2).index_add(0, slot[keep], err)
    count = gt.new_zeros(B * k).index_add(0, slot[keep], gt.new_ones(int(keep.sum())))
    used = (count > 0) & (torch.arange(B * k, device=gt.device) % k > 0)
    if not bool(used.any()):
        return gt.new_zeros(())
    mean = sums[used] / count[used, None]
    return torch.sqrt((mean ** 2).sum(1) + 1e-6).mean()


# --- the pretraining world ------------------------------------------------------------------------

def ensure_world(recipe: Recipe, dataroot: Path, progress: bool = True) -> tuple[str, Path]:
    """Generate the pretraining world under ``dataroot`` unless it is there; its fingerprint
    (the tables' content) and its root (a generated world lives in ``worlds/<id>/`` of the
    dataroot)."""
    p = recipe.world_params(str(dataroot))
    root = Path(ensure_world_data(p, progress=progress))
    files = sorted(f for f in (root / p.version).glob("*.json")
                   if f.name != "flowmod.manifest.json")
    if not files:
        raise PretrainError(f"no tables in {root / p.version}: delete {root} and rerun")
    return fingerprint([(f.name, file_digest(f)) for f in files], n=64), root


def scene_frames(dataroot: Path, version: str) -> dict[str, list[dict]]:
    """``{scene name: its CAM_FRONT sample_data records in time order}``."""
    nusc = open_nuscenes(dataroot, version)
    return {sc["name"]: camera_frames(nusc, sc["token"], keyframes_only=False)
            for sc in sorted(nusc.scene, key=lambda s: s["name"])}


def scene_split(scenes: Sequence[str], val_every: int) -> dict[str, str]:
    """``train`` or ``val`` per scene name: every ``val_every``-th (sorted) is validation."""
    return {s: "val" if k % val_every == val_every - 1 else "train"
            for k, s in enumerate(sorted(scenes))}


def training_pairs(frames: dict[str, list[dict]], split: dict[str, str], max_gap: int,
                   stride: int) -> pd.DataFrame:
    """Pairs of the training scenes: from every ``stride``-th frame, the frames 1 ..
    ``max_gap`` later. Columns scene, gap, sd_token_1/2, path_1/2."""
    rows = []
    for scene, fr in frames.items():
        if split[scene] != "train":
            continue
        for i in range(0, len(fr), stride):
            for gap in range(1, max_gap + 1):
                if i + gap < len(fr):
                    a, b = fr[i], fr[i + gap]
                    rows.append({"scene": scene, "gap": gap, "sd_token_1": a["token"],
                                 "sd_token_2": b["token"], "path_1": a["filename"],
                                 "path_2": b["filename"]})
    return pd.DataFrame(rows)


def validation_set(recipe: Recipe, dataroot: Path, split: dict[str, str]) -> HeldOut:
    """``eval_pairs`` keyframe pairs of the validation scenes holding far vehicles (Table 1,
    30-70 m, the book's selection rules), drawn with the seed, with their exact flow."""
    p = recipe.world_params(str(dataroot))
    nusc = open_nuscenes(dataroot, p.version)
    scenes = filter_scenes(scene_table(nusc), p.exclude_descriptions)
    scenes = scenes[(scenes["excluded_by"] == "") & (scenes["scene"].map(split) == "val")]
    pairs, objects = keyframe_set(nusc, scenes.assign(split="val"), p, progress=False)
    pick = np.random.default_rng([recipe.seed, 1]).permutation(len(pairs))[:recipe.eval_pairs]
    pairs = pairs.iloc[np.sort(pick)].reset_index(drop=True)
    return held_out(pairs, objects, dataroot, p.version, synthetic=True)


# --- data -------------------------------------------------------------------------------------------

@dataclass
class PairCache:
    """Training pairs read at the recipe's scale, decoded once and kept as ``.npy`` in
    ``folder/scale-<scale>``: images (h, w, 3) uint8 BGR, exact flow (h, w, 2) float16 px,
    valid (h, w)."""

    pairs: pd.DataFrame
    dataroot: Path
    version: str
    scale: float
    folder: Path
    focus_depth: tuple[float, float] = Recipe.focus_depth
    _gt: GTFlow | None = field(default=None, repr=False)

    def _at_scale(self) -> Path:
        """Where the files at :attr:`scale` live (one folder per scale)."""
        return self.folder / f"scale-{self.scale:g}"

    def _image(self, rel: str) -> np.ndarray:
        f = self._at_scale() / "images" / (Path(rel).stem + ".npy")
        if f.is_file():
            return np.load(f)
        img = read_image(self.dataroot / rel)
        h, w = (round(s * self.scale) for s in img.shape[:2])
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        f.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(f) as tmp:
            np.save(tmp, img)
        return img

    def _flow(self, i: int, size: tuple[int, int]) -> dict[str, np.ndarray]:
        r = self.pairs.iloc[i]
        f = self._at_scale() / "flow" / f"{r.sd_token_1}_{r.sd_token_2}_{self._depth_key()}.npz"
        if f.is_file():
            z = np.load(f)
            return {"flow": z["flow"].astype(np.float32), "valid": z["valid"],
                    "boxes": z["boxes"]}
        self._gt = self._gt or GTFlow(self.dataroot, self.version)
        flow, valid = self._gt.estimate_tokens(r.sd_token_1, r.sd_token_2)
        small = resize_flow(flow, size).astype(np.float16)
        vsmall = cv2.resize(valid.astype(np.uint8), size[::-1],
                            interpolation=cv2.INTER_NEAREST).astype(bool)
        boxes = agent_boxes(self.dataroot, self.version, r.sd_token_1,
                            *self.focus_depth) * np.float32(self.scale)
        f.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(f) as tmp:
            np.savez(tmp, flow=small, valid=vsmall, boxes=boxes)
        return {"flow": small.astype(np.float32), "valid": vsmall, "boxes": boxes}

    def _depth_key(self) -> str:
        return "{:g}-{:g}m".format(*self.focus_depth)

    def load(self, i: int) -> dict[str, np.ndarray]:
        """Pair ``i``: img1, img2 (h, w, 3) uint8, flow (h, w, 2) float32 px, valid (h, w)
        bool and boxes (N, 4) px at the scale (agents of ``focus_depth`` in frame 1)."""
        r = self.pairs.iloc[i]
        a, b = self._image(r.path_1), self._image(r.path_2)
        return {"img1": a, "img2": b, **self._flow(i, a.shape[:2])}


def window_origin(rng: np.random.Generator, size: tuple[int, int], crop: tuple[int, int],
                  box: np.ndarray | None) -> tuple[int, int]:
    """Top-left (y, x) of a ``crop`` window in a frame of ``size``: uniform, or, given a
    ``box`` (xmin, ymin, xmax, ymax) px, uniform among the windows that hold it (as much of
    it as the crop allows)."""
    (h, w), (ch, cw) = size, crop
    lo, hi = [0, 0], [h - ch, w - cw]
    if box is not None:
        for k, (a, b, c) in enumerate(((box[1], box[3], ch), (box[0], box[2], cw))):
            first, last = int(np.ceil(b)) - c, int(np.floor(a))  # window holds [a, b)
            if first > last:  # the box is larger than the crop: centre on it
                first = last = int(round((a + b - c) / 2))
            lo[k], hi[k] = max(first, 0), min(last, hi[k])
            lo[k] = min(lo[k], hi[k])
    return int(rng.integers(lo[0], hi[0] + 1)), int(rng.integers(lo[1], hi[1] + 1))


def box_id_map(boxes: np.ndarray, size: tuple[int, int], origin: tuple[int, int]
               ) -> np.ndarray:
    """(h, w) int64 box numbers of a window at ``origin`` (y, x): k inside the k-th of
    ``boxes`` (N, 4) px of the frame (a later box over an earlier one), 0 elsewhere."""
    out = np.zeros(size, np.int64)
    for k, (x0, y0, x1, y1) in enumerate(boxes, start=1):
        ys = slice(max(int(y0) - origin[0], 0), max(int(np.ceil(y1)) - origin[0], 0))
        xs = slice(max(int(x0) - origin[1], 0), max(int(np.ceil(x1)) - origin[1], 0))
        out[ys, xs] = k
    return out


def box_weight_map(boxes: np.ndarray, size: tuple[int, int], origin: tuple[int, int],
                   weight: float) -> np.ndarray:
    """(h, w) float32 loss weights of a window at ``origin`` (y, x): 1, plus ``weight``
    inside ``boxes`` (N, 4) px of the frame (the pixels of :func:`box_id_map`)."""
    inside = box_id_map(boxes, size, origin) > 0
    return np.where(inside, np.float32(1.0 + weight), np.float32(1.0)).astype(np.float32)


def draw_batch(data: PairCache, recipe: Recipe, step: int) -> dict[str, Tensor]:
    """The batch of ``step``, drawn with ``(seed, step)``: pairs, one ``crop`` window each
    (holding one of the pair's far boxes with ``focus_p``) and a horizontal flip with
    ``flip_p`` (images mirrored, u negated). Tensors img1, img2 (B, 3, h, w) float BGR
    [0, 255], gt (B, 2, h, w) px, valid (B, 1, h, w), weight (B, 1, h, w) and box_id
    (B, 1, h, w) int64 (:func:`box_id_map`)."""
    rng = np.random.default_rng([recipe.seed, step])
    ch, cw = recipe.crop
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("img1", "img2", "gt", "valid",
                                                        "weight", "box_id")}
    for i in rng.integers(0, len(data.pairs), size=recipe.batch):
        d = data.load(int(i))
        h, w = d["img1"].shape[:2]
        if h < ch or w < cw:
            raise PretrainError(f"crop {recipe.crop} is larger than the frames at scale "
                                f"{recipe.scale} ({h}x{w}): use a smaller crop")
        box = None
        if recipe.focus_p > 0 and rng.random() < recipe.focus_p and len(d["boxes"]):
            box = d["boxes"][int(rng.integers(0, len(d["boxes"])))]
        y, x = window_origin(rng, (h, w), (ch, cw), box)
        win = (slice(y, y + ch), slice(x, x + cw))
        a, b, gt, valid = d["img1"][win], d["img2"][win], d["flow"][win], d["valid"][win]
        wt = box_weight_map(d["boxes"], (ch, cw), (y, x), recipe.box_weight)
        ids = box_id_map(d["boxes"], (ch, cw), (y, x))
        if rng.random() < recipe.flip_p:
            a, b, valid, wt, ids = a[:, ::-1], b[:, ::-1], valid[:, ::-1], wt[:, ::-1], ids[:, ::-1]
            gt = gt[:, ::-1] * np.array([-1.0, 1.0], np.float32)
        out["img1"].append(a.transpose(2, 0, 1))
        out["img2"].append(b.transpose(2, 0, 1))
        out["gt"].append(gt.transpose(2, 0, 1))
        out["valid"].append(valid[None])
        out["weight"].append(wt[None])
        out["box_id"].append(ids[None])
    return {k: torch.from_numpy(np.ascontiguousarray(np.stack(v))).to(
        torch.int64 if k == "box_id" else torch.float32) for k, v in out.items()}


# --- training ------------------------------------------------------------------------------------------

def learning_rate(recipe: Recipe, step: int) -> float:
    """The rate of step ``step`` (0-based): ``lr`` times ``gamma`` per milestone passed."""
    return recipe.lr * recipe.gamma ** sum(step >= m for m in recipe.milestones)


def train_step(model: FastFlowNet, opt: torch.optim.Optimizer, batch: dict[str, Tensor],
               recipe: Recipe, step: int) -> dict[str, float]:
    """One optimiser step on ``batch``; returns the step's loss and finest-level EPE."""
    for g in opt.param_groups:
        g["lr"] = learning_rate(recipe, step)
    x1, x2 = fastflownet_inputs(batch["img1"], batch["img2"])
    levels = model.levels(x1, x2)
    loss, parts = pyramid_loss(levels, batch["gt"], batch["valid"], recipe.level_weights,
                               batch["weight"] if recipe.box_weight else None,
                               recipe.full_res)
    if recipe.box_mean_weight:
        up = FFN_DIV_FLOW * F.interpolate(levels[0], size=batch["gt"].shape[-2:],
                                          mode="bilinear", align_corners=False)
        box = box_mean_loss(up, batch["gt"], batch["valid"], batch["box_id"])
        loss, parts["box_mean"] = loss + recipe.box_mean_weight * box, float(box.detach())
    opt.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), recipe.clip)
    opt.step()
    return {"loss": float(loss.detach()), **parts}


def _resume(work: Path, model: FastFlowNet, opt: torch.optim.Optimizer, recipe: Recipe,
            avg: AveragedModel | None) -> tuple[int, list[dict[str, float]]]:
    last = work / "last.pt"
    if not last.is_file():
        return 0, []
    state = torch.load(last, map_location="cpu", weights_only=True)
    if state["recipe"] != json.dumps(asdict(recipe), sort_keys=True):
        raise PretrainError(f"{last} was written by another recipe: remove {work} or use the "
                            "recipe it was made with")
    model.load_state_dict(state["model"])
    opt.load_state_dict(state["optim"])
    if avg is not None:
        avg.load_state_dict(state["average"])
    return int(state["step"]), list(state["history"])


def _checkpoint(work: Path, model: FastFlowNet, opt: torch.optim.Optimizer, recipe: Recipe,
                step: int, rows: list[dict[str, float]], avg: AveragedModel | None) -> None:
    state = {"model": model.state_dict(), "optim": opt.state_dict(), "step": step,
             "history": rows, "recipe": json.dumps(asdict(recipe), sort_keys=True)}
    if avg is not None:
        state["average"] = avg.state_dict()
        state["result"] = avg.module.state_dict()
    with atomic_path(work / "last.pt") as tmp:
        torch.save(state, tmp)


def phase_result(state: dict[str, Any]) -> dict[str, Tensor]:
    """The weights a phase's checkpoint passes on: the average where it keeps one."""
    return state.get("result", state["model"])


def weight_average(model: FastFlowNet, recipe: Recipe) -> AveragedModel | None:
    """The exponential moving average of ``model``'s weights (``recipe.ema``), or None."""
    if not recipe.ema:
        return None
    return AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(recipe.ema),
                         use_buffers=True)


def train(recipe: Recipe, data: PairCache, work: Path, steps: int, heldout: HeldOut | None,
          progress: bool = True, init: dict[str, Tensor] | None = None, desc: str = "pretrain"
          ) -> tuple[FastFlowNet, list[dict[str, float]]]:
    """Train (or resume) to ``steps`` in ``work`` from :func:`initial_model` or the state
    ``init``; evaluate on ``heldout`` every ``eval_every`` steps. Returns the model and the
    history (a row per step). Runs on ``recipe.threads`` threads (the losses depend on it)
    and gives the caller's thread count back."""
    with torch_threads(recipe.threads):
        return _train(recipe, data, work, steps, heldout, progress, init, desc)



def _train(recipe: Recipe, data: PairCache, work: Path, steps: int, heldout: HeldOut | None,
           progress: bool, init: dict[str, Tensor] | None, desc: str
           ) -> tuple[FastFlowNet, list[dict[str, float]]]:
    work.mkdir(parents=True, exist_ok=True)
    model = initial_model(recipe)
    if init is not None:
        model.load_state_dict(init)
    opt = torch.optim.Adam(model.parameters(), lr=recipe.lr)
    avg = weight_average(model, recipe)
    start, rows = _resume(work, model, opt, recipe, avg)
    model.train()
    pbar = bar(total=steps, initial=start, desc=desc, unit="step",
               disable=not progress)
    for step in range(start, steps):
        t0 = time.perf_counter()
        row = {"step": step + 1, **train_step(model, opt, draw_batch(data, recipe, step),
                                               recipe, step)}
        if avg is not None:
            avg.update_parameters(model)
        row["seconds"] = time.perf_counter() - t0
        if heldout is not None and (step + 1) % recipe.eval_every == 0:
            row.update({f"val_{k}": v for k, v in score_model(
                model if avg is None else avg.module, heldout, recipe.scale).items()},
                val_scale=recipe.scale)
        rows.append(row)
        pbar.update(1)
        pbar.set_postfix(loss=f"{row['loss']:.2f}")
        if (step + 1) % CHECKPOINT_EVERY == 0 or step + 1 == steps:
            _checkpoint(work, model, opt, recipe, step + 1, rows, avg)
    pbar.close()
    return (model if avg is None else avg.module), rows


# --- publishing ----------------------------------------------------------------------------------------

def half_state(model: FastFlowNet) -> dict[str, Tensor]:
    """The model's state_dict in float16 (what is shipped)."""
    return {k: v.detach().cpu().half() for k, v in model.state_dict().items()}


def load_half(path: Path) -> FastFlowNet:
    """A FastFlowNet (float32) from a float16 state_dict file."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    model = FastFlowNet()
    model.load_state_dict({k: v.float() for k, v in state.items()})
    return model.eval()


def curve(rows: Sequence[dict[str, float]]) -> list[dict[str, float]]:
    """The validation rows of a history: step and the val_* metrics."""
    return [{k: v for k, v in r.items() if k == "step" or k.startswith("val_")}
            for r in rows if "val_epe" in r]


def loss_curve(rows: Sequence[dict[str, float]], every: int = CHECKPOINT_EVERY
               ) -> list[dict[str, float]]:
    """The training curve in blocks of ``every`` steps: the last step of each block, the
    block's mean loss and mean finest-level EPE (px, on the training windows)."""
    out = []
    for k in range(0, len(rows), every):
        block = rows[k:k + every]
        out.append({"step": int(block[-1]["step"]),
                    "loss": float(np.mean([r["loss"] for r in block])),
                    "epe2": float(np.mean([r["epe2"] for r in block]))})
    return out


def initial_model(recipe: Recipe) -> FastFlowNet:
    """The network of step 0: what :func:`train` starts from (seeded with the recipe)."""
    torch.manual_seed(recipe.seed)
    return FastFlowNet().eval()


def phase_histories(schedule: Sequence[Recipe], work: Path, first: int = 0
                    ) -> tuple[dict, list[dict]]:
    """The last phase's checkpoint state and the history rows of phases ``first + 1`` on,
    steps counted from the start of the schedule (phase ``k`` lives in ``work/phase<k>``)."""
    rows: list[dict[str, float]] = []
    for k in range(first, len(schedule)):
        state = torch.load(work / f"phase{k + 1}" / "last.pt", map_location="cpu",
                           weights_only=True)
        done = sum(p.steps for p in schedule[:k])
        rows += [{**r, "step": r["step"] + done} for r in state["history"]]
    return state, rows


def shipped_phases(schedule: Sequence[Recipe], out: Path) -> tuple[int, dict[str, Any]]:
    """How many leading phases of ``schedule`` the published weights in ``out`` hold (their
    manifest's schedule; keys it lacks at their defaults), and that manifest."""
    try:
        m = json.loads((out / MANIFEST_NAME).read_text())
        ok = m["sha256"] == file_digest(out / WEIGHTS_NAME)
    except (OSError, ValueError, KeyError) as e:
        raise PretrainError(f"no readable published weights in {out} ({e}): train from "
                            "scratch, without --from-shipped") from None
    made = [{**asdict(Recipe()), **r} for r in m["schedule"]]
    mine = json.loads(json.dumps([asdict(p) for p in schedule]))
    if not ok or len(made) > len(mine) or [json.loads(json.dumps(r)) for r in made] != \
            mine[:len(made)]:
        raise PretrainError(f"the weights in {out} were not made by the first phases of this "
                            "schedule (or their sha256 differs): train from scratch, without "
                            "--from-shipped")
    return len(made), m


def publish(schedule: Sequence[Recipe], work: Path, out: Path, world_fp: str,
            heldout: HeldOut, wall_seconds: float | None = None,
            prior: tuple[int, dict[str, Any]] = (0, {})) -> dict[str, Any]:
    """Publish the last phase's ``last.pt`` as ``out/weights.pt`` (float16) with
    ``out/manifest.json``; the validation errors are those of the float16 weights. With
    ``prior`` (:func:`shipped_phases`) the first phases' records come from the manifest of
    the weights the later phases started from."""
    (n, before), first, last = prior, schedule[0], schedule[-1]
    state, rows = phase_histories(schedule, work, n)
    model = FastFlowNet()
    model.load_state_dict(phase_result(state))
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / WEIGHTS_NAME) as tmp:
        torch.save(half_state(model), tmp)
    final = score_model(load_half(out / WEIGHTS_NAME), heldout, last.scale)
    start = before["validation"]["curve"] if n else [{"step": 0, **{
        f"val_{k}": v for k, v in score_model(initial_model(first), heldout,
                                                first.scale).items()}}]
    manifest = {
        "network": "FastFlowNet (flowmod.flow.architectures), trained from scratch here",
        "schedule": [asdict(p) for p in schedule], "steps": int(rows[-1]["step"]),
        # the frame scale the weights were last trained at, and are scored and run at
        "scale": last.scale,
        "world": {"fingerprint": world_fp, "dataroot_params":
                  first.world_params("data/pretrain").model_dump(
                      include={"seed", "world_scenes", "world_keyframes",
                               "world_sweep_scenes", "world_vehicles"})},
        "validation": {"pairs": len(heldout.img1), "final_float16": final,
                       "baselines": baselines(heldout, last.scale),
                       "curve": [*start, *curve(rows)]},
        "training_curve": [*before.get("training_curve", []), *loss_curve(rows)],
        "first_losses": before.get("first_losses") or [r["loss"] for r in rows[:5]],
        "train_seconds": before.get("train_seconds", 0.0) + float(
            sum(r["seconds"] for r in rows)),
        # the invocation that published (a resumed run: from its resumption only)
        "last_invocation_wall_seconds": wall_seconds,
        "where": {"machine": platform.machine(), "processor": platform.processor(),
                  "torch": torch.__version__, "threads": first.threads,
                  "device": "cpu", "python": platform.python_version()},
        "sha256": file_digest(out / WEIGHTS_NAME),
        "format": "float16 state_dict; load with torch.load(weights_only=True)",
    }
    if n:
        manifest["continued_from"] = {"phases": n, "sha256": before["sha256"],
                                      "where": before.get("continued_from", {}).get(
                                          "where", before["where"])}
    write_json(out / MANIFEST_NAME, manifest)
    return manifest


#: Steps of the recipe the manifest's check repeats from scratch on the smoke world.
CHECK_STEPS = 3
#: Keyframe pairs of the smoke world on which the check scores the shipped weights.
CHECK_PAIRS = 4


def smoke_check(recipe: Recipe, weights: Path, smoke: Params, work: Path, scale: float
                ) -> dict[str, Any]:
    """What a test repeats in seconds on the smoke world (every test session generates it):
    the losses of the recipe's first :data:`CHECK_STEPS` steps from scratch on its pairs (so
    a change of the recipe's code shows), and the shipped float16 weights' errors on
    :data:`CHECK_PAIRS` of its keyframe pairs at frame ``scale`` (so other weights show)."""
    shutil.rmtree(work, ignore_errors=True)  # from scratch, every time
    root = smoke.dataroot_path
    frames = scene_frames(root, smoke.version)
    every = {s: "train" for s in frames}
    pairs = training_pairs(frames, every, recipe.max_gap, recipe.start_stride)
    data = PairCache(pairs, root, smoke.version, recipe.scale, work / "cache")
    _, rows = train(recipe, data, work / "train", CHECK_STEPS, None, progress=False)
    held = validation_set(replace(recipe, eval_pairs=CHECK_PAIRS), root,
                          {s: "val" for s in frames})
    return {"world": world_fingerprint(smoke), "steps": CHECK_STEPS, "scale": scale,
            "first_losses": [r["loss"] for r in rows],
            "weights": score_model(load_half(weights), held, scale)}


def pinned_simd_path() -> str:
    """This process's numpy SIMD path (:func:`flowmod.environment.simd_path`), under which
    the smoke-world check is recorded; PretrainError on a CPU with neither pinned path."""
    path = simd_path()
    if path is None:
        raise PretrainError("numpy runs neither AVX-512 nor AVX2 on this CPU: the smoke-world "
                            "check is recorded per SIMD path; record it on a machine with one")
    return path


def with_check(manifest: dict[str, Any], check: dict[str, Any], path: str) -> dict[str, Any]:
    """``manifest`` with ``check`` (:func:`smoke_check`'s) recorded as SIMD path ``path``'s,
    the other paths' records kept: the smoke world's bytes, and so the check's numbers,
    differ between numpy's AVX-512 and AVX2 paths."""
    return {**manifest, "check": {**manifest.get("check", {}), path: check}}


def prepare(recipe: Recipe, dataroot: Path, work: Path, progress: bool = True
            ) -> tuple[str, PairCache, HeldOut]:
    """The world (generated if missing), its training pairs and the validation set."""
    world_fp, dataroot = ensure_world(recipe, dataroot, progress)
    version = recipe.world_params(str(dataroot)).version
    frames = scene_frames(dataroot, version)
    split = scene_split(list(frames), recipe.val_every)
    pairs = training_pairs(frames, split, recipe.max_gap, recipe.start_stride)
    if pairs.empty:
        raise PretrainError(f"no training pair in {dataroot}: the world has no training scene")
    data = PairCache(pairs, dataroot, version, recipe.scale, work / "cache")
    return world_fp, data, validation_set(recipe, dataroot, split)


def phase_data(data: PairCache, recipe: Recipe) -> PairCache:
    """The pairs a phase draws from: those at least ``min_gap`` frames apart, read at the
    phase's scale, with the phase's far-box depths."""
    pairs = data.pairs[data.pairs["gap"] >= recipe.min_gap].reset_index(drop=True)
    if pairs.empty:
        raise PretrainError(f"min_gap {recipe.min_gap} leaves no training pair (max_gap "
                            f"{recipe.max_gap}): lower it")
    return replace(data, pairs=pairs, focus_depth=recipe.focus_depth, scale=recipe.scale)


def run_schedule(schedule: Sequence[Recipe], data: PairCache, work: Path, total: int,
                 heldout: HeldOut | None, progress: bool = True,
                 start: tuple[int, dict[str, Tensor] | None] = (0, None)) -> FastFlowNet:
    """Train the phases in order (each resumable in ``work/phase<k>``, each later one from
    the weights its predecessor ended with) until ``total`` steps of the whole schedule;
    ``start``: the first phases taken as done, and the weights they ended with."""
    (skip, init), done, model = start, 0, None
    for k, recipe in enumerate(schedule, start=1):
        steps = min(recipe.steps, total - done)
        if k <= skip or steps <= 0:
            done += recipe.steps
            continue
        if recipe.init_float16 and init is not None:
            init = {n: v.half().float() for n, v in init.items()}
        model, _ = train(recipe, phase_data(data, recipe),
                         work / f"phase{k}", steps, heldout, progress, init,
                         desc=f"pretrain fastflownet, phase {k}/{len(schedule)}")
        init, done = model.state_dict(), done + steps
    if model is None:
        raise PretrainError(f"--steps {total}: train at least one step")
    return model


def main(argv: list[str] | None = None) -> int:
    """``python -m flowmod.flow.pretrain``: train (resumable) and publish the weights."""
    ap = argparse.ArgumentParser(prog="python -m flowmod.flow.pretrain",
                                 description=main.__doc__)
    ap.add_argument("--steps", type=int, default=sum(p.steps for p in SCHEDULE),
                    help="train to this step of the whole schedule (default: all of it)")
    ap.add_argument("--dataroot", type=Path, default=repo_root() / "data" / "pretrain")
    ap.add_argument("--work", type=Path, default=repo_root() / "runs" / "pretrain")
    ap.add_argument("--out", type=Path, default=repo_root() / WEIGHTS_DIR)
    ap.add_argument("--publish-only", action="store_true",
                    help="publish the phases' last checkpoints as they are, without training")
    ap.add_argument("--check-only", action="store_true",
                    help="only (re)compute the manifest's smoke-world check of the weights")
    ap.add_argument("--from-shipped", action="store_true",
                    help="take the phases the published weights in --out hold as done and "
                         "train the later ones from those weights")
    args = ap.parse_args(argv)
    recipe, t0, path = SCHEDULE[0], time.time(), pinned_simd_path()  # before any work
    prior = shipped_phases(SCHEDULE, args.out) if args.from_shipped else (0, {})
    args.work.mkdir(parents=True, exist_ok=True)
    if not args.check_only:
        world_fp, data, heldout = prepare(recipe, args.dataroot.resolve(), args.work)
        print(f"[pretrain] {len(data.pairs)} training pairs, {len(heldout.img1)} validation "
              "pairs", flush=True)
        if prior[0] and prior[1]["world"]["fingerprint"] != world_fp:
            raise PretrainError(f"the weights in {args.out} were trained on another world "
                                f"than the recipe's (numpy's SIMD path, {path} here, changes "
                                "its bytes too): train from scratch, without --from-shipped")
        if not args.publish_only:
            init = load_half(args.out / WEIGHTS_NAME).state_dict() if prior[0] else None
            run_schedule(SCHEDULE, data, args.work, args.steps, heldout, start=(prior[0], init))
        m = publish(SCHEDULE, args.work, args.out, world_fp, heldout, time.time() - t0, prior)
        print(f"[pretrain] published {args.out}/weights.pt: step {m['steps']}, validation EPE "
              f"in far boxes {m['validation']['final_float16']['epe_boxes']:.2f} px", flush=True)
    smoke = load_profile("smoke", n_jobs=2)
    ensure_world_data(smoke)
    check = smoke_check(recipe, args.out / WEIGHTS_NAME, smoke, args.work / "check",
                        SCHEDULE[-1].scale)
    manifest = with_check(json.loads((args.out / MANIFEST_NAME).read_text()), check, path)
    write_json(args.out / MANIFEST_NAME, manifest)
    print(f"[pretrain] smoke-world check ({path}): {check}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
