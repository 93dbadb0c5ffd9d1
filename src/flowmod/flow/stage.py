"""The flow stage (chapter 03): the flow of every selected pair with each method of the profile.

Two levels of caching, both keyed so that nothing made from other inputs can ever match:

* the **pool** of per-pair flow files, ``<run>/flow/<method>/pool/<options>/<pair key>.npy``:
  ``options`` is the fingerprint of the method, its code (digest and version), its options
  with their defaults, the storage dtype and scale; a pair's key is the fingerprint of what
  its flow reads (:func:`pair_keys`): for image methods the two image files' names and
  contents, for ``gt`` the world's own description (:func:`world_identity`), the pair's two
  sample_data tokens and its image files' names and sizes. Files are written atomically one
  by one, each with its sha256 logged (a file changed in place is computed again, never
  reused: :func:`altered`), so a killed run resumes where it stopped; a forced recompute
  replaces each file only when its new flow is written; other options live side by side
  (switching back costs nothing). A flow node's manifest records its pool files like its
  own, so a damaged one makes the node "damaged" (:meth:`flowmod.dag.Build.cached`).
* the **nodes** ``flow[<method>/<part>]`` (:data:`STAGE`; parts ``keyframe``, ``general``,
  and chapter 11's ``wide``): ``index.parquet`` listing, for the part's pairs, their pool file and the
  estimation time, with the node's manifest.

Images are checked (exist and decode) before any flow is computed; nothing is ever deleted
first. :class:`FlowReader` reads a published node's flow back at full image size.
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
from joblib import Parallel, delayed

from flowmod import dag
from flowmod.artefacts import atomic_path, file_digest, file_digests, fingerprint, read_manifest
from flowmod.codedigest import code_id
from flowmod.flow.networks import estimator_options
from flowmod.flow.registry import (
    REGISTRY,
    FlowEstimator,
    ImageError,
    available_methods,
    decode,
    describe_option,
    read_image,
)
from flowmod.flow.store import (
    full_shape,
    load_stored_flow,
    load_stored_valid,
    npy_header,
    npy_ok,
    store_flow,
    valid_path,
)
from flowmod.progress import bar
from flowmod.select import PARTS, WIDE, objects_node, read_table

if TYPE_CHECKING:
    from flowmod.params import Params

log = logging.getLogger(__name__)

#: Each pool file's estimation seconds and sha256 when it was written, one JSON line per
#: computed pair (last one wins): a reused file must still have that content.
TIMINGS = "seconds.jsonl"
#: The stat cache of the digests of the images (the image methods' pair keys) and of the
#: pool's files, in each pool folder.
DIGESTS = ".image-digests.json"

# --- images --------------------------------------------------------------------------------

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
    img, warning = decode(path, cv2.IMREAD_REDUCED_GRAYSCALE_8)
    if img is None:
        return "cannot be decoded"
    return f"corrupt: {warning}" if warning else None


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


# --- keys ----------------------------------------------------------------------------------

#: Estimator arguments that do not change the result (where and how fast it runs) or that
#: the pair key already covers (the data).
_NOT_CONFIG = ("device", "batch_size", "model", "dataroot", "version")


def options_config(method: str, dtype: str, store_scale: float,
                   options: Mapping[str, Any]) -> dict[str, Any]:
    """What a method's flow files depend on besides the pair: method, its code (the
    estimator's module and what it imports, :func:`flowmod.codedigest.code_id`, and the
    class's ``code_version`` override), its options with their defaults, the storage dtype
    and scale."""
    if method not in REGISTRY:
        raise ValueError(f"unknown flow method {method!r}; known: {', '.join(available_methods())}")
    if dtype not in ("float16", "float32"):
        raise ValueError(f"dtype={dtype!r}; allowed: float16, float32")
    if not 0.0 < store_scale <= 1.0:
        raise ValueError(f"store_scale={store_scale}; allowed: 0 < store_scale <= 1")
    cls = REGISTRY[method]
    extra = {"dataroot": None, "version": None} if cls.inputs == "tokens" else {}
    try:
        bound = inspect.signature(cls).bind(**extra, **options)
    except TypeError as e:
        raise TypeError(f"flow method {cls.name!r}: {e}") from None
    bound.apply_defaults()
    opts = {k: describe_option(v) for k, v in sorted(bound.arguments.items()) if k not in _NOT_CONFIG}
    for k in cls.file_options:  # new content under an old name is another input
        if isinstance(opts.get(k), str) and Path(opts[k]).expanduser().is_file():
            opts[f"{k}_sha256"] = file_digest(Path(opts[k]).expanduser())
    return {"method": method, "code_version": cls.code_version, "code": code_id(cls.__module__),
            "dtype": dtype, "store_scale": float(store_scale), "options": opts}


def pool_config(method: str, dtype: str, store_scale: float, options: Mapping[str, Any],
                writer: FlowFiles | None = None) -> dict[str, Any]:
    """What a pool folder's files depend on besides the pair (its name is the fingerprint):
    :func:`options_config` and, for a writer other than flow files, its ``config()``."""
    config = options_config(method, dtype, store_scale, options)
    if writer is not None and writer.config():  # flow files keep the key they always had
        config["writer"] = {**writer.config(), "code": code_id(type(writer).__module__)}
    return config


def _keys(pairs: pd.DataFrame, dataroot: str | os.PathLike[str], world: str,
          extras: Mapping[str, Any] | None, by_images: bool = False,
          cache: Path | None = None) -> list[str]:
    """:func:`pair_keys`, with each pair's ``extras`` entry in its key when given."""
    keys = pair_keys(pairs, dataroot, world, by_images, cache)
    if extras is None:
        return keys
    ids = [str(p) for p in pairs["pair_id"]]
    missing = [i for i in ids if i not in extras]
    if missing:
        raise ValueError(f"extras lacks pair(s) {missing[:5]}")
    return [fingerprint({"pair": k, "extra": extras[i]}) for k, i in zip(keys, ids, strict=True)]


