"""The scoring of predictions tables (flowmod.evaluate): which objects a split is scored on,
the seeds' scores, paired comparisons, the original protocol; and chapter 08's analysis of
them (flowmod.chapters.ch08_generalisation): Table 4, failure reasons. Hand-made tables;
seconds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from flowmod import evaluate
from flowmod import metrics as ev
from flowmod.chapters import ch08_generalisation as ch08
from flowmod.chapters import common


def table(n_scenes: int = 4, per: int = 6, seed: int = 0) -> pd.DataFrame:
    """A predictions table: objects of ``n_scenes`` scenes, two seeds' probabilities."""
    rng = np.random.default_rng(seed)
    n = n_scenes * per
    y = (np.arange(n) % 3 == 0).astype(int)
    s0 = np.where(rng.random(n) < 0.8, y, 1 - y) * 0.8 + 0.1
    s1 = np.where(rng.random(n) < 0.6, y, 1 - y) * 0.8 + 0.1
    return pd.DataFrame({
        "ann_token": [f"a{i}" for i in range(n)], "instance_token": [f"i{i // 2}" for i in range(n)],
        "scene": np.repeat([f"sc{k}" for k in range(n_scenes)], per), "label": y,
        "true_label": y, "distance": np.linspace(5, 95, n), "prob_s0": s0, "prob_s1": s1,
        "prob": s0})


def test_seed_columns_and_probabilities_in_seed_order():
    df = table().assign(prob_s10=0.5)
    assert evaluate.seed_columns(df) == ["prob_s0", "prob_s1", "prob_s10"]
    np.testing.assert_array_equal(evaluate.seed_probs(df)[1], df["prob_s1"])
    assert evaluate.seed_probs(df.drop(columns=["prob_s0", "prob_s1", "prob_s10"])).shape == (
        1, len(df)), "without seed columns: the one model's"


def test_scored_objects_are_the_whole_test_split_and_table_4s_range():
    df = table()
    assert evaluate.scored(df, "test", 50.0) is df
    g = evaluate.scored(df, "general", 50.0)
    assert len(g) == (df["distance"] <= 50.0).sum() and g["distance"].max() <= 50.0
    exact = df.assign(distance=[50.0] * len(df))
    assert len(evaluate.scored(exact, "general", 50.0)) == len(df), "<= keeps the boundary"


def test_score_is_the_seed_summary_of_the_label_column():
    df = table()
    s = evaluate.score(df, seed=3)
    want = ev.seed_summary(df["label"], np.stack([df["prob_s0"], df["prob_s1"]]), df["scene"],
                           instances=df["instance_token"], seed=3)
    assert s == want
    assert s["n_instances"] == df["instance_token"].nunique()
    flipped = evaluate.score(df.assign(true_label=1 - df["label"]), "true_label")
    assert flipped["f1"] != s["f1"], "the label column is the one given"


def test_paired_needs_the_same_objects_and_pairs_the_seeds():
    a, b = table(seed=1), table(seed=2)
    d = evaluate.paired(a, b, "a and b", seed=5)
    want = ev.paired_comparison(a["label"].to_numpy(), evaluate.seed_probs(a),
                                evaluate.seed_probs(b), a["scene"].to_numpy(), seed=5)
    assert d == want
    with pytest.raises(ValueError, match="a and c were scored on different objects"):
        evaluate.paired(a, b.iloc[::-1], "a and c")


def test_original_protocol_thins_stills_batches_and_picks_the_best_epoch():
    df = table()
    y = df["label"].to_numpy()
    good = np.where(y == 1, 0.9, 0.1)
    bad = 1 - good
    # seed 0: epoch 2 is perfect; seed 1: only the worst epoch
    epochs = [np.stack([bad, good]), np.stack([bad, bad])]
    r = evaluate.original_protocol(df, epochs, batch_size=4)
    keep = ev.thin_still(y)
    assert r["per_seed_original"] == [1.0, ev.paper_protocol_f1(y[keep], bad[keep], 4)]
    assert r["per_seed_clean"] == [ev.metrics(y, df["prob_s0"])["f1"],
                                   ev.metrics(y, df["prob_s1"])["f1"]]
    assert r["original_minus_clean"] == pytest.approx(r["original"] - r["clean"])
    assert r["clean"] == pytest.approx(np.mean(r["per_seed_clean"]))


def test_table4_scores_the_papers_range_and_beyond_apart():
    df = table()
    t = ch08.table4({"dis": df}, 50.0)
    inside = df[df["distance"] <= 50.0]
    row = t[(t["vehicles"] == "0-50 m (Table 4)")
            & (t["scored against"] == "paper rule (previous keyframe)")].iloc[0]
    s = ev.seed_summary(inside["label"], evaluate.seed_probs(inside), inside["scene"])
    assert row["objects"] == len(inside) and row["F1 (%)"] == round(100 * s["f1"], 1)
    assert (row["P (%)"], row["R (%)"]) == (round(100 * s["precision"], 1),
                                           round(100 * s["recall"], 1))
    assert set(t["vehicles"]) == {"0-50 m (Table 4)", "beyond 50 m"}
    assert len(t) == 4, "both labels for both ranges"
    unknown = ch08.table4({"dis": df.assign(true_label=-1)}, 50.0)
    assert set(unknown["scored against"]) == {"paper rule (previous keyframe)"}


