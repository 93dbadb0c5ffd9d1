"""The benchmarks run by hand, never in the tests, so a renamed library function breaks them
unseen: every name they take from flowmod must exist."""

from __future__ import annotations

import ast
import fnmatch
import importlib
import json
import math
import subprocess
import sys
import types
from pathlib import Path

import pytest

from flowmod.paths import repo_root

BENCHMARKS = sorted((repo_root() / "benchmarks").glob("*.py"))


def _imported(module: str, name: str) -> object | None:
    """``from module import name``: the object, or None where there is no such name."""
    mod = importlib.import_module(module)
    if hasattr(mod, name):
        return getattr(mod, name)
    try:
        return importlib.import_module(f"{module}.{name}")
    except ModuleNotFoundError:
        return None


def unresolved(source: str) -> list[str]:
    """The flowmod names that ``source`` imports or reads as ``module.attr`` and that do not
    exist, each with its line."""
    tree = ast.parse(source)
    bound: dict[str, object] = {}
    missing = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "flowmod":
            for alias in node.names:
                obj = _imported(node.module, alias.name)
                if obj is None:
                    missing.append(f"{node.module}.{alias.name} (line {node.lineno})")
                else:
                    bound[alias.asname or alias.name] = obj
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            obj = bound.get(node.value.id)
            if isinstance(obj, types.ModuleType) and not hasattr(obj, node.attr):
                missing.append(f"{obj.__name__}.{node.attr} (line {node.lineno})")
    return missing


def test_a_renamed_function_is_found():
    src = "from flowmod import dag, pipeline\nfrom flowmod.crops import read_crops, nope\n" \
          "pipeline.published\ndag.published\n"
    assert unresolved(src) == ["flowmod.crops.nope (line 2)", "flowmod.dag.published (line 4)"]


def test_the_benchmarks_are_found():
    assert {"bench_rerun.py", "bench_scale.py"} <= {p.name for p in BENCHMARKS}


@pytest.mark.parametrize("path", BENCHMARKS, ids=lambda p: p.name)
def test_every_flowmod_name_a_benchmark_uses_exists(path: Path):
    assert unresolved(path.read_text()) == []


