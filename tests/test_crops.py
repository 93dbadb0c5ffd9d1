"""flowmod.crops: geometry against a slow reference, flips, and the crop artefacts."""

from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from flowmod import crops
from flowmod.artefacts import read_manifest
from flowmod.crops import CropsError, build_crops, crop_boxes, crop_windows, hflip, read_crops
from flowmod.params import Params

#: The paper's chain up to the crops: the classifiers read only the crops node's arrays,
#: index and flow samples, which the crops-mode test finds equal to the bit (that equal crops
#: train equal models is the rerun-equals-fresh check in tests/test_provenance.py).
CORE_CHAPTERS = ["01", "02", "03", "05"]

# --- a slow, explicit reference of the paper's preprocessing ---------------------------------


def reference_crop(flow: np.ndarray, box, size: int, scale: float) -> np.ndarray:
    """One box, written out step by step: square, scale, np.pad edge, slice, cv2.resize."""
    xmin, ymin, xmax, ymax = box
    side = scale * max(xmax - xmin, ymax - ymin)
    n = max(1, math.floor(side + 0.5))
    # pixel i's centre is at i: the n pixels whose span is centred on the box centre
    x0 = math.floor((xmin + xmax) / 2 - (n - 1) / 2 + 0.5)
    y0 = math.floor((ymin + ymax) / 2 - (n - 1) / 2 + 0.5)
    h, w = flow.shape[:2]
    pad = max(0, -x0, -y0, x0 + n - w, y0 + n - h)
    padded = np.pad(flow, ((pad, pad), (pad, pad), (0, 0)), mode="edge")
    patch = padded[y0 + pad : y0 + pad + n, x0 + pad : x0 + pad + n]
    assert patch.shape == (n, n, 2)
    resized = cv2.resize(np.ascontiguousarray(patch), (size, size),
                         interpolation=cv2.INTER_LINEAR)
    out = np.empty((2, size, size), dtype=np.float32)
    for c in range(2):
        for r in range(size):
            for q in range(size):
                out[c, r, q] = resized[r, q, c]
    return out


def random_boxes(rng: np.random.Generator, w: int, h: int, n: int) -> np.ndarray:
    x1 = rng.uniform(-20, w + 20, n)
    y1 = rng.uniform(-20, h + 20, n)
    bw = rng.uniform(0, 40, n)
    bh = rng.uniform(0, 40, n)
    boxes = np.stack([x1, y1, x1 + bw, y1 + bh], axis=1)
    special = np.array([
        [0, 0, 10, 10],  # at the top-left corner
        [w - 10, h - 10, w, h],  # at the bottom-right corner
        [w - 3, 10, w + 30, 30],  # beyond the right border
        [-25, -5, -2, 12],  # fully outside
        [50, 40, 50, 40],  # zero size -> 1 px window
        [20.2, 30.7, 20.5, 30.9],  # sub-pixel box
        [10, 10, 150, 30],  # wide: window larger than the frame
    ], dtype=float)
    return np.concatenate([boxes, special])


@pytest.fixture(scope="module")
def frame() -> np.ndarray:
    rng = np.random.default_rng(1)
    return rng.normal(0, 3, (72, 128, 2)).astype(np.float32)


@pytest.mark.parametrize("size,scale", [(16, 3.0), (24, 1.5), (7, 3.0)])
def test_crops_equal_slow_reference(frame: np.ndarray, size: int, scale: float) -> None:
    boxes = random_boxes(np.random.default_rng(size), frame.shape[1], frame.shape[0], 40)
    got = crop_boxes(frame, boxes, size, scale)
    assert got.shape == (len(boxes), 2, size, size) and got.dtype == np.float32
    for i, b in enumerate(boxes):
        np.testing.assert_array_equal(got[i], reference_crop(frame, b, size, scale),
                                      err_msg=f"box {i}: {b}")


def test_huge_windows_use_the_gather_path_with_equal_values(frame: np.ndarray) -> None:
    boxes = np.array([[-100.0, -50.0, 300.0, 150.0], [60, 30, 64, 34]])  # 1200 px window
    got = crop_boxes(frame, boxes, 12, 3.0)
    for i, b in enumerate(boxes):
        np.testing.assert_array_equal(got[i], reference_crop(frame, b, 12, 3.0))


def test_window_geometry_and_bad_boxes() -> None:
    np.testing.assert_array_equal(crop_windows([[10, 20, 20, 24]], 3.0), [[1, 8, 30]])
    # the window's span [x0 - 0.5, x0 + n - 0.5] is centred on the box centre (to 0.5 px)
    boxes = random_boxes(np.random.default_rng(3), 128, 72, 200)
    win = crop_windows(boxes, 3.0)
    for axis in (0, 1):
        centre = (boxes[:, axis] + boxes[:, axis + 2]) / 2
        assert np.abs(win[:, axis] + (win[:, 2] - 1) / 2 - centre).max() <= 0.5
    np.testing.assert_array_equal(crop_windows([[5, 5, 5, 5]], 3.0), [[5, 5, 1]])
    assert crop_boxes(np.zeros((8, 8, 2)), np.zeros((0, 4)), 4).shape == (0, 2, 4, 4)
    with pytest.raises(CropsError, match="NaN"):
        crop_windows([[0, 0, np.nan, 1]])
    with pytest.raises(CropsError, match="xmax < xmin"):
        crop_windows([[5, 0, 1, 1]])
    with pytest.raises(CropsError, match=r"\(H, W, 2\)"):
        crop_boxes(np.zeros((8, 8, 3)), [[0, 0, 1, 1]], 4)


