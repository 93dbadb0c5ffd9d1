"""Outputs declared with their stage (issue 51 item 2): each stage names the files its nodes
publish, only its own module names them, every published file is one it declared, and
`make gc` asks the stages for their caches."""

from __future__ import annotations

import ast
import fnmatch
import importlib
import re
from pathlib import Path

from flowmod import pipeline
from flowmod.paths import repo_root

SRC = repo_root() / "src" / "flowmod"
#: Output names another module may hold for another artefact of the same format: the
#: weights catalog names the shipped FastFlowNet file as chapter 12's networks name theirs.
SHARED = {"weights.pt": {"flowweights.py"}}


def _owners() -> dict[str, set[str]]:
    """Each fixed output name -> the source files of the stages that declare it."""
    out: dict[str, set[str]] = {}
    for s in pipeline.STAGES:
        if s.build is None:
            continue
        mod = Path(importlib.import_module(s.build.__module__).__file__).resolve()
        for name in s.outputs:
            if "{" not in name:
                out.setdefault(name, set()).add(str(mod))
    return out


def _strings(path: Path) -> set[str]:
    """The string constants of a module's code (docstrings left out)."""
    tree = ast.parse(path.read_text())
    docs = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr)}
    return {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)
            and isinstance(n.value, str) and id(n) not in docs}


def test_every_stage_declares_its_outputs():
    for s in pipeline.STAGES:
        assert bool(s.outputs) == (s.source is None), f"stage {s.name}: outputs {s.outputs}"
        assert all(re.fullmatch(r"[\w.{}-]+", o) for o in s.outputs), s.outputs


def test_only_the_owning_module_names_an_output_file():
    """No string in the code names another stage's output file: its readers go through the
    owning module's reader functions (``select.read_table``, ``train.model_file``,
    ``evaluate.read_frame`` ...)."""
    owners = _owners()
    offences = []
    for f in sorted(SRC.rglob("*.py")):
        here = str(f.resolve())
        for text in _strings(f):
            for name, mods in owners.items():
                if ((text == name or text.endswith("/" + name)) and here not in mods
                        and f.name not in SHARED.get(name, ())):
                    offences.append(f"{f.relative_to(SRC)} names {name!r} "
                                    f"(owned by {sorted(Path(m).name for m in mods)})")
    assert not offences, offences


def test_every_published_file_is_a_declared_output(smoke_built):
    """On the built smoke study: each node's folder holds its manifest and only files its
    stage declared (``{split}`` matching any name)."""
    by_stage = {s.name: [o.replace("{split}", "*") for s in [s] for o in s.outputs]
                for s in pipeline.STAGES}
    seen = set()
    for node in pipeline.nodes(smoke_built):
        if node.stage == "world" or not pipeline.built(smoke_built, node):
            continue
        folder = pipeline.published(smoke_built, node)
        for f in folder.iterdir():
            if f.name == "manifest.json" or f.name.startswith("."):
                continue
            seen.add(node.stage)
            assert any(fnmatch.fnmatch(f.name, o) for o in by_stage[node.stage]), (
                f"{node}: {f.name} is not among its stage's outputs {by_stage[node.stage]}")
    assert {"select", "crops", "train", "evaluate", "eevaluate"} <= seen, seen


def test_gc_asks_the_stages_for_their_caches():
    with_garbage = {s.name for s in pipeline.STAGES if s.garbage}
    assert with_garbage == {"flow", "crops"}
    text = (SRC / "pipeline.py").read_text()
    assert "index.parquet" not in text and "/pool" not in text  # no stage layout known here
