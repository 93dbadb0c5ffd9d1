"""Chapter 13's backend (:mod:`flowmod.chapters.ch13_flow_errors`) on hand-made published
nodes: quick tests for mutation testing, which runs only the quick tests (the chapter's own
tests execute its notebook on a built world and are slow).

The run folders are written here by hand: each arm's ``eevaluate`` node (its test
predictions and realised errors), each kind's ``elevels`` node (``levels.json``), and for the
real methods' profiles the ``crops`` nodes of the exact flow and of the methods, the
``context`` node (the still-world flow) and the ``evaluate`` nodes. Every expected number is
computed here from those same inputs, with scikit-learn, numpy or by hand: the F1 points of
each arm minus the exact arm's, the slope through the origin, the error profile of each
object pixel by pixel. With all objects in one scene and one model an arm, every scene
resample is the whole set, so an interval is its point estimate exactly.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from handmade import node_folder
from sklearn.metrics import f1_score

from flowmod import metrics
from flowmod.chapters import ch13_flow_errors as ch
from flowmod.dag import Node
from flowmod.params import Params, load_profile

#: The arms of the hand-made experiment, in the order the chapter reads them.
ARMS = ["exact", "noise/0", "noise/1", "pull/0", "pull/1", "ring/0", "ring/1"]
#: Objects of an arm's test rows: the even ones move.
N = 40
#: Each arm's wrong calls (indices of objects called on the wrong side of 0.5): noise makes
#: the classifier better than the exact flow, pull worse, ring changes nothing.
WRONG = {"exact": {0, 7}, "noise/0": {0}, "noise/1": set(),
         "pull/0": {0, 7, 12, 19, 24}, "pull/1": {0, 7, 12, 19, 24, 31, 33, 36, 2, 4},
         "ring/0": {0, 7}, "ring/1": {0, 7}}
#: What each kind's ``levels.json`` records.
LEVELS = {"noise": {"kind": "noise", "unit": "sigma (px)", "targets": [1.0, 2.0],
                    "levels": [0.61234, 1.23456], "reached": [True, True]},
          "pull": {"kind": "pull", "unit": "alpha", "targets": [1.0, 2.0],
                   "levels": [0.4321, 0.9999], "reached": [True, False]},
          "ring": {"kind": "ring", "unit": "sigma (px)", "targets": [1.0, 2.0],
                   "levels": [2.5, 5.0], "reached": [False, False]}}
#: The words the chapter shows for each kind.
WORDS = {"noise": "white noise in the box", "pull": "movers' motion pulled toward the still world",
         "ring": "white noise around the box only"}


def _arm_tables(scenes: int) -> dict[str, tuple[pd.DataFrame, pd.DataFrame]]:
    """(test predictions, realised errors) of each arm: skewed errors (mean != median), the
    ring's far larger around the box than in it, the others' the other way round."""
    label = np.arange(N) % 2 == 0
    obj = pd.DataFrame({"ann_token": [f"a{i}" for i in range(N)],
                        "scene": [f"scene-{i * scenes // N}" for i in range(N)],
                        "fold": 0, "label": label.astype(int)})
    out = {}
    for j, key in enumerate(ARMS):
        call = label.copy()
        call[sorted(WRONG[key])] = ~call[sorted(WRONG[key])]
        rng = np.random.default_rng(j)
        box, ring = (rng.uniform(0.0, 1.0, N) ** 3 * (j + 1) for _ in range(2))
        if key.startswith("ring"):
            box, ring = box / 10, ring * 3
        errors = obj[["ann_token", "fold"]].assign(epe_box=box, epe_ring=ring)
        out[key] = (obj.assign(prob=np.where(call, 0.9, 0.1)), errors)
    return out


def _make_arms(root, scenes: int, seed: int = 0) -> Params:
    """A run folder with every arm's ``eevaluate`` node and every kind's ``elevels`` node."""
    p = load_profile("demo", run_dir=str(root / "runs"), seed=seed,
                     error_kinds=["noise", "pull", "ring"], error_targets=[1.0, 2.0])
    for key, (pred, err) in _arm_tables(scenes).items():
        folder = node_folder(p, Node("eevaluate", "gt", key))
        pred.to_parquet(folder / "test.parquet", index=False)
        err.to_parquet(folder / "errors.parquet", index=False)
    for kind, rec in LEVELS.items():
        (node_folder(p, Node("elevels", "gt", kind)) / "levels.json").write_text(json.dumps(rec))
    return p


@pytest.fixture(scope="module")
def one_scene(tmp_path_factory) -> Params:
    """The experiment with every object in one scene: intervals are point estimates."""
    return _make_arms(tmp_path_factory.mktemp("ch13_one_scene"), scenes=1)


@pytest.fixture(scope="module")
def eight_scenes(tmp_path_factory) -> Params:
    """The experiment over eight scenes (seed 5): intervals that resample something."""
    return _make_arms(tmp_path_factory.mktemp("ch13_eight_scenes"), scenes=8, seed=5)


@pytest.fixture(scope="module")
def one_scene_effects(one_scene) -> pd.DataFrame:
    """:func:`ch.effects` of every arm of the one-scene experiment (computed once)."""
    return ch.effects(one_scene, ARMS)


def _f1(key: str) -> float:
    pred = _arm_tables(1)[key][0]
    return float(f1_score(pred["label"], pred["prob"] > 0.5))


def _delta(key: str) -> float:
    """An arm's F1 minus the exact arm's (points)."""
    return 100 * (_f1(key) - _f1("exact"))


def _error(key: str) -> float:
    """An arm's realised error where its kind is measured (px)."""
    col = "epe_ring" if key.startswith("ring") else "epe_box"
    return float(_arm_tables(1)[key][1][col].mean())


