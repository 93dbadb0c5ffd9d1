"""Peak memory against data size: crops, training and evaluation at 1x, 4x, 16x the objects.

    .venv/bin/python benchmarks/bench_scale.py [--profile demo] [--method dis]
        [--factors 1,4,16] [--stages crops,train,evaluate] [--device cpu]

Source: a built run (``runs/demo``, else ``runs/smoke``): its published crops, flow and model
of one flow method. For every stage and factor the base objects are replicated on disk into a
temporary folder, in the layout the code reads (``<split>.npy`` float16 (N, 2, S, S) memmap +
``<split>.parquet`` index; for the crops stage an objects table whose pairs are renamed copies
``<pair_id>~rNN`` of real pairs, each loading the real flow), and the stage runs through the
library's own functions in a fresh subprocess (``--one STAGE FACTOR ...``):

* crops: ``crops.build_crops`` on the test split's objects (flow via ``FlowReader.load``);
* train: ``train.train_model`` for one epoch (``epochs=1``, Table 2 settings of the profile,
  ``num_workers=0``, no ``record``) on a train subset (128 objects at 1x: one batch),
  validating on a val subset (256 at 1x); ``epochs=1`` is the only bound train_model has,
  so the work grows with the factor (~1-3 min of the ~2-4 min total on 2 CPU cores);
* evaluate: ``evaluate.predict_models`` on the test split with the published model of seed 0
  (the prediction step of the evaluate stage; the geometric baseline is not measured).

A run cross-validated over scene folds (the demo profile) has folds, not splits: fold 0
serves as the test split (with the model of fold 0, which never saw it), fold 1 as train and
fold 2 (else 1) as val.

Each subprocess reports its peak RSS (``ru_maxrss``), its RSS right after its imports
(baseline), the growth between the two, wall seconds and objects/s; also the peak
anonymous and file-backed RSS seen by a 5 ms sampler of ``/proc/self/status``. Pages of a
memmap that the code has touched count in RSS (file-backed, reclaimable) even when it streams,
so ``ru_maxrss`` of a streaming stage grows by about the bytes of the crops it reads or writes;
the anonymous column shows the memory the code actually holds.

Writes ``benchmarks/results/scale.json`` and prints a table and, per stage, the ratio of the
growth at the largest factor to the growth at 1x: PASS when it stays under 1.5x the 1x growth
+ 50 MB (MB = MiB here). Reported, never asserted (exit 0 on FAIL): the machine is shared.
Exit 2 when no built run is found.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

STAGES = ("crops", "train", "evaluate")
SEP = "~r"  # replicated pair ids: <pair_id>~r00, <pair_id>~r01, ...
SLACK_MB, SLACK_RATIO = 50.0, 1.5


# --- memory probes ---------------------------------------------------------------------------


def _maxrss_mb() -> float:
    """Peak RSS of this process so far (``ru_maxrss``: KiB on Linux, bytes on macOS), MiB."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (1024 * 1024) if sys.platform == "darwin" else r / 1024


def _status_mb() -> dict[str, float]:
    """VmRSS, RssAnon, RssFile of this process now (MiB); empty where /proc is missing."""
    out: dict[str, float] = {}
    try:
        with open("/proc/self/status") as f:
            for line in f:
                key, _, rest = line.partition(":")
                if key in ("VmRSS", "RssAnon", "RssFile"):
                    out[key] = int(rest.split()[0]) / 1024  # kB
    except OSError:
        pass
    return out


class _Sampler(threading.Thread):
    """Peak RssAnon / RssFile, sampled every ``interval`` s (may miss very short spikes)."""

    def __init__(self, interval: float = 0.005) -> None:
        super().__init__(daemon=True)
        self.interval = interval
        self.peak = {"RssAnon": 0.0, "RssFile": 0.0}
        self._done = threading.Event()

    def sample(self) -> None:
        s = _status_mb()
        for k in self.peak:
            self.peak[k] = max(self.peak[k], s.get(k, 0.0))

    def run(self) -> None:
        while not self._done.is_set():
            self.sample()
            self._done.wait(self.interval)

    def finish(self) -> dict[str, float]:
        self._done.set()
        self.join()
        self.sample()
        return self.peak


