"""Chapter 12's backend: FastFlowNet trained here, against DIS and the exact flow.

Two sources of weights: the shipped ones (``weights/fastflownet_synth/``, pretrained
supervised on a world of their own by :mod:`flowmod.flow.pretrain`; the demo profile's
``fastflownet`` flow method), read from their manifest; and the networks the ``selfflow``
stage trains in the book (``selfflow_modes``), read from their published nodes."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from flowmod import pipeline
from flowmod.chapters import common
from flowmod.dag import Node
from flowmod.evaluate import paired, scored
from flowmod.extensions.selfflow import (
    read_selfflow,
    read_shipped,
    read_shipped_example,
    selfflow_weights,
)
from flowmod.flow.registry import read_image
from flowmod.flowweights import FASTFLOWNET_SYNTH
from flowmod.flowweights import SHIPPED_DIS_PRESET as DIS_PRESET
from flowmod.flowweights import SHIPPED_FASTFLOWNET_DIR as WEIGHTS_DIR
from flowmod.flowweights import SHIPPED_ROW as SHIPPED
from flowmod.metrics import (
    ci_text,
    group_mean_bootstrap,
    interval,
    verdict,
)
from flowmod.params import Params


def built(params: Params) -> list[str]:
    """The modes of ``selfflow_modes`` whose published weights are current."""
    return [m for m in params.selfflow_modes
            if pipeline.current(params, Node("selfflow", None, m))]


def results(params: Params, mode: str) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The published history and ``eval.json`` of ``selfflow[<mode>]``."""
    folder = pipeline.published(params, Node("selfflow", None, mode))
    return read_selfflow(folder)


def weights_path(params: Params, mode: str) -> Path:
    """The published FastFlowNet checkpoint of ``mode`` (a ``fastflownet_weights`` value)."""
    return selfflow_weights(pipeline.published(params, Node("selfflow", None, mode)))


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
    """Whether a network trained in the book could be Table 3's ``fastflownet`` row in place
    of the shipped weights: decided on the validation-scene pairs, against DIS."""
    if not done:
        return "No network is trained in the book with these parameters."
    better = beats_dis(params, done)
    if not better:
        return ("No network trained in the book beats DIS on the validation scenes' end-point "
                "error; Table 3's `fastflownet` row stays the shipped weights'.")
    path = weights_path(params, better[0])
    return (f"The {better[0]} network beats DIS on the validation scenes' end-point error: "
            f"it can be Table 3's `fastflownet` row with `make book SET=\"fastflownet_weights="
            f"{path}\"`.")


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


def built_note(params: Params, done: list[str]) -> str:
    """A line for the chapter: which networks are trained, and how to train the others."""
    if not params.selfflow_modes:
        return ("This profile trains no flow network (`selfflow_modes` is empty). Set it (e.g. "
                "`selfflow_modes=[photometric]`) and run `make selfflow`.")
    todo = [m for m in params.selfflow_modes if m not in done]
    return common.built_note("Networks trained", done, len(params.selfflow_modes),
                             f"{', '.join(todo)}; {params.selfflow_iters} steps each",
                             "selfflow_build")


# --- the shipped weights (weights/fastflownet_synth) -------------------------------------------


def shipped_manifest() -> dict[str, Any] | None:
    """The manifest of the shipped FastFlowNet weights, or None where they are missing."""
    return FASTFLOWNET_SYNTH.manifest()


def uses_shipped(params: Params) -> bool:
    """Whether this profile's ``fastflownet`` flow method runs the shipped weights."""
    given = params.fastflownet_weights
    return ("fastflownet" in params.flow_methods and given is not None
            and FASTFLOWNET_SYNTH.is_shipped(params.path(given)))