# --- which arms are built, and their predictions ----------------------------------------------


def test_built_lists_the_arms_whose_scoring_node_is_built(one_scene, monkeypatch):
    """``built`` asks about each arm's ``eevaluate[gt/<arm>]`` node, in the arms' order, and
    keeps those built."""
    asked = []

    def fake(p, node):
        assert p is one_scene, "asked with the run's parameters"
        asked.append(node)
        return node.part in {"exact", "pull/1", "noise/0"}

    monkeypatch.setattr(ch.pipeline, "built", fake)
    assert ch.built(one_scene) == ["exact", "noise/0", "pull/1"]
    assert asked == [Node("eevaluate", "gt", k) for k in ARMS]


def test_an_arm_s_predictions_carry_its_realised_errors(one_scene):
    """One arm's test predictions with the realised errors of its own node."""
    pred, err = _arm_tables(1)["pull/1"]
    got = ch.arm_predictions(one_scene, "pull/1")
    assert got["prob"].tolist() == pred["prob"].tolist()
    assert got["epe_box"].tolist() == err["epe_box"].tolist()
    assert got["epe_ring"].tolist() == err["epe_ring"].tolist()


def test_the_levels_table_has_one_row_per_degraded_arm(one_scene):
    """Per built arm but the exact one: the kind in words, the target, the matched level (to
    0.001), its unit, whether it was reached, the realised box and ring errors' means and
    medians (to 0.01)."""
    done = ["exact", "noise/1", "pull/1", "ring/0"]
    got = ch.levels_table(one_scene, done)
    assert got.columns.tolist() == ["kind", "target (px)", "level", "of", "reached",
                                    "box mean (px)", "box median (px)", "ring mean (px)",
                                    "ring median (px)"]
    tables = _arm_tables(1)
    rows = []
    for key, (kind, t) in zip(done[1:], [("noise", 1), ("pull", 1), ("ring", 0)], strict=True):
        err, lv = tables[key][1], LEVELS[kind]
        rows.append([WORDS[kind], lv["targets"][t], round(lv["levels"][t], 3), lv["unit"],
                     "yes" if lv["reached"][t] else "no (largest level)",
                     round(err["epe_box"].mean(), 2), round(err["epe_box"].median(), 2),
                     round(err["epe_ring"].mean(), 2), round(err["epe_ring"].median(), 2)])
    assert got.values.tolist() == rows
    assert got["reached"].tolist() == ["yes", "no (largest level)", "no (largest level)"]
    assert got["level"].tolist() == [1.235, 1.0, 2.5]
    assert ch.levels_table(one_scene, ["exact"]).empty


# --- the effects and the costs ----------------------------------------------------------------


def test_each_effect_is_the_arm_minus_the_exact_arm(one_scene_effects):
    """Every degraded arm minus the exact arm on the same objects (F1 points), named by its
    kind and target, with its realised error where its kind is measured (the ring's around
    the box), the table's columns in order, and its interval as numbers (one scene: the
    estimate itself)."""
    eff = one_scene_effects
    assert eff.columns.tolist() == [
        "kind", "target", "error (px)", "delta", "comparison", "ΔF1 (points)",
        "95% CI, scenes and seeds (points)", "interval counts", "verdict",
        "detectable (points)", "per seed (points)", "replicates with A <= B (%)", "scenes",
        "objects", "ci_lo", "ci_hi"]
    keys = ARMS[1:]
    assert eff["kind"].tolist() == [k.split("/")[0] for k in keys]
    assert eff["target"].tolist() == [int(k.split("/")[1]) for k in keys]
    assert eff["comparison"].tolist() == [f"{WORDS[k.split('/')[0]]}, target {k[-1]} - exact flow"
                                          for k in keys]
    assert eff["error (px)"].tolist() == pytest.approx([_error(k) for k in keys], rel=1e-12)
    want = [_delta(k) for k in keys]
    assert eff["delta"].tolist() == pytest.approx(want, rel=1e-9, abs=1e-9)
    assert eff["ΔF1 (points)"].tolist() == [round(d, 1) for d in want]
    assert eff["ci_lo"].tolist() == pytest.approx(want, rel=1e-9, abs=1e-9)
    assert eff["ci_hi"].tolist() == pytest.approx(want, rel=1e-9, abs=1e-9)
    assert eff["scenes"].tolist() == [1] * len(keys) and eff["objects"].tolist() == [N] * 6
    assert want[0] > 0 > want[2] and want[4] == 0  # noise helps, pull hurts, ring is inert


def test_effects_without_the_exact_arm_or_any_other_are_empty(one_scene):
    """No exact arm, nothing to pair against; the exact arm alone, nothing to pair."""
    assert ch.effects(one_scene, ["noise/0", "pull/0"]).empty
    assert ch.effects(one_scene, ["exact"]).empty
    assert ch.costs(one_scene, pd.DataFrame()).empty


