"""Quick tests of chapter 11's backend (``flowmod/chapters/ch11_all_distances.py``: the
classifier trained on all distances against the paper's), written for mutation testing:
the chapter is otherwise checked only by slow tests on a built smoke study, which mutmut's
quick run (``-m "not slow and not world"``) leaves out.

The predictions are the hand-made study's (``handmade_study``: tests/handmade.py, the demo
profile with chapter 11's ``dis``), the selection tables are published by hand in a
run folder of their own, and the landing page's sentence is read off a hand-made Table 4.
Every expected number is computed here with numpy / scikit-learn from the same tables, not
with flowmod. Complements tests/test_chapter_numbers.py (the paired effects' values and
names) and tests/test_wide.py (the same functions on a built world).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from sklearn.metrics import f1_score

from flowmod import metrics, pipeline
from flowmod.artefacts import write_manifest
from flowmod.chapters import ch11_all_distances as ch11
from flowmod.dag import Node
from flowmod.params import Params, load_profile

#: Within 0.05 of a value shown to 0.1.
SHOWN = 0.05 + 1e-9


@pytest.fixture
def study(handmade_study):
    """The hand-made study: ``(params, {node: {table: predictions}})``."""
    return handmade_study


def _probs(df: pd.DataFrame) -> list[np.ndarray]:
    """Each model's probabilities: ``prob_s<k>`` in order, or ``prob`` alone."""
    cols = sorted((c for c in df.columns if c.startswith("prob_s")), key=lambda c: int(c[6:]))
    return [df[c].to_numpy() for c in cols or ["prob"]]


def _f1(df: pd.DataFrame) -> float:
    """F1 (%) of a predictions table: the mean over its models of each one's F1."""
    return 100 * float(np.mean([f1_score(df["label"], p > 0.5) for p in _probs(df)]))


def _tables(p: Params, tables, split: str) -> dict[bool, pd.DataFrame]:
    """``{wide: predictions}`` of dis on ``split``: trained on all distances, or the
    paper's."""
    flow = {"test": "evaluate", "general": "generalise"}[split]
    return {True: tables[Node("wgeneralise", "dis")][split],
            False: tables[Node(flow, "dis")][split]}


# --- names ----------------------------------------------------------------------------------


def test_band_and_labels_name_the_paper_s_training_range():
    """``band``: ``min-max m`` (``:g``: no trailing .0); ``label``: the method with the
    band or "all distances"; the distance bins are chapter 08's."""
    p = load_profile("demo")
    assert ch11.band(p) == "30-70 m"
    assert ch11.band(load_profile("demo", min_distance=12.5, max_distance=60)) == "12.5-60 m"
    assert ch11.label(p, "dis", False) == "dis (30-70 m)"
    assert ch11.label(p, "gt", True) == "gt (all distances)"
    assert ch11.EDGES == (0, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100.01)


def test_built_lists_the_wide_methods_whose_predictions_are_current(monkeypatch):
    """``built``: the methods of ``wide_methods``, in order, whose ``wgeneralise`` node is
    built (the graph's answer; the lookup is replaced here: hand-made nodes carry no
    fingerprints)."""
    asked = []

    def fake(params, node):
        assert params is p, "each node is asked about with the run's parameters"
        asked.append(node)
        return node in ready

    monkeypatch.setattr(ch11.pipeline, "built", fake)
    p = load_profile("demo", wide_methods=["gt", "dis"])
    ready = {Node("wgeneralise", "dis")}
    assert ch11.built(p) == ["dis"]
    assert asked == [Node("wgeneralise", "gt"), Node("wgeneralise", "dis")]
    ready = {Node("wgeneralise", "gt"), Node("wgeneralise", "dis")}
    assert ch11.built(p) == ["gt", "dis"]
    ready = set()
    assert ch11.built(p) == []
    p = load_profile("demo", wide_methods=[])
    assert ch11.built(p) == []


# --- the training sets ----------------------------------------------------------------------


