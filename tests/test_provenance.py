"""Reruns that never lie: one provenance mechanism (flowmod.dag) for every stage.

On a finished smoke run: every parameter, perturbed, makes exactly the stages that read it and
everything downstream stale in ``--status`` (nothing runs); real reruns recompute exactly
those nodes, rewrite nothing else, and give the numbers of a run from scratch; switching a
parameter back restores instead of recomputing; a failed forced rerun loses nothing.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from flowmod import dag, pipeline, select
from flowmod.chapters import common
from flowmod.flow import ImageError
from flowmod.params import Params

pytestmark = pytest.mark.slow

#: Every parameter: (a valid other value, the stages that read it, only for these methods).
#: This is the specification the ``read_by`` declarations in flowmod/params.py must meet;
#: the test below fails if the two disagree or if the status does not follow them.
SPEC: dict[str, tuple[object, set[str], tuple[str, ...]]] = {
    "profile": ("other", set(), ()),
    "seed": (1, {"world", "select", "flowcheck", "flow", "train", "evaluate", "xtrain",
                  "wtrain", "selfflow", "shipped", "elevels", "etrain", "eevaluate"}, ()),
    "device": ("cpu", set(), ()),
    "force": (True, set(), ()),
    "world_scenes": (5, {"world"}, ()),
    "world_keyframes": (3, {"world"}, ()),
    "world_sweep_scenes": (2, {"world"}, ()),
    "world_vehicles": (17, {"world"}, ()),
    "world_near_movers": (1, {"world"}, ()),
    "categories": (["vehicle.car", "vehicle.truck"], {"select", "general", "wide"}, ()),
    "min_distance": (25.0, {"select", "flowcheck"}, ()),
    "max_distance": (65.0, {"select", "flowcheck"}, ()),
    "distance_mode": ("camera", {"select", "general", "wide"}, ()),
    "visibility_tokens": (["3", "4"], {"select", "general", "wide"}, ()),
    "exclude_descriptions": (["night"], {"select"}, ()),
    "split_fractions": ([0.6, 0.2, 0.2], {"select"}, ()),
    "missing_images": ("skip", {"select", "general", "wide"}, ()),
    "speed_threshold": (2.5, {"select", "general", "difficulty", "wide"}, ()),
    "general_interval": (3, {"general", "wide"}, ()),
    "general_min_distance": (1.0, {"general", "wide"}, ()),
    "general_max_distance": (90.0, {"general", "wide"}, ()),
    "general_max_scenes": (2, {"general"}, ()),
    "general_stride": (2, {"general"}, ()),
    "flow_scale": (0.25, {"flow", "crops", "selfflow", "shipped"}, ()),
    "dis_preset": ("fast", {"flow", "crops"}, ("dis",)),
    "flow_dtype": ("float32", {"flow", "crops"}, ()),
    "raft_weights": ("weights/raft.pth", {"flow", "crops"}, ("raft",)),  # see also below
    "raft_small_weights": ("weights/raft_small.pth", {"flow", "crops"}, ("raft_small",)),
    "fastflownet_weights": ("weights/ffn.pth", {"flow", "crops"}, ("fastflownet",)),
    "n_jobs": (2, set(), ()),
    "executor": ("ray", set(), ()),
    "ray_address": ("auto", set(), ()),
    "crop_size": (48, {"crops", "context"}, ()),
    "crop_scale": (2.5, {"crops", "context", "elevels", "etrain", "eevaluate"}, ()),
    "epochs": (2, {"train", "xtrain", "wtrain", "etrain"}, ()),
    "batch_size": (4, {"train", "xtrain", "wtrain", "etrain"}, ()),
    "lr": (0.02, {"train", "xtrain", "wtrain", "etrain"}, ()),
    "momentum": (0.8, {"train", "xtrain", "wtrain", "etrain"}, ()),
    "weight_decay": (0.02, {"train", "xtrain", "wtrain", "etrain"}, ()),
    "step_size": (4, {"train", "xtrain", "wtrain", "etrain"}, ()),
    "gamma": (0.4, {"train", "xtrain", "wtrain", "etrain"}, ()),
    "hflip_p": (0.3, {"train", "xtrain", "wtrain", "etrain"}, ()),
    "model_width": (24, {"train", "xtrain", "wtrain", "etrain"}, ()),
    "amp": ("bf16", {"train", "xtrain", "wtrain", "etrain"}, ()),
    "input_scaling": ("raw", {"train", "xtrain", "wtrain", "etrain"}, ()),
    "general_beyond_distance": (80.0, {"general"}, ()),
    "raft_iters": (12, {"flow", "crops"}, ("raft", "raft_small")),
    "num_workers": (1, set(), ()),
    "flow_networks": (["raft"], set(), ()),  # read by the runner only (before any stage)
    "flow_store": ("crops", {"flow", "crops"}, ()),
    "flow_keep_pairs": (5, {"flow"}, ()),
    "flowcheck_pairs": (3, {"flowcheck"}, ()),
    "difficulty_pairs": (7, {"difficulty"}, ()),
    "clip_method": ("gt", {"flow"}, ()),
    "extension_build": (False, set(), ()),
    "wide_sweep_stride": (2, {"wide"}, ()),
    "selfflow_build": (False, set(), ()),
    "selfflow_iters": (5, {"selfflow"}, ()),
    "selfflow_batch": (3, {"selfflow"}, ()),
    "selfflow_lr": (1e-3, {"selfflow"}, ()),
    "selfflow_crop": ([128, 128], {"selfflow"}, ()),
    "selfflow_smooth": (0.2, {"selfflow"}, ()),
    "selfflow_pairs": (3, {"selfflow"}, ()),
    "selfflow_eval_pairs": (2, {"selfflow", "shipped"}, ()),
    "shipped_weights": ("weights/other.pt", {"shipped"}, ()),
    "selfflow_eval_every": (3, {"selfflow"}, ()),
    "selfflow_init": ("weights/other.pt", {"selfflow"}, ("finetune",)),
    "selfflow_window": ("crop", {"selfflow"}, ()),
    "selfflow_warmup": (7, {"selfflow"}, ("photometric",)),
    "error_targets": ([1.5], {"elevels"}, ()),
    "error_calibration": (50, {"elevels"}, ()),
    "error_width": (8, {"etrain"}, ()),
}
#: Parameters whose change is not "some stages read another value" (checked on their own).
SPECIAL = {"run_dir", "dataroot", "synthetic", "version", "flow_methods", "seeds", "folds",
           "extension_seeds",
           "extension_inputs",
           "extension_methods", "wide_methods", "selfflow_modes", "raw_input_methods",
           "error_kinds", "error_folds"}


def downstream(p: Params, start: set[dag.Node]) -> set[dag.Node]:
    """``start`` and every node that reads one of them, directly or not."""
    out = set(start)
    for n in pipeline.nodes(p):  # data order: inputs come first
        if any(i in out for i in pipeline.inputs(n, p)):
            out.add(n)
    return out


def not_up_to_date(p: Params) -> set[dag.Node]:
    return {s.node for s in pipeline.status(p) if s.state != "up to date"}


@pytest.fixture(scope="module")
def finished(smoke_built) -> Params:
    """A finished smoke run (all chapters), shared: tests that change it work on a copy."""
    assert not_up_to_date(smoke_built) == set()
    return smoke_built


def test_spec_covers_every_parameter():
    assert set(SPEC) | SPECIAL == set(Params.model_fields)


@pytest.mark.parametrize("name", sorted(SPEC))
def test_every_parameter_makes_exactly_its_readers_and_downstream_stale(finished, name):
    value, stages, methods = SPEC[name]
    assert getattr(finished, name) != value
    p = finished.model_copy(update={name: value})
    direct = {n for n in pipeline.nodes(p)
              if n.stage in stages and (not methods or n.method in methods
                                        or n.part in methods)}
    assert not_up_to_date(p) == downstream(p, direct)
    for s in pipeline.status(p):
        if s.node in direct and s.node.stage != "world":
            assert name in s.why, f"{s.node}: the one-line reason names the parameter: {s.why}"


def test_special_parameters(finished, tmp_path):
    nodes = set(pipeline.nodes(finished))
    # another place for the data (not there yet): the world is missing, and nothing below it
    # can be trusted until it is there; once there (here copied: that the generator makes the
    # same bytes again is tests/test_world.py's) it is the same content (the world's
    # identity), so what was built from it is valid again
    for name, value in (("dataroot", str(tmp_path / "elsewhere")), ("version", "v1.0-other")):
        moved = finished.model_copy(update={name: value})
        st = {s.node: s for s in pipeline.status(moved)}
        assert st[dag.Node("world")].state == "missing"
        assert {n for n, s in st.items() if s.state == "up to date"} == set()
        assert "input world is missing" in st[dag.Node("select")].why
    # synthetic: false says the dataroot itself is the data (real nuScenes): at the parent of
    # the generated worlds there is none; pointed at the world's own folder, nothing changes
    real = finished.model_copy(update={"synthetic": False})
    assert real.dataroot_path == Path(finished.dataroot).resolve() != finished.dataroot_path
    assert {s.node: s.state for s in pipeline.status(real)}[dag.Node("world")] == "missing"
    in_place = finished.model_copy(update={"synthetic": False,
                                           "dataroot": str(finished.dataroot_path)})
    assert in_place.dataroot_path == finished.dataroot_path and not_up_to_date(in_place) == set()
    elsewhere = finished.model_copy(update={"dataroot": str(tmp_path / "elsewhere")})
    shutil.copytree(Path(finished.dataroot), tmp_path / "elsewhere")
    pipeline.build(elsewhere, ["01"])
    assert elsewhere.dataroot_path != finished.dataroot_path
    assert not_up_to_date(elsewhere) == set()
    # another run folder: nothing built there yet
    fresh = finished.model_copy(update={"run_dir": str(tmp_path / "runs")})
    assert not_up_to_date(fresh) == nodes - {dag.Node("world")}
    # one more flow method: its chain is missing, nothing else changes
    more = finished.model_copy(update={"flow_methods": [*finished.flow_methods, "farneback"]})
    assert not_up_to_date(more) == {n for n in pipeline.nodes(more) if n.method == "farneback"
                                    } | {dag.Node("flowcheck")}  # which scores every method
    # another number of folds: a new split, so everything from the selection on is stale
    # (the world and chapter 01's nodes on it are not), and a third model per chain exists
    three = finished.model_copy(update={"folds": 3})
    assert not_up_to_date(three) == set(pipeline.nodes(three)) - {
        dag.Node("world"), dag.Node("difficulty"), dag.Node("example")}
    assert dag.Node("train", "dis", "f2s1") in pipeline.nodes(three)  # two seeds a fold
    assert dag.Node("xtrain", "dis", "residual/f2") in pipeline.nodes(three)  # one (extension)
    assert dag.Node("train", "dis", "s0") in pipeline.nodes(
        finished.model_copy(update={"folds": 1, "seeds": 2}))
    # chapter 10's plan: one input fewer drops its nodes and changes nothing else; one method
    # fewer drops its chains
    fewer = finished.model_copy(update={"extension_inputs": finished.extension_inputs[1:]})
    assert not_up_to_date(fewer) == set() and set(pipeline.nodes(fewer)) < nodes
    gt_only = finished.model_copy(update={"extension_methods": ["gt"]})
    assert not_up_to_date(gt_only) == set()
    assert {n.method for n in pipeline.nodes(gt_only) if n.stage == "xtrain"} == {"gt", None}
    # chapter 11's plan: no method drops all its nodes (and its selection), nothing else
    off = finished.model_copy(update={"wide_methods": []})
    assert not_up_to_date(off) == set()
    assert set(nodes) - set(pipeline.nodes(off)) == {n for n in nodes if pipeline.chapter(n) == "11"}
    # chapter 12's plan: fewer modes drop their networks, nothing else
    one = finished.model_copy(update={"selfflow_modes": ["photometric"]})
    assert not_up_to_date(one) == set()
    assert set(nodes) - set(pipeline.nodes(one)) == {dag.Node("selfflow", None, "supervised"),
                                                     dag.Node("selfflow", None, "finetune")}


#: Parameters read only by the flow networks' nodes, which a CPU profile does not have.
NETWORK_PARAMETERS = ("raft_weights", "raft_small_weights", "fastflownet_weights", "raft_iters")


@pytest.mark.parametrize("name", NETWORK_PARAMETERS)
def test_network_parameters_change_exactly_their_methods_fingerprints(finished, name):
    """On a parameter set whose plan has every network (status only: nothing is built),
    another value changes the expected fingerprints of exactly the nodes its methods'
    flow and crops feed, and no other."""
    value, stages, methods = SPEC[name]
    nets = finished.model_copy(update={
        "flow_methods": [*finished.flow_methods, "raft", "raft_small", "fastflownet"]})
    other = nets.model_copy(update={name: value})
    direct = {n for n in pipeline.nodes(nets) if n.stage in stages and n.method in methods}
    assert direct, "the plan has nodes that read it"
    before, after = pipeline.expected(nets), pipeline.expected(other)
    changed = {n for n in before if before[n] != after[n]}
    assert changed == downstream(nets, direct)


def test_status_explains_in_one_line(finished):
    p = finished.model_copy(update={"dis_preset": "fast"})
    text = pipeline.format_status(p)
    line = next(ln for ln in text.splitlines() if "flow[dis/keyframe]" in ln)
    assert "stale" in line and "dis_preset: 'medium' -> 'fast'" in line
    assert "input flow[dis/keyframe] is stale" in next(
        ln for ln in text.splitlines() if "crops[dis/keyframe]" in ln)
    # the dis chain of chapters 03-08 (12 nodes: two folds x two seeds and the two raw-input
    # models), chapter 10's dis residual (3 nodes), chapter 11's dis chain (flow, crops,
    # two models, predictions) and chapter 03's flowcheck (every method against the exact
    # flow); chapter 12's nodes do not read the dis flow
    assert text.splitlines()[-1] == ("39 of 60 up to date; 21 to build (make run, or python "
                                     "-m flowmod.runner)")
    quiet = pipeline.format_status(p.model_copy(update={"extension_build": False}))
    assert quiet.splitlines()[-1].endswith(
        "chapters 10 and 11's 8 (models, predictions, flow, crops) only with extension_build: "
        "make extensions")
    assert "11  crops[dis/wide]" in quiet


def test_stage_reading_an_undeclared_parameter_fails(finished):
    q = dag.StageParams(finished, dag.Node("crops", "dis", "keyframe"))
    assert q.crop_size == finished.crop_size and q.run_path == finished.run_path
    assert q.n_jobs == finished.n_jobs, "run settings are free"
    with pytest.raises(dag.UndeclaredParameter, match="read_by of Params.epochs"):
        _ = q.epochs


# --- real reruns ------------------------------------------------------------------------------

def snapshot(run: Path) -> dict[Path, tuple[int, int]]:
    """Every artefact file with its (mtime, inode); kept variants, building folders, digest
    caches and the append-only timing logs of the flow pools are not artefacts of a node."""
    return {f: (f.stat().st_mtime_ns, f.stat().st_ino) for f in run.rglob("*")
            if f.is_file() and f.name not in (".digests.json", ".image-digests.json",
                                              "seconds.jsonl", ".flowmod.lock")
            and not any(".variant-" in x or ".building-" in x for x in f.parts)}


def manifests(p: Params) -> dict[dag.Node, float]:
    return {n: (pipeline.recorded(p, n) or {}).get("written") for n in pipeline.nodes(p)}


def scores(p: Params) -> dict[str, object]:
    out = {}
    for m in p.flow_methods:
        preds, s = common.results(p, m, "test")
        out[m] = (round(s["f1"], 12), preds["prob"].round(9).tolist(),
                  common.results(p, m, "general")[0]["prob"].round(9).tolist())
    return out


def rerun(p: Params) -> set[dag.Node]:
    """Build ``p``; return the nodes rebuilt, checking that nothing outside them was touched."""
    before_files, before = snapshot(p.run_path), manifests(p)
    stale = not_up_to_date(p)
    pipeline.build(p)
    after = manifests(p)
    rebuilt = {n for n in after if after[n] != before.get(n)}
    assert rebuilt == stale, "exactly the stale nodes are recomputed"
    inside = [pipeline.node_dir(p, n) for n in rebuilt]
    now = snapshot(p.run_path)
    for f, stat in before_files.items():
        if any(d == f.parent or d in f.parents for d in inside):
            continue  # the rebuilt node's folder (its old content is now a kept variant)
        assert now.get(f) == stat, f"{f} was rewritten although its node is up to date"
    assert not_up_to_date(p) == set()
    return rebuilt


def test_reruns_recompute_exactly_what_changed_and_match_a_fresh_run(finished, tmp_path):
    """Builds after three changes of kind (training only, the selection under everything,
    one method's flow) recompute exactly the stale nodes, touch nothing else, and end where
    a build from scratch does; switching the flow option back restores every node it made
    stale from the kept variants, flow pool and models included, computing nothing. (Which
    nodes each parameter makes stale is checked for every parameter without building:
    test_every_parameter_makes_exactly_its_readers_and_downstream_stale.)"""
    run = tmp_path / "runs"
    shutil.copytree(finished.run_path, run, symlinks=True)
    p = finished.model_copy(update={"run_dir": str(run)})
    assert rerun(p) == set(), "nothing changed: nothing is rebuilt (crops included)"
    # one epoch first, so that the retraining each later step causes is cheap
    steps = [("epochs", 1), ("min_distance", 25.0), ("dis_preset", "fast")]
    for i, (name, value) in enumerate(steps):
        if i == len(steps) - 1:
            before_last = manifests(p)
        p = p.model_copy(update={name: value})
        direct = {n for n in pipeline.nodes(p) if name in dag.reads(n)}
        assert rerun(p) == downstream(p, direct), name
    # the selection's change retrained the models on new crops and chapter 07 scores them
    rec = pipeline.recorded(p, dag.Node("train", "dis", "f0s0"))
    assert rec["inputs"]["crops[dis/keyframe]"] == pipeline.recorded(
        p, dag.Node("crops", "dis", "keyframe"))["fingerprint"]
    # the same parameters from scratch (same world) give the same numbers, also with the
    # classifiers trained two at a time in worker processes (n_jobs is a run setting)
    scratch = p.model_copy(update={"run_dir": str(tmp_path / "scratch"), "n_jobs": 2})
    pipeline.build(scratch, chapters=["01", "02", "03", "05", "06", "07", "08"])  # scores'
    assert scores(scratch) == scores(p)
    models = [n for n in pipeline.nodes(p, ["06"]) if n.stage == "train"]
    assert len(models) > 2 and all(
        (pipeline.node_dir(scratch, n) / "best.pt").read_bytes()
        == (pipeline.node_dir(p, n) / "best.pt").read_bytes() for n in models)
    # switching the flow option back restores its kept variants, from the flow pool to the
    # models: no pair and no model computed again
    pools = sorted((run / "flow" / "dis" / "pool").rglob("*.npy"))
    back = p.model_copy(update={"dis_preset": "medium"})
    direct = {n for n in pipeline.nodes(back) if "dis_preset" in dag.reads(n)}
    stale = [s for s in pipeline.status(back) if s.state != "up to date"]
    assert {s.node for s in stale} == downstream(back, direct)
    assert all("will be restored" in s.why for s in stale)
    rebuilt = rerun(back)
    assert {n.stage for n in rebuilt} >= {"flow", "crops", "train", "evaluate", "xtrain"}
    for n in rebuilt:
        assert pipeline.recorded(back, n)["written"] == before_last[n], f"{n} restored, not rebuilt"
    assert sorted((run / "flow" / "dis" / "pool").rglob("*.npy")) == pools


def test_a_damaged_crops_file_is_reported_and_rebuilt_not_scored(finished, tmp_path):
    """20 crops zeroed in place (same size, a copied run folder or a bad disk): --status
    says "damaged" naming the file, the chapter that builds the node runs again (its
    notebook fingerprint changes), and the next build restores the crops byte for byte
    before anything is scored (issue 41)."""
    import numpy as np

    from flowmod import environment, runner

    run = tmp_path / "runs"
    shutil.copytree(finished.run_path, run, symlinks=True)
    p = finished.model_copy(update={"run_dir": str(run)})
    node = dag.Node("crops", "dis", "keyframe")
    arrays = sorted(f for f in pipeline.node_dir(p, node).glob("*.npy")
                    if np.load(f, mmap_mode="r").ndim == 4)
    target = arrays[0]
    good = target.read_bytes()
    nb = next(n for n in runner.notebooks() if n.stem.startswith("05"))
    values, device = runner.notebook_parameters(nb, p), environment.device_info("cpu")
    clean_fp = runner.notebook_fingerprint(nb, values, p, device)
    x = np.load(target, mmap_mode="r+")
    x[:20] = 0
    x.flush()
    del x
    assert target.stat().st_size == len(good) and target.read_bytes() != good
    st = {s.node: s for s in pipeline.status(p)}[node]
    assert st.state == "damaged" and str(target) in st.why and "same size" in st.why
    assert "damaged" in pipeline.format_status(p) and str(target) in pipeline.format_status(p)
    assert runner.notebook_fingerprint(nb, values, p, device) != clean_fp
    assert rerun(p) == {node}
    assert target.read_bytes() == good
    assert runner.notebook_fingerprint(nb, values, p, device) == clean_fp
    assert scores(p) == scores(finished)


def test_another_world_in_the_same_run_folder_recomputes_flow(finished, tmp_path):
    """The old bug: pair ids repeat across worlds, so flow was reused from the last world."""
    run = tmp_path / "runs"
    shutil.copytree(finished.run_path, run, symlinks=True)
    p = finished.model_copy(update={"run_dir": str(run)})
    other = p.model_copy(update={"dataroot": str(tmp_path / "world2"), "world_vehicles": 12,
                                 "world_scenes": 5, "world_keyframes": 4})  # small: quick
    st = {s.node: s for s in pipeline.status(other)}
    assert st[dag.Node("flow", "gt", "keyframe")].state == "stale"
    old = {m: set(pd.read_parquet(pipeline.node_dir(p, dag.Node("flow", m, "keyframe"))
                                  / "index.parquet")["key"]) for m in p.flow_methods}
    pipeline.build(other, ["01", "02", "03"])
    for method in other.flow_methods:
        idx = pd.read_parquet(pipeline.node_dir(other, dag.Node("flow", method, "keyframe"))
                              / "index.parquet")
        assert not set(idx["key"]) & old[method], "no flow of the old world is reused"
        rec = pipeline.recorded(other, dag.Node("flow", method, "keyframe"))
        assert rec["computed"] == rec["pairs"] == len(idx)


def test_failed_forced_rerun_loses_nothing(finished, tmp_path):
    run, data = tmp_path / "runs", tmp_path / "data"
    shutil.copytree(finished.run_path, run, symlinks=True)
    shutil.copytree(finished.dataroot_path, data)
    p = finished.model_copy(update={"run_dir": str(run), "dataroot": str(data)})
    assert not_up_to_date(p) == set(), "a copy of identical data is the same world"
    pairs = pd.read_parquet(pipeline.node_dir(p, dag.Node("select")) / "pairs.parquet")
    victim = data / pairs["path_2"].iloc[len(pairs) // 2]
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])  # truncated JPEG
    before = snapshot(run)
    forced = p.model_copy(update={"force": True, "flow_methods": ["dis"]})
    with pytest.raises(ImageError, match=str(victim.name)):
        pipeline.build(forced, ["03"])
    assert snapshot(run) == before, "nothing was removed or rewritten"
    # the cut image is an edit of the world: everything below it is stale, nothing is lost
    assert not_up_to_date(p) == set(pipeline.nodes(p)) - {dag.Node("world")}
    assert "1 image(s)" in next(s.why for s in pipeline.status(p) if s.node.stage == "world")
    n_files = [f for f in before if f.suffix == ".npy" and "pool" in f.parts]
    assert n_files and all(f.is_file() for f in n_files)


def test_killed_flow_build_resumes_without_recomputing_finished_pairs(finished, tmp_path,
                                                                      monkeypatch):
    from flowmod.flow import stage

    run = tmp_path / "runs"
    p = finished.model_copy(update={"run_dir": str(run), "flow_methods": ["dis"]})
    pipeline.build(p, ["01", "02"])
    real, calls = stage._one_image_pair, []

    def dying(*args):
        if len(calls) == 3:
            raise KeyboardInterrupt("killed")
        calls.append(args[1])
        return real(*args)

    monkeypatch.setattr(stage, "_one_image_pair", dying)
    with pytest.raises(KeyboardInterrupt):
        pipeline.build(p, ["03"])
    assert pipeline.recorded(p, dag.Node("flow", "dis", "keyframe")) is None, "not published"
    first = list(calls)
    calls.clear()
    monkeypatch.setattr(stage, "_one_image_pair", lambda *a: calls.append(a[1]) or real(*a))
    pipeline.build(p, ["03"])
    assert not set(first) & set(calls), "finished pairs are not computed again"
    rec = pipeline.recorded(p, dag.Node("flow", "dis", "keyframe"))
    assert rec["computed"] == rec["pairs"] - 3
    idx = pd.read_parquet(pipeline.node_dir(p, dag.Node("flow", "dis", "keyframe")) / "index.parquet")
    assert np.isfinite(idx["seconds"]).all(), "timings of the killed run survive"
    assert json.loads((pipeline.node_dir(p, dag.Node("flow", "dis", "keyframe"))
                       / "manifest.json").read_text())["pairs"] == len(idx)


def test_gc_removes_only_what_no_node_reads(finished, tmp_path):
    """runner --gc: a fresh run has nothing to collect; after a flow option changed, the old
    option's files stay while a kept variant lists them and go with --variants; stray files
    and crops pools of other options go; every node stays up to date and readable."""
    from flowmod import runner

    run = tmp_path / "runs"
    shutil.copytree(finished.run_path, run, symlinks=True)
    p = finished.model_copy(update={"run_dir": str(run)})
    assert pipeline.unreferenced(p) == []
    # the medium flow files: chapter 11's wide flow node (stale, not rebuilt: only 03 ran)
    # still reads some of them (its keyframe pairs are the paper's image pairs)
    files = {part: {r.path(pid) for pid in r.pair_ids}
             for part in (*select.PARTS, select.WIDE) for r in [common.flow_reader(p, "dis", part)]}
    medium = files["keyframe"] | files["general"] | files[select.WIDE]
    assert len({f.parent for f in medium}) == 1, "one option folder: medium"
    n_medium = len(medium - files[select.WIDE])
    fast = p.model_copy(update={"dis_preset": "fast"})
    pipeline.build(fast, chapters=["03"])
    pool = run / "flow" / "dis" / "pool"
    assert len([d for d in pool.iterdir() if d.is_dir()]) == 2
    assert pipeline.unreferenced(fast) == [], "the medium flow is a kept variant's"
    stray = next(pool.iterdir()) / "0123456789abcdef.npy"
    stray.write_bytes(b"left by hand")
    other_crops = run / "crops" / "dis" / "pool" / "deadbeefdeadbeef"
    other_crops.mkdir(parents=True)
    (other_crops / "x.npy").write_bytes(b"crops of another geometry")
    assert set(pipeline.unreferenced(fast)) == {stray, other_crops}
    assert runner.main(["--profile", "smoke", "--set", f"run_dir={run}", "--set",
                        f"dataroot={p.dataroot}", "--set", "dis_preset=fast", "--gc",
                        "--variants", "--dry-run"]) == 0
    assert stray.exists() and other_crops.exists(), "dry run removes nothing"
    stale = not_up_to_date(fast)  # crops and below: dis_preset changed, only 03 was rebuilt
    assert {n.stage for n in stale} == {"crops", "train", "evaluate", "generalise", "xtrain",
                                        "xevaluate", "wtrain", "wgeneralise", "flow"}
    assert {n for n in stale if n.stage == "flow"} == {dag.Node("flow", "dis", select.WIDE)}
    n, _ = pipeline.collect_garbage(fast, variants=True)
    variants = 3  # the dis flow nodes' medium results, and flowcheck's (it reads them)
    assert n == 2 + variants + n_medium
    assert not stray.exists() and not other_crops.exists()
    assert {f for f in medium if f.exists()} == files[select.WIDE], "what a node reads stays"
    # the medium folder keeps the files the wide node reads (an emptied one would go)
    assert len([d for d in pool.iterdir() if d.is_dir()]) == 2
    assert not_up_to_date(fast) == stale, "nothing a node reads was removed"
    for part in select.PARTS:
        r = common.flow_reader(fast, "dis", part)
        assert all(r.load(pid).shape[2] == 2 for pid in r.pair_ids)
    # chapter 11's flow rebuilt too: the medium folder empties and goes
    pipeline.GRAPH.build_node(fast, dag.Node("flow", "dis", select.WIDE))
    n, _ = pipeline.collect_garbage(fast, variants=True)
    assert n == 1 + len(files[select.WIDE]), "the wide node's medium variant and its files"
    assert len([d for d in pool.iterdir() if d.is_dir()]) == 1, "emptied option folder removed"
    assert pipeline.collect_garbage(fast) == (0, 0)


def test_edited_world_makes_its_readers_stale_and_recomputes_flow(finished, tmp_path):
    """One annotation moved by 2 m (a still vehicle now drives 4 m/s): the world says what
    was edited, its readers are stale, and a rebuild relabels the vehicle while every pair's
    flow is reused: the image methods' keys are the two images each pair reads, the exact
    flow's the world's own description (issue 53: an edited annotation recomputed all of
    it, though no pair reads annotations)."""
    run, data = tmp_path / "runs", tmp_path / "data"
    shutil.copytree(finished.run_path, run, symlinks=True)
    shutil.copytree(finished.dataroot_path, data)
    p = finished.model_copy(update={"run_dir": str(run), "dataroot": str(data)})
    assert not_up_to_date(p) == set()
    objects = pd.read_parquet(pipeline.node_dir(p, dag.Node("select")) / "objects.parquet")
    pairs = pd.read_parquet(pipeline.node_dir(p, dag.Node("select")) / "pairs.parquet")
    still = objects[objects["label"] == 0].iloc[0]
    sample_2 = pairs.set_index("pair_id").loc[still["pair_id"], "sample_token_2"]
    table = data / p.version / "sample_annotation.json"
    anns = json.loads(table.read_text())
    ann = next(a for a in anns if a["instance_token"] == still["instance_token"]
               and a["sample_token"] == sample_2)
    ann["translation"][0] += 2.0
    table.write_text(json.dumps(anns))
    st = {s.node: s for s in pipeline.status(p)}
    assert st[dag.Node("world")].state == "up to date"
    assert "sample_annotation.json" in st[dag.Node("world")].why
    readers = {n for n in pipeline.nodes(p) if dag.Node("world") in pipeline.inputs(n, p)}
    assert {dag.Node("select"), dag.Node("flow", "dis", "keyframe")} <= readers
    assert all(st[n].why.startswith("input world changed") for n in readers), readers
    assert not_up_to_date(p) == downstream(p, readers)
    pipeline.build(p, ["01", "02", "03"])
    again = pd.read_parquet(pipeline.node_dir(p, dag.Node("select")) / "objects.parquet")
    row = again[(again["ann_token"] == still["ann_token"])].iloc[0]
    assert row["label"] == 1 and row["speed"] == pytest.approx(4.0, abs=0.1)
    for m in p.flow_methods:
        rec = pipeline.recorded(p, dag.Node("flow", m, "keyframe"))
        assert rec["computed"] == 0 and rec["pairs"] > 0, (m, rec["computed"])


def test_train_stage_chooses_the_epoch_on_validation(finished, tmp_path, monkeypatch):
    """The train stage of fold 0 hands train_model the other fold's training scenes to learn
    from, its validation scenes to choose the epoch on, and fold 0's scenes only as unscored
    record."""
    from flowmod import crops, train

    run = tmp_path / "runs"
    shutil.copytree(finished.run_path, run, symlinks=True)
    p = finished.model_copy(update={"run_dir": str(run), "force": True})
    seen, real = {}, train.train_model

    def spy(train_x, train_df, val_x, val_df, out_dir, *args, **kw):
        seen.update(train=set(zip(train_df["fold"], train_df["val_scene"], strict=True)),
                    val=set(zip(val_df["fold"], val_df["val_scene"], strict=True)),
                    record=len(kw["record"]))
        return real(train_x, train_df, val_x, val_df, out_dir, *args, **kw)

    monkeypatch.setattr(train, "train_model", spy)
    pipeline.GRAPH.build_node(p, dag.Node("train", "dis", "f0s0"))
    folder = pipeline.node_dir(p, dag.Node("crops", "dis", "keyframe"))
    assert seen == {"train": {(1, False)}, "val": {(1, True)},
                    "record": len(crops.read_crops(folder, "f0")[1])}


def test_gc_knows_the_other_generated_worlds(finished, tmp_path, capsys):
    """Worlds of other parameters live beside this profile's under the dataroot: --gc says
    so, --gc --worlds removes them and never this profile's."""
    from flowmod import runner

    data = tmp_path / "data"
    shutil.copytree(finished.path(finished.dataroot), data)
    other = data / "worlds" / "0123456789abcdef"
    (other / "v1.0-synth").mkdir(parents=True)
    (other / "v1.0-synth" / "scene.json").write_text("[]")
    args = ["--profile", "smoke", "--gc", "--set", f"run_dir={finished.run_dir}",
            "--set", f"dataroot={data}"]
    assert runner.main(args) == 0
    assert "1 other generated world(s)" in capsys.readouterr().out and other.is_dir()
    assert runner.main([*args, "--worlds"]) == 0
    own = finished.model_copy(update={"dataroot": str(data)}).dataroot_path
    assert not other.exists() and (own / "v1.0-synth" / "scene.json").is_file()


def test_published_files_are_readable_as_the_umask_allows(tmp_path):
    """Issue 41: mkstemp's 0600 survived the rename, so other users of a shared run folder
    or dataroot could not read any artefact."""
    import os

    import numpy as np

    from flowmod.artefacts import atomic_path, write_json

    old = os.umask(0o022)
    try:
        write_json(tmp_path / "a.json", {"x": 1})
        with atomic_path(tmp_path / "b.npy") as tmp:
            np.save(tmp, np.zeros(3))
        assert {oct(p.stat().st_mode & 0o777) for p in tmp_path.iterdir()} == {"0o644"}
        os.umask(0o077)
        write_json(tmp_path / "c.json", {"x": 1})
        assert (tmp_path / "c.json").stat().st_mode & 0o777 == 0o600
    finally:
        os.umask(old)


def test_an_edit_of_a_stages_code_makes_exactly_it_and_its_readers_stale(finished, tmp_path):
    """Issue 53: the crop window scaled by 1.25 in a scratch copy of the package. Its status
    (in a process that imports the copy) names the edited file for every stage whose code
    imports crops.py, their readers wait for them, and nothing else is stale; the copy
    unedited is up to date (a digest is of the code, never of where it lives)."""
    import subprocess
    import sys

    from flowmod import codedigest

    src = tmp_path / "src"
    shutil.copytree(codedigest.PACKAGE_ROOT, src / "flowmod",
                    ignore=shutil.ignore_patterns("__pycache__"))
    script = ("import json, sys; from flowmod import pipeline; from flowmod.params import Params; "
              "p = Params.model_validate_json(sys.argv[1]); "
              "print(json.dumps({str(s.node): [s.state, s.why] for s in pipeline.status(p)}))")

    def status() -> dict[str, list[str]]:
        out = subprocess.run([sys.executable, "-c", script, finished.model_dump_json()],
                             capture_output=True, text=True, check=True,
                             env={**os.environ, "PYTHONPATH": str(src)})
        return json.loads(out.stdout)

    assert {state for state, _ in status().values()} == {"up to date"}
    crops_py = src / "flowmod" / "crops.py"
    text = crops_py.read_text()
    line = "    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)\n"
    assert text.count(line) == 1
    crops_py.write_text(text.replace(line, line + "    scale = scale * 1.25\n", 1))
    st = status()
    edited = {n for n in pipeline.nodes(finished)
              if "crops.py" in pipeline.GRAPH.stage(n).code()}
    assert {dag.Node("crops", "dis", "keyframe"), dag.Node("train", "dis", "f0s0")} <= edited
    assert {n for n, (state, _) in st.items() if state != "up to date"} == {
        str(n) for n in downstream(finished, edited)}
    assert st["crops[dis/keyframe]"][1].startswith("code changed since built: crops.py")
    for n in ("world", "select", "flow[dis/keyframe]", "shipped"):
        assert st[n] == ["up to date", ""], n


def test_a_damaged_flow_pool_file_is_named_and_recomputed_never_cropped(finished, tmp_path):
    """Issue 53: one pool file zeroed in place left status silent and a crops rebuild
    (crop_size=32) published all-zero crops; a deleted one gave a raw FileNotFoundError.
    Now the flow node names the file, no crops are built from it, and a run recomputes that
    pair alone, byte for byte."""
    run = tmp_path / "runs"
    shutil.copytree(finished.run_path, run, symlinks=True)
    p = finished.model_copy(update={"run_dir": str(run)})
    node = dag.Node("flow", "dis", "keyframe")
    idx = pd.read_parquet(pipeline.node_dir(p, node) / "index.parquet")
    victim = run / "flow" / "dis" / "pool" / idx["file"].iloc[1]
    good = victim.read_bytes()
    header = len(good) - int(np.prod(np.load(victim, mmap_mode="r").shape)) * 2
    victim.write_bytes(good[:header] + bytes(len(good) - header))
    st = {s.node: s for s in pipeline.status(p)}
    assert st[node].state == "damaged" and st[node].why.startswith(
        f"{victim} changed since it was built (same size, other content)")
    smaller = p.model_copy(update={"crop_size": 32})
    with pytest.raises(dag.MissingInput, match="crops\\[dis/keyframe\\] reads flow\\[dis/"
                                               "keyframe\\], whose files are damaged"):
        pipeline.build(smaller, ["05"])
    pipeline.build(p, ["03", "05"])  # the gt crops built at 32 px before the refusal: restored
    assert pipeline.recorded(p, node)["computed"] == 1 and victim.read_bytes() == good
    victim.unlink()
    assert pipeline.damaged(p, node) == f"{victim} is missing"
    pipeline.build(p, ["03"])
    assert victim.read_bytes() == good and not_up_to_date(p) == set()
