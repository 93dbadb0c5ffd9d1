"""Chapter 10's backend (:mod:`flowmod.chapters.ch10_inputs`) on hand-made inputs.

Mutation testing of chapter 10's backend found that only the slow notebook tests ran most of
its functions, so that almost every mutant survived the quick tests. These quick tests pin
what each function shows: which chains count as built and in which order the table lists
them, which published table a chain reads, the table's numbers (computed here with
scikit-learn from the same hand-made predictions: ``handmade_study``, tests/handmade.py),
the context crops a role reads, the static world's share of the flow, and the exact words
and names the chapter glues. ``tests/test_chapter_numbers.py`` already checks that every
paired effect is A minus B of its own tables; this file complements it.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from handmade import publish
from sklearn.metrics import f1_score, precision_score, recall_score

from flowmod import pipeline
from flowmod.artefacts import write_manifest
from flowmod.chapters import ch10_inputs as ch10
from flowmod.dag import Node
from flowmod.params import load_profile

#: The table's columns, in order.
TABLE_COLUMNS = ["flow method", "input", "channels", "F1 (%)", "folds (%)",
                 "seed SD of the pooled F1 (points)", "one retraining's SD (points)",
                 "95% CI, scenes and seeds (%)", "P (%)", "R (%)"]
#: Every input's name in a table.
LABELS = {"flow": "flow",
          "residual": "residual [oracle: annotated-box depth]",
          "residual-deployed": "residual-deployed [idealised: exact poses, flat ground, "
                               "annotated 2D box]",
          "flow+static": "flow+static [oracle: annotated-box depth]",
          "images": "images [untuned recipe]",
          "images+flow": "images+flow [untuned recipe]"}
ORACLE = " (static world with annotated-box depth, an oracle a car does not have)"
DEPLOYED = (" (static world from exact ego poses, an exactly flat ground and the target's "
            "annotated 2D box: a car with perfect odometry and detector)")


@pytest.fixture
def study(handmade_study):
    """The hand-made study (tests/handmade.py): ``(params, {node: {table: predictions}})``;
    chapter 10's inputs on gt and dis."""
    return handmade_study


def _demo(**kw):
    """The demo profile with chapter 10 on gt and dis (its other values as they are)."""
    return load_profile("demo", **{"extension_methods": ["gt", "dis"], **kw})


def _built_on_dis_and_images(monkeypatch, seen=None, asked=None):
    """Say that the ``xevaluate`` nodes of dis and of the images alone are built (hand-made
    nodes have no fingerprints to say it), recording the nodes asked about (and with which
    parameters)."""
    def built(params, node):
        if seen is not None:
            seen.append(node)
        if asked is not None:
            asked.append(params)
        return node.stage == "xevaluate" and (node.method == "dis" or node.part == "images")

    monkeypatch.setattr(pipeline, "built", built)


# --- chains ---------------------------------------------------------------------------------


def test_built_keeps_the_chains_whose_evaluation_is_built_in_chain_order(monkeypatch):
    """The built chains, in :func:`~flowmod.extensions.inputs.chains`' order (input by
    input), each asked about by its ``xevaluate`` node."""
    seen: list[Node] = []
    asked: list = []
    _built_on_dis_and_images(monkeypatch, seen, asked)
    p = _demo()
    assert ch10.built(p) == [("dis", "residual"), ("dis", "residual-deployed"),
                             (None, "images"), ("dis", "images+flow")]
    assert asked and all(a is p for a in asked), "each node is asked about with the run's"
    assert seen == [Node("xevaluate", m, v) for m, v in (
        ("gt", "residual"), ("dis", "residual"), ("gt", "residual-deployed"),
        ("dis", "residual-deployed"), (None, "images"), ("gt", "images+flow"),
        ("dis", "images+flow"))]


def test_rows_give_each_method_its_raw_flow_then_its_built_inputs_then_the_images(
        monkeypatch):
    """Per extension method its raw flow (built or not), then its built inputs; the images
    alone last."""
    _built_on_dis_and_images(monkeypatch)
    assert ch10.rows(_demo()) == [("gt", "flow"), ("dis", "flow"), ("dis", "residual"),
                                  ("dis", "residual-deployed"), ("dis", "images+flow"),
                                  (None, "images")]
    assert ch10.rows(_demo(extension_methods=["dis"], extension_inputs=["images"])) == [
        ("dis", "flow"), (None, "images")]


