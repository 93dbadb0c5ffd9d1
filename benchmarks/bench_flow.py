"""Seconds per 1600x900 frame pair and peak memory of every flow method.

    .venv/bin/python benchmarks/bench_flow.py [--methods dis_medium,raft,...] [--repeat N]
        [--scales 1.0,0.5] [--devices cpu,cuda] [--size 1600x900] [--threads N]

Writes ``benchmarks/results/flow.json``. Each (method, scale, device) runs in its own
subprocess, so the peak resident memory (``ru_maxrss``) belongs to that method alone; on CUDA
``torch.cuda.max_memory_allocated`` is reported too. ``peak_rss_mb`` is the peak during the
timed runs (Linux VmHWM reset before them), ``peak_rss_over_before_mb`` its excess over the
resident memory before (imports, the images, the model). The pair is a textured synthetic frame
with known flow (the background zooms as if driving forward, one box moves on its own), so
the classical methods also get an end-point error overall and inside the moving box.

The networks run with RANDOM weights (no trained weights exist here): their times and memory
are representative (fixed work per pair), their flow is meaningless and no error is reported.
Figures only, never asserted: the machine is shared and noisy (2-4x swings).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

METHODS = {
    # name: (flow method, options)
    "dis_ultrafast": ("dis", {"preset": "ultrafast"}),
    "dis_fast": ("dis", {"preset": "fast"}),
    "dis_medium": ("dis", {"preset": "medium"}),
    "farneback": ("farneback", {}),
    "raft": ("raft", {"num_flow_updates": 20}),  # raft_iters: the runs use 20
    "raft_small": ("raft_small", {"num_flow_updates": 20}),
    "fastflownet": ("fastflownet", {}),
}
NETWORKS = ("raft", "raft_small", "fastflownet")
RESULTS = Path(__file__).resolve().parent / "results" / "flow.json"


def _texture(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for s in (2, 4, 8, 16, 32, 64):
        n = rng.random((h // s + 3, w // s + 3)).astype(np.float32)
        up = cv2.resize(n, ((w // s + 3) * s, (h // s + 3) * s), interpolation=cv2.INTER_CUBIC)
        img += up[s : s + h, s : s + w] / np.sqrt(s)
    img = (img - img.min()) / (img.max() - img.min()) * 225 + 15
    return np.dstack([img, np.roll(img, 9, 1), 255 - img]).astype(np.uint8)


def synthetic_pair(h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """img1, img2 (BGR uint8), gt flow (H, W, 2) and the moving box [xmin, ymin, xmax, ymax]."""
    bg = _texture(h, w, 0)
    zoom, c = 1.012, np.array([w / 2, h * 0.45])
    fwd = np.array([[zoom, 0, c[0] * (1 - zoom)], [0, zoom, c[1] * (1 - zoom)]])
    img2 = cv2.warpAffine(bg, fwd, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    gt = np.stack([xs * (zoom - 1) + fwd[0, 2], ys * (zoom - 1) + fwd[1, 2]], -1)
    bw, bh, d = w // 8, h // 8, (7.0, 1.0)  # a "vehicle" overtaking to the right
    x0, y0 = int(w * 0.55), int(h * 0.5)
    car = _texture(bh, bw, 1)
    img1 = bg.copy()
    img1[y0 : y0 + bh, x0 : x0 + bw] = car
    m = np.float64([[1, 0, x0 + d[0]], [0, 1, y0 + d[1]]])
    mask = cv2.warpAffine(np.ones((bh, bw), np.uint8), m, (w, h), flags=cv2.INTER_NEAREST)
    moved = cv2.warpAffine(car, m, (w, h), flags=cv2.INTER_LINEAR)
    img2 = np.where(mask[..., None] > 0, moved, img2)
    gt[y0 : y0 + bh, x0 : x0 + bw] = d
    return img1, img2, gt.astype(np.float32), np.array([[x0, y0, x0 + bw - 1, y0 + bh - 1]])


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter (VmHWM) of this process (Linux >= 4.0)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _peak_rss_mb() -> float:
    """Peak resident memory since the last reset (VmHWM), else since the process start."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _rss_mb() -> float:
    """Current resident memory of this process, MB (Linux /proc; peak if unavailable)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def worker(spec: dict) -> dict:
    """One (method, scale, device) in this process; returns its figures."""
    from flowmod import flow as fl

    method, opts = METHODS[spec["name"]]
    if method in NETWORKS:  # torch only where needed: the classical figures stay torch-free
        import torch

        from flowmod.flow import architectures as fn

        if spec.get("threads"):
            torch.set_num_threads(spec["threads"])
    if spec.get("threads"):
        cv2.setNumThreads(spec["threads"])
    h, w = spec["size"]
    img1, img2, gt, box = synthetic_pair(h, w)
    opts = {**opts, "scale": spec["scale"]}
    out = {k: spec[k] for k in ("name", "scale", "device")}
    out["method"], out["options"] = method, opts
    if method in NETWORKS:
        torch.manual_seed(0)
        model = fn.FastFlowNet() if method == "fastflownet" else fn.build_raft(
            "raft_large" if method == "raft" else "raft_small"
        )
        est = fl.get_estimator(method, model=model, device=spec["device"], **opts)
        out["weights"] = "random (timing only: the flow is meaningless, no error reported)"
        small = cv2.resize(img1, (256, 192))  # warm-up of the kernels at a small size
        est.estimate(small, small)
        if spec["device"] == "cuda":
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
    else:
        est = fl.get_estimator(method, **opts)
    out["rss_before_mb"] = round(_rss_mb(), 1)
    out["peak_is_since_start"] = not _reset_peak_rss()  # else: peak of the timed runs only
    times = []
    for _ in range(spec["repeat"]):
        t0 = time.perf_counter()
        flow = est.estimate(img1, img2)
        if spec["device"] == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    out["seconds_per_pair"] = statistics.median(times)
    out["seconds_all"] = [round(t, 4) for t in times]
    out["peak_rss_mb"] = round(_peak_rss_mb(), 1)
    out["peak_rss_over_before_mb"] = round(out["peak_rss_mb"] - out["rss_before_mb"], 1)
    if spec["device"] == "cuda":
        out["cuda_peak_mb"] = round(torch.cuda.max_memory_allocated() / 2**20, 1)
    if method not in NETWORKS:
        metrics = fl.flow_metrics(flow, gt, boxes=box)
        out["epe_all_px"] = round(metrics["epe"], 3)
        out["epe_moving_box_px"] = round(metrics["epe_boxes"], 3)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", default=",".join(METHODS), help=f"from {', '.join(METHODS)}")
    ap.add_argument("--repeat", type=int, default=1, help="timed runs per method (median)")
    ap.add_argument("--net-repeat", type=int, default=None, help="repeats for networks")
    ap.add_argument("--scales", default="1.0", help="comma-separated flow scales")
    ap.add_argument("--devices", default="auto", help="cpu, cuda, or auto (cpu + cuda if any)")
    ap.add_argument("--size", default="1600x900", help="WxH of the synthetic pair")
    ap.add_argument("--threads", type=int, default=0, help="torch/cv2 threads (0 = default)")
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return 0

    import torch

    names = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in names if m not in METHODS]
    if unknown:
        ap.error(f"unknown methods {unknown}; known: {', '.join(METHODS)}")
    devices = args.devices.split(",")
    if devices == ["auto"]:
        devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    w, h = (int(x) for x in args.size.lower().split("x"))
    runs = []
    for device in devices:
        for name in names:
            if device != "cpu" and name not in NETWORKS:
                continue
            for scale in (float(s) for s in args.scales.split(",")):
                reps = args.net_repeat if (name in NETWORKS and args.net_repeat) else args.repeat
                spec = {"name": name, "scale": scale, "device": device, "size": [h, w],
                        "repeat": reps, "threads": args.threads}  # fmt: skip
                print(f"{name} scale={scale} {device} ...", end=" ", flush=True)
                proc = subprocess.run(
                    [sys.executable, __file__, "--worker", json.dumps(spec)],
                    capture_output=True, text=True,
                )  # fmt: skip
                if proc.returncode != 0:
                    err = (proc.stderr.strip().splitlines() or ["?"])[-1]
                    print(f"failed: {err}")
                    runs.append({**spec, "error": err})
                    continue
                res = json.loads(proc.stdout.strip().splitlines()[-1])
                print(f"{res['seconds_per_pair']:.3f} s/pair, peak RSS {res['peak_rss_mb']:.0f} MB"
                      + (f", EPE {res['epe_all_px']} / box {res['epe_moving_box_px']} px"
                         if "epe_all_px" in res else " (random weights)"))  # fmt: skip
                runs.append(res)

    def sec(name: str, device: str) -> float | None:
        for r in runs:
            if r.get("name") == name and r.get("device") == device and r.get("scale") == 1.0:
                return r.get("seconds_per_pair")
        return None

    ratio = {}
    for device in devices:
        raft, ffn = sec("raft", device), sec("fastflownet", device)
        if raft and ffn:
            ratio[device] = round(raft / ffn, 2)
    result = {
        "what": "seconds per frame pair and peak memory of each flow method (never asserted)",
        "pair": f"{w}x{h} synthetic textured pair, known flow (zoom + one moving box)",
        "networks": "random weights: timing and memory only, no accuracy",
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "torch": torch.__version__,
            "torch_threads": args.threads or torch.get_num_threads(),
            "opencv": cv2.__version__,
            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        },
        "raft_over_fastflownet_seconds": ratio,
        "paper_claim": "FastFlowNet about 10x faster than RAFT (GPU)",
        "runs": runs,
        "written": time.strftime("%Y-%m-%d %H:%M:%S"),
    }
    from flowmod.artefacts import write_json

    write_json(args.out, result)
    print(f"RAFT / FastFlowNet seconds: {ratio}; wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
