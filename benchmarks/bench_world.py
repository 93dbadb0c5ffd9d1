"""Benchmark of the synthetic world: generation frames/s, disk per frame, GT-flow seconds.

    python benchmarks/bench_world.py                # a small world (about a minute)
    python benchmarks/bench_world.py --scenes 40 --keyframes 20 --sweep-scenes 4   # demo size

Writes ``benchmarks/results/world.json`` (never asserted on: the machine is shared and noisy).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

from flowmod.artefacts import write_json


def _dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--keyframes", type=int, default=8)
    ap.add_argument("--sweep-scenes", type=int, default=1)
    ap.add_argument("--vehicles", type=int, default=28)
    ap.add_argument("--n-jobs", type=int, default=2)
    ap.add_argument("--flow-pairs", type=int, default=5, help="GT-flow pairs to time")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "world.json"))
    args = ap.parse_args(argv)

    from flowmod import world

    with tempfile.TemporaryDirectory(prefix="bench_world_") as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        world.generate_world(
            root,
            n_scenes=args.scenes,
            n_keyframes=args.keyframes,
            n_sweep_scenes=args.sweep_scenes,
            vehicles_per_scene=args.vehicles,
            seed=0,
            n_jobs=args.n_jobs,
            progress=False,
        )
        gen_s = time.perf_counter() - t0
        sd = json.loads((root / "v1.0-synth" / "sample_data.json").read_text())
        n_frames = len(sd)
        img_bytes = sum((root / r["filename"]).stat().st_size for r in sd)
        # GT flow for consecutive keyframes
        keys = [r for r in sd if r["is_key_frame"]]
        by_scene: dict[str, list[dict]] = {}
        for r in keys:
            by_scene.setdefault(r["filename"].split("__")[0], []).append(r)
        pairs = [(s[i], s[i + 1]) for s in by_scene.values() for i in range(len(s) - 1)]
        pairs = pairs[: args.flow_pairs]
        world.gt_flow(root, "v1.0-synth", pairs[0][0]["token"], pairs[0][1]["token"])  # warm
        t1 = time.perf_counter()
        for a, b in pairs:
            world.gt_flow(root, "v1.0-synth", a["token"], b["token"])
        flow_s = (time.perf_counter() - t1) / max(len(pairs), 1)
        total_bytes = _dir_bytes(root)
    result = {
        "world": {
            "scenes": args.scenes,
            "keyframes": args.keyframes,
            "sweep_scenes": args.sweep_scenes,
            "vehicles": args.vehicles,
            "n_jobs": args.n_jobs,
        },
        "frames": n_frames,
        "generation_seconds": round(gen_s, 2),
        "frames_per_second": round(n_frames / gen_s, 3),
        "seconds_per_frame_per_job": round(gen_s * args.n_jobs / n_frames, 3),
        "image_bytes_per_frame": int(img_bytes / n_frames),
        "disk_bytes_total": int(total_bytes),
        "disk_bytes_per_frame": int(total_bytes / n_frames),
        "gt_flow_seconds_per_pair": round(flow_s, 3),
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "platform": platform.platform(),
        },
    }
    write_json(args.out, result)
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