def test_table4_rows_format_each_ranges_seed_summary(tmp_path):
    """Every row's numbers are its range's seed summary in percent (one decimal); the
    boundary object is in the paper's range only; a range whose paper label is unknown
    still gets its true-label row; an all-still range is scored (F1 undefined, not left out)."""
    df = table(n_scenes=6).reset_index(drop=True)
    df.loc[3, "distance"] = 50.0  # on the boundary: inside
    df.loc[:2, "true_label"] = -1  # unknown at three frames: scored without them
    far = df["distance"] > 50.0
    df.loc[far, "label"] = -1  # beyond the range: the paper's label unknown
    df.loc[far, "true_label"] = 0  # and every vehicle still
    t = ch08.table4({"dis": df}, 50.0)
    assert list(t["scored against"]) == ["paper rule (previous keyframe)",
                                         "true label at the frame", "true label at the frame"]
    assert list(t["vehicles"]) == ["0-50 m (Table 4)"] * 2 + ["beyond 50 m"]
    assert list(t.columns) == ["method", "vehicles", "scored against", "objects", "scenes",
                               "F1 (%)", "seed range (%)", "P (%)", "R (%)",
                               ev.POOLED_SD_COLUMN, ev.RETRAIN_SD_COLUMN,
                               "balanced accuracy (%)",
                               "always moving F1 (%)", "F1 95% CI, scenes and seeds (%)"]
    for row, d, col in ((t.iloc[0], df[~far], "label"), (t.iloc[1], df[~far].iloc[3:], "true_label"),
                        (t.iloc[2], df[far], "true_label")):
        s = ev.seed_summary(d[col], evaluate.seed_probs(d), d["scene"])
        assert (row["method"], row["objects"], row["scenes"]) == ("dis", len(d), s["n_scenes"])
        for key, name in (("f1", "F1 (%)"), ("precision", "P (%)"), ("recall", "R (%)")):
            want = round(100 * s[key], 1)
            assert row[name] == want or (np.isnan(want) and np.isnan(row[name])), name
        assert row["seed range (%)"] == ev.span(s["f1_min"], s["f1_max"])
        assert row["F1 95% CI, scenes and seeds (%)"] == ev.ci_text(s["ci"], s["n_scenes"])
        assert row[ev.POOLED_SD_COLUMN] == ev.points(s["seed_sd"])
        assert row[ev.RETRAIN_SD_COLUMN] == ev.points(s["retrain_sd"])
        assert row["always moving F1 (%)"] == ev.points(ev.always_moving_f1(d[col]))
    assert np.isnan(t.iloc[2]["F1 (%)"]) and t.iloc[2]["F1 95% CI, scenes and seeds (%)"] == "-", \
        "all still: F1 undefined"
    assert all(t[c].dtype.kind == "f" for c in ("F1 (%)", "P (%)", "R (%)")), "one decimal"
    assert t.iloc[0]["seed range (%)"] != t.iloc[0]["F1 95% CI, scenes and seeds (%)"]


def test_defaults_are_the_documented_seed_and_batch_size():
    """score and paired draw with seed 0 by default; the original protocol batches by 128
    (enough scenes and objects that another seed or batch size gives other numbers)."""
    a, b = table(n_scenes=30, per=10, seed=1), table(n_scenes=30, per=10, seed=2)
    assert evaluate.score(a) == evaluate.score(a, seed=0) != evaluate.score(a, seed=1)
    assert evaluate.paired(a, b, "x") == evaluate.paired(a, b, "x", seed=0) != evaluate.paired(
        a, b, "x", seed=1)
    y = a["label"].to_numpy()
    half = np.where(np.arange(len(y)) % 4 == 0, 1 - y, y) * 0.8 + 0.1  # a quarter wrong
    epochs = [np.stack([half])]
    r = evaluate.original_protocol(a, epochs)
    assert r == evaluate.original_protocol(a, epochs, batch_size=128)
    assert r["per_seed_original"] != evaluate.original_protocol(a, epochs, 129)["per_seed_original"]
    keep = ev.thin_still(y)
    assert r["per_seed_original"] == [ev.paper_protocol_f1(y[keep], half[keep], 128)]
    assert r["per_seed_original"] != [ev.paper_protocol_f1(y, half, 128)], "stills thinned"


def test_failure_reasons_tag_remote_slow_and_crowded():
    df = pd.DataFrame({
        "pair_id": ["p", "p", "q"], "instance_token": ["a", "b", "c"],
        "xmin": [100.0, 130.0, 600.0], "ymin": [100.0, 100.0, 100.0],
        "xmax": [120.0, 150.0, 620.0], "ymax": [120.0, 120.0, 120.0],
        "label": [1, 0, 0], "prob": [0.2, 0.3, 0.9], "distance": [60.0, 20.0, 20.0],
        "speed": [5.0, 0.0, 2.5]})
    boxes = df[["pair_id", "instance_token", "xmin", "ymin", "xmax", "ymax"]]
    t = ch08.failure_reasons(df, boxes, speed_threshold=2.0, scale=3.0)
    assert t["wrong"].tolist() == [True, False, True]
    assert t["unclear_flow"].tolist() == [True, False, True]  # 60 m; 2.5 m/s is near 2
    assert t["crowded"].tolist() == [True, True, False]  # a's window holds b and back
    shares = ch08.failure_shares(t).set_index("reason")
    assert shares.loc["remote or slow", "wrong predictions (%)"] == 100.0
    assert shares.loc["other objects in the crop", "all objects (%)"] == pytest.approx(66.7)