def pair_files(pairs: pd.DataFrame, method: str, dataroot: str | os.PathLike[str], world: str,
               dtype: str, store_scale: float, writer: FlowFiles | None = None,
               extras: Mapping[str, Any] | None = None, digests: Path | None = None,
               **options: Any) -> dict[str, str]:
    """``{pair_id: file}``: where :func:`compute_flow` with the same arguments keeps each
    pair (relative to the pool root), computing nothing (``digests``: a stat cache of the
    images' digests)."""
    writer = writer or FlowFiles(dtype, store_scale)
    opts_fp = fingerprint(pool_config(method, dtype, store_scale, options, writer))
    keys = _keys(pairs, dataroot, world, extras, REGISTRY[method].inputs == "images", digests)
    return {str(p): f"{opts_fp}/{k}.npy" for p, k in zip(pairs["pair_id"], keys, strict=True)}


def pair_keys(pairs: pd.DataFrame, dataroot: str | os.PathLike[str], world: str,
              by_images: bool = False, cache: Path | None = None) -> list[str]:
    """Per-pair cache keys, each from what the pair's flow reads. Image methods
    (``by_images``: DIS, Farneback, the networks): the two image files' names and sha256
    (``cache``: a stat cache of those digests), so an edited annotation or another pair's
    image leaves the key alone. Token methods (``gt``, read from the world's records): ``world``
    (what the method reads of the data, :func:`world_identity`), the two sample_data tokens
    and the images' names and sizes.

    A missing image raises :class:`ImageError` naming it."""
    root = Path(dataroot)
    rels = [str(rel) for r in pairs.itertuples(index=False) for rel in (r.path_1, r.path_2)]
    missing = next((rel for rel in rels if not (root / rel).is_file()), None)
    if missing is not None:
        raise ImageError(f"image missing: {root / missing}")
    what = (file_digests([root / rel for rel in rels], cache) if by_images
            else [(root / rel).stat().st_size for rel in rels])
    keys = []
    for i, r in enumerate(pairs.itertuples(index=False)):
        images = [(rels[2 * i], what[2 * i]), (rels[2 * i + 1], what[2 * i + 1])]
        keys.append(fingerprint({"images": images}) if by_images else fingerprint(
            {"world": world, "sd": [r.sd_token_1, r.sd_token_2], "images": images}))
    return keys


