"""Mutation testing of chapter 07's backend (:mod:`flowmod.chapters.ch07_evaluation`): quick
tests on hand-written inputs (mutmut runs only the tests that need no generated world, and
the chapter is otherwise run only by the slow notebook tests).

A tiny study is written here by hand into a demo-profile run folder (one split, two training
seeds, seed 15, flows gt, dis and fastflownet): each evaluate node's predictions tables, its
score records (written as numbers chosen here, so that every number the chapter records is
one of them, rounded), the original protocol's records, and crops whose flow error is known
pixel by pixel (constant inside each object's box, constant around it). Every expected
number is computed here from those inputs with numpy, pandas or scikit-learn (the scene
bootstrap re-implemented with numpy on the same seeded draws), never by the function tested.
tests/test_chapter_numbers.py and tests/test_tables.py check Table 3's F1 per row, the
effects' A minus B and the verdict words; this file complements them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from sklearn.metrics import f1_score, precision_score, recall_score

from flowmod import pipeline
from flowmod.chapters import ch07_evaluation as ch07
from flowmod.chapters.common import comparison_table
from flowmod.dag import Node
from flowmod.params import Params, load_profile

#: The hand-written study's flow methods, scenes and objects per scene (a mover and a still).
METHODS = ["gt", "dis", "fastflownet"]
SCENES, PER_SCENE = 12, 2
N = SCENES * PER_SCENE
#: Crop size (px) and every object's 2D box: with the crop scale 3 its box covers rows and
#: columns 9 to 19 of the crop (tests/test_evaluate.py's box mask test).
SIZE, BOX, INSIDE = 30, (100.0, 100.0, 130.0, 130.0), slice(9, 20)
#: The study's bootstrap seed: not 0, the functions' default, and one whose intervals here
#: all differ from seed 0's.
SEED = 15
DRAWS = 2000


def _scores(f1, lo, hi, sd, p, r, ci, chance, **extra) -> dict:
    """A score record as :func:`flowmod.metrics.seed_summary` writes it (hand-chosen)."""
    rec = {"f1": f1, "f1_min": lo, "f1_max": hi, "seed_sd": sd, "precision": p, "recall": r,
           "ci": ci, "always_moving_f1": chance, "n": N, "n_scenes": SCENES, "seeds": 2,
           "training_seeds": 2, "unit": "seed", "balanced_accuracy": 0.8}
    return {**rec, **extra}


#: The classifiers' score records per method (gt's has no seed SD: the record's default).
SCORES = {
    "gt": {k: v for k, v in _scores(0.9137, 0.8962, 0.9311, 0.0246, 0.9021, 0.9256,
                                     [0.8544, 0.9683], 0.6154).items() if k != "seed_sd"},
    "dis": _scores(0.8412, 0.8233, 0.8591, 0.0253, 0.8125, 0.8721, [0.7718, 0.9046], 0.6154),
    "fastflownet": _scores(0.7764, 0.7519, 0.8009, 0.0346, 0.7433, 0.8126, [0.6812, 0.8577],
                           0.5833, n=23, n_scenes=11),
}
BASELINE = {"gt": _scores(0.7012, 0.7012, 0.7012, 0.0, 0.6817, 0.7219, [0.61, 0.78], 0.6),
            "dis": _scores(0.6545, 0.6545, 0.6545, 0.0, 0.6311, 0.6797, [0.55, 0.74], 0.6),
            "fastflownet": _scores(0.6321, 0.6321, 0.6321, 0.0, 0.6012, 0.6663, [0.52, 0.71],
                                   0.6)}
RAW = {"gt": _scores(0.8876, 0.8702, 0.9050, 0.02, 0.8711, 0.9048, [0.82, 0.95], 0.6),
       "dis": _scores(0.8023, 0.7844, 0.8202, 0.02, 0.7814, 0.8243, [0.72, 0.87], 0.6)}
#: The original protocol's records (:func:`flowmod.evaluate.original_protocol`).
ORIGINAL = {
    "gt": {"clean": 0.9137, "original": 0.9808, "original_minus_clean": 0.0671,
           "per_seed_clean": [0.8962, 0.9311], "per_seed_original": [0.9674, 0.9941]},
    "dis": {"clean": 0.8412, "original": 0.9516, "original_minus_clean": 0.1104,
            "per_seed_clean": [0.8233, 0.8591], "per_seed_original": [0.9434, 0.9598]},
    "fastflownet": {"clean": 0.7764, "original": 0.8533, "original_minus_clean": 0.0769,
                    "per_seed_clean": [0.7519, 0.8009], "per_seed_original": [0.8434, 0.8632]},
}
#: Which objects each method's models (two seeds) call wrongly.
WRONG = {"gt": ([1, 6], [6, 15]), "dis": ([0, 5, 8, 17], [5, 9, 12, 21]),
         "fastflownet": ([2, 4, 7, 11, 14, 23], [4, 6, 13, 15, 20, 22])}
BASELINE_WRONG = {"gt": [3, 8, 9, 19], "dis": [0, 2, 9, 13, 16], "fastflownet": [1, 4, 7, 19]}
RAW_WRONG = {"gt": [2, 10, 11], "dis": [3, 6, 17, 18, 20]}


def _objects() -> pd.DataFrame:
    """The scored objects: two per scene, the first moving, the second still."""
    i = np.arange(N)
    return pd.DataFrame({
        "ann_token": [f"obj-{k:02d}" for k in i], "instance_token": [f"car-{k}" for k in i],
        "scene": [f"scene-{k // PER_SCENE:02d}" for k in i], "label": (i % 2 == 0).astype(int),
        "distance": 30.0 + 1.5 * i, "speed": 0.25 * i, "category": "vehicle.car",
        "xmin": BOX[0], "ymin": BOX[1], "xmax": BOX[2], "ymax": BOX[3]})


def _probs(wrong: list[int]) -> np.ndarray:
    """0.8 for a mover and 0.2 for a still object, on the wrong side for ``wrong``."""
    y = _objects()["label"].to_numpy()
    right = np.where(y == 1, 0.8, 0.2)
    right[wrong] = 1.0 - right[wrong]
    return right


def _test_table(m: str) -> pd.DataFrame:
    """A classifier's predictions: two seeds (fastflownet's object 0 at 0.25 and 0.75: a
    seed-mean of 0.5 exactly, on no side)."""
    s0, s1 = (_probs(w) for w in WRONG[m])
    if m == "fastflownet":
        s0[0], s1[0] = 0.25, 0.75
    return _objects().assign(prob_s0=s0, prob_s1=s1, prob=s0)


def _baseline_table(m: str) -> pd.DataFrame:
    """The geometric rule's 0/1 calls on the flow of ``m``."""
    return _objects().assign(prob=(_probs(BASELINE_WRONG[m]) > 0.5).astype(float))


