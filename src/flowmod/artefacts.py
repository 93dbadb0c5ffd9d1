"""Stage artefacts: atomic writes and up-to-date manifests.

Every stage writes its outputs through :func:`atomic_path` (a temporary name in the same
folder, renamed into place only when the write finished), so an interrupted run never leaves a
half-written file that a later stage could mistake for a result. Beside a stage's outputs, a
manifest (``<name>.manifest.json``) records the hash of the parameters that produced them;
:func:`is_up_to_date` compares it with the current parameters.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    The temporary file keeps ``path``'s suffix (so ``np.save``/``to_parquet`` keep their
    format) and is removed if the block raises.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_json(path: str | os.PathLike[str], obj: Any) -> None:
    """Write JSON atomically (sorted keys, indented)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


def manifest_path(path: str | os.PathLike[str]) -> Path:
    path = Path(path)
    return path.with_name(path.name + ".manifest.json")


def is_up_to_date(path: str | os.PathLike[str], params_hash: str) -> bool:
    """True if ``path`` exists and its manifest records ``params_hash``."""
    path = Path(path)
    m = manifest_path(path)
    if not (path.exists() and m.is_file()):
        return False
    try:
        return json.loads(m.read_text()).get("params_hash") == params_hash
    except (OSError, json.JSONDecodeError):
        return False


def mark_done(path: str | os.PathLike[str], params_hash: str, **info: Any) -> None:
    """Record that ``path`` was produced by parameters with ``params_hash``."""
    write_json(manifest_path(path), {"params_hash": params_hash, "written": time.time(), **info})


class CheckpointError(ValueError):
    """A weights file does not fit the model it is loaded into; the message names the file
    and the first mismatching keys."""


def state_dict_mismatch(state: Mapping[str, Any], expected: Mapping[str, Any], n: int = 5) -> str:
    """How a state_dict differs from the one a model expects (keys and tensor shapes):
    ``""`` when they agree, else "missing keys: ...; unexpected keys: ...; shape mismatches
    (file != model): ..." listing the first ``n`` of each."""

    def first(items: list[str]) -> str:
        more = f" (+{len(items) - n} more)" if len(items) > n else ""
        return ", ".join(items[:n]) + more

    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    shapes = [f"{k} {tuple(state[k].shape)} != {tuple(expected[k].shape)}"
              for k in expected if k in state and tuple(state[k].shape) != tuple(expected[k].shape)]
    parts = []
    if missing:
        parts.append(f"missing keys: {first(missing)}")
    if unexpected:
        parts.append(f"unexpected keys: {first(unexpected)}")
    if shapes:
        parts.append(f"shape mismatches (file != model): {first(shapes)}")
    return "; ".join(parts)