def test_the_intervals_follow_the_run_s_seed(eight_scenes):
    """Over eight scenes the paired intervals and the costs' intervals are scene resamples
    drawn with the run's seed: another seed draws other scenes (a seed dropped would make
    both runs draw seed 0's)."""
    other = eight_scenes.model_copy(update={"seed": 0})
    a, b = ch.effects(eight_scenes, ARMS), ch.effects(other, ARMS)
    moved = a["ci_lo"].to_numpy() != b["ci_lo"].to_numpy()
    assert moved[a["kind"].to_numpy() == "pull"].all()
    assert (a["delta"] == b["delta"]).all()
    for text, lo, hi in a[["95% CI, scenes and seeds (points)", "ci_lo", "ci_hi"]].to_numpy():
        assert text.startswith(f"{lo:.1f} to {hi:.1f}")  # the numbers its text shows
    assert (a["ci_lo"] < a["ci_hi"])[a["kind"] == "pull"].all()
    ca, cb = ch.costs(eight_scenes, a), ch.costs(other, b)
    pull = ca["kind"] == "pull"
    assert ca.loc[pull, "ci_lo"].item() != cb.loc[pull, "ci_lo"].item()
    assert ca.loc[pull, "ci_lo"].item() < ca.loc[pull, "F1 points lost per px"].item()
    assert ca.loc[pull, "F1 points lost per px"].item() < ca.loc[pull, "ci_hi"].item()
    pd.testing.assert_frame_equal(ch.costs(eight_scenes, a), ca)  # the seed, not fresh draws


def test_an_arm_of_other_objects_is_one_error_naming_it(one_scene, monkeypatch):
    """An arm's predictions of other objects than the exact arm's cannot be paired."""
    real = ch.arm_predictions
    monkeypatch.setattr(ch, "arm_predictions",
                        lambda p, key: real(p, key).iloc[1:] if key == "pull/1" else
                        real(p, key))
    with pytest.raises(ValueError, match=r"^the pull/1 arm and the exact-flow arm were "
                                         "scored on different objects$"):
        ch.effects(one_scene, ["exact", "noise/0", "pull/1"])


def test_a_cost_is_decided_when_its_interval_excludes_0(one_scene, one_scene_effects,
                                                        monkeypatch):
    """"decided" is yes for an interval wholly above or below 0 (however close to it), no
    for one that holds 0."""
    for ci, want in (((0.2, 0.8), "yes"), ((-0.8, -0.2), "yes"), ((-0.1, 0.8), "no"),
                     ((0.0, 0.8), "no")):
        monkeypatch.setattr(ch, "slope_through_origin", lambda e, loss, r, ci=ci: (0.5, *ci))
        got = ch.costs(one_scene, one_scene_effects)
        assert got["decided"].tolist() == [want] * 3, ci


def _slope(kind: str) -> float:
    """Least squares through the origin of the kind's F1 points lost against its error."""
    err = np.array([_error(f"{kind}/{t}") for t in (0, 1)])
    loss = -np.array([_delta(f"{kind}/{t}") for t in (0, 1)])
    return float((err * loss).sum() / (err * err).sum())


def test_costs_are_the_slopes_of_the_points_lost_per_px(one_scene, one_scene_effects):
    """Per kind: the slope through the origin of its F1 points lost against its realised
    error, with the interval from the same scene resamples for every arm (one scene: the
    slope itself), decided when it excludes 0, its levels and largest error; sorted from
    the dearest kind down."""
    cost = ch.costs(one_scene, one_scene_effects)
    assert cost.columns.tolist() == ["kind", "error", "F1 points lost per px", "95% CI",
                                     "ci_lo", "ci_hi", "decided", "levels",
                                     "largest error (px)"]
    assert cost["kind"].tolist() == ["pull", "ring", "noise"]
    assert cost.index.tolist() == [0, 1, 2]
    assert cost["error"].tolist() == [WORDS[k] for k in ("pull", "ring", "noise")]
    slopes = [_slope(k) for k in ("pull", "ring", "noise")]
    assert slopes[0] > 0 and slopes[1] == 0 and slopes[2] < 0
    assert cost["F1 points lost per px"].tolist() == [round(s, 1) for s in slopes]
    assert cost["ci_lo"].tolist() == pytest.approx(slopes, rel=1e-9, abs=1e-9)
    assert cost["ci_hi"].tolist() == pytest.approx(slopes, rel=1e-9, abs=1e-9)
    assert cost["95% CI"].tolist() == [f"{s:.1f} to {s:.1f}" for s in slopes]
    assert cost["decided"].tolist() == ["yes", "no", "yes"]  # the pull above 0, noise below
    assert cost["levels"].tolist() == [2, 2, 2]
    assert cost["largest error (px)"].tolist() == [
        round(max(_error(f"{k}/0"), _error(f"{k}/1")), 2) for k in ("pull", "ring", "noise")]


def test_what_the_chapter_shows_of_effects_and_costs(one_scene_effects):
    """The effects' view keeps seven columns, its interval named for what it resamples;
    the costs' view drops the kind's key and the interval's numbers; empty stays empty."""
    eff = one_scene_effects
    view = ch.effects_view(eff)
    assert view.columns.tolist() == ["comparison", "error (px)", "ΔF1 (points)",
                                     "95% CI, scenes only (points)", "verdict", "scenes",
                                     "objects"]
    assert view["95% CI, scenes only (points)"].tolist() == eff[
        "95% CI, scenes and seeds (points)"].tolist()
    assert view["comparison"].tolist() == eff["comparison"].tolist()
    assert ch.effects_view(pd.DataFrame()).empty
    cost = pd.DataFrame({"kind": ["pull"], "error": ["e"], "F1 points lost per px": [1.0],
                         "95% CI": ["0.5 to 1.5"], "ci_lo": [0.5], "ci_hi": [1.5],
                         "decided": ["yes"], "levels": [2], "largest error (px)": [2.0]})
    assert ch.costs_view(cost).columns.tolist() == [
        "error", "F1 points lost per px", "95% CI", "decided", "levels", "largest error (px)"]
    assert ch.costs_view(pd.DataFrame()).empty


