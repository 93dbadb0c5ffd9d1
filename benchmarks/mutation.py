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
can be split by module (``make mutation MODULES="flowmod.train flowmod.select"``).

The whole set takes many hours on 2 cores, so it is run in parts that each fit in 45 min
(``make mutation PART=k``; ``PART=plan`` lists them without running a test): the modules of
each group (the core modules, the chapters' backends, the extensions, the world) in order,
packed into parts of at most :data:`PART_MINUTES` estimated minutes, a module too large for
one part cut into chunks of whole functions (``flowmod.world.agents 2/5``). The estimate is
mutmut's own listing of a module's mutants (no test run) times :data:`SECONDS_A_MUTANT`:
measured for the modules already run, a guess for the others until their first run (then
update it from the report's minutes).

A module too slow to run whole in a session (the world's: about 15 h) can be estimated
from a random draw of its mutants (``make mutation MODULES=... SAMPLE=n``, or with
``PART=k``: n of each item's): the draw is seeded by the module's (or chunk's) name and
:data:`SAMPLE_SEED`, recorded in :data:`SAMPLES`, and the report gives the sample's score
with its 95 % Wilson interval over the mutants drawn (a sample's time is not recorded as
the module's).
"""

from __future__ import annotations

import ast
import difflib
import fnmatch
import hashlib
import json
import os
import random
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

from flowmod.artefacts import atomic_path, write_json

ROOT = Path(__file__).resolve().parents[1]
#: The core modules whose numbers reach the book, as mutmut names their mutants.
CORE = ("flowmod.metrics", "flowmod.labels", "flowmod.crops", "flowmod.dag",
        "flowmod.evaluate", "flowmod.geometry", "flowmod.select", "flowmod.train",
        "flowmod.flow.estimators", "flowmod.flow.metrics")
#: The packages where the book's numbers are assembled: every module of each is mutated
#: (``only_mutate`` in pyproject.toml; their ``__init__`` and ``__main__`` are not).
PACKAGES = ("flowmod.chapters", "flowmod.extensions", "flowmod.world")


def package_modules(package: str) -> tuple[str, ...]:
    """The modules of ``package`` (its source files but ``__init__``, ``__main__``)."""
    folder = ROOT / "src" / package.replace(".", "/")
    return tuple(f"{package}.{f.stem}" for f in sorted(folder.glob("*.py"))
                 if not f.stem.startswith("__"))


#: Each group's modules in order (the parts of :func:`plan` never mix groups).
GROUPS = {"core": CORE, **{p.rsplit(".", 1)[1]: package_modules(p) for p in PACKAGES}}
#: Every module in scope.
MODULES = tuple(m for mods in GROUPS.values() for m in mods)
#: The most minutes a part is planned to take: each must fit in 45 min, and the estimate
#: (:data:`SECONDS_A_MUTANT`) is rough.
PART_MINUTES = 40.0
#: Wall seconds a mutant takes on 2 cores. Measured: a module's minutes / its mutants in
#: benchmarks/mutation.md at d4a0f7f. Guessed, until a first run: the chapters' and the
#: extensions' quick tests read small hand-made tables (about the core modules' 0.4-1.4 s);
#: the world's generate small worlds of their own (test_world.py: 3 to 12 s a test).
SECONDS_A_MUTANT = {
    "flowmod.metrics": 0.39, "flowmod.labels": 0.53, "flowmod.crops": 0.42,
    "flowmod.dag": 0.55, "flowmod.evaluate": 0.36, "flowmod.geometry": 0.58,
    "flowmod.select": 0.65, "flowmod.train": 1.42, "flowmod.flow.estimators": 1.13,
    "flowmod.flow.metrics": 0.55,
    "flowmod.chapters": 1.0, "flowmod.extensions": 1.0, "flowmod.world": 3.5,
}
VERDICTS = ROOT / "benchmarks" / "mutation_verdicts.json"
#: ``{module or chunk: {"seconds": s, "commit": c, "date": d, "mutants": n}}`` of each
#: module's (or chunk's, ``<module> i/k``) last whole run.
TIMES = ROOT / "benchmarks" / "results" / "mutation_times.json"


#: ``{module or chunk: {"n": drawn, "of": mutants, "seed": its seed, "names": [...],
#: "run_seconds": s}}`` of each ``--sample`` draw (``run_seconds``: the one run of them all).
SAMPLES = ROOT / "benchmarks" / "results" / "mutation_samples.json"
#: Seed of ``--sample``'s draws (each also seeded by its module's or chunk's name).
SAMPLE_SEED = 0


def draw(names: list[str], n: int, key: str, seed: int = SAMPLE_SEED) -> list[str]:
    """``n`` of ``names`` (all if fewer) drawn without replacement, the same for the same
    names, ``n``, ``key`` and ``seed`` (``--seed``; a larger ``n`` with the same seed draws
    mostly the same mutants again: a fresh draw needs another seed); sorted."""
    rng = random.Random(f"{seed}:{key}")
    return sorted(rng.sample(sorted(names), min(n, len(names))))


def wilson(k: int, n: int) -> tuple[float, float]:
    """The 95 % Wilson interval (%) of a share ``k`` of ``n`` (``n`` > 0)."""
    from scipy.stats import binomtest

    ci = binomtest(k, n).proportion_ci(0.95, method="wilson")
    return 100 * ci.low, 100 * ci.high


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


def module_time(module: str, times: dict[str, dict[str, Any]]) -> dict[str, Any] | None:
    """The last whole timing of ``module``: its own run, or the sum of the runs of all its
    chunks of one plan (``<module> i/k``, :func:`plan`; the last chunk's commit)."""
    if module in times:
        return times[module]
    runs: dict[int, dict[int, dict[str, Any]]] = {}
    for key, t in times.items():
        name, _, frac = key.rpartition(" ")
        i, _, k = frac.partition("/")
        if name == module and i.isdigit() and k.isdigit():
            runs.setdefault(int(k), {})[int(i)] = t
    for k, got in sorted(runs.items()):
        if set(got) == set(range(1, k + 1)):
            return {"seconds": sum(t["seconds"] for t in got.values()),
                    "commit": got[k]["commit"]}
    return None


def sampled(module: str, checked: list[str], samples: dict[str, dict[str, Any]]) -> bool:
    """Whether ``module``'s checked mutants are all of ``--sample`` draws of it (or of its
    chunks) and fewer than its mutants: its score is then an estimate."""
    drawn = {n for key, d in samples.items() if key.split(" ")[0] == module
             for n in d["names"]}
    return bool(checked) and set(checked) <= drawn


def score_text(killed: int, denom: int, sample: bool) -> str:
    """The score column: ``killed / denom`` in %, ``-`` without a mutant; for a sample,
    with its 95 % Wilson interval."""
    if not denom:
        return "-"
    text = f"{100 * killed / denom:.1f} %"
    if sample:
        lo, hi = wilson(killed, denom)
        text += f" (sample of {denom}: {lo:.1f}-{hi:.1f})"
    return text


def report(rows: dict[str, str], verdicts: dict[str, dict[str, str]],
           times: dict[str, dict[str, Any]],
           samples: dict[str, dict[str, Any]] | None = None) -> str:
    """The markdown report: when and at which commit, the score and the minutes of the last
    timed run per module (a module of ``--sample`` draws: the sample's score and interval),
    then every survivor and its verdict."""
    when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    lines = ["# Mutation testing", "",
             f"Run at {commit()}, {when}, on {os.cpu_count()} CPUs.", "",
             "`make mutation`: mutmut on the quick tests, one module at a time. Killed = a "
             "test failed (or timed out); no test = no quick test runs the function (counted "
             "as not killed); equivalent = no test can tell it from the code (the verdict says "
             "why); CUDA only = a survivor whose change matters only on a GPU, which no test "
             "here can run (the verdict says what). Score = killed / (mutants - equivalent - "
             "CUDA only). Minutes: the module's last whole run (`mutmut run "
             "\"<module>.*\"`, or the runs of all its chunks: `make mutation PART=k`) and "
             "the commit it ran at; a function changed since then has "
             "its mutants re-tested by mutmut, so every row is of the code above. A module "
             "measured on a random draw of its mutants (`SAMPLE=n`) shows the draw's score "
             "and its 95 % Wilson interval.", "",
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
        checked = [k for k, v in mine.items() if v not in ("not checked", "skipped")]
        partial = len(checked) < len(mine)
        score = score_text(killed, denom, partial and sampled(m, checked, samples or {}))
        t = module_time(m, times)
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


def run_patterns(patterns: list[str]) -> tuple[int, float]:
    """``mutmut run <patterns>``: re-test every mutant whose name matches one; (exit code,
    s)."""
    t0 = time.time()
    proc = subprocess.run([sys.executable, "-m", "mutmut", "run", *patterns], cwd=ROOT,
                          env=one_thread_env())
    return proc.returncode, time.time() - t0


def one_thread_env() -> dict[str, str]:
    """This environment with one thread for BLAS, OpenMP (torch) and MKL: mutmut tests
    mutants in a child process per core, and an OpenBLAS pool of a thread per core in each
    spins on the others' cores (as it did between make test's two workers)."""
    return {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
            "MKL_NUM_THREADS": "1"}


# --- parts that each fit in 45 min ------------------------------------------------------------


def seconds_a_mutant(module: str) -> float:
    """:data:`SECONDS_A_MUTANT` of ``module``: its own, else its package's."""
    key = next(k for k in (module, module.rsplit(".", 1)[0]) if k in SECONDS_A_MUTANT)
    return SECONDS_A_MUTANT[key]


def function_mutants(module: str) -> dict[str, int]:
    """``{function: mutants}`` of ``module`` in source order, from mutmut's own listing of
    the mutants it would make (no test is run); a function's name as mutmut's mutant names
    hold it (``x_name``, ``xǁClassǁmethod``)."""
    return dict(Counter(n[len(module) + 1:].partition("__mutmut_")[0]
                        for n in module_mutants(module)))


def module_mutants(module: str) -> list[str]:
    """The names of every mutant mutmut would make of ``module`` (``<module>.x_f__mutmut_3``),
    in source order, from its own listing (no test is run)."""
    from mutmut.mutation.file_mutation import mutate_file_contents

    rel = Path("src") / (module.replace(".", "/") + ".py")
    names = mutate_file_contents(str(rel), (ROOT / rel).read_text()).mutant_names
    return [f"{module}.{n}" for n in names]


def chunks(functions: dict[str, int], most: int) -> list[list[str]]:
    """``functions`` (in order) cut into runs of whole functions of at most ``most``
    mutants each (a function with more is a run of its own)."""
    out: list[list[str]] = [[]]
    acc = 0
    for name, n in functions.items():
        if out[-1] and acc + n > most:
            out.append([])
            acc = 0
        out[-1].append(name)
        acc += n
    return out


def plan(counts: dict[str, dict[str, int]] | None = None) -> list[list[dict[str, Any]]]:
    """The parts of ``make mutation PART=k``: each a list of items (``name``, ``module``,
    ``patterns`` for ``mutmut run``, ``mutants``, ``minutes``), the modules of each group of
    :data:`GROUPS` in order, a part closed when the next item would take it over
    :data:`PART_MINUTES`; a module over it alone is cut into chunks of whole functions
    (:func:`chunks`). ``counts``: :func:`function_mutants` per module (default: listed
    now)."""
    counts = counts if counts is not None else listing()
    parts: list[list[dict[str, Any]]] = []
    for modules in GROUPS.values():
        parts.append([])
        for m in modules:
            funcs, rate = counts[m], seconds_a_mutant(m)
            pieces = chunks(funcs, int(PART_MINUTES * 60 / rate))
            for i, names in enumerate(pieces, 1):
                n = sum(funcs[f] for f in names)
                item = {"name": m if len(pieces) == 1 else f"{m} {i}/{len(pieces)}",
                        "module": m, "mutants": n, "minutes": n * rate / 60,
                        "patterns": [f"{m}.*"] if len(pieces) == 1 else
                        [f"{m}.{f}__mutmut_*" for f in names]}
                if parts[-1] and sum(x["minutes"] for x in parts[-1]) + item["minutes"] > \
                        PART_MINUTES:
                    parts.append([])
                parts[-1].append(item)
    return [p for p in parts if p]


#: :func:`function_mutants` of each module, kept by the sha256 of its source.
LISTING = ROOT / "benchmarks" / "results" / "mutant_listing.json"


def listing() -> dict[str, dict[str, int]]:
    """:func:`function_mutants` of every module of :data:`MODULES`, listed again only for
    a module whose source changed since it was last listed (:data:`LISTING`: listing them
    all takes about 2 min)."""
    kept = json.loads(LISTING.read_text()) if LISTING.is_file() else {}
    out, fresh = {}, {}
    for m in MODULES:
        digest = hashlib.sha256((ROOT / "src" / (m.replace(".", "/") + ".py")).read_bytes())
        key = digest.hexdigest()
        if kept.get(m, {}).get("sha256") != key:  # pairs: a JSON object's keys get sorted
            fresh[m] = {"sha256": key, "functions": list(function_mutants(m).items())}
        out[m] = dict((fresh.get(m) or kept[m])["functions"])
    if fresh:
        write_json(LISTING, {**kept, **fresh})
    return out


def plan_text(parts: list[list[dict[str, Any]]]) -> str:
    """The parts in words: number, estimated minutes, mutants and items."""
    lines = []
    for k, part in enumerate(parts, 1):
        lines.append(f"part {k}: {sum(x['minutes'] for x in part):.0f} min (estimated), "
                     f"{sum(x['mutants'] for x in part)} mutants: "
                     + ", ".join(x["name"] for x in part))
    return "\n".join(lines)


def item_finished(item: dict[str, Any], rows: dict[str, str]) -> bool:
    """Whether a run tested every mutant of a plan's item (:func:`finished`, for a chunk of
    a module: of its functions)."""
    if len(item["patterns"]) == 1 and item["patterns"][0] == item["module"] + ".*":
        return finished(item["module"], rows)
    mine = [v for k, v in rows.items()
            if any(fnmatch.fnmatchcase(k, p) for p in item["patterns"])]
    return bool(mine) and "not checked" not in mine


def run_samples(items: list[dict[str, Any]], n: int, samples: dict[str, dict[str, Any]],
                seed: int = SAMPLE_SEED) -> int:
    """``--sample n``: a draw of ``n`` of each item's mutants (:func:`draw`), all run by one
    ``mutmut run`` (mutmut runs the whole quick suite once before each run, minutes), each
    draw recorded in :data:`SAMPLES` with that run's seconds; the exit code (0 when every
    mutant drawn was tested)."""
    picks = {}
    for item in items:
        names = [k for k in module_mutants(item["module"])
                 if any(fnmatch.fnmatchcase(k, p) for p in item["patterns"])]
        picks[item["name"]] = (draw(names, n, item["name"], seed), len(names))
        print(f"mutation: {item['name']}: {len(picks[item['name']][0])} of its {len(names)} "
              "mutants drawn", flush=True)
    code, seconds = run_patterns([k for picked, _ in picks.values() for k in picked])
    if code not in (0, 1):
        return code
    rows = results()
    left = [name for name, (picked, _) in picks.items()
            if any(rows.get(k, "not checked") == "not checked" for k in picked)]
    if left:
        print(f"mutation: the sample run stopped before every mutant drawn was tested "
              f"({', '.join(left)}; run it again)", file=sys.stderr)
        return 1
    for name, (picked, of) in picks.items():
        samples[name] = {"n": len(picked), "of": of, "seed": seed,
                         "run_seconds": round(seconds, 1), "commit": commit(),
                         "names": picked}
    write_json(SAMPLES, samples)
    return 0


#: The options :func:`main` takes (anything else that starts with ``-`` is refused).
OPTIONS = ("--part", "--sample", "--seed", "--report-only")
USAGE = ("usage: benchmarks/mutation.py [--part k|plan] [--sample n [--seed s]] "
         "[--report-only] [module ...] (make mutation PART= SAMPLE= SAMPLE_SEED= MODULES=)")


def main(argv: list[str] | None = None) -> int:
    """``make mutation``: run mutmut module by module (module names as arguments: those
    only; ``--part k``: the k-th part of :func:`plan`, ``--part plan``: print the parts and
    stop; ``--sample n``: a draw of n mutants of each module or item, :func:`run_samples`),
    then write the report. ``--report-only``: write the report of the last
    (possibly interrupted) runs; their unchecked mutants are counted."""
    args = sys.argv[1:] if argv is None else argv
    if {"-h", "--help"} & set(args):
        print(USAGE)
        return 0
    values = {i + 1 for i, a in enumerate(args) if a in ("--part", "--sample", "--seed")}
    flags = [a for i, a in enumerate(args)
             if a.startswith("-") and a not in OPTIONS and i not in values]
    if flags:  # before any run: an unknown flag once started every module (hours)
        print(f"mutation: unknown option {flags[0]}; {USAGE}", file=sys.stderr)
        return 2
    partial = "--report-only" in args
    part = args[args.index("--part") + 1] if "--part" in args else None
    size = args[args.index("--sample") + 1] if "--sample" in args else None
    seed = args[args.index("--seed") + 1] if "--seed" in args else str(SAMPLE_SEED)
    if "--seed" in args and (not seed.isdigit() or size is None):
        print(f"mutation: --seed {seed}: give a whole number, with --sample (SAMPLE=6 "
              "SAMPLE_SEED=1)", file=sys.stderr)
        return 2
    if size is not None and not (size.isdigit() and int(size) > 0):
        print(f"mutation: --sample {size}: give a number of mutants, at least 1 (SAMPLE=100)",
              file=sys.stderr)
        return 2
    chosen = [a for a in args if not a.startswith("--") and a not in (part, size, seed)] \
        or list(MODULES)
    unknown = sorted(set(chosen) - set(MODULES))
    if unknown:
        print(f"mutation: {', '.join(unknown)} not in scope (one of: {', '.join(MODULES)})",
              file=sys.stderr)
        return 2
    items = [{"name": m, "module": m, "patterns": [f"{m}.*"]} for m in chosen]
    if part is not None:
        parts = plan()
        if part == "plan":
            print(plan_text(parts))
            return 0
        if not part.isdigit() or not 1 <= int(part) <= len(parts):
            print(f"mutation: --part {part}: there are parts 1 to {len(parts)} (or plan)",
                  file=sys.stderr)
            return 2
        items = parts[int(part) - 1]
    times = json.loads(TIMES.read_text()) if TIMES.is_file() else {}
    samples = json.loads(SAMPLES.read_text()) if SAMPLES.is_file() else {}
    if size is not None and not partial:
        code = run_samples(items, int(size), samples, int(seed))
        if code:
            return code
    for item in ([] if partial or size is not None else items):
        code, seconds = run_patterns(item["patterns"])
        if code not in (0, 1):
            return code
        rows = results()
        if not item_finished(item, rows):
            print(f"mutation: the run of {item['name']} stopped before every mutant was "
                  "tested; its time is not recorded (run it again)", file=sys.stderr)
            return 1
        times[item["name"]] = {
            "seconds": round(seconds, 1), "commit": commit(),
            "date": time.strftime("%Y-%m-%d", time.gmtime()),
            "mutants": sum(any(fnmatch.fnmatchcase(k, p) for p in item["patterns"])
                           for k in rows)}
        write_json(TIMES, times)
    rows = results()
    unchecked = sum(v == "not checked" for v in rows.values())
    if not rows or (unchecked and not partial and part is None and size is None
                    and chosen == list(MODULES)):
        print(f"mutation: mutmut left {unchecked} of {len(rows)} mutants unchecked (its test "
              "run failed: run the tests in mutants/ to see why)", file=sys.stderr)
        return 1
    verdicts = json.loads(VERDICTS.read_text()) if VERDICTS.is_file() else {}
    write_json(ROOT / "benchmarks" / "results" / "mutation.json", rows)
    text = report(rows, verdicts, times, samples)
    if unchecked:
        text += (f"\n{unchecked} of {len(rows)} mutants not checked yet (`make mutation "
                 "PART=k` or `MODULES=...` runs the ones they belong to).\n")
    with atomic_path(ROOT / "benchmarks" / "mutation.md") as tmp:
        tmp.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