def test_predictions_read_each_chain_s_own_published_table(study):
    """The raw flow reads the paper's classifiers (chapter 07's test predictions, chapter
    08's generalisation set); an input reads its own chain's table of the split."""
    p, tables = study
    cases = {("dis", "flow", "test"): tables[Node("evaluate", "dis")]["test"],
             ("gt", "flow", "general"): tables[Node("generalise", "gt")]["general"],
             ("gt", "residual", "test"): tables[Node("xevaluate", "gt", "residual")]["test"],
             ("dis", "images+flow", "general"):
                 tables[Node("xevaluate", "dis", "images+flow")]["general"],
             (None, "images", "test"): tables[Node("xevaluate", None, "images")]["test"]}
    for (m, v, split), want in cases.items():
        pd.testing.assert_frame_equal(ch10.predictions(p, m, v, split), want)


# --- the table ------------------------------------------------------------------------------


def _scores(df):
    """What the table shows of a predictions table, computed with scikit-learn: F1, the
    folds' range, the two seed spreads (points; "-" for one model a fold), P and R."""
    cols = [c for c in df.columns if c.startswith("prob_s")] or ["prob"]
    y, fold = df["label"].to_numpy(), df["fold"].to_numpy()
    calls = [df[c].to_numpy() > 0.5 for c in cols]
    f1 = [f1_score(y, c) for c in calls]
    per_fold = [[f1_score(y[fold == k], c[fold == k]) for c in calls] for k in range(3)]
    fold_f1 = [np.mean(f) for f in per_fold]
    seed_sd = np.std(f1, ddof=1) if len(cols) > 1 else np.nan
    retrain = np.sqrt(np.mean([np.var(f, ddof=1) for f in per_fold])) if len(cols) > 1 \
        else np.nan
    return {"F1 (%)": round(100 * np.mean(f1), 1),
            "folds (%)": f"{100 * min(fold_f1):.1f}-{100 * max(fold_f1):.1f}",
            "seed SD of the pooled F1 (points)": "-" if np.isnan(seed_sd)
            else f"{100 * seed_sd:.1f}",
            "one retraining's SD (points)": "-" if np.isnan(retrain) else f"{100 * retrain:.1f}",
            "P (%)": round(100 * np.mean([precision_score(y, c) for c in calls]), 1),
            "R (%)": round(100 * np.mean([recall_score(y, c) for c in calls]), 1)}


def _check_table(got, chains, frames):
    """``got`` has the table's columns and one row per chain, in order, each with the
    numbers of its own predictions (``frames``) and an interval over the 9 scenes."""
    assert got.columns.tolist() == TABLE_COLUMNS
    assert got["flow method"].tolist() == [m or "-" for m, _ in chains]
    assert got["input"].tolist() == [LABELS[v] for _, v in chains]
    assert got["channels"].tolist() == [{"flow": 2, "residual": 2, "images": 6,
                                         "residual-deployed": 2, "images+flow": 8}[v]
                                        for _, v in chains]
    for i, df in enumerate(frames):
        row = got.iloc[i]
        for col, want in _scores(df).items():
            assert row[col] == (pytest.approx(want, abs=1e-9) if isinstance(want, float)
                                else want), (chains[i], col)
        ci = row["95% CI, scenes and seeds (%)"]
        assert ci.endswith(" (9 scenes: too few)"), ci
        lo, hi = (float(x) for x in ci.split(" ")[0].split("-"))
        assert lo < row["F1 (%)"] < hi


def test_table_scores_each_chain_on_its_own_test_predictions(study):
    """One row per chain given, in order: the method ("-" without flow), the input's label
    and channels, F1, the folds' range, seed spreads, interval, P and R of its own test
    predictions (three seeds for the raw flow, one model a fold for the inputs)."""
    p, tables = study
    chains = [("dis", "flow"), ("gt", "residual"), (None, "images"), ("gt", "flow")]
    frames = [tables[Node("evaluate", "dis")]["test"],
              tables[Node("xevaluate", "gt", "residual")]["test"],
              tables[Node("xevaluate", None, "images")]["test"],
              tables[Node("evaluate", "gt")]["test"]]
    _check_table(ch10.table(p, chains), chains, frames)
    # the test split is scored whole: Table 4's range filters the generalisation set only
    near = p.model_copy(update={"general_max_distance": 40.0})
    assert all((f["distance"] > 40.0).any() for f in frames)
    _check_table(ch10.table(near, chains), chains, frames)


