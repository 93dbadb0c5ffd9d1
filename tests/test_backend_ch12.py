"""Chapter 12's backend (:mod:`flowmod.chapters.ch12_self_trained_flow`), quick tests for
mutation testing: the chapter is otherwise run only by the slow tests that execute its
notebook on a generated world, which mutmut does not run.

Every published node the backend reads (``selfflow[<mode>]``: ``history.csv``,
``eval.json``, ``weights.pt``; ``shipped``: ``world.parquet``, ``pairs.parquet``,
``example.npz``; ``select``: ``pairs.parquet``, ``objects.parquet``) is written here by
hand into a demo-profile run folder under ``tmp_path``, with numbers chosen so that a
swapped operator, a changed rounding or constant, or a row of the wrong method changes what
the backend returns. The expected tables and sentences are written out by hand; the
intervals over scenes are made degenerate (every scene has the same mean), so that their
bounds are known without a bootstrap. Quick: no world, no training.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pandas as pd
import pytest

from flowmod import metrics, pipeline
from flowmod.artefacts import write_manifest
from flowmod.chapters import ch12_self_trained_flow as ch12
from flowmod.dag import Node
from flowmod.params import load_profile
from flowmod.paths import repo_root

DIS = "dis (medium)"
SHIPPED = "fastflownet (shipped)"
SHIPPED_FILE = repo_root() / "weights" / "fastflownet_synth" / "weights.pt"


# --- hand-made published nodes ---------------------------------------------------------------

def _demo(tmp_path, **overrides):
    """The demo profile on a run folder of its own under ``tmp_path``."""
    return load_profile("demo", run_dir=str(tmp_path / "runs"), **overrides)


def _publish(p, node, files=None):
    """A published node: its folder with ``files`` ({name: str | bytes}) and a manifest."""
    folder = pipeline.node_dir(p, node)
    folder.mkdir(parents=True)
    for name, data in (files or {}).items():
        if isinstance(data, bytes):
            (folder / name).write_bytes(data)
        else:
            (folder / name).write_text(data)
    write_manifest(folder / "manifest.json", {"fingerprint": f"hand-made {node}"})
    return folder


def _m(epe, boxes, fl, fl_boxes, sec=0.5):
    """One method's metrics as ``eval.json`` holds them."""
    return {"epe": epe, "epe_boxes": boxes, "fl_all": fl, "fl_all_boxes": fl_boxes,
            "seconds_per_pair": sec}


BASELINES = {"zero flow": _m(10.4567, 5.1234, 80.4567, 90.1234, 0.00123),
             "farneback": _m(4.3219, 2.5678, 30.2345, 40.7654, 0.04567),
             DIS: _m(3.1415, 1.4142, 20.6789, 25.3456, 0.02345)}


def _selfflow(p, mode, *, net, val_net=1.0, val_dis=2.0, steps=300, hist_seconds=(1.0,),
              train_pairs=17, seconds_per_step=1.23456, baselines=None):
    """Publish ``selfflow[<mode>]``: history, evaluation record and a weights file."""
    hist = pd.DataFrame({"step": np.arange(1, len(hist_seconds) + 1) * 100,
                         "seconds": list(hist_seconds), "loss": 1.0})
    ev = {"mode": mode, "steps": steps, "seconds_per_step": seconds_per_step,
          "train_pairs": train_pairs, "train_scenes": ["scene-1"],
          "validation": {"fastflownet": _m(val_net, 0.0, 0.0, 0.0),
                         "baselines": {DIS: _m(val_dis, 0.0, 0.0, 0.0)}},
          "fastflownet": net, "baselines": baselines or BASELINES}
    folder = _publish(p, Node("selfflow", None, mode),
                      {"history.csv": hist.to_csv(index=False), "eval.json": json.dumps(ev),
                       "weights.pt": SHIPPED_FILE.read_bytes()})
    return folder, hist, ev


# --- the trained networks' nodes -------------------------------------------------------------

def test_built_lists_the_current_selfflow_nodes_in_profile_order(tmp_path, monkeypatch):
    """``built`` keeps the modes of ``selfflow_modes`` whose ``selfflow[<mode>]`` node is
    current, in the profile's order (a "built?" lookup stands in for the fingerprints)."""
    p = _demo(tmp_path)
    current = {Node("selfflow", None, "finetune"), Node("selfflow", None, "photometric")}

    def is_current(params, node):
        assert params is p or params.selfflow_modes == [], "asked with the run's parameters"
        return node in current

    monkeypatch.setattr(ch12.pipeline, "current", is_current)
    assert ch12.built(p) == ["photometric", "finetune"]
    assert ch12.built(p.model_copy(update={"selfflow_modes": []})) == []


def test_results_and_weights_path_read_the_published_node_of_the_mode(tmp_path):
    """``results`` returns the mode's own history and evaluation record; ``weights_path``
    its published ``weights.pt``."""
    p = _demo(tmp_path)
    _selfflow(p, "photometric", net=_m(9.0, 9.0, 9.0, 9.0), hist_seconds=(9.0,))
    folder, hist, ev = _selfflow(p, "supervised", net=_m(1.0, 2.0, 3.0, 4.0),
                                 hist_seconds=(2.0, 3.5))
    got_hist, got_ev = ch12.results(p, "supervised")
    pd.testing.assert_frame_equal(got_hist, hist)
    assert got_ev == ev
    assert ch12.weights_path(p, "supervised") == (
        tmp_path / "runs" / "selfflow" / "supervised" / "weights.pt")
    assert ch12.weights_path(p, "supervised").read_bytes() == SHIPPED_FILE.read_bytes()


EPE_COLUMNS = ["method", "EPE (px)", "EPE in boxes (px)", "Fl-all (%)", "Fl-all in boxes (%)",
               "s / pair"]