# --- one measurement (the subprocess) ----------------------------------------------------------


def run_one(stage: str, factor: int, data: Path, profile: str, method: str, device: str,
            model: str, model_amp: str | None, result: Path) -> int:
    """Run one stage on the replicated data in ``data``; write its figures to ``result``."""
    import numpy as np  # noqa: F401  (imports are part of the baseline, same for every stage)
    import pandas as pd
    import torch

    from flowmod import crops, evaluate, train
    from flowmod.chapters.common import flow_reader
    from flowmod.params import load_profile

    base_peak = _maxrss_mb()
    base_now = _status_mb()
    p = load_profile(profile)
    sampler = _Sampler()
    sampler.start()
    t0 = time.perf_counter()
    extra: dict[str, Any] = {}
    if stage == "crops":
        objects = pd.read_parquet(data / "objects.parquet")
        reader = flow_reader(p, method, "keyframe")
        info = crops.build_crops(
            objects, lambda pid: reader.load(pid.split(SEP, 1)[0]), data / "built",
            size=p.crop_size, scale=p.crop_scale, splits=["test"], progress=False)
        n = int(info["test"]["rows"])
        extra["pairs"] = int(info["test"]["pairs"])
    elif stage == "train":
        tx, tdf = crops.read_crops(data, "train")
        vx, vdf = crops.read_crops(data, "val")
        train.train_model(
            tx, tdf, vx, vdf, data / "train_out", train.TrainSettings.of(p), seed=p.seed,
            resume=False, progress=False, epochs=1, num_workers=0, device=device)
        n = len(tdf)
        extra["val_objects"] = len(vdf)
    elif stage == "evaluate":
        x, df = crops.read_crops(data, "test")
        preds = evaluate.predict_models([("s0", Path(model), model_amp)], x, df, device)
        n = len(preds)
    else:
        raise SystemExit(f"unknown stage {stage!r}; one of {STAGES}")
    seconds = time.perf_counter() - t0
    peaks = sampler.finish()
    peak = _maxrss_mb()
    end = _status_mb()
    out = {
        "stage": stage, "factor": factor, "objects": n, **extra,
        "seconds": seconds, "objects_per_s": n / seconds if seconds > 0 else None,
        "peak_rss_mb": peak, "baseline_rss_mb": base_peak, "growth_mb": peak - base_peak,
        "rss_after_imports_now_mb": base_now.get("VmRSS"),
        "baseline_anon_mb": base_now.get("RssAnon"),
        "peak_anon_mb_sampled": peaks["RssAnon"] or None,
        "anon_growth_mb": (peaks["RssAnon"] - base_now["RssAnon"]
                           if "RssAnon" in base_now else None),
        "peak_file_mb_sampled": peaks["RssFile"] or None,
        "baseline_file_mb": base_now.get("RssFile"),
        "file_growth_mb": (peaks["RssFile"] - base_now["RssFile"]
                           if "RssFile" in base_now else None),
        "end_file_mb": end.get("RssFile"), "torch_threads": torch.get_num_threads(),
    }
    result.write_text(json.dumps(out))
    return 0


# --- the source run and its replication (the parent) -------------------------------------------


class NoRun(Exception):
    """No built run to take the base objects from."""


def source_splits(folder: Path) -> dict[str, str]:
    """The published crop files that serve as train, val and test: the splits themselves,
    or, for a run cross-validated over folds, folds 1, 2 (else 1) and 0."""
    if (folder / "test.npy").is_file():
        return {"train": "train", "val": "val", "test": "test"}
    folds = sorted(q.stem for q in folder.glob("f[0-9]*.npy") if q.stem[1:].isdigit())
    if len(folds) < 2:
        raise FileNotFoundError(f"{folder}: neither train/val/test crops nor two folds")
    return {"train": folds[1], "val": folds[2 if len(folds) > 2 else 1], "test": folds[0]}


