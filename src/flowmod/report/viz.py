"""Figures shared by several chapters (matplotlib, Agg-safe)."""

from __future__ import annotations

import io
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from IPython.display import Image, display
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch, Rectangle

from flowmod.artefacts import atomic_path
from flowmod.crops import crop_image
from flowmod.flow import flow_to_color
from flowmod.metrics import MIN_SCENES, metrics, pr_curve
from flowmod.report.draw import draw_boxes, label_colors
from flowmod.report.video import side_by_side

#: The pipeline stages in data-flow order: (chapter, label, artefact).
PIPELINE = [
    ("01", "world /\nnuScenes", "dataroot"),
    ("02", "select\n(Table 1)", "pairs, objects"),
    ("03", "optical\nflow", "flow/<method>"),
    ("04", "labels\n(eq. 1)", "label, speed"),
    ("05", "crops\n(x3, resize)", "crops/<method>"),
    ("06", "train\nResNet18", "models/"),
    ("07", "evaluate\n(Table 3)", "metrics/.../test"),
    ("08", "generalise\n(Table 4)", "metrics/.../general"),
    ("09", "blind\nspots", "(analysis)"),
]


class EmptyFigure(ValueError):
    """A figure would show nothing (names the file and what is empty)."""


def _finite(a: Any) -> bool:
    a = np.ma.filled(np.asarray(a, dtype=float).ravel(), np.nan) if np.size(a) else np.array([])
    return bool(np.isfinite(a).any())


def _has_data(ax: plt.Axes) -> bool:
    """True if ``ax`` draws data: a line in data coordinates, a bar or shape of some size,
    a collection or an image with a finite value (reference lines such as axvline and
    zero-height bars do not count)."""
    lines = [ln for ln in ax.lines if ln.get_transform() == ax.transData
             and _finite(ln.get_xdata()) and _finite(ln.get_ydata())]
    bars = [pt for pt in ax.patches if not isinstance(pt, Rectangle)
            or (pt.get_height() != 0 and pt.get_width() != 0
                and _finite([pt.get_height(), pt.get_width()]))]
    cols = [c for c in ax.collections if len(c.get_offsets()) and _finite(c.get_offsets())
            or any(len(pth.vertices) and _finite(pth.vertices) for pth in c.get_paths())]
    imgs = [im for im in ax.images if _finite(im.get_array())]
    return bool(lines or bars or cols or imgs)


def figure_problems(fig: plt.Figure) -> list[str]:
    """Why ``fig`` would mislead: an axes that is shown without any data on it, or a legend
    entry that counts nothing (``n=0``). Empty list: fine."""
    out = []
    for i, ax in enumerate(fig.axes):
        name = ax.get_title() or ax.get_ylabel() or f"axes {i}"
        if ax.axison and not _has_data(ax):
            out.append(f"{name!r} has no data")
        leg = ax.get_legend()
        for t in leg.get_texts() if leg else []:
            if re.search(r"\bn\s*=\s*0\b", t.get_text()):
                out.append(f"{name!r}: legend entry {t.get_text()!r} counts nothing")
    if not any(_has_data(ax) or (not ax.axison and ax.texts) for ax in fig.axes):
        out.append("no axes has data")
    return out