@pytest.mark.slow
def test_published_protocol_replays_the_original_batch_not_the_training_one(smoke_built):
    """Chapter 07's protocol gap averages F1 per batch of the original's 128, whatever batch
    the models trained with (the smoke trains with 8, the demo with 32)."""
    import json

    from flowmod import dag, pipeline
    from flowmod.chapters import common
    from flowmod.train import EPOCH_PROBS, records_test, seed_parts

    p = smoke_built
    assert p.batch_size != evaluate.ORIGINAL_BATCH == 128
    folder = pipeline.published(p, dag.Node("evaluate", "dis"))
    got = json.loads((folder / "original.json").read_text())
    preds = common.results(p, "dis", "test")[0]
    parts = [part for part in seed_parts(p) if records_test(part)]
    assert parts == ["f0s0", "f1s0"]  # seed 0 of each of the smoke's two folds
    assert not (common.model_path(p, "dis", "f0s1").parent / EPOCH_PROBS).exists()
    epochs = [np.load(common.model_path(p, "dis", part).parent / EPOCH_PROBS) for part in parts]
    want = evaluate.original_protocol(preds, epochs, 128, parts=parts)
    assert got["per_seed_original"] == pytest.approx(want["per_seed_original"])
    assert got["original"] == pytest.approx(want["original"])
    assert got["original"] != pytest.approx(
        evaluate.original_protocol(preds, epochs, p.batch_size, parts=parts)["original"])


@pytest.mark.slow
def test_table3_sets_the_raw_input_models_beside_the_recipe_paired(smoke_built):
    """The smoke's raw_input_methods=[dis]: its raw-input models train on the paper's raw
    input (the network's pre-hook off), seeded as the recipe's seed 0, are scored on the
    same objects, and Table 3 and the paired comparisons carry them."""
    import torch

    from flowmod import dag, pipeline
    from flowmod.chapters import ch07_evaluation as ch07
    from flowmod.chapters import common
    from flowmod.model import INPUT_MODES

    p = smoke_built
    assert p.raw_input_methods == ["dis"] and p.input_scaling == "log"
    test, raw = (common.results(p, "dis", name)[0] for name in ("test", "raw"))
    assert raw["ann_token"].tolist() == test["ann_token"].tolist()
    assert not np.allclose(raw["prob"], test["prob_s0"])
    for part, mode, seed in (("raw/f1", "raw", p.seed + 1), ("f1s0", "log", p.seed + 1)):
        man = pipeline.published(p, dag.Node("train", "dis", part)) / "manifest.json"
        rec = __import__("json").loads(man.read_text())
        assert (rec["input_scaling"], rec["seed"]) == (mode, seed)
    raw_sd, log_sd = (torch.load(common.model_path(p, "dis", part), weights_only=True)
                      for part in ("raw/f1", "f1s0"))
    assert "input_mode" not in raw_sd  # the raw network scales nothing
    assert int(log_sd["input_mode"]) == INPUT_MODES.index("log")
    table = ch07.table3(p)
    row = table[table["Method"] == f"ResNet18 on dis flow, {ch07.RAW_LABEL}"]
    assert len(row) == 1 and not any("gt flow, the paper" in m for m in table["Method"])
    pairs = ch07.comparisons(p).set_index("comparison")
    want = evaluate.paired(test, raw, "x", seed=p.seed)
    got = pairs.loc["dis: log input - raw input"]
    assert got["ΔF1 (points)"] == round(100 * want["delta_f1"], 1)


# --- which model scores which rows, and what each model and rule is fitted on ----------------


def test_each_fold_s_rows_are_scored_by_its_own_seed_models(monkeypatch):
    """Cross-validation: a row of fold k gets the probability of model f<k>s<j> in column
    prob_s<j>, never another fold's (which trained on it). Stub models: a model's
    'probability' is its part's code."""
    code = {"f0s0": 0.01, "f0s1": 0.02, "f1s0": 0.11, "f1s1": 0.12, "f2s0": 0.21, "f2s1": 0.22}
    monkeypatch.setattr("flowmod.model.load_model", lambda path, dev, ch: path)
    monkeypatch.setattr("flowmod.model.predict",
                        lambda model, x, **kw: np.full(len(x), code[model]))
    df = pd.DataFrame({"fold": [2, 0, 1, 0, 2], "label": [1, 0, 1, 0, 1]})
    models = [(part, part, None) for part in sorted(code)]
    out = evaluate.predict_models(models, np.zeros((5, 2, 4, 4)), df, "cpu", folds=3)
    assert out["prob_s0"].tolist() == [0.21, 0.01, 0.11, 0.01, 0.21]
    assert out["prob_s1"].tolist() == [0.22, 0.02, 0.12, 0.02, 0.22]
    assert out["prob"].tolist() == out["prob_s0"].tolist()
    one = evaluate.predict_models([(p, p, None) for p in ("f0s0", "f1s0", "f2s0")],
                                  np.zeros((5, 2, 4, 4)), df, "cpu", folds=3)
    assert "prob_s0" not in one and one["prob"].tolist() == [0.21, 0.01, 0.11, 0.01, 0.21]