def _pool_log(pool: Path) -> dict[str, dict[str, Any]]:
    """``{key: record}`` from :data:`TIMINGS` (the last line of a key wins; unreadable
    lines of a killed run skipped)."""
    out: dict[str, dict[str, Any]] = {}
    f = pool / TIMINGS
    if f.is_file():
        for line in f.read_text().splitlines():
            try:
                rec = json.loads(line)
                out[str(rec["key"])] = {"seconds": float(rec["seconds"]),
                                        "sha256": rec.get("sha256")}
            except (ValueError, KeyError, TypeError, AttributeError):
                continue
    return out


def read_timings(pool: Path) -> dict[str, float]:
    """Seconds per pool file from :data:`TIMINGS`."""
    return {k: r["seconds"] for k, r in _pool_log(pool).items()}


def altered(pool: Path, keys: Sequence[str], writer: FlowFiles) -> set[str]:
    """The keys whose complete pool file no longer has the content recorded when it was
    written (changed in place: zeroed, overwritten at the same size); they are computed
    again instead of reused. Files written before digests were recorded are trusted."""
    logged = {k: r["sha256"] for k, r in _pool_log(pool).items() if r["sha256"]}
    check = [k for k in dict.fromkeys(keys)
             if k in logged and writer.complete(pool / f"{k}.npy")]
    now = file_digests([pool / f"{k}.npy" for k in check], pool / DIGESTS)
    return {k for k, d in zip(check, now, strict=True) if d != logged[k]}


# --- what is kept of a pair -----------------------------------------------------------------

class FlowFiles:
    """What the stage keeps of a pair's flow: the flow file itself (:func:`store_flow` at
    ``dtype`` and ``store_scale``). The default writer of :func:`compute_flow`; another
    writer (the crops of :class:`flowmod.crops.PairCrops`) keeps something else per pair.

    A writer has ``config()`` (what its files depend on besides the flow and the pair; {} for
    flow files), ``write(out, flow, valid, extra)`` (``extra``: the pair's own input, e.g.
    its boxes), ``complete(out)`` (a finished file is there) and ``shape(out)`` (the full
    flow shape it was made from).
    """

    def __init__(self, dtype: str = "float16", store_scale: float = 1.0) -> None:
        self.dtype, self.store_scale = dtype, float(store_scale)

    def config(self) -> dict[str, Any]:
        return {}

    def write(self, out: Path, flow: np.ndarray, valid: np.ndarray | None, extra: Any) -> None:
        store_flow(out, flow, self.dtype, self.store_scale, valid=valid)

    def complete(self, out: Path) -> bool:
        return npy_ok(out, self.dtype)

    def shape(self, out: Path) -> list[int]:
        stored = npy_header(out)[0]
        return [*full_shape(stored, self.store_scale), *stored[2:]]


# --- computing ------------------------------------------------------------------------------

Result = tuple[str, float, tuple[int, ...]]
#: One pair's job for networks: (key, image 1, image 2, output file, extra).
Job = tuple[str, str, str, Path, Any]


def _one_image_pair(est: FlowEstimator, key: str, path1: str, path2: str, out: Path,
                    writer: FlowFiles, extra: Any, threads: int) -> Result:
    """Worker: read, estimate, write one pair; returns (key, seconds, shape)."""
    if threads:
        cv2.setNumThreads(threads)
    img1, img2 = read_image(path1), read_image(path2)
    t0 = time.perf_counter()
    flow = est.estimate(img1, img2)
    seconds = time.perf_counter() - t0
    writer.write(out, flow, None, extra)
    return key, seconds, flow.shape


def _one_token_pair(est: FlowEstimator, key: str, tok1: str, tok2: str, out: Path,
                    writer: FlowFiles, extra: Any, threads: int) -> Result:
    """Worker for token methods (``gt``)."""
    if threads:
        cv2.setNumThreads(threads)
    t0 = time.perf_counter()
    flow, valid = est.estimate_tokens(tok1, tok2)  # type: ignore[attr-defined]
    seconds = time.perf_counter() - t0
    writer.write(out, flow, valid, extra)
    return key, seconds, flow.shape


