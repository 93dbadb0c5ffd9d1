"""Notebook-01 helpers: what the world contains and how hard the motion task is on it.

* :func:`distant_objects` — the paper's keyframe-pair objects (Table 1: 30-70 m from the ego
  pose, visibility '4', all 8 corners inside the image in both keyframes) with their 2D boxes
  and labels, computed with the devkit only (works on real nuScenes too).
* :func:`naive_rule_report` — F1 of "mean GT-flow magnitude inside the 2D box > t" (best t)
  against the speed label, raw and with the surrounding background flow subtracted.
* :func:`annotation_table` / :func:`counts_table` — annotations in view by category, distance,
  speed and label.
* :func:`gt_flow_figure` — a frame pair with its exact flow (synthetic worlds).

All functions are pure (they return data frames, dicts or figures; nothing is written).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from flowmod.params import TABLE1_CATEGORIES

EXCLUDE = ("night", "rain", "lightning")


def _nusc(nusc_or_dataroot: Any, version: str):
    if isinstance(nusc_or_dataroot, (str, os.PathLike)):
        from nuscenes.nuscenes import NuScenes

        return NuScenes(version=version, dataroot=str(nusc_or_dataroot), verbose=False)
    return nusc_or_dataroot


def usable(description: str, exclude: Iterable[str] = EXCLUDE) -> bool:
    """False if a comma-separated item of the description equals an excluded word (any case)."""
    from flowmod.select import description_items

    bad = {e.strip().lower() for e in exclude}
    return not any(item in bad for item in description_items(description))


def distant_objects(
    nusc_or_dataroot: Any,
    version: str = "v1.0-synth",
    *,
    min_distance: float = 30.0,
    max_distance: float = 70.0,
    categories: Iterable[str] = TABLE1_CATEGORIES,
    visibilities: Iterable[str] = ("4",),
    exclude: Iterable[str] = EXCLUDE,
    speed_threshold: float = 2.0,
) -> pd.DataFrame:
    """One row per (consecutive keyframe pair, vehicle qualifying in both keyframes): the
    paper's Table-1 objects of all usable scenes, selected by :mod:`flowmod.select` (the same
    code as the filtering stage), with the pair's sd_token_1/2 and timestamp_1/2 (us)."""
    from flowmod import select
    from flowmod.params import validate

    nusc = _nusc(nusc_or_dataroot, version)
    p = validate({"min_distance": min_distance, "max_distance": max_distance,
                  "categories": list(categories), "visibility_tokens": list(visibilities),
                  "exclude_descriptions": list(exclude), "speed_threshold": speed_threshold})
    scenes = select.filter_scenes(select.scene_table(nusc), p.exclude_descriptions)
    kept = scenes[scenes["excluded_by"] == ""].assign(split="all")
    pairs, objs = select.keyframe_set(nusc, kept, p, progress=False)
    if objs.empty:
        return objs
    cols = ["pair_id", "sd_token_1", "sd_token_2", "timestamp_1", "timestamp_2"]
    return objs.merge(pairs[cols], on="pair_id", how="left")


def best_f1(scores: np.ndarray, labels: np.ndarray) -> tuple[float, float]:
    """Best F1 over thresholds of "score > t" and that t; (nan, nan) without positives."""
    scores = np.asarray(scores, float)
    labels = np.asarray(labels, int)
    pos = int(labels.sum())
    if pos == 0 or scores.size == 0:
        return float("nan"), float("nan")
    order = np.argsort(-scores, kind="stable")
    s, y = scores[order], labels[order]
    tp = np.cumsum(y)
    k = np.arange(1, s.size + 1)
    last = np.r_[s[1:] != s[:-1], True]  # only cut between distinct scores
    f1 = np.where(last, 2 * tp / (k + pos), -1.0)
    i = int(np.argmax(f1))
    t = 0.5 * (s[i] + s[i + 1]) if i + 1 < s.size else s[i] - 1e-6
    # predicting everything moving is also a candidate (t below the minimum)
    return float(f1[i]), float(t)


