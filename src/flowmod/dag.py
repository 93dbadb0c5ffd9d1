"""The engine behind every stage: nodes, fingerprints, what is up to date, and the one driver.

A *stage* is declared once (:class:`Stage`, like a Snakemake rule or a kedro node): its
name, code version, chapter, artefact folder, the nodes it has for a parameter set, each
node's inputs, its gate and the function that builds one node. The study's declarations, in
data order, make a :class:`Graph` (:mod:`flowmod.pipeline`); everything here is generic.

A *node* is one stage for one flow method and part (``crops[dis/keyframe]``). Its
*fingerprint* is :func:`flowmod.artefacts.fingerprint` of :func:`payload`:

    (stage name, the stage's code version, the node,
     the digests of the code the stage runs,
     the values of exactly the parameters the stage reads,
     the fingerprints of the artefacts it read)

where "the parameters the stage reads" is the ``read_by`` declaration on the
:class:`~flowmod.params.Params` fields (the only list; a stage that reads an undeclared
parameter fails, see :class:`StageParams`). "The code the stage runs" is the module of its
build function and every flowmod module that one imports (:mod:`flowmod.codedigest`), so
an edit of that code makes exactly its nodes, and their readers, stale. A *source* stage
(the data) has no inputs: its fingerprint is the identity of its data (:class:`Source`).
No file time enters any fingerprint.

An artefact is up to date iff the fingerprint in its ``manifest.json`` equals the one computed
now. :meth:`Graph.build_node` is the one driver: it computes the fingerprint from the inputs'
manifests; if stale, the stage's build function writes into a building folder beside the
published one (``.<name>.building-<fp>``, where a killed build resumes), and the folder is
published only when the build succeeded; the previous result is kept as a variant
(``.<name>.variant-<fp>``, the last :data:`KEEP_VARIANTS`), so a failed rerun loses nothing
and switching a parameter back restores instead of recomputing. :meth:`Graph.status`
reports every node without running anything.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from flowmod import codedigest
from flowmod.artefacts import (
    DiskFull,
    canonical,
    digest_batch,
    file_digest,
    file_digests,
    fingerprint,
    leftover_temporaries,
    read_manifest,
    write_manifest,
)
from flowmod.params import FILE_DEFAULTS, Params

#: Previous results kept per node (published results replaced by a rebuild).
KEEP_VARIANTS = 2


#: What builds several stale nodes at once (:meth:`Graph.build`): given the nodes, it
#: returns when every one is published, or raises the first failure.
AtOnce = Callable[[list["Node"]], None]


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

    @property
    def key(self) -> str:
        """``method/part`` (the parts that exist), as folders and manifests name it."""
        return "/".join(x for x in (self.method, self.part) if x)


class Source(Protocol):
    """The data a source stage stands for (the world): where it is, its identity, and how
    to make it present. No run folder holds it, so it has no building folder."""

    def location(self, p: Params) -> Path:
        """The data's folder."""

    def fingerprint(self, p: Params) -> str | None:
        """The data's identity now (None: not there and not about to be made)."""

    def record(self, p: Params) -> dict[str, Any] | None:
        """The data's manifest: ``fingerprint`` and what made it (None: not there)."""

    def status(self, p: Params) -> tuple[str, str]:
        """(state, note): ``up to date`` (with a note, e.g. what was edited) or ``missing``
        and why."""

    def ensure(self, p: Params, progress: bool) -> None:
        """Make the data present (generate it), or explain in one line why it cannot be."""


#: A stage's build function: writes one node into ``b.start()``'s folder and returns what
#: its manifest records beside the fingerprint (the driver publishes).
BuildFn = Callable[["Build", bool], "Mapping[str, Any] | None"]


def _no_inputs(node: Node, p: Params) -> tuple[Node, ...]:
    return ()


