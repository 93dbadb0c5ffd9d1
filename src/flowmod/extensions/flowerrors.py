"""Controlled flow errors (issue 52): degrade the exact flow one kind of error at a time.

Where the errors act: on the stored flow crops, not on the full frame. A crop is the exact
flow of the paper's window (``scale`` x the box's longer side, square, about the box centre)
resized bilinearly to ``S x S`` (:mod:`flowmod.crops`), stored as (N, 2, S, S) float16 px
(channel 0 = u, 1 = v). Degrading full frames and cropping them again would cost the exact
flow of every pair once more per degraded variant (~0.26 s a pair: ~700 pairs x 18 variants
is ~55 min on the demo), and the classifier never sees anything outside its crop. What a
faithful degradation needs of the frame is per-object geometry, all of which the crop rows
hold: the crop window ``x0, y0, n`` (frame px, :func:`flowmod.crops.crop_windows`), so that
lost resolution averages cells of the frame's pixel grid however much the crop magnifies a
far vehicle; the box inside the crop (:func:`box_masks`, chapter 07's convention), so that
the pull acts on the vehicle and the ring error only around it; and the still-world flow of
the window (chapter 10's ``<split>.static.npy``, :func:`flowmod.crops.static_crops`), the
flow the vehicle would have standing still. What this gives up, and says so: white noise is
drawn per crop pixel (per frame pixel it would be smoothed by the crop's resize of a far
vehicle and sharpened for a near one), and a cell of lost resolution that the window cuts is
averaged over the part inside the window only.

Arrays: ``flow`` (N, 2, S, S) float px (any float dtype; results are float32); ``box`` (N, S,
S) bool, the crop pixels inside the 2D box; ``still`` (N, 2, S, S) px; ``windows`` (N, 3)
int frame px. Each random error draws from an explicit ``numpy.random.Generator`` or an int
seed (``numpy.random.default_rng`` of it), so a seed gives the same degradation.

Levels (:data:`KINDS`, each kind's one parameter and its search range): ``noise`` sigma px
(per component), ``resolution`` k frame px (cell side), ``pull`` alpha in [0, 1], ``scale``
s (flow x (1 + s)), ``outliers`` p (share of pixels; each gets a vector of fixed length
added), ``ring`` sigma px outside the box. :func:`endpoint_errors` measures the realised
error in the box and in the ring the way chapter 07 does (each object's mean end-point error
over its pixels, then the mean and median over objects); :func:`match_level` finds the level
of a kind that reaches a requested error (the ring's in the ring, which leaves the box exact;
every other kind's in the box), so kinds can be compared at the same box end-point error.
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from flowmod import dag
from flowmod.artefacts import write_json
from flowmod.crops import (
    BOX_COLUMNS,
    SplitReader,
    crop_windows,
    crops_reader,
    gather_fold,
    read_crops,
)
from flowmod.evaluate import predict_splits, read_frame, scored_rows, write_frames
from flowmod.extensions.context import read_context
from flowmod.geometry import window_lattice
from flowmod.params import Params
from flowmod.train import MODEL_OUTPUTS, part_index, seed_parts, train_seed

Seed = np.random.Generator | int

#: Length (px) of each sparse outlier's error vector.
OUTLIER_PX = 16.0


def _crops(flow: Any) -> np.ndarray:
    """(N, 2, S, S) float32 copy of ``flow``; ValueError on another shape."""
    f = np.array(flow, dtype=np.float32)
    if f.ndim != 4 or f.shape[1] != 2 or f.shape[2] != f.shape[3]:
        raise ValueError(f"flow crops must be (N, 2, S, S), got {f.shape}")
    return f


def _mask(mask: Any, shape: tuple[int, ...]) -> np.ndarray:
    """(N, 1, S, S) bool of ``mask`` (N, S, S) (all True for None) for crops of ``shape``."""
    if mask is None:
        return np.ones((shape[0], 1, *shape[2:]), bool)
    m = np.asarray(mask, bool)
    if m.shape != (shape[0], *shape[2:]):
        raise ValueError(f"mask {m.shape} does not fit crops {shape}")
    return m[:, None]


# --- the box inside its crop ------------------------------------------------------------------


def box_masks(boxes: np.ndarray, size: int, scale: float) -> np.ndarray:
    """(N, S, S) bool: the pixels of each crop (``scale`` x the box's longer side about its
    centre, resized to S = ``size``) that the 2D box covers, partly or wholly.

    boxes: (N, 4) xmin, ymin, xmax, ymax frame px. Chapter 07's crop errors use the same
    masks (:func:`flowmod.chapters.ch07_evaluation.box_masks`), so errors measured here
    are comparable with its box and around-the-box medians."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    win = crop_windows(b, scale).astype(np.float64)
    lo = (b[:, :2] - win[:, :2]) / win[:, 2:3] * size
    hi = (b[:, 2:] + 1 - win[:, :2]) / win[:, 2:3] * size
    a = np.clip(np.floor(lo), 0, size).astype(int)
    z = np.clip(np.ceil(hi), 0, size).astype(int)
    mask = np.zeros((len(b), size, size), bool)
    for i, (c0, r0, c1, r1) in enumerate(np.hstack([a, z])):
        mask[i, r0:r1, c0:c1] = True
    return mask


