"""Chapter 05's backend (:mod:`flowmod.chapters.ch05_preprocessing`) in quick tests, for
mutation testing: mutmut runs only the quick tests, and the chapter is otherwise checked
only by the slow notebook runs.

The published crops and flow nodes are written here by hand in a run folder of the smoke
profile (two methods, two folds: the keyframe part stored as ``f0``, ``f1``, the
generalisation set as ``general``), each with its manifest, arrays of known shapes and
flow files in the method's pool; the expected rows, objects and megabytes are worked out
here from the files' own sizes. Complements tests/test_tables.py (crop_color).
"""

from __future__ import annotations

import os

import numpy as np
import pandas as pd
import pytest

from flowmod.artefacts import write_manifest
from flowmod.chapters import ch05_preprocessing as ch05
from flowmod.crops import CropsError
from flowmod.params import load_profile
from flowmod.select import Selection

#: Objects per method and stored array (folds 2: f0, f1; then the generalisation set).
OBJECTS = {"gt": {"f0": 3, "f1": 2, "general": 4}, "dis": {"f0": 1, "f1": 0, "general": 0}}
#: Flow files per method and part, as (rows, cols) of their float16 arrays.
FLOWS = {"gt": {"keyframe": [(300, 400), (200, 400), (100, 400)],
                "general": [(450, 800), (150, 200)]},
         "dis": {"keyframe": [(250, 310)], "general": []}}
#: Side of the stored crops (px) and flow samples per object.
SIDE, SAMPLES = 40, 25


def _node(folder, fingerprint: str):
    folder.mkdir(parents=True)
    write_manifest(folder / "manifest.json", {"fingerprint": fingerprint})
    return folder


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    """The smoke profile on a run folder with the hand-made crops and flow nodes of gt and
    dis: ``(params, {method: bytes of crops, of samples, of flow files})``."""
    return _publish(tmp_path_factory.mktemp("ch05") / "runs")


def _publish(runs):
    """:func:`published`'s run folder, written at ``runs``."""
    p = load_profile("smoke", run_dir=str(runs))
    assert p.flow_methods == ["gt", "dis"] and p.folds == 2 and p.crop_size == 40
    sizes = {}
    for m, splits in OBJECTS.items():
        crop_b = sample_b = flow_b = 0
        for part, names in (("keyframe", ["f0", "f1"]), ("general", ["general"])):
            folder = _node(runs / "crops" / m / part, f"hand-made crops[{m}/{part}]")
            for split in names:
                n = splits[split]
                np.save(folder / f"{split}.npy", np.zeros((n, 2, SIDE, SIDE), np.float16))
                np.save(folder / f"{split}.samples.npy", np.zeros((n, SAMPLES, 2), np.float32))
                crop_b += (folder / f"{split}.npy").stat().st_size
                sample_b += (folder / f"{split}.samples.npy").stat().st_size
            flow = _node(runs / "flow" / m / part, f"hand-made flow[{m}/{part}]")
            pool = runs / "flow" / m / "pool"
            pool.mkdir(exist_ok=True)
            files = [f"{part}-{i}.npy" for i in range(len(FLOWS[m][part]))]
            for f, shape in zip(files, FLOWS[m][part], strict=True):
                np.save(pool / f, np.zeros((*shape, 2), np.float16))
                flow_b += (pool / f).stat().st_size
            pd.DataFrame({"pair_id": pd.Series([f"{part}-{i}" for i in range(len(files))],
                                               dtype=object),
                          "file": pd.Series(files, dtype=object),
                          "seconds": 1.0}).to_parquet(flow / "index.parquet")
        sizes[m] = (crop_b, sample_b, flow_b)
    (runs / "flow" / "dis" / "pool" / "stale.npy").write_bytes(b"\0" * 5000)  # listed by no index
    return p, sizes


def test_folders_are_each_method_s_published_crops_of_both_parts(published):
    """folders: ``{method: {part: crops/<method>/<part>}}`` for the profile's methods, the
    keyframe part first."""
    p, _ = published
    got = ch05.folders(p)
    assert list(got) == ["gt", "dis"]
    for m in ("gt", "dis"):
        assert list(got[m]) == ["keyframe", "general"]
        assert got[m] == {part: p.run_path / "crops" / m / part
                          for part in ("keyframe", "general")}


def test_run_summary_has_one_row_per_method_and_stored_array(published):
    """run_summary: per method and stored array (f0, f1, general) the objects it holds, the
    profile's crop size and the folder relative to the run folder."""
    p, _ = published
    got = ch05.run_summary(p)
    want = pd.DataFrame({
        "method": ["gt"] * 3 + ["dis"] * 3, "split": ["f0", "f1", "general"] * 2,
        "objects": [3, 2, 4, 1, 0, 0], "crop (px)": 40,
        "folder": ["crops/gt/keyframe"] * 2 + ["crops/gt/general"]
        + ["crops/dis/keyframe"] * 2 + ["crops/dis/general"]})
    pd.testing.assert_frame_equal(got, want)