@dataclass(frozen=True)
class Stage:
    """The declaration of one stage.

    ``nodes(p)``: its nodes for a parameter set; ``inputs(node, p)``: the nodes a node reads;
    ``build(b, progress)``: builds one node (:data:`BuildFn`); ``gate``: the run parameter
    without which its nodes are not built (None: always); ``parts``: parts whose nodes
    belong to another chapter, ``{part: (chapter, gate)}``; ``source``: set for the data
    (no build function, no run folder); ``outputs``: the files a node publishes;
    ``garbage``: its cache files nothing reads any more.
    """

    name: str
    #: An override: the code a stage runs enters its fingerprint by content
    #: (:meth:`code`); bump this only for a change the code digest cannot see (a library's
    #: behaviour, a file the code reads): every node of the stage becomes stale.
    version: int
    chapter: str
    #: Folder under the run directory (``{method}``, ``{part}``, ``{key}`` filled per node).
    folder: str
    doc: str
    nodes: Callable[[Params], Iterable[Node]]
    inputs: Callable[[Node, Params], tuple[Node, ...]] = _no_inputs
    build: BuildFn | None = None
    gate: str | None = None
    parts: Mapping[str, tuple[str, str | None]] = field(default_factory=dict)
    source: Source | None = None
    #: The files a node publishes in its folder besides its manifest (``{split}`` stands for
    #: a family of names): the stage's outputs, declared with it. Only the stage's own
    #: module names them; every other reader goes through that module's reader functions.
    outputs: tuple[str, ...] = ()
    #: The stage's per-pair cache files (outside its nodes' folders) that no node of a
    #: parameter set can read any more, ``garbage(p, variants)``; with ``variants``, also
    #: those only kept earlier results read. ``make gc`` asks every stage.
    garbage: Callable[[Params, bool], list[Path]] | None = None
    #: Its nodes never read one another and their results do not depend on what runs beside
    #: them, so the driver may build ``n_jobs`` of them at once in worker processes
    #: (:meth:`Graph.build`'s ``at_once``): the stages that train a classifier on one thread.
    parallel: bool = False

    def chapters(self) -> set[str]:
        """Every chapter that builds some node of this stage."""
        return {self.chapter, *(c for c, _ in self.parts.values())}

    def code(self) -> dict[str, str]:
        """``{module file: digest}`` of the code the stage runs: its build function's module
        and the flowmod modules that imports (:func:`flowmod.codedigest.digests`; {} for a
        source)."""
        return codedigest.digests(self.build.__module__) if self.build is not None else {}


# --- parameters as a node sees them ----------------------------------------------------------

def _meta(name: str) -> dict[str, Any]:
    return Params.model_fields[name].json_schema_extra  # type: ignore[return-value]


def reads(node: Node) -> tuple[str, ...]:
    """The parameters whose values enter ``node``'s fingerprint (the ``read_by`` declaration;
    a parameter with ``methods`` only for the nodes of those flow methods or parts)."""
    out = []
    for name in Params.model_fields:
        meta = _meta(name)
        only = meta["methods"]
        if node.stage in meta["read_by"] and (not only or node.method in only
                                              or node.part in only):
            out.append(name)
    return tuple(out)


def free_parameters() -> tuple[str, ...]:
    """Parameters every stage may read without declaring them: how to run (``run``), where
    the data lives (``location``; its identity is the world's) and which nodes exist
    (``plan``). None of them enters a fingerprint."""
    return tuple(n for n in Params.model_fields if _meta(n)["role"] != "input")


def digest_cache(p: Params) -> Path:
    """The run's stat cache of file digests (never part of a fingerprint)."""
    return p.run_path / ".digests.json"


def values(p: Params, node: Node) -> dict[str, Any]:
    """``{parameter: value}`` of :func:`reads`; a ``file`` parameter contributes the sha256 of
    the file it names (so a replaced weights file is a change, a renamed copy is not), or,
    left null, of the file its reader would find instead (:data:`FILE_DEFAULTS`)."""
    out: dict[str, Any] = {}
    for name in reads(node):
        v = getattr(p, name)
        if _meta(name)["file"]:
            path = p.path(v) if v else FILE_DEFAULTS.get(name, lambda: None)()
            if path is not None and path.is_file():
                v = {"sha256": file_digest(path, digest_cache(p))}
            elif v:
                v = {"missing": str(v)}
        out[name] = v
    return out


