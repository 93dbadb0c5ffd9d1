"""Stage artefacts: atomic writes, fingerprints, manifests and content digests.

Every stage writes its outputs through :func:`atomic_path` (a temporary name in the same
folder, renamed into place only when the write finished), so an interrupted run never leaves a
half-written file that a later stage could mistake for a result. A stage's outputs carry a
manifest (``manifest.json``) whose ``fingerprint`` is :func:`fingerprint` of what made them
(stage, code version, parameter values, the fingerprints of the artefacts it read); the
bookkeeping over stages and nodes is :mod:`flowmod.dag`. :func:`file_digest` identifies input
files by content (sha256), with a stat cache so that unchanged files are not read again.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import re
import shutil
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any


def _umask() -> int:
    """The process's umask (read by setting it, then setting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    The temporary file keeps ``path``'s suffix (so ``np.save``/``to_parquet`` keep their
    format) and is removed if the block raises. The published file is readable as the umask
    allows (``mkstemp`` makes it 0600; a shared dataroot or run folder needs 0644 under the
    usual umask 022).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def leftover_temporaries(folder: Path) -> list[Path]:
    """The temporary files of :func:`atomic_path` under ``folder`` (``.<stem>.<random>.tmp``
    and its suffix): left behind only by a process killed inside the block (a joblib worker
    that died, kill -9)."""
    return sorted(f for f in Path(folder).rglob(".*.tmp*") if f.is_file())


def write_json(path: str | os.PathLike[str], obj: Any) -> None:
    """Write JSON atomically (sorted keys, indented)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


def save_checkpoint(obj: Any, path: str | os.PathLike[str]) -> None:
    """``torch.save`` of ``obj`` to ``path``, atomically and byte for byte the same for equal
    tensors: the one writer of the package's ``.pt`` files. Saved to a path, torch names
    the zip's archive folder after the (random) temporary file; saved to a file object it is
    always ``archive``, and nothing else in the file varies (torch 2.14's serialization id
    hashes the record names and data). Load with ``torch.load(..., weights_only=True)``."""
    import torch  # only the trainers call this; most processes never load torch

    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(obj, f)


#: numpy's message for a short write (``tofile``, ``np.save``; counts of array items):
#: ``OSError`` without errno
_SHORT_WRITE = re.compile(r"(\d+) requested and (\d+) written")
_FULL_TEXT = re.compile("|".join(map(re.escape, (os.strerror(errno.ENOSPC),
                                                 os.strerror(errno.EDQUOT)))))


def disk_full(exc: BaseException | str) -> bool:
    """Whether ``exc`` (or an error it was raised from or during) is a full disk or quota:
    errno ENOSPC / EDQUOT, numpy's "N requested and M written", or (a string: a kernel's
    or a subprocess's error text) either message."""
    if isinstance(exc, str):
        return bool(_FULL_TEXT.search(exc) or _SHORT_WRITE.search(exc))
    return any(isinstance(e, OSError) and (e.errno in (errno.ENOSPC, errno.EDQUOT)
                                           or _SHORT_WRITE.search(str(e)))
               for e in _chain(exc))


