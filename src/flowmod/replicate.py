"""The whole study again on a world no choice has read (``make replicate``).

Builds every stage of a profile twice: with its own master seed (the book's run, usually
already built) and with another (a new world, new folds, new training seeds, in its own run
folder), then writes a dated record of every paired effect the book reports (chapters 07,
10, 11, and chapter 13's costs per kind of flow error) and of Table 3's rows in both
worlds: ``benchmarks/replication.json``, which chapter 14 shows. No notebook runs.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from flowmod import pipeline
from flowmod.artefacts import write_json
from flowmod.chapters import ch07_evaluation as ch07
from flowmod.chapters import ch13_flow_errors as ch13
from flowmod.chapters import ch14_answers as ch14
from flowmod.environment import git_commit
from flowmod.lock import FolderBusy
from flowmod.metrics import CI_COLUMN
from flowmod.params import Params, ProfileError, parse_overrides
from flowmod.paths import repo_root
from flowmod.runner import os_error_line, resolve_profile

#: The master seed of the replication's world unless ``--seed`` says otherwise: one no
#: profile, benchmark or chapter's Try it has used.
DEFAULT_SEED = 20261206


def replicate_overrides(p: Params, seed: int) -> dict[str, Any]:
    """What the replication changes in the book's parameters ``p``: the master seed and the
    run folder (``<run_dir>-replicate-<seed>``); its world gets its own folder under the
    dataroot by itself. ProfileError when ``seed`` is the book's own."""
    if seed == p.seed:
        raise ProfileError(f"--seed {seed} is the book's own master seed: give another "
                           "(the replication must draw a world no choice has read)")
    return {"seed": seed, "run_dir": f"{p.run_dir}-replicate-{seed}"}


def _summary(delta: float, low: float, high: float) -> dict[str, float]:
    return {"delta": float(delta), "low": float(low), "high": float(high)}


def effect_summaries(p: Params) -> dict[tuple[str, str], dict[str, float]]:
    """Every paired effect of a built run by (chapter, comparison): chapter 14's rows (F1
    points, A - B) and chapter 13's cost per kind of error (F1 points lost per px), each as
    its estimate and 95 % interval (``delta``, ``low``, ``high``)."""
    out = {(r["chapter"], r["comparison"]): _summary(r["ΔF1 (points)"], r["low"], r["high"])
           for _, r in ch14.effects(p).iterrows()}
    cost = ch13.costs(p, ch13.effects(p, ch13.built(p)))
    for _, r in cost.iterrows():
        out[("13", f"cost of {r['error']}")] = _summary(
            r["F1 points lost per px"], r["ci_lo"], r["ci_hi"])
    return out


def table3_rows(p: Params) -> dict[str, str]:
    """Table 3 of a built run: method -> ``F1 (low-high)`` (%)."""
    t = ch07.table3(p)
    return {r["Method"]: f"{r['F1 (%)']:.1f} ({r[CI_COLUMN]})" for _, r in t.iterrows()}


def record(book: Params, again: Params) -> dict[str, Any]:
    """The replication record of two built runs (the book's and the replication's): the
    effects and Table 3 rows both have, in the book's order."""
    eb, ea = effect_summaries(book), effect_summaries(again)
    tb, ta = table3_rows(book), table3_rows(again)
    return {
        "date": time.strftime("%Y-%m-%d", time.gmtime()), "commit": git_commit(),
        "profile": book.profile, "book_seed": book.seed, "replicate_seed": again.seed,
        "effects": [{"chapter": c, "comparison": name, "book": eb[(c, name)],
                     "replicate": ea[(c, name)]} for c, name in eb if (c, name) in ea],
        "table3": [{"method": m, "book": tb[m], "replicate": ta[m]} for m in tb if m in ta],
    }


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m flowmod.replicate",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--profile", default="demo", help="params/<name>.yaml or a YAML path")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a parameter of both runs (YAML value), repeatable")
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED,
                    help=f"master seed of the replication's world (default {DEFAULT_SEED})")
    ap.add_argument("--record", default=ch14.REPLICATION_RECORD,
                    help="where to write the record, relative to the repository root")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        overrides = parse_overrides(args.overrides)
        book = resolve_profile(args.profile, overrides)
        again = resolve_profile(args.profile, {**overrides, **replicate_overrides(book, args.seed)})
        for name, p in (("the book's world", book), ("the replication's world", again)):
            print(f"== {name}: seed {p.seed}, {p.run_dir}", flush=True)
            pipeline.build(p, progress=True)
        rec = record(book, again)
        write_json(repo_root() / args.record, rec)
    except (ProfileError, FolderBusy) as e:
        print(f"{type(e).__name__}: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: what was built is kept and the same command resumes",
              file=sys.stderr)
        return 130
    except OSError as e:
        print(os_error_line(e), file=sys.stderr)
        return 2
    print(ch14.replication_table(rec).to_string(index=False))
    print(f"record: {args.record}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