def _raw_table(m: str) -> pd.DataFrame:
    """The raw-input model's predictions (one model)."""
    return _objects().assign(prob=_probs(RAW_WRONG[m]))


def _u(m: str) -> tuple[np.ndarray, np.ndarray]:
    """(inside, around): each object's flow error (px, multiples of 0.625) of ``m`` against
    the exact flow, in the box and around it."""
    if m == "gt":
        return np.zeros(N), np.zeros(N)
    rng = np.random.default_rng(METHODS.index(m))
    inside = 0.625 * rng.integers(1, 6, N)
    around = 0.625 * (rng.permutation(N) + 1 if m == "fastflownet" else rng.integers(1, 25, N))
    return inside, around


def _crops(m: str) -> np.ndarray:
    """(N, 2, S, S) float16 crops whose error against gt's (zero) flow is ``_u(m)``: (3, 4)
    times a fifth of it in each pixel."""
    inside, around = _u(m)
    field = np.repeat((around / 5)[:, None, None], SIZE, 1).repeat(SIZE, 2)
    field[:, INSIDE, INSIDE] = (inside / 5)[:, None, None]
    return np.stack([3 * field, 4 * field], axis=1).astype(np.float16)


def _profile(root: Path, **overrides) -> Params:
    """The study's profile: the demo's, one split, two seeds, seed :data:`SEED`."""
    return load_profile("demo", **{"run_dir": str(root / "runs"), "folds": 1, "seeds": 2,
                                   "seed": SEED, "flow_methods": METHODS,
                                   "raw_input_methods": ["dis", "gt"], **overrides})


def _node(p: Params, node: Node, frames: dict[str, pd.DataFrame],
          records: dict[str, dict] | None = None, arrays: dict[str, np.ndarray] | None = None
          ) -> None:
    """Publish a node's folder: ``<name>.parquet``, ``<name>.json``, ``<name>.npy``, and a
    manifest."""
    folder = pipeline.node_dir(p, node)
    folder.mkdir(parents=True, exist_ok=True)
    for name, df in frames.items():
        df.to_parquet(folder / f"{name}.parquet", index=False)
    for name, rec in (records or {}).items():
        (folder / f"{name}.json").write_text(json.dumps(rec))
    for name, x in (arrays or {}).items():
        np.save(folder / f"{name}.npy", x)
    (folder / "manifest.json").write_text(json.dumps({"fingerprint": f"hand-made {node}"}))


def _write_study(root: Path) -> Params:
    """The hand-written study in ``root``: its profile."""
    p = _profile(root)
    for m in METHODS:
        frames = {"test": _test_table(m), "baseline": _baseline_table(m)}
        records = {"scores": SCORES[m], "baseline": BASELINE[m], "original": ORIGINAL[m]}
        if m in RAW:
            frames["raw"], records["raw"] = _raw_table(m), RAW[m]
        _node(p, Node("evaluate", m), frames, records)
        _node(p, Node("crops", m, "keyframe"), {"test": _objects()}, arrays={"test": _crops(m)})
    # DIS's crops with float16 noise of about 0.01 px (raft is not a method of the profile)
    noise = np.random.default_rng(5).normal(0.0, 0.01, (N, 2, SIZE, SIZE))
    _node(p, Node("crops", "raft", "keyframe"), {"test": _objects()},
          arrays={"test": (_crops("dis") + noise).astype(np.float16)})
    # crops of the same objects in another order (farneback is not a method of the profile)
    _node(p, Node("crops", "farneback", "keyframe"), {"test": _objects().iloc[::-1]},
          arrays={"test": _crops("dis")[::-1]})
    return p


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> Params:
    """The hand-written study (read-only: tests that change files write their own)."""
    return _write_study(tmp_path_factory.mktemp("ch07_study"))


