"""A cold ``make book`` on a fresh clone: its wall time and each chapter's share.

    .venv/bin/python benchmarks/bench_cold.py [--commit HEAD] [--profile demo] [--keep DIR]

Clones ``--commit`` of this repository into a temporary folder (or ``--keep DIR``), runs
``make book`` there from nothing (its own venv, world, artefacts), and writes
``benchmarks/results/cold-<commit>.json``: the wall time of the whole command, the seconds of
each notebook (``build/executed/run_info.json``) and the rest (venv, rendering, browser
check). Run it for two commits one after the other on one machine: machines of one kind
differ by 2x, so compare the ratio. Reported, never asserted; it takes the better part of an
hour.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from flowmod.artefacts import write_json
from flowmod.paths import repo_root


def git(*args: str, cwd: Path) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True,
                          text=True).stdout.strip()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--commit", default="HEAD")
    ap.add_argument("--profile", default="demo")
    ap.add_argument("--keep", type=Path, help="clone here and keep it (default: a temp dir)")
    args = ap.parse_args(argv)
    root = repo_root()
    sha = git("rev-parse", args.commit, cwd=root)
    work = args.keep or Path(tempfile.mkdtemp(prefix="flowmod-cold-"))
    if work.exists() and any(work.iterdir()):
        print(f"{work} is not empty: give an empty or new folder", file=sys.stderr)
        return 2
    subprocess.run(["git", "clone", "-q", str(root), str(work)], check=True)
    git("checkout", "-q", sha, cwd=work)
    t0 = time.perf_counter()
    proc = subprocess.run(["make", "book", f"PROFILE={args.profile}"], cwd=work)
    seconds = time.perf_counter() - t0
    info_path = work / "build" / "executed" / "run_info.json"
    info = json.loads(info_path.read_text()) if info_path.is_file() else {"notebooks": {}}
    notebooks = {k: v.get("seconds") for k, v in info["notebooks"].items()}
    result = {"commit": sha, "date": time.strftime("%Y-%m-%d %H:%M"), "profile": args.profile,
              "exit_code": proc.returncode, "seconds": round(seconds, 1),
              "notebooks_seconds": round(sum(v or 0 for v in notebooks.values()), 1),
              "notebooks": notebooks}
    out = root / "benchmarks" / "results" / f"cold-{sha[:7]}.json"
    write_json(out, result)
    print(json.dumps(result, indent=1))
    print(f"written: {out}")
    if args.keep is None:
        shutil.rmtree(work, ignore_errors=True)
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
