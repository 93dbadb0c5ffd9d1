"""python -m flowmod.predict: a trained model on new frames, as its training crops were made."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from flowmod import dag, pipeline, predict
from flowmod.chapters import common

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def case(smoke_built, tmp_path_factory):
    """A test pair of the smoke run, its objects as a boxes CSV, the dis model that scored it."""
    p = smoke_built
    sel, _ = (common.selection(p), common.made_with(p))
    preds = common.results(p, "dis", "test")[0]
    pid = preds["pair_id"].value_counts().index[0]
    objs = preds[preds["pair_id"] == pid]
    pair = sel.pairs.set_index("pair_id").loc[pid]
    tmp = tmp_path_factory.mktemp("predict")
    boxes = tmp / "boxes.csv"
    objs[["xmin", "ymin", "xmax", "ymax"]].to_csv(boxes, index=False)
    # the model that scored this pair in chapter 07: its fold's
    fold = f"f{int(objs['fold'].iloc[0])}" + ("s0" if p.seeds > 1 else "")
    model = pipeline.node_dir(p, dag.Node("train", "dis", fold)) / "best.pt"
    return {"f1": p.dataroot_path / pair.path_1, "f2": p.dataroot_path / pair.path_2,
            "boxes": boxes, "model": model, "objs": objs, "tmp": tmp, "params": p}


def run(*args):
    """The CLI in a process of its own (as a user runs it)."""
    return subprocess.run([sys.executable, "-m", "flowmod.predict", *map(str, args)],
                          capture_output=True, text=True)


def test_predictions_equal_the_evaluation_of_the_same_model(case):
    recipe = predict.read_recipe(case["model"])
    assert recipe["method"] == "dis" and recipe["crop_size"] == case["params"].crop_size
    f1, f2 = cv2.imread(str(case["f1"])), cv2.imread(str(case["f2"]))
    out = predict.predict_boxes(f1, f2, pd.read_csv(case["boxes"]), case["model"], recipe,
                                device="cpu")
    np.testing.assert_allclose(out["prob"], case["objs"]["prob"], atol=1e-6)


def test_cli_writes_the_annotated_frame_and_works_at_another_size(case):
    out = case["tmp"] / "annotated.png"
    proc = run(case["f1"], case["f2"], "--boxes", case["boxes"], "--model", case["model"],
               "--out", out, "--device", "cpu")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("True") + proc.stdout.count("False") == len(case["objs"])
    assert cv2.imread(str(out)).shape == (900, 1600, 3)
    # the same scene at 800 x 450 (another camera), boxes scaled with it
    small = []
    for name in ("f1", "f2"):
        path = case["tmp"] / f"small_{name}.png"
        cv2.imwrite(str(path), cv2.resize(cv2.imread(str(case[name])), (800, 450),
                                          interpolation=cv2.INTER_AREA))
        small.append(path)
    boxes = pd.read_csv(case["boxes"]) / 2
    boxes.to_csv(case["tmp"] / "small.csv", index=False)
    out2 = case["tmp"] / "small_annotated.png"
    proc = run(*small, "--boxes", case["tmp"] / "small.csv", "--model", case["model"],
               "--out", out2, "--device", "cpu")
    assert proc.returncode == 0, proc.stderr
    assert cv2.imread(str(out2)).shape == (450, 800, 3)


def test_cli_errors_name_the_problem(case, call_main):
    def cli(*args):
        return call_main(predict.main, *args)

    bad = case["tmp"] / "outside.csv"
    pd.DataFrame({"xmin": [10], "ymin": [10], "xmax": [1700], "ymax": [50]}).to_csv(bad,
                                                                                     index=False)
    proc = cli(case["f1"], case["f2"], "--boxes", bad, "--model", case["model"])
    assert proc.returncode == 2 and "rows [0] leave the 1600x900 image" in proc.stderr
    proc = cli(case["f1"], case["f2"], "--boxes", case["boxes"], "--model", case["model"],
               "--method", "farneback")
    assert proc.returncode == 2 and "trained on dis flow" in proc.stderr
    broken = case["tmp"] / "broken.jpg"
    broken.write_bytes(b"not an image")
    proc = cli(broken, case["f2"], "--boxes", case["boxes"], "--model", case["model"])
    assert proc.returncode == 2 and "broken.jpg" in proc.stderr
    gt_model = pipeline.node_dir(case["params"], dag.Node("train", "gt", "f0s0")) / "best.pt"
    proc = cli(case["f1"], case["f2"], "--boxes", case["boxes"], "--model", gt_model)
    assert proc.returncode == 2 and "exact flow (gt)" in proc.stderr


def one_line(proc: subprocess.CompletedProcess) -> str:
    """The error a CLI printed, asserting it is one line (no traceback) and exit code 2."""
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    return lines[0]


def test_cli_damaged_inputs_give_one_line(case, call_main):
    """A model file cut short, a box that is not a number, a CSV without rows and a JPEG
    cut short: one line naming the file (or row and column), never a traceback, and a cut
    frame is refused as the pipeline refuses it."""
    t = case["tmp"]

    def err(*args) -> str:
        return one_line(call_main(predict.main, *args))

    cut_model = t / "cut" / "best.pt"
    cut_model.parent.mkdir()
    data = case["model"].read_bytes()
    cut_model.write_bytes(data[: len(data) // 2])
    (cut_model.parent / "manifest.json").write_bytes(
        (case["model"].parent / "manifest.json").read_bytes())
    line = err(case["f1"], case["f2"], "--boxes", case["boxes"], "--model", cut_model)
    assert "CheckpointError" in line and str(cut_model) in line
    text = t / "text.csv"
    text.write_text("xmin,ymin,xmax,ymax\n10,10,50,50\n10,ten,50,50\n")
    line = err(case["f1"], case["f2"], "--boxes", text, "--model", case["model"])
    assert "row 1, column ymin: 'ten' is not a number" in line
    header = t / "header.csv"
    header.write_text("xmin,ymin,xmax,ymax\n")
    line = err(case["f1"], case["f2"], "--boxes", header, "--model", case["model"])
    assert "no boxes" in line and str(header) in line
    cut = t / "cut.jpg"
    jpg = case["f2"].read_bytes()
    cut.write_bytes(jpg[: len(jpg) * 2 // 3])
    line = err(case["f1"], cut, "--boxes", case["boxes"], "--model", case["model"])
    assert "truncated JPEG" in line and str(cut) in line


def test_a_broken_manifest_and_an_out_that_is_no_image_are_one_line(tmp_path, call_main):
    """Issue 41: both ended in a traceback (the second after printing the results); both
    are now refused before any work."""
    model = tmp_path / "f0s0" / "best.pt"
    model.parent.mkdir()
    model.write_bytes(b"x")
    (model.parent / "manifest.json").write_text('{"recipe": ')
    frames = [tmp_path / "a.jpg", tmp_path / "b.jpg"]
    proc = call_main(predict.main, *frames, "--boxes", tmp_path / "b.csv", "--model", model)
    line = one_line(proc)
    assert "manifest.json: not a readable manifest" in line and "retrain" in line
    proc = call_main(predict.main, *frames, "--boxes", tmp_path / "b.csv", "--model", model,
                     "--out", tmp_path / "out.txt")
    assert "--out" in one_line(proc) and "no image writer for .txt" in one_line(proc)


def test_an_unusable_recipe_is_one_line_naming_the_manifest_and_key(case, call_main):
    """Issue 53: a model manifest without "node" (and no recipe) ended in a KeyError, a null
    recipe value in a TypeError. Each, on a copy of a real model and its manifest, is now one
    line naming the manifest (and the key) and the fix, before the frames are read; and a
    model from before recipes were recorded still gets its recipe from its run folder."""
    real = json.loads((case["model"].parent / "manifest.json").read_text())
    root = case["tmp"] / "recipes"

    def model_with(rel: str, rec: dict, stage_manifests: bool = False) -> Path:
        model = root / rel / "best.pt"
        model.parent.mkdir(parents=True)
        shutil.copy(case["model"], model)
        (model.parent / "manifest.json").write_text(json.dumps(rec))
        if stage_manifests:  # the run folder's flow and crops manifests of the model's method
            run = case["model"].parents[3]  # <run>/models/dis/<part>/best.pt
            for stage in ("flow", "crops"):
                dst = model.parents[3] / stage / "dis" / "keyframe" / "manifest.json"
                dst.parent.mkdir(parents=True)
                shutil.copy(run / stage / "dis" / "keyframe" / "manifest.json", dst)
        return model

    def err(model: Path) -> str:
        return one_line(call_main(predict.main, case["f1"], case["f2"], "--boxes",
                                  case["boxes"], "--model", model, "--device", "cpu"))

    fix = "copy the model's folder again or retrain it"
    bare = {k: v for k, v in real.items() if k not in ("node", "recipe")}
    model = model_with("bare/f0", bare)
    assert err(model) == (f"PredictError: {model.parent / 'manifest.json'}: records neither "
                          "the model's recipe nor the node that trained it (\"node\": None, "
                          f"want \"train[<method>/<part>]\"); {fix}")
    nulls = {**real, "recipe": {**real["recipe"], "flow_params": None, "crop_size": None}}
    model = model_with("nulls/f0", nulls)
    assert err(model) == (f"PredictError: {model.parent / 'manifest.json'}: recipe "
                          "flow_params=None (want a mapping of the flow's parameters); "
                          "crop_size=None (want a whole number of pixels); the manifest is "
                          f"damaged or was edited: {fix}")
    edited = {**real, "recipe": {**real["recipe"], "method": "nope"}}
    model = model_with("method/f0", edited)
    assert err(model) == (f"PredictError: {model.parent / 'manifest.json'}: recipe "
                          "method='nope' is no flow method (known: dis, farneback, "
                          "fastflownet, gt, raft, raft_small); the manifest is damaged or was "
                          f"edited: {fix}")
    flow_params = {**real["recipe"]["flow_params"], "flow_scale": -1}
    edited = {**real, "recipe": {**real["recipe"], "flow_params": flow_params}}
    model = model_with("scale/f0", edited)
    assert err(model) == (f"PredictError: {model.parent / 'manifest.json'}: recipe "
                          "flow_params: flow_scale=-1: Input should be greater than 0; the "
                          f"manifest is damaged or was edited: {fix}")
    old = {k: v for k, v in real.items() if k != "recipe"}  # recorded before recipes were
    assert old["node"].startswith("train[dis/")
    model = model_with("lone/models/dis/f0", old)
    line = err(model)
    assert line.startswith(f"PredictError: {root / 'lone/flow/dis/keyframe/manifest.json'} "
                           f"not found; {model.parent / 'manifest.json'} has no recipe")
    model = model_with("run/models/dis/f0", old, stage_manifests=True)
    assert predict.read_recipe(model) == real["recipe"]


def test_a_device_that_is_not_there_is_one_line_before_work(case, call_main):
    """Issue 53: ``--device foo`` ended in a traceback (a ProfileError from deep inside),
    ``--device cuda`` on a machine without a GPU in a RuntimeError after the flow was
    computed. Both are one line naming the option and the choices, before any work."""
    import torch

    out = case["tmp"] / "device.png"

    def err(device: str) -> str:
        return one_line(call_main(predict.main, case["f1"], case["f2"], "--boxes",
                                  case["boxes"], "--model", case["model"], "--device", device,
                                  "--out", out))

    assert err("foo") == "PredictError: --device 'foo': not a device; give auto, cpu or cuda"
    if not torch.cuda.is_available():
        assert err("cuda") == ("PredictError: --device cuda: no CUDA device is visible on "
                               "this machine; give --device cpu (or auto, which uses a GPU "
                               "when there is one)")
    assert not out.exists()


def test_predict_imports_without_notebook_packages():
    """A server that installs flowmod for inference only has no IPython or matplotlib: the
    predict CLI must import without them (issue 40)."""
    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('IPython', 'matplotlib'):\n"
        "            raise ImportError(f'blocked: {name}')\n"
        "sys.meta_path.insert(0, Block())\n"
        "import flowmod.predict\n"
        "print('ok', 'IPython' in sys.modules, 'matplotlib' in sys.modules)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-800:]
    assert r.stdout.split() == ["ok", "False", "False"]