def _batched(est: FlowEstimator, jobs: list[Job], writer: FlowFiles) -> Iterator[Result]:
    """Sequential batches for networks; the next batch's images load in a thread meanwhile."""
    bs = max(1, getattr(est, "batch_size", 1))
    chunks = [jobs[i : i + bs] for i in range(0, len(jobs), bs)]

    def load(chunk: list[Job]) -> list[tuple[np.ndarray, np.ndarray]]:
        return [(read_image(a), read_image(b)) for _, a, b, _, _ in chunk]

    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        nxt = pool.submit(load, chunks[0]) if chunks else None
        for i, chunk in enumerate(chunks):
            assert nxt is not None
            imgs = nxt.result()
            nxt = pool.submit(load, chunks[i + 1]) if i + 1 < len(chunks) else None
            t0 = time.perf_counter()
            flows = est.estimate_batch([a for a, _ in imgs], [b for _, b in imgs])
            seconds = (time.perf_counter() - t0) / len(chunk)
            for (key, _, _, out, extra), flow in zip(chunk, flows, strict=True):
                writer.write(out, flow, None, extra)
                yield key, seconds, flow.shape


def compute_flow(
    pairs: pd.DataFrame,
    method: str,
    pool_root: str | os.PathLike[str],
    *,
    dataroot: str | os.PathLike[str],
    version: str,
    world: str,
    dtype: str = "float16",
    n_jobs: int = 2,
    progress: bool = True,
    force: bool = False,
    store_scale: float = 1.0,
    label: str = "",
    executor: str = "local",
    ray_address: str = "local",
    writer: FlowFiles | None = None,
    extras: Mapping[str, Any] | None = None,
    **options: Any,
) -> pd.DataFrame:
    """Flow of every pair of ``pairs`` (rows of pairs.parquet) with ``method``, in the pool.

    Files: ``<pool_root>/<options fingerprint>/<pair key>.npy``, (h, w, 2) ``dtype``, pixels of
    the full image, frame 1 -> 2, stored at ``store_scale`` of the image size (a quarter of
    the disk at 0.5; :func:`flowmod.flow.store.load_stored_flow` restores the size). ``world``
    is the data's fingerprint (it enters every pair key). Pairs whose file is complete are
    not recomputed (``force`` recomputes them, each file replaced only when its new flow is
    written). Images of the pairs to compute are checked before any work. ``executor``
    ``local``: CPU methods run in ``n_jobs`` processes, networks in sequential batches;
    ``ray``: on the Ray cluster at ``ray_address`` (:mod:`flowmod.flow.distributed`), with
    the same files. ``writer`` (default :class:`FlowFiles`) decides what is kept of each
    pair; ``extras`` (``{pair_id: JSON-able value}``) is each pair's own input for it and
    enters the pair's key.

    Returns one row per pair in ``pairs``' order: pair_id, key, file (path relative to
    ``pool_root``), seconds (estimation time; NaN if unknown), shape (full (H, W, 2)),
    computed (bool, this call).
    """
    writer = writer or FlowFiles(dtype, store_scale)
    if executor not in ("local", "ray"):
        raise ValueError(f"executor={executor!r}; allowed: local, ray")
    cls = REGISTRY[method]
    ids = _check_pairs(pairs, method)
    pool, opts_fp = _open_pool(Path(pool_root), pool_config(method, dtype, store_scale, options,
                                                            writer))
    root = Path(dataroot)
    keys = _keys(pairs, root, world, extras, cls.inputs == "images", pool / DIGESTS)
    extra = [None] * len(ids) if extras is None else [extras[i] for i in ids]
    redo = altered(pool, keys, writer) if not force else set()
    todo = [i for i, k in enumerate(keys)
            if force or k in redo or not writer.complete(pool / f"{k}.npy")]
    rows = pairs.iloc[todo]
    if len(rows) and cls.inputs == "images":
        check_images([root / p for p in (*rows["path_1"], *rows["path_2"])], n_jobs=n_jobs)
    computed: set[str] = set()
    if len(rows):
        calls = [(keys[i], *((r.sd_token_1, r.sd_token_2) if cls.inputs == "tokens" else
                             (str(root / r.path_1), str(root / r.path_2))),
                  pool / f"{keys[i]}.npy", extra[i])
                 for i, r in zip(todo, rows.itertuples(index=False), strict=True)]
        results = _results(cls, calls, writer, options, dataroot=dataroot, version=version,
                           n_jobs=n_jobs, executor=executor, ray_address=ray_address)
        computed = _log_results(results, pool, len(rows), label or f"flow {method}", progress)
    timings = read_timings(pool)
    shapes = [writer.shape(pool / f"{k}.npy") for k in keys]
    return pd.DataFrame({
        "pair_id": ids, "key": keys, "file": [f"{opts_fp}/{k}.npy" for k in keys],
        "seconds": [timings.get(k, float("nan")) for k in keys], "shape": shapes,
        "computed": [k in computed for k in keys],
    })