def _publish(p: Params, node: Node, **tables: pd.DataFrame) -> None:
    folder = pipeline.GRAPH.node_dir(p, node)
    folder.mkdir(parents=True)
    for name, df in tables.items():
        df.to_parquet(folder / f"{name}.parquet", index=False)
    write_manifest(folder / "manifest.json", {"fingerprint": f"hand-made {node}"})


def _objects(split: list[str], label: list[int], distance: list[float]) -> pd.DataFrame:
    return pd.DataFrame({"split": split, "label": label, "distance": distance})


def test_training_summary_by_fold_counts_both_training_sets(tmp_path):
    """``training_summary`` with the demo's three folds: per training set (the paper's band,
    then all distances) and fold, the pairs, the sweep pairs among them, the objects, the
    moving share (0.1) and the distance range (whole metres)."""
    p = load_profile("demo", run_dir=str(tmp_path / "runs"))
    _publish(p, Node("select"),
             pairs=pd.DataFrame({"split": ["f0", "f0", "f1", "f2"], "set": "keyframe"}),
             objects=_objects(["f0", "f0", "f0", "f1", "f2", "f2"], [1, 0, 1, 0, 1, 1],
                              [31.4, 45.0, 68.6, 50.2, 30.0, 70.0]))
    _publish(p, Node("wide"),
             pairs=pd.DataFrame({"split": ["f0", "f0", "f0", "f1", "f2", "f2"],
                                 "set": ["keyframe", "sweep", "sweep", "sweep", "keyframe",
                                         "keyframe"]}),
             objects=_objects(["f0"] * 4 + ["f1"] + ["f2"] * 3, [1, 0, 0, 0, 1, 0, 1, 1],
                              [2.4, 10.0, 95.6, 40.0, 12.0, 5.0, 6.0, 7.0]))
    t = ch11.training_summary(p)
    assert t.columns.tolist() == ["training set", "split", "pairs", "of them sweep pairs",
                                  "objects", "moving (%)", "distance (m)"]
    assert t.to_dict("list") == {
        "training set": ["paper: 30-70 m keyframes"] * 3 + ["all distances"] * 3,
        "split": ["f0", "f1", "f2"] * 2, "pairs": [2, 1, 1, 3, 1, 2],
        "of them sweep pairs": [0, 0, 0, 2, 1, 0], "objects": [3, 1, 2, 4, 1, 3],
        "moving (%)": [66.7, 0.0, 100.0, 25.0, 100.0, 66.7],
        "distance (m)": ["31-69", "50-50", "30-70", "2-96", "12-12", "5-7"]}


def test_training_summary_of_one_split_has_no_test_rows(tmp_path):
    """``training_summary`` with one fold: the train and val splits of each set only (the
    all-distances part has no test split)."""
    p = load_profile("demo", folds=1, run_dir=str(tmp_path / "runs"))
    for node in (Node("select"), Node("wide")):
        _publish(p, node, pairs=pd.DataFrame({"split": ["train", "val", "test"],
                                              "set": "keyframe"}),
                 objects=_objects(["train", "train", "val", "test"], [1, 0, 1, 1],
                                  [40.0, 60.0, 50.0, 35.0]))
    t = ch11.training_summary(p)
    assert t["split"].tolist() == ["train", "val", "train", "val"]
    assert t["objects"].tolist() == [2, 1, 2, 1]
    assert t["moving (%)"].tolist() == [50.0, 100.0, 50.0, 100.0]