# --- expected values, by hand -------------------------------------------------------------


def _calls(df: pd.DataFrame) -> list[np.ndarray]:
    """Each model's calls (a mover: probability above 0.5) of a predictions table."""
    return [df[c].to_numpy() > 0.5 for c in (["prob_s0", "prob_s1"] if "prob_s1" in df
                                             else ["prob"])]


def _f1(df: pd.DataFrame) -> float:
    """The mean over the table's models of each one's F1 (scikit-learn)."""
    return float(np.mean([f1_score(df["label"], c) for c in _calls(df)]))


def _scene_weights(scenes: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(how often each scene is drawn per replicate (DRAWS, G), the scene of each row):
    whole scenes drawn with replacement, numpy's multinomial seeded with ``seed``."""
    uniq, gi = np.unique(scenes, return_inverse=True)
    k = len(uniq)
    return np.random.default_rng(seed).multinomial(k, np.full(k, 1 / k), size=DRAWS), gi


def _boot_f1(df: pd.DataFrame, seed: int) -> np.ndarray:
    """Replicates of the seed-mean F1: scenes drawn as above and, for two models, each
    replicate's two seeds drawn with replacement (numpy's generator seeded [seed, 1])."""
    w, gi = _scene_weights(df["scene"].to_numpy(), seed)
    y = df["label"].to_numpy() == 1
    calls = np.array(_calls(df))
    s = len(calls)
    pick = (np.zeros((DRAWS, 1), int) if s == 1 else
            np.random.default_rng([seed, 1]).integers(0, s, size=(DRAWS, 1, s))[:, 0, :])

    def drawn(hit: np.ndarray) -> np.ndarray:  # (DRAWS, S): the drawn models' counts
        per_scene = np.array([np.bincount(gi, weights=h.astype(float)) for h in hit])
        return np.take_along_axis(w @ per_scene.T, pick, axis=1)

    tp, fp, fn = drawn(calls & y), drawn(calls & ~y), drawn(~calls & y)
    return (2 * tp / (2 * tp + fp + fn)).mean(axis=1)


def _paired_ci(a: pd.DataFrame, b: pd.DataFrame, seed: int) -> str:
    """The 95 % interval of A's F1 minus B's (points) as the comparison table shows it."""
    lo, hi = np.quantile(_boot_f1(a, seed) - _boot_f1(b, seed), [0.025, 0.975])
    return f"{100 * lo:.1f} to {100 * hi:.1f}"


def _mean_ci(values: np.ndarray, seed: int) -> tuple[float, float]:
    """The 95 % interval of the mean of ``values`` over the study's scenes, drawn whole."""
    w, gi = _scene_weights(_objects()["scene"].to_numpy(), seed)
    reps = (w @ np.bincount(gi, weights=values)) / (w @ np.bincount(gi))
    lo, hi = np.quantile(reps, [0.025, 0.975])
    return float(lo), float(hi)


def _r1(x: float) -> float:
    """A fraction as percent, to 0.1."""
    return round(100 * x, 1)


# --- constants, Table 3 ---------------------------------------------------------------------


def test_the_book_s_fixed_words_and_counts():
    """The raw-input rows' label and the number of example frames are the book's."""
    assert ch07.RAW_LABEL == "the paper's raw input"
    assert ch07.EXAMPLES == 4


def test_raw_methods_are_the_profile_s_flows_trained_on_raw_input_in_its_order(tmp_path):
    """``raw_input_methods`` [dis, gt] gives gt then dis (flow_methods' order); none gives
    none."""
    assert ch07.raw_methods(_profile(tmp_path)) == ["gt", "dis"]
    assert ch07.raw_methods(_profile(tmp_path, input_scaling="raw",
                                     raw_input_methods=[])) == []
    assert ch07.raw_methods(load_profile("demo", raw_input_methods=["dis"])) == ["dis"]


def test_table3_rows_are_the_classifiers_the_raw_input_models_and_the_rule(study):
    """Table 3's rows in order (classifiers, raw-input models in profile order, the rule on
    each flow), each with its own record's F1, precision and recall (%, to 0.1)."""
    t = ch07.table3(study)
    want = ([(f"ResNet18 on {m} flow", SCORES[m]) for m in METHODS]
            + [(f"ResNet18 on {m} flow, the paper's raw input", RAW[m]) for m in ("gt", "dis")]
            + [(f"geometric residual, {m} flow", BASELINE[m]) for m in METHODS])
    assert t["Method"].tolist() == [name for name, _ in want]
    assert t[["F1 (%)", "P (%)", "R (%)"]].to_numpy().tolist() == [
        [_r1(r["f1"]), _r1(r["precision"]), _r1(r["recall"])] for _, r in want]


# --- the paired comparisons -----------------------------------------------------------------

#: The comparisons of the study, in order: (name, A's table, B's table).
PAIRS = [("gt - dis", "test", "gt", "test", "dis"),
         ("gt - fastflownet", "test", "gt", "test", "fastflownet"),
         ("dis - fastflownet", "test", "dis", "test", "fastflownet"),
         *[(f"{m}: classifier - oracle rule", "test", m, "baseline", m) for m in METHODS],
         *[(f"{m}: log input - raw input", "test", m, "raw", m) for m in ("gt", "dis")]]
TABLES = {"test": _test_table, "baseline": _baseline_table, "raw": _raw_table}


def test_comparisons_are_every_pair_then_the_rule_then_the_raw_input_seeded(study):
    """Names and order; each effect A minus B (points); each interval the scene-and-seed
    bootstrap of A - B drawn with the profile's seed (15, not the default 0)."""
    t = ch07.comparisons(study)
    assert t["comparison"].tolist() == [name for name, *_ in PAIRS]
    for (name, ta, ma, tb, mb), delta, ci in zip(
            PAIRS, t["ΔF1 (points)"], t["95% CI, scenes and seeds (points)"], strict=True):
        a, b = TABLES[ta](ma), TABLES[tb](mb)
        assert delta == pytest.approx(round(100 * (_f1(a) - _f1(b)), 1), abs=1e-9), name
        assert ci == _paired_ci(a, b, SEED), name
        assert ci != _paired_ci(a, b, 0), name  # the seed shows


def test_comparisons_refuse_tables_of_different_objects(tmp_path):
    """Two flows' predictions, a classifier and its rule, or the two recipes, scored on
    different objects: a ValueError naming them."""
    p = _write_study(tmp_path)
    folder = {m: pipeline.node_dir(p, Node("evaluate", m)) for m in METHODS}
    for m, name, match in (("dis", "test", "^gt and dis were scored on different objects$"),
                           ("gt", "baseline",
                            "^gt's classifier and rule were scored on different objects$"),
                           ("dis", "raw",
                            "^dis's two recipes were scored on different objects$")):
        f = folder[m] / f"{name}.parquet"
        good = pd.read_parquet(f)
        good.assign(ann_token=good["ann_token"].str.replace("obj-03", "obj-99")).to_parquet(f)
        with pytest.raises(ValueError, match=match):
            ch07.comparisons(p)
        good.to_parquet(f)
    assert len(ch07.comparisons(p)) == len(PAIRS)


def test_answer_says_each_comparison_with_its_verdict():
    """The comparisons in words, joined by "; ", ending with ".": decided ones name the
    better arm, the others say equivalent or inconclusive."""
    row = {"detectable": 0.025, "per_seed": [0.0], "p_not_better": 0.5, "n_scenes": 29,
           "n": 90}
    table = comparison_table({
        "a - b": {**row, "delta_f1": 0.03, "ci": (0.012, 0.051)},
        "c - d": {**row, "delta_f1": -0.04, "ci": (-0.061, -0.02)},
        "e - f": {**row, "delta_f1": 0.002, "ci": (-0.019, 0.019)},
        "g - h": {**row, "delta_f1": 0.01, "ci": (-0.03, 0.05)}})
    words = "(95 % interval over scenes and training seeds"
    assert ch07.answer(table) == (
        f"a - b: +3.0 F1 points {words} 1.2 to 5.1), decided: the first is better; "
        f"c - d: -4.0 F1 points {words} -6.1 to -2.0), decided: the second is better; "
        f"e - f: +0.2 F1 points {words} -1.9 to 1.9; equivalent: within +/-2 points); "
        f"g - h: +1.0 F1 points {words} -3.0 to 5.0; inconclusive: these scenes would "
        "detect 2.5 points or more).")


def test_landing_words_quote_the_headline_against_the_rule_and_the_exact_flow():
    """The headline method's (dis) classifier against the rule and gt against dis, each
    with its interval and verdict word; a comparison the table lacks is said so."""
    row = {"detectable": 0.02, "per_seed": [0.0], "p_not_better": 0.5, "n_scenes": 29,
           "n": 90}
    table = comparison_table({
        "gt - fastflownet": {**row, "delta_f1": 0.05, "ci": (0.02, 0.08)},
        "gt - dis": {**row, "delta_f1": -0.03, "ci": (-0.05, -0.01)},
        "fastflownet: classifier - oracle rule": {**row, "delta_f1": 0.04,
                                                  "ci": (0.01, 0.07)},
        "dis: classifier - oracle rule": {**row, "delta_f1": 0.002, "ci": (-0.019, 0.019)}})
    words = "(95 % interval over scenes and training seeds"
    assert ch07.landing_words(table, load_profile("demo")) == {
        "headline_vs_oracle": f"+0.2 F1 points {words} -1.9 to 1.9; equivalent: within "
                              "+/-2 points), equivalent",
        "exact_vs_headline": f"-3.0 F1 points {words} -5.0 to -1.0), decided"}
    assert ch07.landing_words(table.iloc[:1], load_profile("demo")) == {
        "headline_vs_oracle": "not in this profile", "exact_vs_headline": "not in this profile"}


# --- the original protocol and the recorded numbers -----------------------------------------


def test_protocols_show_each_method_s_clean_and_original_f1(study):
    """Per method in profile order: its own record's clean and original F1 and their
    difference (%, points; to 0.1)."""
    got = ch07.protocols(study)
    want = pd.DataFrame({"method": METHODS,
                         "clean F1 (%)": [_r1(ORIGINAL[m]["clean"]) for m in METHODS],
                         "original protocol F1 (%)": [_r1(ORIGINAL[m]["original"])
                                                      for m in METHODS],
                         "original - clean (points)": [_r1(ORIGINAL[m]["original_minus_clean"])
                                                       for m in METHODS]})
    pd.testing.assert_frame_equal(got, want)
    assert ch07.original_vs_clean(study, "dis") == ORIGINAL["dis"]


def _numbers_want() -> dict:
    """What chapter 07 records of the study, from the hand-written records."""
    want: dict = {}
    for m in METHODS:
        s = SCORES[m]
        want |= {f"test_f1_{m}": _r1(s["f1"]), f"test_f1_min_{m}": _r1(s["f1_min"]),
                 f"test_f1_max_{m}": _r1(s["f1_max"]),
                 f"test_seed_sd_{m}": _r1(s.get("seed_sd", np.nan)),
                 f"baseline_f1_{m}": _r1(BASELINE[m]["f1"])}
    last, head = SCORES["fastflownet"], SCORES["dis"]
    gaps = [o - c for m in METHODS for o, c in zip(ORIGINAL[m]["per_seed_original"],
                                                   ORIGINAL[m]["per_seed_clean"], strict=True)]
    assert (min(gaps), max(gaps)) == pytest.approx((0.0623, 0.1201))
    return want | {
        "n_test": 23, "n_test_scenes": 11, "seeds": 2, "training_seeds": 2,
        "chance_f1": _r1(last["always_moving_f1"]), "scored_by": "mean of 2 training seeds",
        "headline_method": "dis", "headline_f1": _r1(head["f1"]),
        "headline_precision": _r1(head["precision"]), "headline_recall": _r1(head["recall"]),
        "headline_ci_lo": _r1(head["ci"][0]), "headline_ci_hi": _r1(head["ci"][1]),
        "headline_baseline_f1": _r1(BASELINE["dis"]["f1"]),
        "protocol_gap": _r1((0.0671 + 0.1104 + 0.0769) / 3),
        "protocol_gap_range": "6.2 to 12.0 points over the 6 models",
        "bootstrap_draws": 2000}


def test_numbers_record_each_method_the_headline_and_the_protocol_gap(study):
    """Every number chapter 07 records, each from its own record (the objects, scenes and
    seeds of the last method's; a seed SD the record lacks is NaN)."""
    got = ch07.numbers(study)
    want = _numbers_want()
    assert sorted(got) == sorted(want)
    assert np.isnan(got.pop("test_seed_sd_gt")) and np.isnan(want.pop("test_seed_sd_gt"))
    assert got == want
    assert want["protocol_gap"] == 8.5 and want["test_seed_sd_dis"] == 2.5  # 8.48: 101 x 8.6


def test_numbers_say_how_cross_validated_scores_were_pooled(tmp_path):
    """A fold-unit record: pooled over its folds, with its training seeds a fold (one when
    the record does not say)."""
    p = _write_study(tmp_path)
    f = pipeline.node_dir(p, Node("evaluate", "fastflownet")) / "scores.json"
    rec = {**SCORES["fastflownet"], "unit": "fold", "seeds": 3, "training_seeds": 4}
    f.write_text(json.dumps(rec))
    got = ch07.numbers(p)
    assert (got["seeds"], got["training_seeds"]) == (3, 4)
    assert got["scored_by"] == ("pooled over 3 cross-validation folds, each scene scored by "
                                "the models that never saw it, the mean of 4 training seeds "
                                "a fold")
    f.write_text(json.dumps({k: v for k, v in rec.items() if k != "training_seeds"}))
    got = ch07.numbers(p)
    assert got["training_seeds"] == 1
    assert got["scored_by"].endswith("the mean of 1 training seeds a fold")


def test_bootstrap_draws_is_the_intervals_replicate_count(monkeypatch):
    """Every interval of the book draws 2000 replicates; paired comparisons that drew
    another number would make the methods section wrong, so that is an error."""
    assert ch07.bootstrap_draws() == 2000

    def other(y_true, prob_a, prob_b, groups, n=1999, seed=0):
        return {}

    monkeypatch.setattr("flowmod.metrics.paired_comparison", other)
    with pytest.raises(ValueError, match="^the paired comparisons and Table 3 bootstrap "
                                         "different replicates$"):
        ch07.bootstrap_draws()


# --- breakdowns -----------------------------------------------------------------------------


def _small(shift: int) -> pd.DataFrame:
    """12 objects at the distance bins' edges, three scenes, three categories, two seeds."""
    d = [30.0, 35.0, 39.99, 40.0, 45.0, 49.9, 50.0, 55.0, 59.9, 60.0, 65.0, 70.0]
    y = np.array([1, 0, 1, 1, 0, 1, 0, 1, 1, 0, 1, 0])
    s0 = np.where(np.roll(y, shift) == 1, 0.9, 0.1)
    s1 = np.where(np.roll(y, shift + 1) == 1, 0.7, 0.3)
    return pd.DataFrame({"scene": [f"s{k % 3}" for k in range(12)], "label": y,
                         "distance": d, "prob_s0": s0, "prob_s1": s1, "prob": s0,
                         "category": ["vehicle.car", "vehicle.truck", "vehicle.bus"] * 4})


def _group_scores(df: pd.DataFrame) -> tuple[int, int, float]:
    """n, movers and the seed-mean F1 of a group (scikit-learn)."""
    f1 = np.mean([f1_score(df["label"], df[c] > 0.5, zero_division=np.nan)
                  for c in ("prob_s0", "prob_s1")])
    return len(df), int(df["label"].sum()), float(f1)


def test_by_distance_bins_each_method_s_objects_in_10_m_steps_to_70():
    """Per method, bins [30, 40), [40, 50), [50, 60), [60, 70.01) (70 m itself in the last),
    each with its objects, movers and seed-mean F1."""
    preds = {"one": _small(0), "two": _small(1)}
    got = ch07.by_distance(preds)
    assert list(got) == ["one", "two"]
    names = ["[30.0, 40.0)", "[40.0, 50.0)", "[50.0, 60.0)", "[60.0, 70.01)"]
    for m, df in preds.items():
        t = got[m]
        assert t["distance_bin"].tolist() == names
        want = [_group_scores(df.iloc[3 * k:3 * k + 3]) for k in range(4)]
        assert t[["n", "n_moving"]].to_numpy().tolist() == [[n, mv] for n, mv, _ in want]
        assert t["f1"].to_numpy() == pytest.approx([f for *_, f in want], nan_ok=True)
        assert t["scenes"].tolist() == [3, 3, 3, 3]


def test_by_category_stacks_one_block_per_method():
    """F1 per category, the methods' blocks one after another with a ``method`` column."""
    preds = {"one": _small(0), "two": _small(2)}
    got = ch07.by_category(preds)
    assert got.columns.tolist() == ["method", "category", "n", "n_moving", "precision",
                                    "recall", "f1", "accuracy", "ci_lo", "ci_hi", "scenes"]
    cats = ["vehicle.bus", "vehicle.car", "vehicle.truck"]
    assert got["method"].tolist() == ["one"] * 3 + ["two"] * 3
    assert got["category"].tolist() == cats * 2
    assert got.index.tolist() == [0, 1, 2] * 2
    want = [_group_scores(df[df["category"] == c])[2] for df in preds.values() for c in cats]
    assert got["f1"].to_numpy() == pytest.approx(want, nan_ok=True)


def _batch_mean(y: np.ndarray, yhat: np.ndarray, f) -> float:
    """The mean of ``f`` over consecutive batches of 128 (scikit-learn, 0 where undefined)."""
    return float(np.mean([f(y[i:i + 128], yhat[i:i + 128], zero_division=0)
                          for i in range(0, len(y), 128)]))


def test_protocol_scores_score_seed_0_four_ways_per_method():
    """Per method, ``prob`` (seed 0) scored on the whole set, per batch of 128, with stills
    thinned 1 of 2 (the first of each two kept), and thinned per batch."""
    rng = np.random.default_rng(3)
    y = rng.permutation(np.arange(150) % 3 == 0).astype(int)
    prob = np.where(rng.random(150) < 0.8, y, 1 - y) * 0.6 + 0.2
    preds = {"big": pd.DataFrame({"label": y, "prob": prob, "prob_s1": 1 - prob}),
             "small": pd.DataFrame({"label": y[:20], "prob": prob[:20]})}
    got = ch07.protocol_scores(preds)
    assert got.columns.tolist() == ["method", "protocol", "n", "precision", "recall", "f1"]
    names = ["clean: whole set", "per-batch F1, all objects",
             "stills thinned 1 of 2, whole set", "paper protocol: thinned + per-batch"]
    assert got["method"].tolist() == ["big"] * 4 + ["small"] * 4
    assert got["protocol"].tolist() == names * 2
    want = []
    for df in preds.values():
        yy, yhat = df["label"].to_numpy(), (df["prob"] > 0.5).to_numpy().astype(int)
        keep = (yy == 1) | (np.cumsum(yy == 0) % 2 == 1)
        for y_, h_, batch in ((yy, yhat, False), (yy, yhat, True),
                              (yy[keep], yhat[keep], False), (yy[keep], yhat[keep], True)):
            fs = (precision_score, recall_score, f1_score)
            want.append([len(y_), *(_batch_mean(y_, h_, f) if batch else f(y_, h_)
                                    for f in fs)])
    assert got[["n", "precision", "recall", "f1"]].to_numpy() == pytest.approx(np.array(want))
    assert got["f1"].iloc[0] != pytest.approx(got["f1"].iloc[1])  # two batches differ


# --- the flow error in and around the box ---------------------------------------------------


def test_crop_errors_are_the_end_point_errors_inside_and_around_each_box(study):
    """Against the exact flow (the default reference) and against DIS: the mean end-point
    error of the box's pixels and of the rest of the window, per object in order."""
    got = ch07.crop_errors(study, "fastflownet")
    assert got.columns.tolist() == ["ann_token", "scene", "label", "distance", "speed",
                                    "epe_box", "epe_around"]
    pd.testing.assert_frame_equal(got.iloc[:, :5], _objects()[got.columns[:5]])
    inside, around = _u("fastflownet")
    assert got["epe_box"].tolist() == pytest.approx(inside.tolist())
    assert got["epe_around"].tolist() == pytest.approx(around.tolist())
    vs_dis = ch07.crop_errors(study, "fastflownet", reference="dis")
    d_in, d_around = _u("dis")
    assert vs_dis["epe_box"].tolist() == pytest.approx(np.abs(inside - d_in).tolist())
    assert vs_dis["epe_around"].tolist() == pytest.approx(np.abs(around - d_around).tolist())
    # float16 crops nearly equal: their error is computed in float32 (float64 here)
    folder = {m: pipeline.node_dir(study, Node("crops", m, "keyframe")) for m in ("raft", "dis")}
    x, r = (np.load(folder[m] / "test.npy").astype(np.float64) for m in ("raft", "dis"))
    err = np.linalg.norm(x - r, axis=1)
    box = err[:, INSIDE, INSIDE].sum((1, 2))
    near = ch07.crop_errors(study, "raft", reference="dis")
    assert near["epe_box"].to_numpy() == pytest.approx(box / 11 ** 2, rel=1e-5)
    assert near["epe_around"].to_numpy() == pytest.approx(
        (err.sum((1, 2)) - box) / (SIZE ** 2 - 11 ** 2), rel=1e-5)
    with pytest.raises(ValueError, match="^farneback and gt crops hold different objects$"):
        ch07.crop_errors(study, "farneback")


def _explanation_want() -> list[list]:
    """error_explanation(fastflownet, dis) of the study, row by row."""
    a, b = "fastflownet", "dis"
    rows = []
    for k, name in enumerate(("flow error inside the box, median (px)",
                              "flow error around the box, median (px)")):
        ea, eb = _u(a)[k], _u(b)[k]
        worse = np.where(ea > eb, 1.0, np.where(ea == eb, 0.5, 0.0))
        lo, hi = _mean_ci(worse, SEED)
        rows.append([name, round(float(np.median(ea)), 2), round(float(np.median(eb)), 2),
                     _r1(worse.mean()), f"{100 * lo:.1f}-{100 * hi:.1f}"])
    around = _u(a)[1]
    third = np.empty(N, int)
    third[np.argsort(around)] = np.arange(N) // (N // 3)  # distinct errors: eight a third
    edges = np.quantile(around, [0, 1 / 3, 2 / 3, 1])
    label = _objects()["label"].to_numpy()
    right = {m: (_test_table(m)[["prob_s0", "prob_s1"]].mean(axis=1) > 0.5).to_numpy()
             == label for m in (a, b)}
    assert right[a][0] == False  # noqa: E712 (a seed-mean of 0.5 is on no side)
    for k in range(3):
        rows.append([f"classifier accuracy (%), {a}'s error around the box "
                     f"{edges[k]:.1f}-{edges[k + 1]:.1f} px (8 objects)",
                     _r1(right[a][third == k].mean()), _r1(right[b][third == k].mean()), "", ""])
    return rows


def test_error_explanation_compares_two_flows_errors_and_accuracy_by_thirds(study):
    """Medians inside and around the box, the share of objects where A errs more (ties
    half) with its interval over scenes (seed 15), then both classifiers' accuracy by thirds
    of A's error around the box."""
    got = ch07.error_explanation(study, "fastflownet", "dis")
    assert got.columns.tolist() == ["quantity", "fastflownet", "dis",
                                    "objects where fastflownet errs more (%)",
                                    "95% CI over scenes (%)"]
    want = _explanation_want()
    assert got.to_numpy().tolist() == want
    for k in (0, 1):  # ties count half; the profile's seed shows
        ea, eb = _u("fastflownet")[k], _u("dis")[k]
        worse = np.where(ea > eb, 1.0, np.where(ea == eb, 0.5, 0.0))
        lo, hi = _mean_ci(worse, 0)
        assert (worse == 0.5).any() and want[k][4] != f"{100 * lo:.1f}-{100 * hi:.1f}"


def test_error_explanation_pairs_predictions_with_crops_by_object(tmp_path):
    """The classifiers' accuracy by thirds reads each object's own prediction: a test table
    written in another row order gives the same explanation, and one that lacks an object
    of the crops is an error naming the method, not a shifted row."""
    p = _write_study(tmp_path)
    want = _explanation_want()
    node = Node("evaluate", "dis")
    table = pipeline.node_dir(p, node) / "test.parquet"
    pd.read_parquet(table).iloc[::-1].to_parquet(table, index=False)
    assert ch07.error_explanation(p, "fastflownet", "dis").to_numpy().tolist() == want
    pd.read_parquet(table).iloc[1:].to_parquet(table, index=False)
    with pytest.raises(ValueError, match="^dis's test predictions lack 1 of the objects"):
        ch07.error_explanation(p, "fastflownet", "dis")


def test_error_explanation_thirds_put_an_edge_value_above_it_and_round_to_a_tenth(
        monkeypatch):
    """Thirds of A's error around the box by its quantiles: an object whose error equals an
    inner edge counts in the third above it; accuracies are rounded to 0.1 %, medians to
    0.01 px."""
    err = {"x": pd.DataFrame({"ann_token": list("abcdefg"), "scene": list("pqrspqr"),
                              "epe_box": [0.111, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7],
                              "epe_around": [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]}),
           "y": pd.DataFrame({"ann_token": list("abcdefg"), "scene": list("pqrspqr"),
                              "epe_box": [0.0] * 7, "epe_around": [9.0] * 7})}
    right = {"x": np.array([1, 0, 1, 1, 1, 0, 0]), "y": np.array([0, 0, 0, 1, 0, 1, 1])}
    monkeypatch.setattr(ch07, "crop_errors", lambda p, m: err[m])
    monkeypatch.setattr(ch07, "_right", lambda p, m, tokens: right[m])
    got = ch07.error_explanation(load_profile("smoke"), "x", "y")
    # edges 0, 2, 4, 6 px: thirds {0, 1}, {2, 3}, {4, 5, 6} (2 and 4 go up)
    assert got["quantity"].tolist()[2:] == [
        "classifier accuracy (%), x's error around the box 0.0-2.0 px (2 objects)",
        "classifier accuracy (%), x's error around the box 2.0-4.0 px (2 objects)",
        "classifier accuracy (%), x's error around the box 4.0-6.0 px (3 objects)"]
    assert got["x"].tolist() == [0.4, 3.0, 50.0, 100.0, 33.3]
    assert got["y"].tolist() == [0.0, 9.0, 0.0, 50.0, 66.7]


def test_network_pair_is_the_first_network_beside_dis_and_the_exact_flow():
    """(first network, dis) only with gt and dis in the profile."""
    def pair(methods):
        return ch07.network_pair(load_profile(
            "demo", flow_methods=methods, raw_input_methods=None, extension_methods=None,
            wide_methods=None))

    assert pair(["gt", "dis", "farneback", "fastflownet"]) == ("fastflownet", "dis")
    assert pair(["gt", "raft", "dis", "fastflownet"]) == ("raft", "dis")
    assert pair(["gt", "dis", "farneback"]) is None
    assert pair(["dis", "farneback", "fastflownet"]) is None
    assert pair(["gt", "farneback", "fastflownet"]) is None


def test_explanation_words_read_every_number_off_the_table():
    """The sentence quotes the shares, intervals and medians of the first two rows and
    each third's accuracies, in order."""
    share = "objects where raft errs more (%)"
    table = pd.DataFrame([
        ["in", 1.234, 0.5, 61.25, "50.0-70.0"], ["around", 2.0, 3.456, 40.0, "30.5-49.5"],
        ["t1", 90.0, 80.04, "", ""], ["t2", 70.55, 75.0, "", ""], ["t3", 60.0, 50.0, "", ""]],
        columns=["quantity", "raft", "dis", share, "95% CI over scenes (%)"])
    assert ch07.explanation_words(table, "raft", "dis") == (
        "Inside the box, raft's flow errs more than dis's on 61.2 % of the objects (95 % "
        "over scenes 50.0-70.0 %; medians 1.23 and 0.50 px); around the box, on 40.0 % "
        "(30.5-49.5 %; medians 2.00 and 3.46 px). By thirds of raft's error around the "
        "box, from the smallest, the classifiers are right for 90.0 against 80.0 %, 70.5 "
        "against 75.0 %, 60.0 against 50.0 % of the objects (raft against dis).")


def test_network_section_explains_the_network_row_or_says_why_not(study, tmp_path):
    """With a network beside DIS and gt: the network against DIS and its words; without
    one, an empty table and a sentence."""
    table, words = ch07.network_section(study)
    want = _explanation_want()
    assert table.to_numpy().tolist() == want
    (_, a1, b1, s1, c1), (_, a2, b2, s2, c2) = want[:2]
    assert words.startswith(
        f"Inside the box, fastflownet's flow errs more than dis's on {s1:.1f} % of the "
        f"objects (95 % over scenes {c1} %; medians {a1:.2f} and {b1:.2f} px); around the "
        f"box, on {s2:.1f} % ({c2} %; medians {a2:.2f} and {b2:.2f} px).")
    table, words = ch07.network_section(_profile(tmp_path, flow_methods=["gt", "dis"]))
    assert table.columns.tolist() == ["quantity"] and table.empty
    assert words == "This profile has no network flow beside DIS and the exact flow."