@dataclass(frozen=True)
class CropBatch:
    """Clean crops and what the degradations need of their objects.

    flow: (N, 2, S, S) float32 px, the exact flow; box: (N, S, S) bool (:func:`box_masks`);
    still: (N, 2, S, S) float32 px, the still-world flow of each window (None: no ``pull``);
    windows: (N, 3) int ``x0, y0, n`` frame px (None: ``resolution`` counts crop px)."""

    flow: np.ndarray
    box: np.ndarray
    still: np.ndarray | None = None
    windows: np.ndarray | None = None


def crop_batch(flow: Any, boxes: np.ndarray, scale: float, still: Any = None) -> CropBatch:
    """A :class:`CropBatch` of stored crops (N, 2, S, S) px and their rows' boxes (N, 4)
    frame px (``xmin, ymin, xmax, ymax``), the crop ``scale`` they were cut with and, for the
    pull, their still-world flow crops (N, 2, S, S) px."""
    f = _crops(flow)
    return CropBatch(f, box_masks(boxes, f.shape[-1], scale),
                     None if still is None else _crops(still), crop_windows(boxes, scale))


# --- the kinds of error -----------------------------------------------------------------------


def white_noise(flow: Any, sigma: float, rng: Seed, mask: Any = None) -> np.ndarray:
    """flow (N, 2, S, S) px plus independent Gaussian noise of ``sigma`` px on each component
    of each crop pixel where ``mask`` (N, S, S) bool is True (None: everywhere). The
    end-point error of a noisy pixel is Rayleigh: mean ``sigma * sqrt(pi / 2)``, median
    ``sigma * sqrt(2 ln 2)``. The draw does not depend on ``mask`` or ``sigma``."""
    if sigma < 0:
        raise ValueError(f"sigma must be >= 0 px, got {sigma}")
    f = _crops(flow)
    z = np.random.default_rng(rng).standard_normal(f.shape, dtype=np.float32)
    return f + np.float32(sigma) * z * _mask(mask, f.shape)


def ring_noise(flow: Any, sigma: float, box: Any, rng: Seed) -> np.ndarray:
    """White noise of ``sigma`` px (:func:`white_noise`) in the ring only: the crop pixels
    outside the box ``box`` (N, S, S) bool; the box's flow is returned unchanged."""
    return white_noise(flow, sigma, rng, ~np.asarray(box, bool))