def find_source(profiles: list[str], method: str | None) -> dict[str, Any]:
    """The first profile whose run has published crops and flow of ``method`` (default: its
    first estimated flow method); the published model that never saw its test objects (seed 0,
    or fold 0's), if any."""
    from flowmod import dag, pipeline
    from flowmod.chapters.common import flow_reader, model_path
    from flowmod.crops import read_crops
    from flowmod.params import ProfileError, load_profile

    why = []
    for name in profiles:
        try:
            p = load_profile(name)
            m = method or next((x for x in p.flow_methods if x != "gt"), p.flow_methods[0])
            folder = pipeline.published(p, dag.Node("crops", m, "keyframe"))
            splits = source_splits(folder)
            for split in splits.values():
                read_crops(folder, split)
            reader = flow_reader(p, m, "keyframe")
            first = reader.index["pair_id"].iloc[0]
            if not reader.path(first).is_file():
                raise FileNotFoundError(f"flow file {reader.path(first)} missing")
        except (ProfileError, dag.MissingInput, OSError, ValueError, KeyError) as e:
            why.append(f"{name}: {type(e).__name__}: {e}")
            continue
        part = "s0" if splits["test"] == "test" else splits["test"]
        model, amp = None, None
        try:
            model = model_path(p, m, part)
            rec = pipeline.recorded(p, dag.Node("train", m, part)) or {}
            amp = None if rec.get("amp", "off") in (None, "off") else rec["amp"]
            if not model.is_file():
                model = None
        except dag.MissingInput:
            model = None
        return {"profile": name, "params": p, "method": m, "crops": folder, "model": model,
                "model_amp": amp, "run": str(p.run_path), "splits": splits,
                "flow_pairs": set(reader.pair_ids)}
    raise NoRun("\n  ".join(why))


def _tagged(df: Any, k: int) -> Any:
    """Copy ``k`` of index rows: pair and annotation ids renamed ``<id>~rNN``."""
    out = df.assign(pair_id=df["pair_id"].astype(str) + f"{SEP}{k:02d}")
    if "ann_token" in out:
        out["ann_token"] = out["ann_token"].astype(str) + f"{SEP}{k:02d}"
    return out


def replicate_split(src: Path, split: str, rows: Any, factor: int, out: Path,
                    name: str | None = None) -> int:
    """Write ``factor`` copies of ``rows`` of a published split as ``<out>/<name>.npy``
    (float16 memmap, filled copy by copy) + ``<name>.parquet``; returns the rows written."""
    import numpy as np
    import pandas as pd

    from flowmod.crops import read_crops

    x, df = read_crops(src, split)
    base = np.asarray(x[rows])
    n = len(base)
    arr = np.lib.format.open_memmap(out / f"{name or split}.npy", mode="w+", dtype=np.float16,
                                    shape=(n * factor, *base.shape[1:]))
    for k in range(factor):
        arr[k * n:(k + 1) * n] = base
    arr.flush()
    del arr
    sub = df.iloc[rows].reset_index(drop=True)
    pd.concat([_tagged(sub, k) for k in range(factor)], ignore_index=True).to_parquet(
        out / f"{name or split}.parquet", index=False)
    return n * factor


def _subset(n: int, k: int, seed: int = 0) -> Any:
    """Sorted random ``k`` of ``range(n)`` (all of them when k <= 0 or k >= n)."""
    import numpy as np

    if k <= 0 or k >= n:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, size=k, replace=False))