# --- what the notebook shows of the experiment -------------------------------------------------


def test_the_built_note_counts_the_arms_and_names_the_missing(one_scene):
    """How many of the planned arms are built, and which are not; a profile with no kind
    of error says it runs no experiment."""
    assert ch.built_note(one_scene, ARMS) == ("Arms built with these parameters: **7 of 7**.")
    assert ch.built_note(one_scene, ["exact", "ring/1"]) == (
        "Arms built with these parameters: **2 of 7**. Not built: noise/0, noise/1, pull/0, "
        "pull/1, ring/0.")
    none = one_scene.model_copy(update={"error_kinds": []})
    assert ch.built_note(none, []) == (
        "This profile runs no flow-error experiment: it needs the exact flow (`gt` in "
        "`flow_methods`, a generated world's) and at least one kind in `error_kinds`.")


def test_the_scope_table_counts_the_exact_arm_s_test_rows(one_scene):
    """Arms, folds, the experiment's and Table 3's widths, the exact arm's scenes, objects
    and movers; none without the exact arm; Table 3's width where the experiment sets none."""
    got = ch.scope_table(one_scene, ARMS)
    assert got.to_dict("records") == [{
        "arms (models a fold)": 7, "folds trained": 1, "network width": 16,
        "Table 3's width": 32, "test scenes": 1, "test objects": N, "of them moving": N // 2,
        "interval counts": "scenes only"}]
    wide = one_scene.model_copy(update={"error_width": None, "error_folds": 2})
    none = ch.scope_table(wide, ["noise/0"]).iloc[0].to_dict()
    assert none["network width"] == 32 and none["folds trained"] == 2
    assert (none["test scenes"], none["test objects"], none["of them moving"]) == (0, 0, 0)


# --- the real methods' errors in the experiment's terms ----------------------------------------


def _profile_by_hand(flow, exact, still, box) -> list[dict[str, float]]:
    """Each object's error profile, pixel by pixel, as the chapter defines it."""
    out = []
    for f, e, s, b in zip(flow, exact, still, box, strict=True):
        inside = [(r, c) for r in range(b.shape[0]) for c in range(b.shape[1]) if b[r, c]]
        around = [(r, c) for r in range(b.shape[0]) for c in range(b.shape[1]) if not b[r, c]]
        n_in, n_out = max(len(inside), 1), max(len(around), 1)

        def vec(a, r, c):
            return np.array([a[0, r, c], a[1, r, c]], float)

        err = {rc: vec(f, *rc) - vec(e, *rc) for rc in inside + around}
        bias = sum((err[rc] for rc in inside), np.zeros(2)) / n_in
        motion = sum((vec(e, *rc) - vec(s, *rc) for rc in inside), np.zeros(2)) / n_in
        apparent = sum((vec(f, *rc) - vec(s, *rc) for rc in inside), np.zeros(2)) / n_in
        m = math.hypot(*motion)
        lost = max(-(bias @ motion) / m, 0.0) if m >= 0.25 else 0.0
        out.append({"epe_box": sum(math.hypot(*err[rc]) for rc in inside) / n_in,
                    "epe_ring": sum(math.hypot(*err[rc]) for rc in around) / n_out,
                    "scatter": sum(math.hypot(*(err[rc] - bias)) for rc in inside) / n_in,
                    "bias": math.hypot(*bias), "lost": lost,
                    "apparent": math.hypot(*apparent), "motion": m})
    return out


PROFILE_COLUMNS = ["epe_box", "epe_ring", "scatter", "bias", "lost", "apparent", "motion"]


def test_the_error_profile_of_edge_cases_is_exact():
    """Each column on 2x2 crops by hand: a box with no pixel (its means over 1), a box
    covering the crop (no ring), motion exactly at the 0.25 px threshold (counted), below
    it (not counted), an error along the motion (nothing lost), one against a larger
    motion (its projection lost)."""
    rng = np.random.default_rng(3)
    still = np.round(rng.uniform(-2, 2, (6, 2, 2, 2)) * 8) / 8
    box = np.array([[[1, 1], [0, 0]], [[0, 0], [0, 0]], [[1, 1], [1, 1]],
                    [[1, 0], [1, 0]], [[0, 1], [0, 0]], [[1, 1], [0, 1]]], bool)
    motion = np.array([[0.25, 0.0], [1.0, 1.0], [0.0, -0.75], [0.2, 0.0], [3.0, 0.0],
                       [0.0, 1.5]])
    exact = still + motion[:, :, None, None]
    err = np.round(rng.uniform(-1, 1, (6, 2, 2, 2)) * 8) / 8
    err[0] += np.array([-0.5, 0.25])[:, None, None]  # against the motion at the threshold
    err[3] += np.array([-0.5, 0.0])[:, None, None]  # against, below the threshold
    err[4] = np.array([1.0, 0.0])[:, None, None]  # along the motion: nothing lost
    err[5] += np.array([0.0, -2.0])[:, None, None]  # against a larger motion
    flow = exact + err
    got = ch.error_profile(flow, exact, still, box)
    assert got.columns.tolist() == PROFILE_COLUMNS
    want = pd.DataFrame(_profile_by_hand(flow, exact, still, box))
    np.testing.assert_allclose(got.to_numpy(float), want[PROFILE_COLUMNS].to_numpy(),
                               rtol=1e-5, atol=1e-6)
    assert got.loc[0, "lost"] > 0.1 and got.loc[3, "lost"] == 0.0 and got.loc[4, "lost"] == 0.0
    assert got.loc[5, "lost"] > 1.0 and got.loc[2, "epe_ring"] == 0.0
    assert got.loc[1, ["epe_box", "scatter", "bias", "motion"]].tolist() == [0, 0, 0, 0]