def _check_pairs(pairs: pd.DataFrame, method: str) -> list[str]:
    """The pairs' ids; ValueError for a missing column or a duplicate id."""
    need = ["pair_id", "sd_token_1", "sd_token_2", "path_1", "path_2"]
    missing_cols = [c for c in need if c not in pairs.columns]
    if missing_cols:
        raise ValueError(f"pairs lacks column(s) {missing_cols} needed by method {method!r}")
    ids = [str(p) for p in pairs["pair_id"]]
    dup = pd.Series(ids)[pd.Series(ids).duplicated()].unique().tolist()
    if dup:
        raise ValueError(f"duplicate pair_id in pairs: {dup[:5]}")
    return ids


def _open_pool(pool_root: Path, config: dict[str, Any]) -> tuple[Path, str]:
    """The options folder of the pool (created, with its ``config.json``; temporary files
    of a killed run removed) and its name (the options' fingerprint)."""
    opts_fp = fingerprint(config)
    pool = pool_root / opts_fp
    pool.mkdir(parents=True, exist_ok=True)
    cfg_file = pool / "config.json"
    if not cfg_file.is_file():
        with atomic_path(cfg_file) as tmp:
            tmp.write_text(json.dumps(config, indent=2, sort_keys=True) + "\n")
    for tmp in pool.glob(".*.tmp*"):  # left by a killed run
        tmp.unlink(missing_ok=True)
    return pool, opts_fp


def _results(cls: type[FlowEstimator], calls: list[tuple], writer: FlowFiles,
             options: Mapping[str, Any], *, dataroot: str | os.PathLike[str], version: str,
             n_jobs: int, executor: str, ray_address: str) -> Iterator[Result]:
    """The pairs of ``calls`` ((key, input 1, input 2, out, extra)) computed where the
    executor says: Ray, local processes (CPU methods), sequentially, or in batches
    (networks). Yields (key, seconds, shape) as pairs finish."""
    # built here also to fail early (weights, data); Ray's network actors build their own
    local_opts = ({**options, "device": "cpu"} if executor == "ray" and not cls.cpu_bound
                  else options)
    est = (cls(dataroot=dataroot, version=version, **local_opts)  # type: ignore[call-arg]
           if cls.inputs == "tokens" else cls(**local_opts))
    parallel = est.cpu_bound and n_jobs > 1 and len(calls) > 1
    fn = _one_token_pair if cls.inputs == "tokens" else _one_image_pair
    args = [(est, *c[:4], writer, c[4], 1 if parallel else 0) for c in calls]
    if executor == "ray":
        from flowmod.flow.distributed import ray_results  # lazy: ray is heavy, rarely used

        return ray_results(
            fn, args, cls=cls, options=options, cpu_bound=est.cpu_bound, writer=writer,
            batched=_batched, batch_size=getattr(est, "batch_size", 1), address=ray_address,
            n_jobs=n_jobs)
    if parallel:
        return Parallel(n_jobs=n_jobs, return_as="generator_unordered")(
            delayed(fn)(*a) for a in args)
    if est.cpu_bound:
        return (fn(*a) for a in args)
    return _batched(est, list(calls), writer)


