"""The engine on a toy study (no world, no devkit): declarations, fingerprints, status, the
driver, kept variants, gates. Seconds; the real stages are checked in test_provenance."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Any

import pytest

from flowmod import artefacts, dag
from flowmod.artefacts import atomic_path
from flowmod.params import Params, validate

# Toy stages borrow real stage names, so that they read the parameters ``read_by`` declares
# for those names: "select" reads min_distance, "train" reads epochs, "xtrain" is gated.


class Data:
    """A toy source: a file whose content is the data's identity."""

    def __init__(self, name: str) -> None:
        self.name = name

    def location(self, p: Params) -> Path:
        return Path(p.dataroot)

    def fingerprint(self, p: Params) -> str | None:
        f = self.location(p) / self.name
        return f.read_text() if f.is_file() else None

    def record(self, p: Params) -> dict[str, Any] | None:
        fp = self.fingerprint(p)
        return {"fingerprint": fp} if fp else None

    def status(self, p: Params) -> tuple[str, str]:
        return ("up to date", "") if self.fingerprint(p) else ("missing", "no data")

    def ensure(self, p: Params, progress: bool) -> None:
        f = self.location(p) / self.name
        if not f.is_file():
            f.parent.mkdir(parents=True, exist_ok=True)
            f.write_text("v1")


CALLS: list[str] = []


def build_select(b: dag.Build, progress: bool) -> dict[str, Any]:
    CALLS.append(str(b.node))
    data = (b.input_dir(dag.Node("world")) / "data.txt").read_text()
    (b.start(fresh=True) / "out.json").write_text(json.dumps(
        {"data": data, "min_distance": b.params.min_distance}))
    return {"rows": 1}


def build_train(b: dag.Build, progress: bool) -> dict[str, Any]:
    CALLS.append(str(b.node))
    src = json.loads((b.input_dir(dag.Node("select")) / "out.json").read_text())
    (b.start(fresh=True) / "model.json").write_text(json.dumps({**src, "epochs": b.params.epochs,
                                                                "k": b.node.part}))
    return {}


def build_x(b: dag.Build, progress: bool) -> dict[str, Any]:
    CALLS.append(str(b.node))
    (b.start(fresh=True) / "x.json").write_text(
        (b.input_dir(dag.Node("train", None, "s0")) / "model.json").read_text())
    return {}


def build_reads_too_much(b: dag.Build, progress: bool) -> dict[str, Any]:
    return {"lr": b.params.lr}  # "select" does not declare lr


def graph(tmp: Path, select_build=build_select) -> dag.Graph:
    return dag.Graph([
        dag.Stage("world", 1, "01", "", "the toy data", nodes=lambda p: [dag.Node("world")],
                  source=Data("data.txt")),
        dag.Stage("train", 1, "06", "models/{part}", "one model per seed",
                  nodes=lambda p: [dag.Node("train", None, f"s{k}") for k in range(p.seeds)],
                  inputs=lambda n, p: (dag.Node("select"),), build=build_train),
        dag.Stage("select", 1, "02", "select", "the selection",
                  nodes=lambda p: [dag.Node("select")],
                  inputs=lambda n, p: (dag.Node("world"),), build=select_build),
        dag.Stage("xtrain", 1, "10", "extra", "a gated model", gate="extension_build",
                  nodes=lambda p: [dag.Node("xtrain")],
                  inputs=lambda n, p: (dag.Node("train", None, "s0"),), build=build_x),
    ], {"extension_build": "make extensions"})


@pytest.fixture
def toy(tmp_path: Path) -> tuple[dag.Graph, Params]:
    CALLS.clear()
    p = validate({"run_dir": str(tmp_path / "runs"), "dataroot": str(tmp_path / "data"),
                  "seeds": 2, "folds": 1, "synthetic": False, "extension_build": False})
    return graph(tmp_path), p


def states(g: dag.Graph, p: Params) -> dict[str, str]:
    return {str(s.node): s.state for s in g.status(p)}


def test_nodes_come_by_chapter_each_after_its_inputs(toy):
    g, p = toy
    # "train" is declared before "select": the order follows the data, not the declaration
    assert [str(n) for n in g.nodes(p)] == ["world", "select", "train[s0]", "train[s1]",
                                             "xtrain"]
    assert [str(n) for n in g.nodes(p, ["06"])] == ["train[s0]", "train[s1]"]
    assert g.chapter(dag.Node("xtrain")) == "10" and g.gate(dag.Node("xtrain")) == "extension_build"


