"""PROFILE=paper on a devkit-format data set that is not a generated world (a renamed copy
of the smoke world): every notebook runs, only parameters change. A file of its own: it
needs no built smoke study, so pytest-xdist (``--dist loadfile``) runs it while the other
worker builds one."""

import json

import pandas as pd
import pytest

from flowmod import runner
from flowmod.report import book

pytestmark = pytest.mark.slow


def test_paper_profile_runs_on_a_devkit_dataset_by_parameters_only(smoke_world, tmp_path):
    """PROFILE=paper on a renamed copy: every notebook runs; only parameters change (a
    narrower network for 1 epoch: the paper's width 64 is no other code path, and it took
    26 of the test's 150 s)."""
    from flowmod import world

    root = renamed_copy(*smoke_world, tmp_path / "nuscenes")
    assert not world.is_synthetic(root, "v1.0-mini")
    overrides = {"dataroot": str(root), "version": "v1.0-mini",
                 "run_dir": str(tmp_path / "runs"), "epochs": 1, "model_width": 16,
                 "crop_size": 32, "batch_size": 16, "flow_scale": 0.25, "general_max_scenes": 1,
                 "seeds": 1}
    record = runner.run("paper", overrides, out_dir=tmp_path / "executed")
    assert record["status"] == "ok" and record["parameters"]["version"] == "v1.0-mini"
    g2 = book.read_glue(tmp_path / "executed" / "02_filtering.ipynb")
    assert g2["n_keyframe_objects"] > 0 and g2["n_general_objects"] > 0
    assert g2["split_unit"] == "log", "real data is split by log"
    scenes = pd.read_parquet(tmp_path / "runs" / "select" / "pairs.parquet")["scene"]
    assert scenes.str.startswith("scene-1").all()
    assert "true_agreement" not in book.read_glue(tmp_path / "executed" / "04_labeling.ipynb")
    g7 = book.read_glue(tmp_path / "executed" / "07_evaluation.ipynb")
    assert g7["headline_method"] == "dis" and "test_f1_gt" not in g7
    g10 = book.read_glue(tmp_path / "executed" / "10_inputs.ipynb")
    assert g10["ext_n_planned"] == 0, "chapter 10 is off in the paper profile (~90 GB)"
    assert g10["ext_headline"].startswith("not part of this profile")
    g11 = book.read_glue(tmp_path / "executed" / "11_all_distances.ipynb")
    assert g11["wide_n_built"] == 0 and g11["wide_headline"].startswith("not part of this")
    g12 = book.read_glue(tmp_path / "executed" / "12_self_trained_flow.ipynb")
    assert g12["selfflow_n_built"] == 0, "make selfflow trains; make book does not"


# --- the real-data path: a devkit-format data set that is not a generated world -------------

def renamed_copy(dataroot, version, dest):
    """A copy of a world that looks like someone else's nuScenes: version folder v1.0-mini,
    scene names scene-1NNN, and no world description (so no exact ground truth)."""
    import shutil

    shutil.copytree(dataroot, dest, ignore=shutil.ignore_patterns(version))
    shutil.copytree(dataroot / version, dest / "v1.0-mini",
                    ignore=shutil.ignore_patterns("synth_world.json"))
    scene_json = dest / "v1.0-mini" / "scene.json"
    scenes = json.loads(scene_json.read_text())
    log_json = dest / "v1.0-mini" / "log.json"
    logs = json.loads(log_json.read_text())
    for i, sc in enumerate(scenes):
        sc["name"] = f"scene-{1000 + i}"
        if i:  # one drive (log) per scene, as most nuScenes logs hold one or two scenes
            logs.append({**logs[0], "token": f"log-{i:04d}", "logfile": f"n-log-{i}"})
            sc["log_token"] = logs[-1]["token"]
    scene_json.write_text(json.dumps(scenes))
    log_json.write_text(json.dumps(logs))
    map_json = dest / "v1.0-mini" / "map.json"
    maps = json.loads(map_json.read_text())
    maps[0]["log_tokens"] = [lg["token"] for lg in logs]
    map_json.write_text(json.dumps(maps))
    return dest