def test_epe_table_shows_the_first_modes_baselines_then_every_network(tmp_path):
    """One row per baseline (zero flow, Farneback, DIS: of the first mode's record only)
    then one per trained network; EPE and s / pair to 0.01, Fl-all to 0.1."""
    p = _demo(tmp_path)
    other = {k: _m(99.0, 99.0, 99.0, 99.0, 9.0) for k in BASELINES}
    _selfflow(p, "photometric", net=_m(6.7891, 3.4567, 50.6789, 60.1234, 0.31234))
    _selfflow(p, "supervised", net=_m(2.2222, 1.1111, 15.5555, 17.7777, 0.45678),
              baselines=other)
    t = ch12.epe_table(p, ["photometric", "supervised"])
    assert t.columns.tolist() == EPE_COLUMNS
    want = [["zero flow", 10.46, 5.12, 80.5, 90.1, 0.0],
            ["farneback", 4.32, 2.57, 30.2, 40.8, 0.05],
            [DIS, 3.14, 1.41, 20.7, 25.3, 0.02],
            ["fastflownet (photometric)", 6.79, 3.46, 50.7, 60.1, 0.31],
            ["fastflownet (supervised)", 2.22, 1.11, 15.6, 17.8, 0.46]]
    assert t["method"].tolist() == [r[0] for r in want]
    np.testing.assert_allclose(t[EPE_COLUMNS[1:]].to_numpy(float),
                               [r[1:] for r in want], rtol=0, atol=1e-9)
    assert ch12.epe_table(p, []).empty


def test_budget_table_counts_steps_pairs_and_minutes_per_mode(tmp_path):
    """Per mode: steps, pairs seen (steps x ``selfflow_batch``), training pairs, median
    seconds per step (0.01) and the history's seconds summed in minutes (0.1)."""
    p = _demo(tmp_path)
    assert p.selfflow_batch == 4
    _selfflow(p, "photometric", net=_m(1, 1, 1, 1), steps=300, train_pairs=17,
              seconds_per_step=1.23456, hist_seconds=(300.0, 300.0, 27.3))
    _selfflow(p, "finetune", net=_m(1, 1, 1, 1), steps=7, train_pairs=5,
              seconds_per_step=0.98765, hist_seconds=(61.0, 20.6))
    t = ch12.budget_table(p, ["photometric", "finetune"])
    assert t.columns.tolist() == ["mode", "steps", "pairs seen", "training pairs", "s / step",
                                  "training (min)"]
    assert t["mode"].tolist() == ["photometric", "finetune"]
    assert t["steps"].tolist() == [300, 7]
    assert t["pairs seen"].tolist() == [1200, 28]
    assert t["training pairs"].tolist() == [17, 5]
    assert t["s / step"].tolist() == pytest.approx([1.23, 0.99], abs=1e-9)
    assert t["training (min)"].tolist() == pytest.approx([10.5, 1.4], abs=1e-9)  # 627.3, 81.6 s


def test_beats_dis_and_table3_note_decide_on_the_validation_pairs(tmp_path):
    """A network beats DIS when its validation EPE is strictly lower than DIS's there (the
    test pairs do not count); the note names the first such mode's weights, or says none,
    or that no network is trained."""
    p = _demo(tmp_path)
    good_test = _m(0.1, 0.1, 0.1, 0.1)  # far better than DIS on the test pairs: not used
    bad_test = _m(50.0, 50.0, 50.0, 50.0)
    _selfflow(p, "photometric", net=good_test, val_net=2.0, val_dis=2.0)  # a tie
    _selfflow(p, "supervised", net=bad_test, val_net=1.5, val_dis=2.0)
    _selfflow(p, "finetune", net=bad_test, val_net=0.5, val_dis=0.75)
    modes = ["photometric", "supervised", "finetune"]
    assert ch12.beats_dis(p, modes) == ["supervised", "finetune"]
    assert ch12.beats_dis(p, ["finetune", "photometric"]) == ["finetune"]
    assert ch12.beats_dis(p, ["photometric"]) == []
    path = tmp_path / "runs" / "selfflow" / "supervised" / "weights.pt"
    assert ch12.table3_note(p, modes) == (
        "The supervised network beats DIS on the validation scenes' end-point error: it can "
        "be Table 3's `fastflownet` row with `make book SET=\"fastflownet_weights="
        f"{path}\"`.")
    assert ch12.table3_note(p, ["photometric"]) == (
        "No network trained in the book beats DIS on the validation scenes' end-point error; "
        "Table 3's `fastflownet` row stays the shipped weights'.")
    assert ch12.table3_note(p, []) == "No network is trained in the book with these parameters."


def test_headline_gives_each_networks_test_error_beside_dis_and_zero_flow(tmp_path):
    """The landing sentence: each trained network's test EPE (0.1 px) with its mode and
    steps, against DIS's and the zero flow's; else how to train them, or that the profile
    trains none."""
    p = _demo(tmp_path)
    _selfflow(p, "photometric", net=_m(7.26, 0, 0, 0), steps=300)
    _selfflow(p, "finetune", net=_m(2.04, 0, 0, 0), steps=250)
    assert ch12.headline(p, ["photometric", "finetune"]) == (
        "FastFlowNet trained from scratch on this machine reaches a test-scene end-point error "
        "of 7.3 px (photometric, 300 steps) and 2.0 px (finetune, 250 steps) against DIS's "
        "3.1 px and the zero flow's 10.5 px")
    assert ch12.headline(p, ["finetune"]) == (
        "FastFlowNet trained from scratch on this machine reaches a test-scene end-point error "
        "of 2.0 px (finetune, 250 steps) against DIS's 3.1 px and the zero flow's 10.5 px")
    assert ch12.headline(p, []) == (
        "not trained in this run (make selfflow trains FastFlowNet from scratch: 3 x 300 "
        "steps)")
    two = p.model_copy(update={"selfflow_modes": ["photometric", "finetune"],
                               "selfflow_iters": 50})
    assert ch12.headline(two, []) == (
        "not trained in this run (make selfflow trains FastFlowNet from scratch: 2 x 50 "
        "steps)")
    none = p.model_copy(update={"selfflow_modes": []})
    assert ch12.headline(none, []) == "not part of this profile (selfflow_modes is empty)"


