"""The study as a graph of stages: what each one reads, where its artefacts live, whether they
are up to date, and why not. One mechanism for every stage (DESIGN section 1).

A *node* is one stage for one flow method and part (``crops[dis/keyframe]``). Its
*fingerprint* is :func:`flowmod.artefacts.fingerprint` of

    (stage name, the stage's code version, the node's method and part,
     the values of exactly the parameters the stage reads,
     the fingerprints of the artefacts it read)

where "the parameters the stage reads" is the ``read_by`` declaration on the
:class:`~flowmod.params.Params` fields (the only list; a stage that reads an undeclared
parameter fails, see :class:`StageParams`). The world's fingerprint is that of its
generation parameters for a generated world and that of its tables' content for real data,
so the identity of the data (another seed, another dataroot holding other data) reaches
every node below it. No file time enters any fingerprint.

An artefact is up to date iff the fingerprint in its ``manifest.json`` equals the one computed
now. A stage builds a stale node in a building folder beside the published one
(``.<name>.building-<fp>``, where a killed build resumes) and publishes it only when it
succeeded; the previous result is kept as a variant (``.<name>.variant-<fp>``, the last
:data:`KEEP_VARIANTS`), so a failed rerun loses nothing and switching a parameter back
restores instead of recomputing. :func:`status` reports every node without running anything.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flowmod.artefacts import (
    canonical,
    file_digest,
    fingerprint,
    read_manifest,
    write_manifest,
)
from flowmod.params import Params

#: File of a generated world (in ``<dataroot>/<version>/``) that real nuScenes lacks.
WORLD_FILE = "synth_world.json"
#: The world's manifest, beside its tables (written by ``flowmod.world.ensure_world``).
WORLD_MANIFEST = "flowmod.manifest.json"
#: Previous results kept per node (published results replaced by a rebuild).
KEEP_VARIANTS = 2
#: The two parts of the flow and crops stages: the paper's keyframe pairs and the
#: generalisation pairs.
PARTS = ("keyframe", "general")
#: Chapter 11's part of the flow and crops stages: the training set at every distance.
WIDE = "wide"
#: Stages of the nodes that only ``extension_build`` builds (models and their predictions of
#: chapters 10 and 11; chapter 11's flow and crops, see :func:`gated`).
GATED_STAGES = ("xtrain", "xevaluate", "wtrain", "wgeneralise")


@dataclass(frozen=True)
class Stage:
    """A stage of the study: its name, code/format version, chapter, artefact folder."""

    name: str
    #: Bump when the stage's code changes what it writes: every node of it becomes stale.
    version: int
    chapter: str
    #: Folder under the run directory (``{method}``, ``{part}`` filled per node).
    folder: str
    doc: str


#: The stages in data order (the pipeline at a glance).
STAGES: dict[str, Stage] = {s.name: s for s in (
    Stage("world", 1, "01", "", "the data: a generated world or nuScenes tables"),
    Stage("difficulty", 2, "01", "difficulty", "the naive exact-flow rule on the world"),
    Stage("select", 3, "02", "select", "Table-1 keyframe pairs and objects, scene split"),
    Stage("general", 3, "02", "general", "generalisation pairs and objects (held-out scenes)"),
    Stage("flow", 2, "03", "flow/{method}/{part}", "optical flow of every pair"),
    Stage("crops", 4, "05", "crops/{method}/{part}", "flow crops around every object"),
    Stage("train", 4, "06", "models/{method}/{part}", "the classifier of one training seed"),
    Stage("evaluate", 4, "07", "metrics/{method}/test", "test predictions, baseline, scores"),
    Stage("generalise", 3, "08", "metrics/{method}/general", "generalisation predictions"),
    # beyond the paper (chapter 10): other classifier inputs, when extension_inputs is set
    Stage("context", 1, "10", "extensions/context/{part}",
          "static-world flow and image crops of every object"),
    Stage("xtrain", 1, "10", "extensions/models/{key}", "a classifier on another input"),
    Stage("xevaluate", 1, "10", "extensions/metrics/{key}",
          "its test and generalisation predictions"),
    # beyond the paper (chapter 11): trained on all distances, when wide_methods is set;
    # its flow and crops are nodes of the flow and crops stages, part "wide"
    Stage("wide", 1, "11", "extensions/wide/select",
          "training pairs and objects at every distance, sweeps too"),
    Stage("wtrain", 1, "11", "extensions/wide/models/{method}/{part}",
          "a classifier trained on all distances"),
    Stage("wgeneralise", 1, "11", "extensions/wide/metrics/{method}",
          "its generalisation and test predictions"),
    # beyond the paper (chapter 12): FastFlowNet trained here, when selfflow_modes is set
    Stage("selfflow", 1, "12", "selfflow/{part}",
          "FastFlowNet trained from scratch, held-out end-point error"),
)}


class MissingInput(RuntimeError):
    """A stage's input has not been built; the message names it and the chapter to run."""