def pull_to_still(flow: Any, still: Any, alpha: float, mask: Any = None) -> np.ndarray:
    """``flow + alpha * (still - flow)`` where ``mask`` (N, S, S) is True (the vehicle's box;
    None: the whole crop), flow and still (N, 2, S, S) px: the vehicle's own motion shrunk
    by the share ``alpha`` in [0, 1] (1 erases it: the still-world flow). A still vehicle,
    whose flow is the still-world flow, is unchanged."""
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must lie in [0, 1], got {alpha}")
    f, s = _crops(flow), _crops(still)
    if s.shape != f.shape:
        raise ValueError(f"still-world flow {s.shape} does not fit flow {f.shape}")
    pulled = f + np.float32(alpha) * (s - f)
    return np.where(_mask(mask, f.shape), pulled, f)


def scale_error(flow: Any, s: float) -> np.ndarray:
    """``flow * (1 + s)``: a global scale error (s > -1; s = 0.1 makes every vector 10 %
    longer). End-point error ``|s| * |flow|``."""
    if s <= -1:
        raise ValueError(f"scale error s must be > -1, got {s}")
    return _crops(flow) * np.float32(1.0 + s)


def outliers(flow: Any, p: float, rng: Seed, magnitude: float = OUTLIER_PX,
             mask: Any = None) -> np.ndarray:
    """Sparse large errors: each crop pixel (where ``mask`` is True) gets, with probability
    ``p``, a vector of ``magnitude`` px in a uniform direction added (its end-point error is
    ``magnitude``; mean error ``p * magnitude``). One uniform draw per pixel decides, so a
    larger ``p`` keeps the outliers of a smaller one (same seed)."""
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"outlier share p must lie in [0, 1], got {p}")
    f = _crops(flow)
    g = np.random.default_rng(rng)
    n, _, s, _ = f.shape
    u = g.random((n, s, s))
    angle = g.uniform(0.0, 2.0 * np.pi, (n, s, s))
    hit = (u < p) & _mask(mask, f.shape)[:, 0]
    vec = np.stack([np.cos(angle), np.sin(angle)], axis=1) * magnitude
    return f + np.where(hit[:, None], vec, 0.0).astype(np.float32)


def _cells_1d(x: np.ndarray, k: float, upsample: str) -> tuple[np.ndarray, ...]:
    """For coordinates x (S,) frame px and cells of k px (cell c holds the pixels whose
    span lies in ``[c k - 0.5, (c + 1) k - 0.5)``): each x's cell (from 0), the two cells
    the upsampling reads and their weights."""
    cell = np.floor((x + 0.5) / k).astype(int)
    first = cell.min()
    if upsample == "nearest":
        c = cell - first
        return c, c, c, np.ones_like(x), np.zeros_like(x)
    u = (x + 0.5) / k - 0.5 - first  # in cell units, cell centres at integers
    i0 = np.floor(u).astype(int)
    w1 = u - i0
    return cell - first, i0, i0 + 1, 1.0 - w1, w1


def _lost_resolution_one(f: np.ndarray, window: np.ndarray, k: float, upsample: str
                         ) -> np.ndarray:
    """One crop (2, S, S): average over k-px cells of the frame, then upsample."""
    size = f.shape[-1]
    xy = window_lattice(window, size).reshape(size, size, 2)  # where the crop's resize reads
    cx, ax, bx, wax, wbx = _cells_1d(xy[0, :, 0], k, upsample)
    cy, ay, by, way, wby = _cells_1d(xy[:, 0, 1], k, upsample)
    m = int(max(cx.max(), cy.max(), ax.max(), ay.max())) + 2
    idx = (cy[:, None] * m + cx[None, :]).ravel()
    count = np.bincount(idx, minlength=m * m).reshape(m, m)
    sums = np.stack([np.bincount(idx, f[c].ravel(), m * m).reshape(m, m) for c in range(2)])
    mean = sums / np.maximum(count, 1)
    num = np.zeros(f.shape, np.float64)
    den = np.zeros((size, size), np.float64)
    for ry, wy in ((ay, way), (by, wby)):
        for rx, wx in ((ax, wax), (bx, wbx)):
            ry_, rx_ = np.clip(ry, 0, m - 1), np.clip(rx, 0, m - 1)
            w = wy[:, None] * wx[None, :] * (count[np.ix_(ry_, rx_)] > 0)
            num += w * mean[:, ry_][:, :, rx_]
            den += w
    return (num / den).astype(np.float32)