def phase_text(p: dict[str, Any], scale_before: float) -> str:
    """A later phase of the schedule in words (its steps, rate, focus, and its frame scale
    where it differs from ``scale_before``, the previous phase's)."""
    near, far = p["focus_depth"]
    lo, hi = p.get("min_gap", 1), p["max_gap"]
    apart = f"{lo}" if lo == hi else f"{lo} to {hi}"
    pairs = f"; only the pairs {apart} frames apart (keyframes: 6)" if lo > 1 else ""
    start = ("the previous phase's weights as published (float16)" if p.get("init_float16")
             else "the previous phase's weights")
    finest = ("; the finest level's loss on its flow upsampled to every pixel (as inference "
              "does)" if p.get("full_res") else "")
    average = (f"; passes on the moving average of its weights (decay {p['ema']:g})"
               if p.get("ema") else "")
    scale = (f"; frames read at scale {p['scale']:g} (before: {scale_before:g})"
             if p["scale"] != scale_before else "")
    return (f"{p['steps']} more steps from {start} (a fresh Adam "
            f"{p['lr']:g}, x{p['gamma']:g} at its steps "
            f"{', '.join(str(x) for x in p['milestones'])}); a share {p['focus_p']:g} of the "
            f"windows holds the box of an agent {near:g}-{far:g} m away, and box pixels "
            f"weigh {1 + p['box_weight']:g}x in the loss{pairs}{finest}{average}{scale}")


def recipe_table(m: dict[str, Any]) -> pd.DataFrame:
    """How the shipped weights were made, one row per fact, from their manifest."""
    r, w = m["schedule"][0], m["world"]["dataroot_params"]
    rows = {
        "network": m["network"],
        "pretraining world": (f"{w['world_scenes']} scenes x {w['world_keyframes']} keyframes, "
                              f"seed {w['seed']}, sweeps in every scene; every "
                              f"{r['val_every']}th scene for validation; no scene of this "
                              "book's worlds"),
        "pairs": (f"{r.get('min_gap', 1)} to {r['max_gap']} camera frames apart (12 Hz), from every "
                  f"{r['start_stride']}th frame of the training scenes, at scale {r['scale']}"),
        "batch": (f"{r['batch']} random {r['crop'][0]} x {r['crop'][1]} windows, a "
                  f"horizontal flip with p {r['flip_p']}"),
        "loss": ("end-point error against the exact flow (valid pixels) at every decoder "
                 f"level, weights {', '.join(f'{x:g}' for x in r['level_weights'])}"),
        "schedule": (f"Adam {r['lr']:g}, x{r['gamma']:g} at steps "
                     f"{', '.join(str(x) for x in r['milestones'])}; {r['steps']} steps"),
        **{f"phase {k}": phase_text(p, m["schedule"][k - 2]["scale"])
           for k, p in enumerate(m["schedule"][1:], start=2)},
        "training time": (f"{m['train_seconds'] / 3600:.1f} h on {m['where']['device']} "
                          f"({m['where']['threads']} threads, {m['where']['machine']})"),
        "file": f"float16 state_dict, sha256 {m['sha256'][:12]}...",
    }
    return pd.DataFrame({"": list(rows), "shipped weights": list(rows.values())})


def _metric_row(name: str, v: dict[str, float], scale: float | None = None
                ) -> dict[str, Any]:
    """A table row of ``v``'s metrics (with the frame ``scale`` they were scored at, if
    given)."""
    return {"method": name, **({} if scale is None else {"frame scale": scale}),
            "EPE (px)": round(v["epe"], 2),
            "EPE in boxes (px)": round(v["epe_boxes"], 2),
            "Fl-all (%)": round(v["fl_all"], 1), "Fl-all in boxes (%)": round(v["fl_all_boxes"], 1)}