def test_built_note_says_which_networks_are_trained_and_how_to_train_the_others(tmp_path):
    """The chapter's line: d of n networks trained, the others named with their steps and
    the gate's make target; or how to ask for them where the profile trains none."""
    p = _demo(tmp_path)
    assert ch12.built_note(p, ["supervised"]) == (
        "Networks trained with these parameters: **1 of 3** (supervised). The other 2 "
        "(photometric, finetune; 300 steps each) are trained by `make selfflow` (or this "
        "chapter with `selfflow_build=true`).")
    all3 = ["photometric", "supervised", "finetune"]
    assert ch12.built_note(p, all3) == (
        "Networks trained with these parameters: **3 of 3** (photometric, supervised, "
        "finetune).")
    assert ch12.built_note(p.model_copy(update={"selfflow_modes": []}), []) == (
        "This profile trains no flow network (`selfflow_modes` is empty). Set it (e.g. "
        "`selfflow_modes=[photometric]`) and run `make selfflow`.")


def _texture(seed, h=64, w=96):
    """A smooth random BGR image (uint8) that DIS can follow."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (h // 8, w // 8, 3)).astype(np.uint8)
    return cv2.GaussianBlur(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), (5, 5), 0)


def test_shipped_manifest_and_steps_read_the_repositorys_manifest():
    """``shipped_manifest`` is the JSON beside the shipped weights; ``shipped_steps`` its
    steps, 0 without a manifest."""
    m = ch12.shipped_manifest()
    f = repo_root() / "weights" / "fastflownet_synth" / "manifest.json"
    assert m == json.loads(f.read_text())
    assert ch12.shipped_steps(m) == m["steps"] > 0
    assert ch12.shipped_steps({"steps": 7}) == 7
    assert ch12.shipped_steps(None) == 0


def test_uses_shipped_needs_the_fastflownet_method_and_the_shipped_file(tmp_path):
    """True only where ``fastflownet`` is a flow method and ``fastflownet_weights`` names
    the shipped file (relative or absolute); not for another file, none, or no method."""
    p = _demo(tmp_path)
    assert ch12.uses_shipped(p) is True
    assert ch12.uses_shipped(p.model_copy(update={"fastflownet_weights": str(SHIPPED_FILE)}))
    assert not ch12.uses_shipped(p.model_copy(update={"flow_methods": ["gt", "dis"]}))
    assert not ch12.uses_shipped(p.model_copy(update={"fastflownet_weights": None}))
    other = str(tmp_path / "weights.pt")
    assert not ch12.uses_shipped(p.model_copy(update={"fastflownet_weights": other}))


def _phase(**kw):
    """A later phase of the schedule as the manifest records it."""
    base = {"steps": 5000, "lr": 0.0002, "gamma": 0.5, "milestones": [3000, 4000],
            "focus_p": 0.75, "focus_depth": [20.0, 80.0], "box_weight": 20.0, "max_gap": 6,
            "min_gap": 1, "init_float16": False, "full_res": False, "ema": 0.0, "scale": 0.5}
    return {**base, **kw}


def test_phase_text_says_each_option_of_a_phase_only_where_it_is_set():
    """A phase in words: steps, start, rate, focus and box weight always; the frame gaps only
    above 1, float16 start, full-resolution loss, moving average and scale only where set."""
    plain = ("5000 more steps from the previous phase's weights (a fresh Adam 0.0002, x0.5 at "
             "its steps 3000, 4000); a share 0.75 of the windows holds the box of an agent "
             "20-80 m away, and box pixels weigh 21x in the loss")
    assert ch12.phase_text(_phase(), 0.5) == plain
    no_min = _phase()
    del no_min["min_gap"]  # older manifests: every gap from 1
    assert ch12.phase_text(no_min, 0.5) == plain
    everything = _phase(steps=4000, lr=5e-05, gamma=0.25, milestones=[2000], focus_p=0.5,
                        focus_depth=[30.0, 60.5], box_weight=40.0, min_gap=4, init_float16=True,
                        full_res=True, ema=0.999, scale=0.75)
    assert ch12.phase_text(everything, 0.5) == (
        "4000 more steps from the previous phase's weights as published (float16) (a fresh "
        "Adam 5e-05, x0.25 at its steps 2000); a share 0.5 of the windows holds the box of an "
        "agent 30-60.5 m away, and box pixels weigh 41x in the loss; only the pairs 4 to 6 "
        "frames apart (keyframes: 6); the finest level's loss on its flow upsampled to every "
        "pixel (as inference does); passes on the moving average of its weights (decay "
        "0.999); frames read at scale 0.75 (before: 0.5)")
    assert ch12.phase_text(_phase(min_gap=2, max_gap=3), 0.5) == (
        plain + "; only the pairs 2 to 3 frames apart (keyframes: 6)")
    assert ch12.phase_text(_phase(min_gap=6, max_gap=6, scale=0.5), 1.0) == (
        plain + "; only the pairs 6 frames apart (keyframes: 6); frames read at scale 0.5 "
        "(before: 1)")


def _manifest():
    """A small hand-made manifest of the shipped weights: three phases, scale 0.5 then
    0.75."""
    first = {"val_every": 4, "max_gap": 6, "start_stride": 4, "scale": 0.5, "batch": 4,
             "crop": [256, 448], "flip_p": 0.5, "level_weights": [1.0, 0.5, 0.25],
             "lr": 0.0003, "gamma": 0.5, "milestones": [2000, 3000], "steps": 4000}
    curve = [{"step": 0, "val_epe": 31.3721, "val_epe_boxes": 13.0563, "val_fl_all": 59.0681,
              "val_fl_all_boxes": 81.4414, "val_seconds_per_pair": 0.17},
             {"step": 1000, "val_epe": 20.5, "val_epe_boxes": 5.5, "val_fl_all": 45.5,
              "val_fl_all_boxes": 55.5, "val_seconds_per_pair": 0.18}]
    return {
        "network": "FastFlowNet", "steps": 9000, "scale": 0.75, "train_seconds": 9181.0,
        "sha256": "0123456789abcdef0123", "where": {"device": "cpu", "threads": 2,
                                                     "machine": "x86_64"},
        "world": {"dataroot_params": {"world_scenes": 32, "world_keyframes": 10,
                                      "seed": 1000}},
        "schedule": [first, _phase(steps=3000, scale=0.75), _phase(steps=2000, scale=0.75)],
        "training_curve": [{"step": 100, "loss": 42.8, "epe2": 19.1},
                           {"step": 200, "loss": 41.7, "epe2": 18.6}],
        "validation": {"baselines": {"zero flow": _m(30.1234, 12.3456, 90.1234, 95.6789),
                                     DIS: _m(18.7654, 1.4264, 38.1486, 4.7877)},
                       "curve": curve,
                       "final_float16": _m(17.1111, 1.2345, 35.5555, 4.4444)}}


def test_recipe_table_has_one_row_per_fact_of_the_manifest():
    """How the shipped weights were made: network, world, pairs, batch, loss, the first
    phase's schedule, each later phase in words (with the scale before it), the training
    time in hours and the file's digest."""
    t = ch12.recipe_table(_manifest())
    assert t.columns.tolist() == ["", "shipped weights"]
    later = ("more steps from the previous phase's weights (a fresh Adam 0.0002, x0.5 at its "
             "steps 3000, 4000); a share 0.75 of the windows holds the box of an agent 20-80 m "
             "away, and box pixels weigh 21x in the loss")
    assert dict(zip(t[""], t["shipped weights"], strict=True)) == {
        "network": "FastFlowNet",
        "pretraining world": ("32 scenes x 10 keyframes, seed 1000, sweeps in every scene; "
                              "every 4th scene for validation; no scene of this book's "
                              "worlds"),
        "pairs": ("1 to 6 camera frames apart (12 Hz), from every 4th frame of the training "
                  "scenes, at scale 0.5"),
        "batch": "4 random 256 x 448 windows, a horizontal flip with p 0.5",
        "loss": ("end-point error against the exact flow (valid pixels) at every decoder "
                 "level, weights 1, 0.5, 0.25"),
        "schedule": "Adam 0.0003, x0.5 at steps 2000, 3000; 4000 steps",
        "phase 2": f"3000 {later}; frames read at scale 0.75 (before: 0.5)",
        "phase 3": f"2000 {later}",
        "training time": "2.6 h on cpu (2 threads, x86_64)",  # 2.55028 h
        "file": "float16 state_dict, sha256 0123456789ab...",
    }
    assert t[""].tolist()[6:8] == ["phase 2", "phase 3"]
    m = _manifest()
    m["schedule"][0]["min_gap"] = 3
    pairs = dict(zip(*ch12.recipe_table(m).T.to_numpy(), strict=True))["pairs"]
    assert pairs.startswith("3 to 6 camera frames apart"), "the first phase's min_gap"


