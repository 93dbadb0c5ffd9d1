"""The study's pipeline: every stage's declaration in data order, and what runs them.

    from flowmod import params, pipeline
    p = params.load_profile("smoke", run_dir="/tmp/runs")
    pipeline.build(p)                     # every stale node, nothing else
    print(pipeline.format_status(p))      # what runner --status prints
    pipeline.collect_garbage(p)           # what runner --gc does

Each stage is declared once, beside its build function, in its own module
(:class:`flowmod.dag.Stage`); :data:`STAGES` lists them in data order and :data:`GRAPH`
(:class:`flowmod.dag.Graph`) answers every question about them: the nodes of a run, their
inputs, folders, fingerprints and status, and the one driver that builds them. The notebooks
call :func:`build` with their chapter; the chapter backends (:mod:`flowmod.chapters`) read
what is published through :func:`published`.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import pandas as pd

from flowmod import crops, dag, difficulty, evaluate, select, train
from flowmod.extensions import context, flowerrors, inputs, selfflow, wide
from flowmod.flow import accuracy
from flowmod.flow import stage as flow_stage
from flowmod.lock import folder_lock
from flowmod.params import Params
from flowmod.progress import bar as progress_bar
from flowmod.world import source as world_source

#: Every stage, in data order (chapter 01 to 14).
STAGES: tuple[dag.Stage, ...] = (
    world_source.STAGE,      # 01 the data
    difficulty.STAGE,        # 01 the naive exact-flow rule
    difficulty.EXAMPLE_STAGE,  # 01 the exact flow of the example pair
    select.SELECT,           # 02 Table-1 keyframe pairs, scene split
    select.GENERAL,          # 02 generalisation pairs
    flow_stage.STAGE,        # 03 optical flow (chapter 11's part too)
    accuracy.STAGE,          # 03 each flow method against the exact flow
    crops.STAGE,             # 05 flow crops (chapter 11's part too)
    train.STAGE,             # 06 one classifier per seed
    evaluate.EVALUATE,       # 07 test split, baseline, scores
    evaluate.GENERALISE,     # 08 generalisation set
    context.STAGE,           # 10 static-world flow and image crops
    inputs.XTRAIN,           # 10 a classifier on another input
    inputs.XEVALUATE,        # 10 its predictions
    wide.WIDE_STAGE,         # 11 the training set at every distance
    wide.WTRAIN,             # 11 a classifier trained on it
    wide.WGENERALISE,        # 11 its predictions
    selfflow.SHIPPED_STAGE,  # 12 the shipped FastFlowNet weights, held out
    selfflow.STAGE,          # 12 FastFlowNet trained here
    flowerrors.ELEVELS,      # 14 each kind of flow error's level at each target
    flowerrors.ETRAIN,       # 14 a classifier on degraded exact flow
    flowerrors.EEVALUATE,    # 14 its predictions and realised errors
)
#: The make target that turns each gate on.
GATE_TARGETS = {"extension_build": "make extensions", "selfflow_build": "make selfflow"}
GRAPH = dag.Graph(STAGES, GATE_TARGETS)

#: The chapters that build nodes.
CHAPTERS = tuple(sorted({c for s in STAGES for c in s.chapters()}))


def nodes(p: Params, chapters: Iterable[str] | None = None) -> list[dag.Node]:
    """Every node of a run with ``p`` (of ``chapters``), in data order."""
    return GRAPH.nodes(p, chapters)


def inputs(node: dag.Node, p: Params) -> tuple[dag.Node, ...]:
    return GRAPH.inputs(node, p)


def chapter(node: dag.Node) -> str:
    return GRAPH.chapter(node)


def gate(node: dag.Node) -> str | None:
    return GRAPH.gate(node)


def status(p: Params) -> list[dag.NodeStatus]:
    return GRAPH.status(p)


def expected(p: Params) -> dict[dag.Node, str | None]:
    return GRAPH.expected(p)


def node_dir(p: Params, node: dag.Node) -> Path:
    return GRAPH.node_dir(p, node)


def recorded(p: Params, node: dag.Node) -> dict[str, Any] | None:
    return GRAPH.recorded(p, node)


def published(p: Params, node: dag.Node) -> Path:
    return GRAPH.published(p, node)


def current(p: Params, node: dag.Node) -> bool:
    return GRAPH.current(p, node)


def damaged(p: Params, node: dag.Node, rec: dict[str, Any] | None = None) -> str | None:
    return GRAPH.damaged(p, node, rec)


def built(p: Params, node: dag.Node) -> bool:
    return GRAPH.built(p, node)


def build(p: Params, chapters: Iterable[str] | None = None, progress: bool = False
          ) -> list[dag.Node]:
    """Build the stale nodes of the given chapters (default: all), in data order; a gated
    node only with its gate on. Returns the nodes considered."""
    wanted = None if chapters is None else set(chapters)
    unknown = (wanted or set()) - set(CHAPTERS)
    if unknown:
        raise ValueError(f"no stages in chapter(s) {sorted(unknown)}; known: {list(CHAPTERS)}")
    with folder_lock(p.run_path, "pipeline.build"):  # one build per run folder at a time
        return GRAPH.build(p, wanted, progress, at_once=_at_once(p, progress))


def _at_once(p: Params, progress: bool) -> dag.AtOnce | None:
    """How :meth:`flowmod.dag.Graph.build` builds stale nodes of a parallel stage (the
    classifiers): in ``n_jobs`` worker processes, each training on one thread
    (:data:`flowmod.train.CPU_THREADS`, so the weights are those of a build one after the
    other); None with one job. On CUDA they are built one after the other."""
    if p.n_jobs < 2:
        return None

    def run(todo: list[dag.Node]) -> None:
        from flowmod.environment import resolve_device  # torch: only when models train

        if resolve_device(p.device).type != "cpu":
            for node in todo:
                GRAPH.build_node(p, node, progress)
        else:
            _build_in_workers(p, todo, progress)
    return run


def _build_in_workers(p: Params, todo: list[dag.Node], progress: bool) -> None:
    """Build ``todo`` in ``min(n_jobs, len(todo))`` worker processes (joblib's, as the flow
    and the world use: a script that calls :func:`build` needs no ``__main__`` guard), one
    bar here for all. The first failure is raised as its worker raised it and stops the
    others; each node publishes on its own and an unfinished one resumes from its last
    epoch, so nothing finished is lost."""
    from joblib import Parallel, delayed  # only a parallel build needs it
    from joblib.externals.loky.process_executor import TerminatedWorkerError

    jobs = min(p.n_jobs, len(todo))
    bar = progress_bar(total=len(todo), unit="node", disable=not progress,
                       desc=f"{todo[0].stage}: {len(todo)} nodes, {jobs} at a time")
    try:
        for _ in Parallel(n_jobs=jobs, return_as="generator_unordered")(
                delayed(_build_one)(p, node) for node in todo):
            bar.update()
    except TerminatedWorkerError as e:
        raise RuntimeError(
            f"a worker process building {todo[0].stage} nodes died (out of memory, or "
            "killed); the nodes it finished are kept: rerun, or set n_jobs=1 (--set "
            "n_jobs=1) to build them one at a time") from e
    finally:
        bar.close()


def _build_one(p: Params, node: dag.Node) -> None:
    """One node, in a worker process (:func:`_build_in_workers`)."""
    GRAPH.build_node(p, node, progress=False)


# --- status -------------------------------------------------------------------------------------

def status_frame(p: Params) -> pd.DataFrame:
    """:func:`status` as a table: chapter, node, state, gate, why, path."""
    rows = [{"chapter": chapter(s.node), "node": str(s.node), "state": s.state,
             "gate": gate(s.node) or "", "why": s.why, "path": str(s.path)}
            for s in status(p)]
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
                 f"({what[flag]}{extra}) only with {flag}: {GATE_TARGETS[flag]}")
    lines.append(tail)
    return "\n".join(lines)


# --- garbage ------------------------------------------------------------------------------------

def unreferenced(p: Params, variants: bool = False, worlds: bool = False) -> list[Path]:
    """Files of the run folder's per-pair caches that no node of ``p`` can read any more, as
    each stage names them (:attr:`flowmod.dag.Stage.garbage`: flow pool files listed by no
    flow index, crops pool folders of other options than ``p``'s). ``variants``: also every
    kept variant (``.variant-`` folder: an earlier result that switching back would
    restore), and the flow files only they listed. A method with a build in progress (a
    ``.building-`` folder) keeps its files: they are its resume point. ``worlds``: also the
    generated worlds under the dataroot other than ``p``'s."""
    return _kept_aside(p, variants, worlds) + _stage_garbage(p, variants)


def _kept_aside(p: Params, variants: bool, worlds: bool) -> list[Path]:
    """The kept variants (``variants``) and the other generated worlds (``worlds``)."""
    out: list[Path] = sorted(p.run_path.rglob(".*.variant-*")) if variants else []
    return out + (world_source.other_worlds(p) if worlds else [])


def _stage_garbage(p: Params, variants: bool) -> list[Path]:
    """What each stage names as its own caches' garbage (:attr:`flowmod.dag.Stage.garbage`)."""
    return [i for stage in STAGES if stage.garbage for i in stage.garbage(p, variants)]


def collect_garbage(p: Params, dry_run: bool = False, variants: bool = False,
                    worlds: bool = False) -> tuple[int, int]:
    """Remove :func:`unreferenced` files and folders (``dry_run``: only count them); then
    the stages' option folders left without a cache file. Returns (items, bytes)."""
    cached = _stage_garbage(p, variants)  # asked once: the same list unreferenced() gives
    items = _kept_aside(p, variants, worlds) + cached
    size = sum(f.stat().st_size for i in items
               for f in ([i] if i.is_file() else list(i.rglob("*"))) if f.is_file())
    if not dry_run:
        others = set(world_source.other_worlds(p))
        for i in items:
            if i in others:
                world_source.remove_world(i)  # not while a run generates it
            else:
                shutil.rmtree(i) if i.is_dir() else i.unlink()
        for folder in {i.parent for i in cached} - {p.run_path}:  # left without a cache array
            if folder.is_dir() and not any(folder.rglob("*.npy")):
                shutil.rmtree(folder)
    return len(items), size