def test_the_geometric_rule_is_fitted_on_each_fold_s_training_rows(monkeypatch):
    """The rule's threshold comes from fold k's training rows (never its test rows): here
    the training rows put the best threshold near 1 m/s, the test rows near 5."""
    from flowmod import geometry

    rows = []
    for k in range(2):
        for role, fast, slow in (("train", 1.5, 0.5), ("test", 6.0, 4.0)):
            for i in range(4):
                rows.append({"fold": k, "role": role, "label": i % 2, "scene": f"s{k}{i}",
                             "residual_speed": fast if i % 2 else slow})
    objects = pd.DataFrame(rows)

    def gather(read, folds, k, role, part="keyframe"):
        want = "test" if role == "test" else "train"
        sub = objects[(objects["fold"] == k) & (objects["role"] == want)]
        return [np.zeros(len(sub))], sub.drop(columns="residual_speed")

    monkeypatch.setattr(evaluate, "gather_fold", gather)
    monkeypatch.setattr(geometry, "residual_scores", lambda sub, pairs, smp: pd.DataFrame(
        {"residual_speed": objects.loc[
            (objects["fold"] == sub["fold"].iloc[0])
            & (objects["role"] == sub["role"].iloc[0]), "residual_speed"].to_numpy()}))
    test, s = evaluate.geometric_baseline(pd.DataFrame(), None, folds=2)
    assert s["thresholds_m_s"] == [pytest.approx(1.0)] * 2
    assert test["prob"].tolist() == [1.0] * 8  # 4.0 and 6.0 m/s both above 1.0


@pytest.mark.parametrize("part, record, input_mode, what", [
    ("f1s0", "test x of fold 1", None, "dis"),  # seed 0 records the test rows for the replay
    ("f1s2", None, None, "dis"),                # other seeds of a fold do not
    ("raw/f1", None, "raw", "dis raw input"),   # the raw-input model: the paper's input
])
def test_the_training_stage_chooses_on_validation_rows_and_only_records_test(
        monkeypatch, part, record, input_mode, what):
    """train.build hands the trainer fold k's training rows (of its method's keyframe
    crops) to fit, its validation rows to choose the epoch on, and (seed 0 only) its test
    rows to record, never scored in training; a ``raw/`` part trains on the raw input; the
    model's recipe joins the trainer's manifest fields."""
    from types import SimpleNamespace

    from flowmod import dag, train

    seen = {}

    def fold_crops(folder, folds, k, role):
        assert folder == ("published", dag.Node("crops", "dis", "keyframe")) and folds == 3
        return (f"{role} x of fold {k}", role)

    monkeypatch.setattr(train, "fold_crops", fold_crops)
    monkeypatch.setattr(train, "recipe", lambda b_, m: {"of": (b_ is b, m)})

    def fake_train_seed(b_, tr, va, progress, what, record=None, input_mode=None, **kw):
        seen.update(b=b_ is b, train=tr, val=va, record=record, input_mode=input_mode,
                    progress=progress, what=what)
        return {"seed": 5}

    monkeypatch.setattr(train, "train_seed", fake_train_seed)
    b = SimpleNamespace(node=dag.Node("train", "dis", part), params=SimpleNamespace(folds=3),
                        input_dir=lambda node: ("published", node))
    assert train.build(b, progress="shown") == {"seed": 5, "recipe": {"of": (True, "dis")}}
    assert seen == {"b": True, "train": ("train x of fold 1", "train"),
                    "val": ("val x of fold 1", "val"), "record": record,
                    "input_mode": input_mode, "progress": "shown", "what": what}


def test_which_training_parts_record_their_test_rows():
    from flowmod.train import records_test

    assert [records_test(x) for x in ("s0", "s1", "f2", "f2s0", "f2s1", "raw/f0", "raw/s0")] \
        == [True, True, True, True, False, False, False]


def test_models_of_keeps_a_key_s_own_models_apart_from_longer_keys():
    """evaluate[dis] reads train[dis/f<k>s<j>] and train[dis/raw/f<k>]: the recipe's seeds
    and the raw-input models are told apart by their key, never mixed into one seed."""
    from types import SimpleNamespace

    from flowmod import dag

    inputs = {"train[dis/f0s0]": {"amp": "off"}, "train[dis/f0s1]": {"amp": "bf16"},
              "train[dis/raw/f0]": {}, "train[disx/f0s0]": {}, "crops[dis/keyframe]": {}}
    b = SimpleNamespace(inputs=inputs, input_dir=lambda n: Path("/r") / n.stage / str(n.part))
    got = evaluate.models_of(b, "train", "dis")
    assert got == [("f0s0", Path("/r/train/f0s0/best.pt"), None),
                   ("f0s1", Path("/r/train/f0s1/best.pt"), "bf16")]
    assert evaluate.models_of(b, "train", "dis/raw") == [
        ("f0", Path("/r/train/f0/best.pt"), None)]
    assert {str(n) for n in evaluate.EVALUATE.inputs(dag.Node("evaluate", "dis"), _demo())
            if n.stage == "train"} >= {"train[dis/raw/f0]", "train[dis/f2s2]"}
    assert not [n for n in evaluate.EVALUATE.inputs(dag.Node("evaluate", "farneback"), _demo())
                if "raw" in str(n)]


