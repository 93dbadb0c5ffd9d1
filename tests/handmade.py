"""A hand-made study (quick, no world, no training): the files each stage of the demo
profile publishes (its ``<split>.parquet`` tables through :func:`flowmod.evaluate.write_frames`,
the evaluate node's scores by :func:`flowmod.evaluate.score`, a manifest), in a demo-profile
run folder, with predictions whose tables all score differently. The chapters' quick tests
read their backends' numbers off it (``handmade_study`` in conftest.py) and compute the
expected ones from the same tables by hand.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from flowmod import pipeline
from flowmod.artefacts import write_manifest
from flowmod.dag import Node
from flowmod.evaluate import score, write_frames
from flowmod.extensions.inputs import chains
from flowmod.params import Params, load_profile

#: Scenes of the hand-made sets (three per fold) and objects per scene.
SCENES, PER_SCENE = 9, 12
#: |A - B| (F1 points) every hand-made effect exceeds, so that B - A is another number.
POWER = 0.5


def _objects(kind: str, rng: np.random.Generator) -> pd.DataFrame:
    """A scored set: half the objects moving, scenes in three folds; the test split's in
    Table 1's band, the generalisation set's from 2 to 100 m (beyond Table 4's 70 m too)."""
    n = SCENES * PER_SCENE
    scene = np.repeat(np.arange(SCENES), PER_SCENE)
    lo, hi = (30.0, 70.0) if kind == "test" else (2.0, 100.0)
    return pd.DataFrame({"ann_token": [f"{kind}-{i}" for i in range(n)],
                         "instance_token": [f"{kind}-vehicle-{i // 3}" for i in range(n)],
                         "scene": [f"scene-{s}" for s in scene], "fold": scene % 3,
                         "label": rng.permutation(np.arange(n) % 2),
                         "distance": rng.uniform(lo, hi, n), "category": "vehicle.car"})


def _predicted(obj: pd.DataFrame, error: float, seeds: int, rng: np.random.Generator
               ) -> pd.DataFrame:
    """``obj`` with the probabilities of ``seeds`` models (``prob_s<k>`` and ``prob``, seed
    0's, as :func:`flowmod.evaluate.predict_models` writes them; ``prob`` alone for one):
    each on the wrong side of 0.5 for a share ``error`` of the objects, never at 0.5."""
    y = obj["label"].to_numpy()
    probs = []
    for _ in range(seeds):
        right = np.where(y == 1, 0.8, 0.2) + rng.uniform(-0.15, 0.15, len(y))
        probs.append(np.where(rng.random(len(y)) < error, 1.0 - right, right))
    cols = {"prob": probs[0]} if seeds == 1 else {
        **{f"prob_s{k}": p for k, p in enumerate(probs)}, "prob": probs[0]}
    return obj.assign(**cols)


def node_folder(p: Params, node: Node, **record) -> Path:
    """``node``'s published folder as a build leaves it, for a test to write the node's
    files into: made on first use with its manifest (fingerprint ``hand-made <node>`` and
    ``record``, e.g. ``amp="off"`` for a model a reader loads), as it is later."""
    folder = pipeline.GRAPH.node_dir(p, node)
    if not folder.is_dir():
        folder.mkdir(parents=True)
        write_manifest(folder / "manifest.json", {"fingerprint": f"hand-made {node}", **record})
    return folder


def publish(p: Params, node: Node, frames: dict[str, pd.DataFrame],
            scores: dict[str, dict] | None = None) -> None:
    """What a built node leaves in its published folder: its tables, scores, manifest."""
    write_frames(node_folder(p, node), frames, scores or {})


def make_study(root: Path) -> tuple[Params, dict[Node, dict[str, pd.DataFrame]]]:
    """The demo profile (four flow methods, three folds x three seeds, raw-input models of
    gt and dis, chapter 10's inputs on gt and dis, chapter 11's dis) on a run folder of
    hand-made published predictions: ``{node: {table name: predictions}}``, every table
    with an error rate of its own."""
    p = load_profile("demo", run_dir=str(root / "runs"),
                     extension_methods=["gt", "dis"])  # the images' reference: the first
    rng = np.random.default_rng(53)
    test, general = _objects("test", rng), _objects("general", rng)
    errors = iter(np.linspace(0.03, 0.45, 40))

    def pred(obj: pd.DataFrame, seeds: int) -> pd.DataFrame:
        return _predicted(obj, next(errors), seeds, rng)

    tables: dict[Node, dict[str, pd.DataFrame]] = {}
    for m in p.flow_methods:
        ev = {"test": pred(test, p.seeds), "baseline": pred(test, 1).assign(
            prob=lambda d: (d["prob"] > 0.5).astype(float))}  # the rule's 0/1 calls
        if m in p.raw_input_methods:
            ev["raw"] = pred(test, p.extension_seeds)
        tables[Node("evaluate", m)] = ev
        tables[Node("generalise", m)] = {"general": pred(general, p.seeds)}
    for m, v in chains(p):
        tables[Node("xevaluate", m, v)] = {"test": pred(test, 1), "general": pred(general, 1)}
    for m in p.wide_methods:
        tables[Node("wgeneralise", m)] = {"general": pred(general, 1), "test": pred(test, 1)}
    for node, frames in tables.items():
        scores = {}
        if node.stage == "evaluate":
            scores = {("scores" if k == "test" else k): score(df, seed=p.seed)
                      for k, df in frames.items()}
            scores["original"] = {"clean": 0.5, "original": 0.6, "original_minus_clean": 0.1,
                                  "per_seed_clean": [0.5], "per_seed_original": [0.6]}
        publish(p, node, frames, scores)
    return p, tables