def test_flow_values_are_not_rescaled() -> None:
    flow = np.full((50, 50, 2), (2.5, -1.0), dtype=np.float32)
    out = crop_boxes(flow, [[20, 20, 30, 30]], 90)  # 30 px window upsampled x3
    np.testing.assert_allclose(out[0, 0], 2.5)
    np.testing.assert_allclose(out[0, 1], -1.0)


# --- flips ------------------------------------------------------------------------------------


def test_hflip_numpy_mirrors_negates_u_copies_and_is_an_involution() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3, 2, 5, 6)).astype(np.float16)
    x.flags.writeable = False  # as a read-only memmap would be
    before = x.copy()
    y = hflip(x)
    np.testing.assert_array_equal(x, before)  # source untouched
    assert not np.shares_memory(x, y)
    np.testing.assert_array_equal(y[:, 0], -x[:, 0, :, ::-1])
    np.testing.assert_array_equal(y[:, 1], x[:, 1, :, ::-1])
    np.testing.assert_array_equal(hflip(y), x)
    single = hflip(x[0])  # (2, S, S) works too
    np.testing.assert_array_equal(single, y[0])


def test_hflip_torch_matches_numpy() -> None:
    torch = pytest.importorskip("torch")
    x = torch.randn(4, 2, 3, 5)
    before = x.clone()
    y = hflip(x)
    assert torch.equal(x, before)
    np.testing.assert_array_equal(y.numpy(), hflip(x.numpy()))
    assert torch.equal(hflip(y), x)
    with pytest.raises(TypeError):
        hflip([1, 2])


# --- artefacts --------------------------------------------------------------------------------

W, H = 160, 90  # the "image" size the boxes are given in
QUIET = dict(image_size=(W, H), progress=False)


def make_world(tmp_path: Path, flow_shape=(H, W)) -> tuple[pd.DataFrame, Path]:
    """3 pairs (2 train, 1 val), float16 flow files, objects in shuffled order."""
    rng = np.random.default_rng(7)
    flow_dir = tmp_path / "flow"
    (flow_dir / "dis").mkdir(parents=True)
    rows = []
    for k, (pid, split) in enumerate([("p0", "train"), ("p1", "val"), ("p2", "train")]):
        np.save(flow_dir / "dis" / f"{pid}.npy",
                rng.normal(0, 2, (*flow_shape, 2)).astype(np.float16))
        for j in range(3 + k):
            x1, y1 = rng.uniform(-5, W - 10), rng.uniform(-5, H - 10)
            rows.append({
                "pair_id": pid, "scene": "s", "split": split, "ann_token": f"{pid}-{j}",
                "xmin": x1, "ymin": y1, "xmax": x1 + rng.uniform(1, 25),
                "ymax": y1 + rng.uniform(1, 25), "label": int(j % 2), "distance": 40.0,
            })
    objects = pd.DataFrame(rows).sample(frac=1.0, random_state=0).reset_index(drop=True)
    return objects, flow_dir


class CountingLoader:
    """``load(pair_id)`` over the flow files of make_world, counting reads (and able to die)."""

    def __init__(self, flow_dir: Path) -> None:
        self.flow_dir = flow_dir
        self.calls: list[str] = []
        self.fail_at: int | None = None

    def __call__(self, pair_id):
        if self.fail_at is not None and len(self.calls) == self.fail_at:
            raise KeyboardInterrupt("simulated interruption")
        self.calls.append(pair_id)
        return np.load(self.flow_dir / "dis" / f"{pair_id}.npy").astype(np.float32)


def test_build_crops_content_order_and_one_read_per_pair(tmp_path) -> None:
    objects, flow_dir = make_world(tmp_path)
    counter = CountingLoader(flow_dir)
    out = build_crops(objects, counter, tmp_path / "crops", size=16, **QUIET)
    assert set(out) == {"train", "val"}
    assert sorted(counter.calls) == ["p0", "p1", "p2"]  # each flow file read once
    for split in ("train", "val"):
        x, idx = read_crops(tmp_path / "crops", split)
        assert x.dtype == np.float16 and x.shape == (len(idx), 2, 16, 16)
        assert list(idx.columns) == list(objects.columns)
        assert idx["pair_id"].is_monotonic_increasing
        for pid, grp in idx.groupby("pair_id"):
            flow = np.load(flow_dir / "dis" / f"{pid}.npy").astype(np.float32)
            want = crop_boxes(flow, grp[["xmin", "ymin", "xmax", "ymax"]].to_numpy(), 16)
            np.testing.assert_array_equal(x[grp.index.to_numpy()], want.astype(np.float16))
    n_train = (objects["split"] == "train").sum()
    assert len(read_crops(tmp_path / "crops", "train")[1]) == n_train
    assert out["train"]["rows"] == n_train
    # no temporary files left behind
    leftovers = [p.name for p in (tmp_path / "crops").iterdir()
                 if p.name.startswith(".") and "done" not in p.name]
    assert leftovers == []