def _demo():
    from flowmod import params

    return params.load_profile("demo")


def test_box_masks_cover_the_box_inside_its_window():
    from flowmod.chapters import ch07_evaluation as ch07

    df = pd.DataFrame({"xmin": [100.0, 0.0], "ymin": [100.0, 0.0], "xmax": [130.0, 60.0],
                       "ymax": [130.0, 20.0]})
    m = ch07.box_masks(df, 30, 3.0)
    rows, cols = np.flatnonzero(m[0].any(1)), np.flatnonzero(m[0].any(0))
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (9, 19, 9, 19)  # central third
    rows, cols = np.flatnonzero(m[1].any(1)), np.flatnonzero(m[1].any(0))
    # a 60 x 20 box, window 180 px from (-59, -79): columns 59-120 and rows 79-100 of it
    assert (cols.min(), cols.max()) == (9, 19) and (rows.min(), rows.max()) == (13, 16)
    assert m[1].sum() == 11 * 4


def test_crop_errors_compare_each_object_s_crops(smoke_built):
    """Against itself the exact flow has no error; DIS's errors are positive, inside and
    around the box, on Table 3's rows in its order."""
    from flowmod.chapters import ch07_evaluation as ch07
    from flowmod.chapters.common import results

    p = smoke_built
    same = ch07.crop_errors(p, "gt")
    assert (same[["epe_box", "epe_around"]].to_numpy() == 0).all()
    dis = ch07.crop_errors(p, "dis")
    assert dis["ann_token"].tolist() == results(p, "dis", "test")[0]["ann_token"].tolist()
    assert (dis["epe_around"] > 0).mean() > 0.9 and (dis["epe_box"] >= 0).all()
    t = ch07.error_explanation(p, "dis", "gt")
    assert t.loc[0, "gt"] == 0.0 and t.loc[0, "dis"] == round(dis["epe_box"].median(), 2)
    share = (dis["epe_box"] > 0) + 0.5 * (dis["epe_box"] == 0)
    assert t.loc[0, "objects where dis errs more (%)"] == round(100 * share.mean(), 1)


def test_a_training_part_is_named_by_its_last_path_component():
    """``.../f<k>``, ``.../s<j>``, ``.../f<k>s<j>``: one letter alone, or another letter,
    is no training part."""
    from flowmod.train import part_index

    assert [part_index(x) for x in ("gt/raw/f1", "a/b/f2s1")] == [1, 2]
    for bad in ("f", "s", "x1", "X1", "ab", "dis/raw"):
        with pytest.raises(ValueError, match="not a training part"):
            part_index(bad)


def test_raw_input_models_are_one_a_fold_for_the_named_methods_only():
    from flowmod import dag
    from flowmod.params import load_profile
    from flowmod.train import raw_nodes, train_nodes

    p = load_profile("demo").model_copy(update={"raw_input_methods": ["dis"], "folds": 3})
    want = [dag.Node("train", "dis", f"raw/f{k}") for k in range(3)]
    assert raw_nodes(p, "dis") == want and raw_nodes(p, "gt") == []
    assert train_nodes(p)[-3:] == want
    two = p.model_copy(update={"flow_methods": ["gt", "dis"], "seeds": 2, "folds": 2})
    assert [str(n) for n in train_nodes(two)] == [
        "train[gt/f0s0]", "train[gt/f0s1]", "train[gt/f1s0]", "train[gt/f1s1]",
        "train[dis/f0s0]", "train[dis/f0s1]", "train[dis/f1s0]", "train[dis/f1s1]",
        "train[dis/raw/f0]", "train[dis/raw/f1]"]
    assert all(n.stage == "train" for n in train_nodes(two))
    assert raw_nodes(p.model_copy(update={"raw_input_methods": []}), "dis") == []


def test_scored_rows_read_one_split_as_stored_and_pool_every_fold():
    """One split: the test split's arrays and index exactly as read (a memmap stays one);
    two or more folds: every fold's rows, each once."""
    x_test, df_test = np.arange(4)[:, None], pd.DataFrame({"scene": list("abcd")})
    arrays, df = evaluate.scored_rows(
        lambda s: ([x_test], df_test) if s == "test" else pytest.fail(s), 1)
    assert arrays[0] is x_test and df is df_test
    stored = {"f0": pd.DataFrame({"scene": ["a", "b"], "fold": 0}),
              "f1": pd.DataFrame({"scene": ["c"], "fold": 1})}
    (x,), df = evaluate.scored_rows(
        lambda s: ([np.arange(len(stored[s]))[:, None]], stored[s]), 2)
    assert df["scene"].tolist() == ["a", "b", "c"] and len(x) == 3