def test_build_then_nothing_stale_then_exactly_the_readers_of_a_change(toy, tmp_path):
    g, p = toy
    assert states(g, p)["world"] == "missing"
    assert states(g, p)["select"] == "missing"
    g.build(p)
    assert CALLS == ["select", "train[s0]", "train[s1]"], "the gated node is not built"
    assert set(states(g, p).values()) == {"up to date", "missing"}
    assert states(g, p)["xtrain"] == "missing"
    CALLS.clear()
    g.build(p)
    assert CALLS == [], "nothing is rebuilt when nothing changed"
    # a parameter: its reader and what reads it
    q = p.model_copy(update={"min_distance": 25.0})
    st = {str(s.node): s for s in g.status(q)}
    assert st["select"].state == "stale" and "min_distance: 30.0 -> 25.0" in st["select"].why
    assert st["train[s0]"].why == "input select is stale"
    # a parameter nobody reads here (run settings are free): nothing
    assert states(g, p.model_copy(update={"n_jobs": 7})) == states(g, p)
    # another training parameter: only the models
    e = p.model_copy(update={"epochs": 3})
    assert {k for k, v in states(g, e).items() if v == "stale"} == {"train[s0]", "train[s1]"}
    # the data: everything below it
    (tmp_path / "data" / "data.txt").write_text("v2")
    st = {str(s.node): s for s in g.status(p)}
    assert st["select"].why == "input world changed"
    assert {k for k, s in st.items() if s.state == "stale"} == {"select", "train[s0]",
                                                                  "train[s1]"}


def test_switching_back_restores_a_kept_variant_without_building(toy):
    g, p = toy
    g.build(p)
    q = p.model_copy(update={"min_distance": 25.0})
    g.build(q)
    out = json.loads((g.node_dir(p, dag.Node("select")) / "out.json").read_text())
    assert out["min_distance"] == 25.0
    CALLS.clear()
    assert whys(g, p)["select"] == ("min_distance: 25.0 -> 30.0; a kept copy matches and "
                                    "will be restored, nothing recomputed")
    g.build(p)
    assert CALLS == [], "restored, not recomputed"
    out = json.loads((g.node_dir(p, dag.Node("select")) / "out.json").read_text())
    assert out["min_distance"] == 30.0
    # at most KEEP_VARIANTS earlier results are kept per node
    for d in (26.0, 27.0, 28.0, 29.0):
        g.build(p.model_copy(update={"min_distance": d}))
    kept = list(g.node_dir(p, dag.Node("select")).parent.glob(".select.variant-*"))
    assert len(kept) == dag.KEEP_VARIANTS


def test_a_failed_build_keeps_the_published_result_and_its_fingerprint(toy, tmp_path):
    g, p = toy
    g.build(p)
    before = (g.node_dir(p, dag.Node("select")) / "out.json").read_text()

    def failing(b: dag.Build, progress: bool) -> dict[str, Any]:
        (b.start() / "half.json").write_text("{")
        raise RuntimeError("disk full")

    bad = graph(tmp_path, select_build=failing)
    q = p.model_copy(update={"min_distance": 25.0})
    with pytest.raises(RuntimeError, match="disk full"):
        bad.build(q)
    assert (g.node_dir(p, dag.Node("select")) / "out.json").read_text() == before
    assert states(g, p)["select"] == "up to date", "the old result is still the published one"
    building = list(g.node_dir(p, dag.Node("select")).parent.glob(".select.building-*"))
    assert len(building) == 1 and (building[0] / "half.json").is_file(), "kept to resume"



def test_a_resumed_build_publishes_without_a_killed_writer_s_temporary_file(toy, tmp_path):
    """A build killed inside :func:`~flowmod.artefacts.atomic_path` (a dead joblib worker)
    leaves its hidden temporary file in the building folder; the build that resumes there
    publishes without it (and keeps what the killed build finished)."""
    g, p = toy
    with atomic_path(tmp_path / "x" / "best.pt") as tmp:
        assert artefacts.leftover_temporaries(tmp_path / "x") == [tmp], "what it matches"

    def killed(b: dag.Build, progress: bool) -> dict[str, Any]:
        (b.start() / "done.json").write_text("{}")
        (b.dir / "sub").mkdir()
        (b.dir / "sub" / ".half.k3j9_x.tmp.json").write_text("{")  # atomic_path's name
        raise RuntimeError("killed")

    def resumes(b: dag.Build, progress: bool) -> dict[str, Any]:
        assert (b.start() / "done.json").is_file(), "the killed build's folder, resumed"
        (b.dir / "out.json").write_text("{}")
        return {}

    with pytest.raises(RuntimeError, match="killed"):
        graph(tmp_path, select_build=killed).build(p, ["01", "02"])
    graph(tmp_path, select_build=resumes).build(p, ["01", "02"])
    final = g.node_dir(p, dag.Node("select"))
    assert sorted(f.relative_to(final).as_posix() for f in final.rglob("*") if f.is_file()) \
        == ["done.json", "manifest.json", "out.json"]

