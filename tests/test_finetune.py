"""The FastFlowNet fine-tune of chapter 13's answer: its arms and its decision rule."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np
import pytest

from flowmod.flow import finetune as ft
from flowmod.flow.pretrain import SCHEDULE


def test_the_arms_differ_in_the_box_mean_term_only_and_continue_the_last_phase():
    a = ft.arms()
    control, box = asdict(a["control"]), asdict(a["box_mean"])
    assert {k for k in control if control[k] != box[k]} == {"box_mean_weight"}
    assert control["box_mean_weight"] == 0.0 and box["box_mean_weight"] == ft.BOX_MEAN_WEIGHT
    last = asdict(SCHEDULE[-1])
    for k in ("scale", "min_gap", "focus_p", "box_weight", "full_res", "crop", "batch"):
        assert control[k] == last[k], k
    assert control["seed"] not in {p.seed for p in SCHEDULE}, "batches of their own"
    assert control["steps"] == ft.STEPS and not control["init_float16"]


def _rows(values: list[float], key: str) -> list[dict[str, float]]:
    return [{key: v, "epe_boxes": 1.0} for v in values]


def test_paired_differences_resample_whole_scenes():
    scenes = ["a", "a", "b", "b", "c", "c", "d", "d"]
    a = _rows([1.0, 1.2, 0.9, 1.1, 1.0, 1.0, 0.8, 1.0], "bias_boxes")
    b = _rows([1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5], "bias_boxes")
    d = ft.paired(a, b, scenes, "bias_boxes")
    assert d["mean"] == pytest.approx(-0.5)
    assert -0.65 < d["lo"] < d["mean"] < d["hi"] < -0.35
    same = ft.paired(b, b, scenes, "bias_boxes")
    assert same == {"mean": 0.0, "lo": 0.0, "hi": 0.0}
    with pytest.raises(ValueError):
        ft.paired(a, b[:-1], scenes, "bias_boxes")


def _three(box: list[float], control: list[float], shipped: list[float], epe: float = 1.0):
    rows = {"box_mean": _rows(box, "bias_boxes"), "control": _rows(control, "bias_boxes"),
            "shipped": _rows(shipped, "bias_boxes")}
    for r in rows["box_mean"]:
        r["epe_boxes"] = epe
    return rows


SCENES = [s for s in "abcdef" for _ in range(2)]


def test_adopted_only_below_both_references_and_without_a_worse_box_epe():
    rng = np.random.default_rng(0)
    noise = list(rng.normal(0, 0.02, 12))
    low = [0.5 + e for e in noise]
    assert ft.decide(_three(low, [0.8] * 12, [0.9] * 12), SCENES)["adopt"]
    # no better than the control: more training, not the term, did it
    assert not ft.decide(_three(low, low, [0.9] * 12), SCENES)["adopt"]
    # better than the control but not than the shipped weights
    assert not ft.decide(_three(low, [0.8] * 12, [0.3] * 12), SCENES)["adopt"]
    # the box end-point error rose by more than the tolerance
    worse = ft.decide(_three(low, [0.8] * 12, [0.9] * 12, epe=1.0 + 2 * ft.EPE_TOLERANCE),
                      SCENES)
    assert not worse["adopt"]
    assert worse["differences"]["epe_boxes_vs_shipped"]["lo"] == pytest.approx(
        2 * ft.EPE_TOLERANCE)
    within = ft.decide(_three(low, [0.8] * 12, [0.9] * 12, epe=1.0 + ft.EPE_TOLERANCE / 2),
                       SCENES)
    assert within["adopt"]
    d = within["differences"]
    assert d["bias_vs_control"]["mean"] == pytest.approx(np.mean(low) - 0.8)
    assert d["control_bias_vs_shipped"]["mean"] == pytest.approx(-0.1)
    assert d["control_epe_boxes_vs_shipped"] == {"mean": 0.0, "lo": 0.0, "hi": 0.0}