def test_near_counts_count_vehicles_nearer_than_the_band_within_table4(tmp_path):
    """``near_counts``: in the all-distances training set (``wide``) and Table 4's set
    (``general``), the vehicles nearer than ``min_distance`` (strictly) and within
    ``general_max_distance`` (inclusive), and the movers among them; NaN without
    ``wide_methods``."""
    p = load_profile("demo", run_dir=str(tmp_path / "a" / "runs"), general_max_distance=20)
    _publish(p, Node("wide"), objects=_objects(["train"] * 6, [1, 0, 1, 1, 1, 0],
                                                [5.0, 20.0, 20.5, 29.9, 30.0, 80.0]))
    _publish(p, Node("general"), objects=_objects(["general"] * 4, [1, 1, 0, 1],
                                                   [10.0, 19.0, 25.0, 30.0]))
    assert ch11.near_counts(p) == {"wide_near_train": 2.0, "wide_near_train_moving": 1.0,
                                   "wide_near_general": 2.0, "wide_near_general_moving": 2.0}
    q = load_profile("demo", run_dir=str(tmp_path / "b" / "runs"))  # 30 m, Table 4 to 70 m
    _publish(q, Node("wide"), objects=_objects(["train"] * 6, [1, 0, 1, 1, 1, 0],
                                                [5.0, 20.0, 20.5, 29.9, 30.0, 80.0]))
    _publish(q, Node("general"), objects=_objects(["general"] * 4, [1, 1, 0, 1],
                                                   [10.0, 19.0, 25.0, 30.0]))
    got = ch11.near_counts(q)
    assert got == {"wide_near_train": 4.0, "wide_near_train_moving": 3.0,
                   "wide_near_general": 3.0, "wide_near_general_moving": 2.0}
    assert all(isinstance(v, float) for v in got.values())
    none = ch11.near_counts(load_profile("demo", wide_methods=[]))
    assert list(none) == ["wide_near_train", "wide_near_train_moving", "wide_near_general",
                          "wide_near_general_moving"]
    assert all(np.isnan(v) for v in none.values())


# --- the predictions and the tables -------------------------------------------------------


def test_predictions_are_each_classifier_s_published_table(study):
    """``predictions``: trained on all distances, the ``wgeneralise`` node's table of the
    split; the paper's, chapter 07's test table or chapter 08's generalisation table."""
    p, tables = study
    for split in ("general", "test"):
        for wide, want in _tables(p, tables, split).items():
            pd.testing.assert_frame_equal(ch11.predictions(p, "dis", split, wide), want)


def test_table4_sets_the_all_distances_row_beside_the_paper_s(study):
    """``table4``: per wide method the paper's classifier, then (when built) the one trained
    on all distances, each on Table 4's range (<= 70 m) and beyond it, scored against the
    paper's label: F1 the mean over the table's models, the objects of each range."""
    p, tables = study
    got = ch11.table4(p, ["dis"])
    assert got["method"].tolist() == ["dis (30-70 m)"] * 2 + ["dis (all distances)"] * 2
    assert got["vehicles"].tolist() == ["0-70 m (Table 4)", "beyond 70 m"] * 2
    assert set(got["scored against"]) == {"paper rule (previous keyframe)"}
    for i, wide in enumerate((False, True)):
        df = _tables(p, tables, "general")[wide]
        near, far = df[df["distance"] <= 70], df[df["distance"] > 70]
        rows = got.iloc[2 * i:2 * i + 2]
        assert rows["F1 (%)"].tolist() == pytest.approx([_f1(near), _f1(far)], abs=SHOWN)
        assert rows["objects"].tolist() == [len(near), len(far)]
    only = ch11.table4(p, [])
    assert only["method"].tolist() == ["dis (30-70 m)"] * 2
    assert only["F1 (%)"].tolist() == got["F1 (%)"].tolist()[:2]


def test_comparisons_pair_on_table4_s_range_by_default_with_the_run_s_seed(study):
    """``comparisons`` (default split: the generalisation set within Table 4's range): one
    row named "dis: all distances - 30-70 m", on the objects within 70 m, its interval the
    paired bootstrap with the run's seed, scenes only (the wide classifier is one model a
    fold)."""
    p, tables = study
    t = ch11.comparisons(p, ["dis"])
    ab = {w: df[df["distance"] <= 70] for w, df in _tables(p, tables, "general").items()}
    assert t["comparison"].tolist() == ["dis: all distances - 30-70 m"]
    row = t.iloc[0]
    assert row["objects"] == len(ab[True]) < len(tables[Node("generalise", "dis")]["general"])
    assert row["scenes"] == ab[True]["scene"].nunique()
    assert row["ΔF1 (points)"] == pytest.approx(_f1(ab[True]) - _f1(ab[False]), abs=SHOWN)
    assert row["interval counts"] == "scenes only"
    want = metrics.paired_comparison(ab[True]["label"].to_numpy(), np.array(_probs(ab[True])),
                                     np.array(_probs(ab[False])), ab[True]["scene"].to_numpy(),
                                     seed=p.seed, folds=ab[True]["fold"].to_numpy())
    lo, hi = want["ci"]
    assert row["95% CI, scenes and seeds (points)"] == (
        f"{100 * lo:.1f} to {100 * hi:.1f} (9 scenes: too few)")
    assert ch11.comparisons(p, []).empty