#: Crop side and the frame boxes of the hand-made crops, with the pixels each box covers.
SIZE = 6
BOXES = [[100, 100, 103, 103], [100, 100, 101, 103], [50, 60, 55, 61]]
MASKS = [(slice(1, 4), slice(1, 4)), (slice(1, 4), slice(2, 4)), (slice(2, 4), slice(1, 4))]


def _crop_index(split: str, n: int, labels, token_prefix: str = "o") -> pd.DataFrame:
    box = np.array([BOXES[i % 3] for i in range(n)], float)
    return pd.DataFrame({"ann_token": [f"{token_prefix}{split}-{i}" for i in range(n)],
                         "label": labels, "scene": [f"scene-{split}-{i % 2}" for i in range(n)],
                         **{c: box[:, j] for j, c in enumerate(["xmin", "ymin", "xmax",
                                                                  "ymax"])}})


def _make_flows(root, folds: int, seed: int = 0, bad_context: bool = False):
    """A run folder with the keyframe crops of gt, dis and farneback, the still-world flow,
    and the Table 3 predictions of every method (fastflownet's not: it is not built).
    Returns (params, {method: (x, index) over the scored rows}, still, box)."""
    p = load_profile("demo", run_dir=str(root / "runs"), folds=folds, seed=seed,
                     error_kinds=["noise"], error_targets=[1.0])
    splits = [f"f{k}" for k in range(folds)] if folds > 1 else ["test"]
    rng = np.random.default_rng(11)
    rows = {m: [] for m in ("gt", "dis", "farneback")}
    stills = []
    for j, split in enumerate(splits):
        n = 3
        labels = [(i + j) % 2 for i in range(n)]
        idx = _crop_index(split, n, labels)
        still = np.round(rng.uniform(-3, 3, (n, 2, SIZE, SIZE)) * 8) / 8
        gt = still + np.array(labels, float)[:, None, None, None] * 2.0
        stills.append(still)
        ctx = node_folder(p, Node("context", None, "keyframe"))
        np.save(ctx / f"{split}.static.npy", still.astype(np.float16))
        np.save(ctx / f"{split}.deployed.npy", still.astype(np.float16))
        np.save(ctx / f"{split}.images.npy", np.zeros((n, 6, SIZE, SIZE), np.uint8))
        c = _crop_index(split, n, labels, "x") if bad_context and j == 0 else idx
        c.to_parquet(ctx / f"{split}.parquet", index=False)
        flows = {"gt": gt, "dis": gt + np.round(rng.normal(0, 1, gt.shape) * 8) / 8,
                 "farneback": gt * 0.5 + 0.25}
        for m, x in flows.items():
            rows[m].append((x, idx))
            folder = node_folder(p, Node("crops", m, "keyframe"))
            np.save(folder / f"{split}.npy", x.astype(np.float16))
            idx.to_parquet(folder / f"{split}.parquet", index=False)
    box = np.zeros((sum(len(i) for _, i in rows["gt"]), SIZE, SIZE), bool)
    for i in range(len(box)):
        box[(i, *MASKS[i % 3])] = True
    for m, wrong in {"gt": {0, 7}, "dis": {0, 7, 12, 19}, "farneback": {1, 3, 5, 8, 12, 15},
                     "fastflownet": {0}}.items():
        label = np.arange(N) % 2 == 0
        call = label.copy()
        call[sorted(wrong)] = ~call[sorted(wrong)]
        pred = pd.DataFrame({"ann_token": [f"t{i}" for i in range(N)],
                             "scene": [f"scene-{i * 8 // N}" for i in range(N)],
                             "label": label.astype(int), "prob": np.where(call, 0.9, 0.1)})
        pred.to_parquet(node_folder(p, Node("evaluate", m)) / "test.parquet", index=False)
    got = {m: (np.concatenate([x for x, _ in r]).astype(np.float16).astype(np.float32),
               pd.concat([i for _, i in r], ignore_index=True)) for m, r in rows.items()}
    still = np.concatenate(stills).astype(np.float16).astype(np.float32)
    return p, got, still, box


@pytest.fixture(scope="module")
def flows(tmp_path_factory):
    """Two folds of hand-made crops and Table 3 predictions over eight scenes."""
    return _make_flows(tmp_path_factory.mktemp("ch13_flows"), folds=2)


