"""The runner beyond the smoke study: parameters refused before work, a failing notebook,
and every chapter's "Try it" commands as a reader types them. A file of its own, so that
pytest-xdist (``--dist loadfile``) runs it beside the executed smoke study of
test_notebooks.py."""

import json
from pathlib import Path

import nbformat
import pytest

from flowmod import runner
from flowmod.params import ProfileError
from flowmod.report import book
from flowmod.runner import NotebookFailed

pytestmark = pytest.mark.slow


def test_missing_real_dataroot_is_rejected_before_work(tmp_path):
    with pytest.raises(ProfileError, match=r"v1.0-trainval.*not found|does not exist"):
        runner.run("paper", {"dataroot": str(tmp_path)}, out_dir=tmp_path / "executed")
    assert not (tmp_path / "executed").exists()


def test_device_that_does_not_exist_is_rejected_before_work(tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("needs a machine without CUDA")
    with pytest.raises(ProfileError, match="device='cuda'.*no CUDA device"):
        runner.run("smoke", {"device": "cuda"}, out_dir=tmp_path / "executed")
    assert not (tmp_path / "executed").exists()


def test_failing_notebook_stops_the_run_and_is_never_rendered(tmp_path):
    """A notebook that fails stops the run; its copy with the traceback goes to failed/,
    and the previous good executed copy stays in place (papermill writes a hidden running
    copy that replaces it only on success)."""
    nbs = tmp_path / "notebooks"
    nbs.mkdir()
    good = nbformat.read(runner.notebooks()[0], as_version=4)
    nbformat.write(good, nbs / "00_setup.ipynb")
    executed = tmp_path / "executed"
    kw = dict(out_dir=executed, notebooks_dir=nbs)
    runner.run("smoke", {"run_dir": str(tmp_path / "runs")}, **kw)
    before = (executed / "00_setup.ipynb").read_bytes()
    nb = nbformat.read(runner.notebooks()[0], as_version=4)
    nb.cells.append(nbformat.v4.new_code_cell('raise ValueError("boom in a cell")'))
    nbformat.write(nb, nbs / "00_setup.ipynb")
    nbformat.write(good, nbs / "01_later.ipynb")
    with pytest.raises(NotebookFailed, match=r"00_setup.ipynb failed in cell \d+: ValueError: "
                       r"boom(.|\n)*failed/00_setup.ipynb; the previous good copy is kept"):
        runner.run("smoke", {"run_dir": str(tmp_path / "runs")}, **kw)
    assert not (executed / "01_later.ipynb").exists(), "the run must stop at the first failure"
    assert (executed / "00_setup.ipynb").read_bytes() == before
    assert sorted(p.name for p in executed.glob(".*.ipynb")) == [], "no running copy left"
    info = json.loads((executed / "run_info.json").read_text())
    assert info["status"] == "failed" and info["notebooks"]["00_setup"]["status"] == "failed"
    with pytest.raises(book.BookError, match="did not finish"):
        book.build(executed, tmp_path / "html")
    # even with a doctored run record, the failed notebook itself is refused
    with pytest.raises(book.BookError, match="failed when it ran"):
        book.check_executed(executed / "failed" / "00_setup.ipynb")
    assert not (tmp_path / "html").exists()
    # the fix undone: the kept good copy is reused, and the failure it answers goes (issue
    # 53: failed/00_setup.ipynb stayed beside a good copy)
    nbformat.write(good, nbs / "00_setup.ipynb")
    (nbs / "01_later.ipynb").unlink()
    runner.run("smoke", {"run_dir": str(tmp_path / "runs")}, **kw)
    assert (executed / "00_setup.ipynb").read_bytes() == before, "the good copy, reused"
    assert not (executed / "failed" / "00_setup.ipynb").exists()


def test_sigterm_mid_cell_is_one_line_and_the_run_resumes(tmp_path):
    """Issue 53: a runner killed with SIGTERM exited without a word. Sent while a cell runs
    (the kernel's import of flowmod), it now prints one line, as Ctrl-C does (and no ZMQ
    traceback from a kernel shut down mid-cell: the runner kills it), leaves no executed or
    running copy, and the same command then runs the notebook to the end."""
    import signal
    import subprocess
    import sys
    import time

    out, runs = tmp_path / "executed", tmp_path / "runs"
    argv = ["--profile", "smoke", "--only", "00", "--out", str(out), "--set", f"run_dir={runs}"]
    proc = subprocess.Popen([sys.executable, "-m", "flowmod.runner", *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    running = out / ".00_setup.running.ipynb"
    try:
        while proc.poll() is None and not _cell_running(running, "params.from_notebook"):
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert (proc.returncode, stderr) == (
        143, "terminated (SIGTERM): python -m flowmod.runner --profile smoke stopped; the "
        "published results are untouched and the same command resumes\n"), stdout
    assert sorted(p.name for p in out.glob("*.ipynb")) == [] and not running.exists()
    assert runner.main(argv) == 0
    assert (out / "00_setup.ipynb").is_file()


def _cell_running(nb: Path, source: str) -> bool:
    """Whether papermill's running copy ``nb`` marks the cell holding ``source`` running."""
    try:
        cells = nbformat.read(nb, as_version=4).cells
    except Exception:  # noqa: BLE001 - not written yet, or half written
        return False
    return any(source in c.source and c.metadata.get("papermill", {}).get("status") == "running"
               for c in cells)


def test_a_bad_value_given_to_papermill_directly_is_one_line_in_the_kernel(tmp_path):
    """Issue 53: a chapter run by papermill itself (as each chapter's first cell shows) with
    a bad value named the key only at the end of 57-86 lines of traceback through flowmod.
    The kernel now reports flowmod.params.ProfileError as its one line (what papermill
    prints after "Exception encountered at"; papermill's own traceback above it stays)."""
    import subprocess
    import sys

    from flowmod.paths import repo_root

    out = tmp_path / "00_setup.ipynb"
    proc = subprocess.run([sys.executable, "-m", "papermill", "notebooks/00_setup.ipynb",
                           str(out), "-p", "seed", "-1", "--no-progress-bar"],
                          capture_output=True, text=True, cwd=repo_root())
    line = ("ProfileError: notebook parameters (papermill -p / -f, or the parameters cell): "
            "seed=-1: Input should be greater than or equal to 0")
    assert proc.returncode == 1
    kernel = proc.stderr.split("Exception encountered at ", 1)[1].strip().splitlines()
    assert kernel[1:] == [line], proc.stderr[-3000:]
    errors = [o for c in nbformat.read(out, as_version=4).cells for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert [(e["ename"], e["traceback"]) for e in errors] == [("ProfileError", [line])]


@pytest.mark.parametrize("nb_path", runner.notebooks(), ids=lambda p: p.stem)
def test_try_it_commands_run(nb_path, smoke_built, tmp_path, capsys):
    """A chapter's "Try it" commands, as a reader would type them, on a copy of the built
    smoke run (``--profile demo`` becomes ``--profile smoke``), so that they never rot: each
    builds what its parameter changes and executes its chapter. The commands run through
    the runner's ``main`` in this process (the interpreter start is all that differs from a
    shell); the world is the session's, read in place (no command makes one)."""
    import shlex
    import shutil

    from test_sources import try_it_commands

    shutil.copytree(smoke_built.run_path, tmp_path / "runs", symlinks=True)
    prefix = [".venv/bin/python", "-m", "flowmod.runner"]
    for cmd in try_it_commands(nb_path):
        argv = ["smoke" if a == "demo" else a for a in shlex.split(cmd)]
        assert argv[:3] == prefix, cmd
        argv = argv[3:] + ["--set", f"run_dir={tmp_path / 'runs'}", "--set",
                           f"dataroot={smoke_built.dataroot}", "--out", str(tmp_path / "executed")]
        rc = runner.main(argv)
        out, err = capsys.readouterr()
        assert rc == 0, f"{cmd}\n{out[-1500:]}\n{err[-1500:]}"
        if "--status" in cmd:
            assert "stale" in out or "missing" in out, out
        else:
            assert " ok (" in out, out
