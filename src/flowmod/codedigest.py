"""What code an artefact was made by: a digest of each flowmod module a stage runs.

A stage's code is the module that holds its build function and, transitively, every flowmod
module it imports (at module level or inside a function), found by reading the sources'
syntax trees (nothing is imported). A ``from package import name`` counts the module that
``name`` comes from (the submodule, or the module the package's ``__init__`` re-exports it
from), not every module the package holds. Left out are :data:`BOOKKEEPING`: the modules that
decide where and how artefacts are stored and named, never what they hold (parameter values
enter fingerprints by value, :mod:`flowmod.dag`).

A module's digest hashes its syntax tree without docstrings, so an edit of a comment, a
docstring or the layout changes nothing, and any edit of what the code does changes the
digest of that module and of every stage whose code includes it. The granularity is the
module: an edit to one function makes stale every stage that imports its module.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import tempfile
from functools import cache
from pathlib import Path

#: The folder of the ``flowmod`` package (``src/flowmod``).
PACKAGE_ROOT = Path(__file__).resolve().parent
PACKAGE = "flowmod"

#: Modules that never decide what an artefact holds: the engine and its bookkeeping (where
#: artefacts live, atomic writes, fingerprints, locks, progress bars, the parameters'
#: declaration, whose values enter fingerprints themselves) and this module.
BOOKKEEPING = frozenset({
    "flowmod", "flowmod.dag", "flowmod.artefacts", "flowmod.paths", "flowmod.progress",
    "flowmod.lock", "flowmod.environment", "flowmod.params", "flowmod.pipeline",
    "flowmod.codedigest",
})

#: Modules that a module's code runs without importing them: those that register into it
#: (the flow estimators a stage looks up by name in the registry run the modules that
#: define them). ``tests/test_provenance.py`` checks that every registering module is here.
IMPLIED = {"flowmod.flow.registry": ("flowmod.flow.estimators", "flowmod.flow.networks")}


def module_file(module: str, root: Path = PACKAGE_ROOT) -> Path | None:
    """The source file of ``module`` (``flowmod.x.y``) under ``root``, or None (not flowmod's,
    or no such module)."""
    parts = module.split(".")
    if parts[0] != PACKAGE:
        return None
    base = root.joinpath(*parts[1:])
    for f in (base.with_suffix(".py"), base / "__init__.py"):
        if f.is_file():
            return f
    return None


def _is_package(module: str, root: Path) -> bool:
    f = module_file(module, root)
    return f is not None and f.name == "__init__.py"


def _absolute(module: str, level: int, name: str | None, root: Path) -> str:
    """The absolute name of a (possibly relative) import inside ``module``."""
    if not level:
        return name or ""
    base = module.split(".")
    base = base if _is_package(module, root) else base[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join(base + ([name] if name else []))


@cache
def _tree(path: Path) -> ast.Module:
    """``path``'s syntax tree without docstrings (parsed once per process)."""
    return _strip_docstrings(ast.parse(path.read_text(), filename=str(path)))


def _reexports(package: str, root: Path) -> dict[str, str]:
    """``{name: module}`` for the names a package's ``__init__`` imports from flowmod modules."""
    f = module_file(package, root)
    out: dict[str, str] = {}
    if f is None:
        return out
    for node in ast.walk(_tree(f)):
        if isinstance(node, ast.ImportFrom):
            src = _absolute(package, node.level, node.module, root)
            for a in node.names:
                sub = f"{src}.{a.name}"
                out[a.asname or a.name] = sub if module_file(sub, root) else src
    return out


def _resolve(package: str, name: str, root: Path, seen: frozenset[str] = frozenset()) -> str:
    """The module that ``from package import name`` depends on."""
    sub = f"{package}.{name}"
    if module_file(sub, root) is not None:
        return sub
    target = _reexports(package, root).get(name)
    if target is None or target in seen or not _is_package(target, root):
        return target or package
    return _resolve(target, name, root, seen | {target})


def _bound(tree: ast.Module, module: str, root: Path) -> tuple[set[str], dict[str, str]]:
    """The modules an import statement names ({``from x import name``: the module ``name``
    comes from}), and ``{local name: package}`` for the names bound to a package."""
    deps: set[str] = set()
    packages: dict[str, str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                deps.add(a.name)
                if a.asname and _is_package(a.name, root):
                    packages[a.asname] = a.name
        elif (isinstance(node, ast.Call) and isinstance(node.func, (ast.Attribute, ast.Name))
              and getattr(node.func, "attr", getattr(node.func, "id", "")) == "import_module"
              and node.args and isinstance(node.args[0], ast.Constant)):
            deps.add(str(node.args[0].value))  # importlib.import_module("flowmod.x")
        elif isinstance(node, ast.ImportFrom):
            src = _absolute(module, node.level, node.module, root)
            if not _is_package(src, root):
                deps.add(src)
                continue
            for a in node.names:
                dep = _resolve(src, a.name, root)
                if _is_package(dep, root):
                    packages[a.asname or a.name] = dep
                else:
                    deps.add(dep)
    return deps, packages


def _package_uses(tree: ast.Module, packages: dict[str, str], root: Path) -> set[str]:
    """The modules reached through attributes of names bound to a package
    (``world.true_velocity``: the module it comes from); a package name used otherwise
    counts the package's ``__init__`` (and so everything it imports)."""
    out: set[str] = set()
    bases: dict[str, int] = {}
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in packages):
            out.add(_resolve(packages[node.value.id], node.attr, root))
            bases[node.value.id] = bases.get(node.value.id, 0) + 1
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and node.id in packages:
            bases[node.id] = bases.get(node.id, 0) - 1
    return out | {packages[n] for n, left in bases.items() if left < 0}


