"""Chapter 01's stages on a generated world: how hard the motion task is, and an example.

The ``example`` stage keeps the exact flow of chapter 01's example pair (the middle scene's
first two keyframes, the frames the chapter shows through the devkit): ``example.npz``.

The ``difficulty`` stage: how hard the motion task is on a generated world.

:func:`naive_rule_report` scores a trivial rule, "mean exact-flow magnitude inside the 2D box
> t" (best t), against the speed label, raw and with the surrounding background flow
subtracted, on the paper's distant objects (:func:`distant_objects`: Table 1, 30-70 m,
visibility '4', selected by :mod:`flowmod.select`). The stage scores it on
``difficulty_pairs`` keyframe pairs of the profile's world (``difficulty.json``).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from joblib import Parallel, delayed

from flowmod import dag, select
from flowmod.artefacts import atomic_path, write_json
from flowmod.params import TABLE1_CATEGORIES, Params, validate
from flowmod.select import description_items
from flowmod.world import gt_flow, is_generated_world, true_velocity

EXCLUDE = ("night", "rain", "lightning")
def usable(description: str, exclude: Iterable[str] = EXCLUDE) -> bool:
    """False if a comma-separated item of the description equals an excluded word (any case)."""
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
    nusc = select.as_nuscenes(nusc_or_dataroot, version)
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


def box_scores(
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


def scene_scores(dataroot: str, version: str, rows: list[dict]) -> list[dict]:
    """``rows`` (objects of one scene) with the two scores of their box in the exact flow
    of their pair and their true speed (m/s) at frame 1."""
    out = []
    by_pair: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        by_pair.setdefault((r["sd_token_1"], r["sd_token_2"]), []).append(r)
    for (s1, s2), objs in by_pair.items():
        flow, valid = gt_flow(dataroot, version, s1, s2)
        for r in objs:
            raw, rel = box_scores(flow, valid, (r["xmin"], r["ymin"], r["xmax"], r["ymax"]))
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
    nusc = None if objects is not None else select.as_nuscenes(nusc_or_dataroot, version)
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
            delayed(scene_scores)(dataroot, version, g) for g in groups
        )
    else:
        parts = [scene_scores(dataroot, version, g) for g in groups]
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


#: The difficulty node's one file: the naive rule's numbers.
REPORT = "difficulty.json"


def read_report(folder: Path) -> dict[str, Any]:
    """The naive rule's numbers of a published ``difficulty`` node."""
    return json.loads((Path(folder) / REPORT).read_text())


def build(b: dag.Build, progress: bool) -> Mapping[str, Any]:
    """Build the ``difficulty`` node: :data:`REPORT` (the rule's numbers)."""
    q = b.params
    report = naive_rule_report(q.dataroot_path, q.version, speed_threshold=q.speed_threshold,
                               max_pairs=q.difficulty_pairs, n_jobs=q.n_jobs)
    write_json(b.start(fresh=True) / REPORT,
               {k: v for k, v in report.items() if k != "table"})
    return {}


def _nodes(p: Params) -> list[dag.Node]:
    return [dag.Node("difficulty")] if is_generated_world(p) else []


#: The difficulty stage: the naive exact-flow rule on a generated world.
STAGE = dag.Stage("difficulty", 2, "01", "difficulty", "the naive exact-flow rule on the world",
                  nodes=_nodes, inputs=lambda n, p: (dag.Node("world"),), build=build,
                  outputs=(REPORT,))


#: The example node's one file: the example pair's sample_data tokens, its exact flow
#: (float16, px) and valid mask.
EXAMPLE = "example.npz"


def example_tokens(dataroot: str | os.PathLike[str], version: str) -> tuple[str, str]:
    """The CAM_FRONT sample_data tokens of the middle scene's first two keyframes (the
    devkit's scene order: ``scene.json``'s)."""
    tables = Path(dataroot) / version
    scenes = json.loads((tables / "scene.json").read_text())
    samples = {r["token"]: r for r in json.loads((tables / "sample.json").read_text())}
    first = samples[scenes[len(scenes) // 2]["first_sample_token"]]
    keys = {r["sample_token"]: r["token"]
            for r in json.loads((tables / "sample_data.json").read_text()) if r["is_key_frame"]}
    return keys[first["token"]], keys[first["next"]]


def read_example(folder: Path) -> tuple[tuple[str, str], np.ndarray, np.ndarray]:
    """A published ``example`` node: ((sd_token_1, sd_token_2), flow (H, W, 2) float32 px,
    valid (H, W) bool)."""
    with np.load(Path(folder) / EXAMPLE) as z:
        return (str(z["tokens"][0]), str(z["tokens"][1])), z["flow"].astype(np.float32), z["valid"]


def build_example(b: dag.Build, progress: bool) -> Mapping[str, Any]:
    """Build the ``example`` node: :data:`EXAMPLE`."""
    q = b.params
    tokens = example_tokens(q.dataroot_path, q.version)
    flow, valid = gt_flow(q.dataroot_path, q.version, *tokens)
    with atomic_path(b.start(fresh=True) / EXAMPLE) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, tokens=np.array(tokens), flow=flow.astype(np.float16), valid=valid)
    return {}


def _example_nodes(p: Params) -> list[dag.Node]:
    return [dag.Node("example")] if is_generated_world(p) else []


#: The example stage: the exact flow of chapter 01's example pair (generated worlds only).
EXAMPLE_STAGE = dag.Stage("example", 1, "01", "example",
                          "the exact flow of chapter 01's example pair", nodes=_example_nodes, inputs=lambda n, p: (dag.Node("world"),),
                          build=build_example, outputs=(EXAMPLE,))
