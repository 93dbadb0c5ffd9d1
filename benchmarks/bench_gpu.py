"""What a GPU buys this study: flow per method and batch, training crops/s, a demo chain.

    .venv/bin/python benchmarks/bench_gpu.py [--device cuda] [--out benchmarks/gpu.md]
    .venv/bin/python benchmarks/bench_gpu.py --quick        # CPU, tiny sizes, seconds

One prepared script for a session that is lent a GPU (it fits in about 5 minutes on one
H200; carry ``runs/demo/crops/dis`` for the chain). Three sections, each a table:

1. **Flow**: ms a pair of FastFlowNet (the shipped weights), RAFT-large and RAFT-small
   (random weights: timing only, no accuracy) at 1600 x 900, batch 1, 4 and 16, at
   ``flow_scale`` 1 and 0.75 (frames and flow resized on the device on CUDA), with the peak
   memory on CUDA.
2. **Training**: crops/s of one epoch of :func:`flowmod.train.train_model` (the book's code,
   crops resident on the device) at 40 px (width 32, batch 32: the demo) and 224 px (width
   64, batch 128: the paper), with and without bf16 autocast.
3. **A demo chain**: the demo's fold-0 DIS model (seed 0) trained on the device with the
   demo's settings, its validation F1 and seconds an epoch beside the published CPU model's
   (its manifest and history); only validation rows are read. Skipped where no published
   demo crops exist.

Writes a dated Markdown report to ``--out`` (default: ``benchmarks/gpu.md`` on CUDA,
``benchmarks/results/gpu-<device>.md`` elsewhere, so a CPU run never overwrites the GPU
record). Reported, never asserted; ``make test`` runs ``--quick`` on the CPU.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from flowmod import pipeline
from flowmod.artefacts import atomic_path, read_manifest
from flowmod.crops import fold_crops
from flowmod.dag import Node
from flowmod.flow import get_estimator
from flowmod.flow.architectures import build_raft
from flowmod.flow.networks import estimator_options
from flowmod.model import resolve_device
from flowmod.params import load_profile
from flowmod.paths import repo_root
from flowmod.train import TrainSettings, train_model

FULL = (900, 1600)
METHODS = ("fastflownet", "raft_large", "raft_small")
QUICK = {"frame": (48, 64), "batches": [1, 2], "scales": [1.0, 0.75], "repeat": 1,
         "methods": ("fastflownet", "raft_small"), "updates": 2,
         "train": [(16, 8, 16, 64)], "amps": [None]}
REAL = {"frame": FULL, "batches": [1, 4, 16], "scales": [1.0, 0.75], "repeat": 5,
        "methods": METHODS, "updates": None,
        "train": [(40, 32, 32, 8192), (224, 64, 128, 4096)], "amps": [None, "bf16"]}


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _frames(shape: tuple[int, int], n: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """``n`` textured BGR pairs (H, W, 3) uint8, the second shifted 3 px right."""
    rng = np.random.default_rng(0)
    base = rng.integers(10, 245, (n, shape[0], shape[1] + 3, 3), dtype=np.uint8)
    return [b[:, 3:] for b in base], [b[:, :-3] for b in base]


def _estimator(method: str, dev: torch.device, scale: float, batch: int,
               updates: int | None = None) -> Any:
    """The method's estimator; RAFT with ``updates`` flow updates (default 20 / 12)."""
    if method == "fastflownet":
        opts = estimator_options(load_profile("demo"), "fastflownet")
        return get_estimator("fastflownet", weights=opts["weights"], device=dev, scale=scale,
                             batch_size=batch)
    name = "raft" if method == "raft_large" else "raft_small"
    return get_estimator(name, model=build_raft(method), device=dev, scale=scale,
                         batch_size=batch,
                         num_flow_updates=updates or (20 if name == "raft" else 12))


def bench_flow(dev: torch.device, cfg: dict) -> pd.DataFrame:
    """ms a pair per method, batch and scale (median of ``repeat`` batches after one)."""
    rows = []
    for method in cfg["methods"]:
        for scale in cfg["scales"]:
            for batch in cfg["batches"]:
                est = _estimator(method, dev, scale, batch, cfg["updates"])
                a, b = _frames(cfg["frame"], batch)
                est.estimate_batch(a, b)  # warm-up (cuDNN autotuning, allocations)
                if dev.type == "cuda":
                    torch.cuda.reset_peak_memory_stats(dev)
                times = []
                for _ in range(cfg["repeat"]):
                    _sync(dev)
                    t0 = time.perf_counter()
                    est.estimate_batch(a, b)
                    _sync(dev)
                    times.append(time.perf_counter() - t0)
                peak = torch.cuda.max_memory_allocated(dev) / 2**30 if dev.type == "cuda" else None
                rows.append({"method": method, "flow_scale": scale, "batch": batch,
                             "ms a pair": round(1000 * statistics.median(times) / batch, 1),
                             "peak GiB": None if peak is None else round(peak, 1)})
                print(rows[-1], flush=True)
                del est
    return pd.DataFrame(rows)


