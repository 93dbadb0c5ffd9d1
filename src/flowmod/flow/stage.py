"""The flow stage: every selected pair with every method of the profile, cached and resumable.
"""

from __future__ import annotations

import concurrent.futures
import inspect
import json
import logging
import os
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import pandas as pd

from flowmod.artefacts import atomic_path
from flowmod.flow.metrics import boxes_mask, epe, fl_all
from flowmod.flow.networks import estimator_options
from flowmod.flow.registry import (
    _REGISTRY,
    FlowEstimator,
    ImageError,
    _describe,
    available_methods,
    read_image,
)
from flowmod.flow.store import _npy_header, _npy_ok, full_shape, load_flow, store_flow

if TYPE_CHECKING:
    from flowmod.params import Params

log = logging.getLogger(__name__)
#: While computing, the index is rewritten this often (s), so timings survive an interruption.
INDEX_WRITE_SECONDS = 30.0

# --------------------------------------------------------------------------------------------
# the stage runner
# --------------------------------------------------------------------------------------------

_JPEG_SOI, _JPEG_EOI = b"\xff\xd8", b"\xff\xd9"
_PNG_SIG = b"\x89PNG\r\n\x1a\n"


def _image_problem(path: Path) -> str | None:
    """None if ``path`` looks like a complete, decodable image, else what is wrong."""
    try:
        size = path.stat().st_size
    except OSError:
        return "missing"
    if size == 0:
        return "empty"
    try:
        with open(path, "rb") as f:
            head = f.read(8)
            f.seek(max(0, size - 64))
            tail = f.read()
    except OSError as e:
        return f"unreadable ({e.strerror})"
    if head.startswith(_JPEG_SOI) and _JPEG_EOI not in tail:
        return "truncated JPEG (no end marker)"
    if head.startswith(_PNG_SIG) and b"IEND" not in tail:
        return "truncated PNG (no IEND chunk)"
    if cv2.imread(str(path), cv2.IMREAD_REDUCED_GRAYSCALE_8) is None:
        return "cannot be decoded"
    return None


def check_images(paths: Sequence[str | os.PathLike[str]], n_jobs: int = 2, show: int = 5) -> None:
    """Check that every image exists and decodes; :class:`ImageError` listing the first
    ``show`` bad files (with the reason) and their count."""
    unique = list(dict.fromkeys(Path(p) for p in paths))
    with concurrent.futures.ThreadPoolExecutor(max(1, n_jobs)) as pool:
        problems = [
            (p, why) for p, why in zip(unique, pool.map(_image_problem, unique), strict=True) if why
        ]
    if problems:
        first = "; ".join(f"{p} ({why})" for p, why in problems[:show])
        more = f" and {len(problems) - show} more" if len(problems) > show else ""
        raise ImageError(
            f"{len(problems)} of {len(unique)} images are missing or corrupt: {first}{more}"
        )



_NOT_CONFIG = ("device", "batch_size", "model", "dataroot", "version")


def _config(cls: type[FlowEstimator], dtype: str, options: Mapping[str, Any]) -> dict[str, Any]:
    """What the cached flows depend on: method, dtype and the options with their defaults."""
    extra = {"dataroot": None, "version": None} if cls.inputs == "tokens" else {}
    try:
        bound = inspect.signature(cls).bind(**extra, **options)
    except TypeError as e:
        raise TypeError(f"flow method {cls.name!r}: {e}") from None
    bound.apply_defaults()
    opts = {k: _describe(v) for k, v in sorted(bound.arguments.items()) if k not in _NOT_CONFIG}
    return {"method": cls.name, "dtype": dtype, "options": opts, "format": 1}


def _one_image_pair(
    est: FlowEstimator, pid: str, path1: str, path2: str, out: Path, storage: tuple[str, float],
    threads: int,
) -> tuple[str, float, tuple[int, ...]]:
    """Worker: read, estimate, save one pair; returns (pair_id, seconds, shape)."""
    if threads:
        cv2.setNumThreads(threads)
    img1, img2 = read_image(path1), read_image(path2)
    t0 = time.perf_counter()
    flow = est.estimate(img1, img2)
    seconds = time.perf_counter() - t0
    store_flow(out, flow, *storage)
    return pid, seconds, flow.shape


def _one_token_pair(
    est: FlowEstimator, pid: str, tok1: str, tok2: str, out: Path, storage: tuple[str, float],
    threads: int,
) -> tuple[str, float, tuple[int, ...]]:
    """Worker for token methods (``gt``)."""
    if threads:
        cv2.setNumThreads(threads)
    t0 = time.perf_counter()
    flow = est.estimate_tokens(tok1, tok2)  # type: ignore[attr-defined]
    seconds = time.perf_counter() - t0
    store_flow(out, flow, *storage)
    return pid, seconds, flow.shape