METRIC_COLUMNS = ["method", "frame scale", "EPE (px)", "EPE in boxes (px)", "Fl-all (%)",
                  "Fl-all in boxes (%)"]


def test_validation_table_puts_step_0_at_the_first_scale_and_the_rest_at_the_last():
    """The pretraining world's validation pairs: each baseline and the shipped float16
    weights at the last phase's scale, the untrained network (the curve's step 0) at the
    first's; EPE to 0.01, Fl-all to 0.1."""
    t = ch12.validation_table(_manifest())
    assert t.columns.tolist() == METRIC_COLUMNS
    assert t["method"].tolist() == ["zero flow", DIS, "fastflownet, step 0 (untrained)",
                                    "fastflownet (shipped), step 9000"]
    np.testing.assert_allclose(t[METRIC_COLUMNS[1:]].to_numpy(float),
                               [[0.75, 30.12, 12.35, 90.1, 95.7],
                                [0.75, 18.77, 1.43, 38.1, 4.8],
                                [0.5, 31.37, 13.06, 59.1, 81.4],
                                [0.75, 17.11, 1.23, 35.6, 4.4]], rtol=0, atol=1e-9)


def test_scale_changes_and_curves_follow_the_schedule():
    """Each phase that reads another scale than its predecessor, at the step the phases
    before it add up to; the two curves as tables."""
    m = {"schedule": [{"steps": s, "scale": c} for s, c in
                      ((100, 0.5), (200, 0.5), (300, 0.75), (400, 0.75), (500, 1.0))]}
    assert ch12.scale_changes(m) == [(300, 0.75), (1000, 1.0)]
    assert ch12.scale_changes({"schedule": m["schedule"][:1]}) == []
    train, val = ch12.curves(_manifest())
    assert train.columns.tolist() == ["step", "loss", "epe2"]
    assert train["step"].tolist() == [100, 200] and train["loss"].tolist() == [42.8, 41.7]
    assert val.columns.tolist() == ["step", "val_epe", "val_epe_boxes", "val_fl_all",
                                    "val_fl_all_boxes", "val_seconds_per_pair"]
    assert val["val_epe"].tolist() == [31.3721, 20.5]


# --- the shipped weights on this book's world (the ``shipped`` node) ---------------------------