def _run_quick(script: str, out: Path) -> str:
    r = subprocess.run([sys.executable, str(repo_root() / "benchmarks" / script), "--quick",
                        "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-1500:]
    return out.read_text()


def test_the_gpu_benchmark_runs_on_the_cpu_in_seconds(tmp_path):
    """bench_gpu.py is the script a session lent a GPU runs (issue 40): its --quick form runs
    every section on the CPU and writes the report with a measured row for each case."""
    text = _run_quick("bench_gpu.py", tmp_path / "gpu.md")
    assert text.startswith("# What a GPU buys") and "Device: cpu" in text
    flow = [r for r in text.splitlines() if r.startswith(("| fastflownet", "| raft_small"))]
    assert len(flow) == 2 * 2 * 2  # methods x flow scales x batches
    assert all(float(r.split("|")[4]) > 0 for r in flow)  # ms a pair
    train = [r for r in text.splitlines() if r.startswith("|        16 |")]
    assert len(train) == 1 and int(train[0].split("|")[-2]) > 0  # crops/s
    assert "skipped (--quick)" in text


def test_the_loader_benchmark_times_every_input_path(tmp_path):
    import json

    _run_quick("bench_loader.py", tmp_path / "loader.json")
    rows = json.loads((tmp_path / "loader.json").read_text())["rows"]
    assert [r["path"] for r in rows] == ["streamed float16, workers=0",
                                         "resident, cpu (float32, flipped)",
                                         "host float32 (before issue 40)"]
    assert all(r["crops"] == 256 and r["crops_per_s"] > 0 for r in rows)


def _mutation() -> types.ModuleType:
    """benchmarks/mutation.py (``make mutation``) as a module."""
    sys.path.insert(0, str(repo_root() / "benchmarks"))
    try:
        return importlib.import_module("mutation")
    finally:
        sys.path.pop(0)


def test_the_mutation_report_names_its_commit_and_scores_each_module(monkeypatch):
    """benchmarks/mutation.py's report: its commit and date in the header; per module the
    killed share of the mutants that are neither equivalent nor CUDA-only (a verdict given
    for the survivor's current change), a mutant no test runs counted as not killed, and
    the module's last timed run; an open survivor listed."""
    mutation = _mutation()
    monkeypatch.setattr(mutation, "commit", lambda: "abc1234")
    monkeypatch.setattr(mutation, "mutant_sources", lambda: {})
    monkeypatch.setattr(mutation, "change", lambda name, sources: f"change of {name}")
    rows = {"flowmod.labels.x_f__mutmut_1": "killed", "flowmod.labels.x_f__mutmut_2": "timeout",
            "flowmod.labels.x_f__mutmut_3": "survived", "flowmod.labels.x_f__mutmut_4": "survived",
            "flowmod.labels.x_f__mutmut_5": "survived", "flowmod.labels.x_f__mutmut_6": "no tests",
            "flowmod.labels.x_f__mutmut_7": "not checked",
            "flowmod.flow.metrics.x_g__mutmut_1": "survived"}
    verdicts = {"flowmod.labels.x_f__mutmut_3": {
        "change": "change of flowmod.labels.x_f__mutmut_3", "verdict": "equivalent: why"},
        "flowmod.labels.x_f__mutmut_5": {
        "change": "change of flowmod.labels.x_f__mutmut_5", "verdict": "cuda-only: what"},
        "flowmod.flow.metrics.x_g__mutmut_1": {
        "change": "an older change", "verdict": "equivalent: no longer"}}
    times = {"flowmod.labels": {"seconds": 90.0, "commit": "def5678", "date": "2026-12-05"}}
    text = mutation.report(rows, verdicts, times)
    assert text.splitlines()[2].startswith("Run at abc1234, 20")
    lines = {ln.split(" | ")[0]: ln for ln in text.splitlines() if ln.startswith("| flowmod")}
    assert lines["| flowmod.labels"] == ("| flowmod.labels | 7 | 2 | 3 | 1 | 1 | 1 | 50.0 % "
                                         "| 1.5 (def5678) |")
    assert lines["| flowmod.flow.metrics"] == ("| flowmod.flow.metrics | 1 | 0 | 1 | 0 | 0 | 0 "
                                               "| 0.0 % | - |")
    assert "| `labels.x_f__mutmut_4` | `change of flowmod.labels.x_f__mutmut_4` | open |" in text
    assert "open (the verdict was given for another change: recheck)" in text



def _wilson(k: int, n: int) -> tuple[float, float]:
    """The 95 % Wilson score interval (%), by its formula."""
    z, ph = 1.959963984540054, k / n
    mid, half = ph + z * z / (2 * n), z * math.sqrt(ph * (1 - ph) / n + z * z / (4 * n * n))
    return 100 * (mid - half) / (1 + z * z / n), 100 * (mid + half) / (1 + z * z / n)


def test_a_sampled_module_s_score_carries_its_wilson_interval(monkeypatch):
    """A module whose checked mutants are all of a ``--sample`` draw: its score and the 95 %
    Wilson interval over the mutants drawn (equivalents left out); a module partly checked
    outside any draw (an interrupted run): its score alone."""
    mutation = _mutation()
    monkeypatch.setattr(mutation, "commit", lambda: "abc1234")
    monkeypatch.setattr(mutation, "mutant_sources", lambda: {})
    monkeypatch.setattr(mutation, "change", lambda name, sources: f"change of {name}")
    name = "flowmod.world.agents.x_f__mutmut_{}".format
    rows = {name(i): "not checked" for i in range(1, 41)}
    drawn = [name(i) for i in range(1, 13)]
    rows.update({k: "killed" for k in drawn[:9]})
    rows.update({k: "survived" for k in drawn[9:]})
    rows.update({"flowmod.labels.x_f__mutmut_1": "killed",
                 "flowmod.labels.x_f__mutmut_2": "not checked"})
    verdicts = {drawn[9]: {"change": f"change of {drawn[9]}", "verdict": "equivalent: why"},
                drawn[10]: {"change": f"change of {drawn[10]}", "verdict": "equivalent: why"}}
    samples = {"flowmod.world.agents 2/5": {"n": 12, "of": 40, "seed": 0, "names": drawn}}
    text = mutation.report(rows, verdicts, {}, samples)
    lines = {ln.split(" | ")[0]: ln for ln in text.splitlines() if ln.startswith("| flowmod")}
    lo, hi = _wilson(9, 10)  # 12 drawn, 2 equivalent
    assert lines["| flowmod.world.agents"] == (
        f"| flowmod.world.agents | 40 | 9 | 3 | 0 | 2 | 0 | 90.0 % (sample of 10: "
        f"{lo:.1f}-{hi:.1f}) | - |")
    assert (round(lo, 1), round(hi, 1)) == (59.6, 98.2)
    assert lines["| flowmod.labels"].endswith("| 100.0 % | - |")
    other = {"flowmod.world.agents": {"n": 3, "of": 40, "seed": 0, "names": drawn[:3]}}
    assert "| 90.0 % | - |" in mutation.report(rows, verdicts, {}, other)  # not all drawn


def test_a_sample_draw_is_seeded_by_its_item_and_recorded(tmp_path, monkeypatch, capsys):
    """``--sample n``: n of the item's mutants (all if fewer), the same draw for the same
    names and item, another for another item; the run is of the draw only, recorded in
    the samples file; a draw left unchecked, or a bad n, is one line and a failure."""
    mutation = _mutation()
    names = [f"flowmod.labels.x_f__mutmut_{i}" for i in range(1, 101)]
    one = mutation.draw(names, 10, "flowmod.labels")
    assert len(one) == 10 == len(set(one)) and set(one) <= set(names) and one == sorted(one)
    assert mutation.draw(list(reversed(names)), 10, "flowmod.labels") == one
    assert mutation.draw(names, 10, "flowmod.labels 1/2") != one
    assert mutation.draw(names[:4], 10, "x") == sorted(names[:4])
    ran, state = [], {}
    monkeypatch.setattr(mutation, "module_mutants", lambda m: names)
    monkeypatch.setattr(mutation, "run_patterns", lambda pats: (ran.append(pats), (1, 2.0))[1])
    monkeypatch.setattr(mutation, "results", lambda: {k: state.get(k, "not checked")
                                                      for k in names})
    monkeypatch.setattr(mutation, "commit", lambda: "abc1234")
    monkeypatch.setattr(mutation, "SAMPLES", tmp_path / "samples.json")
    for name in ("ROOT", "TIMES", "VERDICTS"):  # a broken check must not write the repo's
        monkeypatch.setattr(mutation, name, tmp_path / name)
    item = {"name": "flowmod.labels", "module": "flowmod.labels",
            "patterns": ["flowmod.labels.x_f__mutmut_1*"]}  # 1, 10-19, 100: 12 mutants
    assert mutation.run_samples([item], 5, {}) == 1
    assert "stopped before every mutant drawn was tested (flowmod.labels" in \
        capsys.readouterr().err
    state.update(dict.fromkeys(names, "killed"))
    samples: dict = {}
    other = {"name": "flowmod.labels 2/2", "module": "flowmod.labels",
             "patterns": ["flowmod.labels.x_f__mutmut_2*"]}  # 2, 20-29: 11 mutants
    assert mutation.run_samples([item, other], 5, samples) == 0
    picked = mutation.draw([n for n in names if fnmatch.fnmatchcase(n, item["patterns"][0])],
                           5, "flowmod.labels")
    picked2 = mutation.draw([n for n in names if fnmatch.fnmatchcase(n, other["patterns"][0])],
                            5, "flowmod.labels 2/2")
    assert ran == [picked, picked + picked2], "one run for every draw"
    assert len(picked) == 5 and picked2 != picked
    assert samples["flowmod.labels"] == {"n": 5, "of": 12, "seed": 0, "run_seconds": 2.0,
                                         "commit": "abc1234", "names": picked}
    assert samples["flowmod.labels 2/2"]["names"] == picked2
    assert samples["flowmod.labels 2/2"]["of"] == 11
    assert json.loads((tmp_path / "samples.json").read_text()) == samples
    for bad in ("0", "x", "-1"):  # a negative value is the option's, not an unknown option
        assert mutation.main(["--sample", bad, "flowmod.labels"]) == 2
        assert f"--sample {bad}: give a number of mutants" in capsys.readouterr().err
    # another seed: another draw, recorded with its seed
    fresh = mutation.draw(names, 10, "flowmod.labels", seed=1)
    assert fresh != one and len(set(fresh) - set(one)) >= 5
    again: dict = {}
    assert mutation.run_samples([item], 5, again, seed=1) == 0
    assert again["flowmod.labels"]["seed"] == 1
    assert again["flowmod.labels"]["names"] == mutation.draw(
        [n for n in names if fnmatch.fnmatchcase(n, item["patterns"][0])], 5, "flowmod.labels",
        seed=1)
    for bad in (["--seed", "x", "--sample", "3"], ["--seed", "1"]):
        assert mutation.main([*bad, "flowmod.labels"]) == 2
        assert "--seed" in capsys.readouterr().err


def test_the_mutation_report_s_commit_ignores_the_report_it_rewrites(tmp_path, monkeypatch):
    """'+ changes' marks an edited tracked file, but not benchmarks/mutation.md, which every
    run rewrites before the next report reads the commit."""
    mutation = _mutation()
    git = lambda *a: subprocess.run(["git", "-C", str(tmp_path), *a], check=True,  # noqa: E731
                                    capture_output=True, text=True).stdout.strip()
    git("init", "-q")
    (tmp_path / "benchmarks").mkdir()
    for f in ("benchmarks/mutation.md", "code.py"):
        (tmp_path / f).write_text("a\n")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "x")
    head = git("rev-parse", "--short", "HEAD")
    monkeypatch.setattr(mutation, "ROOT", tmp_path)
    (tmp_path / "benchmarks/mutation.md").write_text("b\n")
    assert mutation.commit() == head
    (tmp_path / "code.py").write_text("b\n")
    assert mutation.commit() == head + " + changes"


def test_the_mutation_run_records_a_time_only_for_a_whole_run():
    """An interrupted mutmut run (mutants left ``not checked``) or a module with no mutants
    is not a whole run: its seconds must not reach the report."""
    mutation = _mutation()
    rows = {"flowmod.labels.x_f__mutmut_1": "killed", "flowmod.labels.x_f__mutmut_2": "no tests",
            "flowmod.crops.x_g__mutmut_1": "killed", "flowmod.crops.x_g__mutmut_2": "not checked"}
    assert mutation.finished("flowmod.labels", rows)
    assert not mutation.finished("flowmod.crops", rows)
    assert not mutation.finished("flowmod.geometry", rows)


def test_mutation_parts_fit_their_minutes_and_cover_every_function_once(monkeypatch,
                                                                          capsys):
    """``make mutation PART=k``: each group's modules in order, a part closed before it
    would pass PART_MINUTES (estimated: mutants x seconds a mutant), a module too large for
    one part cut into chunks of whole functions in source order (a function larger than a
    part alone), every function in exactly one item; a chunked module's minutes in the
    report are the sum of a run of every chunk of one plan."""
    mutation = _mutation()
    monkeypatch.setattr(mutation, "GROUPS", {"core": ("m.a", "m.b"),
                                             "world": ("w.d", "w.c", "w.e")})
    monkeypatch.setattr(mutation, "SECONDS_A_MUTANT", {"m": 60.0, "w": 60.0})
    monkeypatch.setattr(mutation, "PART_MINUTES", 6.0)  # 6 mutants a part
    counts = {"m.a": {"x_f": 2, "x_g": 1}, "m.b": {"x_h": 2}, "w.d": {"x_n": 1},
              "w.c": {"x_i": 2, "x_j": 4, "x_k": 9, "x_l": 1, "xǁCǁm": 2}, "w.e": {"x_o": 1}}
    parts = mutation.plan(counts)
    assert [[x["name"] for x in part] for part in parts] == [
        ["m.a", "m.b"], ["w.d"], ["w.c 1/3"], ["w.c 2/3"], ["w.c 3/3", "w.e"]]
    assert [sum(x["minutes"] for x in part) for part in parts] == [5.0, 1.0, 6.0, 9.0, 4.0]
    assert parts[0][0]["patterns"] == ["m.a.*"]
    assert [x["patterns"] for x in parts[2] + parts[3]] == [
        ["w.c.x_i__mutmut_*", "w.c.x_j__mutmut_*"], ["w.c.x_k__mutmut_*"]]
    assert parts[4][0]["patterns"] == ["w.c.x_l__mutmut_*", "w.c.xǁCǁm__mutmut_*"]
    assert "part 4: 9 min (estimated), 9 mutants: w.c 2/3" in mutation.plan_text(parts)
    rows = {"w.c.x_i__mutmut_1": "killed", "w.c.x_j__mutmut_1": "survived",
            "w.c.x_k__mutmut_1": "not checked"}
    assert mutation.item_finished(parts[2][0], rows)
    assert not mutation.item_finished(parts[3][0], rows)
    assert not mutation.item_finished(parts[2][0], {})  # no mutant of it ran
    times = {"w.c 1/3": {"seconds": 60.0, "commit": "a"}, "w.c 3/3": {"seconds": 30.0,
                                                                     "commit": "c"}}
    assert mutation.module_time("w.c", times) is None  # 2/3 never ran
    times["w.c 2/3"] = {"seconds": 90.0, "commit": "b"}
    assert mutation.module_time("w.c", times) == {"seconds": 180.0, "commit": "c"}
    monkeypatch.setattr(mutation, "listing", lambda: counts)  # what PART=... plans from
    assert mutation.main(["--part", "plan"]) == 0
    assert capsys.readouterr().out == mutation.plan_text(parts) + "\n"
    # --help prints the usage and runs nothing; an unknown option is one line, before any run
    assert mutation.main(["--help"]) == 0 and capsys.readouterr().out == mutation.USAGE + "\n"
    assert mutation.main(["--sampel", "5"]) == 2
    assert capsys.readouterr().err == f"mutation: unknown option --sampel; {mutation.USAGE}\n"
    for bad in ("0", "6", "two"):
        assert mutation.main(["--part", bad]) == 2
        assert capsys.readouterr().err == (f"mutation: --part {bad}: there are parts 1 to 5 "
                                           "(or plan)\n")


def test_mutmut_runs_its_children_on_one_thread_each(monkeypatch):
    """mutmut tests mutants in a child per core: each gets one BLAS, OpenMP and MKL thread
    (a pool of a thread per core in each child spins on the other's core)."""
    mutation, seen = _mutation(), {}

    def fake_run(argv, cwd, env):
        seen.update(argv=argv, env=env)
        return subprocess.CompletedProcess(argv, 0)

    monkeypatch.setattr(mutation.subprocess, "run", fake_run)
    monkeypatch.setenv("FLOWMOD_PROBE", "kept")
    assert mutation.run_patterns(["flowmod.metrics.*"])[0] == 0
    assert seen["argv"][1:] == ["-m", "mutmut", "run", "flowmod.metrics.*"]
    assert {k: seen["env"][k] for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                        "MKL_NUM_THREADS", "FLOWMOD_PROBE")} == {
        "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
        "FLOWMOD_PROBE": "kept"}