def payload(p: Params, node: Node, version: int, input_fps: Mapping[str, str],
            code: Mapping[str, str] | None = None) -> dict[str, Any]:
    """What ``node``'s fingerprint is the hash of (``version``: its stage's code version;
    ``code``: the digests of the code it runs, :meth:`Stage.code`)."""
    return {"stage": node.stage, "version": version, "node": str(node),
            "code": dict(sorted((code or {}).items())),
            "params": values(p, node), "inputs": dict(sorted(input_fps.items()))}


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

    @property
    def all(self) -> Params:
        """Every parameter, for reading what a *run* setting names (never for values that
        enter the artefacts: those go through the declared attributes)."""
        return self._p


# --- kept results -------------------------------------------------------------------------------

def variant_dir(final: Path, fp: str) -> Path:
    """Where the result with fingerprint ``fp`` of the node published at ``final`` is kept."""
    return final.parent / f".{final.name}.variant-{fp}"


def swap_in(src: Path, final: Path) -> None:  # pragma: no mutate block
    """Make ``src`` the published ``final``; the old ``final`` becomes a variant (the last
    :data:`KEEP_VARIANTS` are kept). Nothing is removed before ``src`` is in place."""
    old = read_manifest(final / "manifest.json") if final.is_dir() else None
    aside = None
    if final.exists():
        aside = variant_dir(final, old["fingerprint"]) if old else final.parent / (
            f".{final.name}.old-{os.getpid()}")
        if aside.exists():
            shutil.rmtree(aside)
        os.replace(final, aside)
    os.replace(src, final)
    new = read_manifest(final / "manifest.json")
    if aside is not None and (old is None or (new and new["fingerprint"] == old["fingerprint"])):
        shutil.rmtree(aside, ignore_errors=True)  # nothing to restore it for
    kept = sorted(final.parent.glob(f".{final.name}.variant-*"), key=_manifest_mtime)
    for d in kept[:-KEEP_VARIANTS] if KEEP_VARIANTS else kept:
        shutil.rmtree(d, ignore_errors=True)


def _manifest_mtime(d: Path) -> float:  # pragma: no mutate block
    m = d / "manifest.json"
    return m.stat().st_mtime if m.is_file() else 0.0


def results(final: Path) -> list[Path]:
    """A node's published folder and its kept variants (those that exist), newest first."""
    kept = sorted(final.parent.glob(f".{final.name}.variant-*"), key=lambda d: -_manifest_mtime(d))
    return [d for d in (final, *kept) if (d / "manifest.json").is_file()]


def output_files(folder: Path, cache: Path | None = None) -> dict[str, dict[str, Any]]:
    """``{relative path: {"size": bytes, "sha256": hex}}`` of the files a node published in
    ``folder`` (all but its manifest and hidden files), recorded in its manifest."""
    out = {}
    for f in sorted(folder.rglob("*")):
        rel = f.relative_to(folder)
        if f.is_file() and rel.name != "manifest.json" and not any(
                part.startswith(".") for part in rel.parts):
            out[rel.as_posix()] = {"size": f.stat().st_size, "sha256": file_digest(f, cache)}
    return out


def cached_files(final: Path, files: Iterable[Path], cache: Path | None = None
                 ) -> dict[str, dict[str, Any]]:
    """:func:`output_files`' record of files outside a node's folder ``final`` (a per-pair
    cache), each by its path relative to ``final`` (``../pool/<options>/<key>.npy``)."""
    files = sorted(set(files))
    digests = file_digests(files, cache)
    return {os.path.relpath(f, final): {"size": f.stat().st_size, "sha256": d}
            for f, d in zip(files, digests, strict=True)}


def damage(folder: Path, rec: Mapping[str, Any] | None, cache: Path | None = None) -> str | None:
    """What is wrong with the files a manifest ``rec`` recorded in ``folder`` (the first
    missing, resized or changed file, per-pair cache files included), or None (also for
    manifests that record none)."""
    for rel, want in (rec or {}).get("files", {}).items():
        f = Path(os.path.normpath(folder / rel))
        try:
            size = f.stat().st_size
        except OSError:
            return f"{f} is missing"
        if size != want["size"]:
            return f"{f} has {size} bytes, {want['size']} when it was built (cut short?)"
        if file_digest(f, cache) != want["sha256"]:
            return f"{f} changed since it was built (same size, other content)"
    return None


