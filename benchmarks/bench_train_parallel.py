"""Two demo classifiers trained one after the other on two threads, against the same two
trained at once in two processes of one thread each (issue 49, item 2).

The demo's network and recipe (width 32, 40-px crops, batches of 32, log input) on 1,900
random training and 450 validation crops, ``--epochs`` epochs each. Prints the wall seconds
of both ways and their ratio, and whether each model's weights are equal bit for bit
between a one-thread run alone and a one-thread run beside another (the parallel build's
promise). Never run it beside other work: two torch processes that share the cores with a
third spin-wait (``benchmarks/profile.md``).

    .venv/bin/python benchmarks/bench_train_parallel.py [--epochs 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHILD = """
import sys, numpy as np, pandas as pd, torch, hashlib
torch.set_num_threads(int(sys.argv[1]))
from flowmod.train import train_model
rng = np.random.default_rng(int(sys.argv[2]))
def split(n):
    x = rng.normal(0, 2, (n, 2, 40, 40)).astype(np.float16)
    y = rng.integers(0, 2, n)
    x[y == 1, 0] += 0.8
    return x, pd.DataFrame({"label": y})
tx, tdf = split(1900)
vx, vdf = split(450)
train_model(tx, tdf, vx, vdf, sys.argv[3], seed=int(sys.argv[2]), epochs=int(sys.argv[4]),
            batch_size=32, width=32, input_mode="log", progress=False, step_size=3, gamma=0.3)
sd = torch.load(sys.argv[3] + "/best.pt", weights_only=True)
print(hashlib.sha256(b"".join(v.numpy().tobytes() for v in sd.values())).hexdigest()[:16])
"""


def run(threads: int, seeds: list[int], epochs: int, parallel: bool) -> tuple[float, list[str]]:
    """Wall seconds of training one model per seed, at once or one after the other."""
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "OMP_NUM_THREADS": str(threads)}
    with tempfile.TemporaryDirectory() as tmp:
        cmds = [[sys.executable, "-c", CHILD, str(threads), str(s), f"{tmp}/m{s}", str(epochs)]
                for s in seeds]
        t = time.perf_counter()
        if parallel:
            procs = [subprocess.Popen(c, env=env, stdout=subprocess.PIPE, text=True)
                     for c in cmds]
            out = [p.communicate()[0].strip() for p in procs]
        else:
            out = [subprocess.run(c, env=env, stdout=subprocess.PIPE, text=True,
                                  check=True).stdout.strip() for c in cmds]
        return time.perf_counter() - t, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=2)
    args = ap.parse_args()
    seeds = [1, 2]
    seq2, h_seq2 = run(2, seeds, args.epochs, parallel=False)
    par1, h_par1 = run(1, seeds, args.epochs, parallel=True)
    seq1, h_seq1 = run(1, seeds, args.epochs, parallel=False)
    result = {"epochs": args.epochs, "sequential_2_threads_s": round(seq2, 1),
              "parallel_2x1_thread_s": round(par1, 1), "sequential_1_thread_s": round(seq1, 1),
              "ratio_2threads_over_parallel": round(seq2 / par1, 2),
              "one_thread_alone_equals_beside_another": h_par1 == h_seq1,
              "two_threads_equals_one_thread": h_seq2 == h_seq1}
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