class UndeclaredParameter(AttributeError):
    """A stage read a parameter that its ``read_by`` declaration does not name."""


@dataclass(frozen=True, order=True)
class Node:
    """One stage for one flow method and part (None where the stage has none)."""

    stage: str
    method: str | None = None
    part: str | None = None

    def __str__(self) -> str:
        inner = "/".join(x for x in (self.method, self.part) if x)
        return f"{self.stage}[{inner}]" if inner else self.stage


# --- the graph ------------------------------------------------------------------------------

def seed_parts(p: Params) -> list[str]:
    """The parts of the train stage: one per training seed (``s0`` .. ``s<seeds-1>``)."""
    return [f"s{k}" for k in range(p.seeds)]


def inputs(node: Node, p: Params) -> tuple[Node, ...]:
    """The nodes whose artefacts ``node`` reads (a model per training seed of ``p``)."""
    s, m, part = node.stage, node.method, node.part
    models = tuple(Node("train", m, k) for k in seed_parts(p))
    world, select = Node("world"), Node("select")
    objects = objects_node(part)
    table: dict[str, tuple[Node, ...]] = {
        "world": (),
        "difficulty": (world,),
        "select": (world,),
        "general": (world, select),
        "flow": (world, objects),
        # crops mode computes the flow itself: the kept flow (figures) is not its input
        "crops": ((Node("flow", m, part), objects) if p.flow_store == "pairs"
                  else (world, objects)),
        "train": (Node("crops", m, "keyframe"),),
        "evaluate": (*models, Node("crops", m, "keyframe"), select),
        "generalise": (*models, Node("crops", m, "general"), Node("general")),
        "wide": (world, select),
        "wtrain": (Node("crops", m, WIDE),),
        "wgeneralise": (*(Node("wtrain", m, k) for k in seed_parts(p)),
                        *(Node("crops", m, pp) for pp in PARTS), Node("general")),
        "selfflow": (world, select),
    }
    if s in table:
        return table[s]
    ctx = {pp: Node("context", None, pp) for pp in PARTS}
    if s == "context":
        return (world, select if part == "keyframe" else Node("general"))
    if s == "xtrain":
        return ((Node("crops", m, "keyframe"),) if m else ()) + (ctx["keyframe"],)
    if s == "xevaluate":
        xmodels = tuple(Node("xtrain", m, f"{part}/{k}") for k in seed_parts(p))
        flow = tuple(Node("crops", m, pp) for pp in PARTS) if m else ()
        return (*xmodels, *flow, *ctx.values())
    raise KeyError(f"unknown stage {s!r}")


def objects_node(part: str | None) -> Node:
    """The selection node holding a flow or crops part's pairs and objects: ``select``
    (keyframe), ``wide`` (chapter 11's part) or ``general``."""
    return {None: Node("select"), "keyframe": Node("select"), WIDE: Node("wide")}.get(
        part, Node("general"))


def is_generated_world(p: Params) -> bool:
    """True if the profile's data is (or will be made as) a generated world."""
    vdir = p.dataroot_path / p.version
    if (vdir / WORLD_FILE).is_file():
        return True
    return p.synthetic and not (vdir / "scene.json").is_file()