def _box_scores(
    flow: np.ndarray, valid: np.ndarray, box: tuple[float, float, float, float]
) -> tuple[float, float]:
    """(mean |flow| in the box, |mean flow in box - median flow of the surrounding ring|)."""
    H, W = valid.shape
    x0, y0, x1, y1 = box
    xa, xb = max(int(math.floor(x0)), 0), min(int(math.ceil(x1)) + 1, W)
    ya, yb = max(int(math.floor(y0)), 0), min(int(math.ceil(y1)) + 1, H)
    f = flow[ya:yb, xa:xb].reshape(-1, 2)
    m = valid[ya:yb, xa:xb].ravel()
    if m.sum() >= 4:
        f = f[m]
    raw = float(np.linalg.norm(f, axis=1).mean())
    # ring: the paper's 3x square crop around the box, minus the box
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    half = 1.5 * max(x1 - x0, y1 - y0)
    ra, rb = max(int(cx - half), 0), min(int(cx + half) + 1, W)
    rc, rd = max(int(cy - half), 0), min(int(cy + half) + 1, H)
    ring = np.ones((rd - rc, rb - ra), bool)
    ring[max(ya - rc, 0) : max(yb - rc, 0), max(xa - ra, 0) : max(xb - ra, 0)] = False
    ring &= valid[rc:rd, ra:rb]
    if ring.sum() >= 4:
        bg = np.median(flow[rc:rd, ra:rb][ring], axis=0)
    else:
        bg = np.zeros(2)
    rel = float(np.linalg.norm(f.mean(axis=0) - bg))
    return raw, rel


def _scene_scores(dataroot: str, version: str, rows: list[dict]) -> list[dict]:
    from flowmod.world import gt_flow, true_velocity

    out = []
    by_pair: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        by_pair.setdefault((r["sd_token_1"], r["sd_token_2"]), []).append(r)
    for (s1, s2), objs in by_pair.items():
        flow, valid = gt_flow(dataroot, version, s1, s2)
        for r in objs:
            raw, rel = _box_scores(flow, valid, (r["xmin"], r["ymin"], r["xmax"], r["ymax"]))
            v = true_velocity(dataroot, version, r["instance_token"], r["timestamp_1"])
            out.append(
                {**r, "score_raw": raw, "score_rel": rel, "true_speed": float(np.linalg.norm(v))}
            )
    return out


def naive_rule_report(
    nusc_or_dataroot: Any,
    version: str = "v1.0-synth",
    *,
    objects: pd.DataFrame | None = None,
    dataroot: str | os.PathLike[str] | None = None,
    speed_threshold: float = 2.0,
    max_pairs: int | None = None,
    n_jobs: int = 1,
    seed: int = 0,
) -> dict:
    """How well a trivial rule separates moving from still distant vehicles (synthetic world).

    For every distant object (see :func:`distant_objects`) the exact flow of its keyframe pair
    gives two scores: ``raw`` = mean |flow| (px) inside the 2D box; ``rel`` = |mean flow in the
    box - median flow in the surrounding 3x square| (ego motion removed, as far as the
    background predicts it). The rule "score > t" is scored by F1 at its best t against the
    label from the true speed at frame 1 (>= ``speed_threshold``) and against the paper's
    forward-difference label. Returns a dict with the numbers and ``table`` (per object).
    ``max_pairs`` subsamples pairs (seeded) to save time.
    """
    from joblib import Parallel, delayed

    nusc = None if objects is not None else _nusc(nusc_or_dataroot, version)
    if dataroot is None:
        dataroot = (
            nusc_or_dataroot
            if isinstance(nusc_or_dataroot, (str, os.PathLike))
            else nusc_or_dataroot.dataroot
        )
    dataroot = str(dataroot)
    if objects is None:
        objects = distant_objects(nusc, version, speed_threshold=speed_threshold)
    if objects.empty:
        return {"n_objects": 0, "table": objects}
    objs = objects
    if max_pairs is not None:
        pairs = objs["sd_token_1"].unique()
        if len(pairs) > max_pairs:
            keep = np.random.default_rng(seed).choice(pairs, max_pairs, replace=False)
            objs = objs[objs["sd_token_1"].isin(set(keep))]
    groups = [g.to_dict("records") for _, g in objs.groupby("scene", sort=True)]
    if n_jobs > 1 and len(groups) > 1:
        parts = Parallel(n_jobs=n_jobs)(
            delayed(_scene_scores)(dataroot, version, g) for g in groups
        )
    else:
        parts = [_scene_scores(dataroot, version, g) for g in groups]
    table = pd.DataFrame([r for p in parts for r in p])
    table["true_label"] = (table["true_speed"] >= speed_threshold).astype(int)
    out: dict[str, Any] = {
        "n_objects": int(len(table)),
        "n_pairs": int(table["sd_token_1"].nunique()),
        "n_scenes": int(table["scene"].nunique()),
        "moving_share": float(table["true_label"].mean()),
    }
    for lab in ("true_label", "label"):
        for sc in ("raw", "rel"):
            f1, t = best_f1(table[f"score_{sc}"].to_numpy(), table[lab].to_numpy())
            key = f"{sc}_vs_{'true' if lab == 'true_label' else 'eq1'}"
            out[f"f1_{key}"] = f1
            out[f"threshold_{key}"] = t
    out["label_agreement"] = float((table["label"] == table["true_label"]).mean())
    out["table"] = table
    return out


