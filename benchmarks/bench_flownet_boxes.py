"""Where the shipped FastFlowNet loses to DIS inside far vehicle boxes.

    .venv/bin/python benchmarks/bench_flownet_boxes.py [--weights weights/fastflownet_synth/weights.pt]
        [--data data/pretrain] [--scales 0.5,0.75,1.0]

On the pretraining recipe's validation pairs (``flowmod.flow.pretrain.validation_set``: the
24 keyframe pairs of its validation scenes, the world ``make flownet`` generates under
``--data``), three measurements, each against DIS (medium) on the same pairs:

* per far box (the 30-70 m vehicles of Table 1), both methods at the frame scale the
  weights were last trained at (their manifest's ``scale``): the mean and the median pixel
  EPE of each method, grouped into quartiles of the box's median exact motion (px): is the
  gap a few large-motion failures or a floor at every motion? And the per-pair box EPE
  difference, FastFlowNet minus DIS, with a 95 % interval over the validation scenes;
* the resolution floor: the exact flow averaged over cells of 2, 4 and 8 px and bilinearly
  upsampled, scored like a method (FastFlowNet predicts at 1/4 of its input: at scale 0.5
  cells of 8 px of the full frame, at 0.75 of 5.3 px);
* the inference scale: both methods at each of ``--scales``.

Prints the tables and writes ``benchmarks/results/flownet_boxes.json``. Measures only.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from flowmod.flow.estimators import DISFlow
from flowmod.flow.metrics import flow_metrics
from flowmod.flow.networks import FastFlowNetFlow
from flowmod.flow.pretrain import (
    Recipe,
    ensure_world,
    load_half,
    scene_frames,
    scene_split,
    validation_set,
)
from flowmod.flow.selftrain import HeldOut, score
from flowmod.metrics import group_mean_bootstrap

ROOT = Path(__file__).resolve().parents[1]


def per_box(fa: np.ndarray, fb: np.ndarray, gt: np.ndarray, valid: np.ndarray,
            boxes: np.ndarray) -> list[tuple[float, float, float, float, float]]:
    """Per box (N, 4) px: (median exact motion px, mean EPE a, mean EPE b, median EPE a,
    median EPE b) over its valid pixels; boxes without valid pixels are left out."""
    rows = []
    for x0, y0, x1, y1 in np.round(boxes).astype(int):
        sl = (slice(max(y0, 0), y1), slice(max(x0, 0), x1))
        v = valid[sl]
        if not v.any():
            continue
        ea = np.linalg.norm(fa[sl] - gt[sl], axis=-1)[v]
        eb = np.linalg.norm(fb[sl] - gt[sl], axis=-1)[v]
        motion = float(np.median(np.linalg.norm(gt[sl], axis=-1)[v]))
        rows.append((motion, float(ea.mean()), float(eb.mean()), float(np.median(ea)),
                     float(np.median(eb))))
    return rows


def quartiles(rows: list[tuple[float, ...]]) -> list[dict[str, float]]:
    """The per-box rows in four groups of rising motion: range, means and medians."""
    a = np.array(rows)
    out = []
    for q in np.array_split(np.argsort(a[:, 0]), 4):
        s = a[q]
        out.append({"motion_px": [round(s[:, 0].min(), 1), round(s[:, 0].max(), 1)],
                    "boxes": len(q), "ffn_mean": s[:, 1].mean(), "dis_mean": s[:, 2].mean(),
                    "ffn_median": float(np.median(s[:, 3])),
                    "dis_median": float(np.median(s[:, 4]))})
    return out


def resolution_floor(h: HeldOut, cell: int) -> dict[str, float]:
    """:func:`score` of the exact flow averaged over ``cell`` px cells and upsampled back."""
    def coarse(k: int) -> np.ndarray:
        g = h.gt[k]
        small = cv2.resize(g, (g.shape[1] // cell, g.shape[0] // cell),
                           interpolation=cv2.INTER_AREA)
        return cv2.resize(small, (g.shape[1], g.shape[0]), interpolation=cv2.INTER_LINEAR)
    rows = [flow_metrics(coarse(k), h.gt[k], h.valid[k], h.boxes[k]) for k in range(len(h.gt))]
    return {k: float(np.nanmean([r[k] for r in rows])) for k in ("epe", "epe_boxes")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--weights", default=str(ROOT / "weights/fastflownet_synth/weights.pt"))
    ap.add_argument("--data", default=str(ROOT / "data/pretrain"))
    ap.add_argument("--scales", default="0.5,0.75,1.0")
    a = ap.parse_args()
    torch.set_num_threads(2)
    r = Recipe()
    _, root = ensure_world(r, Path(a.data).resolve(), progress=False)
    version = r.world_params(str(root)).version
    h = validation_set(r, root, scene_split(list(scene_frames(root, version)), r.val_every))
    model = load_half(Path(a.weights))
    manifest = Path(a.weights).with_name("manifest.json")
    scale = json.loads(manifest.read_text()).get("scale", r.scale) if manifest.is_file() \
        else r.scale
    ffn = FastFlowNetFlow(model=model, device=torch.device("cpu"), scale=scale)
    dis = DISFlow("medium", scale=scale)
    rows, diff = [], []
    for k in range(len(h.img1)):
        fa, fb = ffn.estimate(h.img1[k], h.img2[k]), dis.estimate(h.img1[k], h.img2[k])
        rows += per_box(fa, fb, h.gt[k], h.valid[k], h.boxes[k])
        diff.append(flow_metrics(fa, h.gt[k], h.valid[k], h.boxes[k])["epe_boxes"]
                    - flow_metrics(fb, h.gt[k], h.valid[k], h.boxes[k])["epe_boxes"])
    reps = group_mean_bootstrap(diff, h.scenes, seed=23)
    out = {"weights": a.weights, "scale": scale, "pairs": len(h.img1), "boxes": len(rows),
           "quartiles": quartiles(rows),
           "paired_box_epe": {"ffn_minus_dis": float(np.nanmean(diff)),
                              "ci95_over_scenes": np.nanpercentile(reps, [2.5, 97.5]).tolist(),
                              "scenes": len(set(h.scenes))},
           "resolution_floor": {c: resolution_floor(h, c) for c in (2, 4, 8)}, "scales": {}}
    for s in (float(x) for x in a.scales.split(",")):
        t0 = time.perf_counter()
        est = FastFlowNetFlow(model=model, device=torch.device("cpu"), scale=s)
        out["scales"][s] = {"fastflownet": score(est.estimate, h),
                            "dis": score(DISFlow("medium", scale=s).estimate, h),
                            "seconds": time.perf_counter() - t0}
    print(f"{out['boxes']} far boxes on {out['pairs']} pairs, both methods at scale {scale}; "
          "box EPE px by motion quartile:")
    for q in out["quartiles"]:
        print(f"  motion {q['motion_px'][0]}-{q['motion_px'][1]} px: mean FFN "
              f"{q['ffn_mean']:.2f} DIS {q['dis_mean']:.2f}; median FFN {q['ffn_median']:.2f} "
              f"DIS {q['dis_median']:.2f}")
    d = out["paired_box_epe"]
    print(f"box EPE per pair, FFN - DIS: {d['ffn_minus_dis']:+.2f} px (95 % over the "
          f"{d['scenes']} scenes {d['ci95_over_scenes'][0]:+.2f} to "
          f"{d['ci95_over_scenes'][1]:+.2f})")
    for c, v in out["resolution_floor"].items():
        print(f"exact flow through {c} px cells: EPE {v['epe']:.2f}, box EPE {v['epe_boxes']:.2f}")
    for s, v in out["scales"].items():
        print(f"scale {s}: FFN EPE {v['fastflownet']['epe']:.2f} box {v['fastflownet']['epe_boxes']:.2f}"
              f" | DIS EPE {v['dis']['epe']:.2f} box {v['dis']['epe_boxes']:.2f}")
    res = ROOT / "benchmarks/results"
    res.mkdir(parents=True, exist_ok=True)
    (res / "flownet_boxes.json").write_text(json.dumps(out, indent=1, default=float))


if __name__ == "__main__":
    main()