def lost_resolution(flow: Any, k: float, windows: Any = None, upsample: str = "bilinear"
                    ) -> np.ndarray:
    """The flow averaged over k x k px cells of the frame's pixel grid, then upsampled back,
    as a network that predicts at 1/k resolution does: ``bilinear`` (default; cell means at
    the cells' centres, PyTorch's ``align_corners=False`` upsampling, which FastFlowNet
    uses) or ``nearest`` (each pixel its cell's mean).

    flow (N, 2, S, S) px; k >= 1 frame px (not necessarily whole); windows (N, 3) ``x0, y0,
    n`` frame px of each crop (:func:`flowmod.crops.crop_windows`), None: the crop's own
    pixels are the grid. A cell's mean is that of the crop pixels in it (cells cut by the
    window: the part inside); a cell without a crop pixel (a crop smaller than its window)
    leaves the upsampling's weights to its neighbours. A constant field is unchanged."""
    if not k >= 1:
        raise ValueError(f"cell side k must be >= 1 px, got {k}")
    if upsample not in ("bilinear", "nearest"):
        raise ValueError(f"upsample must be 'bilinear' or 'nearest', got {upsample!r}")
    f = _crops(flow)
    n, _, size, _ = f.shape
    win = (np.tile([0, 0, size], (n, 1)) if windows is None
           else np.asarray(windows, np.float64).reshape(-1, 3))
    if len(win) != n:
        raise ValueError(f"{len(win)} windows for {n} crops")
    out = np.empty_like(f)
    for i in range(n):
        out[i] = _lost_resolution_one(f[i], win[i], float(k), upsample)
    return out


# --- one interface over the kinds, the realised errors, matched levels -------------------------


@dataclass(frozen=True)
class Kind:
    """One kind of error: its level's name and unit, the range :func:`match_level`
    searches, where its error is measured (``box`` or ``ring``) and how it degrades a
    batch: ``apply(batch, level, seed)`` -> (N, 2, S, S) float32 px."""

    level: str
    lo: float
    hi: float
    region: str
    apply: Callable[[CropBatch, float, Seed], np.ndarray]


def _pull(b: CropBatch, alpha: float, seed: Seed) -> np.ndarray:
    if b.still is None:
        raise ValueError("the pull needs the batch's still-world flow (CropBatch.still)")
    return pull_to_still(b.flow, b.still, alpha, b.box)


#: The kinds of issue 52, by name.
KINDS: dict[str, Kind] = {
    "noise": Kind("sigma (px)", 0.0, 20.0, "box",
                  lambda b, v, r: white_noise(b.flow, v, r)),
    "resolution": Kind("k (frame px)", 1.0, 64.0, "box",
                       lambda b, v, r: lost_resolution(b.flow, v, b.windows)),
    "pull": Kind("alpha", 0.0, 1.0, "box", _pull),
    "scale": Kind("s", 0.0, 1.0, "box", lambda b, v, r: scale_error(b.flow, v)),
    "outliers": Kind("p", 0.0, 1.0, "box", lambda b, v, r: outliers(b.flow, v, r)),
    "ring": Kind("sigma (px)", 0.0, 20.0, "ring",
                 lambda b, v, r: ring_noise(b.flow, v, b.box, r)),
}


def degrade(kind: str, batch: CropBatch, level: float, seed: Seed = 0) -> np.ndarray:
    """The batch's flow with one ``kind`` of error (:data:`KINDS`) at ``level``: (N, 2, S,
    S) float32 px."""
    if kind not in KINDS:
        raise ValueError(f"unknown kind of flow error {kind!r}; known: {list(KINDS)}")
    return KINDS[kind].apply(batch, level, seed)


