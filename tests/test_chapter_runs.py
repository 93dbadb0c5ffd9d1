"""The runner beyond the smoke study: parameters refused before work, a failing notebook,
the paper profile on a devkit-format data set that is not a generated world, and every
chapter's "Try it" commands as a reader types them. A file of its own, so that pytest-xdist
(``--dist loadfile``) runs it beside the executed smoke study of test_notebooks.py."""

import json

import nbformat
import pandas as pd
import pytest

from flowmod import runner
from flowmod.params import ProfileError
from flowmod.report import book
from flowmod.runner import NotebookFailed

pytestmark = pytest.mark.slow


def test_missing_real_dataroot_is_rejected_before_work(tmp_path):
    with pytest.raises(ProfileError, match=r"v1.0-trainval.*not found|does not exist"):
        runner.run("paper", {"dataroot": str(tmp_path)}, out_dir=tmp_path / "executed")
    assert not (tmp_path / "executed").exists()


def test_device_that_does_not_exist_is_rejected_before_work(tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("needs a machine without CUDA")
    with pytest.raises(ProfileError, match="device='cuda'.*no CUDA device"):
        runner.run("smoke", {"device": "cuda"}, out_dir=tmp_path / "executed")
    assert not (tmp_path / "executed").exists()


def test_failing_notebook_stops_the_run_and_is_never_rendered(tmp_path):
    nbs = tmp_path / "notebooks"
    nbs.mkdir()
    nb = nbformat.read(runner.notebooks()[0], as_version=4)
    nb.cells.append(nbformat.v4.new_code_cell('raise ValueError("boom in a cell")'))
    nbformat.write(nb, nbs / "00_setup.ipynb")
    nbformat.write(nbformat.read(runner.notebooks()[0], as_version=4), nbs / "01_later.ipynb")
    executed = tmp_path / "executed"
    with pytest.raises(NotebookFailed, match=r"00_setup.ipynb failed in cell \d+: ValueError: boom"):
        runner.run("smoke", {"run_dir": str(tmp_path / "runs")}, out_dir=executed,
                   notebooks_dir=nbs)
    assert not (executed / "01_later.ipynb").exists(), "the run must stop at the first failure"
    info = json.loads((executed / "run_info.json").read_text())
    assert info["status"] == "failed" and info["notebooks"]["00_setup"]["status"] == "failed"
    with pytest.raises(book.BookError, match="did not finish"):
        book.build(executed, tmp_path / "html")
    # even with a doctored run record, the failed notebook itself is refused
    with pytest.raises(book.BookError, match="failed when it ran"):
        book.check_executed(executed / "00_setup.ipynb")
    assert not (tmp_path / "html").exists()


def test_paper_profile_runs_on_a_devkit_dataset_by_parameters_only(smoke_world, tmp_path):
    """PROFILE=paper on a renamed copy: every notebook runs; only parameters change."""
    from flowmod import world

    root = renamed_copy(*smoke_world, tmp_path / "nuscenes")
    assert not world.is_synthetic(root, "v1.0-mini")
    overrides = {"dataroot": str(root), "version": "v1.0-mini",
                 "run_dir": str(tmp_path / "runs"), "epochs": 1,
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


@pytest.mark.parametrize("nb_path", runner.notebooks(), ids=lambda p: p.stem)
def test_try_it_commands_run(nb_path, smoke_built, tmp_path, capsys):
    """A chapter's "Try it" commands, as a reader would type them, on a copy of the built
    smoke run (``--profile demo`` becomes ``--profile smoke``), so that they never rot: each
    builds what its parameter changes and executes its chapter. The commands run through
    the runner's ``main`` in this process (the interpreter start is all that differs from a
    shell); the world is the session's, read in place (no command makes one)."""
    import shlex
    import shutil

    from test_sources import try_it_commands

    shutil.copytree(smoke_built.run_path, tmp_path / "runs", symlinks=True)
    prefix = [".venv/bin/python", "-m", "flowmod.runner"]
    for cmd in try_it_commands(nb_path):
        argv = ["smoke" if a == "demo" else a for a in shlex.split(cmd)]
        assert argv[:3] == prefix, cmd
        argv = argv[3:] + ["--set", f"run_dir={tmp_path / 'runs'}", "--set",
                           f"dataroot={smoke_built.dataroot}", "--out", str(tmp_path / "executed")]
        rc = runner.main(argv)
        out, err = capsys.readouterr()
        assert rc == 0, f"{cmd}\n{out[-1500:]}\n{err[-1500:]}"
        if "--status" in cmd:
            assert "stale" in out or "missing" in out, out
        else:
            assert " ok (" in out, out


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