#: Per method: (EPE, EPE in boxes) every scene has on average; the pairs of scene s1 are
#: 0.5 px off that mean either way, so that each interval over scenes is (mean, mean).
SCENE_MEANS = {"zero flow": (9.0, 4.0), "farneback": (5.0, 3.0), DIS: (3.0, 2.0),
               SHIPPED: (4.0, 1.25)}
#: (pair, scene, offset) in the order the node wrote them (not sorted; method after method).
PAIRS = [("p3", "s1", 0.5), ("p1", "s1", -0.5), ("p4", "s3", 0.0), ("p2", "s2", 0.0)]


def _shipped(p, empty=False):
    """Publish the ``shipped`` node: its table, per-pair errors and example pair."""
    table = pd.DataFrame([{"method": k, **_m(*v, fl=10.25 + i, fl_boxes=20.75 + i,
                                             sec=0.123 + i)}
                          for i, (k, v) in enumerate(SCENE_MEANS.items())])
    long = pd.DataFrame([{"pair_id": pid, "scene": s, "path_1": f"img/{pid}.png",
                          "method": k, "epe": e + d, "epe_boxes": b + 2 * d}
                         for k, (e, b) in SCENE_MEANS.items() for pid, s, d in PAIRS])
    folder = _publish(p, Node("shipped"))
    if empty:
        table, long = pd.DataFrame(), pd.DataFrame()
    table.to_parquet(folder / "world.parquet", index=False)
    long.to_parquet(folder / "pairs.parquet", index=False)
    return folder


def test_held_out_check_gives_each_method_its_errors_and_intervals_over_scenes(tmp_path):
    """The ``shipped`` node's table: per method its rounded metrics, each EPE followed by
    its interval over that method's pairs' scenes (flagged: 3 scenes are too few), and the
    seconds per pair; beside it the per-pair box errors, one column per method, in the
    node's pair order."""
    p = _demo(tmp_path)
    _shipped(p)
    table, errors = ch12.held_out_check(p)
    assert table.columns.tolist() == [
        "method", "EPE (px)", "EPE 95% CI over scenes", "EPE in boxes (px)",
        "EPE in boxes 95% CI over scenes", "Fl-all (%)", "Fl-all in boxes (%)", "s / pair"]
    assert table["method"].tolist() == list(SCENE_MEANS)
    assert table["EPE (px)"].tolist() == [9.0, 5.0, 3.0, 4.0]
    assert table["EPE in boxes (px)"].tolist() == [4.0, 3.0, 2.0, 1.25]
    assert table["EPE 95% CI over scenes"].tolist() == [
        f"{e:.2f}-{e:.2f} (3 scenes: too few)" for e, _ in SCENE_MEANS.values()]
    assert table["EPE in boxes 95% CI over scenes"].tolist() == [
        f"{b:.2f}-{b:.2f} (3 scenes: too few)" for _, b in SCENE_MEANS.values()]
    assert table["Fl-all (%)"].tolist() == pytest.approx([10.2, 11.2, 12.2, 13.2], abs=1e-9)
    assert table["Fl-all in boxes (%)"].tolist() == pytest.approx([20.8, 21.8, 22.8, 23.8],
                                                                 abs=1e-9)
    assert table["s / pair"].tolist() == pytest.approx([0.12, 1.12, 2.12, 3.12], abs=1e-9)
    assert errors.columns.tolist() == ["pair_id", "scene", DIS, "farneback", SHIPPED,
                                       "zero flow"]
    assert errors.columns.name is None
    assert errors["pair_id"].tolist() == ["p3", "p1", "p4", "p2"]
    assert errors["scene"].tolist() == ["s1", "s1", "s3", "s2"]
    for k, (_, b) in SCENE_MEANS.items():
        assert errors[k].tolist() == pytest.approx([b + 1.0, b - 1.0, b, b], abs=1e-12), k


def test_held_out_check_intervals_resample_scenes_with_the_profiles_seed(tmp_path):
    """Each EPE interval is the scene bootstrap of that method's per-pair values with the
    profile's seed, to 0.01 px."""
    p = _demo(tmp_path, seed=5)
    rng = np.random.default_rng(3)
    scenes = np.repeat([f"s{i:02d}" for i in range(12)], 2)  # enough: no flag
    long = pd.DataFrame({"pair_id": [f"p{i}" for i in range(24)], "scene": scenes,
                         "path_1": "x.png", "method": SHIPPED, "epe": rng.uniform(1, 9, 24),
                         "epe_boxes": rng.uniform(0, 4, 24)})
    folder = _publish(p, Node("shipped"))
    pd.DataFrame([{"method": SHIPPED, **_m(5.0, 2.0, 1.0, 1.0)}]).to_parquet(
        folder / "world.parquet", index=False)
    long.to_parquet(folder / "pairs.parquet", index=False)
    table, _ = ch12.held_out_check(p)
    for col, values in (("EPE", long["epe"]), ("EPE in boxes", long["epe_boxes"])):
        lo, hi = _scene_interval(values, scenes, 5)
        assert _scene_interval(values, scenes, 0) != pytest.approx((lo, hi), abs=0.01)
        assert table[f"{col} 95% CI over scenes"].tolist() == [f"{lo:.2f}-{hi:.2f}"]


def test_held_out_check_is_none_without_exact_flow(tmp_path):
    """On data without exact flow the node's tables are empty: (None, None)."""
    p = _demo(tmp_path)
    _shipped(p, empty=True)
    assert ch12.held_out_check(p) == (None, None)