@pytest.mark.parametrize("folds", [2, 1])
def test_a_method_s_errors_are_its_crops_profile_against_the_exact_flow(flows, folds,
                                                                      tmp_path):
    """Every fold's test crops (``f<k>``, or the single split's ``test``) of the method
    against the exact flow's and the still-world flow, in the box each object's frame box
    covers, with each object's label and scene."""
    p, got, still, box = flows if folds == 2 else _make_flows(tmp_path, folds=1)
    t = ch.method_errors(p, "dis")
    assert t.columns.tolist() == [*PROFILE_COLUMNS, "label", "scene"]
    x, idx = got["dis"]
    assert len(t) == 3 * folds
    want = pd.DataFrame(_profile_by_hand(x, got["gt"][0], still, box))
    np.testing.assert_allclose(t[PROFILE_COLUMNS].to_numpy(float),
                               want[PROFILE_COLUMNS].to_numpy(), rtol=1e-5, atol=1e-6)
    assert t["label"].tolist() == idx["label"].tolist()
    assert t["scene"].tolist() == idx["scene"].tolist()
    assert t.index.equals(pd.RangeIndex(3 * folds)), "one table, numbered afresh"


def test_a_method_s_errors_refuse_crops_of_other_objects(tmp_path):
    """Crops whose still-world flow holds other objects are refused, naming the method and
    the split."""
    p, *_ = _make_flows(tmp_path, folds=3, bad_context=True)
    with pytest.raises(ValueError, match=r"^dis, f0: its crops, the exact flow's and the "
                                         r"still-world flow's hold other objects$"):
        ch.method_errors(p, "dis")


def _table3_f1(wrong: set[int]) -> float:
    label = np.arange(N) % 2 == 0
    call = label.copy()
    call[sorted(wrong)] = ~call[sorted(wrong)]
    return float(f1_score(label, call))


def test_profiles_are_each_built_method_s_mean_errors_and_table3_loss(flows, monkeypatch):
    """Per estimated method whose Table 3 scoring is built: its profile's means, the
    median apparent motion of still vehicles and of movers, and the exact flow's F1 minus
    its own (points) with its interval; nothing without the exact flow's scoring."""
    p, got, still, box = flows
    asked = []

    def built(q, node):
        asked.append((q, node))
        return node.method != "fastflownet"

    monkeypatch.setattr(ch.pipeline, "built", built)
    prof = ch.profiles(p)
    assert asked == [(p, Node("evaluate", m))
                     for m in ("gt", "dis", "farneback", "fastflownet")]
    assert all(q is p for q, _ in asked), "asked with the run's parameters"
    assert prof.columns.tolist() == ["method", "epe_box", "epe_ring", "scatter", "bias", "lost",
                                     "apparent, still (px)", "apparent, movers (px)",
                                     "measured", "measured_lo", "measured_hi"]
    assert prof["method"].tolist() == ["dis", "farneback"]
    for r, m in zip(prof.to_dict("records"), ("dis", "farneback"), strict=True):
        x, idx = got[m]
        t = pd.DataFrame(_profile_by_hand(x, got["gt"][0], still, box))
        for c in ("epe_box", "epe_ring", "scatter", "bias", "lost"):
            assert r[c] == pytest.approx(t[c].mean(), rel=1e-5), (m, c)
        lab = idx["label"].to_numpy()
        assert r["apparent, still (px)"] == pytest.approx(t["apparent"][lab == 0].median(),
                                                          rel=1e-5)
        assert r["apparent, movers (px)"] == pytest.approx(t["apparent"][lab == 1].median(),
                                                           rel=1e-5)
    wrong = {"dis": {0, 7, 12, 19}, "farneback": {1, 3, 5, 8, 12, 15}}
    want = [100 * (_table3_f1({0, 7}) - _table3_f1(wrong[m])) for m in ("dis", "farneback")]
    assert prof["measured"].tolist() == pytest.approx(want, rel=1e-9)
    assert (prof["measured_lo"] < prof["measured"]).all()
    assert (prof["measured"] < prof["measured_hi"]).all()
    label = (np.arange(N) % 2 == 0).astype(int)
    scenes = np.array([f"scene-{i * 8 // N}" for i in range(N)])

    def probs(wrong):
        call = label.astype(bool)
        call[sorted(wrong)] = ~call[sorted(wrong)]
        return np.where(call, 0.9, 0.1)[None, :]

    for r, m in zip(prof.to_dict("records"), ("dis", "farneback"), strict=True):
        lo, hi = metrics.paired_comparison(label, probs({0, 7}), probs(wrong[m]), scenes,
                                           seed=p.seed)["ci"]
        assert (r["measured_lo"], r["measured_hi"]) == pytest.approx((100 * lo, 100 * hi),
                                                                     rel=1e-12), m
    other = ch.profiles(p.model_copy(update={"seed": 3}))
    assert (other["measured_lo"] != prof["measured_lo"]).any()  # the run's seed draws
    monkeypatch.setattr(ch.pipeline, "built", lambda q, node: node.method != "gt")
    assert ch.profiles(p).empty
    monkeypatch.setattr(ch.pipeline, "built", lambda q, node: True)
    real = ch.results

    def shifted(q, m, name="test"):
        preds, scores = real(q, m, name)
        return (preds.iloc[1:] if m == "dis" else preds), scores

    monkeypatch.setattr(ch, "results", shifted)
    with pytest.raises(ValueError, match=r"^gt and dis were scored on different objects$"):
        ch.profiles(p)