def endpoint_errors(degraded: Any, clean: Any, box: Any) -> dict[str, Any]:
    """Realised end-point error of ``degraded`` against ``clean`` (N, 2, S, S) px, as
    chapter 07 measures it: each object's mean over its box pixels and over its ring (the
    crop outside the box; NaN where either is empty), then over objects.

    Returns ``box`` and ``ring`` (N,) float64 px per object, and ``box_mean``,
    ``box_median``, ``ring_mean``, ``ring_median`` floats px over the objects."""
    d, c = _crops(degraded), _crops(clean)
    if d.shape != c.shape:
        raise ValueError(f"degraded {d.shape} and clean {c.shape} crops differ in shape")
    inside = _mask(box, d.shape)[:, 0]
    err = np.sqrt(((d.astype(np.float64) - c) ** 2).sum(axis=1))
    out: dict[str, Any] = {}
    for name, m in (("box", inside), ("ring", ~inside)):
        k = m.sum((1, 2))
        per = np.where(k > 0, (err * m).sum((1, 2)) / np.maximum(k, 1), np.nan)
        out[name] = per
        defined = per[~np.isnan(per)]
        out[f"{name}_mean"] = float(defined.mean()) if defined.size else float("nan")
        out[f"{name}_median"] = float(np.median(defined)) if defined.size else float("nan")
    return out


def realised_error(kind: str, batch: CropBatch, level: float, seed: Seed = 0,
                   stat: str = "mean") -> float:
    """The error (px) ``kind`` at ``level`` realises where it is measured (its region's
    ``stat``: ``mean`` or ``median`` over objects, :func:`endpoint_errors`)."""
    if stat not in ("mean", "median"):
        raise ValueError(f"stat must be 'mean' or 'median', got {stat!r}")
    e = endpoint_errors(degrade(kind, batch, level, seed), batch.flow, batch.box)
    return float(e[f"{KINDS[kind].region}_{stat}"])


def match_level(kind: str, batch: CropBatch, target: float, seed: Seed = 0,
                stat: str = "mean", tol: float = 0.01, steps: int = 16) -> float:
    """The level of ``kind`` whose realised error (:func:`realised_error`, the box's; the
    ring's for ``ring``) on the calibration ``batch`` is ``target`` px within ``tol``
    (relative): the range of :data:`KINDS` is scanned in ``steps`` for the first level that
    reaches the target, then bisected (so mildly non-monotone kinds, lost resolution, are
    handled). The noise is the same draw at every level (a Generator is turned into one
    seed first). ValueError when the range cannot reach the target."""
    k = KINDS[kind] if kind in KINDS else None
    if k is None:
        raise ValueError(f"unknown kind of flow error {kind!r}; known: {list(KINDS)}")
    if not target > 0:
        raise ValueError(f"target error must be > 0 px, got {target}")
    s = seed if isinstance(seed, int) else int(np.random.default_rng(seed).integers(2**62))

    def err(v: float) -> float:
        return realised_error(kind, batch, v, s, stat)

    grid = np.linspace(k.lo, k.hi, steps + 1)
    errs = [err(float(v)) for v in grid]
    above = [i for i, e in enumerate(errs) if e >= target]
    if not above or above[0] == 0:
        reach = f"{min(errs):.3g} to {max(errs):.3g} px"
        raise ValueError(f"{kind}: a {stat} {k.region} error of {target:.3g} px is out of "
                         f"reach over {k.level} in [{k.lo}, {k.hi}] ({reach})")
    lo, hi = float(grid[above[0] - 1]), float(grid[above[0]])
    for _ in range(60):
        mid = (lo + hi) / 2
        e = err(mid)
        if abs(e - target) <= tol * target:
            return mid
        lo, hi = (mid, hi) if e < target else (lo, mid)
    return (lo + hi) / 2