def nodes(p: Params) -> list[Node]:
    """Every node of a run with profile ``p``, in data order."""
    out = [Node("world")]
    if is_generated_world(p):
        out.append(Node("difficulty"))
    out += [Node("select"), Node("general")]
    for stage in ("flow", "crops"):
        out += [Node(stage, m, part) for m in p.flow_methods for part in PARTS]
    out += [Node("train", m, k) for m in p.flow_methods for k in seed_parts(p)]
    for stage in ("evaluate", "generalise"):
        out += [Node(stage, m) for m in p.flow_methods]
    if p.extension_inputs:  # chapter 10: see flowmod.variants
        out += [Node("context", None, part) for part in PARTS]
        chains = extension_chains(p)
        out += [Node("xtrain", m, f"{v}/{k}") for m, v in chains for k in seed_parts(p)]
        out += [Node("xevaluate", m, v) for m, v in chains]
    if p.wide_methods:  # chapter 11: see flowmod.wide
        out.append(Node("wide"))
        for m in p.wide_methods:
            out += [Node("flow", m, WIDE)] if p.flow_store == "pairs" else []
            out += [Node("crops", m, WIDE)] + [Node("wtrain", m, k) for k in seed_parts(p)]
        out += [Node("wgeneralise", m) for m in p.wide_methods]
    out += [Node("selfflow", None, mode) for mode in p.selfflow_modes]  # chapter 12
    return out


def chapter(node: Node) -> str:
    """The chapter (``"05"``) whose notebook builds ``node``: its stage's, except the flow
    and crops of chapter 11's part."""
    return "11" if node.part == WIDE else STAGES[node.stage].chapter


def gate(node: Node) -> str | None:
    """The run parameter without which ``node`` is not built, or None: ``extension_build``
    (``make extensions``) for the models and predictions of chapters 10 and 11 and chapter
    11's flow and crops; ``selfflow_build`` (``make selfflow``) for chapter 12's networks."""
    if node.stage == "selfflow":
        return "selfflow_build"
    return "extension_build" if node.stage in GATED_STAGES or node.part == WIDE else None


def gated(node: Node) -> bool:
    """True for the nodes that only a run parameter builds (:func:`gate`)."""
    return gate(node) is not None


#: The make target that turns each gate on.
GATE_TARGETS = {"extension_build": "make extensions", "selfflow_build": "make selfflow"}


def built_note(what: str, done: list[str], planned: int, others: str, flag: str) -> str:
    """A chapter's line on what its gate (``flag``) has built: ``{what} with these
    parameters: **d of n** (names).`` and, while some are missing, ``The other k
    ({others}) are trained by `make ...` (or this chapter with `flag=true`).``"""
    out = (f"{what} with these parameters: **{len(done)} of {planned}** "
           f"({', '.join(done) or 'none'}).")
    if len(done) < planned:
        out += (f" The other {planned - len(done)} ({others}) are trained by "
                f"`{GATE_TARGETS[flag]}` (or this chapter with `{flag}=true`).")
    return out


def extension_chains(p: Params) -> list[tuple[str | None, str]]:
    """The (flow method, input) chains of chapter 10: every extension method with every
    input that holds flow, and the input without flow (``images``) once, method None."""
    return [(m, v) for v in p.extension_inputs
            for m in (p.extension_methods if v != "images" else [None])]


def nodes_of_chapter(p: Params, number: str) -> list[Node]:
    """The nodes a chapter (``"05"``) builds."""
    return [n for n in nodes(p) if chapter(n) == number]


def _meta(name: str) -> dict[str, Any]:
    return Params.model_fields[name].json_schema_extra  # type: ignore[return-value]


def reads(node: Node) -> tuple[str, ...]:
    """The parameters whose values enter ``node``'s fingerprint (the ``read_by`` declaration)."""
    out = []
    for name in Params.model_fields:
        meta = _meta(name)
        if node.stage in meta["read_by"] and (not meta["methods"] or node.method in meta["methods"]):
            out.append(name)
    return tuple(out)


def free_parameters() -> tuple[str, ...]:
    """Parameters every stage may read without declaring them: how to run (``run``), where
    the data lives (``location``; its identity is the world's) and which nodes exist
    (``plan``). None of them enters a fingerprint."""
    return tuple(n for n in Params.model_fields if _meta(n)["role"] != "input")


def values(p: Params, node: Node) -> dict[str, Any]:
    """``{parameter: value}`` of :func:`reads`; a ``file`` parameter contributes the sha256 of
    the file it names (so a replaced weights file is a change, a renamed copy is not)."""
    out: dict[str, Any] = {}
    for name in reads(node):
        v = getattr(p, name)
        if _meta(name)["file"] and v:
            path = p.path(v)
            v = {"sha256": file_digest(path, digest_cache(p))} if path.is_file() else {
                "missing": str(v)}
        out[name] = v
    return out


