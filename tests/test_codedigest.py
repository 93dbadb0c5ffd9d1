"""Code as an input: which flowmod modules a stage runs, their digests, and the staleness
an edit causes (quick; the edit of a scratch copy of the real package is in
test_provenance)."""

from __future__ import annotations

import ast
import json
import textwrap
from pathlib import Path
from typing import Any

import pytest

from flowmod import codedigest, dag
from flowmod.codedigest import closure, digests, source_digest
from flowmod.params import validate


def write_package(root: Path, files: dict[str, str]) -> Path:
    """A scratch ``flowmod`` package under ``root`` (``{relative path: source}``)."""
    pkg = root / "flowmod"
    for rel, src in {"__init__.py": "", **files}.items():
        f = pkg / rel
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(textwrap.dedent(src))
    return pkg


SCRATCH = {
    "a.py": """
        import importlib
        from flowmod import b, dag
        from flowmod.pkg import thing

        def f():
            from flowmod import late  # inside a function counts too
            return importlib.import_module("flowmod.dynamic")
    """,
    "b.py": "X = 1\n",
    "late.py": "Y = 2\n",
    "dynamic.py": "Z = 3\n",
    "dag.py": "from flowmod import unrelated\n",
    "unrelated.py": "W = 4\n",
    "pkg/__init__.py": "from flowmod.pkg.inner import thing\n",
    "pkg/inner.py": "thing = 5\n",
    "pkg/other.py": "from flowmod import unrelated\n",
    "attr.py": "from flowmod import pkg\nV = pkg.thing\n",
    "bare.py": "from flowmod import pkg\nV = pkg\n",
}


def test_closure_follows_every_import_but_bookkeeping_and_unused_package_parts(tmp_path):
    pkg = write_package(tmp_path, SCRATCH)
    assert closure("flowmod.a", pkg) == ["flowmod.a", "flowmod.b", "flowmod.dynamic",
                                         "flowmod.late", "flowmod.pkg.inner"]
    # a package's name used for an attribute counts the module the attribute comes from
    assert closure("flowmod.attr", pkg) == ["flowmod.attr", "flowmod.pkg.inner"]
    # used bare, it counts the package's __init__ and what that imports
    assert closure("flowmod.bare", pkg) == ["flowmod.bare", "flowmod.pkg", "flowmod.pkg.inner"]
    assert digests("numpy", pkg) == {} and closure("flowmod.missing", pkg) == []
    assert set(digests("flowmod.a", pkg)) == {"a.py", "b.py", "dynamic.py", "late.py",
                                              "pkg/inner.py"}


def test_a_relative_import_is_resolved_like_an_absolute_one(tmp_path):
    pkg = write_package(tmp_path, {"pkg/__init__.py": "", "pkg/one.py": "from . import two\n"
                                   "from ..b import X\n", "pkg/two.py": "", "b.py": "X = 1\n"})
    assert closure("flowmod.pkg.one", pkg) == ["flowmod.b", "flowmod.pkg.one", "flowmod.pkg.two"]


def fresh_digest(f: Path) -> str:
    """:func:`source_digest` of ``f`` as it is now (the per-process caches dropped)."""
    codedigest.forget()
    return source_digest(f)


def test_docstrings_comments_and_layout_do_not_change_a_digest_code_does(tmp_path):
    f = tmp_path / "m.py"
    f.write_text('"""Module."""\n\ndef g(x):\n    """Doc."""\n    return x * 3  # three\n')
    base = fresh_digest(f)
    f.write_text('"""Other words."""\n\n\ndef g(x):\n    # a comment\n    return x * 3\n')
    assert fresh_digest(f) == base
    f.write_text('"""Module."""\n\ndef g(x):\n    """Doc."""\n    return x * 2.5\n')
    assert fresh_digest(f) != base and len(base) == 16


def test_changed_names_added_removed_and_edited_files():
    old = {"a.py": "1", "b.py": "2", "c.py": "3"}
    assert codedigest.changed(old, {"a.py": "1", "b.py": "9", "d.py": "4"}) == [
        "b.py", "c.py", "d.py"]
    assert codedigest.changed(old, dict(old)) == []