def match_levels(batch: CropBatch, targets: Any, kinds: Any = None, seed: Seed = 0,
                 stat: str = "mean", tol: float = 0.01) -> dict[str, list[float]]:
    """``{kind: [level per target]}``: :func:`match_level` of each kind (all of
    :data:`KINDS` by default) at each target error (px) on the same calibration batch, so
    the kinds meet at the same box (ring: ring) end-point errors; a target out of a kind's
    reach gives NaN."""
    out: dict[str, list[float]] = {}
    for kind in (list(KINDS) if kinds is None else kinds):
        levels = []
        for t in targets:
            try:
                levels.append(match_level(kind, batch, float(t), seed, stat, tol))
            except ValueError:
                levels.append(float("nan"))
        out[kind] = levels
    return out


# --- the stages (chapter 13) --------------------------------------------------------------------

#: The undegraded arm: the exact flow, trained and scored like every degraded arm.
EXACT = "exact"


def arms(p: Params) -> list[tuple[str, int]]:
    """(kind, target index) of every arm of chapter 13: the exact flow (``(EXACT, 0)``), then
    each kind of ``p.error_kinds`` at each of ``p.error_targets``; none when no kind is set
    or the exact flow (``gt``, a generated world's) is not among the flow methods."""
    if not p.error_kinds or "gt" not in p.flow_methods:
        return []
    return [(EXACT, 0)] + [(k, t) for k in p.error_kinds for t in range(len(p.error_targets))]


def arm_key(kind: str, target: int) -> str:
    """``exact`` or ``<kind>/<target index>``: an arm's part of its nodes' names."""
    return EXACT if kind == EXACT else f"{kind}/{target}"


def parse_arm(key: str) -> tuple[str, int]:
    """(kind, target index) of an arm key (:func:`arm_key`)."""
    kind, _, t = key.partition("/")
    return kind, int(t or 0)


def error_parts(p: Params | dag.StageParams) -> list[str]:
    """The training parts of an arm: one seed a fold, the first ``error_folds`` folds
    (``s0`` with the paper's single split)."""
    return seed_parts(p, 1)[: p.error_folds]


def _split_rng(seed: int, kind: str, target: int, split: str) -> np.random.Generator:
    """The generator of one split's degradation: the same objects get the same error
    whichever node (training or scoring) reads them."""
    return np.random.default_rng([seed, zlib.crc32(f"{kind}/{target}/{split}".encode())])


def _same_objects(crops: pd.DataFrame, context: pd.DataFrame, what: str) -> None:
    """Refuse context crops (their index) that hold other objects than the exact-flow
    crops, in another order included."""
    if not crops["ann_token"].reset_index(drop=True).equals(
            context["ann_token"].reset_index(drop=True)):
        raise ValueError(f"{what}: the exact-flow crops and chapter 10's context crops hold "
                         "other objects; rebuild the context stage")


def _batch(crops_dir: Any, ctx_dir: Any, split: str, scale: float) -> tuple[CropBatch, pd.DataFrame]:
    """The exact-flow crops of one stored split with their boxes and still-world flow."""
    x, df = read_crops(crops_dir, split)
    still, _, cdf = read_context(ctx_dir, split, "boxes") if ctx_dir is not None else (None, None, df)
    _same_objects(df, cdf, f"{split} split")
    return crop_batch(x, df[list(BOX_COLUMNS)].to_numpy(np.float64), scale, still), df


def degraded_reader(q: Any, crops_dir: Any, ctx_dir: Any, kind: str, target: int,
                    level: float) -> SplitReader:
    """A :data:`flowmod.crops.SplitReader` of the exact-flow crops with ``kind`` at ``level``
    (the exact arm: unchanged), each split drawn from its own generator (:func:`_split_rng`)."""
    def read(split: str) -> tuple[list[Any], pd.DataFrame]:
        batch, df = _batch(crops_dir, ctx_dir if kind == "pull" else None, split, q.crop_scale)
        if kind == EXACT:
            return [batch.flow], df
        return [degrade(kind, batch, level, _split_rng(q.seed, kind, target, split))], df
    return read


#: An ``elevels`` node's one file: a kind's levels at the targets.
LEVELS_FILE = "levels.json"


