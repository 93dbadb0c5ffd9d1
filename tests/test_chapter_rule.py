"""One chapter rule, true everywhere (issue 51): every notebook ``NN_name.ipynb`` has its
backend ``flowmod/chapters/chNN_*.py`` and imports it, imports no other chapter's backend,
and types no number in its code cells (the parameters cell apart): its tables, figures and
glued numbers come from the backend, and the notebook shows the library's key calls where
they teach. Reads the notebooks' JSON and the backends' file names; no data, under a second.
"""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb"))
CHAPTERS = ROOT / "src" / "flowmod" / "chapters"
BACKEND = re.compile(r"ch\d\d_\w+")

#: The numbers a notebook's code may type, each with its reason (kept minimal; anything else
#: is a named constant or a function of the backend):
#: - a subscript that is a bare integer, ``x[0]``, ``.iloc[0]``, ``flow_methods[-1]``:
#:   picking the first or the last of something is a choice of element, not a quantity;
#: - the precision of what is shown, the second argument of ``round(value, digits)`` and of
#:   ``viz.table(df, precision)``: how many decimals a reader sees, like the format spec of
#:   an f-string (``f"{x:.1f}"``, a string, which no rule here reads).
PRECISION_CALLS = frozenset({"round", "table"})


def code_cells(nb: Path) -> list[tuple[int, str]]:
    """(index, source) of the notebook's code cells, the ``parameters`` cell left out; IPython
    lines (``%magic``, ``!shell``) blanked so that the rest parses as Python."""
    out = []
    for i, cell in enumerate(json.loads(nb.read_text())["cells"]):
        if cell["cell_type"] != "code" or "parameters" in cell["metadata"].get("tags", []):
            continue
        src = "".join(cell["source"])
        out.append((i, re.sub(r"(?m)^\s*[%!].*$", "", src)))
    return out


def backends_imported(tree: ast.AST) -> set[str]:
    """The chapter backends (``chNN_*``) a cell imports, in any spelling: ``from
    flowmod.chapters import chNN_x``, ``from flowmod.chapters.chNN_x import f``, ``import
    flowmod.chapters.chNN_x``."""
    out = set()
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.ImportFrom) and node.module == "flowmod.chapters":
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("flowmod.chapters."):
            names = [node.module.split(".")[2]]
        elif isinstance(node, ast.Import):
            names = [a.name.split(".")[2] for a in node.names
                     if a.name.startswith("flowmod.chapters.")]
        out |= {n for n in names if BACKEND.fullmatch(n)}
    return out


def _is_int(node: ast.AST) -> bool:
    """A bare integer, ``0`` or ``-1``."""
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        node = node.operand
    return isinstance(node, ast.Constant) and type(node.value) is int


def _constants(node: ast.AST) -> list[ast.Constant]:
    return [n for n in ast.walk(node) if isinstance(n, ast.Constant)]


def typed_numbers(source: str) -> list[tuple[int, object]]:
    """(line, value) of every number typed in ``source`` that no exemption above covers;
    booleans and strings are not numbers."""
    tree = ast.parse(source)
    exempt: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Subscript) and _is_int(node.slice):
            exempt |= {id(c) for c in _constants(node.slice)}
        elif isinstance(node, ast.Call) and len(node.args) >= 2:
            f = node.func
            name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) \
                else None
            if name in PRECISION_CALLS and _is_int(node.args[1]):
                exempt |= {id(c) for c in _constants(node.args[1])}
    return [(n.lineno, n.value) for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and type(n.value) in (int, float, complex)
            and id(n) not in exempt]


def _chapter(nb: Path) -> str:
    return nb.name[:2]


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 14, [nb.name for nb in NOTEBOOKS]


@pytest.mark.parametrize("nb", NOTEBOOKS, ids=lambda p: p.stem)
def test_a_notebook_imports_its_own_backend_and_no_other(nb):
    nn = _chapter(nb)
    own = [p.stem for p in CHAPTERS.glob(f"ch{nn}_*.py")]
    assert len(own) == 1, (f"{nb.name}: want one backend src/flowmod/chapters/ch{nn}_*.py "
                           f"(its tables, figures and glued numbers), found {own}")
    imported = set()
    for _, src in code_cells(nb):
        imported |= backends_imported(ast.parse(src))
    assert own[0] in imported, f"{nb.name} never imports its backend {own[0]}"
    others = sorted(imported - {own[0]})
    assert not others, (f"{nb.name} imports other chapters' backends {others}: what it needs "
                        f"of them goes through {own[0]} (ch14_answers's backend gathers the "
                        "others; its notebook does not)")


@pytest.mark.parametrize("nb", NOTEBOOKS, ids=lambda p: p.stem)
def test_a_notebook_types_no_number_outside_its_parameters(nb):
    typed = [f"cell {i}, line {line}: {value!r}" for i, src in code_cells(nb)
             for line, value in typed_numbers(src)]
    assert not typed, (f"{nb.name}: numbers typed in code cells (a parameter goes in the "
                       f"parameters cell, a bin, count or unit into the backend "
                       f"ch{_chapter(nb)}_*.py as a named constant or function): {typed}")


def test_the_rule_s_readers_see_what_they_should():
    """The finders themselves, on code the rule allows and code it does not."""
    allowed = ("x = preds[0]\ny = df.iloc[-1]\nz = round(v, 1)\nviz.table(t, 2)\n"
               "s = f'{v:.1f} m'\nglue('k', v, display=False)\n")
    assert typed_numbers(allowed) == []
    assert sorted(typed_numbers("bins = [0, 10, 20.5]\nw = 100 * x\ny = a[1:3]\n"
                                "r = round(v, n=2)\nt = viz.table(x, 2.5)\ne = d.iloc[1, 2]\n"
                                "f(width=14)\n")) == [
        (1, 0), (1, 10), (1, 20.5), (2, 100), (3, 1), (3, 3), (4, 2), (5, 2.5), (6, 1), (6, 2),
        (7, 14)]
    tree = ast.parse("from flowmod.chapters import ch03_flow as ch, common\n"
                     "from flowmod.chapters.ch08_generalisation import table4\n"
                     "import flowmod.chapters.ch14_answers\nfrom flowmod import chapters\n")
    assert backends_imported(tree) == {"ch03_flow", "ch08_generalisation", "ch14_answers"}