def test_table_on_the_general_split_scores_within_table_4_s_range(study):
    """On the generalisation set each chain is scored on its objects within
    ``general_max_distance`` (70 m) only."""
    p, tables = study
    chains = [("dis", "flow"), ("dis", "images+flow")]
    frames = [tables[Node("generalise", "dis")]["general"],
              tables[Node("xevaluate", "dis", "images+flow")]["general"]]
    assert p.general_max_distance == 70.0 and (frames[0]["distance"] > 70.0).any()
    _check_table(ch10.table(p, chains, split="general"), chains,
                 [df[df["distance"] <= 70.0] for df in frames])


def test_table_lists_the_built_rows_by_default_and_draws_with_the_profile_s_seed(
        study, monkeypatch):
    """Without chains given, the table lists :func:`rows` (raw flows, built inputs, images);
    its intervals' draws follow ``params.seed``."""
    p, tables = study
    _built_on_dis_and_images(monkeypatch)
    got = ch10.table(p)
    assert list(zip(got["flow method"], got["input"], strict=True)) == [
        ("gt", "flow"), ("dis", "flow"), ("dis", LABELS["residual"]),
        ("dis", LABELS["residual-deployed"]), ("dis", LABELS["images+flow"]),
        ("-", LABELS["images"])]
    col = "95% CI, scenes and seeds (%)"
    other = ch10.table(p.model_copy(update={"seed": 5}))
    assert other[col].tolist() != got[col].tolist()
    assert other["F1 (%)"].tolist() == got["F1 (%)"].tolist()


# --- paired comparisons ---------------------------------------------------------------------


def _f1(df):
    cols = [c for c in df.columns if c.startswith("prob_s")] or ["prob"]
    return float(np.mean([f1_score(df["label"], df[c] > 0.5) for c in cols]))


def test_comparisons_of_the_built_rows_skip_the_raw_flows_on_the_test_split(
        study, monkeypatch):
    """By default: every built input of :func:`rows` (not the raw flows themselves), each
    minus its method's raw flow on the test split; the intervals follow ``params.seed``."""
    p, tables = study
    _built_on_dis_and_images(monkeypatch)
    got = ch10.comparisons(p)
    assert got["comparison"].tolist() == [
        f"dis: {LABELS['residual']} - dis: flow",
        f"dis: {LABELS['residual-deployed']} - dis: flow",
        f"dis: {LABELS['images+flow']} - dis: flow",
        f"{LABELS['images']} - gt: flow"]
    want = 100 * (_f1(tables[Node("xevaluate", None, "images")]["test"])
                  - _f1(tables[Node("evaluate", "gt")]["test"]))
    assert got["ΔF1 (points)"].iloc[-1] == pytest.approx(want, abs=0.05 + 1e-9)
    col = "95% CI, scenes and seeds (points)"
    other = ch10.comparisons(p.model_copy(update={"seed": 5}))
    assert other[col].tolist() != got[col].tolist()
    # the test split is compared whole, whatever Table 4's range
    near = ch10.comparisons(p.model_copy(update={"general_max_distance": 40.0}))
    pd.testing.assert_frame_equal(near, got)


def test_a_comparison_of_tables_of_other_objects_names_both_chains(tmp_path):
    """An input's predictions and its raw flow's on different objects cannot be paired: the
    error names the two chains."""
    p = _demo(extension_methods=["dis"], run_dir=str(tmp_path / "runs"))
    rows = pd.DataFrame({"ann_token": ["a", "b"], "label": [1, 0], "scene": ["s", "t"],
                         "fold": [0, 1], "prob": [0.9, 0.1], "distance": [40.0, 50.0]})
    publish(p, Node("evaluate", "dis"), {"test": rows})
    publish(p, Node("xevaluate", "dis", "residual"),
             {"test": rows.assign(ann_token=["a", "c"])})
    with pytest.raises(ValueError, match=r"^dis/residual and dis/flow were scored on "
                                         "different objects$"):
        ch10.comparisons(p, rows_of=[("dis", "residual")])


