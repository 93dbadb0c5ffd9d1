"""The docs that check themselves (issue 51): ARCHITECTURE.md against the code, and the
README's size, tables, paragraphs and links. Quick: text and syntax trees only (and the
pipeline's stage list), no data, no world.

How ARCHITECTURE.md names a module (inline code, outside fenced blocks):

* by path: ``dag.py``, ``flow/stage.py``, ``world/truth``, ``flowmod/chapters/ch01_world.py``;
  a package by its folder, ``world/``;
* dotted: ``flowmod.runner``, ``dag.Graph.build_node``, ``ch07_evaluation.table3`` (the
  longest prefix that is a module; the package of the bullet it sits in is tried first);
* by its bare name in the bullet of its package (``- `world/`: ... `scene`, `layout` ...``).

A path or a ``flowmod.`` name that is no module fails the test; so does a module that the
page never names. The stage list is the names after the colon of the paragraph that starts ``Stages, in
data order``; the entry points are the modules named under ``**Entry points**``.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "src" / "flowmod"
ARCH = ROOT / "ARCHITECTURE.md"
README = ROOT / "README.md"

#: Every module as its path under src/flowmod without ".py" (``world/truth``); packages'
#: ``__init__`` are the packages themselves (named by their folder).
MODULES = sorted(str(p.relative_to(PKG).with_suffix("")) for p in PKG.rglob("*.py")
                 if p.name != "__init__.py")
#: The README's budget (issue 51): the first screen says what flowmod is, its two commands
#: and their cost, and where to read on; the detail lives in docs/ and ARCHITECTURE.md.
README_MAX_BYTES = 12 * 1024
TABLE_CELL_MAX = 300
PARAGRAPH_MAX = 1000

PACKAGES = sorted(str(p.parent.relative_to(PKG)) for p in PKG.rglob("*/__init__.py"))


def _text(path: Path) -> str:
    """A Markdown file without its fenced blocks (code shown, not names claimed)."""
    return re.sub(r"```.*?```", "", path.read_text(), flags=re.S)


def _spans(text: str) -> list[str]:
    return [" ".join(s.split()) for s in re.findall(r"`([^`]+)`", text)]


def _bullets(text: str) -> list[tuple[str | None, str]]:
    """(package, text) of each bullet or paragraph: a bullet that opens with a package's
    folder (``- `flow/`: ...``) is that package's."""
    out = []
    for block in re.split(r"\n(?=- |\*\*|#)|\n\s*\n", text):
        m = re.match(r"- `([a-z_]+)/`", block)
        pkg = m.group(1) if m and m.group(1) in PACKAGES else None
        out.append((pkg, block))
    return out


def _placeholder(span: str) -> bool:
    return bool(re.search(r"[<>*{}\s]|NN|\bchNN", span))


def resolve(span: str, package: str | None = None) -> tuple[str | None, bool]:
    """(the module ``span`` names or None, whether ``span`` claims to name one)."""
    s = span.strip()
    if _placeholder(s) or s.startswith((".", "-")):
        return None, False
    claims = False
    for prefix in ("src/flowmod/", "flowmod/", "flowmod."):
        if s.startswith(prefix):
            s, claims = s[len(prefix):], True
    if "/" in s or s.endswith(".py"):
        path = s.removesuffix(".py").rstrip("/")
        first = path.split("/")[0]
        if not (claims or first in PACKAGES or ("/" not in path and s.endswith(".py"))):
            return None, False  # another folder of the repository (runs/, tests/, ...)
        if s.endswith("/") and path in PACKAGES:
            return path, True
        return (path if path in MODULES or path in PACKAGES else None), True
    parts = s.split(".")
    if not all(p.isidentifier() for p in parts):
        return None, False
    names = {m.split("/")[-1] for m in MODULES + PACKAGES} | set(PACKAGES)
    if not claims and parts[0] not in names:
        return None, False  # an attribute, a parameter, a variable: not a module's name
    if not claims and len(parts) == 1 and package is None and s not in PACKAGES:
        return None, False  # a bare word outside a package's bullet: too ambiguous to claim
    roots = ([package] if package else []) + [""] + PACKAGES
    for n in range(len(parts), 0, -1):
        for root in roots:
            cand = "/".join(([root] if root else []) + parts[:n])
            if cand in MODULES or cand in PACKAGES:
                return cand, True
    return None, claims


def named_modules(text: str) -> tuple[set[str], list[str]]:
    """(every module or package the text names, the spans that claim a module that is not
    there)."""
    named, missing = set(), []
    for package, block in _bullets(text):
        for span in _spans(block):
            for word in re.split(r"\s*\+\s*", span):  # `context` + `inputs`
                mod, claims = resolve(word, package)
                if mod:
                    named.add(mod)
                elif claims:
                    missing.append(span)
    return named, missing


