"""Which part of a flow method's error reaches the classifier? (issue 52, item 2, first look)

    .venv/bin/python benchmarks/bench_flow_errors.py [--profile demo] [--run-dir runs/demo]

Reads a built run (``make book`` first; chapter 10's still-world crops must be built, as in
the demo and classroom profiles): for every estimated flow method, the keyframe crops of
every fold against the exact flow's crops of the same objects and the still-world flow of
their windows (``extensions/context/keyframe/<split>.static.npy``: the flow each vehicle
would have standing still). Per object, over the pixels of its 2D box (chapter 07's mask):

* ``epe_box``, ``epe_ring``: mean end-point error (px) inside the box and around it;
* ``motion``: the exact flow minus the still-world flow, averaged in the box (px): the
  independent motion the classifier must see (0 for a still vehicle, up to noise);
* ``seen``: the method's flow minus the still-world flow, averaged in the box (px);
* ``contrast``: the method's box-mean flow minus its ring-mean flow (px): what a reader
  of the crop alone, without the oracle's still-world flow, could compare;
* ``recovered``: the share of the motion the method keeps, ``seen . motion / |motion|^2``
  (movers with ``|motion|`` >= 0.25 px only);
* ``bias_along``, ``bias_across``: the box-mean error resolved along the motion's direction
  and across it (px); ``scatter``: the mean distance of the box's errors from their mean.

And per method, how well ``|seen|`` alone separates moving from still vehicles (ROC AUC,
the motion a rule without learning could read), beside the AUC of the exact flow's own
``|motion|``. Figures only, never asserted; writes ``benchmarks/results/flow_errors.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd
from sklearn.metrics import roc_auc_score

from flowmod.chapters.ch07_evaluation import box_masks
from flowmod.crops import read_crops
from flowmod.params import load_profile

RESULTS = Path(__file__).resolve().parent / "results"
MIN_MOTION = 0.25  # px: movers with less box-mean motion than this give no direction


def per_object(x: np.ndarray, gt: np.ndarray, still: np.ndarray, inside: np.ndarray
               ) -> pd.DataFrame:
    """The per-object measures of the module docstring; arrays (N, 2, S, S) px and the box
    mask (N, S, S)."""
    w = inside[:, None].astype(np.float32)
    npx = np.maximum(inside.sum((1, 2)), 1)[:, None]
    err = x - gt
    epe = np.linalg.norm(err, axis=1)
    ring = ~inside
    motion = ((gt - still) * w).sum((2, 3)) / npx
    seen = ((x - still) * w).sum((2, 3)) / npx
    bias = (err * w).sum((2, 3)) / npx
    scatter = (np.linalg.norm(err - bias[:, :, None, None], axis=1) * inside).sum((1, 2))
    rw = ring[:, None].astype(np.float32)
    rpx = np.maximum(ring.sum((1, 2)), 1)[:, None]
    contrast = (x * w).sum((2, 3)) / npx - (x * rw).sum((2, 3)) / rpx
    norm = np.linalg.norm(motion, axis=1)
    unit = motion / np.maximum(norm, 1e-9)[:, None]
    along = (bias * unit).sum(1)
    return pd.DataFrame({
        "epe_box": (epe * inside).sum((1, 2)) / npx[:, 0],
        "epe_ring": (epe * ring).sum((1, 2)) / np.maximum(ring.sum((1, 2)), 1),
        "motion": norm, "seen": np.linalg.norm(seen, axis=1),
        "recovered": np.where(norm >= MIN_MOTION, (seen * motion).sum(1) / np.maximum(
            norm, 1e-9) ** 2, np.nan),
        "bias_along": np.where(norm >= MIN_MOTION, along, np.nan),
        "bias_across": np.where(norm >= MIN_MOTION, np.abs(unit[:, 0] * bias[:, 1]
                                                          - unit[:, 1] * bias[:, 0]), np.nan),
        "scatter": scatter / npx[:, 0],
        "contrast": np.linalg.norm(contrast, axis=1),
    })


def method_table(run: Path, method: str, folds: int, scale: float) -> pd.DataFrame:
    """Every keyframe object of every fold: :func:`per_object` plus label, scene, distance
    (``method`` may be ``gt``: the reference against itself)."""
    out = []
    for k in range(folds):
        split = f"f{k}"
        x, idx = read_crops(run / "crops" / method / "keyframe", split)
        gt, gidx = read_crops(run / "crops" / "gt" / "keyframe", split)
        ctx = run / "extensions" / "context" / "keyframe"
        cidx = pd.read_parquet(ctx / f"{split}.parquet")
        if not (idx["ann_token"].equals(gidx["ann_token"])
                and idx["ann_token"].equals(cidx["ann_token"])):
            raise SystemExit(f"{method}, {split}: crops and still-world crops disagree")
        still = np.load(ctx / f"{split}.static.npy", mmap_mode="r")
        inside = box_masks(idx, x.shape[-1], scale)
        t = per_object(np.asarray(x, np.float32), np.asarray(gt, np.float32),
                       np.asarray(still, np.float32), inside)
        out.append(t.assign(label=idx["label"].to_numpy(), scene=idx["scene"].to_numpy(),
                            distance=idx["distance"].to_numpy()))
    return pd.concat(out, ignore_index=True)


def summary(t: pd.DataFrame) -> dict[str, float]:
    """Medians over objects (movers where a measure needs a motion) and the AUCs."""
    movers = t[t["label"] == 1]
    return {
        "objects": len(t), "movers": len(movers),
        "epe_box_median": t["epe_box"].median(), "epe_ring_median": t["epe_ring"].median(),
        "recovered_median_movers": movers["recovered"].median(),
        "bias_along_median_movers": movers["bias_along"].median(),
        "bias_across_median_movers": movers["bias_across"].median(),
        "scatter_median": t["scatter"].median(),
        "seen_median_still": t.loc[t["label"] == 0, "seen"].median(),
        "seen_median_movers": movers["seen"].median(),
        "auc_seen": roc_auc_score(t["label"], t["seen"]),
        "auc_exact_motion": roc_auc_score(t["label"], t["motion"]),
        "auc_contrast": roc_auc_score(t["label"], t["contrast"]),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="demo")
    ap.add_argument("--run-dir", default=None, help="the run folder (default: the profile's)")
    args = ap.parse_args(argv)
    p = load_profile(args.profile)
    run = Path(args.run_dir) if args.run_dir else p.run_path
    out = {}
    for m in p.flow_methods:  # gt: the reference itself (no error, every motion seen)
        out[m] = summary(method_table(run, m, p.folds, p.crop_scale))
    frame = pd.DataFrame(out).T
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(frame.round(3))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"flow_errors-{args.profile}.json").write_text(
        json.dumps({m: {k: float(v) for k, v in d.items()} for m, d in out.items()}, indent=2)
        + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