def test_comparisons_on_the_test_split_take_every_object_with_the_seed_given(study):
    """On the test split both classifiers are compared on every test object, whatever
    Table 4's range; the interval is the paired bootstrap drawn with ``params.seed`` (not
    the default 0)."""
    p, tables = study
    p5 = p.model_copy(update={"seed": 5})
    t = ch11.comparisons(p5, ["dis"], "test")
    ab = _tables(p, tables, "test")
    row = t.iloc[0]
    assert row["objects"] == len(ab[True]) == len(tables[Node("evaluate", "dis")]["test"])
    assert row["ΔF1 (points)"] == pytest.approx(_f1(ab[True]) - _f1(ab[False]), abs=SHOWN)
    want = metrics.paired_comparison(ab[True]["label"].to_numpy(), np.array(_probs(ab[True])),
                                     np.array(_probs(ab[False])), ab[True]["scene"].to_numpy(),
                                     seed=5, folds=ab[True]["fold"].to_numpy())
    lo, hi = want["ci"]
    assert row["95% CI, scenes and seeds (points)"].startswith(
        f"{100 * lo:.1f} to {100 * hi:.1f} ")
    near = ch11.comparisons(p5.model_copy(update={"general_max_distance": 40.0}), ["dis"],
                            "test")
    pd.testing.assert_frame_equal(near, t)


def test_comparisons_of_tables_of_other_objects_name_the_method(study, monkeypatch):
    """Two classifiers' predictions of different objects cannot be paired: one error that
    names the method's two classifiers."""
    p, tables = study
    real = ch11.predictions

    def shifted(params, method, split, wide):
        df = real(params, method, split, wide)
        return df.iloc[1:] if wide else df

    monkeypatch.setattr(ch11, "predictions", shifted)
    with pytest.raises(ValueError, match=r"^dis: the two classifiers were scored on "
                                         "different objects$"):
        ch11.comparisons(p, ["dis"])


def _bin_f1(y: np.ndarray, probs: list[np.ndarray]) -> float:
    """The mean over models of F1 (NaN without a mover), by hand."""
    out = []
    for pr in probs:
        call = pr > 0.5
        tp, fp, fn = (call & (y == 1)).sum(), (call & (y == 0)).sum(), (~call & (y == 1)).sum()
        out.append(2 * tp / (2 * tp + fp + fn) if tp + fn else np.nan)
    return float(np.mean(out))


def test_by_distance_bins_both_classifiers_of_each_method(study):
    """``by_distance``: per method the paper's classifier then the all-distances one, each
    on the whole generalisation set in chapter 08's 10 m bins (left-closed): the objects,
    movers, F1 (mean over models) and scenes of each bin."""
    p, tables = study
    got = ch11.by_distance(p, ["dis"])
    assert list(got) == ["dis (30-70 m)", "dis (all distances)"]
    edges = ch11.EDGES
    for wide, df in _tables(p, tables, "general").items():
        t = got[ch11.label(p, "dis", wide)]
        k = np.digitize(df["distance"].to_numpy(), edges) - 1  # bin i: [e_i, e_{i+1})
        present = sorted(set(k))
        assert t["distance_bin"].tolist() == [
            f"[{float(edges[i])}, {float(edges[i + 1])})" for i in present]
        y = df["label"].to_numpy()
        assert t["n"].tolist() == [int((k == i).sum()) for i in present]
        assert t["n_moving"].tolist() == [int(y[k == i].sum()) for i in present]
        want = [_bin_f1(y[k == i], [pr[k == i] for pr in _probs(df)]) for i in present]
        np.testing.assert_allclose(t["f1"].to_numpy(), want, equal_nan=True)
        assert t["scenes"].tolist() == [df["scene"][k == i].nunique() for i in present]