def test_a_damaged_published_file_is_reported_and_rebuilt(toy):
    """Manifests record each output's size and sha256: a file cut short, changed in place
    (same size) or removed makes its node "damaged" (status names the file), no longer
    current, and rebuilt by the next build; nothing of it is kept as a variant (issue 41)."""
    import os

    g, p = toy
    g.build(p)
    node = dag.Node("select")
    folder = g.node_dir(p, node)
    out = folder / "out.json"
    good = out.read_bytes()
    rec = g.recorded(p, node)
    assert rec["files"] == {"out.json": {"size": len(good), "sha256": dag.file_digest(out)}}
    assert g.current(p, node) and dag.damage(folder, rec) is None
    for harm, words in (
            (lambda: out.write_bytes(good[:-3]), f"bytes, {len(good)} when it was built"),
            (lambda: out.write_bytes(good.replace(b"v1", b"v7")), "same size, other content"),
            (lambda: out.unlink(), "out.json is missing")):
        harm()
        st = {str(s.node): s for s in g.status(p)}["select"]
        assert st.state == "damaged" and str(out) in st.why and words in st.why, st.why
        assert not g.current(p, node)
        CALLS.clear()
        g.build(p, ["02"])
        assert CALLS == ["select"] and out.read_bytes() == good
        assert states(g, p)["select"] == "up to date"
    assert not list(folder.parent.glob(".select.variant-*")), "a damaged copy is not kept"
    os.utime(out, ns=(1, 1))  # a new time alone, same bytes: read again, still intact
    assert states(g, p)["select"] == "up to date"


def test_force_rebuilds_and_a_missing_input_names_the_chapter(toy):
    g, p = toy
    with pytest.raises(dag.MissingInput, match=r"train\[s0\] reads select.*chapter 02"):
        g.build(p, ["06"])
    g.build(p)
    CALLS.clear()
    g.build(p.model_copy(update={"force": True}), ["06"])
    assert CALLS == ["train[s0]", "train[s1]"]
    with pytest.raises(dag.MissingInput, match="extension_build=true.*make extensions"):
        g.published(p, dag.Node("xtrain"))
    g.build(p.model_copy(update={"extension_build": True}))
    assert CALLS[-1] == "xtrain"


def test_fingerprints_hash_stage_version_node_parameters_and_inputs(toy):
    g, p = toy
    g.build(p)
    rec = g.recorded(p, dag.Node("train", None, "s1"))
    assert rec["stage"] == "train" and rec["node"] == "train[s1]" and rec["version"] == 1
    assert rec["params"]["epochs"] == p.epochs and "min_distance" not in rec["params"]
    assert rec["inputs"] == {"select": g.recorded(p, dag.Node("select"))["fingerprint"]}
    assert rec["fingerprint"] == g.expected(p)[dag.Node("train", None, "s1")]
    assert g.current(p, dag.Node("train", None, "s1")) and g.built(p, dag.Node("train", None, "s1"))
    # another seed's node differs, the same node of another run folder does not
    assert rec["fingerprint"] != g.recorded(p, dag.Node("train", None, "s0"))["fingerprint"]
    v2 = dag.Graph([dataclass_replace(s, version=2) if s.name == "train" else s
                    for s in g.stages.values()], g.gate_targets)
    assert "code version 1 -> 2" in {str(s.node): s.why for s in v2.status(p)}["train[s0]"]


def dataclass_replace(stage: dag.Stage, **kw: Any) -> dag.Stage:
    from dataclasses import replace

    return replace(stage, **kw)


