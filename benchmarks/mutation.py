"""Mutation testing (``make mutation``): does a one-line bug in the code whose numbers reach
the book make a test fail?

mutmut (pinned in environment/requirements.txt; configured in pyproject.toml,
``[tool.mutmut]``) changes one operator, constant or call at a time in the modules below and
runs the quick tests that cover the changed function (``-m "not slow and not world"``). A
mutant that no test notices *survives*. This script runs mutmut, then writes

* ``benchmarks/results/mutation.json``: every mutant's status, per module;
* ``benchmarks/mutation.md``: the score per module and every surviving mutant with its
  verdict from ``benchmarks/mutation_verdicts.json`` (``equivalent: why`` when no test can
  tell the mutant from the code, e.g. a changed default nobody passes; or the test that was
  added for it). A survivor without a verdict is listed as ``open``.

Goal: at least 90 % of the non-equivalent mutants killed. Not part of ``make test``; the
report gives how long it took.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The modules whose numbers reach the book, as mutmut names their mutants.
MODULES = ("flowmod.metrics", "flowmod.labels", "flowmod.crops", "flowmod.dag",
           "flowmod.evaluate", "flowmod.geometry")
VERDICTS = ROOT / "benchmarks" / "mutation_verdicts.json"


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


def module_of(name: str) -> str:
    return next((m for m in MODULES if name.startswith(m + ".")), name.split(".x_")[0])


def report(rows: dict[str, str], verdicts: dict[str, str], seconds: float) -> str:
    """The markdown report: the score per module, then every survivor and its verdict."""
    lines = ["# Mutation testing", "",
             f"`make mutation` ({seconds / 60:.0f} min of this call): mutmut on the quick tests. "
             "Killed = a test failed (or timed out); equivalent = no test can tell it from "
             "the code (the verdict says why).", "",
             "| module | mutants | killed | survived | equivalent | score (non-equivalent) |",
             "|---|---|---|---|---|---|"]
    for m in MODULES:
        mine = {k: v for k, v in rows.items() if module_of(k) == m}
        c = Counter(mine.values())
        killed = c["killed"] + c["timeout"]
        survived = [k for k, v in mine.items() if v == "survived"]
        equivalent = [k for k in survived if verdicts.get(k, "").startswith("equivalent")]
        denom = (len(mine) - len(equivalent) - c["skipped"] - c["no tests"]
                 - c["not checked"])
        score = f"{100 * killed / denom:.1f} %" if denom else "-"
        lines.append(f"| {m} | {len(mine)} | {killed} | {len(survived)} | {len(equivalent)} "
                     f"| {score} |")
    lines += ["", "## Surviving mutants", "", "| mutant | verdict |", "|---|---|"]
    for k, v in sorted(rows.items()):
        if v == "survived":
            lines.append(f"| `{k}` | {verdicts.get(k, 'open')} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """``make mutation``: run mutmut, then write the report. ``--report-only``: write the
    report of the last (possibly interrupted) run; its unchecked mutants are counted."""
    partial = "--report-only" in (sys.argv[1:] if argv is None else argv)
    t0 = time.time()
    if not partial:
        proc = subprocess.run([sys.executable, "-m", "mutmut", "run"], cwd=ROOT)
        if proc.returncode not in (0, 1):
            return proc.returncode
    rows = results()
    unchecked = sum(v == "not checked" for v in rows.values())
    if not rows or (unchecked and not partial):
        print(f"mutation: mutmut left {unchecked} of {len(rows)} mutants unchecked (its test "
              "run failed: run the tests in mutants/ to see why)", file=sys.stderr)
        return 1
    verdicts = json.loads(VERDICTS.read_text()) if VERDICTS.is_file() else {}
    out = ROOT / "benchmarks" / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / "mutation.json").write_text(json.dumps(rows, indent=1, sort_keys=True) + "\n")
    text = report(rows, verdicts, time.time() - t0)
    if unchecked:
        text += (f"\n{unchecked} of {len(rows)} mutants not checked yet (an interrupted run: "
                 "`make mutation` resumes it).\n")
    (ROOT / "benchmarks" / "mutation.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
