"""FastFlowNet trained here, from scratch (chapter 12, the paper's second future-work item).

No pretrained flow weights exist on this machine, so the project's FastFlowNet
(:class:`flowmod.flow.architectures.FastFlowNet`) is trained on the data set's own frames:

- ``photometric`` (self-supervised from scratch, no labels; runs on real nuScenes
  unchanged), after the published unsupervised recipes (UFlow, ARFlow, SMURF): the second
  image warped back by the predicted flow (upsampled to the input's resolution) should look
  like the first. For the first ``selfflow_warmup`` steps the distance is L1 + SSIM, then the
  soft census (ternary) distance, robust, over the pixels that stay inside the image; plus
  ``selfflow_smooth`` x an edge-aware second-order smoothness of the flow on the network's
  1/4-resolution grid, in its pixels;
- ``supervised`` (the reference, synthetic world only): the mean end-point error against the
  world's exact flow over its valid pixels;
- ``finetune``: the photometric loss (census from the first step), starting from a weights
  file (``selfflow_init``): the path of a user who adapts pretrained weights to their own,
  unlabelled frames.

Each trains on whole frames resized to ``selfflow_crop`` (``selfflow_window: frame``, as
ARFlow and UFlow) or on random windows of that size (``crop``), of keyframe pairs at
``flow_scale``, with Adam, ``selfflow_iters`` steps of ``selfflow_batch``
pairs; the batch of step ``i`` is drawn with ``(seed, i)`` so a resumed run (``last.pt``,
written every few steps) sees the same batches as an uninterrupted one. The network's input
and output go through :func:`flowmod.flow.architectures.fastflownet_flow`, the function the
``fastflownet`` estimator uses, so the published ``weights.pt`` is an ordinary FastFlowNet
checkpoint (``fastflownet_weights``). Held-out evaluation: end-point error on pairs of the
validation (curve) and test scenes (once) at full resolution, beside DIS (medium preset) and
Farneback at the same ``flow_scale`` and the zero flow.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F
from torch import Tensor

from flowmod.artefacts import atomic_path
from flowmod.environment import resolve_device
from flowmod.flow.architectures import FFN_DIV_SIZE, FastFlowNet, fastflownet_flow, warp
from flowmod.flow.estimators import DISFlow, FarnebackFlow, GTFlow
from flowmod.flow.metrics import flow_metrics
from flowmod.flow.networks import FastFlowNetFlow
from flowmod.flow.registry import read_image, resize_flow
from flowmod.flowweights import SHIPPED_DIS_PRESET, SHIPPED_ROW
from flowmod.progress import bar
from flowmod.select import fold_roles

#: The ways of training (see the module docstring).
MODES = ("photometric", "supervised", "finetune")
#: How a training pair becomes the network's input (:func:`draw_batch`).
WINDOWS = ("frame", "crop")
#: Steps between resumable checkpoints (``last.pt``).
CHECKPOINT_EVERY = 25
#: Scales at which the photometric loss compares the images (:func:`photometric_loss`): the
#: input's own resolution (the flow upsampled, as UFlow and SMURF warp) and three coarser
#: ones, which widen the reach of the census window.
PHOTOMETRIC_SCALES = (1.0, 0.5, 0.25, 0.125)
#: The DIS preset of the baseline, and the shipped weights' row name in chapter 12's tables
#: (declared in :mod:`flowmod.flowweights`, which chapter 12 reads without torch).
DIS_PRESET, SHIPPED = SHIPPED_DIS_PRESET, SHIPPED_ROW


class SelfFlowError(ValueError):
    """Bad input to the flow training; the message names the thing and the fix."""


# --- losses (pure functions of tensors) -------------------------------------------------------

def _gray(img: Tensor) -> Tensor:
    """(B, 3, H, W) BGR in [0, 255] -> (B, 1, H, W) luminance in [0, 1]."""
    w = img.new_tensor([0.114, 0.587, 0.299]).view(1, 3, 1, 1)
    return (img * w).sum(1, keepdim=True) / 255.0


def census(img: Tensor, size: int = 7) -> Tensor:
    """Soft ternary census transform of (B, 3, H, W) BGR [0, 255] images: (B, size^2, H, W),
    each neighbour's difference to the centre ``d`` mapped to ``d / sqrt(0.81 + d^2)``
    (brightness-invariant; zero padding at the border)."""
    g = 255.0 * _gray(img)
    patches = F.unfold(g, size, padding=size // 2).view(g.shape[0], size * size, *g.shape[-2:])
    d = patches - g
    return d / torch.sqrt(0.81 + d * d)


def census_distance(c1: Tensor, c2: Tensor) -> Tensor:
    """(B, 1, H, W) distance of two census transforms: sum of ``t^2 / (0.1 + t^2)``."""
    t = (c1 - c2) ** 2
    return (t / (0.1 + t)).sum(1, keepdim=True)


def inside(flow: Tensor) -> Tensor:
    """(B, 1, H, W) float mask of the pixels whose target ``p + flow`` is inside the image."""
    _, _, h, w = flow.shape
    xs = torch.arange(w, dtype=flow.dtype, device=flow.device).view(1, 1, w)
    ys = torch.arange(h, dtype=flow.dtype, device=flow.device).view(1, h, 1)
    x, y = xs + flow[:, 0], ys + flow[:, 1]
    return ((x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)).unsqueeze(1).to(flow.dtype)


def ssim_distance(a: Tensor, b: Tensor) -> Tensor:
    """(B, 1, H, W) structural dissimilarity ``(1 - SSIM) / 2`` in [0, 1] of two (B, 3, H, W)
    BGR [0, 255] images over 3x3 windows, averaged over the channels."""
    x, y = a / 255.0, b / 255.0
    mu_x, mu_y = F.avg_pool2d(x, 3, 1, 1), F.avg_pool2d(y, 3, 1, 1)
    var_x = F.avg_pool2d(x * x, 3, 1, 1) - mu_x ** 2
    var_y = F.avg_pool2d(y * y, 3, 1, 1) - mu_y ** 2
    cov = F.avg_pool2d(x * y, 3, 1, 1) - mu_x * mu_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ssim = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)
            / ((mu_x ** 2 + mu_y ** 2 + c1) * (var_x + var_y + c2)))
    return ((1 - ssim) / 2).clamp(0, 1).mean(1, keepdim=True)


def warmup_distance(a: Tensor, b: Tensor) -> Tensor:
    """(B, 1, H, W) warm-up distance of two BGR [0, 255] images: 0.15 x mean absolute
    difference (in [0, 1]) + 0.85 x :func:`ssim_distance` (the L1 + SSIM of ARFlow's and
    UFlow's first phase, before the census loss)."""
    return 0.15 * (a - b).abs().mean(1, keepdim=True) / 255.0 + 0.85 * ssim_distance(a, b)


def second_order_smoothness(flow: Tensor, img: Tensor, edge: float = 150.0) -> Tensor:
    """Edge-aware second-order smoothness (scalar) of ``flow`` (B, 2, H, W, px) on the
    1/4-resolution grid (the network's own output resolution), in pixels of that grid:
    mean |f(x-1) - 2 f(x) + f(x+1)| over both directions, damped by ``exp(-edge * |image
    gradient|)`` (1/4-resolution image in [0, 1]; the larger of the gradients on either side
    of ``x``), as UFlow's."""
    f = 0.25 * F.interpolate(flow, scale_factor=0.25, mode="area")
    g = _gray(F.interpolate(img, scale_factor=0.25, mode="area"))
    loss = flow.new_zeros(())
    for dim in (2, 3):
        n = f.shape[dim]
        d2 = (f.narrow(dim, 0, n - 2) - 2 * f.narrow(dim, 1, n - 2)
              + f.narrow(dim, 2, n - 2)).abs().mean(1, keepdim=True)
        gi = g.diff(dim=dim).abs()
        di = torch.maximum(gi.narrow(dim, 0, n - 2), gi.narrow(dim, 1, n - 2))
        loss = loss + (d2 * torch.exp(-edge * di)).mean()
    return loss / 2


def photometric_loss(img1: Tensor, img2: Tensor, flow: Tensor, smooth: float,
                     scales: Sequence[float] = (1.0,), warm: bool = False
                     ) -> tuple[Tensor, dict[str, float]]:
    """The self-supervised loss of ``flow`` (B, 2, H, W, px; the network's output upsampled
    to the images' resolution) for images (B, 3, H, W) BGR [0, 255]: the distance of img1 and
    img2 warped back by the flow, robust (``(d + 0.01)^0.4``), over pixels that stay inside the
    image, averaged over images and flow resized by each of ``scales`` (coarse scales widen a
    7 px census window's reach: at 1/8 it sees 56 px), plus ``smooth`` x
    :func:`second_order_smoothness`. The distance: :func:`warmup_distance` (L1 + SSIM) while
    ``warm``, else the census distance. The warped image is a function of the flow only (the
    images are constants). Returns (loss, parts)."""
    terms = []
    for s in scales:
        a, b, f = img1, img2, flow
        if s != 1.0:
            a, b = (F.interpolate(x, scale_factor=s, mode="area") for x in (img1, img2))
            f = s * F.interpolate(flow, scale_factor=s, mode="area")
        m = inside(f)
        dist = (warmup_distance(a, warp(b, f)) if warm
                else census_distance(census(a), census(warp(b, f))))
        terms.append(((dist + 0.01) ** 0.4 * m).sum() / m.sum().clamp(min=1.0))
    photo = torch.stack(terms).mean()
    sm = second_order_smoothness(flow, img1)
    return photo + smooth * sm, {"photometric": float(photo.detach()),
                                 "smoothness": float(sm.detach()), "warm-up": float(warm)}


def supervised_loss(flow: Tensor, gt: Tensor, valid: Tensor) -> tuple[Tensor, dict[str, float]]:
    """Mean end-point error (px) of ``flow`` against ``gt`` (B, 2, H, W) over ``valid``
    (B, 1, H, W) pixels. Returns (loss, parts)."""
    err = torch.sqrt(((flow - gt) ** 2).sum(1, keepdim=True) + 1e-6)
    loss = (err * valid).sum() / valid.sum().clamp(min=1.0)
    return loss, {"epe": float(loss.detach())}


# --- data ------------------------------------------------------------------------------------

@dataclass
class FramePairs:
    """Training pairs: image paths (frame 1, frame 2), images read at ``scale``, and for the
    supervised mode the exact flow at that scale (``gt_files``: per pair (flow.npy, valid.npy))."""

    paths: list[tuple[Path, Path]]
    scale: float
    gt_files: list[tuple[Path, Path]] | None = None

    def __len__(self) -> int:
        return len(self.paths)

    def load(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Pair ``i``: (img1, img2) (h, w, 3) uint8 BGR at ``scale``, and (flow (h, w, 2) float32
        px at that scale, valid (h, w) bool) or (None, None)."""
        imgs = []
        for path in self.paths[i]:
            img = read_image(path)
            h, w = (round(s * self.scale) for s in img.shape[:2])
            imgs.append(img if (h, w) == img.shape[:2] else
                        cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA))
        if self.gt_files is None:
            return imgs[0], imgs[1], None, None
        f, v = self.gt_files[i]
        return imgs[0], imgs[1], np.load(f).astype(np.float32), np.load(v)


def cache_gt(pairs: pd.DataFrame, dataroot: Path, version: str, scale: float, out: Path,
             progress: bool = True) -> list[tuple[Path, Path]]:
    """The exact flow of every pair at ``scale`` (float16 px of the scaled image) and its
    valid mask, one file pair per pair in ``out`` (kept across a resumed build)."""
    est = GTFlow(dataroot, version)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for k, r in enumerate(bar(list(pairs.itertuples()), desc="exact flow of the training pairs",
                              disable=not progress)):
        f, v = out / f"{k:05d}.flow.npy", out / f"{k:05d}.valid.npy"
        if not (f.is_file() and v.is_file()):
            flow, valid = est.estimate_tokens(r.sd_token_1, r.sd_token_2)
            h, w = (round(s * scale) for s in flow.shape[:2])
            small = resize_flow(flow, (h, w)) if (h, w) != flow.shape[:2] else flow
            vsmall = cv2.resize(valid.astype(np.uint8), (w, h),
                                interpolation=cv2.INTER_NEAREST).astype(bool)
            with atomic_path(v) as tmp:
                np.save(tmp, vsmall)
            with atomic_path(f) as tmp:
                np.save(tmp, small.astype(np.float16))
        files.append((f, v))
    return files


def draw_batch(data: FramePairs, step: int, seed: int, batch: int, crop: Sequence[int],
               window: str = "crop") -> dict[str, Tensor]:
    """The batch of training step ``step``: ``batch`` pairs drawn with ``(seed, step)``, each
    as a random ``crop`` (h, w) window (``window="crop"``) or as the whole frame resized to
    ``crop`` (``"frame"``: nothing leaves the picture but what leaves the camera's view; the
    exact flow is resized with its vectors). Tensors: img1, img2 (B, 3, h, w) float BGR
    [0, 255]; with exact flow also gt (B, 2, h, w) px and valid (B, 1, h, w)."""
    if window not in WINDOWS:
        raise SelfFlowError(f"selfflow_window={window!r}; allowed: {WINDOWS}")
    rng = np.random.default_rng([seed, step])
    ch, cw = (int(c) for c in crop)
    out: dict[str, list[np.ndarray]] = {"img1": [], "img2": [], "gt": [], "valid": []}
    for i in rng.integers(0, len(data), size=batch):
        a, b, gt, valid = data.load(int(i))
        h, w = a.shape[:2]
        if window == "frame":
            a, b = (cv2.resize(x, (cw, ch), interpolation=cv2.INTER_AREA) for x in (a, b))
            if gt is not None:
                gt = resize_flow(gt, (ch, cw))
                valid = cv2.resize(valid.astype(np.uint8), (cw, ch),
                                   interpolation=cv2.INTER_NEAREST).astype(bool)
            h, w = ch, cw
        if h < ch or w < cw:
            raise SelfFlowError(f"selfflow_crop={list(crop)} is larger than the training "
                                f"images at flow_scale ({h}x{w}): use a smaller crop")
        y, x = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
        out["img1"].append(a[y:y + ch, x:x + cw].transpose(2, 0, 1))
        out["img2"].append(b[y:y + ch, x:x + cw].transpose(2, 0, 1))
        if gt is not None:
            out["gt"].append(gt[y:y + ch, x:x + cw].transpose(2, 0, 1))
            out["valid"].append(valid[None, y:y + ch, x:x + cw])
    return {k: torch.from_numpy(np.stack(v)).float() for k, v in out.items() if v}


# --- evaluation ------------------------------------------------------------------------------

@dataclass
class HeldOut:
    """Held-out pairs at full resolution: images, exact flow and valid mask (None on real
    data), the boxes of their target vehicles (N, 4) px and each pair's scene (the unit an
    interval resamples; empty where unknown)."""

    img1: list[np.ndarray]
    img2: list[np.ndarray]
    gt: list[np.ndarray] | None
    valid: list[np.ndarray] | None
    boxes: list[np.ndarray]
    scenes: list[str] = field(default_factory=list)


def held_out(pairs: pd.DataFrame, objects: pd.DataFrame, dataroot: Path, version: str,
             synthetic: bool) -> HeldOut:
    """Read the held-out pairs (and, on a generated world, their exact flow)."""
    est = GTFlow(dataroot, version) if synthetic else None
    h = HeldOut([], [], [] if est else None, [] if est else None, [])
    cols = ["xmin", "ymin", "xmax", "ymax"]
    for r in pairs.itertuples():
        h.img1.append(read_image(dataroot / r.path_1))
        h.img2.append(read_image(dataroot / r.path_2))
        h.boxes.append(objects.loc[objects["pair_id"] == r.pair_id, cols].to_numpy(float))
        h.scenes.append(str(getattr(r, "scene", "")))
        if est is not None:
            flow, valid = est.estimate_tokens(r.sd_token_1, r.sd_token_2)
            h.gt.append(flow)
            h.valid.append(valid)
    return h


def pair_metrics(estimate: Callable[[np.ndarray, np.ndarray], np.ndarray], data: HeldOut
                 ) -> tuple[list[dict[str, float]], float]:
    """:func:`flowmod.flow.metrics.flow_metrics` of ``estimate(img1, img2) -> (H, W, 2)`` px
    on each held-out pair (none without exact flow), and the estimator's seconds in all (its
    calls only, not the scoring)."""
    rows, seconds = [], 0.0
    for k in range(len(data.img1)):
        t0 = time.perf_counter()
        flow = estimate(data.img1[k], data.img2[k])
        seconds += time.perf_counter() - t0
        if data.gt is not None:
            rows.append(flow_metrics(flow, data.gt[k], data.valid[k], data.boxes[k]))
    return rows, seconds


def mean_metrics(rows: list[dict[str, float]]) -> dict[str, float]:
    """The mean over pairs of :func:`pair_metrics`' rows: EPE (px) and Fl-all (%), overall
    and inside the target vehicles' boxes, and the boxes' mean-error length (px,
    :func:`flowmod.flow.metrics.box_bias`); NaN without rows (no exact flow)."""
    keys = ("epe", "epe_boxes", "fl_all", "fl_all_boxes", "bias_boxes")
    return {k: float(np.nanmean([r[k] for r in rows])) if rows else float("nan")
            for k in keys}


def score(estimate: Callable[[np.ndarray, np.ndarray], np.ndarray], data: HeldOut
          ) -> dict[str, float]:
    """:func:`mean_metrics` of ``estimate(img1, img2) -> (H, W, 2)`` px on the held-out
    pairs, and its seconds per pair (the estimator's calls only); NaN metrics without exact
    flow."""
    rows, seconds = pair_metrics(estimate, data)
    return {"seconds_per_pair": seconds / max(len(data.img1), 1), **mean_metrics(rows)}


def reference_estimators(scale: float) -> dict[str, Callable[[np.ndarray, np.ndarray],
                                                            np.ndarray]]:
    """The reference methods of a flow network's held-out scores: the
    zero flow, Farneback and DIS (medium) at ``scale``, each ``(img1, img2) -> (H, W, 2)``."""
    return {"zero flow": lambda a, b: np.zeros((*a.shape[:2], 2), np.float32),
            "farneback": FarnebackFlow(scale=scale).estimate,
            f"dis ({DIS_PRESET})": DISFlow(DIS_PRESET, scale=scale).estimate}


def baselines(data: HeldOut, scale: float) -> dict[str, dict[str, float]]:
    """:func:`reference_estimators` scored on the held-out pairs."""
    return {m: score(est, data) for m, est in reference_estimators(scale).items()}


def score_model(model: FastFlowNet, data: HeldOut, scale: float) -> dict[str, float]:
    """:func:`score` of a FastFlowNet being trained, through the ``fastflownet`` estimator
    (resize to multiples of 64 at ``scale``, flow back at full size), on its device."""
    was = model.training
    est = FastFlowNetFlow(model=model, device=next(model.parameters()).device, scale=scale)
    try:
        return score(est.estimate, data)
    finally:
        model.train(was)


# --- training --------------------------------------------------------------------------------

def save_state(obj: Any, path: Path) -> None:
    """``torch.save`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def step_loss(model: FastFlowNet, b: dict[str, Tensor], mode: str, smooth: float,
              warm: bool) -> tuple[Tensor, dict[str, float]]:
    """The loss of one batch ``b`` (:func:`draw_batch`) for ``mode``: photometric (with the
    warm-up distance while ``warm``) on the flow upsampled to the batch's resolution, or
    supervised by ``b``'s exact flow."""
    flow = fastflownet_flow(model, b["img1"], b["img2"])
    if mode == "supervised":
        return supervised_loss(flow, b["gt"], b["valid"])
    return photometric_loss(b["img1"], b["img2"], flow, smooth, PHOTOMETRIC_SCALES, warm)


def train_flow(data: FramePairs, mode: str, work: Path, *, iters: int, batch: int, lr: float,
               crop: Sequence[int], smooth: float, seed: int,
               evaluate: Callable[[FastFlowNet], dict[str, float]] | None = None,
               eval_every: int = 0, progress: bool = True, desc: str = "train flow",
               stop_after: int | None = None, device: Any = "cpu", init: Path | None = None,
               window: str = "crop", warmup: int = 0) -> tuple[FastFlowNet, pd.DataFrame]:
    """Train a FastFlowNet in ``work`` (resumable from ``work/last.pt``), from scratch or
    from the weights file ``init`` (a float16 or float32 state_dict).

    ``mode``: ``photometric`` or ``finetune`` (the photometric loss; ``finetune`` needs
    ``init``) or ``supervised`` (``data`` must hold exact flow); ``window``: crops or whole
    frames resized to ``crop`` (:func:`draw_batch`); ``warmup``: the photometric mode's first
    steps use the L1 + SSIM distance instead of the census (:func:`photometric_loss`). Before the
    first step (step 0: the untrained network), every ``eval_every`` steps and after the
    last, ``evaluate(model)`` adds its metrics (``val_<name>``) to the history. ``stop_after``: end after that many steps (tests of resuming); ``device``: where
    the network trains (``auto``: CUDA when there is one). Returns the model
    and the history: one row per step (step, loss, the loss's parts, seconds) with the
    evaluations' columns on their steps."""
    if mode not in MODES:
        raise SelfFlowError(f"mode={mode!r}; allowed: {MODES}")
    if mode == "supervised" and data.gt_files is None:
        raise SelfFlowError("supervised training needs the exact flow (a generated world)")
    if (mode == "finetune") != (init is not None):
        raise SelfFlowError(f"mode={mode!r} with init={init}: the finetune mode, and only it, "
                            "starts from a weights file (selfflow_init)")
    if any(int(c) % FFN_DIV_SIZE for c in crop):
        raise SelfFlowError(f"selfflow_crop={list(crop)}: both sides must be multiples of "
                            f"{FFN_DIV_SIZE} (FastFlowNet's pyramid)")
    dev = resolve_device(device)
    torch.manual_seed(seed)
    model = FastFlowNet().to(dev)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    rows: list[dict[str, float]] = []
    start = 0
    last = work / "last.pt"
    if last.is_file():
        state = torch.load(last, map_location=dev, weights_only=True)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optim"])
        start, rows = int(state["step"]), list(state["history"])
    elif init is not None:
        weights = torch.load(init, map_location=dev, weights_only=True)
        model.load_state_dict({k: v.float() for k, v in weights.items()})
    if evaluate is not None and start == 0:
        rows.append({"step": 0, **{f"val_{k}": v for k, v in evaluate(model).items()}})
    model.train()
    pbar = bar(total=iters, initial=start, desc=desc, unit="step", disable=not progress)
    end = iters if stop_after is None else min(iters, start + stop_after)
    try:
        for step in range(start, end):
            t0 = time.perf_counter()
            b = {k: v.to(dev) for k, v in
                 draw_batch(data, step, seed, batch, crop, window).items()}
            loss, parts = step_loss(model, b, mode, smooth,
                                    warm=mode == "photometric" and step < warmup)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            row: dict[str, float] = {"step": step + 1, "loss": float(loss.detach()), **parts,
                                     "seconds": time.perf_counter() - t0}
            if evaluate is not None and ((eval_every and (step + 1) % eval_every == 0)
                                         or step + 1 == iters):
                row.update({f"val_{k}": v for k, v in evaluate(model).items()})
            rows.append(row)
            pbar.update(1)
            pbar.set_postfix(loss=f"{row['loss']:.3f}")
            if (step + 1) % CHECKPOINT_EVERY == 0 or step + 1 == end:
                save_state({"model": model.state_dict(), "optim": opt.state_dict(),
                       "step": step + 1, "history": rows}, last)
    finally:
        pbar.close()
    return model, pd.DataFrame(rows)


# --- pairs -------------------------------------------------------------------------------------

def sample_pairs(df: pd.DataFrame, n: int, seed: Sequence[int]) -> pd.DataFrame:
    """``n`` rows of ``df`` drawn with ``seed`` (in ``df``'s order)."""
    idx = np.random.default_rng(list(seed)).permutation(len(df))[:n]
    return df.iloc[np.sort(idx)].reset_index(drop=True)


def fold0_pairs(pairs: pd.DataFrame, folds: int, role: str) -> pd.DataFrame:
    """The pairs of one role (``train``, ``val``, ``test``) for a network: of the single
    split, or with cross-validation as for the classifier of fold 0. It trains on ``train``
    pairs, is chosen on ``val`` pairs and scored once on ``test`` pairs."""
    return pairs[fold_roles(pairs, 0, folds) == role]


def validation_pairs(pairs: pd.DataFrame, n: int, seed: int, folds: int = 1) -> pd.DataFrame:
    """The ``n`` validation pairs (of fold 0's validation scenes) drawn with ``seed``: the
    training curve and the choice of a network are made on them."""
    return sample_pairs(fold0_pairs(pairs, folds, "val"), n, (seed, 2))


def heldout_pairs(pairs: pd.DataFrame, n: int, seed: int, folds: int = 1) -> pd.DataFrame:
    """The ``n`` held-out pairs (of the test scenes, :func:`fold0_pairs`) drawn with
    ``seed``."""
    return sample_pairs(fold0_pairs(pairs, folds, "test"), n, (seed, 1))
