"""Chapter 06's backend (flowmod.chapters.ch06_training), quick tests for mutation testing.

mutmut runs only the quick tests, and chapter 06 was otherwise tested only by the slow
notebook runs: every function here is run on tiny hand-made inputs (training histories
published by hand in a demo-profile run folder, hand-made ablation records) and on the
committed records, and its output compared whole (column names, row order, words, numbers)
with what is computed here by hand or with pandas. tests/test_tables.py and
tests/test_chapter_numbers.py check the committed records' consistency and the "decided"
verdicts; this file complements them. No world, no training: about a second.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from flowmod import pipeline
from flowmod.artefacts import write_manifest
from flowmod.chapters import ch06_training as ch06
from flowmod.chapters import common
from flowmod.dag import Node
from flowmod.params import load_profile
from flowmod.paths import repo_root

# --- the published training histories -------------------------------------------------------


def _publish_history(p, method: str, part: str, losses: list[float], best_epoch: int,
                     best_f1: float, seed: int) -> pd.DataFrame:
    """A train node's published history.csv and manifest, written by hand."""
    folder = pipeline.GRAPH.node_dir(p, Node("train", method, part))
    folder.mkdir(parents=True)
    n = len(losses)
    df = pd.DataFrame({"epoch": np.arange(1, n + 1), "train_loss": losses,
                       "val_loss": [x + 0.1 for x in losses],
                       "val_f1": np.linspace(0.5, 0.9, n), "val_precision": 0.7,
                       "val_recall": 0.6, "lr": 0.01, "seconds": np.arange(1, n + 1) * 2.5})
    df.to_csv(folder / "history.csv", index=False)
    write_manifest(folder / "manifest.json", {"fingerprint": f"hand-made {method}/{part}",
                                              "best_epoch": best_epoch, "best_f1": best_f1,
                                              "seed": seed})
    return df


@pytest.fixture
def trained(tmp_path):
    """A demo profile of two flow methods, one fold, two seeds, whose four train nodes are
    published by hand: ``(params, {(method, part): (history, best_epoch, best_f1, seed)})``."""
    p = load_profile("demo", run_dir=str(tmp_path / "runs"), flow_methods=["gt", "dis"],
                     folds=1, seeds=2)
    made = {}
    for i, (m, part) in enumerate([("gt", "s0"), ("gt", "s1"), ("dis", "s0"), ("dis", "s1")]):
        losses = [0.9 - 0.1 * i, 0.5 - 0.05 * i, 0.31 + 0.01 * i]
        made[(m, part)] = (_publish_history(p, m, part, losses, 2 + i % 2, 0.8 + 0.02 * i,
                                            100 + i), 2 + i % 2, 0.8 + 0.02 * i, 100 + i)
    return p, made


def test_history_reads_the_published_csv_and_the_manifests_choice(trained):
    """history(): the node's history.csv as written, with the manifest's best epoch, best
    validation F1 and seed in ``attrs``; the default part is seed 0's (``s0``)."""
    p, made = trained
    for (m, part), (df, epoch, f1, seed) in made.items():
        got = ch06.history(p, m, part)
        pd.testing.assert_frame_equal(got, df, check_dtype=False)
        assert got.attrs == {"best_epoch": epoch, "best_f1": f1, "seed": seed}
    default = ch06.history(p, "dis")
    assert default.attrs["seed"] == made[("dis", "s0")][3]
    assert default["train_loss"].tolist() == made[("dis", "s0")][0]["train_loss"].tolist()


def test_history_of_a_manifest_without_choice_has_empty_attrs(tmp_path):
    """A published node whose manifest records no choice: the attrs are there, all None."""
    p = load_profile("demo", run_dir=str(tmp_path / "runs"))
    folder = pipeline.GRAPH.node_dir(p, Node("train", "gt", "s0"))
    folder.mkdir(parents=True)
    pd.DataFrame({"epoch": [1], "train_loss": [0.5]}).to_csv(folder / "history.csv",
                                                             index=False)
    write_manifest(folder / "manifest.json", {"fingerprint": "x"})
    got = ch06.history(p, "gt")
    assert got.attrs == {"best_epoch": None, "best_f1": None, "seed": None}
    assert got["train_loss"].tolist() == [0.5]