def read_levels(folder: Path) -> dict[str, Any]:
    """A published ``elevels`` node's record: kind, unit, targets, the matched levels,
    whether each was reached, the errors they realised, the objects matched on."""
    return json.loads((Path(folder) / LEVELS_FILE).read_text())


def read_arm(folder: Path) -> pd.DataFrame:
    """A published ``eevaluate`` node's test predictions (``prob``) with each object's
    realised end-point error in its box and ring (``epe_box``, ``epe_ring``, px)."""
    df, err = read_frame(folder, "test"), read_frame(folder, "errors")
    if not df["ann_token"].equals(err["ann_token"]):
        raise ValueError(f"{folder}: predictions and realised errors hold other objects")
    return df.assign(epe_box=err["epe_box"].to_numpy(), epe_ring=err["epe_ring"].to_numpy())


def _level(b: dag.Build, kind: str, target: int) -> float:
    """The level of ``kind`` at target ``target`` that the ``elevels`` node matched."""
    if kind == EXACT:
        return 0.0
    return float(read_levels(b.input_dir(dag.Node("elevels", "gt", kind)))["levels"][target])


def _still_rows(ctx: Path, split: str) -> tuple[list[np.ndarray], pd.DataFrame]:
    """A :data:`flowmod.crops.SplitReader` of the context node's still-world flow in the
    boxes: ``([static], index)``."""
    still, _, cdf = read_context(ctx, split, "boxes")
    return [still], cdf


def build_elevels(b: dag.Build, progress: bool) -> dict[str, Any]:
    """Build one ``elevels[gt/<kind>]`` node: the kind's level at each target error
    (``levels.json``), matched on ``error_calibration`` objects drawn with the seed from
    every scored row; a target out of the kind's reach takes its largest level
    (``reached`` False)."""
    q, kind = b.params, str(b.node.part)
    crops_dir = b.input_dir(dag.Node("crops", "gt", "keyframe"))
    ctx = b.input_dir(dag.Node("context", None, "keyframe")) if kind == "pull" else None
    [x], df = scored_rows(crops_reader(crops_dir), q.folds)
    still = None
    if ctx is not None:
        [still], cdf = scored_rows(lambda s: _still_rows(ctx, s), q.folds)
        _same_objects(df, cdf, "the scored rows")
    pick = np.sort(np.random.default_rng(q.seed).choice(
        len(df), min(q.error_calibration, len(df)), replace=False))
    batch = crop_batch(np.asarray(x)[pick], df[list(BOX_COLUMNS)].to_numpy(np.float64)[pick],
                       q.crop_scale, None if still is None else np.asarray(still)[pick])
    found = match_levels(batch, q.error_targets, [kind], seed=q.seed)[kind]
    levels = [float(v) if np.isfinite(v) else KINDS[kind].hi for v in found]
    write_json(b.start(fresh=True) / LEVELS_FILE,
               {"kind": kind, "unit": KINDS[kind].level, "targets": list(q.error_targets),
                "levels": levels, "reached": [bool(np.isfinite(v)) for v in found],
                "realised": [realised_error(kind, batch, v, q.seed) for v in levels],
                "objects": len(pick)})
    return {"objects": len(pick), "levels": levels}


def build_etrain(b: dag.Build, progress: bool) -> dict[str, Any]:
    """Build one ``etrain[gt/<arm>/<part>]`` node: the classifier (Table 2, epoch chosen on
    validation) trained on the exact flow degraded by the arm's kind at its level."""
    q = b.params
    key, _, part = str(b.node.part).rpartition("/")
    kind, target = parse_arm(key)
    level = _level(b, kind, target)
    ctx = b.input_dir(dag.Node("context", None, "keyframe")) if kind == "pull" else None
    read = degraded_reader(q, b.input_dir(dag.Node("crops", "gt", "keyframe")), ctx, kind,
                           target, level)
    fold = part_index(part)
    train, val = (gather_fold(read, q.folds, fold, role) for role in ("train", "val"))
    info = train_seed(b, (train[0][0], train[1]), (val[0][0], val[1]), progress,
                      f"exact flow, {key}", width=q.error_width)
    return {**info, "kind": kind, "level": level}