def _crops_folder(folder: Path, folds: int = 2) -> None:
    """A crops node's folder of ``folds`` folds: 4 rows a fold (crops, index, samples)."""
    for k in range(folds):
        x = np.full((4, 2, 4, 4), k, np.float16) + np.arange(4, dtype=np.float16)[:, None,
                                                                                 None, None]
        np.save(folder / f"f{k}.npy", x)
        np.save(folder / f"f{k}.samples.npy",
                np.arange(4 * 81 * 2, dtype=np.float32).reshape(4, 81, 2) + 1000 * k)
        pd.DataFrame({"pair_id": [f"p{k}{i}" for i in range(4)], "scene": f"s{k}",
                      "fold": k, "val_scene": False, "label": [0, 1, 0, 1],
                      "ann_token": [f"a{k}{i}" for i in range(4)]}).to_parquet(
            folder / f"f{k}.parquet")


def test_scored_crops_are_each_fold_s_own_rows_read_from_the_folder(tmp_path):
    _crops_folder(tmp_path)
    x, df = evaluate.scored_crops(tmp_path, 2)
    assert df["fold"].tolist() == [0] * 4 + [1] * 4
    assert x[:, 0, 0, 0].tolist() == [0, 1, 2, 3, 1, 2, 3, 4]
    # the generalisation part: one array set, each fold's scenes in turn
    np.save(tmp_path / "general.npy", np.arange(3, dtype=np.float16)[:, None, None, None]
            * np.ones((3, 2, 4, 4), np.float16))
    pd.DataFrame({"fold": [1, 0, 1], "scene": ["a", "b", "c"]}).to_parquet(
        tmp_path / "general.parquet")
    x, df = evaluate.scored_crops(tmp_path, 2, "general")
    assert df["fold"].tolist() == [0, 1, 1] and x[:, 0, 0, 0].tolist() == [1, 0, 2]


def test_the_geometric_baseline_reads_each_row_s_flow_samples(tmp_path, monkeypatch):
    """geometric_baseline on a crops folder: each row's stored flow samples reach the
    residual, aligned with its index row (the fold's train rows fit, its test rows score)."""
    from flowmod import geometry

    _crops_folder(tmp_path)
    seen = []

    def residual(sub, pairs, smp):
        seen.append((sub["pair_id"].tolist(), smp[:, 0, 0].tolist()))
        return pd.DataFrame({"residual_speed": sub["label"].to_numpy() * 5.0})

    monkeypatch.setattr(geometry, "residual_scores", residual)
    test, s = evaluate.geometric_baseline(pd.DataFrame(), tmp_path, folds=2)
    # fold 0: trains on fold 1's rows, tests on its own; then fold 1
    assert seen[1] == (["p00", "p01", "p02", "p03"], [0.0, 162.0, 324.0, 486.0])
    assert seen[0] == (["p10", "p11", "p12", "p13"], [1000.0, 1162.0, 1324.0, 1486.0])
    assert test["prob"].tolist() == [0.0, 1.0] * 4 and len(s["thresholds_m_s"]) == 2


def test_a_predictions_breakdown_scores_every_seed_by_scene(monkeypatch):
    """common.breakdown: metrics.breakdown of the table's labels and every seed's
    probabilities, scenes as the resampled unit, folds when the rows span several."""
    df = pd.DataFrame({"label": [0, 1, 1, 0, 1, 0], "scene": list("aabbcc"),
                       "category": ["car", "bus"] * 3, "fold": [0, 0, 1, 1, 0, 1],
                       "prob_s0": [0.1, 0.9, 0.8, 0.3, 0.2, 0.6],
                       "prob_s1": [0.2, 0.7, 0.6, 0.1, 0.9, 0.4]})
    got = common.breakdown(df, "category")
    want = ev.breakdown(df, df["label"], df[["prob_s0", "prob_s1"]].to_numpy().T,
                        by="category", groups=df["scene"].to_numpy(), folds=df["fold"].to_numpy())
    pd.testing.assert_frame_equal(got, want)
    seen = {}
    monkeypatch.setattr(ev, "breakdown",
                        lambda *a, **k: seen.update(args=a, kw=k) or "table")
    assert common.breakdown(df, "distance", bins=[0, 50]) == "table"
    assert seen["kw"]["by"] == "distance" and seen["kw"]["bins"] == [0, 50]
    assert seen["kw"]["groups"].tolist() == list("aabbcc")
    assert seen["kw"]["folds"].tolist() == [0, 0, 1, 1, 0, 1]
    assert seen["args"][0] is df and seen["args"][1].tolist() == [0, 1, 1, 0, 1, 0]