def annotation_table(
    nusc_or_dataroot: Any, version: str = "v1.0-synth", speed_threshold: float = 2.0
) -> pd.DataFrame:
    """One row per keyframe annotation with any corner in the CAM_FRONT image.

    Columns: scene, usable (not night/rain), category, distance (m), visibility, speed (m/s,
    devkit ``box_velocity``), label, attribute.
    """
    from nuscenes.utils.geometry_utils import BoxVisibility

    nusc = _nusc(nusc_or_dataroot, version)
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


def gt_flow_figure(
    dataroot: str | os.PathLike[str],
    version: str,
    sd_token_1: str,
    sd_token_2: str,
    boxes: pd.DataFrame | None = None,
):
    """A 2x2 matplotlib figure: frame 1, frame 2, GT flow (colour), valid mask.

    ``boxes``: optional rows with xmin, ymin, xmax, ymax (px) and label to draw on frame 1.
    """
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle
    from PIL import Image

    from flowmod.flow import flow_to_color
    from flowmod.world import gt_flow

    sd = {
        r["token"]: r
        for r in json.loads((Path(dataroot) / version / "sample_data.json").read_text())
    }
    flow, valid = gt_flow(dataroot, version, sd_token_1, sd_token_2)
    fig, axes = plt.subplots(2, 2, figsize=(12, 7))
    for ax, tok, title in (
        (axes[0, 0], sd_token_1, "frame 1"),
        (axes[0, 1], sd_token_2, "frame 2"),
    ):
        ax.imshow(Image.open(Path(dataroot) / sd[tok]["filename"]))
        ax.set_title(f"{title}  t = {sd[tok]['timestamp']} us")
    axes[1, 0].imshow(flow_to_color(flow))
    mag = np.linalg.norm(flow, axis=2)
    axes[1, 0].set_title(f"GT flow (max |flow| {mag[valid].max() if valid.any() else 0:.1f} px)")
    axes[1, 1].imshow(valid, cmap="gray")
    axes[1, 1].set_title(f"valid ({100 * valid.mean():.1f} %)")
    if boxes is not None:
        for _, b in boxes.iterrows():
            col = "red" if b.get("label", 0) == 1 else "deepskyblue"
            axes[0, 0].add_patch(
                Rectangle(
                    (b["xmin"], b["ymin"]),
                    b["xmax"] - b["xmin"],
                    b["ymax"] - b["ymin"],
                    fill=False,
                    color=col,
                    lw=1.5,
                )
            )
    for ax in axes.ravel():
        ax.axis("off")
    fig.tight_layout()
    return fig


#: Keyframe pairs (seeded sample) on which the difficulty node scores the naive rule: the
#: exact flow of every pair would cost as much as the flow stage itself.
DIFFICULTY_PAIRS = 240


def difficulty_report(params: Any, nusc: Any = None, progress: bool = True) -> dict:
    """:func:`naive_rule_report`'s numbers for a profile, on :data:`DIFFICULTY_PAIRS` keyframe
    pairs drawn with a fixed seed: the ``difficulty`` node of :mod:`flowmod.dag`
    (``<run_dir>/difficulty/difficulty.json``), recomputed only when the world or the speed
    threshold changed."""
    from flowmod import dag
    from flowmod.artefacts import write_json

    b = dag.begin(params, dag.Node("difficulty"))
    if not b.up_to_date:
        q = b.params
        report = naive_rule_report(nusc or q.dataroot_path, q.version,
                                   speed_threshold=q.speed_threshold,
                                   max_pairs=DIFFICULTY_PAIRS, n_jobs=q.n_jobs)
        write_json(b.start(fresh=True) / "difficulty.json",
                   {k: v for k, v in report.items() if k != "table"})
        b.publish()
    return json.loads((b.final / "difficulty.json").read_text())


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
    import matplotlib.pyplot as plt

    scene = nusc.scene[len(nusc.scene) // 2]
    first = nusc.get("sample", scene["first_sample_token"])
    images = []
    for i, sample in enumerate([first, nusc.get("sample", first["next"])]):
        out = Path(folder) / f"devkit_{i}.png"
        nusc.render_sample_data(sample["data"]["CAM_FRONT"], out_path=str(out), verbose=False)
        plt.close("all")
        images.append(plt.imread(out)[..., 2::-1])
    return first, images
