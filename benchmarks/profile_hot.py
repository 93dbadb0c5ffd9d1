"""cProfile of the cold book's hot spots, at the demo profile's settings.

    .venv/bin/python benchmarks/profile_hot.py [--only train,step,world,gt,fastflownet,dis]

One fold's training (a demo-sized training set of random crops: the cost of a step does
not depend on the values), a training step's milliseconds by memory format and threads, one
world scene (generated at the demo's world settings), one
exact-flow pair and one FastFlowNet pair (the shipped weights, the demo's flow scale) on that
scene's frames, one DIS pair for scale. Writes the top functions of each to
``benchmarks/results/profile-<what>.txt`` and a summary to ``benchmarks/results/profile.json``.
Figures only, never asserted: the machine is noisy, read shares, not seconds.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import tempfile
import time
from pathlib import Path

import numpy as np

from flowmod.params import load_profile

RESULTS = Path(__file__).parent / "results"
#: A demo fold's training set: about 2/3 of the demo's keyframe objects, less validation.
N_TRAIN, N_VAL = 1900, 450


def _profiled(name: str, fn, top: int = 25) -> dict:
    """Run ``fn`` under cProfile; write its top ``top`` functions by own time."""
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    fn()
    prof.disable()
    wall = time.perf_counter() - t0
    out = io.StringIO()
    st = pstats.Stats(prof, stream=out)
    st.sort_stats("tottime").print_stats(top)
    st.sort_stats("cumulative").print_stats(top)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"profile-{name}.txt").write_text(f"{name}: {wall:.2f} s wall\n" + out.getvalue())
    print(f"{name}: {wall:.2f} s")
    return {"seconds": round(wall, 3)}


def train_fold() -> None:
    """One demo model: width 32, 40 px crops, batches of 32, 8 epochs."""
    import pandas as pd

    from flowmod.train import TrainSettings, train_model

    demo = load_profile("demo")
    rng = np.random.default_rng(0)
    x = rng.normal(0, 2, (N_TRAIN + N_VAL, 2, demo.crop_size, demo.crop_size)).astype(np.float16)
    y = rng.integers(0, 2, N_TRAIN + N_VAL)
    tr = pd.DataFrame({"label": y[:N_TRAIN]})
    va = pd.DataFrame({"label": y[N_TRAIN:]})
    with tempfile.TemporaryDirectory() as d:
        train_model(x[:N_TRAIN], tr, x[N_TRAIN:], va, d, TrainSettings.of(demo), seed=0,
                    progress=False)


def step_times(n: int = 30) -> dict:
    """ms per training step of the demo network (batch 32, 40 px) with channels-last or
    contiguous memory and 2 or 1 torch threads."""
    import torch

    from flowmod.model import motion_resnet18

    demo = load_profile("demo")
    out, threads = {}, torch.get_num_threads()
    for cl in (True, False):
        for th in (2, 1):
            torch.manual_seed(0)
            torch.set_num_threads(th)
            fmt = torch.channels_last if cl else torch.contiguous_format
            m = motion_resnet18(width=demo.model_width).to(memory_format=fmt)
            x = torch.randn(demo.batch_size, 2, demo.crop_size, demo.crop_size).contiguous(
                memory_format=fmt)
            y = torch.rand(demo.batch_size)
            opt = torch.optim.SGD(m.parameters(), lr=0.01, momentum=0.9, weight_decay=0.01)
            for i in range(n + 5):
                if i == 5:
                    t0 = time.perf_counter()
                opt.zero_grad()
                torch.nn.functional.binary_cross_entropy_with_logits(m(x).reshape(-1), y).backward()
                opt.step()
            key = f"{'channels_last' if cl else 'contiguous'}, {th} thread(s)"
            out[key] = round((time.perf_counter() - t0) / n * 1000, 1)
            print(f"{key}: {out[key]} ms/step")
    torch.set_num_threads(threads)
    return out


def world_scene(root: Path) -> None:
    """One scene at the demo's world settings (keyframes, vehicles), no sweeps."""
    from flowmod.world import generate_world

    demo = load_profile("demo")
    generate_world(root, "v1.0-synth", n_scenes=1, n_keyframes=demo.world_keyframes,
                   n_sweep_scenes=0, vehicles_per_scene=demo.world_vehicles, seed=demo.seed,
                   n_jobs=1, progress=False)


def first_pair(root: Path) -> tuple[str, str, Path, Path]:
    """The first two CAM_FRONT keyframes of the world at ``root``: tokens and image paths."""
    sd = json.loads((root / "v1.0-synth" / "sample_data.json").read_text())
    frames = sorted((r for r in sd if r["is_key_frame"] and "CAM_FRONT" in r["filename"]),
                    key=lambda r: r["timestamp"])[:2]
    return (frames[0]["token"], frames[1]["token"], root / frames[0]["filename"],
            root / frames[1]["filename"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="train,step,world,gt,fastflownet,dis")
    args = ap.parse_args(argv)
    only = args.only.split(",")
    out: dict = {}
    if "train" in only:
        out["train"] = _profiled("train", train_fold)
    if "step" in only:
        out["step_ms"] = step_times()
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        out["world"] = _profiled("world", lambda: world_scene(root)) if "world" in only else (
            world_scene(root) or {})
        t1, t2, p1, p2 = first_pair(root)
        from flowmod.flow import get_estimator, read_image

        demo = load_profile("demo")
        if "gt" in only:
            gt = get_estimator("gt", dataroot=root, version="v1.0-synth")
            gt.estimate_tokens(t1, t2)  # the world's description, loaded once per process
            from flowmod.world import truth

            truth._depth_frame.cache_clear()  # a cold pair: both frames rendered again
            truth._agent_pose.cache_clear()
            out["gt"] = _profiled("gt", lambda: gt.estimate_tokens(t1, t2))
        a, b = read_image(p1), read_image(p2)
        if "fastflownet" in only:
            ffn = get_estimator("fastflownet", weights=str(demo.path(demo.fastflownet_weights)),
                                scale=demo.flow_scale, device="cpu")
            ffn.estimate(a, b)  # the first call builds what later ones reuse
            out["fastflownet"] = _profiled("fastflownet", lambda: ffn.estimate(a, b))
        if "dis" in only:
            dis = get_estimator("dis", scale=demo.flow_scale)
            out["dis"] = _profiled("dis", lambda: dis.estimate(a, b))
    (RESULTS / "profile.json").write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
