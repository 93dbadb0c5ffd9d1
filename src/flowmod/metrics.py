"""Binary scores over a whole set: precision, recall, F1, intervals, threshold fitting, and the
original code's per-batch protocol (kept only to show its effect).

Labels: 1 = moving, 0 = still; ``prob > threshold`` (0.5) predicts moving, as in the paper.
The clean protocol computes precision, recall and F1 once over all objects of a split. The
original code averaged F1 per batch of 128 and evaluated on a validation set that kept 1 of
every 2 still objects.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
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


def _binary(y_true: Any, y_prob: Any, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    y = np.asarray(y_true).astype(np.int64).reshape(-1)
    p = np.asarray(y_prob, dtype=np.float64).reshape(-1)
    if y.shape != p.shape:
        raise ValueError(f"y_true has {y.size} values but y_prob has {p.size}")
    if not np.isin(y, (0, 1)).all():
        raise ValueError("y_true must hold 0 (still) / 1 (moving) only")
    return y, (p > threshold).astype(np.int64)


def _prf(tp: Any, fp: Any, fn: Any) -> tuple[Any, Any, Any]:
    """Precision, recall, F1 from counts (arrays ok); 0 where undefined (sklearn's 0 rule)."""
    tp, fp, fn = (np.asarray(v, dtype=np.float64) for v in (tp, fp, fn))
    with np.errstate(divide="ignore", invalid="ignore"):
        prec = np.where(tp + fp > 0, tp / (tp + fp), 0.0)
        rec = np.where(tp + fn > 0, tp / (tp + fn), 0.0)
        f1 = np.where(2 * tp + fp + fn > 0, 2 * tp / (2 * tp + fp + fn), 0.0)
    return prec, rec, f1


def metrics(y_true: Any, y_prob: Any, threshold: float = 0.5) -> dict[str, Any]:
    """One precision / recall / F1 / accuracy over the whole set.

    y_true: (N,) 0/1; y_prob: (N,) probabilities (or 0/1 predictions). Returns a dict with
    precision, recall, f1, accuracy (fractions), tp, fp, tn, fn, n, n_moving, n_still,
    confusion ([[tn, fp], [fn, tp]], sklearn's layout) and threshold. Undefined ratios are 0.
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
        "accuracy": (tp + tn) / n if n else 0.0,
        "tp": tp, "fp": fp, "tn": tn, "fn": fn,
        "n": n, "n_moving": int(y.sum()), "n_still": int(n - y.sum()),
        "confusion": [[tn, fp], [fn, tp]], "threshold": float(threshold),
    }


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

    y = np.asarray(y_true).astype(int)
    p = np.asarray(y_prob, dtype=np.float64)
    prec, rec, thr = precision_recall_curve(y, p)
    df = pd.DataFrame({"threshold": thr, "precision": prec[:-1], "recall": rec[:-1]})
    return df.iloc[::-1].reset_index(drop=True), float(average_precision_score(y, p))


def bootstrap_f1_ci(
    y_true: Any, y_prob: Any, n: int = 1000, seed: int = 0, threshold: float = 0.5,
    level: float = 0.95,
) -> tuple[float, float]:
    """Percentile bootstrap CI of the whole-set F1 (objects resampled with replacement).

    Returns (lo, hi) as fractions; ``level`` 0.95 = 95 %. Note objects of one pair/scene are
    correlated, so this interval is optimistic (too narrow) rather than conservative.
    """
    y, yhat = _binary(y_true, y_prob, threshold)
    if len(y) == 0:
        return (0.0, 0.0)
    is_tp = ((yhat == 1) & (y == 1)).astype(np.int32)
    is_fp = ((yhat == 1) & (y == 0)).astype(np.int32)
    is_fn = ((yhat == 0) & (y == 1)).astype(np.int32)
    rng = np.random.default_rng(seed)
    f1s = np.empty(n)
    chunk = max(1, min(n, 2_000_000 // max(1, len(y))))
    for a in range(0, n, chunk):
        b = min(n, a + chunk)
        idx = rng.integers(0, len(y), size=(b - a, len(y)))
        f1s[a:b] = _prf(is_tp[idx].sum(1), is_fp[idx].sum(1), is_fn[idx].sum(1))[2]
    alpha = (1 - level) / 2
    lo, hi = np.quantile(f1s, [alpha, 1 - alpha])
    return float(lo), float(hi)


def breakdown(
    df: pd.DataFrame, y_true: Any, y_prob: Any, by: str = "category", *,
    bins: Sequence[float] | None = None, threshold: float = 0.5,
) -> pd.DataFrame:
    """Metrics per group of objects: one row per value of ``df[by]``.

    ``by='distance'`` groups by distance bins (m, default :data:`DISTANCE_BINS`; empty bins
    dropped); any other column groups by its values. Columns: the group, n, n_moving,
    precision, recall, f1, accuracy.
    """
    y, _ = _binary(y_true, y_prob, threshold)
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
    p = np.asarray(y_prob, dtype=np.float64)
    rows = []
    for g, idx in pd.Series(np.arange(len(y))).groupby(key, observed=True, sort=True):
        m = metrics(y[idx.to_numpy()], p[idx.to_numpy()], threshold)
        rows.append({name: str(g), "n": m["n"], "n_moving": m["n_moving"],
                     **{k: m[k] for k in ("precision", "recall", "f1", "accuracy")}})
    return pd.DataFrame(rows, columns=[name, "n", "n_moving", "precision", "recall", "f1",
                                       "accuracy"])


def table3(rows: Iterable[Mapping[str, Any]] | Mapping[str, Mapping[str, Any]]) -> pd.DataFrame:
    """The paper's Table 3 from per-method results.

    rows: dicts with method, f1, precision, recall (fractions) and optionally ci (lo, hi)
    and n; or a mapping method -> such a dict. Returns columns Method, F1 (%),
    Precision (%), Recall (%), F1 95% CI (%), n; percentages rounded to 0.1.
    """
    if isinstance(rows, Mapping):
        rows = [{"method": k, **v} for k, v in rows.items()]
    out = []
    for r in rows:
        ci = r.get("ci")
        out.append({
            "Method": r["method"],
            "F1 (%)": round(100 * float(r["f1"]), 1),
            "Precision (%)": round(100 * float(r["precision"]), 1),
            "Recall (%)": round(100 * float(r["recall"]), 1),
            "F1 95% CI (%)": (
                f"{100 * ci[0]:.1f}-{100 * ci[1]:.1f}" if ci is not None else ""
            ),
            "n": r.get("n"),
        })
    return pd.DataFrame(out, columns=["Method", "F1 (%)", "Precision (%)", "Recall (%)",
                                      "F1 95% CI (%)", "n"])


# --- the original code's protocol, for comparison --------------------------------------------


def paper_protocol_scores(
    y_true: Any, y_prob: Any, batch_size: int = 128, threshold: float = 0.5
) -> dict[str, float]:
    """Precision, recall, F1 averaged over consecutive batches (the original's bug).

    The original scored each validation batch (in order, batch 128) with sklearn and
    averaged the per-batch values; a batch without positives contributes 0.
    """
    y, yhat = _binary(y_true, y_prob, threshold)
    if len(y) == 0:
        return {"precision": 0.0, "recall": 0.0, "f1": 0.0}
    starts = np.arange(0, len(y), batch_size)
    tp = np.add.reduceat(((yhat == 1) & (y == 1)).astype(np.int64), starts)
    fp = np.add.reduceat(((yhat == 1) & (y == 0)).astype(np.int64), starts)
    fn = np.add.reduceat(((yhat == 0) & (y == 1)).astype(np.int64), starts)
    prec, rec, f1 = _prf(tp, fp, fn)
    return {"precision": float(prec.mean()), "recall": float(rec.mean()), "f1": float(f1.mean())}


def paper_protocol_f1(y_true: Any, y_prob: Any, batch_size: int = 128,
                      threshold: float = 0.5) -> float:
    """F1 averaged per batch of ``batch_size`` (the original's bug); see
    :func:`paper_protocol_scores`."""
    return paper_protocol_scores(y_true, y_prob, batch_size, threshold)["f1"]


def thin_still(y_true: Any, keep: int = 1, every: int = 2) -> np.ndarray:
    """Mask (N,) bool keeping all moving objects and the first ``keep`` of every ``every``
    still objects in order (the original: validation 1 of 2, training 3 of 5)."""
    y = np.asarray(y_true).astype(np.int64).reshape(-1)
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
    y = np.asarray(y_true).astype(np.int64).reshape(-1)
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
    y = np.asarray(labels).astype(np.int64).reshape(-1)
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