def test_histories_are_per_method_in_profile_order_and_per_seed(trained):
    """histories(): one list per flow method of the profile (its order), one history per
    training seed part in order (s0, s1)."""
    p, made = trained
    got = ch06.histories(p)
    assert list(got) == ["gt", "dis"]
    for m, hs in got.items():
        assert [h.attrs["seed"] for h in hs] == [made[(m, k)][3] for k in ("s0", "s1")]
        assert [h["train_loss"].iloc[0] for h in hs] == [made[(m, k)][0]["train_loss"].iloc[0]
                                                        for k in ("s0", "s1")]


# --- Table 2 and the per-model summary -------------------------------------------------------


def _table2_rows(p, models: str) -> list[tuple]:
    return [("Optimizer", "Batch size", p.batch_size), ("Optimizer", "Algorithm", "SGD"),
            ("Optimizer", "Learning rate", p.lr), ("Optimizer", "Weight decay", p.weight_decay),
            ("Optimizer", "Momentum", p.momentum),
            ("Scheduler", "Schedule", "StepLR (per epoch)"),
            ("Scheduler", "Step size", p.step_size), ("Scheduler", "Gamma", p.gamma),
            ("Training", "Epochs", p.epochs), ("Training", "Horizontal flip p", p.hflip_p),
            ("Training", "Models per flow method", models),
            ("Training", "Mixed precision", p.amp), ("Input", "Crop size (px)", p.crop_size),
            ("Input", "Flow channels scaled", p.input_scaling),
            ("Network", "ResNet18 first-stage channels", p.model_width)]


@pytest.mark.parametrize(("folds", "seeds", "models"), [
    (3, 3, "9 (3 folds x 3 seeds)"), (2, 3, "6 (2 folds x 3 seeds)"), (1, 2, "2 (seeds)")])
def test_table2_is_the_profiles_settings_row_by_row(folds, seeds, models):
    """Table 2: every row's function, hyperparameter and setting, in order; the models per
    flow method are folds x seeds with cross-validation (2 folds included), else the seeds."""
    p = load_profile("demo", folds=folds, seeds=seeds)
    got = ch06.table2(p)
    assert list(got.columns) == ["Function", "Hyperparameter", "Setting"]
    assert [tuple(r) for r in got.itertuples(index=False)] == _table2_rows(p, models)


def _h(best_epoch, best_f1, seed, losses, seconds) -> pd.DataFrame:
    df = pd.DataFrame({"train_loss": losses, "seconds": seconds})
    df.attrs.update(best_epoch=best_epoch, best_f1=best_f1, seed=seed)
    return df


def test_mean_val_f1_is_the_mean_chosen_f1_in_percent_to_one_decimal():
    """mean_val_f1(): 100 x the mean of the models' best validation F1, rounded to 0.1."""
    hs = [_h(1, 0.8123, 0, [0.1], [1.0]), _h(2, 0.9, 1, [0.1], [1.0])]
    assert ch06.mean_val_f1(hs) == 85.6  # 85.615
    assert ch06.mean_val_f1(hs[:1]) == 81.2


def test_summary_has_one_row_per_model_with_its_choice_loss_and_time():
    """summary(): per method and seed, the chosen epoch, its validation F1 (%, 0.1), the
    last epoch's training loss (0.0001) and the total seconds (0.1), in input order."""
    hs = {"gt": [_h(3, 0.81234, 7, [0.9, 0.55555, 0.123456], [1.25, 2.5, 3.33]),
                 _h(1, 0.6, 8, [0.7, 0.654321], [4.0, 4.06])],
          "dis": [_h(2, 0.77777, 9, [0.5, 0.2, 0.3333333], [10.0, 0.01, 0.02])]}
    got = ch06.summary(hs)
    want = pd.DataFrame({"method": ["gt", "gt", "dis"], "seed": [7, 8, 9],
                         "chosen epoch": [3, 1, 2], "val F1 (%)": [81.2, 60.0, 77.8],
                         "last train loss": [0.1235, 0.6543, 0.3333],
                         "training (s)": [7.1, 8.1, 10.0]})
    pd.testing.assert_frame_equal(got, want)


# --- the input scaling's ablation -------------------------------------------------------------