def test_reference_and_comparison_names():
    """An input is compared with its own method's raw flow, the images alone with the first
    extension method's; the row names say both sides with the input's label."""
    p = _demo()
    assert ch10.reference(p, "dis") == "dis"
    assert ch10.reference(p, None) == "gt"
    assert ch10.comparison_name(p, "dis", "residual") == (
        "dis: residual [oracle: annotated-box depth] - dis: flow")
    assert ch10.comparison_name(p, None, "images") == "images [untuned recipe] - gt: flow"
    assert ch10.comparison_name(_demo(extension_methods=["dis", "gt"]), None, "images") == (
        "images [untuned recipe] - dis: flow")


# --- inputs and their labels ----------------------------------------------------------------


def test_inputs_table_lists_every_input_with_its_channels_and_flip():
    """One row per input: name, channels, what it holds, the channels a flip negates ("-"
    for none)."""
    want = pd.DataFrame({
        "input": ["flow", "residual", "residual-deployed", "flow+static", "images",
                  "images+flow"],
        "channels": [2, 2, 2, 4, 6, 8],
        "holds": ["raw flow (the paper)", "flow minus static-world flow",
                  "flow minus static-world flow, target depth from its 2D box",
                  "flow and static-world flow", "the two images, no flow",
                  "flow and the two images"],
        "negated by a flip": ["0", "0", "0", "0, 2", "-", "0"]})
    pd.testing.assert_frame_equal(ch10.inputs_table(), want)


def test_input_labels_and_depth_notes_name_oracles_idealisations_and_images():
    """Tables tag the inputs whose static world reads annotated boxes (oracle) or idealised
    measurements, and those with images (untuned recipe); headlines say the depth in full
    ('' without a static world)."""
    for v, label in LABELS.items():
        assert ch10.input_label(v) == label, v
    notes = {"flow": "", "residual": ORACLE, "residual-deployed": DEPLOYED,
             "flow+static": ORACLE, "images": "", "images+flow": ""}
    for v, note in notes.items():
        assert ch10.depth_note(v) == note, v


def test_glue_keys_name_the_method_or_none_and_the_input_without_plus():
    """``<method or none>_<input, + as _>``."""
    assert ch10.glue_key("dis", "flow+static") == "dis_flow_static"
    assert ch10.glue_key(None, "images") == "none_images"
    assert ch10.glue_key("gt", "images+flow") == "gt_images_flow"
    assert ch10.glue_key("dis", "residual-deployed") == "dis_residual-deployed"


def test_explains_method_is_the_exact_flow_where_the_profile_has_it():
    """The static world is measured on the exact flow's crops where there is one, else on
    the first extension method's."""
    assert ch10.explains_method(_demo(extension_methods=["dis"])) == "gt"
    p = load_profile("demo", flow_methods=["farneback", "dis"], raw_input_methods=["dis"],
                     extension_methods=["dis", "farneback"], wide_methods=["dis"])
    assert ch10.explains_method(p) == "dis"


# --- the context crops ----------------------------------------------------------------------


def _write_context(folder, split, df):
    """A context node's files of one split: static (value 1 + row), deployed (value -1 -
    row), images (value 10 + row), index ``df``."""
    folder.mkdir(parents=True, exist_ok=True)
    n = len(df)
    rows = np.arange(n, dtype=np.float32)[:, None, None, None]
    np.save(folder / f"{split}.static.npy", (1 + rows + np.zeros((n, 2, 3, 3))).astype(np.float16))
    np.save(folder / f"{split}.deployed.npy", (-1 - rows + np.zeros((n, 2, 3, 3))).astype(
        np.float16))
    np.save(folder / f"{split}.images.npy", (10 + rows + np.zeros((n, 6, 3, 3))).astype(np.uint8))
    df.to_parquet(folder / f"{split}.parquet", index=False)


