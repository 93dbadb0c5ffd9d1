"""Is training the demo's classifiers arithmetic-bound? (issue 49, item 2)

    .venv/bin/python benchmarks/bench_train_stack.py [--steps 20]

Measures, for the demo network (ResNet18 of width 32, 40 px crops, batches of 32, SGD):
its FLOPs per training step (``torch.utils.flop_counter``) and the machine's rate on it,
against a 2048 x 2048 matmul's rate (what the cores can do); one step on a batch 3x as
large (the most that stacking 3 seeds into one larger computation could save); and K
independent models stacked as one network with grouped convolutions (``groups=K``: each
model its own weights, its own batch norm and its own data), per model-step, K = 1, 2, 3, 6.
Run it alone (never beside another torch process). Figures only, never asserted; results
go to ``benchmarks/results/train_stack.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from flowmod.model import motion_resnet18

RESULTS = Path(__file__).resolve().parent / "results"
CL = torch.channels_last


def _ms_per_call(fn, n: int, warm: int = 3) -> float:
    for _ in range(warm):
        fn()
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n * 1000


def _stepper(model: nn.Module, x: torch.Tensor, y: torch.Tensor):
    opt = torch.optim.SGD(model.parameters(), lr=0.01, momentum=0.9, weight_decay=0.01)

    def step() -> None:
        opt.zero_grad()
        logits = model(x).reshape(y.shape)
        F.binary_cross_entropy_with_logits(logits, y, reduction="none").mean(0).sum().backward()
        opt.step()
    return step


class _Block(nn.Module):
    """ResNet's BasicBlock for K models side by side (grouped convolutions)."""

    def __init__(self, cin: int, cout: int, stride: int, k: int) -> None:
        super().__init__()
        self.c1 = nn.Conv2d(cin * k, cout * k, 3, stride, 1, bias=False, groups=k)
        self.b1 = nn.BatchNorm2d(cout * k)
        self.c2 = nn.Conv2d(cout * k, cout * k, 3, 1, 1, bias=False, groups=k)
        self.b2 = nn.BatchNorm2d(cout * k)
        self.down = None if stride == 1 and cin == cout else nn.Sequential(
            nn.Conv2d(cin * k, cout * k, 1, stride, bias=False, groups=k), nn.BatchNorm2d(cout * k))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.b2(self.c2(F.relu(self.b1(self.c1(x)))))
        return F.relu(out + (x if self.down is None else self.down(x)))


class Stacked(nn.Module):
    """K ResNet18s of width ``w`` as one network: input (B, 2K, S, S) -> logits (B, K)."""

    def __init__(self, k: int, w: int = 32) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(2 * k, w * k, 7, 2, 3, bias=False, groups=k)
        self.bn1 = nn.BatchNorm2d(w * k)
        blocks, cin = [], w
        for i, planes in enumerate((w, 2 * w, 4 * w, 8 * w)):
            blocks += [_Block(cin, planes, 1 if i == 0 else 2, k), _Block(planes, planes, 1, k)]
            cin = planes
        self.layers = nn.Sequential(*blocks)
        self.fc = nn.Conv2d(8 * w * k, k, 1, groups=k)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.max_pool2d(F.relu(self.bn1(self.conv1(x))), 3, 2, 1)
        x = F.adaptive_avg_pool2d(self.layers(x), 1)
        return self.fc(x).flatten(1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20)
    n = ap.parse_args(argv).steps
    torch.manual_seed(0)
    out: dict[str, float] = {"threads": torch.get_num_threads()}
    model = motion_resnet18(width=32).to(memory_format=CL)
    x, y = torch.randn(32, 2, 40, 40).contiguous(memory_format=CL), torch.rand(32)
    step = _stepper(model, x, y)
    with FlopCounterMode(display=False) as fc:
        step()
    out["gflop_per_step"] = fc.get_total_flops() / 1e9
    out["ms_per_step"] = _ms_per_call(step, n)
    out["gflops_training"] = out["gflop_per_step"] / out["ms_per_step"] * 1000
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    out["gflops_matmul"] = 2 * 2048**3 / _ms_per_call(lambda: a @ b, 10) / 1e6
    x3, y3 = torch.randn(96, 2, 40, 40).contiguous(memory_format=CL), torch.rand(96)
    out["ms_per_step_batch96"] = _ms_per_call(_stepper(model, x3, y3), n)
    for k in (1, 2, 3, 6):
        net = Stacked(k).to(memory_format=CL)
        xk = torch.randn(32, 2 * k, 40, 40).contiguous(memory_format=CL)
        out[f"ms_per_model_step_grouped_k{k}"] = _ms_per_call(
            _stepper(net, xk, torch.rand(32, k)), n) / k
    for key, v in out.items():
        print(f"{key}: {v:.1f}")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "train_stack.json").write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
