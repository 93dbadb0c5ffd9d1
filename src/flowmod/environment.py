"""What the study runs on: package versions, the compute device, the git commit."""

from __future__ import annotations

import platform
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from importlib import metadata
from typing import TYPE_CHECKING, Any

import pandas as pd

from flowmod.paths import repo_root

if TYPE_CHECKING:
    import torch

#: Distributions reported in the book's setup chapter and the Reproduce page.
KEY_PACKAGES = (
    "flowmod",
    "torch",
    "torchvision",
    "numpy",
    "nuscenes-devkit",
    "opencv-python-headless",
    "pandas",
    "pyarrow",
    "scikit-learn",
    "matplotlib",
    "papermill",
    "myst-nb",
    "Sphinx",
    "sphinx-book-theme",
)


def versions(packages: tuple[str, ...] = KEY_PACKAGES) -> pd.DataFrame:
    """Installed version of each distribution (``"not installed"`` where absent)."""
    rows = [{"package": "python", "version": platform.python_version()}]
    for name in packages:
        try:
            v = metadata.version(name)
        except metadata.PackageNotFoundError:
            v = "not installed"
        rows.append({"package": name, "version": v})
    return pd.DataFrame(rows)


def simd_path() -> str | None:
    """``"avx512"``, ``"avx2"`` or None: which of numpy's SIMD paths this process runs. Its
    float32 ``exp``, ``log`` and friends round differently on the two, so a generated world's
    bytes (and what is computed on it) are pinned per path; this project's machines have
    either (``NPY_DISABLE_CPU_FEATURES`` can take a process from the first to the second)."""
    from numpy.core._multiarray_umath import __cpu_features__ as cpu

    return "avx512" if cpu.get("AVX512_SKX") else "avx2" if cpu.get("AVX2") else None


def resolve_device(device: Any = "auto") -> torch.device:
    """``"auto"`` (or None) -> CUDA if a CUDA device is usable, else the CPU; anything else
    as :class:`torch.device`. Asking for CUDA without one raises a clear error instead of
    failing mid-run."""
    import torch

    if isinstance(device, torch.device):
        return device
    if device is None or device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device={device!r} was asked for but no CUDA device is visible; "
                           "use 'auto'")
    return dev


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the block on ``n`` torch threads, then restore the caller's count (a process-wide
    setting: left changed, it alters every later float reduction in the process)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def device_info(device: str = "auto") -> dict[str, object]:
    """The device the study will use, with its name and the CPU thread count."""
    import torch

    dev = resolve_device(device).type
    info: dict[str, object] = {
        "device": dev,
        "cpu": platform.processor() or platform.machine(),
        "torch_threads": torch.get_num_threads(),
    }
    if dev == "cuda":
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def device_table(info: dict[str, object]) -> pd.DataFrame:
    """:func:`device_info` as a two-column table (what, value)."""
    return pd.DataFrame({"what": list(info), "value": [str(v) for v in info.values()]})


def git_commit() -> str:
    """The commit of the checkout (``+dirty`` when there are uncommitted changes)."""
    try:
        root = str(repo_root())
        sha = subprocess.run(
            ["git", "-C", root, "rev-parse", "--short=12", "HEAD"],
            capture_output=True, text=True, check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", root, "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, check=True,
        ).stdout.strip()
        return sha + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
