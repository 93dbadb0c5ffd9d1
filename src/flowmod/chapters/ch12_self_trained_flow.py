"""Chapter 12's backend: FastFlowNet trained here, against DIS and the exact flow."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from flowmod import pipeline, world
from flowmod.chapters import common
from flowmod.dag import Node
from flowmod.flow.estimators import DISFlow
from flowmod.flow.networks import FastFlowNetFlow
from flowmod.flow.selftrain import DIS_PRESET, held_out, heldout_pairs
from flowmod.params import Params


def built(params: Params) -> list[str]:
    """The modes of ``selfflow_modes`` whose published weights are current."""
    return [m for m in params.selfflow_modes
            if pipeline.current(params, Node("selfflow", None, m))]


def results(params: Params, mode: str) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The published history and ``eval.json`` of ``selfflow[<mode>]``."""
    folder = pipeline.published(params, Node("selfflow", None, mode))
    return (pd.read_csv(folder / "history.csv"),
            json.loads((folder / "eval.json").read_text()))


def weights_path(params: Params, mode: str) -> Path:
    """The published FastFlowNet checkpoint of ``mode`` (a ``fastflownet_weights`` value)."""
    return pipeline.published(params, Node("selfflow", None, mode)) / "weights.pt"


def epe_table(params: Params, done: list[str]) -> pd.DataFrame:
    """Held-out end-point error and Fl-all, overall and inside the target vehicles' boxes, of
    the baselines and of each trained network (one row each), with seconds per pair on this
    machine (the baselines of the first mode's evaluation: the same pairs for every mode)."""
    rows = []
    for k, mode in enumerate(done):
        _, ev = results(params, mode)
        base = ev["baselines"]
        order = ("zero flow", "farneback", f"dis ({DIS_PRESET})")
        named = ({n: base[n] for n in order} if k == 0 else {}) | {
            f"fastflownet ({mode})": ev["fastflownet"]}
        for name, m in named.items():
            rows.append({"method": name, "EPE (px)": round(m["epe"], 2),
                         "EPE in boxes (px)": round(m["epe_boxes"], 2),
                         "Fl-all (%)": round(m["fl_all"], 1),
                         "Fl-all in boxes (%)": round(m["fl_all_boxes"], 1),
                         "s / pair": round(m["seconds_per_pair"], 2)})
    return pd.DataFrame(rows)


def budget_table(params: Params, done: list[str]) -> pd.DataFrame:
    """What the CPU budget bought per mode: steps, pairs seen, seconds per step (median) and
    the training time."""
    rows = []
    for mode in done:
        hist, ev = results(params, mode)
        rows.append({"mode": mode, "steps": ev["steps"],
                     "pairs seen": ev["steps"] * params.selfflow_batch,
                     "training pairs": ev["train_pairs"],
                     "s / step": round(ev["seconds_per_step"], 2),
                     "training (min)": round(float(hist["seconds"].sum()) / 60, 1)})
    return pd.DataFrame(rows)


def beats_dis(params: Params, done: list[str]) -> list[str]:
    """The modes whose network has a lower EPE than DIS on the validation-scene pairs (the
    choice is made there; the test pairs only report it)."""
    out = []
    for mode in done:
        _, ev = results(params, mode)
        val = ev["validation"]
        if val["fastflownet"]["epe"] < val["baselines"][f"dis ({DIS_PRESET})"]["epe"]:
            out.append(mode)
    return out


def table3_note(params: Params, done: list[str]) -> str:
    """Whether a trained network becomes Table 3's ``fastflownet`` row, and how: decided on
    the validation-scene pairs."""
    if not done:
        return "No network is trained yet, so Table 3 has no `fastflownet` row from here."
    better = beats_dis(params, done)
    if not better:
        return ("No trained network beats DIS on the validation scenes' end-point error, so "
                "Table 3 keeps its rows: a `fastflownet` row from these weights would only "
                "show a flow worse than the classical baseline's.")
    path = weights_path(params, better[0])
    return (f"The {better[0]} network beats DIS on the validation scenes' end-point error: "
            f"Table 3 gains its `fastflownet` row with `make book SET=\"flow_networks="
            f"[fastflownet] fastflownet_weights={path}\"`.")


def headline(params: Params, done: list[str]) -> str:
    """One sentence for the landing page: test-pair EPE of each trained network beside
    DIS's and the zero flow's, or how to build them."""
    if not params.selfflow_modes:
        return "not part of this profile (selfflow_modes is empty)"
    if not done:
        return ("not trained in this run (make selfflow trains FastFlowNet from scratch: "
                f"{len(params.selfflow_modes)} x {params.selfflow_iters} steps)")
    parts, base = [], {}
    for mode in done:
        _, ev = results(params, mode)
        base = ev["baselines"]
        parts.append(f"{ev['fastflownet']['epe']:.1f} px ({mode}, {ev['steps']} steps)")
    return (f"FastFlowNet trained from scratch on this machine reaches a test-scene end-point "
            f"error of {' and '.join(parts)} against DIS's "
            f"{base[f'dis ({DIS_PRESET})']['epe']:.1f} px and the zero flow's "
            f"{base['zero flow']['epe']:.1f} px")


def example(params: Params, done: list[str], k: int = 0
            ) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray | None]:
    """Held-out pair ``k``: frame 1 (BGR), the flows of the exact flow (where there is one),
    DIS and each trained network at full size, and the valid mask, for
    :func:`flowmod.report.viz.flow_figure`."""
    sel = pipeline.published(params, Node("select"))
    pairs = pd.read_parquet(sel / "pairs.parquet")
    test = heldout_pairs(pairs, params.selfflow_eval_pairs, params.seed,
                         params.folds).iloc[[k]]
    synthetic = world.is_synthetic(params.dataroot_path, params.version)
    h = held_out(test, pd.read_parquet(sel / "objects.parquet"), params.dataroot_path,
                 params.version, synthetic)
    flows = {"exact": h.gt[0]} if h.gt else {}
    flows[f"dis ({DIS_PRESET})"] = DISFlow(DIS_PRESET, scale=params.flow_scale).estimate(
        h.img1[0], h.img2[0])
    for mode in done:
        est = FastFlowNetFlow(weights_path(params, mode), device="cpu", scale=params.flow_scale)
        flows[f"fastflownet ({mode})"] = est.estimate(h.img1[0], h.img2[0])
    return h.img1[0], flows, (h.valid[0] if h.valid else None)


def built_note(params: Params, done: list[str]) -> str:
    """A line for the chapter: which networks are trained, and how to train the others."""
    if not params.selfflow_modes:
        return ("This profile trains no flow network (`selfflow_modes` is empty). Set it (e.g. "
                "`selfflow_modes=[photometric]`) and run `make selfflow`.")
    todo = [m for m in params.selfflow_modes if m not in done]
    return common.built_note("Networks trained", done, len(params.selfflow_modes),
                             f"{', '.join(todo)}; {params.selfflow_iters} steps each",
                             "selfflow_build")
