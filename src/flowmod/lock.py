"""One run at a time per folder: an OS file lock, released by the kernel when its holder
exits, however it exits (``kill -9`` included).

    with folder_lock(run_dir, "runner --profile demo"):
        ...  # build, execute notebooks

A second process that asks for the same folder gets :class:`FolderBusy`, one line naming the
process that holds it (pid, command, since when), or waits for it with ``wait=True``.
Processes started by the holder (the notebooks' kernels) inherit the lock through the
environment (:data:`ENV`): they may work in the folder without asking again.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import time
from collections.abc import Iterator
from pathlib import Path

#: File of the lock inside a locked folder.
LOCK_FILE = ".flowmod.lock"
#: Environment variable listing the folders this process's ancestors hold (os.pathsep).
ENV = "FLOWMOD_LOCKS_HELD"


class FolderBusy(RuntimeError):
    """Another process holds the folder; the message names it and what to do."""


def held_by_parent(path: Path) -> bool:
    """True if an ancestor of this process holds the lock file ``path`` (we run on its
    behalf)."""
    held = os.environ.get(ENV, "")
    return str(Path(path).resolve()) in held.split(os.pathsep) if held else False


def _holder(path: Path) -> str:
    try:
        info = json.loads(path.read_text())
    except (OSError, ValueError):
        return "another process"
    since = time.strftime("%H:%M:%S", time.localtime(info.get("since", 0)))
    return f"pid {info.get('pid')} ({info.get('command', '?')}, since {since})"


def folder_lock(folder: str | os.PathLike[str], command: str, wait: bool = False,
                poll: float = 2.0) -> contextlib.AbstractContextManager[None]:
    """Hold ``folder``'s lock (``<folder>/.flowmod.lock``) for the block."""
    return file_lock(Path(folder) / LOCK_FILE, command, wait, poll, what=Path(folder))


@contextlib.contextmanager
def file_lock(path: str | os.PathLike[str], command: str, wait: bool = False,
              poll: float = 2.0, what: Path | None = None) -> Iterator[None]:
    """Hold the lock file ``path`` for the block (created, with its folder, if missing):
    :class:`FolderBusy` naming ``what`` (default: the file) if another process holds it
    (``wait``: block until it is free, saying so once). Re-entrant for the holder's child
    processes (:func:`held_by_parent`)."""
    path = Path(path).resolve()
    folder = what or path
    if held_by_parent(path):
        yield
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        said = False
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                who = _holder(path)
                if not wait:
                    raise FolderBusy(
                        f"{folder} is in use by {who}: wait for it to finish (or pass --wait), "
                        "or give this run another folder") from None
                if not said:
                    print(f"[flowmod] {folder} is in use by {who}; waiting", flush=True)
                    said = True
                time.sleep(poll)
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps({"pid": os.getpid(), "command": command,
                                 "since": time.time()}).encode())
        old = os.environ.get(ENV)
        os.environ[ENV] = os.pathsep.join(x for x in (old, str(path)) if x)
        try:
            yield
        finally:
            if old is None:
                os.environ.pop(ENV, None)
            else:
                os.environ[ENV] = old
    finally:
        os.close(fd)  # closing releases the lock
