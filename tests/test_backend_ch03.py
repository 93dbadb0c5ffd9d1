"""Chapter 03's backend (:mod:`flowmod.chapters.ch03_flow`) in quick tests, for mutation
testing: mutmut runs only the quick tests, and the chapter is otherwise checked only by the
slow notebook runs.

The flow nodes are written here by hand (an ``index.parquet``, a manifest and per-pair flow
files in a pool, read back through the real :class:`flowmod.flow.FlowReader`); each stored
flow is a constant field, so that the expected end-point errors, Fl-all shares and box
medians are computed here with numpy from the tiny world's exact flow (or from hand-made
arrays), not with flowmod's metrics.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd
import pytest

from flowmod import world
from flowmod.artefacts import write_manifest
from flowmod.chapters import ch03_flow as ch03
from flowmod.flow import FlowReader, accuracy
from flowmod.params import load_profile

#: The stored flow files are kept at 1/100 of the 1600 x 900 image (16 x 9 px): small files,
#: and a constant field restores to the same constant at full size.
STORE_SCALE = 0.01
#: The accuracy table's columns, in order.
ACCURACY_COLUMNS = ["set", "vehicles", "method", "EPE all (px)", "Fl-all (%)", "EPE boxes (px)",
                    "EPE boxes 95% CI, scenes (px)", "Fl-all boxes (%)", "s / pair", "pairs"]


def _reader(root, method: str, part: str, flows: dict[str, tuple[float, float]],
            seconds: list[float]) -> FlowReader:
    """A published ``flow[<method>/<part>]`` node written by hand: pair -> constant flow
    (u, v) px, with each pair's estimation seconds; read through the real FlowReader."""
    folder, pool = root / method / part, root / method / "pool"
    folder.mkdir(parents=True)
    pool.mkdir(parents=True, exist_ok=True)
    files = []
    for pid, uv in flows.items():
        files.append(f"{part}-{pid}.npy")
        small = np.empty((9, 16, 2), np.float32)
        small[...] = uv
        np.save(pool / files[-1], small)
    pd.DataFrame({"pair_id": pd.Series(list(flows), dtype=object),
                  "file": pd.Series(files, dtype=object),
                  "seconds": pd.Series(seconds, dtype=float)}).to_parquet(folder / "index.parquet")
    write_manifest(folder / "manifest.json", {"fingerprint": f"hand-made {method}/{part}",
                                              "store_scale": STORE_SCALE})
    return FlowReader(folder, pool, method, part)


def _frames(root, version: str) -> dict[str, list[str]]:
    """Scene name -> its CAM_FRONT keyframes' sample_data tokens in time order, read from the
    world's tables (quicker than loading the devkit)."""
    table = lambda name: json.loads((root / version / f"{name}.json").read_text())  # noqa: E731
    scene_of = {s["token"]: s["scene_token"] for s in table("sample")}
    name = {s["token"]: s["name"] for s in table("scene")}
    out: dict[str, list[tuple[int, str]]] = {}
    for sd in table("sample_data"):
        if sd["is_key_frame"] and sd["filename"].startswith("samples/CAM_FRONT/"):
            out.setdefault(name[scene_of[sd["sample_token"]]], []).append(
                (sd["timestamp"], sd["token"]))
    return {k: [tok for _, tok in sorted(v)] for k, v in out.items()}


def _box_mask(boxes, shape) -> np.ndarray:
    """Pixels inside integer boxes (xmin, ymin, xmax, ymax), both ends inclusive."""
    mask = np.zeros(shape[:2], bool)
    for x0, y0, x1, y1 in boxes:
        mask[y0:y1 + 1, x0:x1 + 1] = True
    return mask