def test_the_profile_view_shows_losses_with_intervals_and_both_prices():
    """The profiles' columns renamed in px, the Table 3 loss with its interval as text,
    each method's two predicted losses beside it; no profile, nothing."""
    prof = pd.DataFrame({"method": ["dis", "farneback"], "epe_box": [1.0, 2.0],
                         "epe_ring": [0.5, 0.25], "scatter": [0.75, 1.5], "bias": [0.1, 0.2],
                         "lost": [0.0, 0.3], "apparent, still (px)": [0.2, 0.4],
                         "apparent, movers (px)": [1.2, 0.9], "measured": [1.26, -0.04],
                         "measured_lo": [-0.55, -2.0], "measured_hi": [3.0, 1.96]})
    pred = pd.DataFrame({"by end-point error": [2.0, 4.0], "by profile": [1.5, np.nan]})
    got = ch.profile_view(prof, pred)
    assert got.columns.tolist() == ["method", "EPE box (px)", "EPE ring (px)", "scatter (px)",
                                    "bias (px)", "against motion (px)", "apparent, still (px)",
                                    "apparent, movers (px)", "Table 3 loss (points)",
                                    "priced as noise (points)", "priced by profile (points)"]
    assert got["Table 3 loss (points)"].tolist() == ["1.3 (-0.6 to 3.0)", "-0.0 (-2.0 to 2.0)"]
    assert got["priced as noise (points)"].tolist() == [2.0, 4.0]
    assert got["priced by profile (points)"].tolist()[0] == 1.5
    assert got["EPE box (px)"].tolist() == [1.0, 2.0]
    assert got["against motion (px)"].tolist() == [0.0, 0.3]
    assert ch.profile_view(prof.iloc[:0], pred).empty


def test_prediction_words_count_the_pairs_each_predictor_orders_as_table3():
    """For each of the three predictors, how many of the methods' pairs it orders as the
    measured losses; fewer than two methods, nothing to order."""
    pred = pd.DataFrame({"measured": [1.0, 3.0, 2.0], "by profile": [10.0, 30.0, 20.0]})
    prof = pd.DataFrame({"epe_box": [2.0, 1.0, 3.0], "apparent, still (px)": [1.0, 3.0, 5.0]})
    assert ch.prediction_words(pred, prof) == (
        "their box end-point error orders 1 of 3 pairs of methods as Table 3 does; the "
        "experiment's price of their profile orders 3 of 3 pairs of methods as Table 3 does; "
        "the apparent motion they give still vehicles orders 2 of 3 pairs of methods as "
        "Table 3 does (with 3 methods, a weak test: read it as a pointer, not a finding)")
    assert ch.prediction_words(pred.iloc[:1], prof.iloc[:1]) == (
        "fewer than two estimated flow methods were built, so nothing can be ordered")
    two = ch.prediction_words(pred.iloc[:2], prof.iloc[:2])
    assert two.startswith("their box end-point error orders 0 of 1 pairs")
    assert ch._pairs_agree(np.array([1.0, 1.0]), np.array([1.0, 2.0])) == (0, 1)  # a tie
    with np.errstate(divide="ignore", invalid="ignore"):
        assert ch._pairs_agree(np.array([2.0, 1.0]), np.array([1.0, 1.0])) == (0, 1)  # in y


def test_predictions_without_profiles_or_costs():
    """No profile: an empty table with the four columns; no cost: every price NaN."""
    empty = ch.predictions(pd.DataFrame(), pd.DataFrame())
    assert empty.empty and empty.columns.tolist() == ["method", "measured",
                                                       "by end-point error", "by profile"]
    prof = pd.DataFrame({"method": ["a"], "epe_box": [1.0], "epe_ring": [1.0],
                         "scatter": [0.5], "bias": [0.2], "lost": [0.1], "measured": [1.0],
                         "measured_lo": [0.0], "measured_hi": [2.0]})
    pred = ch.predictions(prof, pd.DataFrame(columns=["kind", "F1 points lost per px"]))
    assert pred.columns.tolist() == ["method", "measured", "measured_lo", "measured_hi",
                                     "by end-point error", "by profile"]
    assert pred[["by end-point error", "by profile"]].isna().all().all()
    none = ch.predictions(prof, pd.DataFrame())  # what costs() returns without arms
    assert none[["by end-point error", "by profile"]].isna().all().all()


def test_the_slope_through_the_origin_is_computed_in_float64():
    """float32 errors and losses (a parquet column's) are read as float64: the slope and its
    replicates' interval equal the float64 computation to 1e-12."""
    err = np.array([0.1, 0.7, 1.3], np.float32)
    loss = np.array([0.3, 2.2, 3.9], np.float32)
    reps = np.array([[0.2, 0.4], [2.0, 2.5], [3.7, 4.1]], np.float32)
    e, l2, r = (a.astype(np.float64) for a in (err, loss, reps))
    slope = e @ l2 / (e @ e)
    draws = e @ r / (e @ e)
    got = ch.slope_through_origin(err, loss, reps)
    assert got[0] == pytest.approx(slope, rel=1e-12, abs=0)
    assert got[1:] == pytest.approx(tuple(np.quantile(draws, [0.025, 0.975])), rel=1e-12, abs=0)


# --- the answer in words -------------------------------------------------------------------------


def _cost(kinds, lo, hi, slope) -> pd.DataFrame:
    return pd.DataFrame({"kind": kinds, "F1 points lost per px": slope,
                         "95% CI": [f"{a:.1f} to {b:.1f}" for a, b in zip(lo, hi, strict=True)],
                         "ci_lo": lo, "ci_hi": hi})