def _chain(exc: BaseException) -> Iterator[BaseException]:
    """``exc`` and the errors it was raised from or while handling, outermost first."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        yield e
        e = e.__cause__ or e.__context__


class DiskFull(OSError):
    """No space left where a run writes: one line naming the folder, the space free there,
    what the failed write wanted (where known) and the fix (:meth:`at`)."""

    def __init__(self, message: str) -> None:
        super().__init__(errno.ENOSPC, message)

    def __str__(self) -> str:
        return str(self.strerror)

    def __reduce__(self) -> tuple[Any, ...]:  # one argument, not OSError's (errno, text)
        return (type(self), (self.strerror,))

    @classmethod
    def at(cls, folder: str | os.PathLike[str], exc: BaseException | str | None = None,
           doing: str = "", setting: str = "run_dir (--set run_dir=...)") -> DiskFull:
        """The error for a full disk under ``folder`` while ``doing`` (e.g. "building
        crops[dis/keyframe]"); ``exc``: the error seen, whose sizes are quoted when it says
        them; ``setting``: what points the writes elsewhere."""
        where = Path(folder).absolute()
        while not where.exists() and where != where.parent:
            where = where.parent
        usage = shutil.disk_usage(where)
        text = exc if isinstance(exc, str) else " ".join(map(str, _chain(exc))) if exc else ""
        size = _SHORT_WRITE.search(text)
        wanted = f"; a write stopped after {size[2]} of its {size[1]} items" if size else ""
        what = f" while {doing}" if doing else ""
        return cls(f"no space left in {Path(folder)}{what}: {_mb(usage.free)} of "
                   f"{_mb(usage.total)} free there now{wanted}; free some (make gc, or remove "
                   f"old runs) or set {setting} on a disk with room, then rerun: finished "
                   "work is kept")

    @classmethod
    @contextlib.contextmanager
    def guard(cls, folder: str | os.PathLike[str], doing: str = "",
              setting: str = "run_dir (--set run_dir=...)") -> Iterator[None]:
        """Turn a full disk (:func:`disk_full`) inside the block into :meth:`at`'s error;
        every other error passes as it is."""
        try:
            yield
        except Exception as e:
            if isinstance(e, DiskFull) or not disk_full(e):
                raise
            raise cls.at(folder, e, doing, setting) from e


def _mb(n: int) -> str:
    """``n`` bytes in MB, one decimal."""
    return f"{n / 1e6:.1f} MB"


def canonical(obj: Any) -> str:
    """Stable JSON text of ``obj`` (sorted keys, no spaces; tuples as lists, floats as repr)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def fingerprint(payload: Any, n: int = 16) -> str:
    """First ``n`` hex digits of sha256 of :func:`canonical` ``payload``."""
    return hashlib.sha256(canonical(payload).encode()).hexdigest()[:n]


def read_manifest(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The manifest at ``path`` (a ``manifest.json``), or None if absent or unreadable."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and "fingerprint" in data else None


def write_manifest(path: str | os.PathLike[str], record: Mapping[str, Any]) -> None:
    """Write a manifest (must hold ``fingerprint``) atomically, stamped with the time."""
    if "fingerprint" not in record:
        raise ValueError("a manifest needs a fingerprint")
    write_json(path, {**record, "written": time.time()})


#: ``{resolved path: (size, mtime_ns, ctime_ns, sha256)}``: the digests this process knows.
_DIGESTS: dict[str, tuple[int, int, int, str]] = {}
#: The stat caches read into :data:`_DIGESTS` by this process.
_LOADED: set[str] = set()
#: ``{stat cache: the resolved paths it holds}``: what it was read with and asked about.
_OWNED: dict[str, set[str]] = {}
#: Stat caches with entries not yet written, while a :func:`digest_batch` is open.
_PENDING: set[str] = set()
#: How many :func:`digest_batch` blocks are open (0: each call writes its cache at once).
_BATCH_DEPTH = [0]


def _stat_key(st: os.stat_result) -> tuple[int, int, int]:
    """What decides whether a file is read again: its size, mtime and ctime (ns). Putting
    the mtime back after an edit (``touch -d``, ``os.utime``) cannot reset the ctime."""
    return st.st_size, st.st_mtime_ns, st.st_ctime_ns


def _load_digest_cache(cache: Path) -> None:
    """Read a stat cache into :data:`_DIGESTS`, keeping only well-formed entries (a cache of
    another layout, edited or cut short is ignored, and rewritten when next saved)."""
    owned = _OWNED.setdefault(str(cache), set())
    try:
        data = json.loads(cache.read_text())
    except (OSError, ValueError):
        return
    if not isinstance(data, dict):
        return
    for k, v in data.items():
        if (isinstance(v, list) and len(v) == 4 and all(type(x) is int for x in v[:3])
                and isinstance(v[3], str) and len(v[3]) == 64):
            _DIGESTS.setdefault(k, tuple(v))  # type: ignore[arg-type]
            owned.add(k)


def _write_digest_cache(cache: str) -> None:
    """Write a stat cache: the entries of the files it was asked about (not every digest
    this process knows: a test worker or a notebook kernel sees many run folders)."""
    entries = {k: _DIGESTS[k] for k in _OWNED.get(cache, ()) if k in _DIGESTS}
    with contextlib.suppress(OSError):
        write_json(cache, entries)


@contextlib.contextmanager
def digest_batch() -> Iterator[None]:
    """Write the stat caches that :func:`file_digests` updates inside the block once, when
    the outermost block ends (a build or a status check digests hundreds of files, one call
    each: a write after every call re-wrote the whole cache hundreds of times). The cache
    only saves reading: one lost with a killed process costs a re-read, never a wrong
    digest."""
    _BATCH_DEPTH[0] += 1
    try:
        yield
    finally:
        _BATCH_DEPTH[0] -= 1
        if _BATCH_DEPTH[0] == 0:
            while _PENDING:
                _write_digest_cache(_PENDING.pop())


def file_digest(path: str | os.PathLike[str], cache: str | os.PathLike[str] | None = None) -> str:
    """sha256 (hex) of a file's content. ``cache``: a JSON file that remembers digests by
    (resolved path, size, mtime_ns, ctime_ns), so a file is read again only when its stat
    changed (the stat only decides whether to re-read: it never enters a digest)."""
    return file_digests([path], cache)[0]


def file_digests(paths: Sequence[str | os.PathLike[str]],
                 cache: str | os.PathLike[str] | None = None) -> list[str]:
    """:func:`file_digest` of many files, the cache written once at the end, or at the end
    of the open :func:`digest_batch` (OSError for a file that cannot be read)."""
    if cache is not None and str(cache) not in _LOADED:
        _LOADED.add(str(cache))
        _load_digest_cache(Path(cache))
    owned = _OWNED.setdefault(str(cache), set()) if cache is not None else set()
    out, new = [], False
    for path in paths:
        p = Path(path).resolve()
        key = _stat_key(p.stat())
        hit = _DIGESTS.get(str(p))
        if not (hit and hit[:3] == key):
            h = hashlib.sha256()
            with open(p, "rb") as f:
                for block in iter(lambda f=f: f.read(1 << 22), b""):
                    h.update(block)
            hit = _DIGESTS[str(p)] = (*key, h.hexdigest())
            new = True
        if str(p) not in owned:
            owned.add(str(p))
            new = True
        out.append(hit[3])
    if cache is not None and new:
        if _BATCH_DEPTH[0]:
            _PENDING.add(str(cache))
        else:
            _write_digest_cache(str(cache))
    return out


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