def build_eevaluate(b: dag.Build, progress: bool) -> dict[str, Any]:
    """Build one ``eevaluate[gt/<arm>]`` node: the arm's models on their folds' test rows
    (``test.parquet``: ``prob`` by each row's fold) and the realised end-point error of
    each scored object in its box and ring (``errors.parquet``: ``epe_box``, ``epe_ring``,
    px) against the exact flow."""
    q = b.params
    kind, target = parse_arm(str(b.node.part))
    level = _level(b, kind, target)
    crops_dir = b.input_dir(dag.Node("crops", "gt", "keyframe"))
    ctx = b.input_dir(dag.Node("context", None, "keyframe")) if kind == "pull" else None
    read = degraded_reader(q, crops_dir, ctx, kind, target, level)
    clean = degraded_reader(q, crops_dir, None, EXACT, 0, 0.0)
    folds = range(len(error_parts(q)))
    got = [gather_fold(read, q.folds, k, "test") for k in folds]
    x = np.concatenate([np.asarray(a[0]) for a, _ in got])
    df = pd.concat([d for _, d in got], ignore_index=True)
    x0 = np.concatenate([np.asarray(gather_fold(clean, q.folds, k, "test")[0][0]) for k in folds])
    box = box_masks(df[list(BOX_COLUMNS)].to_numpy(np.float64), x.shape[-1], q.crop_scale)
    e = endpoint_errors(x, x0, box)
    predict_splits(b, "etrain", f"gt/{b.node.part}", {"test": (x, df)})
    errors = df[["ann_token", "fold"]].assign(epe_box=e["box"], epe_ring=e["ring"])
    write_frames(b.dir, {"errors": errors}, {"arm": {"kind": kind, "target": target,
                                                     "level": level}})
    return {"n": len(df), "kind": kind, "level": level}


def _needs(kind: str) -> tuple[dag.Node, ...]:
    """What an arm's nodes read: the exact-flow crops, the still-world flow (the pull) and
    the kind's levels (not the exact arm)."""
    return (dag.Node("crops", "gt", "keyframe"),
            *((dag.Node("context", None, "keyframe"),) if kind == "pull" else ()),
            *((dag.Node("elevels", "gt", kind),) if kind != EXACT else ()))


#: Chapter 13: each kind's level at each target error, matched on the exact flow's crops.
ELEVELS = dag.Stage(
    "elevels", 1, "13", "flowerrors/levels/{part}", "a kind of error's level at each target",
    nodes=lambda p: [dag.Node("elevels", "gt", k) for k in p.error_kinds if arms(p)],
    inputs=lambda n, p: _needs(str(n.part))[:-1],
    build=build_elevels, outputs=(LEVELS_FILE,))
#: Chapter 13: one classifier per arm and fold, trained on the degraded exact flow.
ETRAIN = dag.Stage(
    "etrain", 1, "13", "flowerrors/models/{key}", "a classifier on degraded exact flow",
    nodes=lambda p: [dag.Node("etrain", "gt", f"{arm_key(*a)}/{k}") for a in arms(p)
                     for k in error_parts(p)],
    inputs=lambda n, p: _needs(parse_arm(str(n.part).rpartition("/")[0])[0]),
    build=build_etrain, outputs=MODEL_OUTPUTS, parallel=True)
#: Chapter 13: an arm's models on their test rows, with the realised errors.
EEVALUATE = dag.Stage(
    "eevaluate", 1, "13", "flowerrors/metrics/{key}", "its predictions and realised errors",
    nodes=lambda p: [dag.Node("eevaluate", "gt", arm_key(*a)) for a in arms(p)],
    inputs=lambda n, p: (*(dag.Node("etrain", "gt", f"{n.part}/{k}") for k in error_parts(p)),
                         *_needs(parse_arm(str(n.part))[0])),
    build=build_eevaluate, outputs=("test.parquet", "errors.parquet", "arm.json"))
