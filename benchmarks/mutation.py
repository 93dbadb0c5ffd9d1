"""Mutation testing (``make mutation``): does a one-line bug in the code whose numbers reach
the book make a test fail?

mutmut (pinned in environment/requirements.txt; configured in pyproject.toml,
``[tool.mutmut]``) changes one operator, constant or call at a time in the modules below and
runs the quick tests that cover the changed function (``-m "not slow and not world"``). A
mutant that no test notices *survives*. This script runs mutmut, then writes

* ``benchmarks/results/mutation.json``: every mutant's status, per module;
* ``benchmarks/mutation.md``: the score per module and every surviving mutant, its change
  and its verdict from ``benchmarks/mutation_verdicts.json`` (``equivalent: why`` when no
  test can tell the mutant from the code). A verdict names the change it was given for
  (mutmut numbers a function's mutants afresh when the function changes): a survivor
  without one, or whose change is another now, is listed as ``open``.

Goal: at least 90 % of the non-equivalent mutants killed on each module. Not part of
``make test``. Each module is run on its own (``mutmut run "<module>.*"``, which re-tests
every mutant of that module) and timed; the report gives each module's minutes, so a run
can be split by module (``make mutation MODULES="flowmod.train flowmod.select"``) and each
part still fits in 45 min on 2 cores.
"""

from __future__ import annotations

import ast
import difflib
import json
import os
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

from flowmod.artefacts import atomic_path, write_json

ROOT = Path(__file__).resolve().parents[1]
#: The modules whose numbers reach the book, as mutmut names their mutants.
MODULES = ("flowmod.metrics", "flowmod.labels", "flowmod.crops", "flowmod.dag",
           "flowmod.evaluate", "flowmod.geometry", "flowmod.select", "flowmod.train",
           "flowmod.flow.estimators", "flowmod.flow.metrics")
VERDICTS = ROOT / "benchmarks" / "mutation_verdicts.json"
#: ``{module: {"seconds": s, "commit": c, "date": d}}`` of each module's last timed run.
TIMES = ROOT / "benchmarks" / "results" / "mutation_times.json"


def results() -> dict[str, str]:
    """``{mutant name: status}`` of the last run (``mutmut results --all true``)."""
    out = subprocess.run([sys.executable, "-m", "mutmut", "results", "--all", "true"],
                         cwd=ROOT, capture_output=True, text=True, check=True).stdout
    rows = {}
    for line in out.splitlines():
        name, sep, status = line.strip().rpartition(": ")
        if sep and name.startswith("flowmod."):
            rows[name] = status
    return rows


def mutant_sources() -> dict[str, str]:
    """``{function name: source}`` of every function in mutmut's copies of the modules
    (``mutants/src``: the original of each function as ``<name>__mutmut_orig``, each mutant
    as ``<name>__mutmut_<k>``)."""
    out = {}
    for m in MODULES:
        path = ROOT / "mutants" / "src" / (m.replace(".", "/") + ".py")
        if not path.is_file():
            continue
        text = path.read_text()
        lines = text.splitlines()
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef) and "__mutmut_" in node.name:
                body = lines[node.lineno - 1:node.end_lineno]
                out[f"{m}.{node.name}"] = "\n".join(body)
    return out


def change(name: str, sources: dict[str, str]) -> str:
    """The mutant's change as ``old line => new line`` (whitespace collapsed), or ''."""
    base = name.rsplit("__mutmut_", 1)[0]
    orig, mut = sources.get(base + "__mutmut_orig"), sources.get(name)
    if orig is None or mut is None:
        return ""
    short = name.rsplit(".", 1)[-1]
    mut = mut.replace(short, short.rsplit("__mutmut_", 1)[0] + "__mutmut_orig", 1)
    diff = [ln for ln in difflib.unified_diff(orig.splitlines(), mut.splitlines(), lineterm="",
                                              n=0) if ln[:1] in "-+" and ln[:3] not in ("---", "+++")]
    old = " / ".join(" ".join(ln[1:].split()) for ln in diff if ln.startswith("-"))
    new = " / ".join(" ".join(ln[1:].split()) for ln in diff if ln.startswith("+"))
    return f"{old} => {new}"


def verdict(name: str, verdicts: dict[str, dict[str, str]], sources: dict[str, str]) -> str:
    """The recorded verdict if it was given for this very change, else ``open``."""
    v = verdicts.get(name)
    if v is None:
        return "open"
    if v.get("change") != change(name, sources):
        return "open (the verdict was given for another change: recheck)"
    return v["verdict"]


def module_of(name: str) -> str:
    return next((m for m in MODULES if name.startswith(m + ".")), name.split(".x_")[0])


