"""Where things live: the repository root and the standard run layout."""

from __future__ import annotations

import os
from functools import cache
from pathlib import Path


@cache
def repo_root() -> Path:
    """The repository root: ``$FLOWMOD_ROOT``, else the nearest parent holding ``pyproject.toml``
    and ``params/`` (starting from this file, then from the working directory)."""
    env = os.environ.get("FLOWMOD_ROOT")
    if env:
        return Path(env).resolve()
    for start in (Path(__file__).resolve(), Path.cwd().resolve()):
        for d in (start, *start.parents):
            if (d / "pyproject.toml").is_file() and (d / "params").is_dir():
                return d
    raise FileNotFoundError(
        "cannot find the flowmod repository root (a folder with pyproject.toml and params/); "
        "set FLOWMOD_ROOT to it"
    )


def figures_dir(run_dir: Path) -> Path:
    """``<run_dir>/figures``, created on demand."""
    d = Path(run_dir) / "figures"
    d.mkdir(parents=True, exist_ok=True)
    return d


def file_in_the_way(folder: str | os.PathLike[str]) -> Path | None:
    """The file (or dangling link) that stands where ``folder`` or one of its parents must
    be a folder; None when ``folder`` is a folder or can be made (a CLI's check of an output
    folder, before any work)."""
    path = Path(folder).absolute()
    for d in (path, *path.parents):
        if d.exists() or d.is_symlink():
            return None if d.is_dir() else d
    return None