def _scores(uv, gt: np.ndarray, valid: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """EPE and Fl-all (KITTI: error > 3 px and > 5 % of the true magnitude) of the constant
    flow ``uv`` over the valid pixels, and over the valid pixels in ``mask``."""
    g = gt.astype(np.float64)
    err = np.hypot(uv[0] - g[..., 0], uv[1] - g[..., 1])
    out = (err > 3.0) & (err > 0.05 * np.hypot(g[..., 0], g[..., 1]))
    sel = valid & mask
    return {"epe": err[valid].mean(), "fl": 100 * out[valid].mean(),
            "epe_box": err[sel].mean() if sel.any() else np.nan,
            "fl_box": 100 * out[sel].mean() if sel.any() else np.nan}


@pytest.fixture(scope="module")
def frames(tiny_world):
    return _frames(*tiny_world)


def test_run_summary_has_one_row_per_method_and_part_with_the_median_seconds(tmp_path):
    """run_summary: one row per method and part in the readers' order, the pairs each node
    stores and the median of its seconds (NaN ones left out; NaN for a node without pairs)."""
    readers = {
        "dis": {"keyframe": _reader(tmp_path, "dis", "keyframe",
                                    {"a": (0, 0), "b": (0, 0), "c": (0, 0)}, [0.5, 3.0, 1.0]),
                "general": _reader(tmp_path, "dis", "general", {}, [])},
        "raft": {"keyframe": _reader(tmp_path, "raft", "keyframe",
                                     {"a": (0, 0), "b": (0, 0)}, [2.0, np.nan]),
                 "general": _reader(tmp_path, "raft", "general",
                                    {"a": (0, 0), "b": (0, 0), "c": (0, 0), "d": (0, 0)},
                                    [4.0, 1.0, 2.0, 8.0])},
    }
    got = ch03.run_summary(readers)
    assert list(got.columns) == ["method", "part", "pairs", "median s / pair"]
    assert got["method"].tolist() == ["dis", "dis", "raft", "raft"]
    assert got["part"].tolist() == ["keyframe", "general", "keyframe", "general"]
    assert got["pairs"].tolist() == [3, 0, 2, 4]
    med = got["median s / pair"].tolist()
    assert med[0] == 1.0 and np.isnan(med[1]) and med[2] == 2.0 and med[3] == 3.0


def test_flowcheck_rows_score_each_method_on_the_same_drawn_pairs(tiny_world, frames, tmp_path):
    """The flowcheck node's rows (``accuracy.measure``) as chapter 03's table shows them
    (``accuracy_table``): per set (keyframe: vehicles min-max distance; general: 0 to
    min_distance, both ends inclusive) and method, EPE / Fl-all over the valid pixels of
    n_pairs pairs drawn with the seed among those every method stores, and inside the boxes
    of that pair's vehicles in the set's range (a pair without one leaves the box scores);
    the scene interval of the box EPE; the median seconds of the part's node (NaN, without
    a RuntimeWarning, where it has none; so too the box scores of a set without a box)."""
    root, version = tiny_world
    p = load_profile("smoke", dataroot=str(root), version=version)
    assert (p.min_distance, p.max_distance) == (30.0, 70.0)
    # every pair between frames of one world scene (each frame rendered once, kept by the
    # world's cache); the scene column, which the interval groups by, names four scenes
    f = frames["synth-0000"]
    pairs = pd.DataFrame([
        ("kA", "keyframe", "scene-a", f[1], f[0]),
        ("gA", "general", "scene-c", f[2], f[1]),
        ("kB", "keyframe", "scene-a", f[0], f[1]),
        ("kC", "keyframe", "scene-b", f[1], f[2]),
        ("gB", "general", "scene-c", f[0], f[2]),
        ("kD", "keyframe", "scene-b", f[2], f[1]),  # not in every reader: never drawn
        ("gC", "general", "scene-d", f[2], f[0]),
    ], columns=["pair_id", "set", "scene", "sd_token_1", "sd_token_2"])
    objects = pd.DataFrame([  # pair, distance (m), box (px, inclusive)
        ("kA", 50.0, (700, 380, 799, 459)), ("kA", 75.0, (200, 420, 359, 539)),
        ("kA", 29.5, (1200, 400, 1299, 499)), ("kA", 10.0, (900, 500, 999, 599)),
        ("kB", 30.0, (600, 420, 699, 499)), ("kB", 70.0, (1000, 380, 1079, 449)),
        ("kB", 70.5, (100, 450, 299, 599)),
        ("kC", 60.0, (760, 400, 859, 479)), ("kC", 12.0, (300, 500, 499, 649)),
        ("gA", 31.0, (900, 400, 999, 479)), ("gA", 15.0, (500, 500, 699, 699)),
        ("gB", 30.0, (1100, 450, 1299, 599)), ("gB", 30.5, (200, 450, 399, 599)),
        ("gB", 0.5, (500, 500, 699, 699)),
        ("gC", 45.0, (700, 400, 799, 479)),
    ], columns=["pair_id", "distance", "box"])
    objects[["xmin", "ymin", "xmax", "ymax"]] = objects["box"].tolist()
    objects = objects.drop(columns="box")
    rng = np.random.default_rng(5)
    uv = {m: {pid: tuple(rng.uniform(-4, 4, 2).round(2)) for pid in pairs["pair_id"]}
          for m in ("dis", "raft")}
    kf, gen = ["kA", "kB", "kC", "kD"], ["gA", "gB", "gC"]
    readers = {
        "dis": {"keyframe": _reader(tmp_path, "dis", "keyframe",
                                    {k: uv["dis"][k] for k in kf[:3]}, [0.5, np.nan, 1.5]),
                "general": _reader(tmp_path, "dis", "general", {k: uv["dis"][k] for k in gen},
                                   [np.nan] * 3)},
        "raft": {"keyframe": _reader(tmp_path, "raft", "keyframe",
                                     {k: uv["raft"][k] for k in kf}, [2.0, 4.0, 3.0, 10.0]),
                 "general": _reader(tmp_path, "raft", "general",
                                    {k: uv["raft"][k] for k in gen}, [1.0, 2.0, 3.0])},
    }
    seed = 4
    with warnings.catch_warnings():  # no mean of nothing, no median of NaN only
        warnings.simplefilter("error", RuntimeWarning)
        rows = accuracy.measure(root, version, pairs, objects, readers, min_distance=30.0,
                                max_distance=70.0, n_pairs=2, seed=seed)
        got = ch03.accuracy_table(p, rows, readers)

    draw = np.random.default_rng(seed)  # the keyframe set's draw, then the general set's
    picked = {"keyframe": list(draw.choice(np.array(kf[:3]), size=2, replace=False)),
              "general": list(draw.choice(np.array(gen), size=2, replace=False))}
    # both scenes in the keyframe interval; in the general set a pair without a vehicle in
    # range and one with a vehicle at 0.5 m
    assert sorted(picked["keyframe"]) == ["kB", "kC"] and sorted(picked["general"]) == [
        "gB", "gC"]
    scene = pairs.set_index("pair_id")["scene"]
    ranges = {"keyframe": (30.0, 70.0), "general": (0.0, 30.0)}
    want = []
    for kind in ("keyframe", "general"):
        lo, hi = ranges[kind]
        truth = {pid: world.gt_flow(root, version, *pairs.set_index("pair_id").loc[
            pid, ["sd_token_1", "sd_token_2"]]) for pid in picked[kind]}
        for m, secs in (("dis", {"keyframe": 1.0, "general": np.nan}),
                        ("raft", {"keyframe": 3.5, "general": 2.0})):
            per_pair = {}
            for pid, (gt, valid) in truth.items():
                o = objects[(objects["pair_id"] == pid) & (objects["distance"] >= lo)
                            & (objects["distance"] <= hi)]
                boxes = o[["xmin", "ymin", "xmax", "ymax"]].to_numpy()
                per_pair[pid] = _scores(uv[m][pid], gt, valid, _box_mask(boxes, gt.shape))
            boxed = [pid for pid in per_pair if not np.isnan(per_pair[pid]["epe_box"])]
            by_scene = pd.Series({pid: per_pair[pid]["epe_box"] for pid in boxed}).groupby(
                scene[boxed]).mean()
            n_sc = len(by_scene)
            want.append({
                "set": kind, "vehicles": f"{lo:g}-{hi:g} m", "method": m,
                "EPE all (px)": np.mean([v["epe"] for v in per_pair.values()]),
                "Fl-all (%)": np.mean([v["fl"] for v in per_pair.values()]),
                "EPE boxes (px)": np.mean([per_pair[k]["epe_box"] for k in boxed]),
                # 2000 draws of at most 3 scenes: the 2.5 % and 97.5 % percentiles are the
                # lowest and highest single-scene means
                "EPE boxes 95% CI, scenes (px)":
                    f"{by_scene.min():.2f}-{by_scene.max():.2f} ({n_sc} scenes: too few)",
                "Fl-all boxes (%)": np.mean([per_pair[k]["fl_box"] for k in boxed]),
                "s / pair": secs[kind], "pairs": 2})
    want = pd.DataFrame(want)
    assert list(got.columns) == ACCURACY_COLUMNS
    assert got[["set", "vehicles", "method", "EPE boxes 95% CI, scenes (px)", "pairs"]].equals(
        want[["set", "vehicles", "method", "EPE boxes 95% CI, scenes (px)", "pairs"]])
    assert want.loc[0, "vehicles"] == "30-70 m" and want.loc[2, "vehicles"] == "0-30 m"
    for col in ["EPE all (px)", "Fl-all (%)", "EPE boxes (px)", "Fl-all boxes (%)", "s / pair"]:
        np.testing.assert_allclose(got[col].to_numpy(float), want[col].to_numpy(float),
                                   rtol=1e-5, atol=1e-6, err_msg=col)
    assert (0 < got["Fl-all (%)"]).all() and (got["Fl-all (%)"] < 100).all()


def test_flowcheck_draws_with_the_seed_given(tiny_world, frames, tmp_path):
    """With seed 0 (the one pair with a vehicle in range is the one
    seed 0's draw leaves out: no box scores, no interval, no RuntimeWarning); a set without a
    pair that every method stores (here the empty general set) gives no row."""
    root, version = tiny_world
    p = load_profile("smoke", dataroot=str(root), version=version)
    s0 = frames["synth-0000"]
    ids = ["a", "b"]
    pairs = pd.DataFrame({"pair_id": ids, "set": "keyframe", "scene": "synth-0000",
                          "sd_token_1": s0[0], "sd_token_2": s0[1]})
    left_out = sorted(set(ids) - set(np.random.default_rng(0).choice(
        np.array(ids), size=1, replace=False)))
    assert left_out != sorted(set(ids) - set(np.random.default_rng(1).choice(
        np.array(ids), size=1, replace=False)))  # another seed leaves out the other pair
    objects = pd.DataFrame({"pair_id": left_out, "distance": [50.0], "xmin": [700],
                            "ymin": [380], "xmax": [799], "ymax": [459]})
    readers = {"dis": {"keyframe": _reader(tmp_path, "dis", "keyframe",
                                           {k: (1.0, 0.0) for k in ids}, [1.0, 2.0]),
                       "general": _reader(tmp_path, "dis", "general", {}, [])}}
    with warnings.catch_warnings():  # the box scores are NaN without a mean of nothing
        warnings.simplefilter("error", RuntimeWarning)
        rows = accuracy.measure(root, version, pairs, objects, readers, min_distance=30.0,
                                max_distance=70.0, n_pairs=1, seed=0)
        got = ch03.accuracy_table(p, rows, readers)
    assert got["set"].tolist() == ["keyframe"]
    assert got.loc[0, "pairs"] == 1
    assert np.isnan(got.loc[0, "EPE boxes (px)"]) and np.isnan(got.loc[0, "Fl-all boxes (%)"])
    assert got.loc[0, "EPE boxes 95% CI, scenes (px)"] == "-"
    assert got.loc[0, "s / pair"] == 1.5


def test_box_flow_magnitude_is_the_median_over_each_box_s_central_part():
    """box_flow_magnitude: the median |flow| over the central ``inner`` share of each box
    (its centre +/- inner/2 of its sides, truncated to whole pixels, clipped to the image),
    each object in its own row, each pair's flow loaded once."""
    h, w = 12, 10  # taller than wide: a row bound clipped at the width would show
    mag = 100.0 * np.arange(h)[:, None] + np.arange(w)[None, :]  # |flow| = 100 row + col
    ang = np.linspace(0, 2 * np.pi, h * w).reshape(h, w)
    flows = {"p": np.stack([mag * np.cos(ang), mag * np.sin(ang)], -1),
             "q": np.stack([2 * mag, 0 * mag], -1)}
    loads = []

    def load(pid):
        loads.append(pid)
        return flows[pid]

    objects = pd.DataFrame({
        "pair_id": ["p", "q", "p", "q", "p"],
        # p: rows 2-5 x cols 3-6; q: rows 0-3 x cols 0-2 (box out at the top left);
        # p: rows 9-11 x cols 8-9 (out at the bottom right); q: rows 5-6 x cols 4-5;
        # p: rows 0-4 x cols 1-4 (a box reaching 8 rows above the image)
        "xmin": [2.0, -4.0, 7.0, 4.0, 0.0], "ymin": [1.0, -5.0, 8.0, 5.0, -8.0],
        "xmax": [8.0, 4.0, 12.0, 6.0, 5.0], "ymax": [6.0, 5.0, 14.0, 7.0, 8.0]})
    got = ch03.box_flow_magnitude(objects, load)
    windows = [(2, 6, 3, 7, 1), (0, 4, 0, 3, 2), (9, 12, 8, 10, 1), (5, 7, 4, 6, 2),
               (0, 5, 1, 5, 1)]  # rows, cols (end exclusive), flow scale
    want = [f * np.median(mag[r0:r1, c0:c1]) for r0, r1, c0, c1, f in windows]
    assert got == pytest.approx(want, rel=1e-5)
    assert got[0] == pytest.approx(354.5, rel=1e-6)
    # magnitudes in float32 (the stored flow's precision), returned as float64
    assert got.dtype == np.float64
    small = ch03.box_flow_magnitude(objects.iloc[[0]], lambda pid: np.full((h, w, 2), (0.1, 0.2)))
    assert small[0] == float(np.linalg.norm(np.float32([0.1, 0.2])))
    assert small[0] != float(np.linalg.norm([0.1, 0.2]))
    assert sorted(loads) == ["p", "q"]
    full = ch03.box_flow_magnitude(objects.iloc[[0]], load, inner=1.0)  # the whole box
    assert full == pytest.approx([np.median(mag[1:7, 2:9])], rel=1e-5)
