"""Disk of a built run: per object (crops, flow samples), per pair (flow kept), per folder
of ``runs/<profile>/`` against the 0.5 GB goal of the demo, and what trainval would take at
the same rates.

    .venv/bin/python benchmarks/bench_disk.py [--profile demo] [--pairs 34149]

Reads the published artefacts of a finished run (``make book`` first), writes
``benchmarks/results/disk.json`` and prints a table. Reported, never asserted. With
``--lossless`` it also measures what each kind of file would take compressed without loss
(its bytes split into planes by byte significance, then zlib level 6: how far lossless
storage alone could go; ``benchmarks/cold_build.md``).
"""

from __future__ import annotations

import argparse
import json
import zlib
from collections import defaultdict
from pathlib import Path

import numpy as np
import pandas as pd

from flowmod import dag, pipeline
from flowmod.artefacts import write_json
from flowmod.chapters.ch05_preprocessing import storage_table
from flowmod.flow.store import npy_header
from flowmod.params import load_profile
from flowmod.paths import repo_root

#: CAM_FRONT keyframe pairs of nuScenes trainval (850 scenes, ~40 keyframes each).
TRAINVAL_PAIRS = 34_149


def folder_bytes(folder: Path) -> int:
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())


def file_kind(rel: Path) -> str:
    """The kind of a run file for :func:`lossless_table`, by folder and name."""
    parts, name = rel.parts, rel.name
    if parts[0] == "flow" and "pool" in parts:
        return "flow pool: valid masks" if name.endswith(".valid.npy") else "flow pool: flow"
    if name == "best.pt":
        return f"{parts[0]}: model weights" if parts[0] != "extensions" else \
            "extensions: model weights"
    if name.endswith(".samples.npy"):
        return "crops: flow samples"
    if name.endswith(".npy"):  # crops/<m>/<part>/f0.npy; <split>.static.npy; epoch_probs.npy
        sub = name.split(".")[-2] if name.count(".") > 1 else (
            "crops" if parts[0] == "crops" else name[:-4])
        return f"{parts[0]}: {sub} arrays"
    return f"{parts[0]}: other"


def shuffled_zlib(data: bytes, itemsize: int) -> int:
    """Bytes of ``data`` compressed losslessly: planes by byte significance, zlib level 6."""
    if itemsize > 1 and len(data) % itemsize == 0:
        data = np.frombuffer(data, np.uint8).reshape(-1, itemsize).T.tobytes()
    return len(zlib.compress(data, 6))


def lossless_table(run: Path) -> dict[str, dict[str, float]]:
    """Per :func:`file_kind`: files, MB, MB compressed without loss, their ratio."""
    rows: dict[str, dict[str, float]] = defaultdict(lambda: {"files": 0, "MB": 0.0,
                                                              "MB lossless": 0.0})
    for f in sorted(run.rglob("*")):
        if not f.is_file() or any(x.startswith(".") for x in f.relative_to(run).parts):
            continue
        row, data = rows[file_kind(f.relative_to(run))], f.read_bytes()
        # float16 weights; a .npy's own dtype; tables and the rest as bytes
        size = 2 if f.suffix == ".pt" else _npy_itemsize(f) if f.suffix == ".npy" else 1
        row["files"] += 1
        row["MB"] += len(data) / 1e6
        row["MB lossless"] += shuffled_zlib(data, size) / 1e6
    for row in rows.values():
        row["ratio"] = row["MB lossless"] / row["MB"] if row["MB"] else float("nan")
    return dict(sorted(rows.items(), key=lambda kv: -kv[1]["MB"]))


def _npy_itemsize(path: Path) -> int:
    """The item size of a .npy file's array (1 when it cannot be read)."""
    try:
        return npy_header(path)[2].itemsize
    except (ValueError, OSError):
        return 1


def method_row(p, storage: dict[str, float]) -> dict[str, float]:
    """One method's row of :func:`flowmod.chapters.ch05_preprocessing.storage_table` (crops and samples per object,
    the flow kept) with what is left in the crops-mode pool (nothing once every crops node is
    published) and the pairs selected."""
    m = storage["method"]
    pool = p.run_path / "crops" / m / "pool"
    pairs = sum(len(pd.read_parquet(pipeline.published(p, dag.Node(n)) / "pairs.parquet"))
                for n in ("select", "general"))
    return {
        "objects": storage["objects"], "crop kB / object": storage["per object (kB)"],
        "samples kB / object": storage["flow samples per object (kB)"],
        "flow pairs kept": storage["flow pairs"],
        "flow MB / pair kept": storage["flow per pair (MB)"],
        "crops pool MB left": (folder_bytes(pool) if pool.is_dir() else 0) / 1e6,
        "model MB": sum(f.stat().st_size for f in (p.run_path / "models" / m).rglob("best.pt"))
        / 1e6,
        "pairs selected": pairs,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--profile", default="demo")
    ap.add_argument("--lossless", action="store_true",
                    help="also measure each kind of file compressed without loss (slow: reads "
                         "every file)")
    ap.add_argument("--pairs", type=int, default=TRAINVAL_PAIRS,
                    help="pairs to extrapolate to (default: trainval keyframe pairs)")
    args = ap.parse_args(argv)
    p = load_profile(args.profile)
    missing = [str(s.node) for s in pipeline.status(p) if s.state != "up to date"]
    if missing:
        print(f"{len(missing)} nodes not up to date ({', '.join(missing[:3])} ...): run `make book` "
              f"(PROFILE={args.profile}) first")
        return 2
    folders = {d.name: folder_bytes(d) / 1e6 for d in sorted(p.run_path.iterdir()) if d.is_dir()}
    storage = storage_table(p)  # rounded to 0.01: the per-object figures of chapter 05
    methods = {r["method"]: method_row(p, r) for r in storage.to_dict("records")}
    for row in methods.values():
        obj_per_pair = row["objects"] / max(row["pairs selected"], 1)
        row["objects / pair"] = obj_per_pair
        row[f"crops GB at {args.pairs} pairs"] = (
            args.pairs * obj_per_pair * (row["crop kB / object"] + row["samples kB / object"]))
        row[f"crops GB at {args.pairs} pairs"] /= 1e6
    out = {"profile": args.profile, "flow_store": p.flow_store, "flow_scale": p.flow_scale,
           "crop_size": p.crop_size, "run MB by folder": folders,
           "run MB total": sum(folders.values()),
           "chapter 10 models MB": folder_bytes(ext) / 1e6 if (ext := p.run_path / "extensions"
                                                              / "models").is_dir() else 0.0,
           "chapter 11 models and crops MB": sum(
               folder_bytes(d) / 1e6 for d in (p.run_path / "extensions" / "wide" / "models",
                                               *(p.run_path / "crops").glob("*/wide"))
               if d.is_dir()),
           "demo goal MB (make book)": 500,
           "methods": methods}
    if args.lossless:
        out["lossless by kind"] = lossless_table(p.run_path)
    res = repo_root() / "benchmarks" / "results"
    res.mkdir(parents=True, exist_ok=True)
    write_json(res / "disk.json", out)
    print(json.dumps(out, indent=2, default=lambda v: round(v, 3)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
