"""Chapter 01's backend: what the world contains and how hard the motion task is on it.

* :func:`annotation_table` / :func:`counts_table`: annotations in view by category, distance,
  speed and label;
* :func:`gt_flow_figure`: the example pair with its exact flow (the ``example`` node);
* :func:`devkit_counts` / :func:`devkit_frames`: what the official devkit loads and draws;
* :func:`difficulty`: the published numbers of the difficulty stage
  (:mod:`flowmod.difficulty`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from PIL import Image

from flowmod import pipeline
from flowmod.dag import Node
from flowmod.difficulty import read_example, read_report, usable
from flowmod.flow import flow_to_color
from flowmod.params import Params
from flowmod.select import as_nuscenes

#: How many scenes the devkit's scene table shows.
SCENES_SHOWN = 12
#: Bins of the world's distance histogram (m): 0 to 100 m in 5 m steps.
DISTANCE_BINS = np.arange(0, 105, 5)


def difficulty(p: Params) -> dict[str, Any]:
    """The difficulty node's numbers (:func:`flowmod.difficulty.read_report`)."""
    return read_report(pipeline.published(p, Node("difficulty")))


def annotation_table(
    nusc_or_dataroot: Any, version: str = "v1.0-synth", speed_threshold: float = 2.0
) -> pd.DataFrame:
    """One row per keyframe annotation with any corner in the CAM_FRONT image.

    Columns: scene, usable (not night/rain), category, distance (m), visibility, speed (m/s,
    devkit ``box_velocity``), label, attribute.
    """
    from nuscenes.utils.geometry_utils import BoxVisibility

    nusc = as_nuscenes(nusc_or_dataroot, version)
    rows = []
    for scene in nusc.scene:
        ok = usable(scene["description"])
        tok = scene["first_sample_token"]
        while tok:
            sample = nusc.get("sample", tok)
            sd = nusc.get("sample_data", sample["data"]["CAM_FRONT"])
            ego = np.array(nusc.get("ego_pose", sd["ego_pose_token"])["translation"])
            _, boxes, _ = nusc.get_sample_data(sd["token"], box_vis_level=BoxVisibility.ANY)
            seen = {b.token for b in boxes}
            for ann_token in sample["anns"]:
                if ann_token not in seen:
                    continue
                ann = nusc.get("sample_annotation", ann_token)
                v = nusc.box_velocity(ann_token)
                speed = float(np.linalg.norm(v[:2])) if np.all(np.isfinite(v)) else float("nan")
                attrs = [nusc.get("attribute", a)["name"] for a in ann["attribute_tokens"]]
                rows.append(
                    {
                        "scene": scene["name"],
                        "usable": ok,
                        "category": ann["category_name"],
                        "distance": float(np.linalg.norm(np.array(ann["translation"]) - ego)),
                        "visibility": ann["visibility_token"],
                        "speed": speed,
                        "label": int(speed >= speed_threshold) if np.isfinite(speed) else -1,
                        "attribute": attrs[0] if attrs else "",
                    }
                )
            tok = sample["next"]
    return pd.DataFrame(rows)


def counts_table(
    annotations: pd.DataFrame, bins: tuple[float, ...] = (0, 30, 70, 1000)
) -> pd.DataFrame:
    """Counts of in-view annotations by category x distance bin, with the moving share.

    ``annotations``: from :func:`annotation_table`.
    """
    a = annotations.copy()
    labels = [
        f"{int(lo)}-{int(hi)} m" if hi < 1000 else f">{int(lo)} m"
        for lo, hi in zip(bins[:-1], bins[1:], strict=True)
    ]
    a["distance_bin"] = pd.cut(a["distance"], bins=list(bins), labels=labels, right=False)
    t = a.pivot_table(
        index="category",
        columns="distance_bin",
        values="scene",
        aggfunc="count",
        fill_value=0,
        observed=False,
    )
    t["total"] = t.sum(axis=1)
    known = a[a["label"] >= 0]
    t["moving %"] = (100 * known.groupby("category")["label"].mean()).round(1)
    return t.sort_values("total", ascending=False)


def gt_flow_figure(p: Params):
    """A 2x2 matplotlib figure of the ``example`` node (:mod:`flowmod.difficulty`): frame 1,
    frame 2, their exact flow (colour) and its valid mask."""
    tokens, flow, valid = read_example(pipeline.published(p, Node("example")))
    sd = {r["token"]: r for r in json.loads(
        (p.dataroot_path / p.version / "sample_data.json").read_text())}
    fig, axes = plt.subplots(2, 2, figsize=(12, 7))
    for ax, tok, title in ((axes[0, 0], tokens[0], "frame 1"), (axes[0, 1], tokens[1], "frame 2")):
        ax.imshow(Image.open(p.dataroot_path / sd[tok]["filename"]))
        ax.set_title(f"{title}  t = {sd[tok]['timestamp']} us")
    axes[1, 0].imshow(flow_to_color(flow))
    mag = np.linalg.norm(flow, axis=2)
    axes[1, 0].set_title(f"GT flow (max |flow| {mag[valid].max() if valid.any() else 0:.1f} px)")
    axes[1, 1].imshow(valid, cmap="gray")
    axes[1, 1].set_title(f"valid ({100 * valid.mean():.1f} %)")
    for ax in axes.ravel():
        ax.axis("off")
    fig.tight_layout()
    return fig


def devkit_counts(nusc: Any) -> dict[str, int]:
    """How many scenes, samples, CAM_FRONT frames, annotations and instances the devkit
    loaded."""
    return {"scenes": len(nusc.scene), "samples": len(nusc.sample),
            "CAM_FRONT frames": len(nusc.sample_data),
            "annotations": len(nusc.sample_annotation), "instances": len(nusc.instance)}


def as_table(mapping: dict[str, Any], key: str, value: str) -> pd.DataFrame:
    """A flat mapping as a two-column table (floats rounded to 3 decimals)."""
    return pd.DataFrame({key: list(mapping),
                         value: [round(v, 3) if isinstance(v, float) else v
                                 for v in mapping.values()]})


def devkit_frames(nusc: Any, folder: str | os.PathLike[str]) -> tuple[dict, list[np.ndarray]]:
    """The first two keyframes of the middle scene as the devkit's ``render_sample_data``
    draws them (boxes in the devkit's colours), saved under ``folder``: (first sample,
    [BGR images])."""
    scene = nusc.scene[len(nusc.scene) // 2]
    first = nusc.get("sample", scene["first_sample_token"])
    images = []
    for i, sample in enumerate([first, nusc.get("sample", first["next"])]):
        out = Path(folder) / f"devkit_{i}.png"
        nusc.render_sample_data(sample["data"]["CAM_FRONT"], out_path=str(out), verbose=False)
        plt.close("all")
        images.append(plt.imread(out)[..., 2::-1])
    return first, images