def _far(y: np.ndarray, probs: list[np.ndarray]) -> float:
    """The mean over models of the share of still objects called moving (%)."""
    return 100 * float(np.mean([(pr[y == 0] > 0.5).mean() for pr in probs]))


@pytest.mark.parametrize("near", [30.0, 20.5, "a vehicle's distance"])
def test_near_far_scores_near_and_far_vehicles_of_table4_s_range(study, near):
    """``near_far``: per classifier (the paper's, then all distances) on Table 4's range,
    F1 and the still vehicles called moving (means over models, to 0.1), objects and movers,
    nearer than ``near`` m and from ``near`` m (a vehicle exactly there counts as far) to
    70 m."""
    p, tables = study
    if near == 30.0:
        got = ch11.near_far(p, ["dis"])
    else:
        if not isinstance(near, float):  # the 40th nearest vehicle's distance
            near = float(np.sort(tables[Node("wgeneralise", "dis")]["general"]["distance"])[40])
            assert f"{near:g}" != "30"
        got = ch11.near_far(p, ["dis"], near)
    a, b = f"< {near:g} m", f"{near:g}-70 m"
    assert got.columns.tolist() == [
        "classifier", f"F1 {a} (%)", f"still called moving {a} (%)", f"n {a}", f"moving {a}",
        f"F1 {b} (%)", f"still called moving {b} (%)", f"n {b}", f"moving {b}"]
    assert got["classifier"].tolist() == ["dis (30-70 m)", "dis (all distances)"]
    for i, wide in enumerate((False, True)):
        df = _tables(p, tables, "general")[wide]
        df = df[df["distance"] <= 70]
        for name, part in ((a, df[df["distance"] < near]), (b, df[df["distance"] >= near])):
            y = part["label"].to_numpy()
            row = got.iloc[i]
            f1, fa = row[f"F1 {name} (%)"], row[f"still called moving {name} (%)"]
            assert f1 == pytest.approx(_f1(part), abs=SHOWN), (wide, name)
            assert fa == pytest.approx(_far(y, _probs(part)), abs=SHOWN), (wide, name)
            assert (round(f1, 1), round(fa, 1)) == (f1, fa)  # shown to 0.1
            assert (row[f"n {name}"], row[f"moving {name}"]) == (len(y), int(y.sum()))
    assert got.iloc[0, 1:].tolist() != got.iloc[1, 1:].tolist()


# --- words ----------------------------------------------------------------------------------


def test_built_note_names_the_built_methods_and_the_models_still_to_train():
    """``built_note``: without ``wide_methods`` how to set them; else "d of n" and, while
    some are missing, which and their models (parts a method: the demo's three folds)."""
    assert ch11.built_note(load_profile("demo", wide_methods=[]), []) == (
        "This profile trains no classifier on all distances (`wide_methods` is empty). Set "
        "it (e.g. `wide_methods=[dis]`) and run `make extensions`.")
    demo = load_profile("demo")
    assert ch11.built_note(demo, []) == (
        "Methods trained on all distances with these parameters: **0 of 1** (none). The "
        "other 1 (dis; 3 models) are trained by `make extensions` (or this chapter with "
        "`extension_build=true`).")
    assert ch11.built_note(demo, ["dis"]) == (
        "Methods trained on all distances with these parameters: **1 of 1** (dis).")
    two = load_profile("demo", wide_methods=["gt", "dis"])
    assert ch11.built_note(two, ["dis"]) == (
        "Methods trained on all distances with these parameters: **1 of 2** (dis). The "
        "other 1 (gt; 3 models) are trained by `make extensions` (or this chapter with "
        "`extension_build=true`).")
    assert "(gt, dis; 6 models)" in ch11.built_note(two, [])