def test_predict_models_scores_every_seed_with_real_checkpoints(tmp_path):
    """One split: ``prob_<part>`` of each saved model (loaded for two channels, on the
    default device) on every row and ``prob`` = the first listed; cross-validation: each
    row by its fold's model, a fold without a model left NaN (float); a checkpoint of other
    channels is refused unless the caller takes the checkpoint's (``in_channels=None``)."""
    import torch

    from flowmod.model import CheckpointError, load_model, motion_resnet18, predict

    paths = {}
    for i, part in enumerate(("s0", "s1", "f0", "f1")):
        torch.manual_seed(i)
        paths[part] = tmp_path / f"{part}.pt"
        torch.save(motion_resnet18(width=4).state_dict(), paths[part])
    x = np.random.default_rng(0).normal(0, 3, (5, 2, 32, 32)).astype(np.float32)
    df = pd.DataFrame({"fold": [1, 0, 1, 0, 2], "label": [1, 0, 1, 0, 1]})
    want = {p: predict(load_model(paths[p]), x, device="cpu") for p in paths}
    out = evaluate.predict_models([("s1", paths["s1"], None), ("s0", paths["s0"], None)], x, df)
    assert list(out.columns) == ["fold", "label", "prob_s1", "prob_s0", "prob"]
    np.testing.assert_allclose(out["prob_s0"], want["s0"], rtol=1e-6)
    np.testing.assert_allclose(out["prob_s1"], want["s1"], rtol=1e-6)
    np.testing.assert_allclose(out["prob"], want["s1"], rtol=1e-6)
    assert not np.allclose(want["s0"], want["s1"])
    cv = evaluate.predict_models([("f0", paths["f0"], None), ("f1", paths["f1"], None)], x, df,
                                 folds=3)
    assert cv["prob"].dtype == np.float64 and np.isnan(cv["prob"].iloc[4])
    np.testing.assert_allclose(cv["prob"].iloc[[1, 3]], want["f0"][[1, 3]], rtol=1e-6)
    np.testing.assert_allclose(cv["prob"].iloc[[0, 2]], want["f1"][[0, 2]], rtol=1e-6)
    torch.save(motion_resnet18(3, width=4).state_dict(), tmp_path / "three.pt")
    x3 = np.zeros((5, 3, 32, 32), np.float32)
    for folds, part in ((1, "s0"), (3, "f0")):
        with pytest.raises(CheckpointError):
            evaluate.predict_models([(part, tmp_path / "three.pt", None)], x3, df, folds=folds)
        got = evaluate.predict_models([(part, tmp_path / "three.pt", None)], x3, df,
                                      in_channels=None, folds=folds)
        assert got["prob"].notna().sum() == (5 if folds == 1 else 2)


def test_the_geometric_baseline_of_one_split_and_its_record(tmp_path, monkeypatch):
    """One split (the default): fitted on the train split, scored on the test split; the
    record is the test rows' score (seed 0 by default) with the threshold; the test rows
    come back with a fresh index and no extra column; the pairs reach the residual."""
    from flowmod import geometry

    for split, labels_ in (("train", [0, 1, 0, 1]), ("val", [1, 0]), ("test", [1, 0, 0, 1])):
        n = len(labels_)
        np.save(tmp_path / f"{split}.npy", np.zeros((n, 2, 4, 4), np.float16))
        np.save(tmp_path / f"{split}.samples.npy", np.zeros((n, 81, 2), np.float32))
        pd.DataFrame({"pair_id": [f"{split}{i}" for i in range(n)], "label": labels_,
                      "scene": [f"{split}-s{i}" for i in range(n)]},
                     index=np.arange(n) + 10).to_parquet(tmp_path / f"{split}.parquet")
    pairs = pd.DataFrame({"pair_id": ["x"]})
    monkeypatch.setattr(geometry, "residual_scores", lambda sub, p, smp: pd.DataFrame(
        {"residual_speed": (sub["label"].to_numpy() * 4.0 + 0.5) if p is pairs else None}))
    test, s = evaluate.geometric_baseline(pairs, tmp_path)
    assert test["pair_id"].tolist() == ["test0", "test1", "test2", "test3"]
    assert list(test.columns) == ["pair_id", "label", "scene", "residual_speed", "prob"]
    assert test.index.tolist() == [0, 1, 2, 3] and test["prob"].tolist() == [1.0, 0, 0, 1.0]
    t = s["thresholds_m_s"][0]
    want = {**evaluate.score(test, seed=0), "threshold_m_s": t, "thresholds_m_s": [t]}
    assert 0.5 <= t < 4.5 and repr(s) == repr(want)  # repr: NaN equals NaN


def test_models_of_reads_past_longer_keys_whatever_their_order():
    from types import SimpleNamespace

    inputs = {"train[dis/raw/f0]": {}, "train[dis/f1]": {"amp": "bf16"}, "train[dis/f0]": {}}
    b = SimpleNamespace(inputs=inputs,
                        input_dir=lambda n: Path("/r") / n.stage / n.method / str(n.part))
    assert evaluate.models_of(b, "train", "dis") == [
        ("f0", Path("/r/train/dis/f0/best.pt"), None), ("f1", Path("/r/train/dis/f1/best.pt"),
                                                        "bf16")]


def test_seed_columns_are_the_numbered_ones_in_number_order():
    df = pd.DataFrame(columns=["prob", "prob_s10", "prob_s2", "prob_sx", "prob_s0", "xxxxxx12"])
    assert evaluate.seed_columns(df) == ["prob_s0", "prob_s2", "prob_s10"]