@cache
def imports(module: str, root: Path = PACKAGE_ROOT) -> frozenset[str]:
    """The flowmod modules ``module`` imports directly (anywhere in its source)."""
    f = module_file(module, root)
    if f is None:
        return frozenset()
    deps, packages = _bound(_tree(f), module, root)
    deps |= _package_uses(_tree(f), packages, root) | set(IMPLIED.get(module, ()))
    return frozenset(m for m in deps if m != module and module_file(m, root) is not None)


def closure(module: str, root: Path = PACKAGE_ROOT) -> list[str]:
    """``module`` and every flowmod module it imports, transitively, less
    :data:`BOOKKEEPING` (sorted)."""
    todo, seen = [module], set()
    while todo:
        m = todo.pop()
        if m in seen or module_file(m, root) is None:
            continue
        seen.add(m)
        todo += sorted(imports(m, root) - BOOKKEEPING)
    return sorted(seen - BOOKKEEPING)


def _strip_docstrings(tree: ast.Module) -> ast.Module:
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and body and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return tree


@cache
def source_digest(path: Path) -> str:
    """16 hex digits of sha256 of ``path``'s syntax tree without docstrings (comments and
    layout never reach the tree)."""
    return hashlib.sha256(ast.dump(_tree(path)).encode()).hexdigest()[:16]


def relative_name(path: Path, root: Path = PACKAGE_ROOT) -> str:
    """A module file as messages name it, relative to the package (``crops.py``,
    ``flow/stage.py``)."""
    return path.relative_to(root).as_posix()


@cache
def _digests(module: str, root: Path) -> tuple[tuple[str, str], ...]:
    kept = _stored(root)["modules"].get(module)
    if kept is not None:
        return tuple((str(f), str(d)) for f, d in kept)
    files = [module_file(m, root) for m in closure(module, root)]
    out = tuple((relative_name(f, root), source_digest(f)) for f in files if f is not None)
    _store(root, "modules", {module: [list(x) for x in out]})
    return out


def digests(module: str, root: Path = PACKAGE_ROOT) -> dict[str, str]:
    """``{file relative to the package: digest}`` of :func:`closure` ``(module)``: the code a
    stage whose build function lives in ``module`` runs ({} for a module outside flowmod).
    Computed once per process (the sources of a running process do not change under it)."""
    return dict(_digests(module, root))


def code_id(module: str, root: Path = PACKAGE_ROOT) -> str:
    """16 hex digits naming :func:`digests` ``(module)`` as a whole."""
    blob = "".join(f"{k}={v};" for k, v in sorted(digests(module, root).items()))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def forget() -> None:
    """Drop what this process has read and computed (for a process that edits sources and
    reads them again, such as a test: a running stage runs the code it imported, so the
    digests are otherwise read once per process)."""
    for fn in (_tree, imports, source_digest, _digests, package_key, _stored):
        fn.cache_clear()


def changed(old: dict[str, str], new: dict[str, str]) -> list[str]:
    """The files whose digest differs between two :func:`digests` records (added, removed
    or edited), sorted."""
    return sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))


# --------------------------------------------------------------------------------------------
# the results kept between processes
# --------------------------------------------------------------------------------------------
# Reading the syntax trees takes one to three seconds, and every process that asks whether a
# node is current (each notebook's kernel, each CLI) asked again. The results are kept in
# one file in the package's ``__pycache__``, under a key that hashes every source file's
# bytes: any edit of any file makes another key, so a kept result is always that of the
# code on disk. A file that cannot be read or written only costs the time.

#: The file that keeps the results, inside the package's ``__pycache__`` folder.
CACHE_NAME = "flowmod-codedigest.json"


@cache
def package_key(root: Path = PACKAGE_ROOT) -> str:
    """16 hex digits of sha256 over every ``*.py`` file under ``root`` (its path relative
    to ``root`` and its bytes): the key of the kept results."""
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:16]


@cache
def _stored(root: Path) -> dict:
    """The kept results of the code under ``root`` now: ``{"key", "sources": {file:
    digest}, "modules": {module: [[file, digest], ...]}}`` (empty where none are kept)."""
    empty = {"key": package_key(root), "sources": {}, "modules": {}}
    try:
        kept = json.loads((root / "__pycache__" / CACHE_NAME).read_text())
    except (OSError, ValueError):
        return empty
    ok = (isinstance(kept, dict) and kept.get("key") == empty["key"]
          and isinstance(kept.get("sources"), dict) and isinstance(kept.get("modules"), dict))
    return kept if ok else empty


def _store(root: Path, kind: str, values: dict[str, object]) -> None:
    """Keep ``values`` under ``kind`` (in memory, and in the file: a temporary file, then a
    rename; where the folder cannot be written, in memory only)."""
    kept = _stored(root)
    kept[kind].update(values)
    folder = root / "__pycache__"
    tmp = None
    try:
        folder.mkdir(exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".codedigest.", suffix=".tmp", dir=folder)
        with os.fdopen(fd, "w") as out:
            json.dump(kept, out, sort_keys=True)
        os.chmod(tmp, 0o644)
        os.replace(tmp, folder / CACHE_NAME)
    except OSError:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


def source_digests(root: Path | None = None) -> dict[str, str]:
    """``{file relative to the package: digest}`` (:func:`source_digest`) of every ``*.py``
    under ``root`` (default :data:`PACKAGE_ROOT`), sorted by file."""
    root = PACKAGE_ROOT if root is None else root
    files = {relative_name(f, root): f for f in sorted(root.rglob("*.py"))}
    kept = _stored(root)["sources"]
    missing = {n: source_digest(f) for n, f in files.items() if n not in kept}
    if missing:
        _store(root, "sources", missing)
    return {n: str(kept[n]) for n in files}
