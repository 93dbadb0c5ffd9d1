"""A full disk is one line naming the folder, the space there and the fix, wherever it
happens: a stage's build (the driver), a notebook (the runner) and the book. Real writes
that fail: /dev/full answers every write with ENOSPC, and numpy's ``tofile`` into it gives
its short-write error ("N requested and M written") that the issue's run died with."""

from __future__ import annotations

import contextlib
import errno
import os
import pickle
import re
import shutil
from pathlib import Path

import nbformat
import numpy as np
import pytest
import torch
from test_dag import graph, toy  # noqa: F401 - the toy study and its fixture

from flowmod import dag, runner
from flowmod.artefacts import DiskFull, disk_full
from flowmod.report import book

FULL = Path("/dev/full")
pytestmark = pytest.mark.skipif(not FULL.is_char_device(), reason="needs Linux's /dev/full")


@pytest.fixture(autouse=True)
def _full_stays_a_device():
    """Code that removes a file it failed to write (pandas does) would replace the
    machine's /dev/full by a regular file: no test here may write to it by name that way."""
    yield
    assert FULL.is_char_device(), "a test replaced /dev/full: restore it (mknod /dev/full c 1 7)"


def short_write() -> None:
    """90000 float64 to a full device: numpy's OSError without an errno."""
    np.zeros(90_000).tofile(FULL)


def caught(fn) -> BaseException:
    try:
        fn()
    except BaseException as e:  # noqa: BLE001 - the error itself is what is tested
        return e
    raise AssertionError("no error")


def test_disk_full_knows_every_form_a_full_disk_takes():
    def torch_save():  # torch's RuntimeError, raised while handling the OSError
        f = open(FULL, "wb")  # noqa: SIM115 - closed below, its own error aside
        try:
            torch.save({"w": torch.zeros(100_000)}, f)
        finally:
            with contextlib.suppress(OSError):
                f.close()

    def write_text():
        FULL.write_text("x" * 100_000)

    for fn in (short_write, torch_save, write_text):
        assert disk_full(caught(fn)), fn.__name__
    assert isinstance(caught(torch_save), RuntimeError)
    assert disk_full(OSError(errno.EDQUOT, "Disk quota exceeded"))
    assert disk_full("OSError: [Errno 28] No space left on device: 'x.png'")
    assert disk_full("720000 requested and 585664 written")
    for other in (OSError(errno.ENOENT, "No such file"), ValueError("720 requested"),
                  "ValueError: bad value"):
        assert not disk_full(other), other


def test_the_line_names_the_folder_the_space_and_the_fix():
    e = DiskFull.at("/dev", "OSError: 720000 requested and 585664 written",
                    "building crops[dis/keyframe]")
    usage = shutil.disk_usage("/dev")
    assert str(e) == (
        f"no space left in /dev while building crops[dis/keyframe]: {usage.free / 1e6:.1f} MB "
        f"of {usage.total / 1e6:.1f} MB free there now; a write stopped after 585664 of "
        "its 720000 items; free some (make gc, or remove old runs) or set run_dir (--set "
        "run_dir=...) on a disk with room, then rerun: finished work is kept")
    assert isinstance(e, OSError) and e.errno == errno.ENOSPC and "\n" not in str(e)
    back = pickle.loads(pickle.dumps(e))  # crosses process boundaries (Ray, joblib) intact
    assert type(back) is DiskFull and str(back) == str(e)
    # a folder not made yet: the space of the nearest one that exists
    assert str(DiskFull.at("/dev/no/such", None, setting="--out")).startswith(
        f"no space left in /dev/no/such: {usage.free / 1e6:.1f} MB of")


FREE = r"\d+\.\d MB of \d+\.\d MB free there now"