def payload(p: Params, node: Node, input_fps: Mapping[str, str]) -> dict[str, Any]:
    """What ``node``'s fingerprint is the hash of."""
    return {"stage": node.stage, "version": STAGES[node.stage].version, "node": str(node),
            "params": values(p, node), "inputs": dict(sorted(input_fps.items()))}


# --- where artefacts live -------------------------------------------------------------------

def node_dir(p: Params, node: Node) -> Path:
    """The published folder of ``node`` (the world's: ``<dataroot>/<version>``)."""
    if node.stage == "world":
        return p.dataroot_path / p.version
    key = "/".join(x for x in (node.method, node.part) if x)
    rel = STAGES[node.stage].folder.format(method=node.method, part=node.part, key=key)
    return p.run_path / rel


def manifest_file(p: Params, node: Node) -> Path:
    d = node_dir(p, node)
    return d / (WORLD_MANIFEST if node.stage == "world" else "manifest.json")


def digest_cache(p: Params) -> Path:
    """The run's stat cache of file digests (never part of a fingerprint)."""
    return p.run_path / ".digests.json"


def tables_digest(p: Params) -> str:
    """sha256 over the content of every ``*.json`` table of ``<dataroot>/<version>``."""
    vdir = p.dataroot_path / p.version
    files = sorted(f for f in vdir.glob("*.json") if f.name != WORLD_MANIFEST)
    return fingerprint([(f.name, file_digest(f, digest_cache(p))) for f in files], n=64)


def world_fingerprint(p: Params) -> str | None:
    """The world node's fingerprint now: generation parameters for a world generated (or
    about to be) from this profile, content of the tables for any other data; None when the
    data is missing."""
    vdir = p.dataroot_path / p.version
    generated = (vdir / WORLD_FILE).is_file()
    if (vdir / "scene.json").is_file() and not generated:
        return fingerprint({"stage": "world", "tables": tables_digest(p)})
    if p.synthetic:
        return fingerprint(payload(p, Node("world"), {}))
    if generated:  # someone's generated world, used as it is
        rec = read_manifest(vdir / WORLD_MANIFEST)
        return rec["fingerprint"] if rec else fingerprint({"stage": "world",
                                                            "tables": tables_digest(p)})
    return None


def recorded(p: Params, node: Node) -> dict[str, Any] | None:
    """The manifest of ``node``'s published artefacts (None if never built). Real nuScenes
    has no manifest: its record is its content fingerprint."""
    rec = read_manifest(manifest_file(p, node))
    if rec is None and node.stage == "world" and not (p.synthetic and is_generated_world(p)):
        fp = world_fingerprint(p)
        return {"fingerprint": fp, "node": "world"} if fp else None
    return rec


# --- what is up to date ---------------------------------------------------------------------

def expected(p: Params) -> dict[Node, str | None]:
    """Every node's fingerprint for the parameters ``p`` (None below a missing input)."""
    exp: dict[Node, str | None] = {}
    for node in nodes(p):
        if node.stage == "world":
            exp[node] = world_fingerprint(p)
            continue
        ins = inputs(node, p)
        if any(exp.get(i) is None for i in ins):
            exp[node] = None
        else:
            exp[node] = fingerprint(payload(p, node, {str(i): exp[i] for i in ins}))
    return exp


@dataclass
class NodeStatus:
    """One line of :func:`status`."""

    node: Node
    state: str  # "up to date" | "stale" | "missing"
    why: str
    path: Path
    fingerprint: str | None = None
    recorded: str | None = None


def _variant(final: Path, fp: str) -> Path:
    return final.parent / f".{final.name}.variant-{fp}"


def _diff(old: Mapping[str, Any], new: Mapping[str, Any], n: int = 3) -> list[str]:
    keys = [k for k in sorted(set(old) | set(new)) if canonical(old.get(k)) != canonical(new.get(k))]
    out = [f"{k}: {_short(old.get(k, '-'))} -> {_short(new.get(k, '-'))}" for k in keys[:n]]
    return out + ([f"(+{len(keys) - n} more)"] if len(keys) > n else [])