def test_context_split_reads_a_role_of_fold_0_a_stored_split_or_the_general_set(tmp_path):
    """With three folds: ``test`` is fold 0's array; ``train`` and ``val`` gather the other
    folds' rows of that role; a stored split (``f2``) and the generalisation set are read
    as stored; always the static world with annotated-box depth."""
    p = _demo(run_dir=str(tmp_path / "runs"))
    assert p.folds == 3
    key = pipeline.GRAPH.node_dir(p, Node("context", None, "keyframe"))
    gen = pipeline.GRAPH.node_dir(p, Node("context", None, "general"))
    for k, val in enumerate([[False, True], [True, False, False], [False, True, False]]):
        df = pd.DataFrame({"ann_token": [f"f{k}-{i}" for i in range(len(val))], "fold": k,
                           "val_scene": val})
        _write_context(key, f"f{k}", df)
    _write_context(gen, "general", pd.DataFrame({"ann_token": ["g0", "g1", "g2", "g3"],
                                                 "fold": [0, 1, 0, 2], "val_scene": False}))
    for folder in (key, gen):
        write_manifest(folder / "manifest.json", {"fingerprint": "hand-made"})
    want = {"test": (["f0-0", "f0-1"], [1, 2]), "train": (["f1-1", "f1-2", "f2-0", "f2-2"],
                                                           [2, 3, 1, 3]),
            "val": (["f1-0", "f2-1"], [1, 2]), "f2": (["f2-0", "f2-1", "f2-2"], [1, 2, 3]),
            "general": (["g0", "g1", "g2", "g3"], [1, 2, 3, 4])}
    for split, (tokens, static) in want.items():
        s, images, df = ch10.context_split(p, split)
        assert df["ann_token"].tolist() == tokens, split
        assert np.asarray(s)[:, 0, 0, 0].tolist() == static, split  # static, not deployed
        assert np.asarray(images)[:, 0, 0, 0].tolist() == [9 + x for x in static], split
        assert np.asarray(s).shape == (len(tokens), 2, 3, 3), split


def test_static_explains_takes_medians_in_the_box_s_square_per_class():
    """Per class (still, moving): objects, the median over objects of the median flow
    magnitude in the middle third of the crop, of the residual's, and of their ratio (a
    flow of 0 divided by 1e-6 px); the border of the crop is never read; a class without
    objects gets NaN."""
    s = 6  # the box's square: rows and columns 2 and 3
    flow = np.full((3, 2, s, s), 100.0)
    static = np.full((3, 2, s, s), -50.0)
    flow[:, :, 2:4, 2:4] = np.array([[3.0, 4.0], [6.0, 8.0], [0.0, 0.0]])[:, :, None, None]
    flow[0, :, 2, 2] = [30.0, 40.0]  # one pixel of the square off: the median keeps 5
    static[:, :, 2:4, 2:4] = np.array([[0.0, 4.0], [6.0, 0.0], [0.0, 1.0]])[:, :, None, None]
    got = ch10.static_explains(flow, static, np.array([0, 0, 1]))
    assert got.columns.tolist() == ["vehicles", "objects", "flow at the box (px)",
                                    "residual (px)", "residual / flow"]
    assert got["vehicles"].tolist() == ["still", "moving"]
    assert got["objects"].tolist() == [2, 1]
    # still: |flow| 5 and 10, residual |(3, 0)| = 3 and |(0, 8)| = 8, ratios 0.6 and 0.8
    assert got.iloc[0, 2:].tolist() == pytest.approx([7.5, 5.5, 0.7], rel=1e-6)
    # moving: no flow; residual |(0, -1)| = 1
    assert got.iloc[1, 2:].tolist() == pytest.approx([0.0, 1.0, 1e6], rel=1e-7)
    none = ch10.static_explains(flow[:2], static[:2], np.array([0, 0]))
    assert none["objects"].tolist() == [2, 0]
    assert none.iloc[1, 2:].isna().all() and not none.iloc[0, 2:].isna().any()
    # crops as stored (float16) with flow past 256 px: squared, float16 overflows, so the
    # magnitudes are taken in float32
    fast = ch10.static_explains((flow * 100).astype(np.float16),
                                (static * 100).astype(np.float16), np.array([0, 0, 1]))
    assert fast.iloc[0, 2:].tolist() == pytest.approx([750.0, 550.0, 0.7], rel=1e-6)
    odd = ch10.static_explains(flow[:, :, :5, :5], static[:, :, :5, :5], np.array([0, 0, 1]))
    # s = 5: the square is rows and columns 1 to 3, which reaches the border of 100 px
    assert odd.iloc[0, 2] > 50.0


# --- words ----------------------------------------------------------------------------------