def test_the_answer_in_full_when_one_motion_kind_costs():
    """The whole sentence when only the pull costs measurably (its interval above 0) and
    the others' intervals hold 0 (an interval touching 0 from above is not above it)."""
    cost = _cost(["pull", "scale", "noise"], [2.5, 0.0, -1.25], [9.0, 3.0, 0.5],
                 [5.0, 1.5, -0.25])
    assert ch.answer(cost) == (
        "Per pixel of end-point error, only movers' motion pulled toward the still world "
        "(5.0, 2.5 to 9.0) costs the classifier measurably (F1 points per px, 95 % interval)"
        "; the other 2 kinds (a global scale error, white noise in the box) cost nothing "
        "these scenes resolve, every interval contains 0 (from -1.2 to 3.0). What decides is "
        "whether the error erases a vehicle's own motion, not its size: a more accurate flow "
        "(the paper's RAFT) can make the weaker classifier when its little error falls on "
        "the vehicles' own motion. This is what this world shows, not a measurement on real "
        "nuScenes")


def test_the_answer_when_every_kind_costs_or_none_does():
    """Two kinds that both cost: no 'other kinds' clause, and the kind decides; none that
    costs: the span of every interval; two kinds are enough to compare."""
    both = ch.answer(_cost(["resolution", "outliers"], [0.5, 1.0], [2.0, 4.0], [1.0, 2.5]))
    assert both == (
        "Per pixel of end-point error, only lost resolution (cell means) (1.0, 0.5 to 2.0); "
        "sparse large outliers (2.5, 1.0 to 4.0) costs the classifier measurably (F1 points "
        "per px, 95 % interval). What decides is its kind, not its size: a more accurate "
        "flow (the paper's RAFT) can make the weaker classifier when its little error falls "
        "on the vehicles' own motion. This is what this world shows, not a measurement on "
        "real nuScenes")
    none = ch.answer(_cost(["pull", "ring"], [-0.5, -3.0], [2.0, 0.75], [1.0, -1.0]))
    assert none == (
        "No kind of error costs the classifier measurably at these errors (F1 points per px, "
        "every 95 % interval between -3.0 and 2.0): in this world the end-point error, "
        "whatever its kind, does not decide the classifier")
    assert ch.answer(_cost(["pull"], [1.0], [2.0], [1.5])) == (
        "Too few kinds of error were built to compare their costs")


def test_the_constants_the_chapter_reads():
    """The motion below which nothing is lost and every kind's words, as the book shows
    them."""
    assert ch.MIN_MOTION == 0.25
    assert ch.KIND_WORDS == {**WORDS, "resolution": "lost resolution (cell means)",
                             "scale": "a global scale error",
                             "outliers": "sparse large outliers"}
    assert ch.COMPONENTS == {"scatter": "noise", "lost": "pull", "bias": "scale",
                             "epe_ring": "ring"}
    assert ch.MOTION_KINDS == {"pull"}


# --- the fine-tune's record (benchmarks/finetune.json) ------------------------------------------


def _finetune_record(adopt: bool, vs_control: tuple[float, float, float]) -> dict:
    diff = {"mean": 0.06, "lo": 0.041, "hi": 0.078}
    mean, lo, hi = vs_control
    means = {k: {"bias_boxes": b, "epe_boxes": e, "epe": 18.0}
             for k, b, e in (("shipped", 0.8, 1.4), ("control", 0.7, 1.3), ("box_mean", 0.6, 1.5))}
    return {"recipes": {"box_mean": {"steps": 800, "box_mean_weight": 4.0}},
            "validation": {"means": means, "pair_scenes": ["a", "b", "a", "c"]},
            "decision": {"adopt": adopt, "differences": {
                "bias_vs_control": {"mean": mean, "lo": lo, "hi": hi},
                "epe_boxes_vs_shipped": diff}}}


def test_the_finetune_words_give_the_outcome_the_two_differences_and_their_reading():
    assert ch.finetune_words(None).startswith("No fine-tune is recorded yet (`make flownet-")
    held = ch.finetune_words(_finetune_record(False, (0.004, -0.048, 0.063)))
    assert "(800 steps, the term weighted 4) was not adopted (the shipped weights" in held
    assert "mean box bias by +0.004 px (-0.048 to +0.063)" in held
    assert "box end-point error by +0.060 px (+0.041 to +0.078)" in held
    assert "over the 3 validation scenes" in held
    assert held.endswith("did not lower the bias this chapter prices beyond what the same "
                         "training does without it")
    won = ch.finetune_words(_finetune_record(True, (-0.1, -0.2, -0.01)))
    assert " was adopted: against" in won and won.endswith("beyond what the same training "
                                                           "does without it")
    assert "lowered the bias" in won
    worse = ch.finetune_words(_finetune_record(False, (0.1, 0.01, 0.2)))
    assert worse.endswith("The term raised the bias against the same training without it")


def test_the_finetune_table_lists_each_weights_scores_in_order():
    t = ch.finetune_table(_finetune_record(False, (0.0, -1.0, 1.0)))
    assert t["weights"].tolist() == list(ch.FINETUNE_ARMS.values())
    assert t["box bias (px)"].tolist() == [0.8, 0.7, 0.6]
    assert t["box EPE (px)"].tolist() == [1.4, 1.3, 1.5] and (t["EPE (px)"] == 18.0).all()


def test_the_committed_finetune_record_is_chapter_13_s_input():
    from flowmod import runner
    from flowmod.flow.finetune import FINETUNE_RECORD

    assert runner.RECORDS["13"] == (FINETUNE_RECORD,)
    record = ch.finetune_record()
    assert record is not None and set(record["validation"]["means"]) == set(ch.FINETUNE_ARMS)