def test_stale_nodes_of_parallel_stages_go_to_at_once_in_runs_that_read_no_other(tmp_path):
    """With ``at_once``, each run of consecutive nodes of parallel stages, none reading
    another of the run, goes to it when two or more are stale (only the stale ones);
    everything else is built here, in data order."""
    g0 = graph(tmp_path)
    g = dag.Graph([dataclass_replace(s, parallel=s.name in ("train", "xtrain"))
                   for s in g0.stages.values()], g0.gate_targets)
    p = validate({"run_dir": str(tmp_path / "runs"), "dataroot": str(tmp_path / "data"),
                  "seeds": 3, "folds": 1, "synthetic": False, "extension_build": True})
    CALLS.clear()
    batches: list[list[str]] = []

    def at_once(todo: list[dag.Node]) -> None:
        batches.append([str(n) for n in todo])
        for n in reversed(todo):  # any order: none reads another
            g.build_node(p, n)

    g.build(p, at_once=at_once)
    # xtrain reads train[s0], so it starts a run of its own (alone: built here)
    assert batches == [["train[s0]", "train[s1]", "train[s2]"]]
    assert CALLS == ["select", "train[s2]", "train[s1]", "train[s0]", "xtrain"]
    assert set(states(g, p).values()) == {"up to date"}
    batches.clear()
    g.build(p, at_once=at_once)
    assert batches == [], "nothing stale: nothing to build at once"
    for k in (0, 2):
        shutil.rmtree(g.node_dir(p, dag.Node("train", None, f"s{k}")))
    CALLS.clear()
    g.build(p, at_once=at_once)
    assert batches == [["train[s0]", "train[s2]"]], "only the stale ones"
    assert CALLS == ["train[s2]", "train[s0]"], "their fingerprints are as before: xtrain stays"
    shutil.rmtree(g.node_dir(p, dag.Node("train", None, "s1")))
    CALLS.clear()
    batches.clear()
    g.build(p, at_once=at_once)
    assert batches == [] and CALLS == ["train[s1]"], "one stale node is built here"
    CALLS.clear()
    g.build(p.model_copy(update={"epochs": 3}))
    assert CALLS == ["train[s0]", "train[s1]", "train[s2]", "xtrain"], "no at_once: in order"


def test_a_stage_reading_an_undeclared_parameter_fails(toy, tmp_path):
    g, p = toy
    bad = graph(tmp_path, select_build=build_reads_too_much)
    with pytest.raises(dag.UndeclaredParameter, match=r"^stage select read parameter 'lr', "
                       r"which it does not declare: add 'select' to read_by of Params\.lr "
                       r"\(flowmod/params\.py\), so that its fingerprint follows the value$"):
        bad.build(p)


def test_after_publish_runs_once_the_result_is_in_place(toy, tmp_path):
    seen = []

    def build(b: dag.Build, progress: bool) -> dict[str, Any]:
        (b.start() / "out.json").write_text("{}")
        b.after_publish(lambda: seen.append((b.final / "out.json").is_file()))
        return {}

    g, p = toy
    graph(tmp_path, select_build=build).build(p, ["01", "02"])
    assert seen == [True]


def test_node_names_and_the_parameters_a_node_reads():
    assert str(dag.Node("flow", "dis", "keyframe")) == "flow[dis/keyframe]"
    assert str(dag.Node("train", None, "s0")) == "train[s0]" and str(dag.Node("select")) == "select"
    # a method's own parameter is read by that method's nodes only
    assert "dis_preset" in dag.reads(dag.Node("flow", "dis", "keyframe"))
    assert "dis_preset" not in dag.reads(dag.Node("flow", "gt", "keyframe"))
    assert "flow_dtype" in dag.reads(dag.Node("flow", "gt", "keyframe"))


def test_diff_names_the_first_changed_keys_then_counts_the_rest():
    old, new = {"a": 1, "b": 2, "c": 3, "d": 4, "e": 5}, {"a": 1, "b": 9, "c": 8, "d": 7, "e": 6}
    assert dag.diff(old, new) == ["b: 2 -> 9", "c: 3 -> 8", "d: 4 -> 7", "(+1 more)"]
    assert dag.diff(old, new, n=4) == ["b: 2 -> 9", "c: 3 -> 8", "d: 4 -> 7", "e: 5 -> 6"]
    assert dag.diff(old, new, n=1) == ["b: 2 -> 9", "(+3 more)"]
    # a key on one side only shows '-' on the other
    assert dag.diff({"gone": 1, "same": 1}, {"new": "x", "same": 1}) == [
        "gone: 1 -> '-'", "new: '-' -> 'x'"]
    assert dag.diff({"k": "x" * 50}, {"k": 1}) == [f"k: '{'x' * 36}... -> 1"]


def build_empty(b: dag.Build, progress: bool) -> dict[str, Any]:
    b.start(fresh=True)
    return {}