def show(fig: plt.Figure, path: str | Path, dpi: int = 110) -> None:
    """Save ``fig`` as a PNG file, close it, and display the file in the notebook.

    Figures enter the book as files (``runs/<profile>/figures/``), shown once. A figure that
    would show nothing (:func:`figure_problems`) raises :class:`EmptyFigure` instead.
    """
    path = Path(path)
    problems = figure_problems(fig)
    if problems:
        plt.close(fig)
        raise EmptyFigure(f"{path.name}: {'; '.join(problems)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    write_if_changed(path, buf.getvalue())
    display(Image(filename=str(path)))


def write_if_changed(path: Path, data: bytes) -> bool:
    """Write ``data`` to ``path`` (atomically) unless the file already holds exactly it, so
    a rerun that draws the same figure leaves the file, its time and its readers alone.
    Returns True if it wrote."""
    if path.is_file() and path.stat().st_size == len(data) and path.read_bytes() == data:
        return False
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return True


def pipeline_figure() -> plt.Figure:
    """The study's pipeline as a left-to-right chain of stages."""
    fig, ax = plt.subplots(figsize=(12, 2.4))
    n = len(PIPELINE)
    for i, (num, label, artefact) in enumerate(PIPELINE):
        x = i * 1.5
        box = FancyBboxPatch((x, 0.3), 1.1, 1.0, boxstyle="round,pad=0.05",
                             fc="#e8f0fe" if num != "06" else "#fde8e8", ec="#334")
        ax.add_patch(box)
        ax.text(x + 0.55, 0.8, label, ha="center", va="center", fontsize=9)
        ax.text(x + 0.55, 1.45, num, ha="center", va="bottom", fontsize=8, color="#667")
        ax.text(x + 0.55, 0.1, artefact, ha="center", va="top", fontsize=7, color="#445",
                family="monospace")
        if i < n - 1:
            ax.add_patch(FancyArrowPatch((x + 1.15, 0.8), (x + 1.45, 0.8),
                                         arrowstyle="-|>", mutation_scale=12, color="#334"))
    ax.set_xlim(-0.2, n * 1.5 - 0.2)
    ax.set_ylim(-0.3, 1.8)
    ax.axis("off")
    fig.tight_layout()
    return fig


def frames_grid(images: list[np.ndarray], titles: list[str], ncols: int = 2,
                width: float = 14.0) -> plt.Figure:
    """BGR images in a grid with titles."""
    n = len(images)
    nrows = max(1, int(np.ceil(n / ncols)))
    h, w = images[0].shape[:2]
    fig, axes = plt.subplots(nrows, ncols, figsize=(width, width / ncols * h / w * nrows + 0.4),
                             squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, img, title in zip(axes.ravel(), images, titles, strict=False):
        ax.imshow(img[..., ::-1] if img.ndim == 3 else img)
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def histogram(values: dict[str, np.ndarray], bins: np.ndarray, xlabel: str,
              vline: float | None = None, vlabel: str = "") -> plt.Figure:
    """Overlaid histograms of named value arrays, with an optional vertical line."""
    fig, ax = plt.subplots(figsize=(7, 3.2))
    for name, v in values.items():
        ax.hist(np.asarray(v, dtype=float), bins=bins, alpha=0.6, label=f"{name} (n={len(v)})")
    if vline is not None:
        ax.axvline(vline, color="k", ls="--", lw=1, label=vlabel)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("objects")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def object_thumbnails(dataroot: str | Path, pairs: pd.DataFrame, objects: pd.DataFrame,
                      scale: float = 3.0, size: int = 192) -> list[np.ndarray]:
    """For each object row: the frame-1 image cropped like the classifier's input
    (:func:`flowmod.crops.crop_image`: square, ``scale`` x the box's longer side,
    edge-padded), box drawn in its label colour, resized to ``size`` px."""
    paths = pairs.set_index("pair_id")["path_1"]
    out = []
    for row in objects.itertuples():
        img = cv2.imread(str(Path(dataroot) / paths[row.pair_id]))
        if img is None:
            raise FileNotFoundError(f"cannot read {Path(dataroot) / paths[row.pair_id]}")
        box = np.array([[row.xmin, row.ymin, row.xmax, row.ymax]])
        img = draw_boxes(img, box, label_colors([row.label]), thickness=1)
        out.append(crop_image(img, box, size, scale)[0])
    return out


def scatter_by_label(x: np.ndarray, y: np.ndarray, labels: np.ndarray, xlabel: str,
                     ylabel: str, title: str = "", logy: bool = False) -> plt.Figure:
    """Scatter of still (blue) and moving (red) objects."""
    fig, ax = plt.subplots(figsize=(7, 3.6))
    labels = np.asarray(labels)
    for lab, color, name in ((0, "tab:blue", "still"), (1, "tab:red", "moving")):
        m = labels == lab
        ax.scatter(np.asarray(x)[m], np.asarray(y)[m], s=6, alpha=0.5, c=color,
                   label=f"{name} (n={int(m.sum())})")
    if logy:
        ax.set_yscale("symlog", linthresh=1.0)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def crop_steps_figure(image: np.ndarray, flow_rgb: np.ndarray, box: np.ndarray,
                      window: np.ndarray, crop: np.ndarray, crop_rgb: np.ndarray) -> plt.Figure:
    """The paper's preprocessing on one object, in four panels.

    image: (H, W, 3) BGR frame 1; flow_rgb: (H, W, 3) RGB flow colours; box: (4,) xyxy px;
    window: (3,) x0, y0, side px of the tripled square; crop: (2, S, S) flow crop (px);
    crop_rgb: (S, S, 3) its colours.
    """
    x0, y0, x1, y1 = box
    s = max(x1 - x0, y1 - y0)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    wx, wy, side = window
    pad = side * 0.6
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.8))
    for ax, img, title in ((axes[0], image[..., ::-1], "1. frame 1 and the 2D box"),
                           (axes[1], flow_rgb, "2. square (max side), tripled")):
        ax.imshow(img)
        ax.add_patch(plt.Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="yellow", lw=1.5))
        ax.set_xlim(wx - pad, wx + side + pad)
        ax.set_ylim(wy + side + pad, wy - pad)
        ax.set_title(title, fontsize=9)
    axes[1].add_patch(plt.Rectangle((cx - s / 2, cy - s / 2), s, s, fill=False, ec="w", ls="--"))
    axes[1].add_patch(plt.Rectangle((wx, wy), side, side, fill=False, ec="w", lw=2))
    axes[2].imshow(crop_rgb)
    axes[2].set_title(f"3. crop, edge-padded, resized to {crop.shape[-1]} px", fontsize=9)
    uv = np.concatenate([crop[0], crop[1]], axis=1)
    im = axes[3].imshow(uv, cmap="coolwarm", vmin=-np.abs(uv).max(), vmax=np.abs(uv).max())
    axes[3].set_title("4. the network's input: u | v (px)", fontsize=9)
    fig.colorbar(im, ax=axes[3], fraction=0.046)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    return fig