def _log_results(results: Iterator[Result], pool: Path, total: int, label: str,
                 progress: bool) -> set[str]:
    """Consume ``results``, logging each pair's estimation seconds and its file's sha256 to
    the pool's :data:`TIMINGS` as it finishes; returns the keys computed."""
    computed: set[str] = set()
    with (bar(total=total, desc=label, unit="pair", disable=not progress) as pbar,
          open(pool / TIMINGS, "a") as log_f):
        for key, seconds, _shape in results:
            sha = file_digest(pool / f"{key}.npy")  # known to this process: not read again
            log_f.write(json.dumps({"key": key, "seconds": round(seconds, 6),
                                    "sha256": sha}) + "\n")
            log_f.flush()
            computed.add(key)
            pbar.update(1)
    return computed


# --- the stage ------------------------------------------------------------------------------

def flow_root(params: Params) -> Path:
    """``<run_dir>/flow``."""
    return params.run_path / "flow"


#: Pairs of chapter 08's clip (6 s at 6 frames per second).
CLIP_PAIRS = 36


def figure_pair(pairs: pd.DataFrame, objects: pd.DataFrame) -> str:
    """The pair of ``pairs`` with the most objects (Figure 1; the first one on a tie)."""
    n_obj = pairs["pair_id"].map(objects.groupby("pair_id").size()).fillna(0)
    return str(pairs["pair_id"].iloc[int(np.argmax(n_obj.to_numpy()))])


def clip_pairs(pairs: pd.DataFrame, n: int = CLIP_PAIRS) -> pd.DataFrame:
    """Chapter 08's clip: the first ``n`` pairs (in time) of the scene with the most pairs."""
    scene = pairs["scene"].value_counts().index[0]
    return pairs[pairs["scene"] == scene].sort_values("timestamp_1").head(n)


def kept_pairs(pairs: pd.DataFrame, objects: pd.DataFrame, part: str, n: int,
               seed: int, clip: bool = True) -> pd.DataFrame:
    """Crops mode (``flow_store: crops``): the pairs of a part whose flow is kept for the
    book's figures and EPE tables: Figure 1's pair (keyframe) or, with ``clip``, the clip's
    pairs (general), and ``n`` more drawn with ``seed``; in ``pairs``' order."""
    if not len(pairs):
        return pairs
    shown = ({figure_pair(pairs, objects)} if part == "keyframe"
             else set(clip_pairs(pairs)["pair_id"]) if clip else set())
    rest = pairs.loc[~pairs["pair_id"].isin(shown), "pair_id"].to_numpy()
    rng = np.random.default_rng([seed, 0 if part == "keyframe" else 1])
    drawn = rng.choice(rest, size=min(n, len(rest)), replace=False) if len(rest) else []
    return pairs[pairs["pair_id"].isin(shown | set(drawn))]


#: A flow node's one file: per pair its file in the method's pool.
INDEX = "index.parquet"


def unreferenced_pool(p: Params, variants: bool) -> list[Path]:
    """The flow stage's garbage: pool files listed by no flow index (published or kept
    variant; with ``variants``, the files only kept variants list count as unreferenced).
    A method with a build in progress keeps its files: they are its resume point."""
    out: list[Path] = []
    for method_dir in sorted((p.run_path / "flow").glob("*")):
        pool = method_dir / "pool"
        if not pool.is_dir() or any(method_dir.glob(".*.building-*")):
            continue
        keep: set[Path] = set()
        for index in method_dir.glob(f"*/{INDEX}"):  # published and .variant- folders
            if variants and ".variant-" in index.parent.name:
                continue
            for f in pd.read_parquet(index, columns=["file"])["file"]:
                keep |= {pool / f, valid_path(pool / f)}
        out += [f for f in sorted(pool.rglob("*.npy")) if f not in keep]
    return out


