"""python -m flowmod.report.book: what it refuses before any work, and waiting for another
build. Quick: no study is run (the book's own build is tested on the executed smoke study
in test_notebooks.py)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

from flowmod import lock
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


def test_a_build_held_elsewhere_names_wait_and_wait_waits_for_it(tmp_path, call_main):
    """Issue 53: the FolderBusy line suggested ``--wait``, which the book's CLI lacked. Without
    it the book stops with that line; with it, it waits for the holder and then goes on (here
    to the missing run record: the wait is what is tested, not Sphinx)."""
    out = tmp_path / "html"
    holder = subprocess.Popen(  # another build holds the book's lock until its stdin closes
        [sys.executable, "-c", "import sys; from flowmod.lock import file_lock\n"
         f"with file_lock({str(tmp_path / '.html.lock')!r}, 'another build'):\n"
         "    print('held', flush=True); sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        env={k: v for k, v in os.environ.items() if k != lock.ENV})
    try:
        assert holder.stdout.readline().strip() == "held"
        argv = ["--executed", tmp_path / "executed", "--out", out]
        proc = call_main(book.main, *argv)
        lines = proc.stderr.splitlines()
        assert proc.returncode == 1 and len(lines) == 1, proc.stderr
        assert lines[0].startswith(f"FolderBusy: {out} is in use by pid {holder.pid} (another "
                                   "build, since ")
        assert lines[0].endswith("wait for it to finish (or pass --wait), or give this run "
                                 "another folder")
        threading.Timer(0.5, holder.stdin.close).start()  # the other build ends
        proc = call_main(book.main, *argv, "--wait")
        assert holder.stdin.closed, "--wait returned while the other build held the lock"
    finally:
        holder.kill()
        holder.wait()
    assert proc.stdout.startswith(f"[flowmod] {out} is in use by pid {holder.pid} (another "
                                  "build, since ")
    assert proc.stdout.endswith("; waiting\n")
    assert (proc.returncode, proc.stderr) == (
        1, f"BookError: {tmp_path / 'executed' / 'run_info.json'} not found: run the "
        "notebooks first (`make run`)\n")