def test_scored_rows_keep_a_fresh_index_and_the_original_protocol_names_its_models():
    stored = {"f0": pd.DataFrame({"scene": ["a", "b"], "fold": 0}, index=[5, 6]),
              "f1": pd.DataFrame({"scene": ["c"], "fold": 1}, index=[7])}
    _, df = evaluate.scored_rows(lambda s: ([np.arange(len(stored[s]))], stored[s]), 2)
    assert df.index.tolist() == [0, 1, 2]
    one = table()
    y = one["label"].to_numpy()
    r = evaluate.original_protocol(one, [np.stack([np.where(y == 1, 0.9, 0.1)])] * 2)
    assert r["models"] == "seeds"
    folds = one.assign(fold=np.arange(len(one)) % 2)
    eps = [np.stack([np.full((folds["fold"] == k).sum(), 0.7)]) for k in (0, 1)]
    assert evaluate.original_protocol(folds, eps)["models"] == "folds"
    with pytest.raises(ValueError):
        evaluate.original_protocol(folds, eps, parts=["f0"])


def test_paired_and_table4_resample_by_fold_when_rows_span_several():
    """With cross-validation the intervals are drawn within each fold's scenes."""
    a, b = table(n_scenes=12, per=6, seed=1), table(n_scenes=12, per=6, seed=2)
    fold = a["scene"].map({s: i % 3 for i, s in enumerate(sorted(a["scene"].unique()))})
    a, b = a.assign(fold=fold), b.assign(fold=fold)
    got = evaluate.paired(a, b, "x")
    assert got == ev.paired_comparison(a["label"].to_numpy(), evaluate.seed_probs(a),
                                       evaluate.seed_probs(b), a["scene"].to_numpy(),
                                       folds=fold.to_numpy())
    assert got != ev.paired_comparison(a["label"].to_numpy(), evaluate.seed_probs(a),
                                       evaluate.seed_probs(b), a["scene"].to_numpy())
    t = ch08.table4({"dis": a.assign(distance=10.0)}, 50.0).iloc[0]
    s = ev.seed_summary(a["label"], evaluate.seed_probs(a), a["scene"], folds=fold.to_numpy())
    assert t["F1 95% CI, scenes and seeds (%)"] == ev.ci_text(s["ci"], s["n_scenes"])
    one = ch08.table4({"dis": a.iloc[:1].assign(distance=10.0)}, 50.0)
    assert one["objects"].tolist() == [1, 1]  # a range of one object is scored
    recall = ch08.table4({"dis": a.assign(distance=10.0)}, 50.0)["R (%)"].iloc[0]
    assert recall == round(recall, 1)
    no_true = ch08.table4({"dis": a.drop(columns="true_label").assign(distance=10.0)}, 50.0)
    assert list(no_true["scored against"]) == ["paper rule (previous keyframe)"]


def test_the_baseline_seeds_its_interval_and_indexes_pooled_folds_afresh(tmp_path,
                                                                         monkeypatch):
    """geometric_baseline: the record's interval is drawn with the seed given (0 by
    default), and the pooled test rows of several folds get one fresh index."""
    from flowmod import geometry

    rng = np.random.default_rng(4)
    for k in range(2):
        n = 12
        np.save(tmp_path / f"f{k}.npy", np.zeros((n, 2, 4, 4), np.float16))
        np.save(tmp_path / f"f{k}.samples.npy", np.zeros((n, 81, 2), np.float32))
        pd.DataFrame({"pair_id": [f"p{k}{i}" for i in range(n)], "fold": k,
                      "val_scene": [i % 4 == 0 for i in range(n)],
                      "label": rng.integers(0, 2, n), "scene": [f"s{k}{i}" for i in range(n)],
                      }).to_parquet(tmp_path / f"f{k}.parquet")
    monkeypatch.setattr(geometry, "residual_scores", lambda sub, p, smp: pd.DataFrame(
        {"residual_speed": sub["label"].to_numpy() * 0.8 + rng.uniform(0, 1.5, len(sub))}))
    test, s = evaluate.geometric_baseline(pd.DataFrame(), tmp_path, folds=2)
    assert test.index.tolist() == list(range(24))
    assert s["ci"] == evaluate.score(test, seed=0)["ci"] != evaluate.score(test, seed=3)["ci"]
    test3, s3 = evaluate.geometric_baseline(pd.DataFrame(), tmp_path, seed=3, folds=2)
    assert s3["ci"] == evaluate.score(test3, seed=3)["ci"]


def test_two_folds_are_cross_validation(monkeypatch):
    """folds=2 is cross-validation too: each row by its own fold's model."""
    monkeypatch.setattr("flowmod.model.load_model", lambda path, dev, ch: path)
    monkeypatch.setattr("flowmod.model.predict", lambda model, x, **kw: np.full(len(x), model))
    df = pd.DataFrame({"fold": [1, 0, 1]})
    out = evaluate.predict_models([("f0", 0.2, None), ("f1", 0.7, None)], np.zeros((3, 2, 4, 4)),
                                  df, "cpu", folds=2)
    assert out["prob"].tolist() == [0.7, 0.2, 0.7] and "prob_f0" not in out
