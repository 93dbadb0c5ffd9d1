"""Every notebook through papermill on the smoke profile, then the book built from that run.

The recommenders pattern: run with small parameters, then assert on what each notebook
recorded (myst-nb glue values), not on the absence of an exception alone.
"""

import json
import re

import nbformat
import pytest

from flowmod import book, runner
from flowmod.params import ProfileError
from flowmod.runner import NotebookFailed

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    """The whole study executed once on the smoke profile, in a temporary run folder."""
    base = tmp_path_factory.mktemp("smoke_run")
    executed = base / "executed"
    overrides = {"run_dir": str(base / "runs"), "dataroot": str(base / "data")}
    record = runner.run("smoke", overrides, out_dir=executed)
    return {"executed": executed, "record": record, "base": base}


def glue_of(smoke_run, stem):
    return book.read_glue(smoke_run["executed"] / f"{stem}.ipynb")


def test_every_notebook_ran(smoke_run):
    record = smoke_run["record"]
    assert record["status"] == "ok"
    assert set(record["notebooks"]) == {nb.stem for nb in runner.notebooks()}
    on_disk = json.loads((smoke_run["executed"] / "run_info.json").read_text())
    assert on_disk["status"] == "ok" and on_disk["profile"] == "smoke"


def test_setup_records_profile_and_environment(smoke_run):
    g = glue_of(smoke_run, "00_setup")
    assert g["profile"] == "smoke"
    assert g["torch_version"] == "2.14.1"
    assert g["device"] in ("cpu", "cuda")
    assert g["n_parameters"] >= 40
    assert (smoke_run["base"] / "runs" / "figures" / "pipeline.png").stat().st_size > 5000


def test_device_that_does_not_exist_is_rejected_before_work(tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("needs a machine without CUDA")
    with pytest.raises(ProfileError, match="device='cuda'.*no CUDA device"):
        runner.run("smoke", {"device": "cuda"}, out_dir=tmp_path / "executed")
    assert not (tmp_path / "executed").exists()


def test_failing_notebook_stops_the_run_and_is_never_rendered(tmp_path):
    nbs = tmp_path / "notebooks"
    nbs.mkdir()
    nb = nbformat.read(runner.notebooks()[0], as_version=4)
    nb.cells.append(nbformat.v4.new_code_cell('raise ValueError("boom in a cell")'))
    nbformat.write(nb, nbs / "00_setup.ipynb")
    nbformat.write(nbformat.read(runner.notebooks()[0], as_version=4), nbs / "01_later.ipynb")
    executed = tmp_path / "executed"
    with pytest.raises(NotebookFailed, match=r"00_setup.ipynb failed in cell \d+: ValueError: boom"):
        runner.run("smoke", {"run_dir": str(tmp_path / "runs")}, out_dir=executed,
                   notebooks_dir=nbs)
    assert not (executed / "01_later.ipynb").exists(), "the run must stop at the first failure"
    info = json.loads((executed / "run_info.json").read_text())
    assert info["status"] == "failed" and info["notebooks"]["00_setup"]["status"] == "failed"
    with pytest.raises(book.BookError, match="did not finish"):
        book.build(executed, tmp_path / "html")
    # even with a doctored run record, the failed notebook itself is refused
    with pytest.raises(book.BookError, match="failed when it ran"):
        book.check_executed(executed / "00_setup.ipynb")
    assert not (tmp_path / "html").exists()


def test_book_builds_offline_with_warnings_as_errors(smoke_run, tmp_path):
    out = tmp_path / "html"
    index = book.build(smoke_run["executed"], out)
    assert index.is_file()
    pages = {p.name for p in out.glob("*.html")}
    for nb in runner.notebooks():
        assert f"{nb.stem}.html" in pages
    assert "reproduce.html" in pages
    reproduce = (out / "reproduce.html").read_text()
    assert smoke_run["record"]["commit"] in reproduce
    assert "torch" in reproduce and "2.14.1" in reproduce
    # the setup chapter shows its figure, and the figure file is in the build
    setup = (out / "00_setup.html").read_text()
    imgs = re.findall(r'<img[^>]+src="([^"]+)"', setup)
    assert imgs and all((out / src).is_file() for src in imgs)
    # nothing is loaded from the network: no remote scripts, styles or images
    for page in out.glob("*.html"):
        remote = re.findall(r'<(?:script|link|img)[^>]+(?:src|href)="(https?:)?//', page.read_text())
        assert not remote, f"{page.name} loads remote resources"
    assert (out / "_static" / "_vendor" / "mathjax" / "tex-chtml.js").is_file()
    # and in a real browser: every page loads, every image resolves, no request leaves
    # localhost (headless Chromium, installed by `make browser`)
    from flowmod import browser

    try:
        browser.find_chromium()
    except browser.ChromiumNotFound:
        if not browser.in_ci():
            pytest.skip("Chromium missing (`make browser`)")
        raise
    browser.assert_book_ok(out, screenshot=tmp_path / "book-screenshot.png")


def test_executed_copies_keep_sources_clean(smoke_run):
    for nb in runner.notebooks():
        src = nbformat.read(nb, as_version=4)
        assert not any(c.get("outputs") for c in src.cells if c.cell_type == "code")
