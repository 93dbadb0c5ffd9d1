"""Disk of a built run: per object (crops, flow samples), per pair (flow kept, crops pool)
and per folder of ``runs/<profile>/``, and what trainval would take at the same rates.

    .venv/bin/python benchmarks/bench_disk.py [--profile demo] [--pairs 34149]

Reads the published artefacts of a finished run (``make book`` first), writes
``benchmarks/results/disk.json`` and prints a table. Reported, never asserted.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from flowmod import crops, dag, flow
from flowmod.artefacts import write_json
from flowmod.params import load_profile
from flowmod.paths import repo_root

#: CAM_FRONT keyframe pairs of nuScenes trainval (850 scenes, ~40 keyframes each).
TRAINVAL_PAIRS = 34_149


def folder_bytes(folder: Path) -> int:
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())


def method_row(p, m: str) -> dict[str, float]:
    n_obj, crop_b, sample_b = 0, 0, 0
    for part, splits in crops.PART_SPLITS.items():
        folder = dag.published(p, dag.Node("crops", m, part))
        for split in splits:
            npy = crops.crop_paths(folder, split)[0]
            n_obj += int(np.load(npy, mmap_mode="r").shape[0])
            crop_b += npy.stat().st_size
            sample_b += crops.samples_path(folder, split).stat().st_size
    readers = [flow.FlowReader(p, m, part) for part in dag.PARTS]
    kept = [r.path(pid) for r in readers for pid in r.pair_ids]
    flow_b = sum(f.stat().st_size for f in kept)
    pool = p.run_path / "crops" / m / "pool"
    pool_files = list(pool.rglob("*.npy")) if pool.is_dir() else []
    n_pool_pairs = sum(1 for f in pool_files if not f.name.endswith(".samples.npy"))
    pairs = sum(len(pd.read_parquet(dag.published(p, dag.Node(n)) / "pairs.parquet"))
                for n in ("select", "general"))
    return {
        "objects": n_obj, "crop kB / object": crop_b / max(n_obj, 1) / 1e3,
        "samples kB / object": sample_b / max(n_obj, 1) / 1e3,
        "flow pairs kept": len(kept), "flow MB / pair kept": flow_b / max(len(kept), 1) / 1e6,
        "crops pool pairs": n_pool_pairs,
        "crops pool kB / pair": folder_bytes(pool) / max(n_pool_pairs, 1) / 1e3,
        "pairs selected": pairs,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--profile", default="demo")
    ap.add_argument("--pairs", type=int, default=TRAINVAL_PAIRS,
                    help="pairs to extrapolate to (default: trainval keyframe pairs)")
    args = ap.parse_args(argv)
    p = load_profile(args.profile)
    missing = [str(s.node) for s in dag.status(p) if s.state != "up to date"]
    if missing:
        print(f"{len(missing)} nodes not up to date ({', '.join(missing[:3])} ...): run `make book` "
              f"(PROFILE={args.profile}) first")
        return 2
    folders = {d.name: folder_bytes(d) / 1e6 for d in sorted(p.run_path.iterdir()) if d.is_dir()}
    methods = {m: method_row(p, m) for m in p.flow_methods}
    for row in methods.values():
        obj_per_pair = row["objects"] / max(row["pairs selected"], 1)
        row["objects / pair"] = obj_per_pair
        row[f"crops GB at {args.pairs} pairs"] = (
            args.pairs * obj_per_pair * (row["crop kB / object"] + row["samples kB / object"]))
        row[f"crops GB at {args.pairs} pairs"] /= 1e6
    out = {"profile": args.profile, "flow_store": p.flow_store, "flow_scale": p.flow_scale,
           "crop_size": p.crop_size, "run MB by folder": folders,
           "run MB total": sum(folders.values()), "methods": methods}
    res = repo_root() / "benchmarks" / "results"
    res.mkdir(parents=True, exist_ok=True)
    write_json(res / "disk.json", out)
    print(json.dumps(out, indent=2, default=lambda v: round(v, 3)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