def validation_table(m: dict[str, Any]) -> pd.DataFrame:
    """The pretraining world's validation pairs: the baselines, the untrained network (step
    0, at the first phase's frame scale) and the shipped float16 weights (at the last
    phase's, as the baselines)."""
    val, first, last = m["validation"], m["schedule"][0]["scale"], m["scale"]
    rows = [_metric_row(k, v, last) for k, v in val["baselines"].items()]
    step0 = {k[4:]: v for k, v in val["curve"][0].items() if k.startswith("val_")}
    rows.append(_metric_row("fastflownet, step 0 (untrained)", step0, first))
    rows.append(_metric_row(f"{SHIPPED}, step {m['steps']}", val["final_float16"], last))
    return pd.DataFrame(rows)


def scale_changes(m: dict[str, Any]) -> list[tuple[int, float]]:
    """(step of the whole schedule, new frame scale) where a phase reads frames at another
    scale than its predecessor."""
    out, done = [], 0
    for before, p in zip(m["schedule"], m["schedule"][1:], strict=False):
        done += before["steps"]
        if p["scale"] != before["scale"]:
            out.append((done, p["scale"]))
    return out


def curves(m: dict[str, Any]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(training curve: step, loss, epe2 per block of steps; validation curve: step, val_*)."""
    return pd.DataFrame(m["training_curve"]), pd.DataFrame(m["validation"]["curve"])


#: The table's EPE columns and the per-pair values of the ``shipped`` node behind them.
_PER_PAIR = {"EPE (px)": "epe", "EPE in boxes (px)": "epe_boxes"}


def held_out_check(params: Params) -> tuple[pd.DataFrame | None, pd.DataFrame | None]:
    """The published ``shipped`` node (:func:`flowmod.extensions.selfflow.build_shipped`):
    (its table: the shipped weights beside the zero flow, Farneback and DIS on held-out
    pairs of this book's world, each EPE with its 95 % interval over scenes and the seconds
    per pair where the node was built; per held-out pair its scene and each method's EPE in
    the boxes, px, one column per method); (None, None) on data without exact flow."""
    folder = pipeline.published(params, Node("shipped"))
    raw, long = read_shipped(folder)
    if raw.empty:
        return None, None
    rows = []
    for _, r in raw.iterrows():
        mine = long[long["method"] == r["method"]]
        row: dict[str, Any] = {}
        for col, v in _metric_row(r["method"], r).items():
            row[col] = v
            if col in _PER_PAIR:  # each EPE followed by its interval over scenes
                row[f"{col.removesuffix(' (px)')} 95% CI over scenes"] = common.epe_ci(
                    mine[_PER_PAIR[col]], mine["scene"], params.seed)
        rows.append({**row, "s / pair": round(r["seconds_per_pair"], 2)})
    wide = long.pivot(index=["pair_id", "scene"], columns="method", values="epe_boxes")
    order = long.drop_duplicates("pair_id")["pair_id"].tolist()
    errors = wide.reset_index().set_index("pair_id").loc[order].reset_index()
    errors.columns.name = None
    return pd.DataFrame(rows), errors


def shipped_example(params: Params) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """The first held-out pair of the ``shipped`` node: (its frame 1, the exact, DIS and
    shipped flows at full size, the exact flow's valid mask), for
    :func:`flowmod.report.viz.flow_figure`."""
    folder = pipeline.published(params, Node("shipped"))
    arrays = read_shipped_example(folder)
    path = read_shipped(folder)[1]["path_1"].iloc[0]
    flows = {"exact": arrays["exact"], f"dis ({DIS_PRESET})": arrays[f"dis ({DIS_PRESET})"],
             SHIPPED: arrays[SHIPPED]}
    return (read_image(params.dataroot_path / path),
            {k: v.astype(np.float32) for k, v in flows.items()}, arrays["valid"])


def box_difference(errors: pd.DataFrame | None, seed: int = 0) -> dict[str, Any] | None:
    """The shipped network's end-point error inside the target boxes minus DIS's (px),
    paired per held-out pair (``errors``: :func:`held_out_check`'s), with its 95 % interval
    over scenes (only those with a defined difference) and its verdict; None without
    exact flow."""
    if errors is None:
        return None
    diff = (errors[SHIPPED] - errors[f"dis ({DIS_PRESET})"]).to_numpy(float)
    ci = interval(group_mean_bootstrap(diff, errors["scene"], seed=seed))
    return {"diff": float(np.nanmean(diff)), "ci": ci, "verdict": verdict(ci),
            "scenes": int(errors["scene"][~np.isnan(diff)].nunique())}


def observation(params: Params, errors: pd.DataFrame | None,
                methods: tuple[str, str] = ("fastflownet", "dis")) -> dict[str, Any]:
    """The paper's observation (the less accurate flow classified better) on this study's
    numbers: the shipped network minus DIS in end-point error inside the target boxes (px,
    paired per held-out pair with a scene-level interval; ``errors``: the per-pair table of
    :func:`held_out_check`, None without exact flow), and in Table 3's F1 (paired, same
    test objects, scene-level interval), and Table 4's likewise. Empty where Table 3 has no
    ``fastflownet`` and ``dis`` rows or they are not built. ``methods``: the two chains
    compared (the first's flow is the shipped weights')."""
    if not all(m in params.flow_methods and pipeline.built(params, Node("generalise", m))
               for m in methods):
        return {}
    out: dict[str, Any] = {"epe_boxes_minus_dis": box_difference(errors, params.seed)}
    for name, label in (("test", "Table 3"), ("general", "Table 4")):
        a, b = (scored(common.results(params, m, name)[0], name, params.general_max_distance)
                for m in methods)
        row = common.comparison_table({f"{methods[0]} - {methods[1]} ({label})": paired(
            a, b, f"{methods[0]} and {methods[1]} ({label})", seed=params.seed)}).iloc[0]
        out[name] = row
    return out


def world_words(table: pd.DataFrame | None, n: int) -> str:
    """What the shipped network gets right and wrong against DIS on ``table``'s ``n`` pairs
    of this book's world, in numbers (or why there are none)."""
    if table is None:
        return ("This data set has no exact flow, so the shipped weights' errors cannot be "
                "measured on it; where `fastflownet` is one of `flow_methods`, Table 3 still "
                "shows how their flow classifies.")
    t = table.set_index("method")
    f, d = t.loc[SHIPPED], t.loc[f"dis ({DIS_PRESET})"]

    def rel(a: float, b: float) -> str:  # at the precision shown (0.1 px)
        a, b = round(a, 1), round(b, 1)
        return "lower than" if a < b else "higher than" if a > b else "equal to"

    return (f"On {n} keyframe pairs of this book's world (scenes the network never saw), its "
            f"end-point error is {f['EPE (px)']:.1f} px over the frame, {rel(f['EPE (px)'], d['EPE (px)'])} "
            f"DIS's {d['EPE (px)']:.1f} px, and {f['EPE in boxes (px)']:.1f} px inside the far "
            f"vehicles' boxes, {rel(f['EPE in boxes (px)'], d['EPE in boxes (px)'])} DIS's "
            f"{d['EPE in boxes (px)']:.1f} px (Fl-all in the boxes {f['Fl-all in boxes (%)']:.1f} "
            f"against {d['Fl-all in boxes (%)']:.1f} %); it takes {f['s / pair']:.2f} s a pair "
            f"where they were computed against DIS's {d['s / pair']:.2f} s.")


def observation_words(obs: dict[str, Any]) -> str:
    """The paper's observation answered with :func:`observation`'s numbers, or why not."""
    if not obs:
        return ("Table 3 of this profile has no `fastflownet` and `dis` rows to compare "
                "(`flow_methods`), so this chapter cannot answer it here.")
    d = obs["epe_boxes_minus_dis"]
    t3, t4 = obs["test"], obs["general"]
    text = (f"Its classifier minus DIS's, paired on the same objects: "
            f"{common.difference_words(t3)} on Table 3 and {common.difference_words(t4)} on "
            "Table 4. ")
    if d is None:
        return text + "Without exact flow, which of the two flows is more accurate is unknown."
    acc = {"A better": "less accurate than", "B better": "more accurate than"}.get(
        d["verdict"], "not told apart from")
    text = (f"Inside the target boxes the shipped FastFlowNet's flow is {acc} DIS's "
            f"({d['diff']:+.2f} px of end-point error, 95 % interval over {d['scenes']} "
            f"scenes {d['ci'][0]:+.2f} to {d['ci'][1]:+.2f}). " + text)
    if not common.decided(t3["verdict"]):
        return text + ("These scenes cannot tell the two classifiers apart on Table 3, so "
                       "they neither repeat nor contradict the paper's observation.")
    if d["verdict"] == "undecided":
        return text + ("The classifiers differ where these pairs cannot tell the flows' "
                       "accuracy in the boxes apart: the paper's observation is neither "
                       "repeated nor contradicted here.")
    repeats = (t3["verdict"] == "A better") == (d["verdict"] == "A better")
    return text + ("The less accurate flow classifies better here too: the paper's observation "
                   "repeats." if repeats else
                   "Here the more accurate flow classifies better: the paper's observation "
                   "does not repeat.")


def shipped_headline(m: dict[str, Any] | None, table: pd.DataFrame | None,
                     obs: dict[str, Any], diff: dict[str, Any] | None = None) -> str:
    """One sentence for the landing page on the shipped weights: their held-out error in
    the boxes beside DIS's with the paired difference's interval over scenes (``diff``:
    :func:`box_difference`), and their classifier against DIS's."""
    if m is None:
        return (f"no shipped FastFlowNet weights in {WEIGHTS_DIR} (`make flownet` makes "
                "them)")
    text = (f"FastFlowNet pretrained here, supervised on a synthetic world of its own "
            f"({m['steps']} steps, {m['train_seconds'] / 3600:.1f} h on a CPU)")
    if table is not None:
        t = table.set_index("method")
        text += (f", has an end-point error of {t.loc[SHIPPED, 'EPE in boxes (px)']:.1f} px "
                 "inside the far vehicles' boxes of this book's world against DIS's "
                 f"{t.loc[f'dis ({DIS_PRESET})', 'EPE in boxes (px)']:.1f} px")
        if diff is not None:
            ci = ci_text(diff["ci"], diff["scenes"], " to ", "+.2f")
            text += (f" (paired per pair {diff['diff']:+.2f} px, 95 % interval over scenes "
                     f"{ci}{'' if diff['verdict'] == 'undecided' else ', decided'})")
    if obs:
        text += (f"; its classifier minus DIS's on Table 3: "
                 f"{common.difference_words(obs['test'])}")
    return text


def shipped_note(params: Params, m: dict[str, Any] | None) -> str:
    """A line for the chapter: which weights this profile's ``fastflownet`` runs."""
    if m is None:
        return (f"No shipped weights in `{WEIGHTS_DIR}`: `make flownet` makes them (about an "
                "hour on a CPU, resumable).")
    where = ("this profile's `fastflownet` flow method runs them" if uses_shipped(params)
             else "this profile's `fastflownet` flow method does not run them "
                  "(`flow_methods`, `fastflownet_weights`)")
    text = (f"Shipped weights: `{WEIGHTS_DIR}/weights.pt`, {m['steps']} steps, sha256 "
            f"`{m['sha256'][:12]}`; {where}.")
    if m["scale"] != params.flow_scale:
        text += (f" They were trained last on frames at scale {m['scale']:g}; this profile "
                 f"computes flow at {params.flow_scale:g} (`flow_scale`), where they were "
                 "not validated.")
    return text


def shipped_steps(manifest: dict[str, Any] | None) -> int:
    """The training steps of the shipped weights (:func:`shipped_manifest`; 0 without them)."""
    return manifest["steps"] if manifest else 0