def _short(v: Any) -> str:
    s = repr(v)
    return s if len(s) <= 40 else s[:37] + "..."


def status(p: Params) -> list[NodeStatus]:
    """Every node of the run: up to date, stale or missing, and why, in one line each.
    Runs nothing and writes nothing (file digests of real data are cached)."""
    exp = expected(p)
    out: dict[Node, NodeStatus] = {}
    for node in nodes(p):
        path = node_dir(p, node)
        rec = recorded(p, node)
        fp = exp[node]
        ins = inputs(node, p)
        if rec is not None and fp is not None and rec["fingerprint"] == fp:
            out[node] = NodeStatus(node, "up to date", "", path, fp, fp)
            continue
        if node.stage == "world":
            why = (f"no data at {path}" if fp is None else
                   f"not generated yet at {path}" if rec is None else
                   "generated with other parameters: " + "; ".join(
                       _diff(rec.get("params", {}), values(p, node))))
            out[node] = NodeStatus(node, "missing" if rec is None else "stale", why, path, fp,
                                   rec and rec["fingerprint"])
            continue
        waiting = [i for i in ins if out[i].state != "up to date"]
        if rec is None:
            why = "never built" + (f"; waits for {waiting[-1]}" if waiting else "")
            out[node] = NodeStatus(node, "missing", why, path, fp, None)
            continue
        reasons = []
        if rec.get("version") != STAGES[node.stage].version:
            reasons.append(f"code version {rec.get('version')} -> {STAGES[node.stage].version}")
        reasons += _diff(rec.get("params", {}), values(p, node))
        changed = [f"input {i} " + ("is stale" if i in waiting else "changed")
                   for i in ins if rec.get("inputs", {}).get(str(i)) != exp[i]]
        reasons += changed[:1] + ([f"(+{len(changed) - 1} more inputs)"] if len(changed) > 1
                                  else [])
        if fp is not None and (_variant(path, fp) / "manifest.json").is_file():
            reasons.append("a kept copy matches and will be restored, nothing recomputed")
        out[node] = NodeStatus(node, "stale", "; ".join(reasons) or "fingerprint differs", path,
                               fp, rec["fingerprint"])
    return list(out.values())


# --- building a node ------------------------------------------------------------------------

class StageParams:
    """``Params`` as one node sees them: the parameters it declares (``read_by``) and the free
    ones (:func:`free_parameters`); reading any other raises :class:`UndeclaredParameter`,
    so the declaration that the fingerprint uses cannot silently fall behind the code."""

    def __init__(self, p: Params, node: Node) -> None:
        object.__setattr__(self, "_p", p)
        object.__setattr__(self, "_node", node)
        object.__setattr__(self, "_allowed", set(reads(node)) | set(free_parameters()))

    def __getattr__(self, name: str) -> Any:
        if name in Params.model_fields and name not in self._allowed:
            raise UndeclaredParameter(
                f"stage {self._node} read parameter {name!r}, which it does not declare: add "
                f"{self._node.stage!r} to read_by of Params.{name} (flowmod/params.py), so that "
                "its fingerprint follows the value"
            )
        return getattr(self._p, name)

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("parameters are read-only")