def test_shipped_example_is_the_first_pairs_frame_and_float32_flows(tmp_path):
    """The ``shipped`` node's example: frame 1 of its first pair (read from the data set),
    the exact, DIS and shipped flows as float32 (other arrays left out) and the valid
    mask."""
    data = tmp_path / "data"
    p = _demo(tmp_path, dataroot=str(data), synthetic=False)
    folder = _shipped(p)
    (data / "img").mkdir(parents=True)
    for k, (pid, _, _) in enumerate(PAIRS):
        cv2.imwrite(str(data / "img" / f"{pid}.png"), _texture(k, 8, 16))
    rng = np.random.default_rng(0)
    arrays = {k: rng.normal(0, 3, (8, 16, 2)).astype(np.float16)
              for k in ("exact", DIS, SHIPPED, "farneback")}
    valid = rng.random((8, 16)) > 0.3
    np.savez(folder / "example.npz", **arrays, valid=valid)
    img, flows, got_valid = ch12.shipped_example(p)
    np.testing.assert_array_equal(img, cv2.imread(str(data / "img" / "p3.png")))
    assert list(flows) == ["exact", DIS, SHIPPED]
    for k, v in flows.items():
        assert v.dtype == np.float32
        np.testing.assert_array_equal(v, arrays[k].astype(np.float32))
    np.testing.assert_array_equal(got_valid, valid)


def test_box_difference_is_the_shipped_minus_dis_per_pair_with_its_scenes():
    """The shipped network's box EPE minus DIS's, paired per pair: the mean over defined
    pairs, its interval over scenes (degenerate: every scene's mean is the same), the
    verdict and the scenes with a defined difference."""
    errors = pd.DataFrame({"scene": ["a", "a", "b", "c", "b"],
                           SHIPPED: [1.0, 4.0, 3.0, np.nan, 2.0],
                           DIS: [0.5, 1.5, 1.5, 1.0, 0.5]})
    assert ch12.box_difference(errors, seed=3) == {"diff": 1.5, "ci": (1.5, 1.5),
                                                   "verdict": "A better", "scenes": 2}
    flipped = errors.rename(columns={SHIPPED: DIS, DIS: SHIPPED})
    assert ch12.box_difference(flipped) == {"diff": -1.5, "ci": (-1.5, -1.5),
                                            "verdict": "B better", "scenes": 2}


def _scene_interval(values, scenes, seed, n=2000):
    """The 95 % percentile interval of the mean of ``values`` over pairs, whole scenes
    drawn with replacement (numpy's multinomial draws, seeded), NaN values left out."""
    v, g = np.asarray(values, float), np.asarray(scenes)
    keep = ~np.isnan(v)
    names = sorted(set(g[keep]))
    sums = np.array([v[keep][g[keep] == s].sum() for s in names])
    counts = np.array([(g[keep] == s).sum() for s in names], float)
    w = np.random.default_rng(seed).multinomial(len(names), [1 / len(names)] * len(names),
                                                size=n)
    return tuple(np.quantile((w @ sums) / (w @ counts), [0.025, 0.975]))


def test_box_difference_resamples_scenes_with_the_given_seed():
    """The interval of the paired difference resamples whole scenes with ``seed`` (0 by
    default), as a scene bootstrap written out with numpy does."""
    rng = np.random.default_rng(7)
    scenes = np.repeat(["a", "b", "c", "d", "e"], 3)
    errors = pd.DataFrame({"scene": scenes, SHIPPED: rng.uniform(0, 3, 15),
                           DIS: rng.uniform(0, 2, 15)})
    diff = (errors[SHIPPED] - errors[DIS]).to_numpy()
    want0, want5 = _scene_interval(diff, scenes, 0), _scene_interval(diff, scenes, 5)
    assert want0 != pytest.approx(want5, abs=1e-6)
    assert ch12.box_difference(errors)["ci"] == pytest.approx(want0, abs=1e-12)
    assert ch12.box_difference(errors, seed=5)["ci"] == pytest.approx(want5, abs=1e-12)


def test_observation_pairs_the_shipped_chain_with_dis_or_is_empty(handmade_study,
                                                                  monkeypatch):
    """On the hand-made study: the box difference (with the profile's seed) and Table 3's
    and Table 4's paired rows, named fastflownet - dis; empty where a chain is not a flow
    method or not built."""
    p, _ = handmade_study
    monkeypatch.setattr(ch12.pipeline, "built", lambda params, node: True)
    errors = pd.DataFrame({"scene": ["a", "a", "b"], SHIPPED: [1.0, 2.0, 0.5],
                           DIS: [1.5, 4.0, 1.75]})
    obs = ch12.observation(p, errors)
    assert list(obs) == ["epe_boxes_minus_dis", "test", "general"]
    assert obs["epe_boxes_minus_dis"] == {"diff": -1.25,
                                          "ci": (-1.25, -1.25), "verdict": "B better",
                                          "scenes": 2}
    assert obs["test"]["comparison"] == "fastflownet - dis (Table 3)"
    assert obs["general"]["comparison"] == "fastflownet - dis (Table 4)"
    assert ch12.observation(p, None)["epe_boxes_minus_dis"] is None
    rng = np.random.default_rng(1)
    spread = pd.DataFrame({"scene": np.repeat([f"s{i:02d}" for i in range(12)], 2),
                           SHIPPED: rng.uniform(0, 3, 24), DIS: rng.uniform(0, 3, 24)})
    diff = (spread[SHIPPED] - spread[DIS]).to_numpy()
    seeded = ch12.observation(p.model_copy(update={"seed": 9}), spread)
    want = _scene_interval(diff, spread["scene"], 9)
    assert want != pytest.approx(_scene_interval(diff, spread["scene"], 0), abs=1e-6)
    assert seeded["epe_boxes_minus_dis"]["ci"] == pytest.approx(want, abs=1e-12)
    assert ch12.observation(p, errors, methods=("raft", "dis")) == {}
    assert ch12.observation(p, errors, methods=("dis", "raft")) == {}
    monkeypatch.setattr(ch12.pipeline, "built", lambda params, node: node.method != "dis")
    assert ch12.observation(p, errors) == {}
    monkeypatch.setattr(ch12.pipeline, "built",
                        lambda params, node: node.method != "fastflownet")
    assert ch12.observation(p, errors) == {}



