"""Apply a trained classifier to your own frames.

    python -m flowmod.predict FRAME1 FRAME2 --boxes BOXES.csv \\
        --model runs/demo/models/dis/f0s0/best.pt [--out annotated.png] [--device auto]

The flow method and its options, how flow was stored, and the crop geometry are taken from
the model's recorded recipe (the ``manifest.json`` beside ``best.pt``), so the frames are
processed exactly as the training crops were: flow between the two frames, the storage round
trip (dtype, scale), the paper's crop around each box. BOXES.csv has columns xmin, ymin,
xmax, ymax (pixels of FRAME1; an ``id`` column is kept if present). Prints moving/still and
the probability per box, and writes FRAME1 with red (moving) and blue (still) boxes.
Frames of any size work (both the same size); boxes must lie inside the image.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from flowmod.artefacts import CheckpointError
from flowmod.crops import pair_crops
from flowmod.environment import resolve_device
from flowmod.flow import (
    ImageError,
    MissingWeightsError,
    available_methods,
    check_images,
    get_estimator,
    read_image,
)
from flowmod.flow.networks import estimator_options
from flowmod.flow.store import roundtrip
from flowmod.model import load_model, predict
from flowmod.params import ProfileError, validate
from flowmod.report.draw import draw_boxes, label_colors
from flowmod.train import recipe_from


class PredictError(ValueError):
    """The inputs cannot be used; the message names the file or value and the fix."""


#: What a model's recipe must give: key -> (types its value may take, in words).
RECIPE_FIELDS: dict[str, tuple[tuple[type, ...], str]] = {
    "method": ((str,), "a flow method's name"),
    "flow_params": ((dict,), "a mapping of the flow's parameters"),
    "crop_size": ((int,), "a whole number of pixels"),
    "crop_scale": ((int, float), "a number"),
    "flow_dtype": ((str, type(None)), "a dtype name or null"),
    "store_scale": ((int, float, type(None)), "a number or null"),
}


def read_recipe(model: Path) -> dict[str, Any]:
    """The recipe recorded beside a model (flow method and options, storage, crops); for a
    model published before recipes were recorded, rebuilt from its run folder's manifests.
    :class:`PredictError` naming the manifest and the key when it is not usable."""
    man = model.parent / "manifest.json"
    if not man.is_file():
        raise PredictError(f"{man} not found: --model must be a best.pt published by the "
                           "training stage (runs/<profile>/models/<method>/<part>/best.pt, "
                           "part f<k>s<j>, f<k> or s<k>)")
    rec = _read_json(man, "model manifest", "copy the model's folder again or retrain it")
    recipe = rec["recipe"] if rec.get("recipe") else _recipe_from_run(model, man, rec)
    check_recipe(recipe, man)
    return recipe


def _read_json(path: Path, what: str, fix: str) -> dict[str, Any]:
    """A JSON object from ``path``; :class:`PredictError` saying ``what`` it should be and
    the ``fix`` when it is unreadable or not an object."""
    try:
        rec = json.loads(path.read_text())
    except OSError as e:
        raise PredictError(f"{path}: cannot read the {what} ({e.strerror}); {fix}") from None
    except ValueError as e:  # JSONDecodeError, or bytes that are not text
        raise PredictError(f"{path}: not a readable manifest ({e}); {fix}") from None
    if not isinstance(rec, dict):
        raise PredictError(f"{path}: not a {what} (a JSON object); {fix}")
    return rec


def _recipe_from_run(model: Path, man: Path, rec: dict[str, Any]) -> dict[str, Any]:
    """The recipe of a model published before recipes were recorded: from the manifests of
    the flow and crops nodes in the run folder it was published in."""
    node = rec.get("node")
    parts = node.split("[", 1)[1].split("/", 1) if isinstance(node, str) and "[" in node else []
    if len(parts) != 2:
        raise PredictError(f"{man}: records neither the model's recipe nor the node that "
                           f"trained it (\"node\": {node!r}, want \"train[<method>/<part>]\");"
                           " copy the model's folder again or retrain it")
    method, folder = parts[0], model.resolve().parent
    run = folder.parents[2] if len(folder.parents) > 2 else folder
    fix = (f"{man} has no recipe (a model from before recipes were recorded), so predict "
           "reads its run folder: keep the model in the run that trained it, or retrain it")
    found = []
    for stage in ("flow", "crops"):
        path = run / stage / method / "keyframe" / "manifest.json"
        if not path.is_file():
            raise PredictError(f"{path} not found; {fix}")
        found.append(_read_json(path, f"{stage} manifest", fix))
    return recipe_from(method, *found)


def check_recipe(recipe: Any, man: Path) -> None:
    """:class:`PredictError` naming every key of :data:`RECIPE_FIELDS` that ``recipe`` (read
    from ``man``) lacks or holds a value of the wrong type for."""
    if not isinstance(recipe, dict):
        raise PredictError(f"{man}: its recipe is {recipe!r}, not a mapping; copy the model's "
                           "folder again or retrain it")
    bad = [f"{key}={recipe.get(key)!r} (want {words})"
           for key, (types, words) in RECIPE_FIELDS.items()
           if not isinstance(recipe.get(key), types) or isinstance(recipe.get(key), bool)]
    fix = "the manifest is damaged or was edited: copy the model's folder again or retrain it"
    if bad:
        raise PredictError(f"{man}: recipe {'; '.join(bad)}; {fix}")
    if recipe["method"] not in available_methods():
        raise PredictError(f"{man}: recipe method={recipe['method']!r} is no flow method "
                           f"(known: {', '.join(available_methods())}); {fix}")
    try:  # the values the flow is computed with (a nested mapping is a file's record)
        validate({k: v for k, v in recipe["flow_params"].items() if not isinstance(v, dict)},
                 source=f"{man}: recipe flow_params")
    except ProfileError as e:
        raise PredictError(f"{e}; {fix}") from None


def check_device(device: str) -> None:
    """:class:`PredictError` for a ``--device`` that is not auto, cpu or cuda, or cuda on a
    machine without a visible CUDA device."""
    if device not in ("auto", "cpu", "cuda"):
        raise PredictError(f"--device {device!r}: not a device; give auto, cpu or cuda")
    try:
        resolve_device(device)
    except RuntimeError:
        raise PredictError("--device cuda: no CUDA device is visible on this machine; give "
                           "--device cpu (or auto, which uses a GPU when there is one)") from None


def read_boxes(path: Path, width: int, height: int) -> pd.DataFrame:
    """Boxes (xmin, ymin, xmax, ymax px) from a CSV; :class:`PredictError` naming the rows that
    are malformed or outside a ``width`` x ``height`` image."""
    try:
        df = pd.read_csv(path)
    except (OSError, ValueError) as e:
        raise PredictError(f"{path}: cannot read the boxes CSV ({e})") from None
    cols = ["xmin", "ymin", "xmax", "ymax"]
    missing = [c for c in cols if c not in df.columns]
    if missing:
        raise PredictError(f"{path}: needs columns {cols} (missing {missing})")
    if df.empty:
        raise PredictError(f"{path}: no boxes (only a header): give one row per box")
    numbers = df[cols].apply(pd.to_numeric, errors="coerce")
    text = numbers.isna() & df[cols].notna()
    if text.any(axis=None):
        row, col = next((r, c) for r in range(len(df)) for c in cols if text.iloc[r][c])
        raise PredictError(f"{path}: row {row}, column {col}: {df[col].iloc[row]!r} is not a "
                           "number (pixel coordinates of FRAME1)")
    b = numbers.to_numpy(dtype=float)
    bad = ~np.isfinite(b).all(axis=1) | (b[:, 2] <= b[:, 0]) | (b[:, 3] <= b[:, 1])
    outside = (b[:, 0] < 0) | (b[:, 1] < 0) | (b[:, 2] > width - 1) | (b[:, 3] > height - 1)
    if bad.any():
        raise PredictError(f"{path}: rows {np.flatnonzero(bad).tolist()} are not boxes "
                           "(need xmin < xmax and ymin < ymax, finite)")
    if outside.any():
        raise PredictError(f"{path}: rows {np.flatnonzero(outside).tolist()} leave the "
                           f"{width}x{height} image (pixel coordinates of FRAME1)")
    return df


def predict_boxes(frame1: np.ndarray, frame2: np.ndarray, boxes: pd.DataFrame,
                  model_path: Path, recipe: dict[str, Any], device: str = "auto"
                  ) -> pd.DataFrame:
    """Probability of moving for each box, processed as the model's training crops were."""
    method = recipe["method"]
    if method == "gt":
        raise PredictError("this model was trained on the synthetic world's exact flow (gt), "
                           "which exists only for generated frames: use a model of a method "
                           "that works from images (dis, farneback, raft, fastflownet)")
    # a weights file enters a fingerprint by its digest: for networks, the file is looked up
    # in $TORCH_HOME (MissingWeightsError says where) rather than by the recorded path
    flow_params = {k: v for k, v in recipe["flow_params"].items() if not isinstance(v, dict)}
    p = validate({**flow_params, "device": device})
    flow = get_estimator(method, **estimator_options(p, method)).estimate(frame1, frame2)
    flow = roundtrip(flow, recipe.get("flow_dtype") or "float32",
                     float(recipe.get("store_scale") or 1.0))
    h, w = frame1.shape[:2]
    x = pair_crops(flow, boxes[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float),
                   int(recipe["crop_size"]), float(recipe["crop_scale"]), (w, h))[0]
    model = load_model(model_path, device)
    prob = predict(model, x, device=device)
    return boxes.assign(prob=prob, moving=prob > 0.5)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m flowmod.predict",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("frame1", type=Path)
    ap.add_argument("frame2", type=Path)
    ap.add_argument("--boxes", type=Path, required=True, help="CSV: xmin, ymin, xmax, ymax")
    ap.add_argument("--model", type=Path, required=True, help="a published best.pt")
    ap.add_argument("--method", default=None,
                    help="flow method expected (checked against the model's recipe)")
    ap.add_argument("--out", type=Path, default=None, help="annotated FRAME1 (PNG/JPEG)")
    ap.add_argument("--device", default="auto")
    args = ap.parse_args(argv)
    try:
        if args.out and not cv2.haveImageWriter(str(args.out)):
            raise PredictError(f"--out {args.out}: no image writer for "
                               f"{args.out.suffix or 'a name without extension'}; give a .png "
                               "or .jpg path")
        check_device(args.device)
        if not args.model.is_file():
            raise PredictError(f"model not found: {args.model}")
        recipe = read_recipe(args.model)
        if args.method and args.method != recipe["method"]:
            raise PredictError(f"--method {args.method} but {args.model} was trained on "
                               f"{recipe['method']} flow: its crops would not mean the same")
        check_images([args.frame1, args.frame2])  # as the pipeline does: whole, decodable
        f1, f2 = read_image(args.frame1), read_image(args.frame2)
        if f1.shape != f2.shape:
            raise PredictError(f"frames differ in size: {f1.shape[1]}x{f1.shape[0]} "
                               f"({args.frame1}) vs {f2.shape[1]}x{f2.shape[0]} ({args.frame2})")
        boxes = read_boxes(args.boxes, f1.shape[1], f1.shape[0])
        out = predict_boxes(f1, f2, boxes, args.model, recipe, args.device)
    except (PredictError, ImageError, CheckpointError, MissingWeightsError) as e:
        print(f"{type(e).__name__}: {e}", file=sys.stderr)
        return 2
    print(out.assign(prob=out["prob"].round(3)).to_string(index=False))
    if args.out:
        img = draw_boxes(f1, out[["xmin", "ymin", "xmax", "ymax"]].to_numpy(),
                         label_colors(out["moving"].astype(int)),
                         [f"{p:.2f}" for p in out["prob"]])
        if not cv2.imwrite(str(args.out), img):
            print(f"PredictError: cannot write {args.out}", file=sys.stderr)
            return 2
        print(f"written: {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
