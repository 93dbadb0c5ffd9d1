"""Seconds per pair of the exact flow, before and after issue 49 item 3, beside DIS.

    .venv/bin/python benchmarks/bench_gt.py [--reps 7]

One scene at the demo profile's world settings (as ``profile_hot.py``), its keyframe pairs
in order, timed alternately, ``--reps`` rounds (the machine is noisy: read the medians'
ratios, measured in the same rounds):

- ``before``: the replaced whole-frame code (``tests/test_truth.py``'s reference), pair 0;
- ``cold``: today's ``flow_between`` on pair 0 with empty caches (both frames rendered);
- ``chain``: today's, every pair of the scene in order, caches emptied first (each frame
  rendered once, as the flow stage meets a scene's consecutive pairs), per pair;
- ``dis``, ``dis_1thread``: DIS on pair 0's images at the demo's flow scale, OpenCV's
  default threads and one thread (the flow stage's workers run one thread each).

Prints the medians and writes them to ``benchmarks/results/bench_gt.json``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from flowmod.flow import get_estimator, read_image
from flowmod.params import load_profile
from flowmod.world import truth

HERE = Path(__file__).parent
RESULTS = HERE / "results"


def _reference():
    """``_reference_flow`` of tests/test_truth.py (the code before item 3)."""
    spec = importlib.util.spec_from_file_location("test_truth", HERE.parent / "tests" /
                                                  "test_truth.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod._reference_flow


def _seconds(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def _forget() -> None:
    truth._depth_frame.cache_clear()
    truth._agent_pose.cache_clear()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=7)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(HERE))
    from profile_hot import first_pair, world_scene

    reference = _reference()
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        world_scene(root)
        key = truth._world_key(root, "v1.0-synth")
        geo = truth._geometry(*key, 0)
        ts = [(f["ts"] - geo.scene["t0_us"]) / 1e6 for f in geo.scene["frames"]]
        pairs = list(zip(ts[:-1], ts[1:], strict=True))
        _, _, p1, p2 = first_pair(root)
        a, b = read_image(p1), read_image(p2)
        dis = get_estimator("dis", scale=load_profile("demo").flow_scale)
        threads = cv2.getNumThreads()

        def dis_1thread() -> None:
            cv2.setNumThreads(1)
            dis.estimate(a, b)
            cv2.setNumThreads(threads)

        def chain() -> None:
            for t1, t2 in pairs:
                truth.flow_between(geo, t1, t2)

        cases = {
            "before": lambda: reference(geo, *pairs[0]),
            "cold": lambda: _forget() or truth.flow_between(geo, *pairs[0]),
            "chain": lambda: _forget() or chain(),
            "dis": lambda: dis.estimate(a, b),
            "dis_1thread": dis_1thread,
        }
        per = {"chain": len(pairs)}
        for fn in cases.values():  # warm: imports, the rays' cache
            fn()
        times: dict[str, list[float]] = {k: [] for k in cases}
        for _ in range(args.reps):
            for k, fn in cases.items():
                times[k].append(_seconds(fn) / per.get(k, 1))
    med = {k: float(np.median(v)) for k, v in times.items()}
    out = {"seconds_per_pair_median": {k: round(v, 4) for k, v in med.items()},
           "ratio_to_dis": {k: round(v / med["dis"], 2) for k, v in med.items()},
           "ratio_to_dis_1thread": {k: round(v / med["dis_1thread"], 2) for k, v in med.items()},
           "reps": args.reps, "pairs_in_chain": len(pairs)}
    print(json.dumps(out, indent=2))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "bench_gt.json").write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
