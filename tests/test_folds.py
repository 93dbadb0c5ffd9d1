"""Cross-validation over scenes (``folds``): the assignment, the roles of each fold's model,
reading a fold's rows, and scores pooled over folds. No world needed."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from flowmod import crops, evaluate, metrics
from flowmod.params import load_profile, validate
from flowmod.select import SelectionError, assign_folds, fold_roles, with_folds

SCENES = [f"s{i:02d}" for i in range(40)]


def test_every_scene_is_in_one_fold_and_folds_are_balanced():
    a = assign_folds(SCENES, 3, 0.176, seed=0)
    assert sorted(a) == SCENES
    sizes = np.bincount([k for k, _ in a.values()])
    assert sizes.tolist() == [14, 13, 13]
    # validation scenes: about val_share of each fold, at least one
    val = np.bincount([k for k, v in a.values() if v], minlength=3)
    assert val.tolist() == [2, 2, 2]
    assert a == assign_folds(SCENES, 3, 0.176, seed=0)
    assert a != assign_folds(SCENES, 3, 0.176, seed=1)


def test_groups_stay_together_and_sweep_scenes_are_spread():
    groups = {s: f"log{int(s[1:]) // 4}" for s in SCENES}  # 10 logs of 4 scenes
    a = assign_folds(SCENES, 3, 0.2, seed=3, groups=groups)
    for g in set(groups.values()):
        members = [s for s in SCENES if groups[s] == g]
        assert len({a[s] for s in members}) == 1, g  # fold and val flag shared by the log
    sweeps = ["s01", "s05", "s09", "s13", "s17", "s21"]  # six logs with sweeps
    b = assign_folds(SCENES, 3, 0.2, seed=3, spread=sweeps)
    assert sorted(np.bincount([b[s][0] for s in sweeps]).tolist()) == [2, 2, 2]
    with pytest.raises(SelectionError, match="folds=5 but the kept scenes form only 4"):
        assign_folds(SCENES[:4], 5, 0.2, seed=0)


def test_folds_of_one_and_two_groups_and_a_share_under_one_scene():
    """As many groups as folds is allowed (one scene per fold, no validation scene there);
    a fold of two groups gets one validation group; a share that rounds below one still
    gives one."""
    one = assign_folds(SCENES[:3], 3, 0.2, seed=0)
    assert sorted(k for k, _ in one.values()) == [0, 1, 2]
    assert not any(v for _, v in one.values())
    two = assign_folds(SCENES[:6], 3, 0.2, seed=0)
    assert np.bincount([k for k, v in two.values() if v], minlength=3).tolist() == [1, 1, 1]
    three = assign_folds(SCENES[:9], 3, 0.25, seed=0)  # 0.25 * 3 groups rounds to 1
    assert np.bincount([k for k, v in three.values() if v], minlength=3).tolist() == [1, 1, 1]
    with pytest.raises(SelectionError, match=r"form only 2 independent group\(s\): use fewer "
                       r"folds or more scenes$"):
        assign_folds(SCENES[:2], 3, 0.2, seed=0)


def _objects() -> pd.DataFrame:
    a = assign_folds(SCENES[:9], 3, 0.25, seed=0)
    scenes = pd.DataFrame({"scene": list(a), "fold": [k for k, _ in a.values()],
                           "val_scene": [v for _, v in a.values()]})
    obj = pd.DataFrame({"scene": np.repeat(SCENES[:9], 2), "label": [0, 1] * 9})
    return with_folds(obj, scenes).assign(split=lambda d: "f" + d["fold"].astype(str))


def test_rows_get_their_scene_s_fold_as_int_and_val_flag_as_bool():
    scenes = pd.DataFrame({"scene": ["a", "b"], "fold": [1.0, 0.0], "val_scene": [1, 0]})
    out = with_folds(pd.DataFrame({"scene": ["b", "a", "a"]}), scenes)
    assert out["fold"].tolist() == [0, 1, 1] and out["fold"].dtype == int
    assert out["val_scene"].tolist() == [False, True, True] and out["val_scene"].dtype == bool


def test_fold_roles_test_its_own_fold_and_train_on_the_others():
    obj = _objects()
    seen_test = []
    for k in range(3):
        r = fold_roles(obj, k, 3)
        assert (r[obj["fold"] == k] == "test").all()
        other = obj["fold"] != k
        assert set(r[other]) == {"train", "val"}
        assert (r[other & obj["val_scene"]] == "val").all()
        seen_test += list(obj.loc[r == "test", "scene"])
    assert sorted(seen_test) == sorted(obj["scene"])  # every scene tested exactly once
    one = obj.assign(split=["train", "val", "test"] * 6)
    assert (fold_roles(one, 0, 1) == one["split"].to_numpy()).all()


def test_gather_fold_reads_the_rows_of_each_role(tmp_path):
    obj = _objects()
    stored = {f"f{k}": obj[obj["fold"] == k].reset_index(drop=True) for k in range(3)}

    def read(split):
        df = stored[split]
        return [np.arange(len(df))[:, None] + 100 * int(split[1]), None], df

    for k in range(3):
        seen = {}
        for role in ("train", "val", "test"):
            (x, none), df = crops.gather_fold(read, 3, k, role)
            assert none is None and len(x) == len(df)
            assert (fold_roles(df, k, 3) == role).all()
            seen[role] = set(df["scene"])
        assert seen["test"] == set(obj.loc[obj["fold"] == k, "scene"])
        assert not (seen["train"] & seen["val"]) and not (seen["train"] & seen["test"])
        assert seen["train"] | seen["val"] | seen["test"] == set(obj["scene"])
    # every row scored once, by its fold
    (x,), df = evaluate.scored_rows(lambda s: (read(s)[0][:1], stored[s]), 3)
    assert sorted(df["scene"]) == sorted(obj["scene"]) and len(x) == len(obj)


def test_scores_pool_the_folds_and_show_their_range():
    y = np.array([1, 1, 0, 0, 1, 0, 1, 0])
    p = np.array([0.9, 0.2, 0.1, 0.1, 0.9, 0.8, 0.9, 0.1])
    fold = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    s = metrics.seed_summary(y, p, np.arange(8) // 2, folds=fold)
    assert s["unit"] == "fold" and s["seeds"] == 2
    assert s["f1"] == pytest.approx(metrics.metrics(y, p)["f1"])  # pooled, not the mean
    f0, f1 = metrics.metrics(y[:4], p[:4])["f1"], metrics.metrics(y[4:], p[4:])["f1"]
    assert (s["f1_min"], s["f1_max"]) == (pytest.approx(min(f0, f1)), pytest.approx(max(f0, f1)))
    t = metrics.table3({"x": s})
    assert "fold range (%)" in t and t.loc[0, "folds"] == 2
    c = metrics.paired_comparison(y, p, np.full(8, 0.9), np.arange(8) // 2, folds=fold)
    assert c["unit"] == "fold" and len(c["per_seed"]) == 2
    assert c["per_seed"][0] == pytest.approx(f0 - metrics.metrics(y[:4], np.full(4, .9))["f1"])
    assert "per fold (points)" in metrics.comparison_table({"a - b": c})


def test_a_predictions_table_of_folds_is_scored_by_fold():
    df = pd.DataFrame({"label": [1, 0, 1, 0], "prob": [0.9, 0.1, 0.2, 0.1],
                       "fold": [0, 0, 1, 1], "scene": ["a", "a", "b", "b"],
                       "ann_token": list("wxyz")})
    s = evaluate.score(df)
    assert s["unit"] == "fold" and s["f1_min"] == 0.0 and s["f1_max"] == 1.0
    assert evaluate.fold_of(df.assign(prob_s0=0.5)) is not None  # seeds per fold: still folds
    assert evaluate.fold_of(df[df["fold"] == 1]) is None  # one fold's rows: one set of models
    r = evaluate.original_protocol(df, [np.array([[0.9, 0.1]]), np.array([[0.9, 0.1]])], 2)
    assert r["models"] == "folds" and r["per_seed_clean"] == [1.0, 0.0]
    assert r["per_seed_original"] == [1.0, 1.0]  # each fold's epochs on its own rows


def test_seeds_per_fold_are_scored_per_seed_and_pooled_over_folds():
    df = pd.DataFrame({"label": [1, 0, 1, 0], "fold": [0, 0, 1, 1],
                       "prob_s0": [0.9, 0.1, 0.2, 0.1], "prob_s1": [0.9, 0.9, 0.9, 0.1],
                       "scene": ["a", "a", "b", "b"], "ann_token": list("wxyz")})
    df = df.assign(prob=df["prob_s0"])
    s = evaluate.score(df)
    f_s0 = metrics.metrics(df["label"], df["prob_s0"])["f1"]
    f_s1 = metrics.metrics(df["label"], df["prob_s1"])["f1"]
    assert s["training_seeds"] == 2 and s["unit"] == "fold" and s["seeds"] == 2
    assert s["f1"] == pytest.approx((f_s0 + f_s1) / 2)
    assert s["seed_sd"] == pytest.approx(abs(f_s0 - f_s1) / np.sqrt(2))
    # fold 1: seed 0 F1 0, seed 1 F1 1 -> its range entry is their mean
    assert s["f1_min"] == pytest.approx(0.5 * (0.0 + 1.0))
    parts = ["f0s0", "f0s1", "f1s0", "f1s1"]
    ep = [np.array([[0.9, 0.1]])] * 4
    r = evaluate.original_protocol(df, ep, 2, parts=parts)
    assert r["per_seed_clean"] == [1.0, pytest.approx(2 / 3), 0.0, 1.0]


def test_the_training_parts_of_seeds_and_folds():
    from flowmod.train import part_index, part_seed, part_seed_offset, seed_parts

    p = load_profile("demo")
    assert seed_parts(p.model_copy(update={"seeds": 2, "folds": 2})) == [
        "f0s0", "f0s1", "f1s0", "f1s1"]
    assert seed_parts(p.model_copy(update={"seeds": 1, "folds": 3})) == ["f0", "f1", "f2"]
    assert seed_parts(p.model_copy(update={"seeds": 2, "folds": 1})) == ["s0", "s1"]
    assert [part_index(x) for x in ("f2s1", "dis/f1", "s3", "residual/f0s2")] == [2, 1, 3, 0]
    assert [part_seed(x) for x in ("f2s1", "f1", "s3", "residual/f0s2")] == [1, 0, 3, 2]
    offsets = [part_seed_offset(x) for x in seed_parts(p.model_copy(update={"seeds": 3}))]
    assert offsets[:4] == [0, 100, 200, 1] and len(set(offsets)) == len(offsets)
    assert [part_seed_offset(x) for x in ("s3", "f2", "f2s1", "raw/s1")] == [3, 2, 102, 1]
    with pytest.raises(ValueError, match="not a training part"):
        part_index("keyframe")



def test_folds_and_seeds_combine():
    demo = load_profile("demo")
    assert demo.folds == 3 and demo.seeds == 3
    assert load_profile("paper", dataroot="/x").folds == 1
    assert validate({"folds": 3, "seeds": 2}).seeds == 2
    assert validate({"folds": 1, "seeds": 3}).seeds == 3