def fan_in_graph(tmp: Path) -> dag.Graph:
    """The toy graph plus a node reading every seed's model and a stage with a part that
    belongs to another chapter (behind a gate)."""
    g = graph(tmp)
    return dag.Graph([*g.stages.values(),
                      dag.Stage("evaluate", 1, "07", "eval", "reads every seed",
                                nodes=lambda p: [dag.Node("evaluate")],
                                inputs=lambda n, p: tuple(dag.Node("train", None, f"s{k}")
                                                          for k in range(p.seeds)),
                                build=build_empty),
                      dag.Stage("wide", 1, "02", "wide/{part}", "a part elsewhere",
                                nodes=lambda p: [dag.Node("wide", None, "near"),
                                                 dag.Node("wide", None, "far")],
                                parts={"far": ("11", "extension_build")}, build=build_empty)],
                     g.gate_targets)


def whys(g: dag.Graph, p: Params) -> dict[str, str]:
    return {str(s.node): s.why for s in g.status(p)}


def test_status_says_exactly_why_each_node_is_not_up_to_date(tmp_path):
    p = validate({"run_dir": str(tmp_path / "runs"), "dataroot": str(tmp_path / "data"),
                  "seeds": 2, "folds": 1, "synthetic": False})
    g = fan_in_graph(tmp_path)
    assert g.chapter(dag.Node("wide", None, "far")) == "11" != g.chapter(
        dag.Node("wide", None, "near")) == "02"
    assert g.gate(dag.Node("wide", None, "far")) == "extension_build"
    assert g.gate(dag.Node("wide", None, "near")) is None
    assert whys(g, p)["select"] == "never built; waits for world"
    assert g.expected(p)[dag.Node("select")] is None, "below missing data: no fingerprint"
    g.build(p, ["01"])
    assert whys(g, p)["select"] == "never built"
    g.build(p, ["01", "02", "06", "07"])
    # one parameter: its reader names it, nothing else
    q = p.model_copy(update={"min_distance": 25.0})
    assert whys(g, q)["select"] == "min_distance: 30.0 -> 25.0"
    assert whys(g, q)["evaluate"] == "input train[s0] is stale; (+1 more inputs)"
    # one step up only: the models still match the published selection
    assert g.current(q, dag.Node("train", None, "s0")) and not g.current(q, dag.Node("select"))
    # the data gone: its reader's input is missing, the rest below is stale
    (tmp_path / "data" / "data.txt").unlink()
    st = whys(g, p)
    assert st["select"] == "input world is missing" and st["train[s0]"] == "input select is stale"


def test_expected_of_chosen_nodes_reads_their_inputs_manifests(toy):
    g, p = toy
    s0 = dag.Node("train", None, "s0")
    assert g.expected(p, [s0]) == {s0: None}, "an input never built: no fingerprint"
    g.build(p)
    assert g.expected(p, [s0]) == {s0: g.recorded(p, s0)["fingerprint"]}


def test_a_node_s_results_are_its_published_folder_then_its_variants_newest_first(tmp_path):
    """dag.results: the published folder and the kept variants that hold a manifest, newest
    manifest first (what a rebuild may restore from)."""
    import os

    final = tmp_path / "crops"
    dirs = {name: tmp_path / name for name in
            ("crops", ".crops.variant-a", ".crops.variant-b", ".crops.variant-c")}
    for i, (name, d) in enumerate(dirs.items()):
        d.mkdir()
        if name != ".crops.variant-c":  # no manifest: not a result
            (d / "manifest.json").write_text(json.dumps({"fingerprint": name}))
            os.utime(d / "manifest.json", (1000 + i, 1000 + i))
    assert dag.results(final) == [final, dirs[".crops.variant-b"], dirs[".crops.variant-a"]]
    (final / "manifest.json").unlink()
    assert dag.results(final) == [dirs[".crops.variant-b"], dirs[".crops.variant-a"]]


def test_a_building_folder_goes_only_when_its_block_raises(tmp_path):
    kept = tmp_path / "kept"
    kept.mkdir()
    with dag.removed_on_error(kept) as d:
        assert d == kept
    assert kept.is_dir()
    with pytest.raises(KeyboardInterrupt), dag.removed_on_error(kept):
        raise KeyboardInterrupt
    assert not kept.exists()