def test_storage_table_gives_each_method_s_bytes_per_object_and_per_pair(published):
    """storage_table: per method the objects of all its arrays, the crops' megabytes in all
    and kilobytes per object, the flow samples' kilobytes per object, the flow files its
    nodes list (not the pool's other files) in all and per pair, beside a float32 full-frame
    flow (1600 x 900 x 2 x 4 bytes); a method of one object and one pair divides by 1; all
    to two decimals."""
    p, sizes = published
    rows = []
    for m, (crop_b, sample_b, flow_b) in sizes.items():
        n_obj = sum(OBJECTS[m].values())
        n_flow = sum(len(v) for v in FLOWS[m].values())
        rows.append({"method": m, "objects": n_obj, "crops total (MB)": crop_b / 1e6,
                     "per object (kB)": crop_b / n_obj / 1e3,
                     "flow samples per object (kB)": sample_b / n_obj / 1e3,
                     "flow pairs": n_flow, "flow total (MB)": flow_b / 1e6,
                     "flow per pair (MB)": flow_b / n_flow / 1e6,
                     "original: float32 flow per pair (MB)": 11.52})
    want = pd.DataFrame(rows).round(2)
    got = ch05.storage_table(p)
    pd.testing.assert_frame_equal(got, want)
    # the numbers themselves, worked out from the arrays' shapes (128-byte .npy headers)
    assert got["objects"].tolist() == [9, 1]
    assert got["per object (kB)"].tolist() == [round((9 * 6400 + 3 * 128) / 9 / 1e3, 2),
                                               round((6400 + 3 * 128) / 1e3, 2)]
    assert got["flow samples per object (kB)"].tolist() == [
        round((9 * 200 + 3 * 128) / 9 / 1e3, 2), round((200 + 3 * 128) / 1e3, 2)]
    assert got["flow pairs"].tolist() == [5, 1]
    assert got["flow per pair (MB)"].tolist() == [
        round((4 * (120_000 + 80_000 + 40_000 + 360_000 + 30_000) + 5 * 128) / 5 / 1e6, 2),
        round((4 * 77_500 + 128) / 1e6, 2)]



def test_storage_table_counts_megabytes_and_kilobytes_in_powers_of_ten(tmp_path):
    """Megabytes are 10^6 bytes and kilobytes 10^3 (not 2^20, nor one more): shown with two
    decimals, so each file here is grown (sparse, no disk used) to tens of gigabytes, where
    a divisor one too large moves the second decimal."""
    p, _ = _publish(tmp_path / "runs")
    grown = {}
    for m in ("gt", "dis"):
        files = [*sorted((p.run_path / "crops" / m).glob("*/*.npy")),
                 *sorted((p.run_path / "flow" / m / "pool").glob("*.npy"))]
        for f in files:
            os.truncate(f, f.stat().st_size + 30 * 10**9)
        grown[m] = files
    got = ch05.storage_table(p).set_index("method")
    gt = {kind: sum(f.stat().st_size for f in grown["gt"]
                    if f.name.endswith(".samples.npy") == (kind == "samples")
                    and (f.parent.name == "pool") == (kind == "flow"))
          for kind in ("crops", "samples", "flow")}
    assert gt["crops"] > 5 * 10**10 and gt["flow"] > 10**11
    assert got.loc["gt", "crops total (MB)"] == round(gt["crops"] / 10**6, 2)
    assert got.loc["gt", "per object (kB)"] == round(gt["crops"] / 9 / 10**3, 2)
    assert got.loc["gt", "flow samples per object (kB)"] == round(gt["samples"] / 9 / 10**3, 2)
    assert got.loc["gt", "flow total (MB)"] == round(gt["flow"] / 10**6, 2)
    assert got.loc["gt", "flow per pair (MB)"] == round(gt["flow"] / 5 / 10**6, 2)
    assert got.loc["gt", "original: float32 flow per pair (MB)"] == 11.52


def _selection() -> Selection:
    objects = pd.DataFrame({
        "set": ["keyframe"] * 6 + ["general"] * 2,
        "label": [1, 1, 0, 1, 1, 1, 1, 1],
        "pair_id": ["p1", "p2", "p1", "p3", "p2", "p3", "g1", "g1"],
        "xmin": [100.0, 200.0, 0.0, 300.0, 50.0, 10.0, 0.0, 0.0],
        "xmax": [110.0, 240.0, 500.0, 320.0, 80.0, 60.0, 1.0, 2.0],  # widths 10 40 . 20 30 50
        "ann_token": [f"a{i}" for i in range(8)]})
    pairs = pd.DataFrame({"pair_id": ["p1", "p2", "p3", "g1"], "set": ["keyframe"] * 3 + [
        "general"], "path_1": ["i1.jpg", "i2.jpg", "i3.jpg", "g.jpg"]})
    return Selection(pairs=pairs, objects=objects, scenes=pd.DataFrame())


def test_median_mover_is_the_moving_keyframe_vehicle_of_median_width():
    """median_mover: among the moving keyframe vehicles (not the still ones, not the
    generalisation set's), the one at index n // 2 of the widths' order, and its pair's
    row; with ``among``, only those of the listed pairs."""
    sel = _selection()
    row, pair = ch05.median_mover(sel)
    assert row["ann_token"] == "a4"  # widths 10 20 30 40 50: the third, 30 px
    assert pair.name == "p2" and pair["path_1"] == "i2.jpg"
    row, pair = ch05.median_mover(sel, among=["p1", "p3"])  # 10 20 50: 20 px
    assert row["ann_token"] == "a3" and pair.name == "p3" and pair["path_1"] == "i3.jpg"
    row, _ = ch05.median_mover(sel, among=iter(["p1", "p2"]))  # 10 40 30: index 1 of 3
    assert row["ann_token"] == "a4"
    row, _ = ch05.median_mover(sel, among=("p2",))  # widths 40 30: index 1 of 2, 40 px
    assert row["ann_token"] == "a1"


def test_median_mover_without_a_mover_among_the_stored_pairs_names_the_problem():
    """median_mover raises CropsError when no moving keyframe vehicle is in the pairs with
    stored flow (an empty ``among`` included)."""
    msg = "no moving keyframe vehicle among the pairs with stored flow"
    with pytest.raises(CropsError) as err:
        ch05.median_mover(_selection(), among=["g1"])
    assert str(err.value) == msg
    with pytest.raises(CropsError) as err:
        ch05.median_mover(_selection(), among=[])
    assert str(err.value) == msg