@dataclass
class Build:
    """Building one node: its fingerprint from the recorded fingerprints of its inputs, the
    published folder, and a building folder that becomes the published one on success.

    ``up_to_date``: nothing to do (the published artefacts, or a kept variant now restored,
    carry this fingerprint, and ``force`` is off). Otherwise write into :meth:`start`'s
    folder and call :meth:`publish`.
    """

    node: Node
    params: StageParams
    inputs: dict[str, dict[str, Any]]
    payload: dict[str, Any]
    fingerprint: str
    final: Path
    up_to_date: bool
    restored: bool = False
    dir: Path = field(init=False)

    def __post_init__(self) -> None:
        self.dir = self.final.parent / f".{self.final.name}.building-{self.fingerprint}"

    def input_dir(self, node: Node) -> Path:
        """The published folder of one of this node's inputs."""
        return node_dir(self.params._p, node)

    def start(self, fresh: bool = False) -> Path:
        """The building folder (created; kept from a killed build unless ``fresh``)."""
        if fresh and self.dir.exists():
            shutil.rmtree(self.dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        return self.dir

    def publish(self, **info: Any) -> Path:
        """Write the manifest into the building folder and make it the published one; the
        previous result becomes a variant. Returns the published folder."""
        write_manifest(self.dir / "manifest.json", {**self.payload, "fingerprint": self.fingerprint,
                                                    **info})
        _swap_in(self.dir, self.final)
        return self.final


def _swap_in(src: Path, final: Path) -> None:
    """Make ``src`` the published ``final``; the old ``final`` becomes a variant."""
    old = read_manifest(final / "manifest.json") if final.is_dir() else None
    if final.exists():
        aside = _variant(final, old["fingerprint"]) if old else final.parent / (
            f".{final.name}.old-{os.getpid()}")
        if aside.exists():
            shutil.rmtree(aside)
        os.replace(final, aside)
        if old is None:
            shutil.rmtree(aside, ignore_errors=True)
    os.replace(src, final)
    variants = sorted(final.parent.glob(f".{final.name}.variant-*"),
                      key=lambda d: (d / "manifest.json").stat().st_mtime
                      if (d / "manifest.json").is_file() else 0.0)
    for d in variants[:-KEEP_VARIANTS] if KEEP_VARIANTS else variants:
        shutil.rmtree(d, ignore_errors=True)


def begin(p: Params, node: Node) -> Build:
    """Start building ``node``: read its inputs' manifests (:class:`MissingInput` if one was
    never built), compute its fingerprint, and decide whether anything must be done (a kept
    variant with this fingerprint is restored instead of recomputed)."""
    recs: dict[str, dict[str, Any]] = {}
    for i in inputs(node, p):
        rec = recorded(p, i)
        if rec is None:
            raise MissingInput(f"{node} reads {i}, which has not been built: {_how(i)}")
        recs[str(i)] = rec
    pl = payload(p, node, {k: r["fingerprint"] for k, r in recs.items()})
    fp = fingerprint(pl)
    final = node_dir(p, node)
    current = read_manifest(final / "manifest.json")
    up = not p.force and current is not None and current["fingerprint"] == fp
    b = Build(node, StageParams(p, node), recs, pl, fp, final, up)
    if not up and not p.force and (_variant(final, fp) / "manifest.json").is_file():
        _swap_in(_variant(final, fp), final)
        b.up_to_date = b.restored = True
    return b


def results(final: Path) -> list[Path]:
    """A node's published folder and its kept variants (those that exist), newest first."""
    kept = sorted(final.parent.glob(f".{final.name}.variant-*"),
                  key=lambda d: -(d / "manifest.json").stat().st_mtime
                  if (d / "manifest.json").is_file() else 0.0)
    return [d for d in (final, *kept) if (d / "manifest.json").is_file()]


def current(p: Params, node: Node) -> bool:
    """True iff ``node``'s published artefacts carry the fingerprint that its inputs'
    published artefacts and ``p``'s values of its parameters give now: nothing it read was
    rebuilt and none of its parameters changed since. Unlike :func:`status` it looks one
    step up only, so a notebook that declares just its chapter's parameters can ask."""
    rec = recorded(p, node)
    if rec is None:
        return False
    fps = {}
    for i in inputs(node, p):
        r = recorded(p, i)
        if r is None:
            return False
        fps[str(i)] = r["fingerprint"]
    return rec.get("fingerprint") == fingerprint(payload(p, node, fps))


def published(p: Params, node: Node) -> Path:
    """The published folder of ``node`` for reading; :class:`MissingInput` if never built."""
    if recorded(p, node) is None:
        raise MissingInput(f"{node} has not been built: {_how(node)}")
    return node_dir(p, node)


def _how(node: Node) -> str:
    """How to build ``node``: the chapter to run (and ``extension_build`` where gated)."""
    ch, flag = chapter(node), gate(node)
    if flag:
        return (f"run chapter {ch} with {flag}=true first ({GATE_TARGETS[flag]}, or "
                f"python -m flowmod.runner --only {ch} --set {flag}=true)")
    return f"run chapter {ch} first (python -m flowmod.runner --only {ch})"


@contextlib.contextmanager
def removed_on_error(path: Path) -> Iterator[Path]:
    """Yield ``path``; remove it if the block raises (for building folders that cannot resume)."""
    try:
        yield path
    except BaseException:
        shutil.rmtree(path, ignore_errors=True)
        raise
