"""python -m flowmod.report.book: what it refuses before any work. Quick: no study is run
(the book's own build is tested on the executed smoke study in test_notebooks.py)."""

from __future__ import annotations

from flowmod.report import book


def test_out_that_is_a_file_is_refused_before_any_work(tmp_path, call_main):
    """Issue 53: ``--out FILE`` renamed the file to a hidden ``.old`` and put a folder in its
    place (the next build failed with a traceback). Now one line, and nothing is touched: no
    lock file, no staging folder, the file as it was."""
    executed = tmp_path / "executed"
    executed.mkdir()
    afile = tmp_path / "book.html"
    afile.write_text("mine")
    proc = call_main(book.main, "--executed", executed, "--out", afile)
    assert (proc.returncode, proc.stdout) == (1, "")
    assert proc.stderr == (f"BookError: --out {afile}: {afile} is a file, not a folder; give a "
                           "folder for the HTML book (it is made if absent) or move the file "
                           "away\n")
    below = afile / "html"  # a folder beneath a file: the file is named
    proc = call_main(book.main, "--executed", executed, "--out", below)
    assert proc.returncode == 1 and proc.stderr.startswith(
        f"BookError: --out {below}: {afile} is a file, not a folder;")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["book.html", "executed"]
    assert afile.read_text() == "mine"
