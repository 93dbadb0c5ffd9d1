"""A second ``make book`` with nothing changed: how long it takes, and that no stage recomputes.

    .venv/bin/python benchmarks/bench_rerun.py [--profile demo] [--make "make book"]

Runs the command once (it should find everything up to date), records the wall time, the
seconds and reuse of each notebook (``build/executed/run_info.json``) and every node's
manifest before and after (a rebuilt node has a new manifest), and writes
``benchmarks/results/rerun.json``. Reported, never asserted: the machine is noisy.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time

from flowmod import pipeline
from flowmod.artefacts import write_json
from flowmod.params import load_profile
from flowmod.paths import repo_root


def manifests(p) -> dict[str, float | None]:
    return {str(n): (pipeline.recorded(p, n) or {}).get("written") for n in pipeline.nodes(p)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--profile", default="demo")
    ap.add_argument("--make", default="make book", help="the command to time")
    args = ap.parse_args(argv)
    root = repo_root()
    p = load_profile(args.profile)
    stale_before = [str(s.node) for s in pipeline.status(p) if s.state != "up to date"]
    before = manifests(p)
    t0 = time.perf_counter()
    proc = subprocess.run(shlex.split(args.make) + [f"PROFILE={args.profile}"], cwd=root)
    seconds = time.perf_counter() - t0
    after = manifests(p)
    info = json.loads((root / "build" / "executed" / "run_info.json").read_text())
    result = {
        "command": f"{args.make} PROFILE={args.profile}", "exit_code": proc.returncode,
        "seconds": round(seconds, 1), "stale_before": stale_before,
        "rebuilt": [n for n in after if after[n] != before.get(n)],
        "notebooks": info["notebooks"],
    }
    out = root / "benchmarks" / "results" / "rerun.json"
    write_json(out, result)
    print(json.dumps({k: v for k, v in result.items() if k != "notebooks"}, indent=1))
    print(f"written: {out}")
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