def _crops(n: int, size: int, seed: int) -> tuple[np.ndarray, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    y = np.arange(n) % 2
    x = rng.normal(0, 3, (n, 2, size, size)).astype(np.float32)
    x[y == 1, 0] += 2.0
    return x.astype(np.float16), pd.DataFrame({"label": y})


def bench_training(dev: torch.device, cfg: dict, tmp: Path) -> pd.DataFrame:
    """crops/s of one training epoch (the book's ``train_model``, one epoch, its
    ``seconds``), per crop size, width, batch and autocast."""
    rows = []
    for size, width, batch, n in cfg["train"]:
        tx, tdf = _crops(n, size, 0)
        vx, vdf = _crops(max(batch, 64), size, 1)
        for amp in cfg["amps"]:
            s = TrainSettings(epochs=2, batch_size=batch, width=width, amp=amp or "none",
                              device=dev)
            h = train_model(tx, tdf, vx, vdf, tmp / f"t{size}-{amp}", s, progress=False,
                            resume=False)
            sec = float(h["seconds"].iloc[-1])  # the second epoch: warm
            rows.append({"crop px": size, "width": width, "batch": batch,
                         "autocast": amp or "off", "crops": n, "s an epoch": round(sec, 2),
                         "crops/s": round(n / sec)})
            print(rows[-1], flush=True)
    return pd.DataFrame(rows)


def bench_chain(dev: torch.device, tmp: Path) -> pd.DataFrame | str:
    """The demo's fold-0 DIS model, seed 0, on ``dev`` against the published CPU model."""
    p = load_profile("demo")
    folder = pipeline.published(p, Node("crops", "dis", "keyframe"))
    model = pipeline.published(p, Node("train", "dis", "f0s0" if p.seeds > 1 else "f0"))
    if folder is None or model is None or not (model / "history.csv").is_file():
        return "skipped: no published demo crops and model (run `make book` first)"
    train, val = fold_crops(folder, p.folds, 0, "train"), fold_crops(folder, p.folds, 0, "val")
    t0 = time.perf_counter()
    h = train_model(*train, *val, tmp / "chain", TrainSettings.of(p), device=dev,
                    seed=p.seed, progress=False, resume=False)
    wall = time.perf_counter() - t0
    cpu = pd.read_csv(model / "history.csv")
    rec = read_manifest(model / "manifest.json") or {}
    return pd.DataFrame([
        {"where": f"{dev} (this run)", "val F1 (%)": round(100 * h.attrs["best_f1"], 1),
         "best epoch": h.attrs["best_epoch"], "s an epoch": round(float(h["seconds"].median()), 2),
         "wall s": round(wall, 1)},
        {"where": "cpu (the published model)",
         "val F1 (%)": round(100 * float(rec.get("best_f1", cpu["val_f1"].max())), 1),
         "best epoch": rec.get("best_epoch"), "s an epoch": round(float(cpu["seconds"].median()), 2),
         "wall s": round(float(cpu["seconds"].sum()), 1)}])


def report(dev: torch.device, parts: dict[str, pd.DataFrame | str], seconds: float) -> str:
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor() or "cpu"
    lines = [f"# What a GPU buys: `benchmarks/bench_gpu.py` ({time.strftime('%Y-%m-%d')})", "",
             f"Device: {dev} ({name}), torch {torch.__version__}, {torch.get_num_threads()} "
             f"CPU threads; {seconds:.0f} s in all.", ""]
    for title, part in parts.items():
        lines += [f"## {title}", ""]
        lines += [part if isinstance(part, str) else part.to_markdown(index=False), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--quick", action="store_true", help="tiny sizes: seconds on a CPU")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    dev = resolve_device(args.device)
    cfg = QUICK if args.quick else REAL
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        parts = {"Flow, ms a pair": bench_flow(dev, cfg),
                 "Training, one epoch": bench_training(dev, cfg, Path(tmp)),
                 "A demo chain (DIS, fold 0, seed 0; validation rows only)":
                     bench_chain(dev, Path(tmp)) if not args.quick else "skipped (--quick)"}
    text = report(dev, parts, time.perf_counter() - t0)
    out = args.out or (repo_root() / "benchmarks" / ("gpu.md" if dev.type == "cuda" else
                                                      f"results/gpu-{dev.type}.md"))
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp_out:
        tmp_out.write_text(text)
    print(text)
    print(f"written: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
