"""Crops/s of the training input path alone (no network), issue 40.

    .venv/bin/python benchmarks/bench_loader.py [--size 224] [--n 4096] [--batch 128]
                                                [--workers 0 2] [--quick]

Writes float16 crops (N, 2, S, S) to a memmap in a scratch folder, reads them once (warm
page cache, as in a training epoch after the first) and times every path of
:mod:`flowmod.train` over one epoch's plan (:func:`flowmod.train.epoch_plan`, flips drawn):

- ``streamed, workers=W``: what feeds a GPU: float16 batches gathered from the memmap by a
  DataLoader (``W`` worker processes), :meth:`flowmod.train.StreamedCrops.host_batches`,
  plus one copy of each batch (what pinning it costs on CUDA, where the batch then moves
  and is converted and flipped on the device);
- ``resident, cpu``: :class:`flowmod.train.ResidentCrops` on the CPU: float32 batches with
  the flips applied, the CPU training path's input;
- ``host float32 (before)``: the path before issue 40: numpy gather and float32 conversion
  per batch on the host.

Prints a table and writes ``benchmarks/results/loader.json``. Reported, never asserted.
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import torch

from flowmod.artefacts import write_json
from flowmod.crops import hflip
from flowmod.paths import repo_root
from flowmod.train import CropDataset, ResidentCrops, StreamedCrops, epoch_plan


def make_crops(folder: Path, n: int, size: int) -> np.memmap:
    """A float16 memmap of ``n`` random flow crops (n, 2, size, size), px, read once."""
    arr = np.lib.format.open_memmap(folder / f"crops{size}.npy", mode="w+", dtype=np.float16,
                                    shape=(n, 2, size, size))
    rng = np.random.default_rng(0)
    for a in range(0, n, 256):
        arr[a : a + 256] = rng.normal(0, 5, arr[a : a + 256].shape).astype(np.float16)
    arr.flush()
    x = np.load(folder / f"crops{size}.npy", mmap_mode="r")
    x.sum(dtype=np.float32)  # warm the page cache
    return x


def _flipped(batches: Iterator[tuple[torch.Tensor, torch.Tensor]], flips: np.ndarray
             ) -> Iterator[int]:
    """Apply each batch's flips as the training loop does; yield the batch sizes."""
    pos = 0
    for xb, yb in batches:
        fb = torch.from_numpy(flips[pos : pos + len(yb)])
        pos += len(yb)
        if bool(fb.any()):
            xb[fb] = hflip(xb[fb], (0,))
        yield len(yb)


def _host_float32(x: np.ndarray, y: np.ndarray, plan: list[np.ndarray]
                  ) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    ds = CropDataset(x, y)
    for idx in plan:
        xb, yb = ds[idx]
        yield xb.float(), yb


def paths(x: np.ndarray, y: np.ndarray, workers: list[int]
          ) -> dict[str, Callable[[list[np.ndarray]], Iterator[tuple[torch.Tensor, torch.Tensor]]]]:
    """Every input path by name: plan -> batches."""
    cpu = torch.device("cpu")
    out = {f"streamed float16, workers={w}": StreamedCrops(x, y, cpu, w).host_batches
           for w in workers}
    out["resident, cpu (float32, flipped)"] = ResidentCrops(x, y, cpu).batches
    out["host float32 (before issue 40)"] = lambda plan: _host_float32(x, y, plan)
    return out


def measure(size: int, n: int, batch: int, workers: list[int], tmp: Path, repeat: int) -> list:
    x = make_crops(tmp, n, size)
    y = (np.arange(n) % 2).astype(np.float32)
    rows = []
    for name, fn in paths(x, y, workers).items():
        best = float("inf")
        for r in range(repeat):
            plan, flips = epoch_plan(n, batch, 0.5, 0, r + 1)
            t0 = time.perf_counter()
            if name.startswith("streamed"):  # + the copy into pinned memory a GPU's needs
                seen = sum(len(yb) + 0 * len(xb.clone()) for xb, yb in fn(plan))
            else:
                seen = sum(_flipped(fn(plan), flips))
            best = min(best, time.perf_counter() - t0)
        rows.append({"size": size, "path": name, "crops": seen, "batch": batch,
                     "crops_per_s": round(seen / best)})
        print(rows[-1], flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, nargs="+", default=[224, 40])
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--workers", type=int, nargs="+", default=[0, 2])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="tiny sizes (seconds): a smoke run")
    ap.add_argument("--out", type=Path, default=None, help="JSON path (default results/)")
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.n, args.repeat, args.workers = [16], 256, 1, [0]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.size:
            rows += measure(size, args.n, args.batch, args.workers, Path(tmp), args.repeat)
    out = args.out or repo_root() / "benchmarks" / "results" / "loader.json"
    write_json(out, {"date": time.strftime("%Y-%m-%d"), "machine": platform.machine(),
                     "cores": torch.get_num_threads(), "rows": rows})
    print(f"written: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
