"""The study's stages run in-process, in data order: the same stage functions that the
notebooks call, for tests, benchmarks and scripts that need the artefacts but not the book.

    from flowmod import params, pipeline
    p = params.load_profile("smoke", run_dir="/tmp/runs")
    pipeline.build(p)                     # every stale node, nothing else
    print(pipeline.format_status(p))      # what runner --status prints
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import pandas as pd

from flowmod import crops, dag, evaluate, flow, select, train, world
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
    rows = [{"chapter": dag.STAGES[s.node.stage].chapter, "node": str(s.node), "state": s.state,
             "why": s.why, "path": str(s.path)} for s in dag.status(p)]
    return pd.DataFrame(rows, columns=["chapter", "node", "state", "why", "path"])


def format_status(p: Params) -> str:
    """One line per node, like ``dvc status``: up to date / stale / missing, and why."""
    df = status_frame(p)
    width = max(len(n) for n in df["node"]) if len(df) else 10
    lines = []
    for r in df.itertuples(index=False):
        why = f"  {r.why}" if r.why else ""
        lines.append(f"{r.chapter}  {r.node:<{width}}  {r.state:<10}{why}")
    n_stale = int((df["state"] != "up to date").sum())
    lines.append(f"{len(df) - n_stale} of {len(df)} up to date" + (
        f"; {n_stale} to build (make run, or python -m flowmod.runner)" if n_stale else ""))
    return "\n".join(lines)
