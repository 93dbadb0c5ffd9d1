"""Rebuilds with nothing changed write the same bytes: executed notebooks (papermill gives
its injected cell a random id) and the book's page sources. Checkpoints: test_learning."""

import nbformat
import papermill
import pytest

from flowmod import runner
from flowmod.report import book


@pytest.fixture
def parameterized(tmp_path):
    """Two copies of chapter 00 as papermill writes them before execution: the parameters
    injected, each injected cell with its own random id."""
    paths = []
    for name in ("a.ipynb", "b.ipynb"):
        nb = papermill.iorw.load_notebook_node(str(runner.notebooks()[0]))
        nb = papermill.parameterize.parameterize_notebook(nb, {"seed": 3})
        nbformat.write(nb, tmp_path / name)
        paths.append(tmp_path / name)
    return paths


def injected(nb: nbformat.NotebookNode) -> nbformat.NotebookNode:
    return next(c for c in nb.cells if "injected-parameters" in c.metadata.get("tags", []))


def test_executed_copies_get_the_same_valid_cell_ids(parameterized):
    a, b = parameterized
    ids = [injected(nbformat.read(p, as_version=4)).id for p in parameterized]
    assert ids[0] != ids[1], "papermill's ids are random: the premise of this test"
    for path in parameterized:  # the runner stamps each executed copy in place
        runner._stamp(path, "fp", 1.5, "2026-01-01 00:00:00 UTC")
    assert a.read_bytes() == b.read_bytes()
    nb = nbformat.read(a, as_version=4)
    nbformat.validate(nb)
    ids = [c.id for c in nb.cells]
    assert len(set(ids)) == len(ids) and all(len(i) == 12 for i in ids)
    # an id follows its cell's source: another value injected, another id for that cell only
    other = papermill.parameterize.parameterize_notebook(
        papermill.iorw.load_notebook_node(str(runner.notebooks()[0])), {"seed": 4})
    runner.stable_cell_ids(other)
    assert [c.id for c in other.cells if c.id not in ids] == [injected(other).id]


def test_a_page_source_is_the_same_every_build(parameterized):
    """The book replaces the injected cell by a table of the values that ran; the new cell's
    id is fixed, so the staged page (and Sphinx's _sources copy) is rewritten only when the
    notebook changed."""
    a, _ = parameterized
    pages = [nbformat.writes(book.for_the_page(nbformat.read(a, as_version=4)))
             for _ in range(2)]
    assert pages[0] == pages[1]
    page = nbformat.reads(pages[0], as_version=4)
    nbformat.validate(page)
    assert [c.id for c in page.cells if "flowmod-parameters" in c.source] == ["parameters-ran"]