def test_build_crops_skips_when_up_to_date_and_rebuilds_on_change(tmp_path):
    objects, flow_dir = make_world(tmp_path)
    counter = CountingLoader(flow_dir)
    kw = dict(size=8, **QUIET)
    build_crops(objects, counter, tmp_path / "c", **kw)
    assert len(counter.calls) == 3
    build_crops(objects, counter, tmp_path / "c", **kw)
    assert len(counter.calls) == 3  # up to date: nothing read
    build_crops(objects, counter, tmp_path / "c", size=8, scale=2.0, **QUIET)
    assert len(counter.calls) == 6  # new parameters: rebuilt
    changed = objects.copy()
    changed.loc[changed["pair_id"] == "p1", "xmin"] -= 1.0
    build_crops(changed, counter, tmp_path / "c", size=8, scale=2.0, **QUIET)
    assert counter.calls[6:] == ["p1"]  # only the changed split (val) is rebuilt


def test_build_crops_is_atomic_and_resumes(tmp_path) -> None:
    objects, flow_dir = make_world(tmp_path)
    train_only = objects[objects["split"] == "train"]
    counter = CountingLoader(flow_dir)
    counter.fail_at = 1  # die while loading the second pair of the split
    with pytest.raises(KeyboardInterrupt):
        build_crops(train_only, counter, tmp_path / "c", size=8, **QUIET, checkpoint_every=1)
    npy, index = crops.crop_paths(tmp_path / "c", "train")
    assert not npy.exists() and not index.exists()  # nothing half-written under final names
    counter.fail_at = None
    build_crops(train_only, counter, tmp_path / "c", size=8, **QUIET)
    assert counter.calls == ["p0", "p2"]  # resumed: p0 was not read again
    fresh = tmp_path / "fresh"
    build_crops(train_only, CountingLoader(flow_dir), fresh, size=8, **QUIET)
    np.testing.assert_array_equal(np.load(npy), np.load(crops.crop_paths(fresh, "train")[0]))