def _batched(
    est: FlowEstimator, jobs: list[tuple[str, str, str, Path]], storage: tuple[str, float]
) -> Iterator[tuple[str, float, tuple[int, ...]]]:
    """Sequential batches for networks; the next batch's images load in a thread meanwhile."""
    bs = max(1, getattr(est, "batch_size", 1))
    chunks = [jobs[i : i + bs] for i in range(0, len(jobs), bs)]

    def load(chunk: list[tuple[str, str, str, Path]]) -> list[tuple[np.ndarray, np.ndarray]]:
        return [(read_image(a), read_image(b)) for _, a, b, _ in chunk]

    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        nxt = pool.submit(load, chunks[0]) if chunks else None
        for i, chunk in enumerate(chunks):
            assert nxt is not None
            imgs = nxt.result()
            nxt = pool.submit(load, chunks[i + 1]) if i + 1 < len(chunks) else None
            t0 = time.perf_counter()
            flows = est.estimate_batch([a for a, _ in imgs], [b for _, b in imgs])
            seconds = (time.perf_counter() - t0) / len(chunk)
            for (pid, _, _, out), flow in zip(chunk, flows, strict=True):
                store_flow(out, flow, *storage)
                yield pid, seconds, flow.shape


def _read_index(path: Path) -> pd.DataFrame | None:
    if not path.is_file():
        return None
    try:
        df = pd.read_parquet(path)
    except Exception as e:  # noqa: BLE001 - a bad index is rebuilt from the files
        log.warning("ignoring unreadable flow index %s (%s)", path, e)
        return None
    return df if "pair_id" in df.columns else None


def _write_index(
    path: Path, rows: Mapping[str, dict[str, Any]], order: Sequence[str]
) -> pd.DataFrame:
    known = set(order)
    ids = [p for p in order if p in rows] + [p for p in rows if p not in known]
    df = pd.DataFrame(
        {
            "pair_id": ids,
            "seconds": [float(rows[p]["seconds"]) for p in ids],
            "shape": [[int(x) for x in rows[p]["shape"]] for p in ids],
            "file": [f"{p}.npy" for p in ids],
        }
    )
    with atomic_path(path) as tmp:
        df.to_parquet(tmp, index=False)
    return df