def test_every_module_architecture_names_exists():
    _, missing = named_modules(_text(ARCH))
    assert not missing, f"ARCHITECTURE.md names modules that src/flowmod lacks: {missing}"


def test_architecture_names_every_module():
    named, _ = named_modules(_text(ARCH))
    unnamed = [m for m in MODULES + PACKAGES if m not in named]
    assert not unnamed, f"modules ARCHITECTURE.md never names (add each to its layer): {unnamed}"


def _line(text: str, start: str) -> str:
    """The paragraph of ``text`` that starts with ``start``."""
    for para in re.split(r"\n\s*\n", text):
        if para.lstrip().startswith(start):
            return para
    raise AssertionError(f"ARCHITECTURE.md has no paragraph starting {start!r}")


def test_the_stage_list_is_pipeline_stages():
    from flowmod import pipeline

    listed = _spans(_line(_text(ARCH), "Stages, in data order").split(":", 1)[1])
    assert listed == [s.name for s in pipeline.STAGES], (
        "ARCHITECTURE.md's 'Stages, in data order' line differs from pipeline.STAGES")


def _entry_modules() -> set[str]:
    """The modules that define a top-level ``main`` (each with its ``__main__`` block)."""
    out = set()
    for m in MODULES:
        src = (PKG / f"{m}.py").read_text()
        tree = ast.parse(src)
        if any(isinstance(n, ast.FunctionDef) and n.name == "main" for n in tree.body):
            assert 'if __name__ == "__main__"' in src, f"{m}.py: main() but no __main__ block"
            out.add(m)
    return out


def test_the_entry_points_are_the_modules_with_main():
    text = _text(ARCH)
    section = text.split("**Entry points**", 1)[1].split("\n## ", 1)[0]
    named, missing = named_modules(section)
    assert not missing, f"ARCHITECTURE.md's entry points name no module: {missing}"
    assert named == _entry_modules(), (
        f"entry points: ARCHITECTURE.md names {sorted(named)}, the modules with main() are "
        f"{sorted(_entry_modules())}")


@pytest.mark.parametrize(("span", "package", "want"), [
    ("dag.py", None, ("dag", True)),
    ("world/truth", None, ("world/truth", True)),
    ("flow/stage.py", None, ("flow/stage", True)),
    ("chapters/ch07_evaluation.py", None, ("chapters/ch07_evaluation", True)),
    ("ch07_evaluation.table3", "chapters", ("chapters/ch07_evaluation", True)),
    ("flowmod.report.book", None, ("report/book", True)),
    ("dag.Graph.build_node", None, ("dag", True)),
    ("scene", "world", ("world/scene", True)),
    ("scene", None, (None, False)),
    ("runs/<profile>/", None, (None, False)),
    ("weights/fastflownet_synth/", None, (None, False)),
    ("tests/test_sources.py", None, (None, False)),
    ("nosuch.py", None, (None, True)),
    ("world/nosuch", None, (None, True)),
    ("flowmod.nosuch", None, (None, True)),
])
def test_the_reader_of_module_names(span, package, want):
    assert resolve(span, package) == want
# -- README -----------------------------------------------------------------------------


def test_the_readme_is_short():
    size = README.stat().st_size
    assert size <= README_MAX_BYTES, (
        f"README.md is {size} bytes, over {README_MAX_BYTES}: move detail to docs/")


def test_no_readme_table_cell_is_long():
    long = [c.strip()[:60] for line in _text(README).splitlines()
            if line.lstrip().startswith("|") for c in line.strip().strip("|").split("|")
            if len(c.strip()) > TABLE_CELL_MAX]
    assert not long, f"README.md table cells over {TABLE_CELL_MAX} characters: {long}"


def test_no_readme_paragraph_is_long():
    long = [p.strip()[:60] for p in re.split(r"\n\s*\n", _text(README))
            if not p.lstrip().startswith("|") and len(" ".join(p.split())) > PARAGRAPH_MAX]
    assert not long, f"README.md paragraphs over {PARAGRAPH_MAX} characters: {long}"


def test_every_relative_link_of_the_docs_resolves():
    docs = [README, ARCH, *sorted((ROOT / "docs").glob("*.md"))]
    broken = []
    for doc in docs:
        for target in re.findall(r"\]\(([^)\s]+)\)", _text(doc)):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            if not (doc.parent / target.split("#")[0]).exists():
                broken.append(f"{doc.relative_to(ROOT)}: {target}")
    assert not broken, f"relative links to files that are not there: {broken}"
