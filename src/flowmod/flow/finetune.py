"""Chapter 13's answer used once: the shipped FastFlowNet fine-tuned on the error that costs.

Chapter 13 finds that what costs a classifier F1 is a far vehicle's motion pulled toward
(or pushed off) the still-world flow: an error of the box's *mean* flow, which end-point
error averaged over pixels barely sees. This module fine-tunes the shipped weights
(:mod:`flowmod.flow.pretrain`) with a loss on exactly that (:func:`flowmod.flow.pretrain.
box_mean_loss`, the length of each far box's mean error) beside the pretraining loss, and a
control that trains the same steps, windows and seed without it, so that what the extra
term does is told apart from what more training does. Both start from the shipped float16
file and train on the pretraining world (:class:`flowmod.flow.pretrain.Recipe`: its own
seed, no scene of the book's), and both are scored, with the shipped weights, on its
validation pairs (the manifest's), never on the book's scenes.

The decision rule, fixed before the run: the fine-tune is adopted only if its validation
box bias (:func:`flowmod.flow.metrics.box_bias`, px) is lower than the control's *and* the
shipped weights', each paired difference's 95 % interval over validation scenes below 0,
and its end-point error in the boxes no worse than the shipped weights' (interval upper end
<= 0.05 px). ``python -m flowmod.flow.finetune`` (``make flownet-finetune``) trains both arms
(resumable), scores them and writes :data:`FINETUNE_RECORD`, which chapter 13 shows;
``benchmarks/flownet.md`` reports the run.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from flowmod.artefacts import file_digest, write_json
from flowmod.flowweights import MANIFEST_NAME, WEIGHTS_NAME
from flowmod.metrics import group_mean_bootstrap, interval
from flowmod.paths import repo_root

#: The committed record of the last run (chapter 13 shows it), relative to the repository.
FINETUNE_RECORD = "benchmarks/finetune.json"
#: Steps of each arm (about 0.9 s a step on 2 cores: both arms in about half an hour).
STEPS = 800
#: The fine-tune's term weight (px of box-mean error against the pyramid loss, about 2 px
#: on these windows: the term weighs about twice the finest level); chosen before the run.
BOX_MEAN_WEIGHT = 4.0
#: Largest rise of the box end-point error (px, the interval's upper end) still adopted.
EPE_TOLERANCE = 0.05


def arms() -> dict[str, Any]:
    """The two recipes: ``control`` continues the last shipped phase's recipe (far-box
    windows and weights, pairs 4-6 frames apart, full-resolution finest level, frames at
    0.75) at a fine-tune's rate and a shorter weight average; ``box_mean`` adds the term."""
    from flowmod.flow.pretrain import SCHEDULE

    control = replace(SCHEDULE[-1], seed=9, steps=STEPS, lr=5e-5, milestones=(STEPS * 5 // 8,),
                      eval_every=STEPS, ema=0.995, init_float16=False)
    return {"control": control, "box_mean": replace(control, box_mean_weight=BOX_MEAN_WEIGHT)}


def paired(a: list[dict[str, float]], b: list[dict[str, float]], scenes: list[str],
           key: str, seed: int = 0) -> dict[str, float]:
    """Mean of ``a`` minus ``b`` in metric ``key`` over the pairs (rows of
    :func:`flowmod.flow.selftrain.pair_metrics`) and its 95 % interval with whole scenes
    resampled."""
    d = np.array([x[key] - y[key] for x, y in zip(a, b, strict=True)], dtype=np.float64)
    lo, hi = interval(group_mean_bootstrap(d, scenes, seed=seed))
    return {"mean": float(np.nanmean(d)), "lo": lo, "hi": hi}


def decide(rows: dict[str, list[dict[str, float]]], scenes: list[str]) -> dict[str, Any]:
    """The module's decision rule on the per-pair validation rows of ``shipped``,
    ``control`` and ``box_mean``: the paired differences it reads and whether it adopts."""
    d = {"bias_vs_control": paired(rows["box_mean"], rows["control"], scenes, "bias_boxes"),
         "bias_vs_shipped": paired(rows["box_mean"], rows["shipped"], scenes, "bias_boxes"),
         "epe_boxes_vs_shipped": paired(rows["box_mean"], rows["shipped"], scenes,
                                        "epe_boxes"),
         "control_bias_vs_shipped": paired(rows["control"], rows["shipped"], scenes,
                                           "bias_boxes"),
         "control_epe_boxes_vs_shipped": paired(rows["control"], rows["shipped"], scenes,
                                                "epe_boxes")}
    adopt = (d["bias_vs_control"]["hi"] < 0 and d["bias_vs_shipped"]["hi"] < 0
             and d["epe_boxes_vs_shipped"]["hi"] <= EPE_TOLERANCE)
    return {"differences": d, "adopt": bool(adopt)}


def _score(state: dict[str, Any], heldout: Any, scale: float) -> list[dict[str, float]]:
    """Per-pair validation rows of a state_dict rounded to float16 (as it would ship)."""
    from flowmod.flow.networks import FastFlowNetFlow
    from flowmod.flow.selftrain import pair_metrics

    half = {k: v.half().float() for k, v in state.items()}
    return pair_metrics(FastFlowNetFlow(half, device="cpu", scale=scale).estimate, heldout)[0]


def run(dataroot: Path, work: Path, shipped: Path, progress: bool = True) -> dict[str, Any]:
    """Train both arms from the ``shipped`` weights (resumable in ``work/<arm>``), score
    them and the shipped weights on the validation pairs, decide; returns the record."""
    from flowmod.flow import pretrain as pt
    from flowmod.flow.selftrain import mean_metrics

    recipes, t0 = arms(), time.time()
    init = pt.load_half(shipped / WEIGHTS_NAME).state_dict()
    # the validation pairs of the manifest (drawn with the first phase's seed); every
    # phase's data is read at its own scale (phase_data)
    last = pt.SCHEDULE[-1]
    world_fp, data, heldout = pt.prepare(pt.SCHEDULE[0], dataroot, work, progress)
    states = {"shipped": init}
    for name, recipe in recipes.items():
        model, _ = pt.train(recipe, pt.phase_data(data, recipe), work / name, recipe.steps,
                            None, progress, init, desc=f"fine-tune fastflownet, {name}")
        states[name] = model.state_dict()
    rows = {k: _score(v, heldout, last.scale) for k, v in states.items()}
    return {"recipes": {k: asdict(v) for k, v in recipes.items()},
            "shipped_sha256": file_digest(shipped / WEIGHTS_NAME),
            "world": {"fingerprint": world_fp, "shipped_on": json.loads(
                (shipped / MANIFEST_NAME).read_text())["world"]["fingerprint"]},
            "validation": {"pairs": len(heldout.img1), "pair_scenes": list(heldout.scenes),
                           "means": {k: mean_metrics(v) for k, v in rows.items()},
                           "rows": rows},
            "decision": decide(rows, heldout.scenes),
            "wall_seconds": time.time() - t0,
            "where": {"machine": platform.machine(), "threads": last.threads}}


def main(argv: list[str] | None = None) -> int:
    """``python -m flowmod.flow.finetune``: train, score and decide (see the module)."""
    from flowmod.flow.pretrain import WEIGHTS_DIR

    ap = argparse.ArgumentParser(prog="python -m flowmod.flow.finetune",
                                 description=main.__doc__)
    ap.add_argument("--dataroot", type=Path, default=repo_root() / "data" / "pretrain")
    ap.add_argument("--work", type=Path, default=repo_root() / "runs" / "finetune")
    ap.add_argument("--shipped", type=Path, default=repo_root() / WEIGHTS_DIR)
    ap.add_argument("--record", type=Path, default=repo_root() / FINETUNE_RECORD,
                    help="where the record goes (chapter 13 shows the default's)")
    args = ap.parse_args(argv)
    if not (args.shipped / WEIGHTS_NAME).is_file():
        raise SystemExit(f"no weights in {args.shipped}: give --shipped the folder of a "
                         "weights.pt and its manifest.json")
    record = run(args.dataroot.resolve(), args.work, args.shipped)
    write_json(args.record, record)
    means = record["validation"]["means"]
    for k, m in means.items():
        print(f"[finetune] {k}: box bias {m['bias_boxes']:.3f} px, box EPE "
              f"{m['epe_boxes']:.3f} px, EPE {m['epe']:.2f} px", flush=True)
    print(f"[finetune] adopt: {record['decision']['adopt']} ({args.record})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