def compute_flow(
    pairs: pd.DataFrame,
    method: str,
    out_dir: str | os.PathLike[str],
    *,
    dataroot: str | os.PathLike[str],
    version: str,
    dtype: str = "float16",
    n_jobs: int = 2,
    progress: bool = True,
    force: bool = False,
    store_scale: float = 1.0,
    **options: Any,
) -> pd.DataFrame:
    """Flow of every pair of ``pairs`` (rows of pairs.parquet) with ``method``.

    ``store_scale`` < 1 stores each flow at that fraction of the image size (values still in
    full-image pixels; :func:`load_flow` restores the size): 0.5 needs a quarter of the disk.

    Writes ``<out_dir>/<method>/<pair_id>.npy`` ((H, W, 2) ``dtype``, pixels, frame 1 -> 2)
    and ``<out_dir>/<method>/index.parquet`` (pair_id, seconds = estimation time per pair,
    shape, file name in that folder), both atomically. Resumable: pairs whose .npy is complete
    (header, dtype and size checked) are not recomputed; temporary and truncated files are.
    A change of method options or dtype (recorded in ``config.json``), or ``force``, deletes
    the folder's flows first. Images (``path_1``, ``path_2`` relative to ``dataroot``) are
    checked before any work. CPU methods run pairs in ``n_jobs`` processes; networks run
    sequential batches. Returns the index rows of ``pairs`` plus ``computed`` (bool, this
    call). One run per method folder at a time.
    """
    if method not in _REGISTRY:
        raise ValueError(f"unknown flow method {method!r}; known: {', '.join(available_methods())}")
    if dtype not in ("float16", "float32"):
        raise ValueError(f"dtype={dtype!r}; allowed: float16, float32")
    cls = _REGISTRY[method]
    need = [
        "pair_id",
        *(("sd_token_1", "sd_token_2") if cls.inputs == "tokens" else ("path_1", "path_2")),
    ]
    missing_cols = [c for c in need if c not in pairs.columns]
    if missing_cols:
        raise ValueError(f"pairs lacks column(s) {missing_cols} needed by method {method!r}")
    ids = [str(p) for p in pairs["pair_id"]]
    dup = pd.Series(ids)[pd.Series(ids).duplicated()].unique().tolist()
    if dup:
        raise ValueError(f"duplicate pair_id in pairs: {dup[:5]}")
    bad = [p for p in ids if not p or "/" in p or "\\" in p or p.startswith(".")]
    if bad:
        raise ValueError(f"pair_id values must be plain file names: {bad[:5]}")

    folder = Path(out_dir) / method
    folder.mkdir(parents=True, exist_ok=True)
    index_path = folder / "index.parquet"
    config_path = folder / "config.json"
    if not 0.0 < store_scale <= 1.0:
        raise ValueError(f"store_scale={store_scale}; allowed: 0 < store_scale <= 1")
    config = {**_config(cls, dtype, options), "store_scale": float(store_scale)}
    storage = (dtype, float(store_scale))
    old_config = None
    if config_path.is_file():
        try:
            old_config = json.loads(config_path.read_text())
        except (OSError, json.JSONDecodeError):
            old_config = None
    stale = force or (old_config is not None and old_config != config)
    for tmp in folder.glob(".*.tmp*"):  # left by an interrupted run
        tmp.unlink(missing_ok=True)
    if stale:
        log.warning(
            "flow/%s: %s; deleting its cached flows",
            method,
            "forced" if force else f"options changed ({old_config} -> {config})",
        )
        for f in folder.glob("*.npy"):
            f.unlink()
        index_path.unlink(missing_ok=True)
    if stale or old_config is None:
        with atomic_path(config_path) as tmp:
            tmp.write_text(json.dumps(config, indent=2, sort_keys=True) + "\n")

    rows: dict[str, dict[str, Any]] = {}
    old = _read_index(index_path)
    if old is not None:
        for r in old.itertuples(index=False):
            if (folder / f"{r.pair_id}.npy").is_file():
                rows[str(r.pair_id)] = {"seconds": r.seconds, "shape": list(r.shape)}
    done = set()
    for pid in ids:
        f = folder / f"{pid}.npy"
        if _npy_ok(f, dtype):
            done.add(pid)
            if pid not in rows:  # finished before the index was last written
                stored = _npy_header(f)[0]
                rows[pid] = {"seconds": float("nan"),
                             "shape": [*full_shape(stored, store_scale), *stored[2:]]}
        else:
            rows.pop(pid, None)
    todo = pairs[[pid not in done for pid in ids]]

    root = Path(dataroot)
    if len(todo) and cls.inputs == "images":
        paths = [root / p for p in (*todo["path_1"], *todo["path_2"])]
        check_images(paths, n_jobs=n_jobs)

    computed: set[str] = set()
    if len(todo):
        if cls.inputs == "tokens":
            est = cls(dataroot=dataroot, version=version, **options)  # type: ignore[call-arg]
        else:
            est = cls(**options)
        parallel = est.cpu_bound and n_jobs > 1 and len(todo) > 1
        threads = 1 if parallel else 0
        results: Iterator[tuple[str, float, tuple[int, ...]]] | Any
        if cls.inputs == "tokens":
            calls = [
                (
                    _one_token_pair,
                    (
                        est,
                        str(r.pair_id),
                        r.sd_token_1,
                        r.sd_token_2,
                        folder / f"{r.pair_id}.npy",
                        storage,
                        threads,
                    ),
                )
                for r in todo.itertuples(index=False)
            ]
        else:
            calls = [
                (
                    _one_image_pair,
                    (
                        est,
                        str(r.pair_id),
                        str(root / r.path_1),
                        str(root / r.path_2),
                        folder / f"{r.pair_id}.npy",
                        storage,
                        threads,
                    ),
                )
                for r in todo.itertuples(index=False)
            ]
        if parallel:
            from joblib import Parallel, delayed

            results = Parallel(n_jobs=n_jobs, return_as="generator_unordered")(
                delayed(fn)(*args) for fn, args in calls
            )
        elif est.cpu_bound:
            results = (fn(*args) for fn, args in calls)
        else:
            jobs = [(a[1], a[2], a[3], a[4]) for _, a in calls]
            results = _batched(est, jobs, storage)

        from tqdm import tqdm

        last_write = time.monotonic()
        with tqdm(total=len(todo), desc=f"flow {method}", unit="pair", disable=not progress) as bar:
            for pid, seconds, shape in results:
                rows[pid] = {"seconds": seconds, "shape": list(shape)}
                computed.add(pid)
                bar.update(1)
                if time.monotonic() - last_write > INDEX_WRITE_SECONDS:  # if interrupted
                    _write_index(index_path, rows, ids)
                    last_write = time.monotonic()
    index = _write_index(index_path, rows, ids)
    out = index[index["pair_id"].isin(set(ids))].reset_index(drop=True)
    out["computed"] = out["pair_id"].isin(computed)
    return out


