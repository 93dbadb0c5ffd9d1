"""Throughput of the learning stages: cropping, loading, training, inference; disk per object.

    .venv/bin/python benchmarks/bench_learning.py [--quick] [--threads N]

Writes ``benchmarks/results/learning.json``. Figures only, never asserted: the machine is
shared and noisy (2-4x swings), so read them as orders of magnitude.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from flowmod.artefacts import write_json
from flowmod.crops import crop_boxes, hflip
from flowmod.model import motion_resnet18
from flowmod.train import CropDataset

FRAME_W, FRAME_H = 1600, 900


def _boxes(rng: np.random.Generator, n: int) -> np.ndarray:
    """Vehicle boxes like Table 1's (30-70 m): 20-150 px wide, some at the border."""
    w = rng.uniform(20, 150, n)
    h = w * rng.uniform(0.5, 1.0, n)
    x1 = rng.uniform(-0.2 * w, FRAME_W - 0.8 * w)
    y1 = rng.uniform(350, 600, n)
    return np.stack([x1, y1, x1 + w, y1 + h], axis=1)


def _median_time(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_crops(sizes: list[int], tmp: Path, repeat: int) -> dict:
    rng = np.random.default_rng(0)
    flow16 = rng.normal(0, 3, (FRAME_H, FRAME_W, 2)).astype(np.float16)
    path = tmp / "flow.npy"
    np.save(path, flow16)
    boxes = _boxes(rng, 8)  # objects per frame pair
    flow32 = flow16.astype(np.float32)
    out = {"boxes_per_frame": len(boxes)}
    load_s = _median_time(lambda: np.load(path).astype(np.float32), repeat)
    out["flow_load_s_per_pair"] = load_s
    for s in sizes:
        crop_s = _median_time(lambda s=s: crop_boxes(flow32, boxes, s, 3.0), repeat)
        out[f"S{s}"] = {
            "crops_per_s_in_memory": len(boxes) / crop_s,
            "crops_per_s_with_flow_load": len(boxes) / (crop_s + load_s),
        }
    return out


def bench_loader_and_training(size: int, n: int, batch: int, steps: int, tmp: Path) -> dict:
    rng = np.random.default_rng(1)
    arr = np.lib.format.open_memmap(tmp / f"crops{size}.npy", mode="w+", dtype=np.float16,
                                    shape=(n, 2, size, size))
    arr[:] = rng.normal(0, 2, arr.shape).astype(np.float16)
    arr.flush()
    x = np.load(tmp / f"crops{size}.npy", mmap_mode="r")
    y = (np.arange(n) % 2).astype(np.float32)
    ds = CropDataset(x, y)
    perm = rng.permutation(n)
    batches = [np.sort(perm[a : a + batch]) for a in range(0, n - batch + 1, batch)]

    def load_all() -> None:
        for b in batches:
            xb, _ = ds[b]
            mask = torch.rand(len(b)) < 0.5
            xb[mask] = hflip(xb[mask])
            xb.contiguous(memory_format=torch.channels_last)

    load_s = _median_time(load_all, 3)
    res = {"n": n, "batch": batch,
           "loader_samples_per_s": len(batches) * batch / load_s}

    torch.manual_seed(0)
    model = motion_resnet18().to(memory_format=torch.channels_last)
    opt = torch.optim.SGD(model.parameters(), lr=0.01, momentum=0.9, weight_decay=0.01)
    loss_fn = torch.nn.BCEWithLogitsLoss()
    xb, yb = ds[batches[0]]
    xb = xb.float().contiguous(memory_format=torch.channels_last)

    for amp in (None, "bf16"):
        def step(amp=amp) -> None:
            opt.zero_grad(set_to_none=True)
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp is not None):
                logits = model(xb).reshape(-1)
            loss_fn(logits.float(), yb).backward()
            opt.step()

        step()  # warm-up
        train_s = _median_time(step, steps)
        model.eval()
        with torch.inference_mode():
            def infer(amp=amp) -> None:
                with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp is not None):
                    model(xb)

            infer()
            infer_s = _median_time(infer, steps)
        model.train()
        key = "fp32" if amp is None else amp
        res[f"train_samples_per_s_{key}"] = batch / train_s
        res[f"inference_samples_per_s_{key}"] = batch / infer_s
    return res


def bench_train_model(size: int, n: int, tmp: Path) -> dict:
    """One epoch of train_model (batch 128, flips, validation on n // 4) end to end."""
    import pandas as pd

    from flowmod.train import train_model

    rng = np.random.default_rng(2)
    y = np.arange(n) % 2
    x = rng.normal(0, 2, (n, 2, size, size)).astype(np.float16)
    df = pd.DataFrame({"label": y})
    nv = n // 4
    t0 = time.perf_counter()
    hist = train_model(x, df, x[:nv], df.iloc[:nv], tmp / f"train{size}", epochs=1,
                       batch_size=128, device="cpu", progress=False)
    wall = time.perf_counter() - t0
    return {"n_train": n, "n_val": nv, "epoch_seconds": float(hist["seconds"].iloc[0]),
            "wall_seconds_incl_setup": wall,
            "train_plus_val_samples_per_s": (n + nv) / float(hist["seconds"].iloc[0])}


def disk_per_object(sizes: list[int]) -> dict:
    frame = FRAME_W * FRAME_H * 2 * 4  # the original: full-frame float32 flow per pair
    out = {"original_full_frame_float32_bytes_per_pair": frame}
    for s in sizes:
        crop = 2 * s * s * 2  # float16
        out[f"crop_S{s}_float16_bytes_per_object"] = crop
        out[f"crop_S{s}_objects_per_full_frame"] = frame / crop
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats and samples")
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "learning.json"))
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    sizes = [64, 224]
    repeat = 3 if args.quick else 7
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        result = {
            "machine": {"platform": platform.platform(), "torch": torch.__version__,
                        "threads": torch.get_num_threads(), "processor": platform.processor()},
            "crops": bench_crops(sizes, tmp, repeat),
            "S64": bench_loader_and_training(64, 512 if args.quick else 2048, 32,
                                             3 if args.quick else 5, tmp),
            "S224": bench_loader_and_training(224, 128 if args.quick else 512, 32,
                                              2 if args.quick else 3, tmp),
            "train_model_S64": bench_train_model(64, 512 if args.quick else 1024, tmp),
            "disk": disk_per_object(sizes),
        }
    write_json(args.out, result)
    import json

    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