def test_a_node_s_parameters_are_read_only_and_other_nodes_are_found_by_the_graph():
    from types import SimpleNamespace

    p = validate({"profile": "smoke"})
    q = dag.StageParams(p, dag.Node("train", "dis", "f0"))
    with pytest.raises(AttributeError, match="parameters are read-only"):
        q.epochs = 3
    assert q.epochs == p.epochs
    graph = SimpleNamespace(node_dir=lambda params, node: ("dir", params is p, str(node)))
    b = dag.Build(graph=graph, node=dag.Node("train", "dis", "f0"), params=q, inputs={},
                  payload={}, fingerprint="f", final=Path("/r/x"), up_to_date=False)
    assert b.other(dag.Node("crops", "dis", "wide")) == ("dir", True, "crops[dis/wide]")


def test_status_lines_carry_the_node_s_folder_and_both_fingerprints(toy):
    g, p = toy
    assert not g.current(p, dag.Node("select")), "never built"
    g.build(p)
    for st in g.status(p):
        if st.node.stage not in ("select", "train"):  # the data; the gated node
            continue
        rec = g.recorded(p, st.node)
        assert (st.state, st.why, st.path) == ("up to date", "", g.node_dir(p, st.node))
        assert st.fingerprint == g.expected(p)[st.node] == st.recorded == rec["fingerprint"]


def test_old_or_odd_manifests_are_stale_with_a_reason(toy):
    """A manifest of an older version without params and inputs, or one whose fingerprint
    alone differs, makes its node stale with a reason, not a crash."""
    g, p = toy
    g.build(p)
    path = g.node_dir(p, dag.Node("select")) / "manifest.json"
    rec = json.loads(path.read_text())
    path.write_text(json.dumps({**rec, "fingerprint": "other"}))
    assert whys(g, p)["select"] == "fingerprint differs"
    old = {k: v for k, v in rec.items() if k not in ("params", "inputs")}
    path.write_text(json.dumps({**old, "fingerprint": "other", "version": 0}))
    why = whys(g, p)["select"]
    assert why.startswith("code version 0 -> 1; categories: '-' -> ['vehicle.car', ")
    assert re.search(r"; \(\+\d+ more\); input world changed$", why), why


def test_damage_checks_the_files_a_manifest_records_through_the_run_s_digest_cache(toy):
    """damaged() reads the manifest itself when not given; status, current and damaged
    keep the run's digest cache (a file is read again only when its stat changed); a
    manifest that records no files has no damage; the published files are every file but
    the manifest and hidden ones."""
    from flowmod import artefacts

    g, p = toy
    g.build(p)
    node = dag.Node("select")
    folder = g.node_dir(p, node)
    assert dag.damage(folder, {"fingerprint": "x"}) is None
    for call in (lambda: g.status(p), lambda: g.current(p, node), lambda: g.damaged(p, node)):
        dag.digest_cache(p).unlink(missing_ok=True)
        artefacts._DIGESTS.clear()
        call()
        assert str((folder / "out.json").resolve()) in json.loads(
            dag.digest_cache(p).read_text())
    (folder / "out.json").write_text("cut")
    assert "out.json has 3 bytes" in g.damaged(p, node)
    (folder / ".hidden").write_text("x")
    (folder / "sub").mkdir()
    (folder / "sub" / "b.txt").write_text("b")
    (folder / "sub" / ".c").write_text("c")
    assert sorted(dag.output_files(folder)) == ["out.json", "sub/b.txt"]


def test_parameter_values_are_shortened_past_forty_characters():
    assert dag._short("x" * 38) == repr("x" * 38)  # 40 characters: as they are
    assert dag._short("x" * 39) == repr("x" * 39)[:37] + "..."


def test_reading_a_node_that_is_not_an_input_names_the_fix(toy):
    from types import SimpleNamespace

    g, p = toy
    b = dag.Build(graph=g, node=dag.Node("train", None, "s0"), params=SimpleNamespace(all=p),
                  inputs={"select": {}}, payload={}, fingerprint="f", final=Path("/r/x"),
                  up_to_date=False)
    assert b.input_dir(dag.Node("select")) == g.node_dir(p, dag.Node("select"))
    with pytest.raises(KeyError, match=r"train\[s0\] does not read world: add it to its "
                                       r"stage's inputs"):
        b.input_dir(dag.Node("world"))


