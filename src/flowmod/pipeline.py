"""The study's stages run in-process, in data order: the same stage functions that the
notebooks call, for tests, benchmarks and scripts that need the artefacts but not the book.

    from flowmod import params, pipeline
    p = params.load_profile("smoke", run_dir="/tmp/runs")
    pipeline.build(p)                     # every stale node, nothing else
    print(pipeline.format_status(p))      # what runner --status prints
    pipeline.collect_garbage(p)           # what runner --gc does
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import pandas as pd

from flowmod import crops, dag, evaluate, flow, select, train, variants, wide, world
from flowmod.flow import selftrain
from flowmod.params import Params
from flowmod.report import world_report

#: The builder of each chapter's stages, in data order.
BUILDERS: dict[str, Callable[[Params, bool], Any]] = {
    "01": lambda p, progress: (world.ensure_world(p, progress=progress),
                               dag.is_generated_world(p)
                               and world_report.difficulty_report(p, progress=progress)),
    "02": lambda p, progress: select.run(p, progress=progress),
    "03": lambda p, progress: flow.run(p, progress=progress),
    "05": lambda p, progress: crops.run(p, progress=progress),
    "06": lambda p, progress: train.run(p, progress=progress),
    "07": lambda p, progress: evaluate.run(p),
    "08": lambda p, progress: evaluate.run_general(p),
    "10": lambda p, progress: variants.run(p, progress=progress),
    "11": lambda p, progress: wide.run(p, progress=progress),
    "12": lambda p, progress: selftrain.run(p, progress=progress),
}


def build(p: Params, chapters: Iterable[str] | None = None, progress: bool = False) -> None:
    """Build the stale nodes of the given chapters (default: all), in data order."""
    wanted = set(chapters) if chapters is not None else set(BUILDERS)
    unknown = wanted - set(BUILDERS)
    if unknown:
        raise ValueError(f"no stages in chapter(s) {sorted(unknown)}; known: {list(BUILDERS)}")
    for ch, builder in BUILDERS.items():
        if ch in wanted:
            builder(p, progress)


def status_frame(p: Params) -> pd.DataFrame:
    """:func:`flowmod.dag.status` as a table: chapter, node, state, why, path."""
    rows = [{"chapter": dag.chapter(s.node), "node": str(s.node), "state": s.state,
             "gate": dag.gate(s.node) or "", "why": s.why, "path": str(s.path)}
            for s in dag.status(p)]
    return pd.DataFrame(rows, columns=["chapter", "node", "state", "gate", "why", "path"])


def format_status(p: Params) -> str:
    """One line per node, like ``dvc status``: up to date / stale / missing, and why."""
    df = status_frame(p)
    width = max(len(n) for n in df["node"]) if len(df) else 10
    lines = []
    for r in df.itertuples(index=False):
        why = f"  {r.why}" if r.why else ""
        lines.append(f"{r.chapter}  {r.node:<{width}}  {r.state:<10}{why}")
    stale = df[df["state"] != "up to date"]
    n_stale = len(stale)
    tail = f"{len(df) - n_stale} of {len(df)} up to date" + (
        f"; {n_stale} to build (make run, or python -m flowmod.runner)" if n_stale else "")
    what = {"extension_build": "models, predictions", "selfflow_build": "flow networks"}
    for flag, gated in stale[stale["gate"] != ""].groupby("gate", sort=True):
        if getattr(p, flag):
            continue
        which = " and ".join(sorted(set(gated["chapter"])))
        extra = ", flow, crops" if "11" in which else ""
        tail += (f"; chapter{'s' * (' and ' in which)} {which}'s {len(gated)} "
                 f"({what[flag]}{extra}) only with {flag}: {dag.GATE_TARGETS[flag]}")
    lines.append(tail)
    return "\n".join(lines)


def unreferenced(p: Params, variants: bool = False) -> list[Path]:
    """Files of the run folder's per-pair caches that no node of ``p`` can read any more:
    flow pool files listed by no flow index (published or kept variant) and crops pool
    folders of other options than ``p``'s (another geometry, flow option or dtype; the
    crops nodes themselves keep their arrays; in ``flow_store: pairs`` no crops pool is
    read). ``variants``: also every kept variant
    (``.variant-`` folder: an earlier result that switching back would restore), and the
    flow files only they listed. A method with a build in progress (a ``.building-``
    folder) keeps its flow files: its unlisted files are its resume point."""
    from flowmod.flow.store import valid_path

    out: list[Path] = sorted(p.run_path.rglob(".*.variant-*")) if variants else []
    for method_dir in sorted((p.run_path / "flow").glob("*")):
        pool = method_dir / "pool"
        if not pool.is_dir() or any(method_dir.glob(".*.building-*")):
            continue
        keep: set[Path] = set()
        for index in method_dir.glob("*/index.parquet"):  # published and .variant- folders
            if variants and ".variant-" in index.parent.name:
                continue
            for f in pd.read_parquet(index, columns=["file"])["file"]:
                keep |= {pool / f, valid_path(pool / f)}
        out += [f for f in sorted(pool.rglob("*.npy")) if f not in keep]
    for pool_root in sorted((p.run_path / "crops").glob("*/pool")):
        m = pool_root.parent.name
        if any(pool_root.parent.glob(".*.building-*")):
            continue
        current = (crops.crops_pool(p, m) if p.flow_store == "crops" and m in p.flow_methods
                   else None)
        out += [d for d in sorted(pool_root.iterdir()) if d.is_dir() and d != current]
    return out


def collect_garbage(p: Params, dry_run: bool = False,
                    variants: bool = False) -> tuple[int, int]:
    """Remove :func:`unreferenced` files and folders (``dry_run``: only count them); then
    option folders left without flow files. Returns (items, bytes)."""
    import shutil

    items = unreferenced(p, variants)
    size = sum(f.stat().st_size for i in items
               for f in ([i] if i.is_file() else list(i.rglob("*"))) if f.is_file())
    if not dry_run:
        for i in items:
            shutil.rmtree(i) if i.is_dir() else i.unlink()
        for folder in (p.run_path / "flow").glob("*/pool/*"):
            if folder.is_dir() and not any(folder.glob("*.npy")):
                shutil.rmtree(folder)
    return len(items), size
