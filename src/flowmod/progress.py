"""Progress bars, one mechanism for every long loop: tqdm, either where the caller sees it
(a terminal or a notebook) or, while ``python -m flowmod.runner`` executes the notebooks, into
the runner's side channel (the file named by ``$FLOWMOD_PROGRESS``), which the runner shows
in the terminal (items done / total, rate, ETA) and which never enters the book's pages.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from typing import IO, Any

#: Environment variable naming the side-channel file (set by the runner).
ENV = "FLOWMOD_PROGRESS"

_channel: tuple[str, IO[str]] | None = None


def _side_channel() -> IO[str] | None:
    global _channel
    path = os.environ.get(ENV)
    if not path:
        return None
    if _channel is None or _channel[0] != path:
        try:
            _channel = (path, open(path, "a", buffering=1, encoding="utf-8"))  # noqa: SIM115
        except OSError:  # an unusable side channel never stops the work: bars go to stderr
            return None
    return _channel[1]


def bar(iterable: Iterable[Any] | None = None, *, total: int | None = None, desc: str = "",
        unit: str = "it", disable: bool = False, **kw: Any) -> Any:
    """A tqdm progress bar over ``iterable`` (or ``total`` items updated by hand)."""
    side = _side_channel()
    if side is not None:
        from tqdm import tqdm

        return tqdm(iterable, total=total, desc=desc, unit=unit, file=side, ascii=True,
                    ncols=100, mininterval=2.0, disable=disable, **kw)
    from tqdm.auto import tqdm as auto_tqdm

    return auto_tqdm(iterable, total=total, desc=desc, unit=unit, disable=disable, **kw)