def test_a_file_parameter_enters_a_fingerprint_by_its_content(tmp_path):
    """values(): a file parameter contributes its file's sha256 (through the run's digest
    cache), a path that does not exist says so, and an unset one without a default file is
    None."""
    import hashlib

    from flowmod import artefacts

    weights = tmp_path / "w.pth"
    weights.write_bytes(b"weights")
    p = validate({"run_dir": str(tmp_path / "runs"), "dataroot": str(tmp_path / "data"),
                  "synthetic": False, "raft_weights": str(weights)})
    node = dag.Node("flow", "raft", "keyframe")
    artefacts._DIGESTS.clear()
    (tmp_path / "runs").mkdir()
    assert dag.values(p, node)["raft_weights"] == {"sha256": hashlib.sha256(b"weights").hexdigest()}
    assert str(weights.resolve()) in json.loads(dag.digest_cache(p).read_text())
    assert dag.digest_cache(p) == tmp_path / "runs" / ".digests.json"
    gone = str(tmp_path / "gone.pth")
    assert dag.values(p.model_copy(update={"raft_weights": gone}), node)["raft_weights"] == {
        "missing": gone}
    assert dag.values(p.model_copy(update={"raft_weights": None}), node)["raft_weights"] is None


def test_the_study_s_graph_gives_each_node_its_own_inputs(tmp_path):
    from flowmod import pipeline

    p = validate({"run_dir": str(tmp_path / "runs"), "flow_store": "pairs"})
    assert pipeline.GRAPH.inputs(dag.Node("crops", "dis", "general"), p) == (
        dag.Node("flow", "dis", "general"), dag.Node("general"))
    assert pipeline.GRAPH.inputs(dag.Node("crops", "gt", "keyframe"), p) == (
        dag.Node("flow", "gt", "keyframe"), dag.Node("select"))


def test_published_digests_can_go_through_a_cache_and_a_file_without_default_stays_none(
        tmp_path, monkeypatch):
    from flowmod import artefacts

    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "a.txt").write_text("a")
    artefacts._DIGESTS.clear()
    files = dag.output_files(tmp_path / "out", tmp_path / "cache.json")
    assert list(files) == ["a.txt"]
    assert str((tmp_path / "out" / "a.txt").resolve()) in json.loads(
        (tmp_path / "cache.json").read_text())
    # an unset file parameter whose default file nobody registered (the flow networks
    # register theirs when imported)
    monkeypatch.delitem(dag.FILE_DEFAULTS, "raft_weights", raising=False)
    p = validate({"run_dir": str(tmp_path / "runs"), "raft_weights": None})
    assert dag.values(p, dag.Node("flow", "raft", "keyframe"))["raft_weights"] is None


def test_a_digest_batch_writes_each_stat_cache_once_with_only_its_own_files(
        tmp_path, monkeypatch):
    """Inside :func:`artefacts.digest_batch` a stat cache is written once, when the
    outermost block ends (a status check wrote it after every node: hundreds of rewrites of
    a growing file); each cache holds the files it was asked about, not every digest the
    process knows (a test worker's caches grew with every run folder it had seen)."""
    import hashlib

    from flowmod import artefacts

    files = [tmp_path / f"{k}.bin" for k in "abc"]
    for f in files:
        f.write_bytes(f.name.encode())
    other = tmp_path / "elsewhere.bin"
    other.write_bytes(b"x")
    artefacts.file_digest(other, tmp_path / "other.json")
    cache, writes = tmp_path / "run.json", []
    real = artefacts.write_json
    monkeypatch.setattr(artefacts, "write_json", lambda p, o: (writes.append(p), real(p, o)))
    with artefacts.digest_batch():
        with artefacts.digest_batch():
            for f in files:
                artefacts.file_digest(f, cache)
        assert writes == [] and not cache.exists(), "nothing written inside the batch"
    assert writes == [str(cache)]
    entries = json.loads(cache.read_text())
    assert {k: v[3] for k, v in entries.items()} == {
        str(f.resolve()): hashlib.sha256(f.name.encode()).hexdigest() for f in files}
    with artefacts.digest_batch():
        artefacts.file_digests(files, cache)
    assert writes == [str(cache)], "nothing new: not written again"
    artefacts.file_digest(other, cache)  # known to the process, new to this cache
    assert writes == [str(cache)] * 2 and str(other.resolve()) in json.loads(cache.read_text())


def test_a_status_check_writes_the_run_s_digest_cache_once(toy, monkeypatch):
    from flowmod import artefacts

    g, p = toy
    g.build(p)
    dag.digest_cache(p).unlink()
    artefacts._DIGESTS.clear()
    writes = []
    real = artefacts.write_json
    monkeypatch.setattr(artefacts, "write_json", lambda f, o: (writes.append(f), real(f, o)))
    assert {s.state for s in g.status(p)} == {"up to date", "missing"}
    assert writes == [str(dag.digest_cache(p))]
    assert len(json.loads(dag.digest_cache(p).read_text())) >= 2


