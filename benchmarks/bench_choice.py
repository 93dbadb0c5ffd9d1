"""A demo-only choice against another value, paired on one chain (the differences page).

    .venv/bin/python benchmarks/bench_choice.py --set model_width=64 [--method dis]
    .venv/bin/python benchmarks/bench_choice.py --set batch_size=128 step_size=10 gamma=0.5

Needs a built demo (``make book``). Copies ``runs/demo`` into ``runs/demo-<name>`` (hard
links: published artefacts are replaced by rename, never written in place), trains the
``method`` chain's classifiers there with the ``--set`` values (the demo's folds, seeds and
every other parameter and artefact unchanged) and scores them as chapter 07 does; then
compares the demo's chain with them, paired on the same objects (Table 3's test scenes and
Table 4's set) with the interval over scenes, and writes
``benchmarks/results/choice-<name>.json``. Only training parameters (those that leave the
crops as they are) make sense here. Reported, never asserted; the differences page points
to the dated records of it (``benchmarks/width.md``, ``benchmarks/schedule.md``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

from flowmod import pipeline
from flowmod.artefacts import write_json
from flowmod.chapters.common import results
from flowmod.evaluate import paired, scored
from flowmod.metrics import comparison_table
from flowmod.params import ProfileError, load_profile, parse_overrides
from flowmod.paths import repo_root


def _overrides(pairs: list[str]) -> dict:
    """``--set key=value`` items as a dict (:func:`flowmod.params.parse_overrides`); a bad
    item ends the run with its one-line message."""
    try:
        return parse_overrides(pairs)
    except ProfileError as e:
        raise SystemExit(f"{e} (e.g. --set model_width=64)") from None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", nargs="+", required=True, metavar="KEY=VALUE")
    ap.add_argument("--method", default="dis")
    args = ap.parse_args(argv)
    over = _overrides(args.set)
    name = "-".join(f"{k}{v}" for k, v in over.items())
    root = repo_root()
    demo = load_profile("demo")
    run = f"{demo.run_dir}-{name}"
    if not (root / run).exists():
        subprocess.run(["cp", "-al", str(demo.run_path), str(root / run)], check=True)
    other = load_profile("demo", run_dir=run, flow_methods=[args.method], extension_inputs=[],
                         wide_methods=[], selfflow_modes=[], **over)
    t0 = time.perf_counter()
    pipeline.build(other, ["06", "07", "08"], progress=True)
    seconds = time.perf_counter() - t0
    what = ", ".join(f"{k} {getattr(demo, k)}" for k in over)
    rows = {}
    for split, table_name in (("test", "test"), ("general", "general")):
        a = scored(results(demo, args.method, table_name)[0], split, demo.general_max_distance)
        b = scored(results(other, args.method, table_name)[0], split, demo.general_max_distance)
        rows[f"{split}: demo ({what}) - {name}"] = paired(
            a, b, f"{args.method} with two settings", demo.seed)
    table = comparison_table(rows)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root,
                            capture_output=True, text=True).stdout.strip()
    out = root / "benchmarks" / "results" / f"choice-{name}.json"
    write_json(out, {"commit": commit, "date": time.strftime("%Y-%m-%d"),
                     "method": args.method, "demo": {k: getattr(demo, k) for k in over},
                     "other": over, "train_and_score_seconds": round(seconds, 1),
                     "table": table.to_dict("records")})
    print(table.to_string(index=False))
    print(json.dumps({"seconds": round(seconds, 1)}))
    print(f"written: {out}; remove {run} when done (shutil.rmtree)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
