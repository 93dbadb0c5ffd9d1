"""Binary scores over a whole set: precision, recall, F1, intervals, threshold fitting, and the
original code's per-batch protocol (kept only to show its effect).

Labels: 1 = moving, 0 = still; ``prob > threshold`` (0.5) predicts moving, as in the paper.
The clean protocol computes precision, recall and F1 once over all objects of a split. The
original code averaged F1 per batch of 128 and evaluated on a validation set that kept 1 of
every 2 still objects.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from statistics import NormalDist
from typing import Any

import numpy as np
import pandas as pd

#: Distance bins (m) of the breakdown tables (Table 1 range 30-70 m, plus the near field).
DISTANCE_BINS = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, np.inf)


def sigmoid(z: Any) -> np.ndarray:
    """Logistic function of logits, without overflow warnings for large |z|."""
    from scipy.special import expit

    return expit(np.asarray(z, dtype=np.float64))



# --- metrics ---------------------------------------------------------------------------------


def labels01(y_true: Any) -> np.ndarray:
    """Labels (N,) int64 0 (still) / 1 (moving); any other value (0.5, 2, -1: unknown) is a
    ValueError, checked before the cast so that 0.9 is not silently read as 0."""
    y = np.asarray(y_true).reshape(-1)
    if not np.isin(y, (0, 1)).all():
        raise ValueError("y_true must hold 0 (still) / 1 (moving) only")
    return y.astype(np.int64)


def _binary(y_true: Any, y_prob: Any, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    y = labels01(y_true)
    p = np.asarray(y_prob, dtype=np.float64).reshape(-1)
    if y.shape != p.shape:
        raise ValueError(f"y_true has {y.size} values but y_prob has {p.size}")
    return y, (p > threshold).astype(np.int64)


def _prf(tp: Any, fp: Any, fn: Any, undefined: float = np.nan) -> tuple[Any, Any, Any]:
    """Precision, recall, F1 of the moving class from counts (arrays ok). Where undefined
    they are ``undefined`` (NaN; the original's sklearn code used 0): precision without a
    predicted mover, recall and F1 without a true mover (F1 = 2PR / (P + R) needs R)."""
    tp, fp, fn = (np.asarray(v, dtype=np.float64) for v in (tp, fp, fn))
    with np.errstate(divide="ignore", invalid="ignore"):
        prec = np.where(tp + fp > 0, tp / (tp + fp), undefined)
        rec = np.where(tp + fn > 0, tp / (tp + fn), undefined)
        f1 = np.where(tp + fn > 0, 2 * tp / (2 * tp + fp + fn), undefined)
    return prec, rec, f1


def metrics(y_true: Any, y_prob: Any, threshold: float = 0.5) -> dict[str, Any]:
    """One precision / recall / F1 / accuracy over the whole set.

    y_true: (N,) 0/1; y_prob: (N,) probabilities (or 0/1 predictions). Returns a dict with
    precision, recall, f1, accuracy (fractions), tp, fp, tn, fn, n, n_moving, n_still,
    confusion ([[tn, fp], [fn, tp]], sklearn's layout) and threshold. Undefined ratios are NaN
    (recall and F1 without a mover, precision without a predicted mover, accuracy of none).
    """
    y, yhat = _binary(y_true, y_prob, threshold)
    tp = int(((yhat == 1) & (y == 1)).sum())
    fp = int(((yhat == 1) & (y == 0)).sum())
    fn = int(((yhat == 0) & (y == 1)).sum())
    tn = int(((yhat == 0) & (y == 0)).sum())
    prec, rec, f1 = (float(v) for v in _prf(tp, fp, fn))
    n = len(y)
    return {
        "precision": prec, "recall": rec, "f1": f1,
        "accuracy": (tp + tn) / n if n else float("nan"),
        "tp": tp, "fp": fp, "tn": tn, "fn": fn,
        "n": n, "n_moving": int(y.sum()), "n_still": int(n - y.sum()),
        "confusion": [[tn, fp], [fn, tp]], "threshold": float(threshold),
    }


def false_alarm_rate(y_true: Any, y_prob: Any, threshold: float = 0.5) -> float:
    """Share of the still objects called moving (``prob > threshold``, the convention of
    :func:`metrics`): fp / (fp + tn); NaN without a still object."""
    m = metrics(y_true, y_prob, threshold)
    return m["fp"] / m["n_still"] if m["n_still"] else float("nan")


def threshold_sweep(y_true: Any, y_prob: Any, thresholds: Sequence[float] | None = None) -> pd.DataFrame:
    """Metrics at each threshold (default 0.05 .. 0.95): threshold, precision, recall, f1,
    accuracy."""
    ts = np.round(np.arange(0.05, 0.951, 0.05), 2) if thresholds is None else thresholds
    rows = []
    for t in ts:
        m = metrics(y_true, y_prob, float(t))
        rows.append({k: m[k] for k in ("threshold", "precision", "recall", "f1", "accuracy")})
    return pd.DataFrame(rows)


def pr_curve(y_true: Any, y_prob: Any) -> tuple[pd.DataFrame, float]:
    """Precision-recall curve and average precision.

    Returns (DataFrame with threshold, precision, recall for every distinct score, from the
    highest threshold down, AP). Predicted moving when ``prob >= threshold`` here (curve
    convention).
    """
    from sklearn.metrics import average_precision_score, precision_recall_curve

    y = labels01(y_true)
    p = np.asarray(y_prob, dtype=np.float64)
    prec, rec, thr = precision_recall_curve(y, p)
    df = pd.DataFrame({"threshold": thr, "precision": prec[:-1], "recall": rec[:-1]})
    return df.iloc[::-1].reset_index(drop=True), float(average_precision_score(y, p))


def _counts(y: np.ndarray, probs: np.ndarray, groups: np.ndarray, threshold: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """tp, fp, fn per (model, group): each (S, G) for probs (S, N)."""
    _, gi = np.unique(groups, return_inverse=True)
    n_groups = int(gi.max()) + 1 if len(gi) else 0
    out = []
    for cond in ((1, 1), (1, 0), (0, 1)):  # (predicted, true): tp, fp, fn
        rows = []
        for p in probs:
            yhat = (p > threshold).astype(np.int64)
            hit = ((yhat == cond[0]) & (y == cond[1])).astype(np.float64)
            rows.append(np.bincount(gi, weights=hit, minlength=n_groups))
        out.append(np.asarray(rows))
    return out[0], out[1], out[2]


def _as_models(y_true: Any, y_prob: Any) -> tuple[np.ndarray, np.ndarray]:
    """(y (N,), probs (S, N)): one row per model (a training seed)."""
    y = labels01(y_true)
    probs = np.asarray(y_prob, dtype=np.float64)
    probs = probs[None] if probs.ndim == 1 else probs
    if probs.shape[-1] != len(y):
        raise ValueError(f"y_true has {len(y)} values but y_prob has shape {probs.shape}")
    return y, probs


def scene_draws(k: int, n: int, seed: int) -> np.ndarray:
    """(n, k) float64: how often each of ``k`` scenes is drawn in each of ``n`` bootstrap
    replicates (k draws with replacement, seeded)."""
    rng = np.random.default_rng(seed)
    return rng.multinomial(k, np.full(k, 1.0 / k), size=n).astype(np.float64)


def seed_draws(models: int, strata: int, n: int, seed: int) -> np.ndarray:
    """(n, strata, models) int64: which of ``models`` training seeds each replicate draws
    (``models`` draws with replacement) in each stratum (fold), seeded; the identity when
    there is one model (nothing to resample)."""
    if models == 1:
        return np.zeros((n, strata, 1), dtype=np.int64)
    rng = np.random.default_rng([int(seed), 1])
    return rng.integers(0, models, size=(n, strata, models))


def _scene_strata(g: np.ndarray, folds: Any) -> np.ndarray:
    """(G,) the fold of each scene (0 everywhere without folds); a scene lies in one fold."""
    uniq, gi = np.unique(g, return_inverse=True)
    if folds is None:
        return np.zeros(len(uniq), dtype=np.int64)
    f = np.asarray(folds).reshape(-1)
    if len(f) != len(g):
        raise ValueError(f"folds has {len(f)} values but groups has {len(g)}")
    _, fi = np.unique(f, return_inverse=True)
    out = np.zeros(len(uniq), dtype=np.int64)
    out[gi] = fi
    return out


def scene_bootstrap(y_true: Any, y_prob: Any, groups: Any, n: int = 2000, seed: int = 0,
                    threshold: float = 0.5, folds: Any = None) -> np.ndarray:
    """Bootstrap replicates of the whole-set F1, whole *groups* (scenes) and training seeds
    resampled (a two-level bootstrap).

    Objects of one scene are not independent (one vehicle appears in many consecutive
    pairs; a scene shares its light, traffic and ego motion), so the unit resampled is the
    scene: each replicate draws as many scenes as there are, with replacement, and keeps all
    their objects. y_prob: (N,) or (S, N) for S models (training seeds) scored on the same
    objects. Training is the second source of noise: each replicate also draws S of the S
    seeds with replacement (:func:`seed_draws`), separately in each fold (``folds``: the
    fold of each object; the seed-k models of two folds are separate trainings), and its
    value is the mean over the drawn seeds of their F1 on the drawn scenes; NaN where the
    drawn scenes hold no mover (F1 undefined; not 0). Two calls with the same ``seed`` and
    the same S draw the same scenes and seeds, so their difference is paired on both.
    Returns (n,) replicates.
    """
    y, probs = _as_models(y_true, y_prob)
    g = np.asarray(groups).reshape(-1)
    if len(g) != len(y):
        raise ValueError(f"groups has {len(g)} values but y_true has {len(y)}")
    if len(y) == 0:
        return np.full(n, np.nan)
    tp, fp, fn = _counts(y, probs, g, threshold)  # (S, G) each
    strata = _scene_strata(g, folds)
    w = scene_draws(tp.shape[1], n, seed)  # (n, G)
    pick = seed_draws(len(probs), int(strata.max()) + 1, n, seed)[:, strata, :]  # (n, G, S)
    cols = np.arange(tp.shape[1])[None, :, None]
    tp_r, fp_r, fn_r = (np.einsum("rg,rgs->rs", w, c[pick, cols]) for c in (tp, fp, fn))
    f1 = _prf(tp_r, fp_r, fn_r)[2]  # (n, S): drawn seeds on drawn scenes
    return f1.mean(axis=1)


def group_mean_bootstrap(values: Any, groups: Any, n: int = 2000, seed: int = 0
                         ) -> np.ndarray:
    """Bootstrap replicates of the mean of per-item ``values`` (N,) (a paired difference per
    frame pair, say) with whole ``groups`` (scenes) resampled, as :func:`scene_bootstrap`
    does for F1; NaN values are left out. Returns (n,) replicates, NaN when none is left."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    g = np.asarray(groups).reshape(-1)
    if len(g) != len(v):
        raise ValueError(f"groups has {len(g)} values but values has {len(v)}")
    keep = ~np.isnan(v)
    if not keep.any():
        return np.full(n, np.nan)
    _, idx = np.unique(g[keep], return_inverse=True)
    sums, counts = np.bincount(idx, weights=v[keep]), np.bincount(idx).astype(np.float64)
    w = scene_draws(len(sums), n, seed)
    return (w @ sums) / (w @ counts)


def interval(replicates: Any, level: float = 0.95) -> tuple[float, float]:
    """Percentile interval of bootstrap replicates, over the defined (non-NaN) ones; (NaN,
    NaN) when none is defined."""
    r = np.asarray(replicates, dtype=np.float64).reshape(-1)
    r = r[~np.isnan(r)]
    if r.size == 0:
        return float("nan"), float("nan")
    alpha = (1 - level) / 2
    lo, hi = np.quantile(r, [alpha, 1 - alpha])
    return float(lo), float(hi)


#: Power at which :func:`detectable` sizes the smallest difference the scenes can resolve.
POWER = 0.8


def detectable(replicates: Any, level: float = 0.95, power: float = POWER) -> float:
    """The smallest true difference that a paired comparison over these scenes would find
    (its interval excluding zero) with probability ``power``: ``(z(1 - a/2) + z(power)) *
    SE``, SE the standard deviation of the defined bootstrap replicates of the difference
    (the normal approximation; 2.8 SE at 95 % and 80 %). NaN with fewer than two."""
    r = np.asarray(replicates, dtype=np.float64).reshape(-1)
    r = r[~np.isnan(r)]
    if r.size < 2:
        return float("nan")
    z = NormalDist().inv_cdf
    return float((z(1 - (1 - level) / 2) + z(power)) * r.std(ddof=1))


def verdict(ci: tuple[float, float]) -> str:
    """``A better`` or ``B better`` when the interval of A - B excludes zero, else
    ``undecided`` (also when it is undefined)."""
    lo, hi = ci
    if lo > 0:
        return "A better"
    if hi < 0:
        return "B better"
    return "undecided"


def bootstrap_f1_ci(y_true: Any, y_prob: Any, groups: Any, n: int = 2000, seed: int = 0,
                    threshold: float = 0.5, level: float = 0.95, folds: Any = None
                    ) -> tuple[float, float]:
    """Percentile bootstrap interval of the (seed-mean) F1 over scenes and training seeds;
    see :func:`scene_bootstrap`."""
    return interval(scene_bootstrap(y_true, y_prob, groups, n, seed, threshold, folds), level)


def _per_fold(y: np.ndarray, probs: np.ndarray, folds: np.ndarray, threshold: float
              ) -> list[dict[str, Any]]:
    """Each fold's scores (cross-validation: each fold's rows by its own models): precision,
    recall and F1 the means over the S training seeds (probs (S, N)), tp, fp, fn their sums
    divided by S."""
    out = []
    for k in np.unique(folds):
        ms = [metrics(y[folds == k], p[folds == k], threshold) for p in probs]
        out.append({key: float(np.mean([m[key] for m in ms]))
                    for key in ("f1", "precision", "recall", "tp", "fp", "fn")})
    return out


def seed_sd(values: Any) -> float:
    """Standard deviation (ddof 1) of per-seed scores; NaN with fewer than two defined."""
    v = np.asarray(values, dtype=np.float64)
    v = v[~np.isnan(v)]
    return float(v.std(ddof=1)) if v.size > 1 else float("nan")


def retrain_sd(y: np.ndarray, probs: np.ndarray, folds: np.ndarray | None,
               threshold: float = 0.5) -> float:
    """What one retraining moves an F1 (a fraction): the seeds' standard deviation (ddof 1)
    of the F1 of each fold's objects by that fold's models, pooled over the folds (the root
    of the mean variance; folds without two defined F1 left out); without ``folds``, of the
    F1 on all objects. probs: (S, N); NaN with fewer than two seeds."""
    if folds is None:
        return seed_sd([metrics(y, p, threshold)["f1"] for p in probs])
    var = [seed_sd([metrics(y[folds == k], p[folds == k], threshold)["f1"] for p in probs]) ** 2
           for k in np.unique(folds)]
    var = [v for v in var if not np.isnan(v)]
    return float(np.sqrt(np.mean(var))) if var else float("nan")


#: The two spreads over training seeds a table shows (percentage points): of the F1 pooled
#: over every object (what :func:`seed_summary` averages; with folds, a seed's models of
#: every fold together), and of one retraining (:func:`retrain_sd`).
POOLED_SD_COLUMN, RETRAIN_SD_COLUMN = ("seed SD of the pooled F1 (points)",
                                       "one retraining's SD (points)")


def sd_cells(r: Mapping[str, Any]) -> dict[str, str]:
    """A table's two seed-spread cells (:data:`POOLED_SD_COLUMN`, :data:`RETRAIN_SD_COLUMN`)
    from a :func:`seed_summary` (``seed_sd``, ``retrain_sd``); "-" where undefined."""
    return {POOLED_SD_COLUMN: points(r.get("seed_sd", float("nan"))),
            RETRAIN_SD_COLUMN: points(r.get("retrain_sd", float("nan")))}


def always_moving_f1(y_true: Any) -> float:
    """The chance reference: F1 of calling every object moving, 2P / (2P + N) for P movers
    and N still objects (its recall is 1, its precision the share of movers); NaN without
    a mover."""
    y = labels01(y_true)
    return float(_prf(y.sum(), len(y) - y.sum(), 0)[2])


def balanced_accuracy(y_true: Any, y_prob: Any, threshold: float = 0.5) -> float:
    """The mean of the recalls of the moving and of the still class (0.5 for any constant
    answer, whatever the share of movers); NaN without an object of either class."""
    m = metrics(y_true, y_prob, threshold)
    if not m["n_moving"] or not m["n_still"]:
        return float("nan")
    return (m["tp"] / m["n_moving"] + m["tn"] / m["n_still"]) / 2


def seed_summary(y_true: Any, y_prob: Any, groups: Any, instances: Any = None, n: int = 2000,
                 seed: int = 0, threshold: float = 0.5, level: float = 0.95,
                 folds: Any = None) -> dict[str, Any]:
    """Scores of S models (training seeds) on the same objects: per-seed precision, recall
    and F1; their mean, min and max, the seeds' standard deviation (``seed_sd``) and what
    one retraining moves (``retrain_sd``: :func:`retrain_sd`); the
    interval of the mean F1 over scenes and seeds (:func:`scene_bootstrap`); the chance
    reference (:func:`always_moving_f1`) and the balanced accuracy; and what the interval
    resamples: number of scenes, objects and (if given) vehicle instances.

    With ``folds`` (the fold of each object; each object predicted by its fold's models,
    row s of y_prob by the seed-s ones), precision, recall and F1 are pooled over every
    object per seed, and the per-unit entries, min and max are the folds' (each fold's
    seed-mean F1 on its own objects)."""
    y, probs = _as_models(y_true, y_prob)
    pooled = [metrics(y, p, threshold) for p in probs]
    per = pooled if folds is None else _per_fold(y, probs, np.asarray(folds), threshold)
    f1 = np.array([m["f1"] for m in per], dtype=float)
    defined = f1[~np.isnan(f1)]  # a fold without movers has no F1
    out: dict[str, Any] = {
        "seeds": len(per), "unit": "fold" if folds is not None else "seed",
        "training_seeds": len(probs),
        "f1": float(np.mean([m["f1"] for m in pooled])),
        "seed_sd": seed_sd([m["f1"] for m in pooled]),
        "retrain_sd": retrain_sd(y, probs, None if folds is None else np.asarray(folds),
                                 threshold),
        "f1_min": float(defined.min()) if defined.size else float("nan"),
        "f1_max": float(defined.max()) if defined.size else float("nan"),
        "precision": float(np.mean([m["precision"] for m in pooled])),
        "recall": float(np.mean([m["recall"] for m in pooled])),
        "balanced_accuracy": float(np.mean([balanced_accuracy(y, p, threshold)
                                            for p in probs])),
        "always_moving_f1": always_moving_f1(y),
        "per_seed": [{k: m[k] for k in ("f1", "precision", "recall", "tp", "fp", "fn")}
                     for m in per],
        "ci": bootstrap_f1_ci(y, probs, groups, n, seed, threshold, level, folds),
        "level": level,
        "n": len(y), "n_moving": int(y.sum()), "n_scenes": int(len(np.unique(groups))),
    }
    if instances is not None:
        out["n_instances"] = int(len(np.unique(np.asarray(instances))))
    return out


def two_sided_p(replicates: Any) -> float:
    """The paired bootstrap's two-sided p-value of A - B from its replicates (NaN: left
    out): twice the smaller of the shares with A - B <= 0 and with A - B >= 0, at most 1;
    NaN when none is defined. A replicate with A = B counts on both sides, so an effect whose
    percentile interval holds 0 is never below 5 % (where many replicates tie at 0, taking
    the share with A <= B alone called such an effect certain)."""
    r = np.asarray(replicates, dtype=np.float64).reshape(-1)
    r = r[~np.isnan(r)]
    if r.size == 0:
        return float("nan")
    return float(min(1.0, 2 * min(np.mean(r <= 0), np.mean(r >= 0))))


def paired_comparison(y_true: Any, prob_a: Any, prob_b: Any, groups: Any, n: int = 2000,
                      seed: int = 0, threshold: float = 0.5, level: float = 0.95,
                      folds: Any = None) -> dict[str, Any]:
    """Method A minus method B on the same objects: the difference of their seed-mean F1,
    its interval over scenes and training seeds (:func:`scene_bootstrap`: the same scenes
    and the same seed indices drawn for both methods, so what they share cancels), the
    per-seed differences (seed k of A against seed k of B; with ``folds``, as
    :func:`seed_summary`, fold k's seed-mean), the share of replicates in which A is not
    better and the number of replicates left out because their scenes hold no mover (F1
    undefined for both); and ``detectable``, the smallest difference these scenes would
    resolve (:func:`detectable`), for a question the interval leaves open."""
    y, pa = _as_models(y_true, prob_a)
    _, pb = _as_models(y_true, prob_b)
    ra = scene_bootstrap(y, pa, groups, n, seed, threshold, folds)
    rb = scene_bootstrap(y, pb, groups, n, seed, threshold, folds)  # same seed: same draws
    fa = np.array([metrics(y, p, threshold)["f1"] for p in pa])
    fb = np.array([metrics(y, p, threshold)["f1"] for p in pb])
    if folds is not None:
        f = np.asarray(folds)
        per = [a["f1"] - b["f1"] for a, b in zip(_per_fold(y, pa, f, threshold),
                                                   _per_fold(y, pb, f, threshold),
                                                   strict=True)]
    else:
        k = min(len(fa), len(fb))
        per = (fa[:k] - fb[:k]).tolist()
    d = ra - rb
    defined = d[~np.isnan(d)]
    return {"delta_f1": float(fa.mean() - fb.mean()), "ci": interval(d, level),
            "detectable": detectable(d, level),
            "per_seed": per, "training_seeds": [len(pa), len(pb)],
            "p_not_better": float(np.mean(defined <= 0)) if defined.size else float("nan"),
            "p_two_sided": two_sided_p(d),
            "undefined_replicates": int(d.size - defined.size),
            "unit": "fold" if folds is not None else "seed",
            "n": len(y), "n_scenes": int(len(np.unique(groups)))}


def breakdown(
    df: pd.DataFrame, y_true: Any, y_prob: Any, by: str = "category", *,
    bins: Sequence[float] | None = None, threshold: float = 0.5, groups: Any = None,
    n_boot: int = 1000, seed: int = 0, folds: Any = None,
) -> pd.DataFrame:
    """Metrics per group of objects: one row per value of ``df[by]``.

    ``by='distance'`` groups by distance bins (m, default :data:`DISTANCE_BINS`; empty bins
    dropped); any other column groups by its values. y_prob: (N,) or (S, N) for S training
    seeds (scores are means over seeds). With ``groups`` (the scene of each object), each
    row also gets the 95 % interval of its F1 over scenes and seeds (``ci_lo``, ``ci_hi``;
    seeds resampled within ``folds``, the fold of each object, if given) and its number of
    scenes. Columns: the group, n, n_moving, precision, recall, f1, accuracy
    (and ci_lo, ci_hi, scenes).
    """
    y, probs = _as_models(y_true, y_prob)
    if len(df) != len(y):
        raise ValueError(f"df has {len(df)} rows but y_true has {len(y)} values")
    if by not in df.columns:
        raise KeyError(f"breakdown by {by!r}: no such column (have {list(df.columns)})")
    key = df[by].to_numpy()
    name = by
    if by == "distance" or bins is not None:
        edges = list(DISTANCE_BINS if bins is None else bins)
        key = pd.cut(df[by].to_numpy(dtype=float), edges, right=False)
        name = f"{by}_bin"
    g = None if groups is None else np.asarray(groups).reshape(-1)
    cols = [name, "n", "n_moving", "precision", "recall", "f1", "accuracy"]
    rows = []
    for k, idx in pd.Series(np.arange(len(y))).groupby(key, observed=True, sort=True):
        i = idx.to_numpy()
        ms = [metrics(y[i], p[i], threshold) for p in probs]
        row = {name: str(k), "n": len(i), "n_moving": int(y[i].sum()),
               **{m: float(np.mean([x[m] for x in ms]))
                  for m in ("precision", "recall", "f1", "accuracy")}}
        if g is not None:
            row["ci_lo"], row["ci_hi"] = bootstrap_f1_ci(
                y[i], probs[:, i], g[i], n_boot, seed, threshold,
                folds=None if folds is None else np.asarray(folds)[i])
            row["scenes"] = int(len(np.unique(g[i])))
        rows.append(row)
    if g is not None:
        cols += ["ci_lo", "ci_hi", "scenes"]
    return pd.DataFrame(rows, columns=cols)


def points(x: Any, fmt: str = ".1f") -> str:
    """A fraction as percentage points for a table cell; "-" where undefined (NaN)."""
    x = float(x)
    return "-" if np.isnan(x) else format(100 * x, fmt)


def span(lo: Any, hi: Any, sep: str = "-") -> str:
    """An interval of fractions as "lo-hi" in percentage points; "-" where undefined."""
    a, b = points(lo), points(hi)
    return "-" if "-" in (a, b) else f"{a}{sep}{b}"


#: Fewer scenes than this, and a bootstrap interval over scenes is not to be trusted: it is
#: shown flagged (:func:`ci_text`).
MIN_SCENES = 10


def ci_text(ci: Any, n_scenes: Any, sep: str = "-", fmt: str | None = None) -> str:
    """:func:`span` of an interval over scenes (or, with ``fmt``, its values as they are,
    e.g. ``.2f`` for px), flagged "(n scenes: too few)" where it resamples fewer than
    :data:`MIN_SCENES`."""
    if ci is None:
        return ""
    if fmt is None:
        text = span(*ci, sep=sep)
    else:
        text = ("-" if any(not np.isfinite(v) for v in ci)
                else f"{ci[0]:{fmt}}{sep}{ci[1]:{fmt}}")
    try:
        few = int(n_scenes) < MIN_SCENES
    except (TypeError, ValueError):
        few = False
    return f"{text} ({int(n_scenes)} scenes: too few)" if few and text != "-" else text


def table3(rows: Iterable[Mapping[str, Any]] | Mapping[str, Mapping[str, Any]]) -> pd.DataFrame:
    """The paper's Table 3 from per-method results (:func:`seed_summary` dicts, or any dict
    with f1, precision, recall and optionally f1_min/f1_max, seeds, training_seeds, seed_sd,
    retrain_sd,
    ci, balanced_accuracy, always_moving_f1, n, n_scenes, n_instances; a mapping method ->
    such a dict also works).

    Columns: Method, F1 (%) (mean over training seeds), the two seed spreads (points;
    :func:`sd_cells`, "-" for one seed),
    seed range (%) (of F1), seeds, P (%) and R (%) (precision and recall, means over
    seeds), balanced accuracy (%) (prevalence-free), always moving F1 (%) (the chance
    reference), F1 95% CI (%) (whole test scenes and training seeds resampled), scenes,
    objects, vehicles; percentages to 0.1. Cross-validated results (``unit`` fold) give
    F1, P and R pooled over the folds and ``fold range (%)``, ``folds`` instead.
    """
    if isinstance(rows, Mapping):
        rows = [{"method": k, **v} for k, v in rows.items()]
    rows = list(rows)
    unit = unit_of(rows)
    out = []
    for r in rows:
        ci = r.get("ci")
        lo, hi = r.get("f1_min"), r.get("f1_max")
        out.append({
            "Method": r["method"],
            "F1 (%)": round(100 * float(r["f1"]), 1),
            **sd_cells(r),
            f"{unit} range (%)": (span(lo, hi)
                                  if lo is not None and r.get("seeds", 1) > 1 else ""),
            f"{unit}s": r.get("seeds", ""),
            "training seeds": r.get("training_seeds", ""),
            "P (%)": round(100 * float(r["precision"]), 1),
            "R (%)": round(100 * float(r["recall"]), 1),
            "balanced accuracy (%)": points(r.get("balanced_accuracy", float("nan"))),
            "always moving F1 (%)": points(r.get("always_moving_f1", float("nan"))),
            CI_COLUMN: ci_text(ci, r.get("n_scenes")),
            "scenes": r.get("n_scenes", ""),
            "objects": r.get("n", ""),
            "vehicles": r.get("n_instances", ""),
        })
    return pd.DataFrame(out, columns=list(out[0]) if out else ["Method"])


#: The interval column of :func:`table3`: what it resamples.
CI_COLUMN = "F1 95% CI, scenes and seeds (%)"


#: Columns of :func:`comparison_table` (also when it has no row).
COMPARISON_COLUMNS = ["comparison", "ΔF1 (points)", "95% CI, scenes and seeds (points)",
                      "verdict", "detectable (points)", "per seed (points)",
                      "replicates with A <= B (%)", "scenes", "objects"]


def unit_of(rows: Iterable[Mapping[str, Any]]) -> str:
    """``fold`` if the results come from cross-validation (``unit``), else ``seed``."""
    return "fold" if any(r.get("unit") == "fold" for r in rows) else "seed"


def comparison_table(rows: Mapping[str, Mapping[str, Any]]) -> pd.DataFrame:
    """Paired differences ``{"A - B": paired_comparison(...)}`` as a table (F1 points;
    columns :data:`COMPARISON_COLUMNS`, ``per fold`` for cross-validated results): the
    verdict, and the smallest difference the scenes would detect (80 % power)."""
    unit = unit_of(rows.values())
    out = []
    for name, r in rows.items():
        out.append({
            "comparison": name,
            "ΔF1 (points)": round(100 * r["delta_f1"], 1),
            "95% CI, scenes and seeds (points)": ci_text(r["ci"], r["n_scenes"], sep=" to "),
            "verdict": verdict(r["ci"]),
            "detectable (points)": round(100 * r.get("detectable", float("nan")), 1),
            f"per {unit} (points)": ", ".join(points(d, "+.1f") for d in r["per_seed"]),
            "replicates with A <= B (%)": round(100 * r["p_not_better"], 1),
            "scenes": r["n_scenes"], "objects": r["n"],
        })
    table = pd.DataFrame(out, columns=[c.replace("per seed", f"per {unit}")
                                       for c in COMPARISON_COLUMNS])
    # the interval as numbers (points), row by row, for plots (the column holds its text)
    table.attrs["ci_points"] = [(100 * r["ci"][0], 100 * r["ci"][1]) if r.get("ci") is not None
                                else (float("nan"), float("nan")) for r in rows.values()]
    # each row's two-sided p-value (:func:`two_sided_p`; NaN for a row made without one)
    table.attrs["p_two_sided"] = [float(r.get("p_two_sided", float("nan")))
                                  for r in rows.values()]
    return table


# --- the original code's protocol, for comparison --------------------------------------------


def paper_protocol_scores(
    y_true: Any, y_prob: Any, batch_size: int = 128, threshold: float = 0.5
) -> dict[str, float]:
    """Precision, recall, F1 averaged over consecutive batches (the original's bug).

    The original scored each validation batch (in order, batch 128) with sklearn and
    averaged the per-batch values; a batch without positives contributes 0 (sklearn's
    ``zero_division`` default, kept here because this reproduces the original's number).
    """
    y, yhat = _binary(y_true, y_prob, threshold)
    if len(y) == 0:
        return {"precision": 0.0, "recall": 0.0, "f1": 0.0}
    starts = np.arange(0, len(y), batch_size)
    tp = np.add.reduceat(((yhat == 1) & (y == 1)).astype(np.int64), starts)
    fp = np.add.reduceat(((yhat == 1) & (y == 0)).astype(np.int64), starts)
    fn = np.add.reduceat(((yhat == 0) & (y == 1)).astype(np.int64), starts)
    prec, rec, f1 = _prf(tp, fp, fn, undefined=0.0)
    return {"precision": float(prec.mean()), "recall": float(rec.mean()), "f1": float(f1.mean())}


def paper_protocol_f1(y_true: Any, y_prob: Any, batch_size: int = 128,
                      threshold: float = 0.5) -> float:
    """F1 averaged per batch of ``batch_size`` (the original's bug); see
    :func:`paper_protocol_scores`."""
    return paper_protocol_scores(y_true, y_prob, batch_size, threshold)["f1"]


def thin_still(y_true: Any, keep: int = 1, every: int = 2) -> np.ndarray:
    """Mask (N,) bool keeping all moving objects and the first ``keep`` of every ``every``
    still objects in order (the original: validation 1 of 2, training 3 of 5)."""
    y = labels01(y_true)
    if not 0 < keep <= every:
        raise ValueError(f"need 0 < keep <= every, got keep={keep}, every={every}")
    still_rank = np.cumsum(y == 0) - 1  # 0-based rank among still objects
    return (y == 1) | (still_rank % every < keep)


def protocol_comparison(
    y_true: Any, y_prob: Any, batch_size: int = 128, threshold: float = 0.5
) -> pd.DataFrame:
    """One model scored both ways, side by side.

    Rows: clean (whole set, all objects), per-batch F1 (all objects), thinned stills (whole
    set), paper protocol (thinned + per-batch). Columns: protocol, n, precision, recall, f1.
    """
    y = labels01(y_true)
    p = np.asarray(y_prob, dtype=np.float64).reshape(-1)
    keep = thin_still(y)
    rows = []
    for name, yy, pp, per_batch in (
        ("clean: whole set", y, p, False),
        ("per-batch F1, all objects", y, p, True),
        ("stills thinned 1 of 2, whole set", y[keep], p[keep], False),
        ("paper protocol: thinned + per-batch", y[keep], p[keep], True),
    ):
        m = (paper_protocol_scores(yy, pp, batch_size, threshold) if per_batch
             else metrics(yy, pp, threshold))
        rows.append({"protocol": name, "n": len(yy),
                     **{k: m[k] for k in ("precision", "recall", "f1")}})
    return pd.DataFrame(rows)


# --- a geometric baseline without learning ---------------------------------------------------


def fit_threshold(scores: Any, labels: Any) -> float:
    """The threshold t maximising F1 of ``score > t`` on (training) data.

    scores: (N,) any 1-D score where larger means 'more likely moving' (e.g. the residual
    flow magnitude, px); labels: (N,) 0/1. t is the midpoint between two consecutive distinct
    scores (or just below the smallest one); ties in F1 go to the higher threshold.
    """
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    y = labels01(labels)
    if s.shape != y.shape or s.size == 0:
        raise ValueError(f"need equally long non-empty scores and labels, got {s.size}, {y.size}")
    if not np.isfinite(s).all():
        raise ValueError("scores contain NaN/inf")
    if y.sum() == 0:  # nothing moving: call nothing moving
        return float(s.max())
    order = np.argsort(-s, kind="mergesort")
    s_sorted, y_sorted = s[order], y[order]
    # Cut after each run of equal scores: predicted positive = the first k sorted objects.
    last_of_run = np.r_[s_sorted[1:] != s_sorted[:-1], True]
    tp = np.cumsum(y_sorted)[last_of_run]
    k = np.flatnonzero(last_of_run) + 1
    fp = k - tp
    fn = y.sum() - tp
    f1 = _prf(tp, fp, fn)[2]
    best = int(np.argmax(f1))  # first maximum = highest threshold
    cut_hi = s_sorted[last_of_run][best]  # the lowest score still called moving
    below = s_sorted[k[best]] if k[best] < len(s_sorted) else cut_hi - 1.0
    return float((cut_hi + below) / 2)


def apply_threshold(scores: Any, t: float) -> np.ndarray:
    """(N,) int 0/1: 1 (moving) where score > t."""
    return (np.asarray(scores, dtype=np.float64) > t).astype(np.int64)


