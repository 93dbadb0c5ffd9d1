"""Boxes drawn on frames with OpenCV only: what the predict CLI needs of the report layer,
kept apart from :mod:`~flowmod.report.viz` (matplotlib, IPython) so that inference on a
server installs neither."""

from __future__ import annotations

import cv2
import numpy as np

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