def _table4(rows: dict[str, tuple[float, float, float]]) -> pd.DataFrame:
    """A hand-made Table 4: per label (Table 4's F1 against the paper's label, the true
    label's F1, F1 beyond the range) three rows, only the first of which headlines quote."""
    out = []
    for method, (paper, true, beyond) in rows.items():
        out += [{"method": method, "vehicles": "0-70 m (Table 4)",
                 "scored against": "paper rule (previous keyframe)", "F1 (%)": paper,
                 metrics.CI_COLUMN: f"{paper - 5:.1f}-{paper + 5:.1f}"},
                {"method": method, "vehicles": "0-70 m (Table 4)",
                 "scored against": "true label at the frame", "F1 (%)": true,
                 metrics.CI_COLUMN: "0.0-1.0"},
                {"method": method, "vehicles": "beyond 70 m",
                 "scored against": "paper rule (previous keyframe)", "F1 (%)": beyond,
                 metrics.CI_COLUMN: "2.0-3.0"}]
    return pd.DataFrame(out)


def _paired(*deltas: float) -> pd.DataFrame:
    return pd.DataFrame({"ΔF1 (points)": list(deltas),
                         "95% CI, scenes and seeds (points)": [f"{d - 1:.1f} to {d + 1:.1f}"
                                                               for d in deltas],
                         "verdict": "A better", "detectable (points)": 3.0})


def test_headline_quotes_table4_s_f1_of_both_trainings_and_their_difference():
    """``headline``: Table 4's F1 (paper's label, Table 4's range) of the main built method
    trained on all distances, its interval, the paper's training's F1, and with a paired
    table of one row per built method its row's difference; the main method is the first
    built one other than gt (gt when it is the only one)."""
    demo = load_profile("demo")
    table = _table4({"dis (30-70 m)": (75.4, 11.1, 22.2),
                     "dis (all distances)": (81.26, 33.3, 44.4)})
    head = ("trained on every distance up to 70 m instead of 30-70 m keyframes only, the dis "
            "classifier reaches Table 4 F1 81.3 % (interval over scenes and seeds 76.3-86.3 %) "
            "against 75.4 %")
    assert ch11.headline(demo, table, ["dis"]) == head
    assert ch11.headline(demo, table, ["dis"], _paired(5.84)) == head + (
        ": +5.8 F1 points (95 % interval over scenes and training seeds 4.8 to 6.8)")
    assert ch11.headline(demo, table, ["dis"], _paired(5.84, 1.0)) == head
    two = load_profile("demo", wide_methods=["gt", "dis"], general_max_distance=60)
    table2 = pd.concat([table, _table4({"gt (30-70 m)": (90.0, 1.0, 2.0),
                                        "gt (all distances)": (95.0, 3.0, 4.0)})])
    both = ch11.headline(two, table2, ["gt", "dis"], _paired(-2.0, 5.84))
    assert both.startswith("trained on every distance up to 60 m instead of 30-70 m "
                           "keyframes only, the dis classifier reaches Table 4 F1 81.3 %")
    assert both.endswith("against 75.4 %: +5.8 F1 points (95 % interval over scenes and "
                         "training seeds 4.8 to 6.8)")
    gt = ch11.headline(two, table2, ["gt"], _paired(-2.0))
    assert gt == ("trained on every distance up to 60 m instead of 30-70 m keyframes only, "
                  "the gt classifier reaches Table 4 F1 95.0 % (interval over scenes and seeds "
                  "90.0-100.0 %) against 90.0 %: -2.0 F1 points (95 % interval over scenes and "
                  "training seeds -3.0 to -1.0)")


def test_headline_says_when_the_chapter_is_not_part_of_the_profile_or_not_built():
    """``headline`` without a built method: not part of the profile (no ``wide_methods``),
    or not built with the number of models ``make extensions`` trains."""
    assert ch11.headline(load_profile("demo", wide_methods=[]), pd.DataFrame(), []) == (
        "not part of this profile (wide_methods is empty)")
    assert ch11.headline(load_profile("demo"), pd.DataFrame(), []) == (
        "not built in this run (make extensions trains them: 3 models)")
    assert ch11.headline(load_profile("demo", wide_methods=["gt", "dis"], folds=1),
                         pd.DataFrame(), []) == (
        "not built in this run (make extensions trains them: 2 models)")
