"""Seconds per training step of chapter 12's FastFlowNet, apart from the rest of its stage.

    .venv/bin/python benchmarks/bench_selfflow.py [--device cpu|cuda] [--repeat N]

Times one optimiser step (forward, loss, backward, Adam) of the photometric (census phase)
and the supervised loss on random images at the demo's input size and batch, and at the
paper profile's (skipped on CPU: minutes a step); the held-out inference of one 1600 x 900
pair at flow_scale 0.5; and one supervised step of torchvision's RAFT-small (what training
it like the shipped FastFlowNet would cost). Writes
``benchmarks/results/selfflow_<device>.json``. Figures only, never asserted: the machine is
noisy (2-4x swings); compare them as ratios (photometric / supervised, RAFT-small /
FastFlowNet, this machine / a GPU).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import numpy as np
import torch

from flowmod.artefacts import write_json
from flowmod.environment import resolve_device
from flowmod.flow import selftrain
from flowmod.flow.architectures import FastFlowNet
from flowmod.flow.networks import FastFlowNetFlow
from flowmod.params import load_profile
from flowmod.paths import repo_root


def step_seconds(mode: str, batch: int, crop: tuple[int, int], dev: torch.device,
                 repeat: int) -> float:
    """Median seconds of one training step (after a warm-up step)."""
    torch.manual_seed(0)
    model = FastFlowNet().to(dev)
    opt = torch.optim.Adam(model.parameters(), lr=3e-4)
    g = torch.Generator().manual_seed(0)
    h, w = crop
    x1 = (255 * torch.rand(batch, 3, h, w, generator=g)).to(dev)
    x2 = (255 * torch.rand(batch, 3, h, w, generator=g)).to(dev)
    gt = (5 * torch.randn(batch, 2, h, w, generator=g)).to(dev)
    valid = torch.ones(batch, 1, h, w, device=dev)
    times = []
    for k in range(repeat + 1):
        if dev.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        loss = selftrain.step_loss(model, {"img1": x1, "img2": x2, "gt": gt, "valid": valid},
                                   mode, 2.0, warm=False)[0]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if dev.type == "cuda":
            torch.cuda.synchronize()
        if k:
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def raft_small_step_seconds(batch: int, crop: tuple[int, int], dev: torch.device,
                            repeat: int, updates: int = 12) -> float:
    """Median seconds of one supervised RAFT-small step (torchvision's, from scratch; L1 on
    every update's flow, weights 0.8^k as RAFT's sequence loss), the cost of training it the
    way the shipped FastFlowNet was (issue 23's optional RAFT)."""
    from torchvision.models.optical_flow import raft_small

    torch.manual_seed(0)
    model = raft_small(weights=None).to(dev).train()
    opt = torch.optim.AdamW(model.parameters(), lr=4e-4)
    g = torch.Generator().manual_seed(0)
    x1, x2 = (2 * torch.rand(batch, 3, *crop, generator=g) - 1 for _ in range(2))
    gt = 5 * torch.randn(batch, 2, *crop, generator=g)
    x1, x2, gt = x1.to(dev), x2.to(dev), gt.to(dev)
    times = []
    for k in range(repeat + 1):
        t0 = time.perf_counter()
        preds = model(x1, x2, num_flow_updates=updates)
        loss = sum(0.8 ** (len(preds) - 1 - i) * (f - gt).abs().mean()
                   for i, f in enumerate(preds))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if dev.type == "cuda":
            torch.cuda.synchronize()
        if k:
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    dev = resolve_device(args.device)
    demo, paper = load_profile("demo"), load_profile("paper", dataroot="/unused")
    settings = {"demo": (demo.selfflow_batch, tuple(demo.selfflow_crop))}
    if dev.type == "cuda":
        settings["paper"] = (paper.selfflow_batch, tuple(paper.selfflow_crop))
    out: dict = {"device": str(dev), "machine": platform.processor() or platform.machine(),
                 "torch_threads": torch.get_num_threads(), "steps": {}}
    for name, (batch, crop) in settings.items():
        for mode in ("photometric", "supervised"):  # finetune's step is photometric's
            s = step_seconds(mode, batch, crop, dev, args.repeat)
            out["steps"][f"{name} {mode} (batch {batch}, {crop[0]}x{crop[1]})"] = {
                "s_per_step": s, "pairs_per_s": batch / s}
    batch, crop = settings["demo"]
    s = raft_small_step_seconds(batch, crop, dev, max(1, args.repeat // 2))
    out["steps"][f"demo raft_small supervised (batch {batch}, {crop[0]}x{crop[1]}, 12 updates)"] = {
        "s_per_step": s, "pairs_per_s": batch / s}
    rng = np.random.default_rng(0)
    img1 = rng.integers(0, 256, (900, 1600, 3), dtype=np.uint8)
    img2 = np.roll(img1, 3, axis=1)
    est = FastFlowNetFlow(model=FastFlowNet(), device=dev, scale=0.5)
    est.estimate(img1, img2)  # warm-up
    t0 = time.perf_counter()
    for _ in range(args.repeat):
        est.estimate(img1, img2)
    out["inference_s_per_pair_1600x900_scale_0.5"] = (time.perf_counter() - t0) / args.repeat
    steps = out["steps"]
    demo_steps = [v["s_per_step"] for k, v in steps.items()
                  if k.startswith("demo") and "raft" not in k]
    out["demo_budget_min"] = demo.selfflow_iters * sum(demo_steps) / 60
    if "paper" in " ".join(steps):
        out["paper_budget_h"] = paper.selfflow_iters * next(
            v["s_per_step"] for k, v in steps.items() if k.startswith("paper photometric")) / 3600
    res = repo_root() / "benchmarks" / "results"
    res.mkdir(parents=True, exist_ok=True)
    write_json(res / f"selfflow_{dev.type}.json", out)
    import json

    print(json.dumps(out, indent=2, default=lambda v: round(v, 3)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
