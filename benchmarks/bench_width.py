"""The demo's half-width ResNet18 against the paper's width, paired on one chain.

    .venv/bin/python benchmarks/bench_width.py [--method dis] [--width 64]

Needs a built demo (``make book``). Copies ``runs/demo`` into ``runs/demo-width<W>`` (hard
links: published artefacts are replaced by rename, never written in place), trains the
``method`` chain's classifiers there at ``--width`` (the demo's folds, seeds, epochs and
every other parameter unchanged) and scores them as chapter 07 does; then compares the
demo's chain (its own ``model_width``) with them, paired on the same objects (Table 3's test
scenes and Table 4's set) with the interval over scenes, and writes
``benchmarks/results/width.json``. Reported, never asserted; the differences page points to
the dated record of it (``benchmarks/width.md``).
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
from flowmod.params import load_profile
from flowmod.paths import repo_root


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--method", default="dis")
    ap.add_argument("--width", type=int, default=64)
    args = ap.parse_args(argv)
    root = repo_root()
    demo = load_profile("demo")
    run = f"{demo.run_dir}-width{args.width}"
    if not (root / run).exists():
        subprocess.run(["cp", "-al", str(demo.run_path), str(root / run)], check=True)
    other = load_profile("demo", run_dir=run, model_width=args.width,
                         flow_methods=[args.method], extension_inputs=[], wide_methods=[],
                         selfflow_modes=[])
    t0 = time.perf_counter()
    pipeline.build(other, ["06", "07", "08"], progress=True)
    seconds = time.perf_counter() - t0
    rows = {}
    for split, name in (("test", "test"), ("general", "general")):
        a = scored(results(demo, args.method, name)[0], split, demo.general_max_distance)
        b = scored(results(other, args.method, name)[0], split, demo.general_max_distance)
        rows[f"{split}: width {demo.model_width} - width {args.width}"] = paired(
            a, b, f"{args.method} at two widths", demo.seed)
    table = comparison_table(rows)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root,
                            capture_output=True, text=True).stdout.strip()
    out = root / "benchmarks" / "results" / "width.json"
    write_json(out, {"commit": commit, "date": time.strftime("%Y-%m-%d"),
                     "method": args.method, "widths": [demo.model_width, args.width],
                     "train_and_score_seconds": round(seconds, 1),
                     "table": table.to_dict("records")})
    print(table.to_string(index=False))
    print(json.dumps({"seconds": round(seconds, 1)}))
    print(f"written: {out}; remove {run} when done (shutil.rmtree)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