def test_observation_asks_each_chain_with_the_run_s_parameters_and_scores_its_splits(
        handmade_study, monkeypatch):
    """Each chain is asked about by its ``generalise`` node with the run's parameters;
    Table 3's row pairs every test object whatever Table 4's range, Table 4's those within
    it; both intervals are drawn with the run's seed; predictions of different objects are
    one error naming both chains and the table."""
    p, tables = handmade_study
    asked = []

    def built(params, node):
        asked.append((params, node))
        return True

    monkeypatch.setattr(ch12.pipeline, "built", built)
    q = p.model_copy(update={"seed": 5, "general_max_distance": 40.0})
    obs = ch12.observation(q, None)
    assert [n for _, n in asked] == [Node("generalise", "fastflownet"),
                                     Node("generalise", "dis")]
    assert all(params is q for params, _ in asked)
    for split, node, near in (("test", "evaluate", False), ("general", "generalise", True)):
        a, b = (tables[Node(node, m)][split] for m in ("fastflownet", "dis"))
        if near:
            a, b = a[a["distance"] <= 40], b[b["distance"] <= 40]
        assert 0 < len(a) and (len(a) < len(tables[Node(node, "dis")][split])) == near
        assert obs[split]["objects"] == len(a)
        probs = [np.array([df[c].to_numpy() for c in sorted(
            (c for c in df.columns if c.startswith("prob_s")), key=lambda c: int(c[6:]))])
            for df in (a, b)]
        want = metrics.paired_comparison(a["label"].to_numpy(), *probs, a["scene"].to_numpy(),
                                         seed=5, folds=a["fold"].to_numpy())
        lo, hi = want["ci"]
        assert obs[split]["95% CI, scenes and seeds (points)"].startswith(
            f"{100 * lo:.1f} to {100 * hi:.1f}"), split
    real = ch12.common.results

    def shifted(params, method, split):
        preds, s = real(params, method, split)
        return (preds.iloc[1:] if method == "dis" else preds), s

    monkeypatch.setattr(ch12.common, "results", shifted)
    with pytest.raises(ValueError, match=r"^fastflownet and dis \(Table 3\) were scored on "
                                         "different objects$"):
        ch12.observation(p, None)


# --- the chapter's sentences -------------------------------------------------------------------

def _world_table(f_epe, f_boxes, d_epe, d_boxes):
    row = {"Fl-all (%)": 30.0, "Fl-all in boxes (%)": 9.04, "s / pair": 0.1234}
    return pd.DataFrame([{"method": "zero flow", "EPE (px)": 99.0, "EPE in boxes (px)": 99.0,
                          "Fl-all (%)": 99.0, "Fl-all in boxes (%)": 99.0, "s / pair": 0.0},
                         {"method": SHIPPED, "EPE (px)": f_epe, "EPE in boxes (px)": f_boxes,
                          **row},
                         {"method": DIS, "EPE (px)": d_epe, "EPE in boxes (px)": d_boxes,
                          **row, "Fl-all in boxes (%)": 12.36, "s / pair": 0.0456}])


def test_world_words_state_the_shipped_network_against_dis_in_numbers():
    """The sentence on this book's world: both EPEs (0.1 px) with lower / higher / equal at
    that precision, the box Fl-all of each and the seconds per pair; or why there are
    none."""
    assert ch12.world_words(_world_table(14.26, 2.04, 13.2, 1.5), 16) == (
        "On 16 keyframe pairs of this book's world (scenes the network never saw), its "
        "end-point error is 14.3 px over the frame, higher than DIS's 13.2 px, and 2.0 px "
        "inside the far vehicles' boxes, higher than DIS's 1.5 px (Fl-all in the boxes 9.0 "
        "against 12.4 %); it takes 0.12 s a pair where they were computed against DIS's "
        "0.05 s.")
    words = ch12.world_words(_world_table(13.16, 1.04, 13.2, 1.5), 8)
    assert "13.2 px over the frame, equal to DIS's 13.2 px" in words
    assert "1.0 px inside the far vehicles' boxes, lower than DIS's 1.5 px" in words
    assert words.startswith("On 8 keyframe pairs")
    words = ch12.world_words(_world_table(13.16, 1.04, 13.2, 1.01), 8)  # both shown 1.0
    assert "1.0 px inside the far vehicles' boxes, equal to DIS's 1.0 px" in words
    assert ch12.world_words(None, 16) == (
        "This data set has no exact flow, so the shipped weights' errors cannot be measured "
        "on it; where `fastflownet` is one of `flow_methods`, Table 3 still shows how their "
        "flow classifies.")


T3 = {"ΔF1 (points)": 4.04, "95% CI, scenes and seeds (points)": "1.0 to 7.0",
      "verdict": "A better", "detectable (points)": 3.0}
T4 = {"ΔF1 (points)": -0.36, "95% CI, scenes and seeds (points)": "-2.5 to 1.8",
      "verdict": "inconclusive", "detectable (points)": 3.04}
T3_WORDS = "+4.0 F1 points (95 % interval over scenes and training seeds 1.0 to 7.0)"
T4_WORDS = ("-0.4 F1 points (95 % interval over scenes and training seeds -2.5 to 1.8; "
            "inconclusive: these scenes would detect 3.0 points or more)")
CLASSIFIERS = (f"Its classifier minus DIS's, paired on the same objects: {T3_WORDS} on "
               f"Table 3 and {T4_WORDS} on Table 4. ")


def _box(verdict, diff=1.234, ci=(0.5, 1.956), scenes=3):
    return {"diff": diff, "ci": ci, "verdict": verdict, "scenes": scenes}