def test_the_disk_benchmark_sorts_files_by_kind_and_compresses_without_loss(tmp_path):
    """bench_disk.py --lossless (issue 49, item 5: measure first): each kind of run file with
    its bytes and its bytes compressed without loss. A smooth float16 flow compresses far
    better split into byte planes; noise does not compress; hidden files are not counted."""
    import zlib

    import numpy as np

    sys.path.insert(0, str(repo_root() / "benchmarks"))
    try:
        bench_disk = importlib.import_module("bench_disk")
    finally:
        sys.path.pop(0)
    pool = tmp_path / "flow" / "dis" / "pool" / "abc"
    pool.mkdir(parents=True)
    y, x = np.mgrid[0:90, 0:160].astype(np.float32)
    smooth = np.stack([x / 7, y / 9], axis=-1).astype(np.float16)
    np.save(pool / "p.npy", smooth)
    np.save(pool / "p.valid.npy", np.ones((90, 160), bool))
    crops = tmp_path / "crops" / "dis" / "keyframe"
    crops.mkdir(parents=True)
    noise = np.random.default_rng(0).integers(0, 256, 20_000, dtype=np.uint8)
    np.save(crops / "f0.npy", noise)
    np.save(crops / "f0.samples.npy", smooth[:9, :9])
    (crops / ".f0.npy.tmp").write_bytes(b"x" * 1000)
    (tmp_path / "models" / "dis" / "f0s0").mkdir(parents=True)
    (tmp_path / "models" / "dis" / "f0s0" / "best.pt").write_bytes(smooth.tobytes())
    np.save(tmp_path / "models" / "dis" / "f0s0" / "epoch_probs.npy", smooth[:3])
    table = bench_disk.lossless_table(tmp_path)
    assert sorted(table) == ["crops: crops arrays", "crops: flow samples", "flow pool: flow",
                             "flow pool: valid masks", "models: epoch_probs arrays",
                             "models: model weights"]
    assert all(r["files"] == 1 for r in table.values())
    flow = table["flow pool: flow"]
    assert flow["MB"] == (pool / "p.npy").stat().st_size / 1e6
    # a .npy is split by its own item size (float16: 2 byte planes)
    stored = (pool / "p.npy").read_bytes()
    assert flow["MB lossless"] == bench_disk.shuffled_zlib(stored, 2) / 1e6
    assert flow["MB lossless"] != bench_disk.shuffled_zlib(stored, 1) / 1e6
    raw = smooth.tobytes()
    assert bench_disk.shuffled_zlib(raw, 2) < 0.8 * len(zlib.compress(raw, 6))
    assert flow["ratio"] < 0.5 and table["crops: crops arrays"]["ratio"] > 0.95
    assert table["models: model weights"]["MB lossless"] == bench_disk.shuffled_zlib(raw, 2) / 1e6