def test_a_stage_that_fills_the_disk_stops_with_one_line_and_loses_nothing(toy):  # noqa: F811
    """The driver names the run folder and the node; the published result stays."""
    g, p = toy
    g.build(p, ["01", "02"])
    select = dag.Node("select")
    before = (g.node_dir(p, select) / "out.json").read_bytes()

    def fills_the_disk(b: dag.Build, progress: bool) -> dict:
        b.start(fresh=True)
        short_write()
        return {}

    full = graph(Path(p.run_dir).parent, select_build=fills_the_disk)
    with pytest.raises(DiskFull) as e:
        full.build_node(p.model_copy(update={"force": True}), select)
    assert re.fullmatch(
        rf"no space left in {re.escape(str(p.run_path))} while building select: {FREE}; a "
        r"write stopped after 0 of its 90000 items; free some \(make gc, or remove old runs\) or "
        r"set run_dir \(--set run_dir=\.\.\.\) on a disk with room, then rerun: finished work "
        r"is kept", str(e.value))
    assert (g.node_dir(p, select) / "out.json").read_bytes() == before
    assert g.current(p, select)


def test_a_notebook_that_fills_the_disk_fails_in_one_line(tmp_path):
    """A chapter's own write (outside the driver) is named by the runner; the run stops
    at it, as at any failing notebook."""
    nbs = one_cell_notebook(tmp_path / "notebooks",
                            f'import numpy as np\nnp.zeros(90_000).tofile("{FULL}")')
    overrides = {"run_dir": str(tmp_path / "runs")}
    with pytest.raises(runner.NotebookFailed) as e:
        runner.run("smoke", overrides, out_dir=tmp_path / "executed", notebooks_dir=nbs)
    first, second = str(e.value).splitlines()
    run_path = runner.resolve_profile("smoke", overrides, say=lambda _: None).run_path
    assert re.fullmatch(rf"00_fill.ipynb failed in cell 3: DiskFull: no space left in "
                        rf"{re.escape(str(run_path))}: {FREE}; a write stopped after 0 "
                        r"of its 90000 items; .* finished work is kept", first), first
    assert second.startswith("executed copy with the traceback: ")


def one_cell_notebook(folder: Path, code: str) -> Path:
    """``folder/00_fill.ipynb``: a parameters cell (``seed``) and ``code``."""
    folder.mkdir()
    nb = nbformat.v4.new_notebook(cells=[
        nbformat.v4.new_code_cell("seed: int = 0  # the seed", metadata={"tags": ["parameters"]}),
        nbformat.v4.new_code_cell(code)])
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3",
                                 "language": "python"}
    nbformat.write(nb, folder / "00_fill.ipynb")
    return folder


def test_a_full_disk_under_the_executed_notebooks_is_one_line(tmp_path, capsys):
    """papermill's own write of the executed copy (here: into a full device) stops the run
    with the line naming --out; the CLI prints it alone."""
    nbs = one_cell_notebook(tmp_path / "notebooks", "x = 1")
    executed = tmp_path / "executed"
    executed.mkdir()
    (executed / ".00_fill.running.ipynb").symlink_to(FULL)
    with pytest.raises(DiskFull) as e:
        runner.run("smoke", {"run_dir": str(tmp_path / "runs")}, out_dir=executed,
                   notebooks_dir=nbs)
    assert re.fullmatch(
        rf"no space left in {re.escape(str(executed))} while writing executed notebooks: "
        rf"{FREE}; free some \(make gc, or remove old runs\) or set --out on a disk with "
        r"room, then rerun: finished work is kept", str(e.value))
    assert runner.os_error_line(e.value) == str(e.value)
    assert not (executed / "00_fill.ipynb").exists()


def test_a_full_disk_under_the_book_is_one_line(tmp_path, capsys):
    """Sphinx's report of a failed write (a page of traceback) becomes the one line."""
    staging, out = tmp_path / "src", tmp_path / "html"
    staging.mkdir()
    out.mkdir()
    (staging / "conf.py").write_text('project = "x"\n')
    (staging / "index.rst").write_text("Title\n=====\n\nText.\n")
    (out / "index.html").symlink_to(FULL)
    with pytest.raises(book.BookError) as e, book._room(out, "building the book"):
        book._sphinx(staging, out, dict(os.environ))
    assert re.fullmatch(
        rf"no space left in {re.escape(str(out))} while building the book: {FREE}; free some "
        r"\(make gc, or remove old runs\) or set --out on a disk with room, then rerun: "
        r"finished work is kept; the published book is unchanged", str(e.value))
    assert "Traceback" not in capsys.readouterr().err