def test_an_edit_whose_mtime_is_put_back_is_still_seen(tmp_path):
    """Issue 53: the stat cache was keyed by size and mtime, so a same-size edit with its
    mtime restored (``touch -d``, ``os.utime``) kept the old digest and passed as up to
    date. The ctime, which no user call can set back, is in the key."""
    import hashlib
    import os

    from flowmod import artefacts

    f, cache = tmp_path / "crops.npy", tmp_path / ".digests.json"
    f.write_bytes(b"\x01" * 64)
    st = f.stat()
    assert artefacts.file_digest(f, cache) == hashlib.sha256(b"\x01" * 64).hexdigest()
    f.write_bytes(b"\x00" * 64)
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert f.stat().st_mtime_ns == st.st_mtime_ns and f.stat().st_size == st.st_size
    assert artefacts.file_digest(f, cache) == hashlib.sha256(b"\x00" * 64).hexdigest()
    assert dag.damage(tmp_path, {"files": {"crops.npy": {
        "size": 64, "sha256": hashlib.sha256(b"\x01" * 64).hexdigest()}}}, cache) == (
        f"{f} changed since it was built (same size, other content)")


@pytest.mark.parametrize("text", ['["not", "a", "dict"]', '{"/x": 5}', '{"/x": [1, 2, "h"]}',
                                  '{"/x": [1, 2, 3, 4]}', "{cut"])
def test_a_malformed_digest_cache_is_ignored_and_rewritten(toy, text):
    """Issue 53: a ``.digests.json`` of the wrong shape crashed ``--status`` with a
    TypeError; it is ignored (every file read again) and rewritten well-formed."""
    from flowmod import artefacts

    g, p = toy
    g.build(p)
    artefacts._DIGESTS.clear()
    artefacts._LOADED.clear()
    dag.digest_cache(p).write_text(text)
    assert {s.state for s in g.status(p)} == {"up to date", "missing"}
    entries = json.loads(dag.digest_cache(p).read_text())
    out = str((g.node_dir(p, dag.Node("select")) / "out.json").resolve())
    assert "/x" not in entries and len(entries[out]) == 4 and len(entries[out][3]) == 64


def build_pooled(b: dag.Build, progress: bool) -> dict[str, Any]:
    """A toy select whose result lists a file of a per-pair cache outside its folder."""
    CALLS.append(str(b.node))
    pool = b.params.all.run_path / "pool"
    pool.mkdir(parents=True, exist_ok=True)
    (pool / "a.npy").write_bytes(b"flow")
    (b.start(fresh=True) / "out.json").write_text(json.dumps({"file": "a.npy"}))
    b.cached([pool / "a.npy"])
    return {}


def test_a_cached_file_is_recorded_checked_and_guards_its_readers(tmp_path):
    """Issue 53: the flow pool's files were outside the damage check; a zeroed one left
    status silent and its readers were built from it. A node's cached files are in its
    manifest; damaged, the node says so, no reader is built from it, and a run rebuilds
    it before its readers."""
    g = graph(tmp_path, select_build=build_pooled)
    p = validate({"run_dir": str(tmp_path / "runs"), "dataroot": str(tmp_path / "data"),
                  "seeds": 1, "folds": 1, "synthetic": False, "extension_build": False})
    g.build(p)
    files = g.recorded(p, dag.Node("select"))["files"]
    assert sorted(files) == ["../pool/a.npy", "out.json"]
    assert files["../pool/a.npy"]["size"] == 4
    pool_file = tmp_path / "runs" / "pool" / "a.npy"
    pool_file.write_bytes(b"\0\0\0\0")
    st = {str(s.node): s for s in g.status(p)}
    assert st["select"].state == "damaged"
    assert st["select"].why == (f"{pool_file} changed since it was built (same size, other "
                                "content); the next run rebuilds it")
    with pytest.raises(dag.MissingInput, match=re.escape(
            f"train[s0] reads select, whose files are damaged ({pool_file} changed since it "
            "was built (same size, other content)): rebuild it, run chapter 02 first")):
        g.build_node(p, dag.Node("train", None, "s0"))
    CALLS.clear()
    g.build(p)
    assert CALLS == ["select"] and pool_file.read_bytes() == b"flow"
    pool_file.unlink()
    assert g.damaged(p, dag.Node("select")) == f"{pool_file} is missing"