def prepare(stage: str, factor: int, src: dict[str, Any], args: argparse.Namespace,
            data: Path) -> None:
    """The replicated inputs of one stage at one factor, in ``data``."""
    import pandas as pd

    from flowmod.crops import read_crops

    data.mkdir(parents=True)
    folder, splits = src["crops"], src["splits"]
    if stage == "crops":
        # the test split's objects as the crops stage received them (the crop index is the
        # objects table sorted by pair), each pair copied ``factor`` times under a new id
        _, df = read_crops(folder, splits["test"])
        df = df.assign(split="test")
        # a run in crops mode keeps the flow of some pairs only
        pairs = df["pair_id"].drop_duplicates()
        pairs = pairs[pairs.isin(src["flow_pairs"])]
        if pairs.empty:
            raise RuntimeError(f"no test pair of {folder} has its flow stored")
        if args.base_crops_pairs > 0:
            pairs = pairs.iloc[: args.base_crops_pairs]
        sub = df[df["pair_id"].isin(set(pairs))].reset_index(drop=True)
        pd.concat([_tagged(sub, k) for k in range(factor)], ignore_index=True).to_parquet(
            data / "objects.parquet", index=False)
    elif stage == "train":
        for split, k in (("train", args.base_train), ("val", args.base_val)):
            n = len(read_crops(folder, splits[split])[1])
            replicate_split(folder, splits[split], _subset(n, k), factor, data, name=split)
    elif stage == "evaluate":
        n = len(read_crops(folder, splits["test"])[1])
        replicate_split(folder, splits["test"], _subset(n, args.base_eval), factor, data,
                        name="test")
    else:
        raise ValueError(stage)


def measure(stage: str, factor: int, src: dict[str, Any], args: argparse.Namespace,
            tmp: Path, model: Path) -> dict[str, Any]:
    data = tmp / f"{stage}_x{factor}"
    t0 = time.perf_counter()
    prepare(stage, factor, src, args, data)
    prep_s = time.perf_counter() - t0
    result = tmp / f"{stage}_x{factor}.json"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--one", stage, str(factor),
           "--data", str(data), "--profile", src["profile"], "--method", src["method"],
           "--device", args.device, "--model", str(model),
           "--model-amp", src["model_amp"] or "none", "--result", str(result)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
    shutil.rmtree(data, ignore_errors=True)
    if proc.returncode != 0 or not result.is_file():
        sys.stderr.write(proc.stdout[-4000:] + proc.stderr[-4000:])
        raise RuntimeError(f"{stage} x{factor}: subprocess exited {proc.returncode}")
    row = json.loads(result.read_text())
    row["prepare_seconds"] = prep_s
    return row


# --- report ------------------------------------------------------------------------------------


def _fmt(v: Any, nd: int = 1) -> str:
    return "-" if v is None else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))