# --------------------------------------------------------------------------------------------
# the stage (notebook 03)
# --------------------------------------------------------------------------------------------

def flow_dir(params: Params) -> Path:
    """``<run_dir>/flow``."""
    return params.run_path / "flow"


def run(params: Params, pairs: pd.DataFrame, progress: bool = True) -> dict[str, pd.DataFrame]:
    """Flow of every pair for each method of ``params.flow_methods``; cached and resumable.

    Returns ``{method: index}`` (pair_id, seconds, shape, file, computed).
    """
    out = {}
    for method in params.flow_methods:
        out[method] = compute_flow(
            pairs, method, flow_dir(params), dataroot=params.dataroot_path,
            version=params.version, dtype=params.flow_dtype, n_jobs=params.n_jobs,
            progress=progress, force=params.force, store_scale=params.flow_scale,
            **estimator_options(params, method),
        )
    return out


def accuracy_table(
    params: Params, pairs: pd.DataFrame, objects: pd.DataFrame, indexes: dict[str, pd.DataFrame],
    n_pairs: int = 20, seed: int = 0,
) -> pd.DataFrame:
    """EPE / Fl-all against the world's exact flow, overall and inside far (keyframe set,
    min-max distance) and near (generalisation set, < min_distance) vehicle boxes, with the
    median seconds per pair; on ``n_pairs`` random pairs of each set (synthetic world only)."""
    from flowmod import world

    rng = np.random.default_rng(seed)
    rows = []
    for kind, dmin, dmax in (("keyframe", params.min_distance, params.max_distance),
                             ("general", 0.0, params.min_distance)):
        ids = pairs.loc[pairs["set"] == kind, "pair_id"].to_numpy()
        if len(ids) == 0:
            continue
        pick = rng.choice(ids, size=min(n_pairs, len(ids)), replace=False)
        sub = pairs.set_index("pair_id").loc[pick]
        gts = {pid: world.gt_flow(params.dataroot_path, params.version, r.sd_token_1,
                                  r.sd_token_2) for pid, r in sub.iterrows()}
        for method in indexes:
            acc: dict[str, list[float]] = {"epe": [], "fl": [], "epe_box": [], "fl_box": []}
            for pid, (gt, valid) in gts.items():
                est = load_flow(flow_dir(params), method, pid)
                obj = objects[(objects["pair_id"] == pid) & objects["distance"].between(dmin, dmax)]
                mask = boxes_mask(obj[["xmin", "ymin", "xmax", "ymax"]].to_numpy(), gt.shape)
                acc["epe"].append(epe(est, gt, valid))
                acc["fl"].append(fl_all(est, gt, valid))
                if (mask & valid).any():
                    acc["epe_box"].append(epe(est, gt, valid, mask))
                    acc["fl_box"].append(fl_all(est, gt, valid, mask))
            secs = indexes[method]["seconds"]
            rows.append({
                "set": kind, "vehicles": f"{dmin:g}-{dmax:g} m", "method": method,
                "EPE all (px)": np.mean(acc["epe"]), "Fl-all (%)": np.mean(acc["fl"]),
                "EPE boxes (px)": np.mean(acc["epe_box"]) if acc["epe_box"] else np.nan,
                "Fl-all boxes (%)": np.mean(acc["fl_box"]) if acc["fl_box"] else np.nan,
                "s / pair": float(np.nanmedian(secs)) if secs.notna().any() else np.nan,
                "pairs": len(gts),
            })
    return pd.DataFrame(rows)


def box_flow_magnitude(objects: pd.DataFrame, load: Any, inner: float = 0.6) -> np.ndarray:
    """Median flow magnitude (px) over the central ``inner`` fraction of each object's box.

    ``load(pair_id) -> (H, W, 2)``; each pair's flow is read once.
    """
    out = np.full(len(objects), np.nan)
    for pid, idx in objects.groupby("pair_id", sort=False).indices.items():
        f = load(pid)
        mag = np.linalg.norm(f.astype(np.float32), axis=-1)
        for i in idx:
            o = objects.iloc[i]
            cx, cy = (o.xmin + o.xmax) / 2, (o.ymin + o.ymax) / 2
            hw, hh = (o.xmax - o.xmin) * inner / 2, (o.ymax - o.ymin) * inner / 2
            y0, y1 = int(max(cy - hh, 0)), int(min(cy + hh, mag.shape[0] - 1)) + 1
            x0, x1 = int(max(cx - hw, 0)), int(min(cx + hw, mag.shape[1] - 1)) + 1
            out[i] = float(np.median(mag[y0:y1, x0:x1]))
    return out