def test_the_real_stages_run_the_code_they_import():
    crops = digests("flowmod.crops")
    assert {"crops.py", "geometry.py", "flow/stage.py", "flow/store.py"} <= set(crops)
    # the estimators a stage looks up by name in the registry are its code too
    assert {"flow/estimators.py", "flow/networks.py"} <= set(crops)
    assert not {"train.py", "dag.py", "params.py", "artefacts.py"} & set(crops)
    select = digests("flowmod.select")
    assert "select.py" in select and "world/truth.py" in select
    assert not [f for f in select if f.startswith(("flow/", "world/dataset"))], select
    assert set(digests("flowmod.train")) >= {"train.py", "model.py", "crops.py", "metrics.py"}


def test_every_module_that_registers_an_estimator_is_implied_by_the_registry():
    registering = set()
    for f in sorted(codedigest.PACKAGE_ROOT.rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ClassDef) and any(
                    getattr(d, "id", None) == "register_estimator" for d in node.decorator_list):
                rel = f.relative_to(codedigest.PACKAGE_ROOT.parent).with_suffix("")
                registering.add(".".join(rel.parts))
    assert registering == set(codedigest.IMPLIED["flowmod.flow.registry"])


# --- the engine: an edit of a stage's code makes it and its readers stale -----------------

def build_out(b: dag.Build, progress: bool) -> dict[str, Any]:
    (b.start(fresh=True) / "out.json").write_text(json.dumps({"node": str(b.node)}))
    return {}


def build_reader(b: dag.Build, progress: bool) -> dict[str, Any]:
    src = (b.input_dir(dag.Node("select")) / "out.json").read_text()
    (b.start(fresh=True) / "out.json").write_text(src)
    return {}


def test_a_stage_whose_code_changed_is_stale_and_names_the_files(tmp_path):
    """The toy stages' build functions stand for two real flowmod modules (labels and
    geometry); pointing one at another real module is an edit of the code it runs."""
    build_out.__module__, build_reader.__module__ = "flowmod.labels", "flowmod.geometry"
    g = dag.Graph([
        dag.Stage("select", 1, "02", "select", "", nodes=lambda p: [dag.Node("select")],
                  build=build_out),
        dag.Stage("train", 1, "06", "train", "", nodes=lambda p: [dag.Node("train")],
                  inputs=lambda n, p: (dag.Node("select"),), build=build_reader),
    ], {})
    p = validate({"run_dir": str(tmp_path / "runs"), "dataroot": str(tmp_path),
                  "synthetic": False})
    g.build(p)
    rec = g.recorded(p, dag.Node("select"))
    assert rec["code"] == {"labels.py": source_digest(codedigest.PACKAGE_ROOT / "labels.py")}
    assert {s.state for s in g.status(p)} == {"up to date"}
    try:
        build_out.__module__ = "flowmod.metrics"
        st = {str(s.node): s for s in g.status(p)}
        assert st["select"].state == "stale"
        assert st["select"].why == "code changed since built: labels.py, metrics.py"
        assert st["train"].why == "input select is stale"
        build_reader.__module__ = "flowmod.metrics"
        assert {str(s.node): s.why for s in g.status(p)}["train"] == (
            "code changed since built: geometry.py, metrics.py; input select is stale")
    finally:
        build_out.__module__ = build_reader.__module__ = __name__


def test_code_changes_says_when_a_manifest_predates_code_digests():
    assert dag.code_changes({}, {"crops.py": "1"}) == [
        "code not recorded (built before code entered fingerprints)"]
    assert dag.code_changes({}, {}) == []
    many = {f"m{i}.py": "1" for i in range(5)}
    assert dag.code_changes({"code": {}}, many) == [
        "code changed since built: m0.py, m1.py, m2.py (+2 more)"]


@pytest.mark.parametrize("module", ["flowmod.crops", "flowmod.select"])
def test_a_digest_is_the_same_in_every_process(module):
    import subprocess
    import sys

    code = f"import json; from flowmod import codedigest; print(json.dumps(codedigest.digests({module!r})))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) == digests(module)