def table(rows: list[dict[str, Any]]) -> str:
    cols = [("stage", "stage", 0), ("factor", "x", 0), ("objects", "objects", 0),
            ("peak_rss_mb", "peak RSS", 1), ("baseline_rss_mb", "baseline", 1),
            ("growth_mb", "growth", 1), ("anon_growth_mb", "anon growth*", 1),
            ("file_growth_mb", "file growth*", 1), ("seconds", "seconds", 1),
            ("objects_per_s", "objects/s", 1)]
    cells = [[h for _, h, _ in cols]] + [[_fmt(r.get(k), nd) for k, _, nd in cols] for r in rows]
    widths = [max(len(c[i]) for c in cells) for i in range(len(cols))]
    lines = ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(
        line, widths, strict=True))) for line in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def verdict(rows: list[dict[str, Any]], key: str) -> dict[str, Any] | None:
    """Growth at the largest factor against 1x (the smallest) for one stage's rows."""
    rs = sorted(rows, key=lambda r: r["factor"])
    if len(rs) < 2 or rs[0].get(key) is None or rs[-1].get(key) is None:
        return None
    g1, gn = max(rs[0][key], 0.0), max(rs[-1][key], 0.0)
    limit = SLACK_RATIO * g1 + SLACK_MB
    dn = rs[-1]["objects"] - rs[0]["objects"]
    # the slope between the two largest factors leaves out the warm-up of a tiny 1x (one
    # training batch: optimizer state and allocator caches are not at their steady state)
    dt = rs[-1]["objects"] - rs[-2]["objects"]
    return {"factor_lo": rs[0]["factor"], "factor_hi": rs[-1]["factor"],
            "growth_lo_mb": g1, "growth_hi_mb": gn,
            "ratio": gn / g1 if g1 > 0 else None, "limit_mb": limit,
            "mb_per_1k_objects": (gn - g1) / dn * 1000 if dn else None,
            "factor_tail": rs[-2]["factor"],
            "tail_mb_per_1k_objects": ((gn - max(rs[-2][key], 0.0)) / dt * 1000
                                       if dt else None),
            "flat": bool(gn < limit)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--one", nargs=2, metavar=("STAGE", "FACTOR"),
                    help="internal: measure one stage at one factor (in a fresh process)")
    ap.add_argument("--data", type=Path, help="internal: the replicated inputs")
    ap.add_argument("--result", type=Path, help="internal: where to write the figures")
    ap.add_argument("--model", default="", help="internal: the model for evaluate")
    ap.add_argument("--model-amp", default="none", help="internal: its precision")
    ap.add_argument("--profile", default=None,
                    help="run to take the data from (default: demo, else smoke)")
    ap.add_argument("--method", default=None, help="flow method (default: the profile's "
                    "first estimated one)")
    ap.add_argument("--factors", default="1,4,16")
    ap.add_argument("--stages", default=",".join(STAGES))
    ap.add_argument("--device", default="cpu", help="torch device for train/evaluate")
    ap.add_argument("--base-train", type=int, default=128,
                    help="train objects at 1x (training is ~50 objects/s on 2 CPU cores)")
    ap.add_argument("--base-val", type=int, default=256,
                    help="val objects at 1x (256 = train_model's eval batch: every factor "
                    "validates in full batches)")
    ap.add_argument("--base-eval", type=int, default=0,
                    help="test objects at 1x for evaluate (0: the whole test split)")
    ap.add_argument("--base-crops-pairs", type=int, default=0,
                    help="test pairs at 1x for crops (0: all the test split's pairs)")
    ap.add_argument("--timeout", type=float, default=900, help="seconds per subprocess")
    ap.add_argument("--tmp", type=Path, default=None, help="folder for the replicated data")
    ap.add_argument("--out", type=Path,
                    default=Path(__file__).resolve().parent / "results" / "scale.json")
    args = ap.parse_args(argv)

    if args.one:
        amp = None if args.model_amp in ("none", "off", "") else args.model_amp
        return run_one(args.one[0], int(args.one[1]), args.data, args.profile, args.method,
                       args.device, args.model, amp, args.result)

    factors = sorted({int(f) for f in args.factors.split(",")})
    stages = [s.strip() for s in args.stages.split(",") if s.strip()]
    bad = [s for s in stages if s not in STAGES]
    if bad or not factors or factors[0] < 1:
        ap.error(f"stages must be among {STAGES} (got {bad}); factors >= 1 (got {factors})")
    try:
        src = find_source([args.profile] if args.profile else ["demo", "smoke"], args.method)
    except NoRun as e:
        print("bench_scale: no built run with published crops and flow to measure:\n  "
              f"{e}\nBuild one first: `make book` (profile demo, ~30 min) or "
              "`.venv/bin/python -m flowmod.runner --profile smoke` (minutes), then rerun "
              "(with --profile smoke for the latter).", file=sys.stderr)
        return 2

    import torch

    from flowmod.artefacts import write_json

    t_all = time.perf_counter()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="bench_scale_", dir=args.tmp) as d:
        tmp = Path(d)
        model = src["model"]
        if model is None and "evaluate" in stages:
            # no published model: an untrained one has the same memory behaviour
            from flowmod.model import motion_resnet18

            model = tmp / "untrained.pt"
            torch.save(motion_resnet18().state_dict(), model)
            print("no published model of seed 0: evaluate uses an untrained ResNet18")
        print(f"source: {src['run']} ({src['profile']}), method {src['method']}, crops "
              f"{src['crops']}; factors {factors}; one subprocess per measurement")
        for stage in stages:
            for f in factors:
                print(f"  {stage} x{f} ...", end="", flush=True)
                row = measure(stage, f, src, args, tmp, Path(model or ""))
                rows.append(row)
                print(f" {row['objects']} objects, {row['seconds']:.1f} s, peak RSS "
                      f"{row['peak_rss_mb']:.0f} MiB", flush=True)

    crop_shape = None
    try:
        from flowmod.crops import read_crops

        crop_shape = list(read_crops(src["crops"], "test")[0].shape[1:])
    except Exception:  # noqa: BLE001 - only for the reference figure
        pass
    summary = {}
    print()
    print(table(rows))
    print("all MiB. growth = peak RSS (ru_maxrss) - ru_maxrss after imports. * sampled every "
          "5 ms from /proc/self/status, peak minus the value after imports: anon = RssAnon "
          "(heap, tensors), file = RssFile (memmap pages touched, libraries loaded late)")
    print()
    f32_per_1k = (4 * math.prod(crop_shape) * 1000 / 2**20
                  if crop_shape else None)
    for stage in stages:
        sr = [r for r in rows if r["stage"] == stage]
        v = verdict(sr, "growth_mb")
        va = verdict(sr, "anon_growth_mb")
        summary[stage] = {"rss": v, "anon": va}
        if v is None:
            continue
        ratio = "n/a" if v["ratio"] is None else f"{v['ratio']:.2f}"
        line = (f"{stage:9s} growth x{v['factor_hi']} / x{v['factor_lo']}: "
                f"{v['growth_hi_mb']:.1f} / {v['growth_lo_mb']:.1f} MiB = {ratio} "
                f"(limit {v['limit_mb']:.1f} MiB) -> {'PASS' if v['flat'] else 'FAIL'}; MiB per 1k "
                f"objects x{v['factor_lo']}->x{v['factor_hi']} "
                f"{_fmt(v['mb_per_1k_objects'], 2)}, x{v['factor_tail']}->x{v['factor_hi']} "
                f"{_fmt(v['tail_mb_per_1k_objects'], 2)}")
        if va is not None:
            line += (f"\n{'':10s}anon only: {va['growth_hi_mb']:.1f} / "
                     f"{va['growth_lo_mb']:.1f} MiB -> {'PASS' if va['flat'] else 'FAIL'}; "
                     f"MiB per 1k objects {_fmt(va['mb_per_1k_objects'], 2)}, "
                     f"{_fmt(va['tail_mb_per_1k_objects'], 2)}")
        print(line)
    if f32_per_1k:
        print(f"reference: one float32 copy of a split = {f32_per_1k:.1f} MiB per 1k objects "
              f"(crops {crop_shape}), its float16 memmap {f32_per_1k / 2:.1f}")
    result = {
        "units": "MiB (2**20 bytes); ru_maxrss peak; baseline = ru_maxrss after imports",
        "criterion": f"flat if growth at the largest factor < {SLACK_RATIO} x growth at 1x "
                     f"+ {SLACK_MB} MiB",
        "machine": {"platform": platform.platform(), "python": platform.python_version(),
                    "torch": torch.__version__, "cpus": os.cpu_count(),
                    "threads": torch.get_num_threads()},
        "source": {"profile": src["profile"], "run": src["run"], "method": src["method"],
                   "crops": str(src["crops"]), "model": str(src["model"])},
        "config": {"factors": factors, "base_train": args.base_train,
                   "base_val": args.base_val, "base_eval": args.base_eval,
                   "base_crops_pairs": args.base_crops_pairs, "device": args.device,
                   "crop_shape": crop_shape},
        "rows": rows, "summary": summary,
        "total_seconds": time.perf_counter() - t_all,
    }
    write_json(args.out, result)
    print(f"written: {args.out} ({result['total_seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