def crop_gallery(x: np.ndarray, labels: np.ndarray, n: int = 8, seed: int = 0,
                 titles: list[str] | None = None) -> plt.Figure:
    """Flow-colour crops of ``n`` still (top row) and ``n`` moving (bottom row) objects.

    x: (N, 2, S, S) crops, px. Colours share one magnitude scale per crop.
    """
    rng = np.random.default_rng(seed)
    labels = np.asarray(labels)
    fig, axes = plt.subplots(2, n, figsize=(1.6 * n, 3.6), squeeze=False)
    for row, lab, name in ((0, 0, "still"), (1, 1, "moving")):
        idx = np.flatnonzero(labels == lab)
        pick = rng.choice(idx, size=min(n, len(idx)), replace=False) if len(idx) else []
        for ax in axes[row]:
            ax.axis("off")
        for ax, i in zip(axes[row], pick, strict=False):
            ax.imshow(flow_to_color(np.asarray(x[i], dtype=np.float32).transpose(1, 2, 0)))
            ax.set_title(titles[i] if titles else name, fontsize=7,
                         color="tab:red" if lab else "tab:blue")
    fig.tight_layout()
    return fig


def input_gallery(images: np.ndarray, flow: np.ndarray, static: np.ndarray,
                  labels: np.ndarray, instances: np.ndarray | None = None, n: int = 3,
                  seed: int = 0) -> plt.Figure:
    """For ``n`` still and ``n`` moving objects (rows; one per vehicle ``instances`` if
    given): the frame-1 image crop, the flow crop, the static-world flow of the same window
    and their difference (the residual input). The three flows share one colour scale per
    row: the 95th percentile of the flow's magnitude in the box's square (the middle third)
    or of the residual's, whichever is larger (larger vectors saturate).

    images: (N, 6, S, S) uint8 (frame 1 = channels 0-2); flow, static: (N, 2, S, S) px."""
    rng = np.random.default_rng(seed)
    labels = np.asarray(labels)
    keys = np.arange(len(labels)) if instances is None else np.asarray(instances)
    pick = []
    for lab in (0, 1):
        idx = np.flatnonzero(labels == lab)
        _, first = np.unique(keys[idx], return_index=True)  # one object per vehicle
        cand = idx[np.sort(first)]
        pick += [(lab, i) for i in sorted(rng.choice(cand, size=min(n, len(cand)),
                                                     replace=False))]
    fig, axes = plt.subplots(max(1, len(pick)), 4, figsize=(7.2, 1.8 * max(1, len(pick))),
                             squeeze=False)
    cols = ("image (frame 1)", "flow", "static-world flow", "residual")
    s = flow.shape[-1]
    a, b = s // 3, s - s // 3
    for r, (lab, i) in enumerate(pick):
        f = np.asarray(flow[i], np.float32).transpose(1, 2, 0)
        st = np.asarray(static[i], np.float32).transpose(1, 2, 0)
        top = max(float(np.percentile(np.linalg.norm(f[a:b, a:b], axis=2), 95)),
                  float(np.percentile(np.linalg.norm(f - st, axis=2), 95)), 1e-3)
        panes = [np.asarray(images[i][:3]).transpose(1, 2, 0)] + [
            flow_to_color(x, max_flow=top) for x in (f, st, f - st)]
        for c, (ax, im) in enumerate(zip(axes[r], panes, strict=True)):
            ax.imshow(im)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(cols[c], fontsize=8)
        axes[r][0].set_ylabel(f"{'moving' if lab else 'still'}\nscale {top:.1f} px",
                              fontsize=7, color="tab:red" if lab else "tab:blue")
    fig.tight_layout()
    return fig