def test_boxes_are_scaled_to_a_reduced_flow_grid(tmp_path) -> None:
    objects, flow_dir = make_world(tmp_path, flow_shape=(H // 2, W // 2))
    build_crops(objects, CountingLoader(flow_dir), tmp_path / "c", size=8, **QUIET)
    x, idx = read_crops(tmp_path / "c", "val")
    flow = np.load(flow_dir / "dis" / "p1.npy").astype(np.float32)
    # pixel centres of the half-size grid: x_small = (x + 0.5) / 2 - 0.5
    want = crop_boxes(flow, (idx[["xmin", "ymin", "xmax", "ymax"]].to_numpy() + 0.5) / 2 - 0.5, 8)
    np.testing.assert_array_equal(x, want.astype(np.float16))


def test_read_crops_errors_name_both_files(tmp_path) -> None:
    objects, flow_dir = make_world(tmp_path)
    build_crops(objects, CountingLoader(flow_dir), tmp_path / "c", size=8, **QUIET)
    npy, index = crops.crop_paths(tmp_path / "c", "train")
    pd.read_parquet(index).iloc[:-1].to_parquet(index)
    with pytest.raises(CropsError, match="disagree") as e:
        read_crops(tmp_path / "c", "train")
    assert str(npy) in str(e.value) and str(index) in str(e.value)
    with pytest.raises(CropsError, match="missing"):
        read_crops(tmp_path / "c", "test")


def test_empty_split_gets_an_empty_array(tmp_path) -> None:
    objects, flow_dir = make_world(tmp_path)
    info = build_crops(objects, CountingLoader(flow_dir), tmp_path / "c", size=8,
                       splits=("train", "val", "test"), **QUIET)
    assert info["test"]["rows"] == 0
    x, idx = read_crops(tmp_path / "c", "test")
    assert x.shape == (0, 2, 8, 8) and len(idx) == 0


def test_padded_flow_grid_is_refused(tmp_path) -> None:
    objects, flow_dir = make_world(tmp_path, flow_shape=(H + 4, W))  # like RAFT's 904 rows
    with pytest.raises(CropsError, match=r"padded flow not unpadded\? \(RAFT pads 900 rows "
                                         r"to 904\)$"):
        build_crops(objects, CountingLoader(flow_dir), tmp_path / "c", size=8, **QUIET)
    with pytest.raises(CropsError, match=r"^size must be >= 1, got 0$"):
        crops.crop_image(np.zeros((4, 4, 2)), np.array([[0.0, 0.0, 2.0, 2.0]]), 0)


def test_nonfinite_flow_is_zeroed_and_recorded(tmp_path) -> None:
    objects, flow_dir = make_world(tmp_path)
    f = np.load(flow_dir / "dis" / "p1.npy")
    f[:, : W // 2] = np.nan  # invalid pixels (e.g. GT flow leaving the image)
    np.save(flow_dir / "dis" / "p1.npy", f)
    info = build_crops(objects, CountingLoader(flow_dir), tmp_path / "c", size=8, **QUIET)
    x, _ = read_crops(tmp_path / "c", "val")
    assert np.isfinite(x).all()
    assert info["val"]["nonfinite_flow_values_zeroed"] > 0


@pytest.mark.slow
def test_crops_mode_gives_the_stored_flow_crops_and_keeps_few_pairs(smoke_built, tmp_path):
    """flow_store: crops on the smoke world: every crop, flow sample and index bit-identical
    to the crops cut from stored flow (gt with its valid mask included); the flow nodes
    keep only the figures' and the seeded pairs; a rerun computes nothing; and the disk it
    takes is that of crops, not of flow."""
    from flowmod import dag, pipeline, select
    from flowmod.chapters import common

    local = smoke_built
    p = local.model_copy(update={"flow_store": "crops", "flow_keep_pairs": 2,
                                 "run_dir": str(tmp_path / "runs")})
    pipeline.build(p, chapters=CORE_CHAPTERS)
    for m in p.flow_methods:
        for part in crops.PARTS:
            for split in crops.part_splits(part, p.folds):
                xa, ia = common.open_crops(local, m, split)
                xb, ib = common.open_crops(p, m, split)
                np.testing.assert_array_equal(xa, xb)
                pd.testing.assert_frame_equal(ia, ib)
                node = dag.Node("crops", m, part)
                np.testing.assert_array_equal(
                    crops.read_samples(pipeline.published(local, node), split),
                    crops.read_samples(pipeline.published(p, node), split))
            kept = common.flow_reader(p, m, part).pair_ids
            every = common.flow_reader(local, m, part).pair_ids
            assert set(kept) <= set(every)  # general: the whole clip may be all of it
            for pid in kept:  # kept flow is the same flow
                np.testing.assert_array_equal(common.flow_reader(p, m, part).load(pid),
                                              common.flow_reader(local, m, part).load(pid))
        key = common.flow_reader(p, m, "keyframe").pair_ids
        assert len(key) == 3 < len(common.flow_reader(local, m, "keyframe").pair_ids), (
            "Figure 1's pair and 2 drawn")

    def size(folder: Path) -> int:
        return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())

    def flow_bytes(q, m: str) -> int:
        r = common.flow_reader(q, m, "keyframe")
        return sum(r.path(pid).stat().st_size for pid in r.pair_ids)

    for m in p.flow_methods:
        n_all = len(common.flow_reader(local, m, "keyframe").pair_ids)
        assert flow_bytes(p, m) * n_all == flow_bytes(local, m) * 3, "3 pairs' flow kept"
        # published: the node's arrays hold the crops, the per-pair files are gone
        assert not list((Path(p.run_dir) / "crops" / m / "pool").rglob("*.npy"))
        node_dirs = [pipeline.published(p, dag.Node("crops", m, part)) for part in select.PARTS]
        assert sum(size(d) for d in node_dirs) < 0.2 * size(Path(local.run_dir) / "flow" / m / "pool")
        for d in node_dirs:
            assert read_manifest(d / "manifest.json")["flow_computed"] == len(
                pd.read_parquet(d / crops.POOL_KEYS)) > 0
    st = pipeline.status_frame(p)
    assert st[st["chapter"].isin(CORE_CHAPTERS)]["state"].eq("up to date").all()
    def stamps() -> dict[Path, int]:  # the run folder's lock file is not an artefact
        return {f: f.stat().st_mtime_ns for f in Path(p.run_dir).rglob("*")
                if f.is_file() and f.name != ".flowmod.lock"}

    before = stamps()
    pipeline.build(p.model_copy(update={"force": False}), chapters=CORE_CHAPTERS)
    assert stamps() == before

    # other splits, the same boxes: the crops nodes are rebuilt from the published rows,
    # no flow computed, every pair's crops as before
    q = Params.model_validate({**p.model_dump(), "split_fractions": [0.6, 0.2, 0.2]})
    old = {m: pipeline.recorded(p, dag.Node("crops", m, "keyframe"))["fingerprint"]
           for m in p.flow_methods}
    pipeline.build(q, chapters=["02", "05"])
    for m in q.flow_methods:
        node = dag.Node("crops", m, "keyframe")
        rebuilt = read_manifest(pipeline.published(q, node) / "manifest.json")
        assert rebuilt["flow_computed"] == 0
        assert rebuilt["fingerprint"] != old[m]

        def every_split(r, m=m):
            parts = [common.open_crops(r, m, s) for s in crops.part_splits("keyframe", r.folds)]
            idx = pd.concat([i for _, i in parts], ignore_index=True)
            order = np.argsort(idx["pair_id"].to_numpy(), kind="stable")
            return np.concatenate([np.asarray(x) for x, _ in parts])[order], idx.iloc[order]

        (xa, ia), (xb, ib) = every_split(p), every_split(q)
        np.testing.assert_array_equal(xa, xb)
        assert not list((Path(q.run_dir) / "crops" / m / "pool").rglob("*.npy"))

    # issue 53: a node whose files changed in place is never a source of restored pairs
    # (the kept variant of p's node is: it still holds what it published)
    r = Params.model_validate({**p.model_dump(), "split_fractions": [0.5, 0.25, 0.25]})
    for m in q.flow_methods:
        node = dag.Node("crops", m, "keyframe")
        arrays, _ = crops.crop_paths(pipeline.published(q, node), crops.part_splits(
            "keyframe", q.folds)[0])
        raw = arrays.read_bytes()
        arrays.write_bytes(raw[:128] + bytes(len(raw) - 128))
    pipeline.build(r, chapters=["02", "05"])
    for m in r.flow_methods:
        np.testing.assert_array_equal(every_split(p, m)[0], every_split(r, m)[0])


def test_pair_crops_writer_resumes_and_refuses_mixed_splits(tmp_path) -> None:
    """Crops mode's per-pair files through compute_flow: a crops file cut short (a kill while
    writing) is the only pair computed again; its crops equal pair_crops on the round-tripped
    flow; objects of one pair in two splits are refused, naming the pair."""
    from test_flow import KW, make_dataroot

    import flowmod.flow as fl

    root = tmp_path / "data"
    pairs = make_dataroot(root, n=3, size=(60, 80))
    boxes = {p: [[10.0 + i, 12.0, 30.0 + i, 40.0], [40.0, 5.0, 70.0, 25.0]]
             for i, p in enumerate(pairs["pair_id"])}
    writer = crops.PairCrops("float16", 0.5, size=8, scale=2.0, image_size=(80, 60))
    kw = {**KW, "dataroot": root, "store_scale": 0.5, "writer": writer, "extras": boxes}
    first = fl.compute_flow(pairs, "dis", tmp_path / "pool", **kw)
    assert first["computed"].all() and list(first["shape"].iloc[0]) == [60, 80, 2]
    f1 = tmp_path / "pool" / first["file"].iloc[1]
    got = writer.items(f1, 2)
    img = [fl.read_image(root / pairs[c].iloc[1]) for c in ("path_1", "path_2")]
    flow = fl.store.roundtrip(fl.get_estimator("dis").estimate(*img), "float16", 0.5)
    want = crops.pair_crops(flow, np.array(boxes["p1"]), 8, 2.0, (80, 60))
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert got[0].shape == (2, 2, 8, 8) and got[0].dtype == np.float16

    f1.write_bytes(f1.read_bytes()[:-10])  # cut short
    again = fl.compute_flow(pairs, "dis", tmp_path / "pool", **kw)
    assert list(again["computed"]) == [False, True, False]
    other = fl.compute_flow(pairs, "dis", tmp_path / "pool",
                            **{**kw, "extras": {**boxes, "p0": boxes["p0"][:1]}})
    assert list(other["computed"]) == [True, False, False], "other boxes: another key"

    objects = pd.DataFrame({"pair_id": ["a", "a", "b"], "split": ["train", "val", "val"],
                            "xmin": 1.0, "ymin": 1.0, "xmax": 5.0, "ymax": 5.0})
    with pytest.raises(CropsError, match=r"several splits: \['a'\]"):
        crops.pair_boxes(objects)


@pytest.mark.parametrize("dtype", [object, "category"])
def test_split_objects_keeps_each_pairs_rows_in_their_table_order(dtype) -> None:
    """One split's objects are grouped by pair_id and, within a pair, stay in the table's
    order (a stable sort), also for object or categorical (dictionary-read) pair ids, whose
    default sort is not stable; the other split's rows are left out."""
    rng = np.random.default_rng(0)
    pair = rng.choice(["p0", "p1", "p2"], 40)
    split = np.where(np.arange(40) % 7 == 3, "val", "train")
    objects = pd.DataFrame({"pair_id": pd.Series(pair).astype(dtype), "split": split,
                            "row": np.arange(40)})
    got = crops.split_objects(objects, "train")
    want = sorted((p, i) for i, (p, s) in enumerate(zip(pair, split, strict=True))
                  if s == "train")
    assert got["row"].tolist() == [i for _, i in want]
    assert got.index.tolist() == list(range(len(want)))


def test_pair_boxes_in_object_order_and_mixed_splits_named_five_at_most() -> None:
    """Each pair's boxes in the objects' order, pairs in order of first appearance; pairs
    spread over splits are refused, naming the first five of them."""
    objects = pd.DataFrame({"pair_id": ["b", "a", "b"], "split": ["val", "train", "val"],
                            "xmin": [1.0, 2.0, 3.0], "ymin": [4.0, 5.0, 6.0],
                            "xmax": [7.0, 8.0, 9.0], "ymax": [10.0, 11.0, 12.0]})
    got = crops.pair_boxes(objects)
    assert list(got) == ["b", "a"]
    assert got == {"b": [[1.0, 4.0, 7.0, 10.0], [3.0, 6.0, 9.0, 12.0]],
                   "a": [[2.0, 5.0, 8.0, 11.0]]}
    mixed = pd.DataFrame({"pair_id": list("abcdef") * 2, "split": ["train"] * 6 + ["val"] * 6,
                          "xmin": 1.0, "ymin": 1.0, "xmax": 5.0, "ymax": 5.0})
    with pytest.raises(CropsError, match=r"several splits: \['a', 'b', 'c', 'd', 'e'\]$"):
        crops.pair_boxes(mixed)
    ints = objects.astype({c: int for c in ("xmin", "ymin", "xmax", "ymax")})
    assert all(type(v) is float for b in crops.pair_boxes(ints).values() for r in b for v in r)


def test_a_flow_of_another_size_names_its_pair_or_a_question_mark() -> None:
    """A flow that is no rescaled copy of the image is refused naming the pair given, or
    '?' when none is."""
    flow, boxes = np.zeros((90, 100, 2), np.float32), np.array([[10.0, 10.0, 20.0, 20.0]])
    with pytest.raises(CropsError, match=r"^flow of pair \? is 100x90"):
        crops.pair_crops(flow, boxes, 8, 3.0, image_size=(160, 90))
    with pytest.raises(CropsError, match=r"^flow of pair p7 is"):
        crops.pair_crops(flow, boxes, 8, 3.0, image_size=(160, 90), pair_id="p7")


# --- mutation-testing kills: windows at the frame's edges, checks and dtypes ---------------


def _reference_crops(image: np.ndarray, boxes, size: int, scale: float = 3.0) -> np.ndarray:
    """Each window gathered with clipped (edge-replicated) indices, resized bilinearly."""
    out = []
    for x, y, k in crop_windows(boxes, scale).tolist():
        rows = np.clip(np.arange(y, y + k), 0, image.shape[0] - 1)
        cols = np.clip(np.arange(x, x + k), 0, image.shape[1] - 1)
        patch = image[np.ix_(rows, cols)]
        out.append(cv2.resize(patch, (size, size), interpolation=cv2.INTER_LINEAR)
                   .reshape(size, size, image.shape[2]))
    return np.stack(out)


@pytest.mark.parametrize("box", [[90.0, 20.0, 98.0, 28.0],   # leaves the right edge only
                                 [20.0, 50.0, 28.0, 58.0],   # the bottom edge only
                                 [1.0, 1.0, 9.0, 9.0],       # the top-left corner
                                 [40.0, 25.0, 48.0, 33.0]])  # inside
def test_crop_image_replicates_the_edge_on_every_side(box):
    """A window leaving the frame on any side holds the edge pixels repeated (the padded
    path, margin from the side it leaves), equal to a gather with clipped indices."""
    yy, xx = np.mgrid[0:60, 0:100].astype(np.float32)
    image = np.dstack([xx * 1.5 + yy, yy * 2.0 - xx])  # (60, 100, 2), no two pixels alike
    got = crops.crop_image(image, np.array([box]), 12)
    np.testing.assert_array_equal(got, _reference_crops(image, [box], 12))


def test_crop_defaults_and_size_one():
    """The default scale is the paper's 3; a 1 x 1 crop is allowed."""
    rng = np.random.default_rng(0)
    image = rng.normal(size=(50, 80, 2)).astype(np.float32)
    box = np.array([[30.0, 20.0, 36.0, 26.0]])
    np.testing.assert_array_equal(crops.crop_image(image, box, 8),
                                  crops.crop_image(image, box, 8, 3.0))
    np.testing.assert_array_equal(crop_windows(box), crop_windows(box, 3.0))
    assert crops.crop_image(image, box, 1).shape == (1, 1, 1, 2)
    assert crop_boxes(image.astype(np.float64), box, 4).dtype == np.float32


def test_crop_windows_compute_in_float64_whatever_the_boxes_dtype():
    """float32 boxes are widened first: in float32 this window would start a pixel off."""
    b32 = np.array([[1.3, 154.5, 195.7, 191.0]], dtype=np.float32)
    np.testing.assert_array_equal(crop_windows(b32), crop_windows(b32.astype(np.float64)))
    assert crop_windows(b32)[0].tolist() == [-193, -118, 583]


def test_crop_windows_name_exactly_the_bad_rows():
    """NaN rows and inverted rows are named (the first five); an empty (zero-size) box is
    not inverted."""
    b = np.array([[0, 0, 10, 10]] * 9, dtype=np.float64)
    b[[2, 4, 5, 6, 7, 8], 1] = np.nan
    with pytest.raises(CropsError, match=r"NaN/inf \(rows \[2, 4, 5, 6, 7\]\.\.\.\)"):
        crop_windows(b)
    b = np.array([[0, 0, 0, 5], [0, 0, 5, 0], [6, 0, 5, 5], [0, 6, 5, 5], [0, 0, 5, 5]]
                 + [[6, 6, 5, 5]] * 4, dtype=np.float64)
    with pytest.raises(CropsError, match=r"ymax < ymin \(rows \[2, 3, 5, 6, 7\]\.\.\.\)"):
        crop_windows(b)
    assert crop_windows(b[[0, 1, 4]])[:, 2].tolist() == [15, 15, 15]


def test_hflip_names_the_type_it_refuses():
    with pytest.raises(TypeError, match="got list"):
        hflip([[1.0]])


def test_pair_crops_rescale_boxes_fix_non_finite_and_keep_dtypes():
    """Flow at half resolution: boxes map onto its grid by pixel centres ((x + 0.5) s - 0.5,
    also for integer boxes); NaN flow becomes 0; crops float16, samples float32; the given
    scale is used; a height more than 1.5 px off a rescale is refused with the image size."""
    rng = np.random.default_rng(1)
    flow = rng.normal(size=(450, 800, 2)).astype(np.float32)
    flow[100:110, 200:210] = np.nan
    boxes = np.array([[400, 200, 440, 230], [100, 300, 160, 340]])  # int, full resolution
    c, s, n_bad, hw = crops.pair_crops(flow, boxes, 8, 2.0)
    assert (n_bad, hw) == (200, [450, 800])
    assert c.dtype == np.float16 and s.dtype == np.float32
    clean = np.nan_to_num(flow, nan=0.0)
    half = (boxes.astype(np.float64) + 0.5) * 0.5 - 0.5
    np.testing.assert_array_equal(c, crop_boxes(clean, half, 8, 2.0).astype(np.float16))
    np.testing.assert_array_equal(s, crops.box_samples(clean, half).astype(np.float32))
    assert np.isfinite(c).all()
    # 8 x 6 px: a 1/200 rescale would have 4.5 rows, 6 is 1.5 off: still rounding
    crops.pair_crops(np.zeros((6, 8, 2), np.float32), boxes, 4, 2.0)
    crops.pair_crops(np.zeros((901, 1600, 2), np.float32), boxes, 8, 2.0)  # 1 px off
    with pytest.raises(CropsError, match=r"is 1600x902 \(WxH\), not the 1600x900 image"):
        crops.pair_crops(np.zeros((902, 1600, 2), np.float32), boxes, 8, 2.0)


# --- the static-world crops (chapter 10) and the stage's routing ------------------------------

@pytest.fixture(scope="module")
def tiny_pairs(tiny_world, tmp_path_factory):
    """(objects, pairs, frame boxes) of two keyframe pairs of the tiny world's selection."""
    from flowmod import select
    from flowmod.params import validate

    root, version = tiny_world
    p = validate({"profile": "smoke", "dataroot": str(root), "version": version,
                  "run_dir": str(tmp_path_factory.mktemp("tiny_run")), "synthetic": False})
    nusc = select.open_nuscenes(root, version)
    sel = select.select_keyframes(p, nusc, progress=False)
    pids = sorted(sel.pairs["pair_id"])[:2]
    objects = sel.objects[sel.objects["pair_id"].isin(pids)].reset_index(drop=True)
    pairs = sel.pairs[sel.pairs["pair_id"].isin(pids)].reset_index(drop=True)
    boxes = {pid: select.frame_boxes_3d(nusc, sd) for pid, sd in
             zip(pairs["pair_id"], pairs["sd_token_1"], strict=True)}
    return objects, pairs, boxes


def _static_reference(o, pair, boxes3d, size, scale, depth):
    """One object's static-world crop from geometry's functions, step by step."""
    from flowmod import geometry

    K, T1, T2 = geometry.pair_cameras(pair)
    box = np.array([o.xmin, o.ymin, o.xmax, o.ymax])
    win = crop_windows(box[None], scale)[0]
    if depth == "ground":
        return geometry.static_flow_crop(win, size, K, T1, T2, [], 0.0,
                                         image_size=(1600, 900), box2d=box)
    if boxes3d is None:
        boxes3d = [((o.center_x, o.center_y, o.center_z), (o.size_w, o.size_l, o.size_h),
                    (o.qw, o.qx, o.qy, o.qz))]
    cam = []
    for c, wlh, q in boxes3d:
        c_cam, rot = geometry.box_in_camera(T1, np.asarray(c, float), np.asarray(q, float))
        if c_cam[2] > 0:
            cam.append((c_cam, np.asarray(wlh, float), rot))
    return geometry.static_flow_crop(win, size, K, T1, T2, cam, 0.0, image_size=(1600, 900))


def test_static_crops_are_the_geometry_of_each_object_s_window(tiny_pairs):
    """static_crops: per depth, each object's crop is geometry.static_flow_crop of its
    window (scale x its box) with its pair's cameras: ``boxes`` with the pair's frame boxes
    (those in front of the camera) or the object's own box, ``ground`` from its 2D box."""
    objects, pairs, frame_boxes = tiny_pairs
    by_pair = pairs.set_index("pair_id")
    got = crops.static_crops(objects, pairs, 12, 2.5, frame_boxes=frame_boxes,
                             depths=("boxes", "ground"))
    own = crops.static_crops(objects, pairs, 12, 2.5)
    assert set(got) == {"boxes", "ground"} and set(own) == {"boxes"}
    assert got["boxes"].shape == (len(objects), 2, 12, 12) and got["boxes"].dtype == np.float32
    for i, o in enumerate(objects.itertuples(index=False)):
        pair = by_pair.loc[o.pair_id]
        for depth, boxes3d, out in (("boxes", frame_boxes[o.pair_id], got["boxes"]),
                                    ("ground", None, got["ground"]), ("boxes", None, own["boxes"])):
            np.testing.assert_allclose(out[i], _static_reference(o, pair, boxes3d, 12, 2.5, depth),
                                       rtol=1e-5, atol=1e-4)
    assert not np.allclose(got["boxes"], got["ground"])  # the depths differ
    with pytest.raises(ValueError, match=r"unknown static-world depth \['sky'\]"):
        crops.static_crops(objects, pairs, 12, 2.5, depths=("sky",))


def test_each_crops_part_is_stored_by_split_or_fold_and_read_from_its_node(tmp_path):
    from flowmod import dag
    from flowmod.params import load_profile

    assert crops.part_splits("general", 3) == ("general",)
    assert crops.part_splits("keyframe", 3) == ("f0", "f1", "f2")
    assert crops.part_splits("wide", 2) == ("f0", "f1")
    assert crops.part_splits("keyframe", 1) == ("train", "val", "test")
    assert crops.part_splits("wide", 1) == ("train", "val")
    assert [crops.part_of(s) for s in ("general", "train", "f1")] == [
        "general", "keyframe", "keyframe"]
    pd.DataFrame({"pair_id": ["a"], "split": ["f1"], "xmin": [1.0], "ymin": [2.0],
                  "xmax": [3.0], "ymax": [4.0]}).to_parquet(tmp_path / "objects.parquet")
    assert crops.part_objects(tmp_path, "general")["split"].tolist() == ["general"]
    assert crops.part_objects(tmp_path, "keyframe")["split"].tolist() == ["f1"]
    pd.DataFrame({"pair_id": []}).to_parquet(tmp_path / "objects.parquet")
    assert list(crops.part_objects(tmp_path, "general").columns) == [
        "pair_id", "split", "xmin", "ymin", "xmax", "ymax"]
    p = load_profile("demo").model_copy(update={"flow_methods": ["gt", "dis"],
                                                "wide_methods": ["dis"], "flow_store": "pairs"})
    assert [str(n) for n in crops.STAGE.nodes(p)] == [
        "crops[gt/keyframe]", "crops[gt/general]", "crops[dis/keyframe]", "crops[dis/general]",
        "crops[dis/wide]"]
    node = dag.Node("crops", "dis", "general")
    assert crops.STAGE.inputs(node, p) == (dag.Node("flow", "dis", "general"),
                                           dag.Node("general"))
    assert crops.STAGE.inputs(node, p.model_copy(update={"flow_store": "crops"})) == (
        dag.Node("world"), dag.Node("general"))


def test_fold_crops_reads_the_rows_of_a_role_from_a_crops_folder(tmp_path):
    """fold_crops: the crops of a node's folder that play a role for a fold's model (the
    test rows: the fold's own array, read as stored)."""
    x = np.arange(3 * 2 * 4 * 4, dtype=np.float16).reshape(3, 2, 4, 4)
    for k in range(2):
        np.save(tmp_path / f"f{k}.npy", x + k)
        pd.DataFrame({"pair_id": ["a", "b", "c"], "fold": k, "val_scene": [False, True, False],
                      "scene": ["s1", "s2", "s3"]}).to_parquet(tmp_path / f"f{k}.parquet")
    xt, dft = crops.fold_crops(tmp_path, 2, 1, "test")
    np.testing.assert_array_equal(xt, x + 1)
    assert dft["fold"].tolist() == [1, 1, 1]
    xg, dfg = crops.fold_crops(tmp_path, 2, 1, "train")
    assert len(dfg) == len(xg) and set(dfg["fold"]) == {0}
    assert dfg.index.tolist() == [0, 1]  # the train rows of fold 0, indexed afresh
    np.save(tmp_path / "general.npy", x)
    pd.DataFrame({"pair_id": ["a", "b", "c"], "fold": [1, 0, 1]}, index=[7, 8, 9]).to_parquet(
        tmp_path / "general.parquet")
    xs, dfs = crops.fold_crops(tmp_path, 2, 1, "test", part="general")
    assert dfs["pair_id"].tolist() == ["a", "c"] and dfs.index.tolist() == [0, 1]
    np.testing.assert_array_equal(xs, x[[0, 2]])


def test_static_crops_of_a_window_leaving_the_frame_take_the_edge_s_geometry(capsys):
    """A box at the frame's left edge: the window leaves the frame, where the static flow is
    that of the nearest frame pixel (as the flow crop's edge padding); every depth is filled
    whatever the order of ``depths``; no bar unless asked, a counted one when asked."""
    from flowmod import geometry

    cam1 = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.5],
                     [0.0, 0.0, 0.0, 1.0]])
    cam2 = cam1.copy()
    cam2[0, 3] += 1.0
    K = np.array([[1266.0, 0.0, 816.0], [0.0, 1266.0, 491.0], [0.0, 0.0, 1.0]])
    pairs = pd.DataFrame([{"pair_id": "p", "intrinsic": K.ravel().tolist(),
                           "cam2global_1": cam1.ravel().tolist(),
                           "cam2global_2": cam2.ravel().tolist()}])
    objects = pd.DataFrame([{"pair_id": "p", "xmin": 2.0, "ymin": 480.0, "xmax": 60.0,
                             "ymax": 530.0, "center_x": 25.0, "center_y": 12.0,
                             "center_z": 0.75, "size_w": 1.8, "size_l": 4.5, "size_h": 1.5,
                             "qw": 1.0, "qx": 0.0, "qy": 0.0, "qz": 0.0}])
    got = crops.static_crops(objects, pairs, 10, 3.0, depths=("ground", "boxes"))
    assert capsys.readouterr().err == ""
    win = crop_windows(objects[["xmin", "ymin", "xmax", "ymax"]].to_numpy(), 3.0)[0]
    assert win[0] < 0  # the window leaves the frame
    box = objects[["xmin", "ymin", "xmax", "ymax"]].to_numpy()[0]
    ground = geometry.static_flow_crop(win, 10, K, cam1, cam2, [], 0.0,
                                       image_size=(1600, 900), box2d=box)
    np.testing.assert_allclose(got["ground"], ground[None], atol=1e-4)
    unclipped = geometry.static_flow_crop(win, 10, K, cam1, cam2, [], 0.0, box2d=box)
    assert not np.allclose(ground, unclipped, atol=1e-3)
    c, rot = geometry.box_in_camera(cam1, np.array([25.0, 12.0, 0.75]), np.array([1.0, 0, 0, 0]))
    boxes = geometry.static_flow_crop(win, 10, K, cam1, cam2, [(c, np.array([1.8, 4.5, 1.5]),
                                                               rot)], 0.0, image_size=(1600, 900))
    np.testing.assert_allclose(got["boxes"], boxes[None], atol=1e-4)
    crops.static_crops(objects, pairs, 10, 3.0, progress=True)
    err = capsys.readouterr().err
    assert re.search(r"static-world crops: 100%\|[^|]*\| 1/1 \[[^]]*object/s\]", err), err


def test_a_crop_size_below_one_is_refused():
    with pytest.raises(CropsError, match=r"^size must be >= 1, got 0$"):
        crops.crop_image(np.zeros((4, 4, 2)), np.array([[0.0, 0.0, 2.0, 2.0]]), 0)