def test_the_runners_library_digest_ignores_docstrings_not_code(tmp_path, monkeypatch):
    """An executed chapter is reused while the library's code is unchanged: a docstring
    edit re-executes no notebook, a code edit every one."""
    import shutil

    from flowmod import runner

    copy = tmp_path / "flowmod"
    shutil.copytree(codedigest.PACKAGE_ROOT, copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(codedigest, "PACKAGE_ROOT", copy)
    codedigest.forget()
    base = runner.code_digest()
    f = copy / "report" / "viz.py"
    f.write_text(f.read_text().replace('"""', '"""Reworded. ', 1) + "\n# a comment\n")
    codedigest.forget()
    assert runner.code_digest() == base
    f.write_text(f.read_text() + "\nEXTRA = 1\n")
    codedigest.forget()
    assert runner.code_digest() != base


def _copy_package(tmp_path, monkeypatch):
    """A scratch copy of the package (no ``__pycache__``) as :data:`PACKAGE_ROOT`."""
    import shutil

    copy = tmp_path / "flowmod"
    shutil.copytree(codedigest.PACKAGE_ROOT, copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(codedigest, "PACKAGE_ROOT", copy)
    codedigest.forget()
    return copy


def test_a_later_process_reads_the_kept_digests_of_the_same_code(tmp_path, monkeypatch):
    """The digests are kept in the package's ``__pycache__`` under a key of every source
    file's bytes: a later process (here: after :func:`forget`) takes them from there, and
    any edit of any file makes them unread (another key)."""
    copy = _copy_package(tmp_path, monkeypatch)
    first = codedigest.digests("flowmod.crops", copy)
    sources = codedigest.source_digests()
    kept_file = copy / "__pycache__" / codedigest.CACHE_NAME
    kept = json.loads(kept_file.read_text())
    assert kept["key"] == codedigest.package_key(copy)
    assert kept["modules"]["flowmod.crops"] == [list(x) for x in first.items()]
    assert kept["sources"] == sources and len(sources) == len(list(copy.rglob("*.py")))
    assert oct(kept_file.stat().st_mode & 0o777) == "0o644"
    # what is kept is what a later process reads: a planted value shows it
    kept["modules"]["flowmod.crops"] = [["crops.py", "planted"]]
    kept["sources"]["crops.py"] = "planted"
    kept_file.write_text(json.dumps(kept))
    codedigest.forget()
    assert codedigest.digests("flowmod.crops", copy) == {"crops.py": "planted"}
    assert codedigest.source_digests()["crops.py"] == "planted"
    # an edit anywhere (a file no stage reads) gives another key: computed again
    (copy / "report" / "viz.py").write_text((copy / "report" / "viz.py").read_text() + "\n")
    codedigest.forget()
    assert codedigest.package_key(copy) != kept["key"]
    assert codedigest.digests("flowmod.crops", copy) == first
    assert codedigest.source_digests() == sources


@pytest.mark.parametrize("content", ["not json", "[1, 2]", '{"key": "x"}', ""])
def test_a_damaged_kept_file_is_computed_again_and_replaced(tmp_path, monkeypatch, content):
    copy = _copy_package(tmp_path, monkeypatch)
    fresh = codedigest.digests("flowmod.select", copy)
    kept_file = copy / "__pycache__" / codedigest.CACHE_NAME
    kept_file.write_text(content)
    codedigest.forget()
    assert codedigest.digests("flowmod.select", copy) == fresh
    assert json.loads(kept_file.read_text())["modules"]["flowmod.select"] == [
        list(x) for x in fresh.items()]


def test_a_package_folder_that_cannot_be_written_costs_only_time(tmp_path, monkeypatch):
    copy = _copy_package(tmp_path, monkeypatch)
    fresh = codedigest.digests("flowmod.select", copy)
    (copy / "__pycache__" / codedigest.CACHE_NAME).unlink()
    (copy / "__pycache__").rmdir()
    (copy / "__pycache__").write_text("a file where the folder should be")
    codedigest.forget()
    assert codedigest.digests("flowmod.select", copy) == fresh
    assert codedigest.source_digests()["select.py"] == codedigest.source_digest(copy / "select.py")
    assert sorted(p.name for p in copy.iterdir() if p.name.startswith(".")) == []


def test_a_kept_file_that_cannot_be_replaced_leaves_no_temporary_file(tmp_path, monkeypatch):
    copy = _copy_package(tmp_path, monkeypatch)
    fresh = codedigest.digests("flowmod.select", copy)
    kept_file = copy / "__pycache__" / codedigest.CACHE_NAME
    kept_file.unlink()
    (kept_file / "inside").mkdir(parents=True)  # a folder in its place: the rename fails
    codedigest.forget()
    assert codedigest.digests("flowmod.select", copy) == fresh
    assert sorted(p.name for p in (copy / "__pycache__").iterdir()) == [codedigest.CACHE_NAME]