def test_observation_words_answer_the_papers_observation_in_every_case():
    """The observation in words: the flows' accuracy in the boxes (with its interval), the
    classifiers' differences on Tables 3 and 4, and whether the paper's observation repeats
    (both decided, the less accurate flow classifying better), is contradicted, or is left
    open; or why it cannot be answered."""
    assert ch12.observation_words({}) == (
        "Table 3 of this profile has no `fastflownet` and `dis` rows to compare "
        "(`flow_methods`), so this chapter cannot answer it here.")
    obs = {"epe_boxes_minus_dis": None, "test": T3, "general": T4}
    assert ch12.observation_words(obs) == (
        CLASSIFIERS + "Without exact flow, which of the two flows is more accurate is unknown.")

    def box(verdict, what):
        return (f"Inside the target boxes the shipped FastFlowNet's flow is {what} DIS's "
                "(+1.23 px of end-point error, 95 % interval over 3 scenes +0.50 to +1.96). ")

    repeats = ("The less accurate flow classifies better here too: the paper's observation "
               "repeats.")
    not_repeats = ("Here the more accurate flow classifies better: the paper's observation "
                   "does not repeat.")
    cases = [("A better", "A better", "less accurate than", repeats),
             ("B better", "B better", "more accurate than", repeats),
             ("B better", "A better", "more accurate than", not_repeats),
             ("A better", "B better", "less accurate than", not_repeats)]
    for flows, t3, what, end in cases:
        obs = {"epe_boxes_minus_dis": _box(flows), "test": {**T3, "verdict": t3},
               "general": T4}
        assert ch12.observation_words(obs) == box(flows, what) + CLASSIFIERS + end, (flows, t3)
    obs = {"epe_boxes_minus_dis": _box("undecided"), "test": T3, "general": T4}
    assert ch12.observation_words(obs) == (
        box("undecided", "not told apart from") + CLASSIFIERS
        + "The classifiers differ where these pairs cannot tell the flows' accuracy in the "
          "boxes apart: the paper's observation is neither repeated nor contradicted here.")
    for t3 in ("inconclusive", "equivalent"):
        undecided = {**T4, "verdict": t3}
        obs = {"epe_boxes_minus_dis": _box("A better"), "test": undecided, "general": T3}
        assert ch12.observation_words(obs).endswith(
            "These scenes cannot tell the two classifiers apart on Table 3, so they neither "
            "repeat nor contradict the paper's observation."), t3
    obs = {"epe_boxes_minus_dis": _box("A better"), "test": {**T4, "verdict": "inconclusive"},
           "general": T3}
    assert ch12.observation_words(obs).startswith(
        box("A better", "less accurate than") + "Its classifier minus DIS's, paired on the "
        f"same objects: {T4_WORDS} on Table 3 and {T3_WORDS} on Table 4. ")


def test_shipped_headline_adds_each_part_it_has_numbers_for():
    """The landing sentence on the shipped weights: steps and hours; the box EPE against
    DIS's where measured, with the paired difference and its interval (flagged decided or
    with too few scenes); Table 3's difference where compared; or where the weights are
    missing."""
    m = {"steps": 9000, "train_seconds": 9181.0}  # 2.55028 h
    head = ("FastFlowNet pretrained here, supervised on a synthetic world of its own (9000 "
            "steps, 2.6 h on a CPU)")
    assert ch12.shipped_headline(m, None, {}) == head
    table = _world_table(14.26, 1.04, 13.2, 1.56)
    boxes = (", has an end-point error of 1.0 px inside the far vehicles' boxes of this "
             "book's world against DIS's 1.6 px")
    assert ch12.shipped_headline(m, table, {}) == head + boxes
    undecided = _box("undecided", diff=-0.256, ci=(-0.804, 0.2), scenes=12)
    assert ch12.shipped_headline(m, table, {}, undecided) == head + boxes + (
        " (paired per pair -0.26 px, 95 % interval over scenes -0.80 to +0.20)")
    decided = _box("B better", diff=-0.5, ci=(-0.9, -0.1), scenes=4)
    assert ch12.shipped_headline(m, table, {}, decided) == head + boxes + (
        " (paired per pair -0.50 px, 95 % interval over scenes -0.90 to -0.10 (4 scenes: too "
        "few), decided)")
    obs = {"test": T3, "general": T4, "epe_boxes_minus_dis": None}
    assert ch12.shipped_headline(m, None, obs) == (
        head + f"; its classifier minus DIS's on Table 3: {T3_WORDS}")
    assert ch12.shipped_headline(None, table, obs, decided) == (
        "no shipped FastFlowNet weights in weights/fastflownet_synth (`make flownet` makes "
        "them)")


def test_shipped_note_says_whether_the_profile_runs_the_weights_and_at_which_scale(tmp_path):
    """The chapter's line on the shipped weights: their file, steps and digest, whether
    this profile's ``fastflownet`` runs them, and a warning where it computes flow at
    another scale than they were trained at last; or how to make them."""
    p = _demo(tmp_path)
    m = {"steps": 9000, "sha256": "0123456789abcdef0123", "scale": 0.75}
    start = ("Shipped weights: `weights/fastflownet_synth/weights.pt`, 9000 steps, sha256 "
             "`0123456789ab`; ")
    assert ch12.shipped_note(p, m) == (
        start + "this profile's `fastflownet` flow method runs them.")
    other = p.model_copy(update={"flow_methods": ["gt", "dis"], "flow_scale": 0.5})
    assert ch12.shipped_note(other, m) == (
        start + "this profile's `fastflownet` flow method does not run them (`flow_methods`, "
        "`fastflownet_weights`). They were trained last on frames at scale 0.75; this "
        "profile computes flow at 0.5 (`flow_scale`), where they were not validated.")
    assert ch12.shipped_note(p, None) == (
        "No shipped weights in `weights/fastflownet_synth`: `make flownet` makes them (about "
        "an hour on a CPU, resumable).")