def training_curves(histories: dict[str, list[pd.DataFrame]]) -> plt.Figure:
    """Training loss, validation loss and validation F1 per epoch: one colour per method, one
    line per training seed (the first seed solid, the others thin)."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.4))
    for i, (method, hs) in enumerate(histories.items()):
        color = f"C{i}"
        for k, h in enumerate(hs):
            lw, alpha = (1.6, 1.0) if k == 0 else (0.8, 0.5)
            lab = method if k == 0 else None
            axes[0].plot(h["epoch"], h["train_loss"], color=color, lw=lw, alpha=alpha,
                         label=f"{lab} train" if lab else None)
            axes[0].plot(h["epoch"], h["val_loss"], ls="--", color=color, lw=lw, alpha=alpha,
                         label=f"{lab} val" if lab else None)
            axes[1].plot(h["epoch"], h["val_f1"], marker="o", ms=3, color=color, lw=lw,
                         alpha=alpha, label=lab)
            best = h.attrs.get("best_epoch")
            if best:
                axes[1].scatter([best], [h.loc[h["epoch"] == best, "val_f1"]], s=60,
                                facecolors="none", edgecolors=color)
    axes[0].set(xlabel="epoch", ylabel="BCE loss", title="loss")
    axes[1].set(xlabel="epoch", ylabel="F1", title="validation F1 (circle: chosen epoch)",
                ylim=(0, 1))
    for ax in axes:
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def flow_training_curves(histories: dict[str, pd.DataFrame],
                         references: dict[str, float]) -> plt.Figure:
    """A flow network's training: the loss per step (left, one colour per way of training,
    smoothed over 25 steps) and the validation end-point error at each evaluation (right; step
    0: the untrained network), with
    the ``references`` (e.g. DIS: name -> EPE px) as horizontal lines."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.4))
    for i, (name, h) in enumerate(histories.items()):
        steps = h.dropna(subset=["loss"])  # step 0 (the untrained network) has no loss
        loss = steps["loss"].rolling(25, min_periods=1).mean()
        axes[0].plot(steps["step"], loss / loss.iloc[0], color=f"C{i}", label=name)
        ev = h.dropna(subset=["val_epe"])
        axes[1].plot(ev["step"], ev["val_epe"], marker="o", ms=3, color=f"C{i}", label=name)
    for j, (name, v) in enumerate(references.items()):
        axes[1].axhline(v, color="0.5", ls=("--", ":", "-.")[j % 3], lw=1, label=name)
    axes[0].set(xlabel="step", ylabel="loss / first step's", title="training loss",
                yscale="log")
    axes[1].set(xlabel="step", ylabel="EPE (px)", title="validation end-point error")
    for ax in axes:
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def pretrain_curves(train: pd.DataFrame, val: pd.DataFrame,
                    references: dict[str, dict[str, float]],
                    scale_changes: Sequence[tuple[int, float]] = ()) -> plt.Figure:
    """The shipped network's training: ``train`` (step, loss per block of steps; left) and
    the validation end-point error overall and inside the far vehicles' boxes (``val``:
    step, val_epe, val_epe_boxes; step 0 the untrained network), with each of
    ``references`` (name -> {epe, epe_boxes} px) as a horizontal line and each of
    ``scale_changes`` (step, new frame scale) as a labelled vertical line."""
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.3))
    for ax in axes:
        for step, scale in scale_changes:
            ax.axvline(step, color="0.5", ls=":", lw=1)
            ax.annotate(f"frames at {scale:g}", (step, 1.0), xycoords=("data", "axes fraction"),
                        xytext=(2, -10), textcoords="offset points", fontsize=7, color="0.3")
    axes[0].plot(train["step"], train["loss"], color="C0")
    axes[0].set(xlabel="step", ylabel="loss (mean per block)", title="training loss",
                yscale="log")
    for ax, key, title in ((axes[1], "epe", "validation EPE"),
                           (axes[2], "epe_boxes", "validation EPE in far vehicles' boxes")):
        ax.plot(val["step"], val[f"val_{key}"], marker="o", ms=4, color="C0",
                label="fastflownet")
        for j, (name, ref) in enumerate(references.items()):
            ax.axhline(ref[key], color=f"C{j + 1}", ls=("--", ":", "-.")[j % 3], lw=1,
                       label=name)
        ax.set(xlabel="step", ylabel="EPE (px)", title=title, ylim=(0, None))
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def prediction_frames(dataroot: str | Path, pairs: pd.DataFrame, preds: pd.DataFrame,
                      n: int = 4, seed: int = 0, threshold: float = 0.5,
                      ) -> tuple[list[np.ndarray], list[str]]:
    """Figure 2 style: frame 1 of ``n`` pairs with each object's box coloured by the
    prediction (blue still, red moving); wrong predictions get a yellow ``x`` tag.

    preds: objects with pair_id, box, label and prob. Pairs holding a wrong prediction are
    preferred, half of the picks, so both failures and successes show.
    """
    rng = np.random.default_rng(seed)
    wrong = preds.assign(wrong=(preds["prob"] > threshold).astype(int) != preds["label"])
    per_pair = wrong.groupby("pair_id")["wrong"].agg(["any", "size"])
    bad = per_pair.index[per_pair["any"]].to_numpy()
    good = per_pair.index[~per_pair["any"] & (per_pair["size"] >= 2)].to_numpy()
    n_bad = min(len(bad), n // 2)
    pick = list(rng.choice(bad, n_bad, replace=False)) if n_bad else []
    rest = good if len(good) else per_pair.index.to_numpy()
    pick += list(rng.choice(rest, min(n - n_bad, len(rest)), replace=False))
    paths = pairs.set_index("pair_id")["path_1"]
    images, titles = [], []
    for pid in pick:
        img = cv2.imread(str(Path(dataroot) / paths[pid]))
        obj = wrong[wrong["pair_id"] == pid]
        pred = (obj["prob"] > threshold).astype(int).to_numpy()
        texts = [("x " if w else "") + f"{p:.2f}" for w, p in zip(obj["wrong"], obj["prob"],
                                                                 strict=True)]
        img = draw_boxes(img, obj[["xmin", "ymin", "xmax", "ymax"]].to_numpy(),
                         label_colors(pred), texts)
        images.append(img)
        titles.append(f"{pid}: {int(obj['wrong'].sum())} wrong of {len(obj)}")
    return images, titles


def confusion_and_pr(results: dict[str, pd.DataFrame], threshold: float = 0.5) -> plt.Figure:
    """Confusion matrix per method and all precision-recall curves (prob vs label)."""
    n = len(results)
    fig, axes = plt.subplots(1, n + 1, figsize=(3.2 * (n + 1), 3.2))
    for ax, (name, df) in zip(axes[:n], results.items(), strict=True):
        cm = np.asarray(metrics(df["label"], df["prob"], threshold)["confusion"])
        ax.imshow(cm, cmap="Blues")
        for (i, j), v in np.ndenumerate(cm):
            ax.text(j, i, str(v), ha="center", va="center",
                    color="white" if v > cm.max() / 2 else "black")
        ax.set_xticks([0, 1], ["still", "moving"])
        ax.set_yticks([0, 1], ["still", "moving"])
        ax.set(xlabel="predicted", ylabel="true", title=name)
    for name, df in results.items():
        curve, ap = pr_curve(df["label"], df["prob"])
        axes[n].plot(curve["recall"], curve["precision"], label=f"{name} (AP {ap:.2f})")
    axes[n].set(xlabel="recall", ylabel="precision", title="precision-recall", xlim=(0, 1),
                ylim=(0, 1.02))
    axes[n].legend(fontsize=7)
    fig.tight_layout()
    return fig


def _bin_ticks(t: pd.DataFrame, key: str) -> list[str]:
    """Tick labels of :func:`f1_by`: the group, its objects and, where the table counts
    them, its scenes, flagged "too few" below :data:`flowmod.metrics.MIN_SCENES`."""
    labels = []
    for i, (k, n) in enumerate(zip(t[key].astype(str), t["n"], strict=True)):
        text = f"{k}\nn={n}"
        if "scenes" in t:
            sc = int(t["scenes"].iloc[i])
            text += f"\n{sc} sc." + (" (too few)" if sc < MIN_SCENES else "")
        labels.append(text)
    return labels


def f1_by(tables: dict[str, pd.DataFrame], key: str, xlabel: str, min_n: int = 10,
          metric: str = "f1") -> plt.Figure:
    """F1 per group (e.g. distance bin) for each method, from :func:`metrics.breakdown`:
    the scene-level 95 % interval as error bars (when the table has one) and the number of
    objects (and scenes, flagged when too few) under each group; groups with fewer than
    ``min_n`` objects are drawn hollow and grey, so an almost empty bin is not read as a
    failure. A group without a mover, where F1 and recall are undefined, shows instead the
    share of its still vehicles called moving (a cross)."""
    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    names = list(tables)
    width = 0.12
    for j, (name, t) in enumerate(tables.items()):
        x = np.arange(len(t)) + (j - (len(names) - 1) / 2) * width
        ok = t["n"].to_numpy() >= min_n
        f1 = t[metric].to_numpy()
        if "ci_lo" in t and metric == "f1":
            err = np.stack([f1 - t["ci_lo"].to_numpy(), t["ci_hi"].to_numpy() - f1])
            ax.errorbar(x[ok], f1[ok], yerr=err[:, ok], fmt="o", ms=4, capsize=2,
                        color=f"C{j}", label=name)
        else:
            ax.plot(x[ok], f1[ok], "o", ms=4, color=f"C{j}", label=name)
        ax.plot(x[~ok], f1[~ok], "o", ms=4, mfc="none", color="0.6")
        still = (t["n_moving"].to_numpy() == 0) if "n_moving" in t else np.zeros(len(t), bool)
        if still.any() and "accuracy" in t:
            ax.plot(x[still], 1 - t["accuracy"].to_numpy()[still], "x", ms=6,
                    color=f"C{j}" if ok[still].all() else "0.6",
                    label="still vehicles called moving (no mover in the group)"
                    if j == 0 else None)
    first = next(iter(tables.values()))
    ax.set_xticks(np.arange(len(first)), _bin_ticks(first, key))
    ylabel = metric if metric != "f1" else "F1"
    if any(ln.get_marker() == "x" for ln in ax.get_lines()):
        ylabel += " (dots); false alarms (crosses)"
    ax.set(xlabel=xlabel, ylabel=ylabel, ylim=(-0.02, 1.05))
    ax.legend(fontsize=7, title=f"hollow grey: fewer than {min_n} objects", title_fontsize=7)
    ax.tick_params(axis="x", labelsize=7)
    fig.tight_layout()
    return fig


def cell_roc(scores: dict[str, np.ndarray], labels: np.ndarray, cell: np.ndarray,
             points: dict[str, tuple[float, float]]) -> plt.Figure:
    """ROC curves of several scores (N,) each: the share of all still vehicles (``labels``
    0) called moving against the share of the movers of ``cell`` (N,) bool recalled, over
    every threshold (``score > t``), in %; ``points``: named operating points (false-alarm
    rate %, recall %), drawn on the curves."""
    fig, ax = plt.subplots(figsize=(4.8, 4.2))
    still = np.asarray(labels) == 0
    for name, sc in scores.items():
        sc = np.asarray(sc, float)
        ts = np.concatenate([[np.inf], np.unique(sc[np.isfinite(sc)])[::-1], [-np.inf]])
        fpr = [(sc[still] > t).mean() * 100 for t in ts]
        tpr = [(sc[cell] > t).mean() * 100 if cell.any() else np.nan for t in ts]
        ax.plot(fpr, tpr, lw=1.2, label=name, drawstyle="steps-post")
    for k, (name, (x, y)) in enumerate(points.items()):
        ax.plot([x], [y], "o^sv"[k % 4], color="k", ms=6, label=name)
    ax.set_xlabel("still vehicles called moving (%)")
    ax.set_ylabel("movers of the cell recalled (%)")
    ax.set_xlim(0, 100)
    ax.set_ylim(0, 101)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return fig


def forest(effects: pd.DataFrame, delta: float | None = None) -> plt.Figure:
    """Every paired effect of the book (rows of :func:`flowmod.chapters.ch14_answers.effects`:
    chapter, comparison, ``ΔF1 (points)``, ``low``, ``high``, verdict) as a point with its
    95 % interval over scenes and training seeds; filled where the interval excludes 0
    (decided: ``A better``, ``B better``), a hollow square where it is ``equivalent``, a
    hollow circle otherwise; one colour per chapter; ``delta`` (points): the band of
    equivalence, shaded; a dashed bar where the interval counts scenes only (an arm with
    one model a fold: column ``interval counts``)."""
    n = len(effects)
    counts = effects["interval counts"] if "interval counts" in effects else None
    fig, ax = plt.subplots(figsize=(7.5, 0.3 * n + 1.2))
    chapters = sorted(effects["chapter"].unique())
    y = np.arange(n)[::-1]
    cols = effects[["ΔF1 (points)", "low", "high"]].to_numpy(float)
    for yi, (d, lo, hi), ch, verdict in zip(y, cols, effects["chapter"], effects["verdict"],
                                           strict=True):
        c = f"C{chapters.index(ch)}"
        err = [[d - lo], [hi - d]] if np.isfinite([lo, hi]).all() else None
        filled = verdict in ("A better", "B better")
        bars = ax.errorbar([d], [yi], xerr=err, fmt="s" if verdict == "equivalent" else "o",
                           ms=5, capsize=2, color=c, mfc=c if filled else "white")
        if err is not None and counts is not None and counts.iloc[n - 1 - yi] == "scenes only":
            bars[2][0].set_linestyle("--")
    if delta:
        ax.axvspan(-delta, delta, color="0.92", zorder=0)
    ax.axvline(0.0, color="0.4", lw=0.8, ls="--")
    ax.set_yticks(y, [f"{ch}: {name}" for ch, name in zip(effects["chapter"],
                                                          effects["comparison"], strict=True)],
                  fontsize=7)
    ax.set_xlabel("ΔF1, A - B (points); bar: 95 % interval over scenes and training seeds; "
                  "filled: decided" + ("; square: equivalent (shaded band)" if delta else "")
                  + ("; dashed: scenes only" if counts is not None else ""),
                  fontsize=8)
    fig.tight_layout()
    return fig


def error_curves(effects: pd.DataFrame, words: dict[str, str],
                 methods: pd.DataFrame | None = None) -> plt.Figure:
    """Chapter 13: ΔF1 (points, degraded arm minus the exact-flow arm) against the realised
    end-point error (px, ``error (px)``: in the box; the ring kind's around it), one line
    per kind (``kind``, named by ``words``) with 95 % interval bars (``ci_lo``, ``ci_hi``);
    ``methods`` (``method``, ``epe_box``, ``measured`` = exact minus method, with
    ``measured_lo``, ``measured_hi``): the real methods' Table 3 differences at their box
    end-point errors, as black diamonds."""
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    for i, (kind, g) in enumerate(effects.groupby("kind", sort=False)):
        x = np.r_[0.0, g["error (px)"].to_numpy(float)]
        d = np.r_[0.0, g["ΔF1 (points)"].to_numpy(float)]
        lo = np.r_[0.0, g["ci_lo"].to_numpy(float)]
        hi = np.r_[0.0, g["ci_hi"].to_numpy(float)]
        ax.errorbar(x + 0.012 * (i - 2.5), d, yerr=[d - lo, hi - d], marker="o", ms=4,
                    capsize=2, color=f"C{i}", label=words.get(kind, kind))
    if methods is not None and len(methods):
        m = methods
        ax.errorbar(m["epe_box"], -m["measured"], yerr=[m["measured_hi"] - m["measured"],
                                                       m["measured"] - m["measured_lo"]],
                    fmt="D", color="k", ms=5, capsize=2, label="real methods (Table 3)")
        for _, r in m.iterrows():
            ax.annotate(r["method"], (r["epe_box"], -r["measured"]), fontsize=7,
                        xytext=(4, -10), textcoords="offset points")
    ax.axhline(0.0, color="0.4", lw=0.8, ls="--")
    ax.set_xlabel("realised mean end-point error (px; in the box, the ring kind around it)")
    ax.set_ylabel("ΔF1 against the exact flow (points)")
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    return fig


def image(path: str | Path) -> Image:
    """A PNG file (a figure :func:`show` wrote) as a displayable object, e.g. for ``glue``."""
    return Image(filename=str(path))


def table(df: pd.DataFrame, precision: int = 1) -> Any:
    """A table as the book shows it: no index column, numbers right-aligned and rounded to
    ``precision`` decimals (units belong in the column names), "-" for an undefined (NaN)
    value."""
    df = df.reset_index(drop=True)
    numeric = [c for c in df.columns if pd.api.types.is_numeric_dtype(df[c])
               and not pd.api.types.is_bool_dtype(df[c])]
    floats = [c for c in numeric if pd.api.types.is_float_dtype(df[c])]
    return (df.style.hide(axis="index").format(na_rep="-")
            .format(precision=precision, subset=floats, na_rep="-")
            .set_properties(subset=numeric, **{"text-align": "right"}))


def scene_clip(dataroot: str | Path, pairs: pd.DataFrame, preds: pd.DataFrame, load_flow,
               width: int = 800, threshold: float = 0.5) -> list[np.ndarray]:
    """Frames of a clip: each pair's frame 1 with boxes coloured by the prediction (blue
    still, red moving), beside its flow; pairs in time order, ``width`` px per half."""
    frames = []
    for row in pairs.sort_values("timestamp_1").itertuples():
        img = cv2.imread(str(Path(dataroot) / row.path_1))
        obj = preds[preds["pair_id"] == row.pair_id]
        pred = (obj["prob"] > threshold).astype(int).to_numpy()
        img = draw_boxes(img, obj[["xmin", "ymin", "xmax", "ymax"]].to_numpy(),
                         label_colors(pred), thickness=4)
        h = int(round(img.shape[0] * width / img.shape[1]))
        small = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
        f = flow_to_color(load_flow(row.pair_id))
        frames.append(side_by_side(small, cv2.resize(f, (width, h),
                                                     interpolation=cv2.INTER_AREA)))
    return frames


def example_frames(sel: Any, dataroot: str | Path, n: int = 4, seed: int = 0,
                   kind: str = "keyframe") -> tuple[list[np.ndarray], list[str]]:
    """``n`` frame-1 images of random pairs with their selected boxes drawn (blue still,
    red moving), and titles."""
    pairs = sel.pairs[sel.pairs["set"] == kind]
    counts = sel.objects[sel.objects["set"] == kind].groupby("pair_id").size()
    rich = pairs[pairs["pair_id"].isin(counts[counts >= 2].index)]
    pick = (rich if len(rich) >= n else pairs).sample(min(n, len(pairs)), random_state=seed)
    images, titles = [], []
    for row in pick.itertuples():
        img = cv2.imread(str(Path(dataroot) / row.path_1))
        if img is None:
            raise FileNotFoundError(f"cannot read image {Path(dataroot) / row.path_1}")
        obj = sel.objects[sel.objects["pair_id"] == row.pair_id]
        boxes = obj[["xmin", "ymin", "xmax", "ymax"]].to_numpy()
        texts = [f"{d:.0f} m {s:.1f} m/s" for d, s in zip(obj["distance"], obj["speed"],
                                                          strict=True)]
        images.append(draw_boxes(img, boxes, label_colors(obj["label"]), texts))
        titles.append(f"{row.pair_id} ({len(obj)} targets)")
    return images, titles


def color_wheel(size: int = 101) -> np.ndarray:
    """(size, size, 3) uint8 RGB legend of the flow colour code: the colour of a flow
    vector pointing from the centre to each pixel, full saturation at the rim."""
    r = np.linspace(-1.0, 1.0, size, dtype=np.float32)
    u, v = np.meshgrid(r, r)
    inside = np.hypot(u, v) <= 1.0
    wheel = flow_to_color(np.stack([u * inside, v * inside], axis=-1), max_flow=1.0)
    wheel[~inside] = 255
    return wheel


def flow_figure(image: np.ndarray, flows: dict[str, np.ndarray], valid: np.ndarray | None = None,
                percentile: float = 95.0) -> tuple[plt.Figure, float]:
    """Figure 1: frame 1 (BGR) and each method's flow on one colour scale, with the colour
    wheel as legend. The scale is the ``percentile`` of the flow magnitude over the pixels
    where the flow is defined and visible (``valid``, from the exact flow, else all), pooled
    over methods, so that one method's outliers do not wash out the others. Returns the
    figure and the scale (px at full saturation)."""
    sel = valid if valid is not None else np.ones(image.shape[:2], bool)
    mags = np.concatenate([np.hypot(f[..., 0], f[..., 1])[sel] for f in flows.values()])
    vmax = float(max(np.percentile(mags, percentile), 1e-3))
    n = len(flows) + 1
    ncols = 2
    nrows = int(np.ceil(n / ncols))
    h, w = image.shape[:2]
    fig, axes = plt.subplots(nrows, ncols, figsize=(13, 13 / ncols * h / w * nrows + 0.5),
                             squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    panels = [("frame 1", image[..., ::-1])] + [
        (name, flow_to_color(f, max_flow=vmax)) for name, f in flows.items()]
    for ax, (title, img) in zip(axes.ravel(), panels, strict=False):
        ax.imshow(img)
        ax.set_title(title, fontsize=9)
    inset = axes.ravel()[1].inset_axes([0.84, 0.02, 0.15, 0.15 * w / h])
    inset.imshow(color_wheel())
    inset.set_title(f"{vmax:.0f} px", fontsize=7, pad=1)
    inset.axis("off")
    fig.tight_layout()
    return fig, vmax