@contextlib.contextmanager
def removed_on_error(path: Path) -> Iterator[Path]:
    """Yield ``path``; remove it if the block raises (for building folders that cannot resume)."""
    try:
        yield path
    except BaseException:
        shutil.rmtree(path, ignore_errors=True)
        raise


# --- building one node --------------------------------------------------------------------------

@dataclass
class Build:
    """Building one node: its fingerprint from the recorded fingerprints of its inputs, the
    published folder, and a building folder that becomes the published one on success.

    ``up_to_date``: nothing to do (the published artefacts, or a kept variant now restored,
    carry this fingerprint, and ``force`` is off). Otherwise the stage's build function
    writes into :meth:`start`'s folder; :meth:`Graph.build_node` publishes.
    """

    graph: Graph
    node: Node
    params: StageParams
    inputs: dict[str, dict[str, Any]]
    payload: dict[str, Any]
    fingerprint: str
    final: Path
    up_to_date: bool
    restored: bool = False
    dir: Path = field(init=False)
    _after: list[Callable[[], None]] = field(default_factory=list, repr=False)
    _cached: list[Path] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        self.dir = self.final.parent / f".{self.final.name}.building-{self.fingerprint}"

    def input_dir(self, node: Node) -> Path:
        """The published folder of one of this node's inputs."""
        if str(node) not in self.inputs:
            raise KeyError(f"{self.node} does not read {node}: add it to its stage's inputs")
        return self.graph.node_dir(self.params.all, node)

    def other(self, node: Node) -> Path:
        """The published folder of a node that is *not* an input (a cache to reuse, never
        something the result depends on)."""
        return self.graph.node_dir(self.params.all, node)

    def start(self, fresh: bool = False) -> Path:  # pragma: no mutate block
        """The building folder (created; kept from a killed build unless ``fresh``)."""
        if fresh and self.dir.exists():
            shutil.rmtree(self.dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        return self.dir

    def cached(self, files: Iterable[Path]) -> None:
        """Files outside the node's folder that its result lists and its readers read (a
        per-pair cache such as the flow pool): the manifest records them beside the
        published files (by path relative to the node's folder) and :func:`damage` checks
        them alike."""
        self._cached += [Path(f) for f in files]

    def after_publish(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` once the node is published (to remove what the result replaces)."""
        self._after.append(fn)

    def publish(self, **info: Any) -> Path:  # pragma: no mutate block
        """Write the manifest into the building folder and make it the published one; the
        previous result becomes a variant (without the temporary files a killed build left in
        the building folder). Returns the published folder."""
        for f in leftover_temporaries(self.dir):
            f.unlink()
        cache = digest_cache(self.params.all)
        files = {**output_files(self.dir, cache), **cached_files(self.final, self._cached, cache)}
        write_manifest(self.dir / "manifest.json", {**self.payload, "fingerprint": self.fingerprint,
                                                    **info, "files": files})
        swap_in(self.dir, self.final)
        for fn in self._after:
            fn()
        return self.final


# --- status -------------------------------------------------------------------------------------

@dataclass
class NodeStatus:
    """One line of :meth:`Graph.status`."""

    node: Node
    state: str  # "up to date" | "stale" | "missing" | "damaged"
    why: str
    path: Path
    fingerprint: str | None = None
    recorded: str | None = None


def _short(v: Any) -> str:
    s = repr(v)
    return s if len(s) <= 40 else s[:37] + "..."


def code_changes(rec: Mapping[str, Any], code: Mapping[str, str], n: int = 3) -> list[str]:
    """``["code changed since built: crops.py, flow/stage.py"]`` (the first ``n`` files
    whose code differs from what the manifest ``rec`` records), or [] if none does."""
    if "code" not in rec:
        return ["code not recorded (built before code entered fingerprints)"] if code else []
    files = codedigest.changed(rec["code"], dict(code))
    more = f" (+{len(files) - n} more)" if len(files) > n else ""
    return [f"code changed since built: {', '.join(files[:n])}{more}"] if files else []


def diff(old: Mapping[str, Any], new: Mapping[str, Any], n: int = 3) -> list[str]:
    """``key: old -> new`` for the (first ``n``) keys whose values differ."""
    keys = [k for k in sorted(set(old) | set(new)) if canonical(old.get(k)) != canonical(new.get(k))]
    out = [f"{k}: {_short(old.get(k, '-'))} -> {_short(new.get(k, '-'))}" for k in keys[:n]]
    return out + ([f"(+{len(keys) - n} more)"] if len(keys) > n else [])


# --- the graph ----------------------------------------------------------------------------------

class Graph:
    """The study's stages (declarations in data order) and everything that follows from them:
    nodes, inputs, folders, fingerprints, status, and the driver that builds nodes.

    ``gate_targets``: the make target that turns each gate on (for messages)."""

    def __init__(self, stages: Iterable[Stage], gate_targets: Mapping[str, str]) -> None:
        self.stages: dict[str, Stage] = {s.name: s for s in stages}
        self.gate_targets = dict(gate_targets)

    # -- structure --
    def stage(self, node: Node) -> Stage:
        return self.stages[node.stage]

    def inputs(self, node: Node, p: Params) -> tuple[Node, ...]:
        """The nodes whose artefacts ``node`` reads."""
        return tuple(self.stage(node).inputs(node, p))

    def chapter(self, node: Node) -> str:
        """The chapter (``"05"``) whose notebook builds ``node``."""
        s = self.stage(node)
        return s.parts[node.part][0] if node.part in s.parts else s.chapter

    def gate(self, node: Node) -> str | None:
        """The run parameter without which ``node`` is not built, or None."""
        s = self.stage(node)
        return s.parts[node.part][1] if node.part in s.parts else s.gate

    def nodes(self, p: Params, chapters: Iterable[str] | None = None) -> list[Node]:
        """Every node of a run with ``p`` (of ``chapters``, default all), by chapter, each
        after its inputs."""
        wanted = None if chapters is None else set(chapters)
        planned = [n for s in self.stages.values()
                   if wanted is None or s.chapters() & wanted for n in s.nodes(p)]
        if wanted is not None:
            planned = [n for n in planned if self.chapter(n) in wanted]
        known, order, seen = set(planned), [], set()

        def visit(n: Node) -> None:
            if n in seen:
                return
            seen.add(n)
            for i in self.inputs(n, p):
                if i in known:
                    visit(i)
            order.append(n)

        for n in planned:
            visit(n)
        return sorted(order, key=self.chapter)

    # -- where artefacts live --
    def node_dir(self, p: Params, node: Node) -> Path:  # pragma: no mutate block
        """The published folder of ``node`` (a source's: its data folder)."""
        s = self.stage(node)
        if s.source is not None:
            return s.source.location(p)
        rel = s.folder.format(method=node.method, part=node.part, key=node.key)
        return p.run_path / rel

    def recorded(self, p: Params, node: Node) -> dict[str, Any] | None:  # pragma: no mutate block
        """The manifest of ``node``'s published artefacts (None if never built)."""
        s = self.stage(node)
        if s.source is not None:
            return s.source.record(p)
        return read_manifest(self.node_dir(p, node) / "manifest.json")

    @digest_batch()
    def expected(self, p: Params, nodes: Iterable[Node] | None = None) -> dict[Node, str | None]:
        """Every node's fingerprint for ``p`` (None below a missing input)."""
        exp: dict[Node, str | None] = {}
        for node in self.nodes(p) if nodes is None else nodes:
            s = self.stage(node)
            if s.source is not None:
                exp[node] = s.source.fingerprint(p)
                continue
            ins = self.inputs(node, p)
            fps = {str(i): exp.get(i) if i in exp else self._recorded_fp(p, i) for i in ins}
            exp[node] = None if any(v is None for v in fps.values()) else fingerprint(
                payload(p, node, s.version, fps, s.code()))
        return exp

    def _recorded_fp(self, p: Params, node: Node) -> str | None:
        rec = self.recorded(p, node)
        return rec["fingerprint"] if rec else None

    @digest_batch()
    def status(self, p: Params) -> list[NodeStatus]:
        """Every node of the run: up to date, stale or missing, and why, in one line each.
        Runs nothing and writes nothing (file digests of real data are cached)."""
        exp = self.expected(p)
        out: dict[Node, NodeStatus] = {}
        for node in exp:
            path, rec, fp = self.node_dir(p, node), self.recorded(p, node), exp[node]
            if self.stage(node).source is not None:
                state, why = self.stage(node).source.status(p)
            elif rec is not None and fp is not None and rec["fingerprint"] == fp:
                broken = damage(path, rec, digest_cache(p))
                state, why = ("damaged", f"{broken}; the next run rebuilds it") if broken \
                    else ("up to date", "")
            else:
                waiting = [i for i in self.inputs(node, p) if out[i].state != "up to date"]
                state, why = self._stale(p, node, rec, fp, exp, waiting)
            out[node] = NodeStatus(node, state, why, path, fp, rec and rec["fingerprint"])
        return list(out.values())

    def _stale(self, p: Params, node: Node, rec: dict[str, Any] | None, fp: str | None,
               exp: Mapping[Node, str | None], waiting: list[Node]) -> tuple[str, str]:
        """(state, reason) of a node whose manifest does not carry ``fp``."""
        if rec is None:
            return "missing", "never built" + (f"; waits for {waiting[-1]}" if waiting else "")
        s = self.stage(node)
        reasons = []
        if rec.get("version") != s.version:
            reasons.append(f"code version {rec.get('version')} -> {s.version}")
        reasons += code_changes(rec, s.code())
        reasons += diff(rec.get("params", {}), values(p, node))
        changed = [f"input {i} " + ("changed" if i not in waiting else "is missing"
                                    if exp[i] is None and self.stage(i).source else "is stale")
                   for i in self.inputs(node, p) if rec.get("inputs", {}).get(str(i)) != exp[i]]
        reasons += changed[:1] + ([f"(+{len(changed) - 1} more inputs)"] if len(changed) > 1
                                  else [])
        final = self.node_dir(p, node)
        if fp is not None and (variant_dir(final, fp) / "manifest.json").is_file():
            reasons.append("a kept copy matches and will be restored, nothing recomputed")
        return "stale", "; ".join(reasons) or "fingerprint differs"

    # -- the driver --
    def begin(self, p: Params, node: Node) -> Build:  # pragma: no mutate block
        """Start building ``node``: read its inputs' manifests (:class:`MissingInput` if one
        was never built or its files are damaged: nothing is built from a file that is not
        what was published), compute its fingerprint, and decide whether anything must be
        done (a kept variant with this fingerprint is restored instead of recomputed)."""
        recs: dict[str, dict[str, Any]] = {}
        for i in self.inputs(node, p):
            rec = self.recorded(p, i)
            if rec is None:
                raise MissingInput(f"{node} reads {i}, which has not been built: {self.how(i)}")
            broken = self.damaged(p, i, rec)
            if broken:
                raise MissingInput(f"{node} reads {i}, whose files are damaged ({broken}): "
                                   f"rebuild it, {self.how(i)}")
            recs[str(i)] = rec
        s = self.stage(node)
        pl = payload(p, node, s.version, {k: r["fingerprint"] for k, r in recs.items()},
                     s.code())
        fp = fingerprint(pl)
        final = self.node_dir(p, node)
        current = read_manifest(final / "manifest.json")
        up = (not p.force and current is not None and current["fingerprint"] == fp
              and damage(final, current, digest_cache(p)) is None)
        b = Build(self, node, StageParams(p, node), recs, pl, fp, final, up)
        if not up and not p.force and (variant_dir(final, fp) / "manifest.json").is_file():
            swap_in(variant_dir(final, fp), final)
            b.up_to_date = b.restored = True
        return b

    def build_node(self, p: Params, node: Node, progress: bool = False) -> Path:  # pragma: no mutate block
        """Bring one node up to date (inputs must be built): the one place where a stage's
        build function runs and its result is published. Returns the published folder."""
        s = self.stage(node)
        if s.source is not None:
            with DiskFull.guard(p.dataroot_path, f"making {node}", "dataroot (--set dataroot=...)"):
                s.source.ensure(p, progress)
            return s.source.location(p)
        b = self.begin(p, node)
        if not b.up_to_date:
            if s.build is None:
                raise TypeError(f"stage {s.name} declares no build function")
            with DiskFull.guard(p.run_path, f"building {node}"):
                b.publish(**(s.build(b, progress) or {}))
        return b.final

    @digest_batch()
    def build(self, p: Params, chapters: Iterable[str] | None = None,
              progress: bool = False, at_once: AtOnce | None = None
              ) -> list[Node]:  # pragma: no mutate block
        """Build the stale nodes of ``chapters`` (default: all) in data order; a gated node
        only when its gate is on. Returns the nodes considered.

        ``at_once``: builds several stale nodes at once (:func:`flowmod.pipeline.build`'s
        worker processes). It is given each run of consecutive nodes of
        :attr:`Stage.parallel` stages of which none reads another and at least two are
        stale; every other node is built here, one after the other."""
        done = [n for n in self.nodes(p, chapters)
                if self.gate(n) is None or getattr(p, self.gate(n))]
        for batch in self._batches(p, done, at_once is not None):
            stale = [n for n in batch if not self.begin(p, n).up_to_date] if len(batch) > 1 \
                else batch
            if at_once is not None and len(stale) > 1:
                at_once(stale)
            else:
                for node in stale:
                    self.build_node(p, node, progress)
        return done

    def _batches(self, p: Params, nodes: list[Node], parallel: bool) -> list[list[Node]]:
        """``nodes`` cut into runs that may build at once (with ``parallel``: consecutive
        nodes of parallel stages, none an input of another); every other node alone."""
        out: list[list[Node]] = []
        for n in nodes:
            last = out[-1] if out else []
            if (parallel and last and self.stage(n).parallel and self.stage(last[0]).parallel
                    and not set(self.inputs(n, p)) & set(last)):
                last.append(n)
            else:
                out.append([n])
        return out

    # -- reading --
    def current(self, p: Params, node: Node) -> bool:
        """True iff ``node``'s published artefacts carry the fingerprint that its inputs'
        published artefacts and ``p``'s values of its parameters give now: nothing it read
        was rebuilt and none of its parameters changed since. Unlike :meth:`status` it looks
        one step up only, so a notebook that declares just its chapter's parameters can ask."""
        rec = self.recorded(p, node)
        if rec is None:
            return False
        exp = self.expected(p, [node])
        return (exp[node] is not None and rec.get("fingerprint") == exp[node]
                and self.damaged(p, node, rec) is None)

    def damaged(self, p: Params, node: Node, rec: dict[str, Any] | None = None) -> str | None:
        """What is wrong with ``node``'s published files (:func:`damage`), or None. ``rec``:
        its manifest, where the caller has read it already."""
        if self.stage(node).source is not None:
            return None
        rec = self.recorded(p, node) if rec is None else rec
        return damage(self.node_dir(p, node), rec, digest_cache(p))

    @digest_batch()
    def built(self, p: Params, node: Node) -> bool:  # pragma: no mutate block
        """:meth:`current` for ``node`` and, recursively, for every input of its chapter (a
        chapter's result counts only if what the chapter itself built under it is current)."""
        ch = self.chapter(node)
        return self.current(p, node) and all(
            self.built(p, i) for i in self.inputs(node, p) if self.chapter(i) == ch)

    def published(self, p: Params, node: Node) -> Path:  # pragma: no mutate block
        """The published folder of ``node`` for reading; :class:`MissingInput` if never built."""
        if self.recorded(p, node) is None:
            raise MissingInput(f"{node} has not been built: {self.how(node)}")
        return self.node_dir(p, node)

    def how(self, node: Node) -> str:
        """How to build ``node``: the chapter to run (and its gate where gated)."""
        ch, flag = self.chapter(node), self.gate(node)
        if flag:
            return (f"run chapter {ch} with {flag}=true first ({self.gate_targets[flag]}, or "
                    f"python -m flowmod.runner --only {ch} --set {flag}=true)")
        return f"run chapter {ch} first (python -m flowmod.runner --only {ch})"