def build(b: dag.Build, progress: bool) -> Mapping[str, Any]:
    """Build one ``flow[<method>/<part>]`` node: the flow of the part's pairs (in crops mode
    only those :func:`kept_pairs` keeps), from the pool where possible; ``index.parquet``."""
    q, method, part = b.params, b.node.method, b.node.part
    sel = b.input_dir(objects_node(part))
    pairs = read_table(sel, "pairs")
    if q.flow_store == "crops":  # the crops stage computes the rest itself
        objects = read_table(sel, "objects")
        pairs = kept_pairs(pairs, objects, part, q.flow_keep_pairs, q.seed,
                           clip=method == q.clip_method)
    idx = compute_flow(
        pairs, method, flow_root(q) / method / "pool", dataroot=q.dataroot_path,
        version=q.version, world=world_identity(q, method, b.inputs["world"]["fingerprint"]),
        dtype=q.flow_dtype, n_jobs=q.n_jobs, progress=progress, force=q.force,
        store_scale=q.flow_scale, label=f"flow {method}/{part}",
        executor=q.executor, ray_address=q.ray_address,
        **estimator_options(q, method))
    with atomic_path(b.start(fresh=True) / INDEX) as tmp:
        idx.drop(columns="computed").to_parquet(tmp, index=False)
    b.cached(flow_root(q) / method / "pool" / f for f in idx["file"])
    return {"pairs": len(idx), "computed": int(idx["computed"].sum()),
            "store_scale": q.flow_scale, "dtype": q.flow_dtype, "kept": q.flow_store}


def world_identity(q: dag.StageParams, method: str, world: str) -> str:
    """What the pair keys of ``method`` take of the data besides each pair: for a token
    method the digests of the files it reads (``world_files``: ``gt`` reads the world's own
    description, so an edited annotation recomputes none of its pairs), else the data's
    fingerprint ``world`` (image methods' keys are their images)."""
    files = REGISTRY[method].world_files
    if not files:
        return world
    vdir = q.dataroot_path / q.version
    return fingerprint({f: file_digest(vdir / f, dag.digest_cache(q.all)) for f in files})


def _nodes(p: Params) -> list[dag.Node]:
    """The paper's two parts of every flow method; chapter 11's part of its methods (in
    pairs mode: in crops mode its crops compute their flow)."""
    out = [dag.Node("flow", m, part) for m in p.flow_methods for part in PARTS]
    if p.flow_store == "pairs":
        out += [dag.Node("flow", m, WIDE) for m in p.wide_methods]
    return out


#: The flow stage (chapter 03; chapter 11's part with extension_build).
STAGE = dag.Stage("flow", 2, "03", "flow/{method}/{part}", "optical flow of every pair",
                  nodes=_nodes, inputs=lambda n, p: (dag.Node("world"), objects_node(n.part)),
                  build=build, parts={WIDE: ("11", "extension_build")},
                  outputs=(INDEX,), garbage=unreferenced_pool)


class FlowReader:
    """The published flow of one node: ``reader.load(pair_id)`` -> (H, W, 2) float32, pixels
    of the full image, frame 1 -> 2."""

    def __init__(self, folder: Path, pool: Path, method: str, part: str = "keyframe") -> None:
        """``folder``: the published ``flow[<method>/<part>]`` node; ``pool``: the method's
        pool of per-pair files (:func:`flow_root` / method / pool)."""
        self.method, self.part = method, part
        self.index = pd.read_parquet(folder / INDEX)
        rec = read_manifest(folder / "manifest.json") or {}
        self.store_scale = float(rec.get("store_scale", 1.0))
        self.pool = pool
        self._files = dict(zip(self.index["pair_id"], self.index["file"], strict=True))

    def __contains__(self, pair_id: str) -> bool:
        return pair_id in self._files

    @property
    def pair_ids(self) -> list[str]:
        """The pairs whose flow is stored (all of the part's, or those kept in crops mode)."""
        return list(self._files)

    def path(self, pair_id: str) -> Path:
        if pair_id not in self._files:
            raise KeyError(f"pair {pair_id!r} is not in flow[{self.method}/{self.part}]")
        return self.pool / self._files[pair_id]

    def load(self, pair_id: str) -> np.ndarray:
        return load_stored_flow(self.path(pair_id), self.store_scale)

    def load_valid(self, pair_id: str) -> np.ndarray | None:
        """The stored valid mask (H, W) bool (``gt`` only), or None."""
        return load_stored_valid(self.path(pair_id), self.store_scale)