def commit() -> str:
    """The checkout's commit (short), ``+ changes`` when its tracked files differ from it
    (the report itself, which every run rewrites, not counted)."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True,
                              text=True).stdout.strip()
    dirty = git("status", "--porcelain", "--untracked-files=no", "--", ".",
                ":!benchmarks/mutation.md")
    return (git("rev-parse", "--short", "HEAD") or "unknown") + (" + changes" if dirty else "")


def report(rows: dict[str, str], verdicts: dict[str, dict[str, str]],
           times: dict[str, dict[str, Any]]) -> str:
    """The markdown report: when and at which commit, the score and the minutes of the last
    timed run per module, then every survivor and its verdict."""
    when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    lines = ["# Mutation testing", "",
             f"Run at {commit()}, {when}, on {os.cpu_count()} CPUs.", "",
             "`make mutation`: mutmut on the quick tests, one module at a time. Killed = a "
             "test failed (or timed out); no test = no quick test runs the function (counted "
             "as not killed); equivalent = no test can tell it from the code (the verdict says "
             "why); CUDA only = a survivor whose change matters only on a GPU, which no test "
             "here can run (the verdict says what). Score = killed / (mutants - equivalent - "
             "CUDA only). Minutes: the module's last whole run (`mutmut run "
             "\"<module>.*\"`) and the commit it ran at; a function changed since then has "
             "its mutants re-tested by mutmut, so every row is of the code above.", "",
             "| module | mutants | killed | survived | no test | equivalent | CUDA only "
             "| score | minutes (commit) |",
             "|---|---|---|---|---|---|---|---|---|"]
    sources = mutant_sources()
    given = {k: verdict(k, verdicts, sources) for k, v in rows.items() if v == "survived"}
    for m in MODULES:
        mine = {k: v for k, v in rows.items() if module_of(k) == m}
        c = Counter(mine.values())
        killed = c["killed"] + c["timeout"]
        survived = [k for k, v in mine.items() if v == "survived"]
        equivalent = [k for k in survived if given[k].startswith("equivalent")]
        cuda = [k for k in survived if given[k].startswith("cuda-only")]
        denom = len(mine) - len(equivalent) - len(cuda) - c["skipped"] - c["not checked"]
        score = f"{100 * killed / denom:.1f} %" if denom else "-"
        t = times.get(m)
        took = f"{t['seconds'] / 60:.1f} ({t['commit']})" if t else "-"
        lines.append(f"| {m} | {len(mine)} | {killed} | {len(survived)} | {c['no tests']} "
                     f"| {len(equivalent)} | {len(cuda)} | {score} | {took} |")
    lines += ["", "## Surviving mutants", "", "| mutant | change | verdict |", "|---|---|---|"]
    for k in sorted(given):
        what = change(k, sources).replace("|", "\\|")
        lines.append(f"| `{k.removeprefix('flowmod.')}` | `{what}` | {given[k]} |")
    return "\n".join(lines) + "\n"


def finished(module: str, rows: dict[str, str]) -> bool:
    """Whether a run tested every mutant of ``module``: it has mutants and none is left
    ``not checked`` (an interrupted run leaves some), so only a whole run's time counts."""
    mine = [v for k, v in rows.items() if module_of(k) == module]
    return bool(mine) and "not checked" not in mine


def run_module(module: str) -> tuple[int, float]:
    """``mutmut run "<module>.*"``: re-test every mutant of one module; (exit code, s)."""
    t0 = time.time()
    proc = subprocess.run([sys.executable, "-m", "mutmut", "run", f"{module}.*"], cwd=ROOT)
    return proc.returncode, time.time() - t0


def main(argv: list[str] | None = None) -> int:
    """``make mutation``: run mutmut module by module (module names as arguments: those
    only), then write the report. ``--report-only``: write the report of the last (possibly
    interrupted) runs; their unchecked mutants are counted."""
    args = sys.argv[1:] if argv is None else argv
    partial = "--report-only" in args
    chosen = [a for a in args if not a.startswith("--")] or list(MODULES)
    unknown = sorted(set(chosen) - set(MODULES))
    if unknown:
        print(f"mutation: {', '.join(unknown)} not in scope (one of: {', '.join(MODULES)})",
              file=sys.stderr)
        return 2
    times = json.loads(TIMES.read_text()) if TIMES.is_file() else {}
    for m in ([] if partial else chosen):
        code, seconds = run_module(m)
        if code not in (0, 1):
            return code
        if not finished(m, results()):
            print(f"mutation: the run of {m} stopped before every mutant was tested; its "
                  "time is not recorded (run it again)", file=sys.stderr)
            return 1
        times[m] = {"seconds": round(seconds, 1), "commit": commit(),
                    "date": time.strftime("%Y-%m-%d", time.gmtime())}
        write_json(TIMES, times)
    rows = results()
    unchecked = sum(v == "not checked" for v in rows.values())
    if not rows or (unchecked and not partial and chosen == list(MODULES)):
        print(f"mutation: mutmut left {unchecked} of {len(rows)} mutants unchecked (its test "
              "run failed: run the tests in mutants/ to see why)", file=sys.stderr)
        return 1
    verdicts = json.loads(VERDICTS.read_text()) if VERDICTS.is_file() else {}
    write_json(ROOT / "benchmarks" / "results" / "mutation.json", rows)
    text = report(rows, verdicts, times)
    if unchecked:
        text += (f"\n{unchecked} of {len(rows)} mutants not checked yet (`make mutation "
                 "MODULES=...` runs the modules they belong to).\n")
    with atomic_path(ROOT / "benchmarks" / "mutation.md") as tmp:
        tmp.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
