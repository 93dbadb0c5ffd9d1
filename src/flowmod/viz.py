"""Figures shared by several chapters (matplotlib, Agg-safe)."""

from __future__ import annotations

from pathlib import Path

import cv2
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch

#: The pipeline stages in data-flow order: (chapter, label, artefact).
PIPELINE = [
    ("01", "world /\nnuScenes", "dataroot"),
    ("02", "select\n(Table 1)", "pairs, objects"),
    ("03", "optical\nflow", "flow/<method>"),
    ("04", "labels\n(eq. 1)", "label, speed"),
    ("05", "crops\n(x3, resize)", "crops/<method>"),
    ("06", "train\nResNet18", "models/"),
    ("07", "evaluate\n(Table 3)", "metrics/"),
    ("08", "generalise\n(Table 4)", "metrics/general"),
]


def show(fig: plt.Figure, path: str | Path, dpi: int = 110) -> None:
    """Save ``fig`` as a PNG file, close it, and display the file in the notebook.

    Figures enter the book as files (``runs/<profile>/figures/``), shown once.
    """
    from IPython.display import Image, display

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    display(Image(filename=str(path)))


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


#: Box colours (BGR for OpenCV): the paper's Figure 2 convention, blue = still, red = moving.
STILL_BGR = (255, 120, 0)
MOVING_BGR = (0, 0, 255)
OTHER_BGR = (0, 200, 255)


def draw_boxes(
    image: np.ndarray, boxes: np.ndarray, colors: list[tuple[int, int, int]] | None = None,
    texts: list[str] | None = None, thickness: int = 3,
) -> np.ndarray:
    """A copy of ``image`` (H, W, 3) uint8 BGR with ``boxes`` (N, 4) xmin, ymin, xmax, ymax px
    drawn as rectangles, optionally with a label above each."""
    out = image.copy()
    for i, (x0, y0, x1, y1) in enumerate(np.asarray(boxes, dtype=float).round().astype(int)):
        c = colors[i] if colors else OTHER_BGR
        cv2.rectangle(out, (x0, y0), (x1, y1), c, thickness)
        if texts:
            cv2.putText(out, texts[i], (x0, max(y0 - 6, 12)), cv2.FONT_HERSHEY_SIMPLEX, 0.8, c, 2)
    return out


def label_colors(labels: np.ndarray) -> list[tuple[int, int, int]]:
    """Figure-2 colours for 0/1 labels (blue still, red moving)."""
    return [MOVING_BGR if int(v) == 1 else STILL_BGR for v in labels]


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
    """For each object row: the frame-1 image around its box (square, ``scale`` x the box's
    longer side, edge-padded), box drawn in its label colour, resized to ``size`` px."""
    paths = pairs.set_index("pair_id")["path_1"]
    out = []
    for row in objects.itertuples():
        img = cv2.imread(str(Path(dataroot) / paths[row.pair_id]))
        if img is None:
            raise FileNotFoundError(f"cannot read {Path(dataroot) / paths[row.pair_id]}")
        img = draw_boxes(img, np.array([[row.xmin, row.ymin, row.xmax, row.ymax]]),
                         label_colors([row.label]), thickness=1)
        cx, cy = (row.xmin + row.xmax) / 2, (row.ymin + row.ymax) / 2
        half = max(row.xmax - row.xmin, row.ymax - row.ymin) * scale / 2
        x0, y0 = int(round(cx - half)), int(round(cy - half))
        side = max(int(round(2 * half)), 2)
        pad = side + 1
        padded = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
        crop = padded[y0 + pad:y0 + pad + side, x0 + pad:x0 + pad + side]
        out.append(cv2.resize(crop, (size, size), interpolation=cv2.INTER_LINEAR))
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
