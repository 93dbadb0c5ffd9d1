"""FastFlowNet trained here, from scratch (chapter 12, the paper's second future-work item).

No pretrained flow weights exist on this machine, so the project's FastFlowNet
(:class:`flowmod.flow.nets.FastFlowNet`) is trained on the data set's own frames:

- ``photometric`` (self-supervised, no labels; runs on real nuScenes unchanged): the second
  image warped back by the predicted flow should look like the first. Loss: the soft census
  (ternary) distance of the two, robust (Charbonnier), over the pixels that stay inside the
  image, plus ``selfflow_smooth`` x an edge-aware first-order smoothness of the flow;
- ``supervised`` (the reference, synthetic world only): the mean end-point error against the
  world's exact flow over its valid pixels.

Both train on random ``selfflow_crop`` windows of consecutive keyframe pairs of the train
and val scenes at ``flow_scale``, with Adam, ``selfflow_iters`` steps of ``selfflow_batch``
pairs; the batch of step ``i`` is drawn with ``(seed, i)`` so a resumed run (``last.pt``,
written every few steps) sees the same batches as an uninterrupted one. The network's input
and output go through :func:`flowmod.flow.nets.fastflownet_flow`, the function the
``fastflownet`` estimator uses, so the published ``weights.pt`` is an ordinary FastFlowNet
checkpoint (``fastflownet_weights``). Held-out evaluation: end-point error on pairs of the
test scenes at full resolution, beside DIS (medium preset) and Farneback at the same
``flow_scale`` and the zero flow.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F
from torch import Tensor

from flowmod.artefacts import atomic_path, write_json
from flowmod.flow.estimators import DISFlow, FarnebackFlow, GTFlow
from flowmod.flow.metrics import flow_metrics
from flowmod.flow.nets import FFN_DIV_SIZE, FastFlowNet, fastflownet_flow, warp
from flowmod.flow.networks import FastFlowNetFlow
from flowmod.flow.registry import read_image, resize_flow
from flowmod.progress import bar

#: The two ways of training (see the module docstring).
MODES = ("photometric", "supervised")
#: Steps between resumable checkpoints (``last.pt``).
CHECKPOINT_EVERY = 25
#: Scales at which the photometric loss compares the images (:func:`photometric_loss`): half
#: the window (FastFlowNet's flow is at 1/4 resolution anyway) and two coarser ones.
PHOTOMETRIC_SCALES = (0.5, 0.25, 0.125)
#: The DIS preset of the baseline (the CPU default of chapter 03).
DIS_PRESET = "medium"


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


def smoothness(flow: Tensor, img: Tensor, edge: float = 10.0) -> Tensor:
    """Edge-aware first-order smoothness (scalar): mean |flow gradient| (px / px), damped by
    ``exp(-edge * |image gradient|)`` (image in [0, 1]) where the image has an edge."""
    g = _gray(img)
    loss = flow.new_zeros(())
    for dim in (2, 3):
        df = flow.diff(dim=dim).abs().mean(1, keepdim=True)
        di = g.diff(dim=dim).abs()
        loss = loss + (df * torch.exp(-edge * di)).mean()
    return loss / 2


def photometric_loss(img1: Tensor, img2: Tensor, flow: Tensor, smooth: float,
                     scales: Sequence[float] = (1.0,)) -> tuple[Tensor, dict[str, float]]:
    """The self-supervised loss of ``flow`` (B, 2, H, W, px) for images (B, 3, H, W) BGR
    [0, 255]: robust census distance of img1 and img2 warped back by the flow, over pixels
    that stay inside the image, averaged over images and flow resized by each of ``scales``
    (coarse scales widen the census window's reach: a 7 px window at 1/8 sees 56 px), plus
    ``smooth`` x :func:`smoothness` at the first scale. Returns (loss, parts)."""
    terms, sm = [], flow.new_zeros(())
    for k, s in enumerate(scales):
        a, b, f = img1, img2, flow
        if s != 1.0:
            a, b = (F.interpolate(x, scale_factor=s, mode="area") for x in (img1, img2))
            f = s * F.interpolate(flow, scale_factor=s, mode="area")
        m = inside(f)
        dist = census_distance(census(a), census(warp(b, f)))
        terms.append(((dist + 0.01) ** 0.4 * m).sum() / m.sum().clamp(min=1.0))
        if k == 0:
            sm = smoothness(f, a)
    photo = torch.stack(terms).mean()
    return photo + smooth * sm, {"photometric": float(photo.detach()),
                                 "smoothness": float(sm.detach())}


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
        import cv2

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
            import cv2

            vsmall = cv2.resize(valid.astype(np.uint8), (w, h),
                                interpolation=cv2.INTER_NEAREST).astype(bool)
            with atomic_path(v) as tmp:
                np.save(tmp, vsmall)
            with atomic_path(f) as tmp:
                np.save(tmp, small.astype(np.float16))
        files.append((f, v))
    return files


def draw_batch(data: FramePairs, step: int, seed: int, batch: int, crop: Sequence[int]
               ) -> dict[str, Tensor]:
    """The batch of training step ``step``: ``batch`` pairs and one random ``crop`` (h, w)
    window each, drawn with ``(seed, step)``. Tensors: img1, img2 (B, 3, h, w) float BGR
    [0, 255]; with exact flow also gt (B, 2, h, w) px and valid (B, 1, h, w)."""
    rng = np.random.default_rng([seed, step])
    ch, cw = (int(c) for c in crop)
    out: dict[str, list[np.ndarray]] = {"img1": [], "img2": [], "gt": [], "valid": []}
    for i in rng.integers(0, len(data), size=batch):
        a, b, gt, valid = data.load(int(i))
        h, w = a.shape[:2]
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
    data) and the boxes of their target vehicles (N, 4) px."""

    img1: list[np.ndarray]
    img2: list[np.ndarray]
    gt: list[np.ndarray] | None
    valid: list[np.ndarray] | None
    boxes: list[np.ndarray]


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
        if est is not None:
            flow, valid = est.estimate_tokens(r.sd_token_1, r.sd_token_2)
            h.gt.append(flow)
            h.valid.append(valid)
    return h


def score(estimate: Callable[[np.ndarray, np.ndarray], np.ndarray], data: HeldOut
          ) -> dict[str, float]:
    """Mean over the held-out pairs of EPE (px) and Fl-all (%), overall and inside the target
    vehicles' boxes, of ``estimate(img1, img2) -> (H, W, 2)`` px, and its seconds per pair;
    NaN metrics without exact flow."""
    rows, t0 = [], time.perf_counter()
    for k in range(len(data.img1)):
        flow = estimate(data.img1[k], data.img2[k])
        if data.gt is not None:
            rows.append(flow_metrics(flow, data.gt[k], data.valid[k], data.boxes[k]))
    out = {"seconds_per_pair": (time.perf_counter() - t0) / max(len(data.img1), 1)}
    keys = ("epe", "epe_boxes", "fl_all", "fl_all_boxes")
    out.update({k: float(np.nanmean([r[k] for r in rows])) if rows else float("nan")
                for k in keys})
    return out


def baselines(data: HeldOut, scale: float) -> dict[str, dict[str, float]]:
    """The reference methods on the held-out pairs: the zero flow, Farneback and DIS (medium)
    at ``scale``."""
    dis, farneback = DISFlow(DIS_PRESET, scale=scale), FarnebackFlow(scale=scale)
    return {"zero flow": score(lambda a, b: np.zeros((*a.shape[:2], 2), np.float32), data),
            "farneback": score(farneback.estimate, data),
            f"dis ({DIS_PRESET})": score(dis.estimate, data)}


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

def _save(obj: Any, path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def train_flow(data: FramePairs, mode: str, work: Path, *, iters: int, batch: int, lr: float,
               crop: Sequence[int], smooth: float, seed: int,
               evaluate: Callable[[FastFlowNet], dict[str, float]] | None = None,
               eval_every: int = 0, progress: bool = True, desc: str = "train flow",
               stop_after: int | None = None, device: Any = "cpu"
               ) -> tuple[FastFlowNet, pd.DataFrame]:
    """Train a FastFlowNet from scratch in ``work`` (resumable from ``work/last.pt``).

    ``mode``: ``photometric`` or ``supervised`` (``data`` must hold exact flow). Every
    ``eval_every`` steps and after the last, ``evaluate(model)`` adds held-out metrics to the
    history. ``stop_after``: end after that many steps (tests of resuming); ``device``: where
    the network trains (``auto``: CUDA when there is one). Returns the model
    and the history: one row per step (step, loss, the loss's parts, seconds) with the
    evaluations' columns on their steps."""
    if mode not in MODES:
        raise SelfFlowError(f"mode={mode!r}; allowed: {MODES}")
    if mode == "supervised" and data.gt_files is None:
        raise SelfFlowError("supervised training needs the exact flow (a generated world)")
    if any(int(c) % FFN_DIV_SIZE for c in crop):
        raise SelfFlowError(f"selfflow_crop={list(crop)}: both sides must be multiples of "
                            f"{FFN_DIV_SIZE} (FastFlowNet's pyramid)")
    from flowmod.environment import resolve_device

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
    model.train()
    pbar = bar(total=iters, initial=start, desc=desc, unit="step", disable=not progress)
    end = iters if stop_after is None else min(iters, start + stop_after)
    try:
        for step in range(start, end):
            t0 = time.perf_counter()
            b = {k: v.to(dev) for k, v in draw_batch(data, step, seed, batch, crop).items()}
            flow = fastflownet_flow(model, b["img1"], b["img2"])
            if mode == "photometric":
                loss, parts = photometric_loss(b["img1"], b["img2"], flow, smooth,
                                               PHOTOMETRIC_SCALES)
            else:
                loss, parts = supervised_loss(flow, b["gt"], b["valid"])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            row: dict[str, float] = {"step": step + 1, "loss": float(loss.detach()), **parts,
                                     "seconds": time.perf_counter() - t0}
            if evaluate is not None and ((eval_every and (step + 1) % eval_every == 0)
                                         or step + 1 == iters):
                row.update({f"heldout_{k}": v for k, v in evaluate(model).items()})
            rows.append(row)
            pbar.update(1)
            pbar.set_postfix(loss=f"{row['loss']:.3f}")
            if (step + 1) % CHECKPOINT_EVERY == 0 or step + 1 == end:
                _save({"model": model.state_dict(), "optim": opt.state_dict(),
                       "step": step + 1, "history": rows}, last)
    finally:
        pbar.close()
    return model, pd.DataFrame(rows)


# --- the stage (chapter 12) -------------------------------------------------------------------

def _sample(df: pd.DataFrame, n: int, seed: Sequence[int]) -> pd.DataFrame:
    idx = np.random.default_rng(list(seed)).permutation(len(df))[:n]
    return df.iloc[np.sort(idx)].reset_index(drop=True)


def heldout_pairs(pairs: pd.DataFrame, n: int, seed: int) -> pd.DataFrame:
    """The ``n`` held-out pairs (of the test scenes) drawn with ``seed``."""
    return _sample(pairs[pairs["split"] == "test"], n, (seed, 1))


def run(params: Any, progress: bool = True) -> list[str]:
    """Build every stale ``selfflow[<mode>]`` node when ``selfflow_build`` is on (``make
    selfflow``); otherwise build nothing. Returns the modes whose weights are current."""
    from flowmod import dag

    for mode in params.selfflow_modes if params.selfflow_build else ():
        b = dag.begin(params, dag.Node("selfflow", None, mode))
        if not b.up_to_date:
            _build(b, mode, progress)
    return built(params)


def _build(b: Any, mode: str, progress: bool) -> None:
    """Train, evaluate and publish one ``selfflow[<mode>]`` node (``b``: its
    :class:`flowmod.dag.Build`): ``weights.pt`` (a FastFlowNet state_dict), ``history.csv``
    and ``eval.json`` (held-out metrics of the network and of the baselines)."""
    import functools
    import shutil

    from flowmod import dag, world

    q = b.params
    root = q.dataroot_path
    synthetic = world.is_synthetic(root, q.version)
    if mode == "supervised" and not synthetic:
        raise SelfFlowError(
            f"selfflow_modes has 'supervised', but {root} ({q.version}) is not a generated "
            "world: there is no exact flow to supervise with; use selfflow_modes=[photometric]")
    sel = b.input_dir(dag.Node("select"))
    pairs = pd.read_parquet(sel / "pairs.parquet")
    train = _sample(pairs[pairs["split"].isin(["train", "val"])], q.selfflow_pairs, (q.seed, 0))
    test = heldout_pairs(pairs, q.selfflow_eval_pairs, q.seed)
    if train.empty or test.empty:
        raise SelfFlowError(f"no training ({len(train)}) or held-out ({len(test)}) pair in "
                            "chapter 02's selection: run chapter 02 first")
    work = b.start(fresh=q.force)
    gt_files = (cache_gt(train, root, q.version, q.flow_scale, work / "gt", progress)
                if mode == "supervised" else None)
    data = FramePairs([(root / r.path_1, root / r.path_2) for r in train.itertuples()],
                      q.flow_scale, gt_files)
    heldout = held_out(test, pd.read_parquet(sel / "objects.parquet"), root, q.version,
                       synthetic)
    model, hist = train_flow(
        data, mode, work, iters=q.selfflow_iters, batch=q.selfflow_batch, lr=q.selfflow_lr,
        crop=q.selfflow_crop, smooth=q.selfflow_smooth, seed=q.seed,
        evaluate=functools.partial(score_model, data=heldout, scale=q.flow_scale),
        eval_every=q.selfflow_eval_every, progress=progress,
        desc=f"train fastflownet ({mode})", device=q.device)
    _save({k: v.cpu() for k, v in model.state_dict().items()}, work / "weights.pt")
    with atomic_path(work / "history.csv") as tmp:
        hist.to_csv(tmp, index=False)
    final = {k[len("heldout_"):]: v for k, v in hist.iloc[-1].items() if k.startswith("heldout_")}
    write_json(work / "eval.json", {
        "mode": mode, "steps": int(hist["step"].iloc[-1]),
        "seconds_per_step": float(hist["seconds"].median()),
        "train_pairs": len(train), "heldout_pairs": len(test),
        "fastflownet": final, "baselines": baselines(heldout, q.flow_scale)})
    shutil.rmtree(work / "gt", ignore_errors=True)
    (work / "last.pt").unlink(missing_ok=True)
    b.publish(mode=mode, steps=int(hist["step"].iloc[-1]))


def built(params: Any) -> list[str]:
    """The modes of ``selfflow_modes`` whose published weights are current."""
    from flowmod import dag

    return [m for m in params.selfflow_modes if dag.current(params, dag.Node("selfflow", None, m))]


# --- the chapter's tables and figures ---------------------------------------------------------

def results(params: Any, mode: str) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The published history and ``eval.json`` of ``selfflow[<mode>]``."""
    import json

    from flowmod import dag

    folder = dag.published(params, dag.Node("selfflow", None, mode))
    return (pd.read_csv(folder / "history.csv"),
            json.loads((folder / "eval.json").read_text()))


def weights_path(params: Any, mode: str) -> Path:
    """The published FastFlowNet checkpoint of ``mode`` (a ``fastflownet_weights`` value)."""
    from flowmod import dag

    return dag.published(params, dag.Node("selfflow", None, mode)) / "weights.pt"


def epe_table(params: Any, done: list[str]) -> pd.DataFrame:
    """Held-out end-point error and Fl-all, overall and inside the target vehicles' boxes, of
    the baselines and of each trained network (one row each), with seconds per pair on this
    machine (the baselines of the first mode's evaluation: the same pairs for every mode)."""
    rows = []
    for k, mode in enumerate(done):
        _, ev = results(params, mode)
        base = ev["baselines"]
        order = ("zero flow", "farneback", f"dis ({DIS_PRESET})")
        named = ({n: base[n] for n in order} if k == 0 else {}) | {
            f"fastflownet ({mode})": ev["fastflownet"]}
        for name, m in named.items():
            rows.append({"method": name, "EPE (px)": round(m["epe"], 2),
                         "EPE in boxes (px)": round(m["epe_boxes"], 2),
                         "Fl-all (%)": round(m["fl_all"], 1),
                         "Fl-all in boxes (%)": round(m["fl_all_boxes"], 1),
                         "s / pair": round(m["seconds_per_pair"], 2)})
    return pd.DataFrame(rows)


def budget_table(params: Any, done: list[str]) -> pd.DataFrame:
    """What the CPU budget bought per mode: steps, pairs seen, seconds per step (median) and
    the training time."""
    rows = []
    for mode in done:
        hist, ev = results(params, mode)
        rows.append({"mode": mode, "steps": ev["steps"],
                     "pairs seen": ev["steps"] * params.selfflow_batch,
                     "training pairs": ev["train_pairs"],
                     "s / step": round(ev["seconds_per_step"], 2),
                     "training (min)": round(float(hist["seconds"].sum()) / 60, 1)})
    return pd.DataFrame(rows)


def beats_dis(params: Any, done: list[str]) -> list[str]:
    """The modes whose network has a lower held-out EPE than DIS."""
    out = []
    for mode in done:
        _, ev = results(params, mode)
        if ev["fastflownet"]["epe"] < ev["baselines"][f"dis ({DIS_PRESET})"]["epe"]:
            out.append(mode)
    return out


def table3_note(params: Any, done: list[str]) -> str:
    """Whether a trained network becomes Table 3's ``fastflownet`` row, and how."""
    if not done:
        return "No network is trained yet, so Table 3 has no `fastflownet` row from here."
    better = beats_dis(params, done)
    if not better:
        return ("No trained network beats DIS on the held-out end-point error, so Table 3 "
                "keeps its rows: a `fastflownet` row from these weights would only show a "
                "flow worse than the classical baseline's.")
    path = weights_path(params, better[0])
    return (f"The {better[0]} network beats DIS on the held-out end-point error: Table 3 gains "
            f"its `fastflownet` row with `make book SET=\"flow_networks=[fastflownet] "
            f"fastflownet_weights={path}\"`.")


def headline(params: Any, done: list[str]) -> str:
    """One sentence for the landing page: held-out EPE of each trained network against DIS,
    or how to build them."""
    if not params.selfflow_modes:
        return "not part of this profile (selfflow_modes is empty)"
    if not done:
        return ("not trained in this run (make selfflow trains FastFlowNet from scratch: "
                f"{len(params.selfflow_modes)} x {params.selfflow_iters} steps)")
    parts, dis = [], None
    for mode in done:
        hist, ev = results(params, mode)
        dis = ev["baselines"][f"dis ({DIS_PRESET})"]["epe"]
        parts.append(f"{ev['fastflownet']['epe']:.1f} px ({mode}, {ev['steps']} steps)")
    return (f"FastFlowNet trained from scratch on this machine reaches a held-out end-point "
            f"error of {' and '.join(parts)} against DIS's {dis:.1f} px")


def example(params: Any, done: list[str], k: int = 0
            ) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray | None]:
    """Held-out pair ``k``: frame 1 (BGR), the flows of the exact flow (where there is one),
    DIS and each trained network at full size, and the valid mask, for
    :func:`flowmod.report.viz.flow_figure`."""
    from flowmod import dag, world

    sel = dag.published(params, dag.Node("select"))
    pairs = pd.read_parquet(sel / "pairs.parquet")
    test = heldout_pairs(pairs, params.selfflow_eval_pairs, params.seed).iloc[[k]]
    synthetic = world.is_synthetic(params.dataroot_path, params.version)
    h = held_out(test, pd.read_parquet(sel / "objects.parquet"), params.dataroot_path,
                 params.version, synthetic)
    flows = {"exact": h.gt[0]} if h.gt else {}
    flows[f"dis ({DIS_PRESET})"] = DISFlow(DIS_PRESET, scale=params.flow_scale).estimate(
        h.img1[0], h.img2[0])
    for mode in done:
        est = FastFlowNetFlow(weights_path(params, mode), device="cpu", scale=params.flow_scale)
        flows[f"fastflownet ({mode})"] = est.estimate(h.img1[0], h.img2[0])
    return h.img1[0], flows, (h.valid[0] if h.valid else None)


def built_note(params: Any, done: list[str]) -> str:
    """A line for the chapter: which networks are trained, and how to train the others."""
    if not params.selfflow_modes:
        return ("This profile trains no flow network (`selfflow_modes` is empty). Set it (e.g. "
                "`selfflow_modes=[photometric]`) and run `make selfflow`.")
    from flowmod import dag

    todo = [m for m in params.selfflow_modes if m not in done]
    return dag.built_note("Networks trained", done, len(params.selfflow_modes),
                          f"{', '.join(todo)}; {params.selfflow_iters} steps each",
                          "selfflow_build")