def test_ablation_record_is_the_committed_json():
    """ablation_record(): benchmarks/ablation.json as committed, parsed."""
    want = json.loads((repo_root() / "benchmarks" / "ablation.json").read_text())
    assert ch06.ablation_record() == want


#: (method, fold, mode) -> validation F1 of two seeds: methods and modes not in
#: alphabetical order (the table keeps the record's order), means with a second decimal.
ABLATION = {("gt", 1, "raw"): (0.8, 0.9), ("gt", 1, "log"): (0.9, 0.95),
            ("gt", 0, "raw"): (0.7, 0.71), ("gt", 0, "log"): (0.6, 0.8),
            ("dis", 1, "raw"): (0.5, 0.5), ("dis", 1, "log"): (0.8, 0.83),
            ("dis", 0, "raw"): (0.4, 0.6), ("dis", 0, "log"): (0.75, 0.75)}


def _record(rows=None, choice="log") -> dict:
    if rows is None:
        rows = [{"method": m, "fold": f, "mode": mode, "seed": s, "val_f1": v, "epoch": 3}
                for (m, f, mode), vs in ABLATION.items() for s, v in enumerate(vs)]
    return {"rows": rows, "rule": "highest mean", "choice": choice, "date": "2026-12-04",
            "commit": "abc1234"}


def test_ablation_table_is_per_fold_then_per_method_then_overall():
    """ablation_table(): rows per (method, fold) in the record's order, then each method's
    mean, then the mean over every row; columns the modes in the record's order; values
    100 x validation F1, rounded to 0.1."""
    got = ch06.ablation_table(_record())
    assert list(got.columns) == ["method", "fold", "raw", "log"]
    assert got.columns.name == "mode"
    keys = list(dict.fromkeys((m, f) for m, f, _ in ABLATION))
    assert [tuple(r) for r in got[["method", "fold"]].itertuples(index=False)] == [
        (m, str(f)) for m, f in keys] + [("gt", "mean"), ("dis", "mean"),
                                         ("every method", "mean")]
    for mode in ("raw", "log"):
        per_fold = [100 * np.mean(ABLATION[(m, f, mode)]) for m, f in keys]
        per_method = [100 * np.mean([v for (m2, _, md), vs in ABLATION.items()
                                     if m2 == m and md == mode for v in vs])
                      for m in ("gt", "dis")]
        overall = 100 * np.mean([v for (_, _, md), vs in ABLATION.items() if md == mode
                                 for v in vs])
        want = [round(x, 1) for x in per_fold + per_method + [overall]]
        assert got[mode].tolist() == pytest.approx(want, abs=1e-9), mode
    # a mean that a second decimal would change (dis, log: 78.25)
    assert got.loc[5, "log"] in (78.2, 78.3)


def test_ablation_words_say_the_choice_its_means_and_the_record():
    """ablation_words(): the rule, the choice, the best and the raw mode's mean validation
    F1, the folds, seeds and methods (record order) and the record's date and commit; a
    profile that trains with the choice adds nothing, another one says so."""
    rec = _record()
    raw = 100 * np.mean([v for (_, _, md), vs in ABLATION.items() if md == "raw" for v in vs])
    log = 100 * np.mean([v for (_, _, md), vs in ABLATION.items() if md == "log" for v in vs])
    base = (f"The rule (highest mean) chose **log**: mean validation F1 {log:.1f} % against "
            f"{raw:.1f} % for the raw flow, over 2 folds x 2 seeds of gt, dis (run of "
            "2026-12-04, commit abc1234; no test row read).")
    assert base == ("The rule (highest mean) chose **log**: mean validation F1 79.8 % against "
                    "63.9 % for the raw flow, over 2 folds x 2 seeds of gt, dis (run of "
                    "2026-12-04, commit abc1234; no test row read).")
    assert ch06.ablation_words(rec, load_profile("demo")) == base
    other = load_profile("demo", input_scaling="raw", raw_input_methods=[])
    assert ch06.ablation_words(rec, other) == base + (
        " This run's profile trains with **raw** instead (its own choice, not this "
        "record's).")


