"""Figures shared by several chapters (matplotlib, Agg-safe)."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
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


def show(fig: plt.Figure, path: str | Path, dpi: int = 110) -> Path:
    """Save ``fig`` as a PNG file, close it, and display the file in the notebook.

    Figures enter the book as files (``runs/<profile>/figures/``), shown once.
    """
    from IPython.display import Image, display

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    display(Image(filename=str(path)))
    return path


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