def test_built_note_counts_the_chains_and_the_models_left_to_train():
    """With inputs: the built chains of all (no flow for the images) and the models the
    others need (one a fold each: 3); without inputs: how to set them."""
    p = _demo()
    got = ch10.built_note(p, [("dis", "residual"), (None, "images")])
    assert got == ("Chains built with these parameters: **2 of 7** (dis/residual, no "
                   "flow/images). The other 5 (15 models) are trained by `make extensions` "
                   "(or this chapter with `extension_build=true`).")
    assert ch10.built_note(_demo(extension_seeds=2), []) == (
        "Chains built with these parameters: **0 of 7** (none). The other 7 (42 models) are "
        "trained by `make extensions` (or this chapter with `extension_build=true`).")
    assert ch10.built_note(_demo(extension_inputs=[]), []) == (
        "This profile trains no other input (`extension_inputs` is empty): the tables below "
        "hold the paper's raw-flow models only. Set it (e.g. `extension_inputs=[residual]`) "
        "and run `make extensions`.")


def _paired_rows(names):
    """A hand-made comparison table: one row per name, the second inconclusive."""
    rows = [{"ΔF1 (points)": 1.234, "95% CI, scenes and seeds (points)": "0.3 to 2.1",
             "verdict": "A better", "detectable (points)": 1.5},
            {"ΔF1 (points)": -0.46, "95% CI, scenes and seeds (points)": "-2.0 to 1.1",
             "verdict": "inconclusive", "detectable (points)": 3.04},
            {"ΔF1 (points)": 0.05, "95% CI, scenes and seeds (points)": "-1.0 to 1.2",
             "verdict": "equivalent", "detectable (points)": 1.0}]
    return pd.DataFrame([{"comparison": n, **r} for n, r in zip(names, rows, strict=False)])


def test_headline_says_each_input_of_the_profile_in_order_on_the_main_method():
    """On the first estimated extension method, each input of ``extension_inputs`` in the
    profile's order (the images against the first method's flow), with its depth note and
    its difference in words; inputs without a row are left out."""
    p = _demo(extension_inputs=["images", "residual-deployed", "residual"])
    table = _paired_rows([f"dis: {LABELS['residual']} - dis: flow",
                          f"{LABELS['images']} - gt: flow",
                          f"dis: {LABELS['residual-deployed']} - dis: flow"])
    assert ch10.headline(p, table) == (
        "against the raw dis flow, paired on the test scenes: "
        "images (no flow; against gt flow) -0.5 F1 points (95 % interval over scenes and "
        "training seeds -2.0 to 1.1; inconclusive: these scenes would detect 3.0 points or "
        "more); "
        f"residual-deployed{DEPLOYED} +0.1 F1 points (95 % interval over scenes and training "
        "seeds -1.0 to 1.2; equivalent: within +/-2 points); "
        f"residual{ORACLE} +1.2 F1 points (95 % interval over scenes and training seeds 0.3 "
        "to 2.1)")
    only = ch10.headline(_demo(extension_inputs=["images+flow", "residual"]),
                         table.iloc[:1])
    assert only == ("against the raw dis flow, paired on the test scenes: "
                    f"residual{ORACLE} +1.2 F1 points (95 % interval over scenes and training "
                    "seeds 0.3 to 2.1)")


def test_headline_main_method_is_gt_only_without_an_estimated_one():
    """With ``gt`` the only extension method the headline is on ``gt``'s raw flow."""
    p = _demo(extension_methods=["gt"], extension_inputs=["residual"])
    table = _paired_rows([f"gt: {LABELS['residual']} - gt: flow"])
    assert ch10.headline(p, table).startswith(
        f"against the raw gt flow, paired on the test scenes: residual{ORACLE} +1.2 F1")


def test_headline_without_rows_says_how_to_build_or_that_the_profile_has_none():
    """No row of the profile's inputs: how many models `make extensions` trains (chains x
    one model a fold); no inputs at all: that the profile has none."""
    empty = _paired_rows(["dis: something else - dis: flow"])
    assert ch10.headline(_demo(), empty) == (
        "not built in this run (make extensions trains them: 21 models)")
    assert ch10.headline(_demo(extension_methods=["dis"], extension_inputs=["residual"]),
                         empty) == "not built in this run (make extensions trains them: 3 models)"
    assert ch10.headline(_demo(extension_inputs=[]), empty) == (
        "not part of this profile (extension_inputs is empty)")
    assert ch10.headline(_demo(extension_inputs=[], extension_methods=[]), empty) == (
        "not part of this profile (extension_inputs is empty)")