def test_ablation_words_without_a_raw_mode_say_nan():
    """A record without the raw mode: the raw flow's mean is not a number (nan), not an
    error; the best mode is the highest mean (here 'log', though the record chose 'clip')."""
    rows = [{"method": "dis", "fold": 0, "mode": mode, "seed": s, "val_f1": v + s / 10}
            for mode, v in (("clip", 0.5), ("log", 0.7)) for s in (0, 1)]
    words = ch06.ablation_words(_record(rows, choice="clip"), load_profile("demo"))
    assert words.startswith("The rule (highest mean) chose **clip**: mean validation F1 "
                            "75.0 % against nan % for the raw flow, over 1 fold x 2 seeds "
                            "of dis (run of")


# --- the ablation's other steps -----------------------------------------------------------------


def test_steps_record_is_the_committed_json_or_none(monkeypatch, tmp_path):
    """steps_record(): benchmarks/ablation_steps.json parsed, or None where the repository
    has none (the repository root pointed at an empty folder)."""
    path = repo_root() / "benchmarks" / "ablation_steps.json"
    if not path.is_file():
        pytest.skip("no ablation_steps.json committed")
    assert ch06.steps_record() == json.loads(path.read_text())
    monkeypatch.setattr(common, "repo_root", lambda: tmp_path)  # where records are read
    assert ch06.steps_record() is None
    (tmp_path / "benchmarks").mkdir()
    (tmp_path / "benchmarks" / "ablation_steps.json").write_text('{"effects": []}')
    assert ch06.steps_record() == {"effects": []}


def _effect(step, variant, against, units, recipe, variant_f1, low, high, seconds):
    return {"step": step, "variant": variant, "scored against": against, "units": units,
            "recipe (%)": recipe, "variant (%)": variant_f1,
            "effect (points)": round(variant_f1 - recipe, 2), "low": low, "high": high,
            "seconds a model": seconds}


#: Three steps, two of them against the annotated labels, with second decimals to round.
EFFECTS = [_effect("epochs", "16", "annotated", 3, 85.76, 86.68, -1.26, 3.14, 48.04),
           _effect("epochs", "16", "true", 3, 85.23, 86.33, 0.26, 4.96, 48.04),
           _effect("flip", "none", "annotated", 6, 80.12, 77.0, -5.55, -0.74, 12.36)]


def test_steps_table_rounds_and_formats_each_step():
    """steps_table(): the record's effects in order with their interval in words (signed,
    0.1), "decided" where the interval excludes 0, in the book's column order, the numbers
    rounded to 0.1."""
    got = ch06.steps_table({"date": "d", "commit": "c", "effects": EFFECTS})
    want = pd.DataFrame({
        "step": ["epochs", "epochs", "flip"], "variant": ["16", "16", "none"],
        "scored against": ["annotated", "true", "annotated"], "units": [3, 3, 6],
        "recipe (%)": [85.8, 85.2, 80.1], "variant (%)": [86.7, 86.3, 77.0],
        "effect (points)": [0.9, 1.1, -3.1],
        "95% interval (points)": ["-1.3 to +3.1", "+0.3 to +5.0", "-5.5 to -0.7"],
        "decided": ["no", "yes", "yes"], "seconds a model": [48.0, 48.0, 12.4]})
    pd.testing.assert_frame_equal(got, want)


def test_steps_words_are_the_annotated_steps_glued():
    """steps_words(): the sentence over the steps scored against the annotated labels only
    (the largest number of units; each step's effect, interval and verdict; joined by "; ")
    with the record's date and commit."""
    rec = {"date": "2026-12-05", "commit": "def5678", "effects": EFFECTS}
    assert ch06.steps_words(rec) == (
        "Against the recipe, on validation rows only (6 paired (method, fold, seed) units "
        "each; run of 2026-12-05, commit def5678): epochs (16): +0.9 points (-1.3 to +3.1, "
        "not decided); flip (none): -3.1 points (-5.5 to -0.7, decided).")


def test_steps_words_of_a_record_without_annotated_steps_say_so():
    """No step scored against the annotated labels: one sentence that says so (not an empty
    list of steps)."""
    rec = {"date": "2026-12-05", "commit": "def5678", "effects": EFFECTS[1:2]}
    assert ch06.steps_words(rec) == (
        "The record of 2026-12-05 (commit def5678) holds no step scored against the "
        "annotated labels.")
