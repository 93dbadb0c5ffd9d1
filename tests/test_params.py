"""Profiles and parameter validation: good profiles load, bad values fail fast and clearly."""

import subprocess
import sys

import pytest
import yaml

from flowmod import params
from flowmod.params import Params, ProfileError, load_profile, validate
from flowmod.paths import repo_root


@pytest.mark.parametrize("name", ["smoke", "demo"])
def test_shipped_profiles_validate(name):
    p = load_profile(name)
    assert p.profile == name
    assert p.run_dir == f"runs/{name}"
    assert p.min_distance < p.max_distance


def test_paper_profile_keeps_paper_settings_and_requires_dataroot():
    with pytest.raises(ProfileError, match="dataroot is required"):
        load_profile("paper")
    p = load_profile("paper", dataroot="/data/sets/nuscenes")
    # Table 2 and the preprocessing of the paper
    assert (p.crop_size, p.epochs, p.batch_size) == (224, 60, 128)
    assert (p.lr, p.momentum, p.weight_decay, p.step_size, p.gamma) == (0.01, 0.9, 0.01, 10, 0.5)
    assert (p.min_distance, p.max_distance, p.visibility_tokens) == (30.0, 70.0, ["4"])
    assert p.categories == params.TABLE1_CATEGORIES and len(p.categories) == 7
    assert p.version == "v1.0-trainval"
    # at scale: crops straight from flow, mixed precision and loader workers (a GPU run)
    assert (p.flow_store, p.amp, p.num_workers) == ("crops", "bf16", 4)


@pytest.mark.parametrize("name", ["demo", "classroom", "paper"])
def test_the_crop_factor_and_table4_range_are_the_paper_s(name):
    """The paper crops 3 times the box's longer side and scores Table 4 up to 70 m: values
    of the method, not of a profile's size, so every shipped profile keeps them (issue 53:
    2.5 or 75 m were caught only because notebook parameter cells must equal the defaults,
    so the same change in a profile would have passed)."""
    p = load_profile(name, dataroot="/data/sets/nuscenes")
    assert (p.crop_scale, p.general_max_distance) == (3.0, 70.0)
    assert (p.min_distance, p.max_distance) == (30.0, 70.0)  # Table 1's band


def test_defaults_are_the_demo_profile():
    demo = load_profile("demo")
    assert Params() == demo


@pytest.mark.parametrize(
    ("override", "needle"),
    [
        ({"min_distance": 80.0}, "min_distance=80.0 must be < max_distance=70.0"),
        ({"speed_threshold": -1.0}, "speed_threshold=-1.0"),
        ({"epochs": "many"}, "epochs='many'"),
        ({"flow_methods": ["dis", "lucas"]}, "flow_methods.1='lucas'"),
        ({"split_fractions": [0.5, 0.5, 0.5]}, "must sum to 1"),
        ({"split_fractions": [1.0]}, "three non-negative numbers"),
        ({"visibility_tokens": ["5"]}, "visibility_tokens.0='5'"),
        ({"crop_size": 4}, "crop_size=4"),
        ({"categories": []}, "categories is empty"),
        ({"dataroot": ""}, "dataroot is required"),
        ({"world_sweep_scenes": 199}, "world_sweep_scenes=199 must be <= world_scenes=100"),
        ({"raw_input_methods": ["raft"]}, "['raft'] not in flow_methods"),
        ({"input_scaling": "raw", "raw_input_methods": ["dis"]},
         "input_scaling, which is raw already"),
    ],
)
def test_bad_values_name_the_key(override, needle):
    with pytest.raises(ProfileError) as e:
        validate(override, source="test")
    assert needle in str(e.value)
    assert str(e.value).startswith("test: ")


def test_unknown_key_lists_allowed_keys():
    with pytest.raises(ProfileError) as e:
        validate({"epochz": 3})
    msg = str(e.value)
    assert "unknown key 'epochz'" in msg
    assert "epochs" in msg and "crop_size" in msg


def test_several_errors_are_reported_together():
    with pytest.raises(ProfileError) as e:
        validate({"epochs": 0, "lr": -1})
    assert "epochs=0" in str(e.value) and "lr=-1" in str(e.value)


def test_missing_profile_lists_known_ones():
    with pytest.raises(ProfileError, match="known: classroom, demo, paper, smoke"):
        load_profile("nonexistent")


def test_profile_must_be_a_mapping(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(ProfileError, match="must be a mapping"):
        load_profile(str(bad))


def test_from_notebook_takes_only_param_names():
    ns = {"epochs": 3, "crop_size": 32, "pd": object(), "_private": 1}
    p = params.from_notebook(ns)
    assert (p.epochs, p.crop_size) == (3, 32)


def test_paths_resolve_against_repo_root():
    p = validate({"run_dir": "runs/x", "dataroot": "/abs/data", "synthetic": False})
    assert p.run_path == repo_root() / "runs" / "x"
    assert str(p.dataroot_path) == "/abs/data"
    # a generated world lives in a folder of its own, named by its generation parameters
    g = validate({"dataroot": "data/demo"})
    assert g.dataroot_path == repo_root() / "data" / "demo" / "worlds" / g.world_id
    assert validate({"dataroot": "data/demo", "seed": 1}).world_id != g.world_id
    assert validate({"dataroot": "data/demo", "epochs": 1}).world_id == g.world_id


def test_cli_rejects_a_bad_profile_before_work(tmp_path, call_main, monkeypatch):
    from flowmod import runner

    monkeypatch.chdir(repo_root())
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"profile": "bad", "min_distance": 90.0}))
    out = tmp_path / "executed"
    proc = call_main(runner.main, "--profile", bad, "--out", out)
    assert proc.returncode == 2
    assert "min_distance=90.0 must be < max_distance=70.0" in proc.stderr
    assert not out.exists(), "a bad profile must be rejected before any notebook runs"


def _runner(*args, cwd=None) -> subprocess.CompletedProcess:
    """The runner CLI in a process of its own, as a user runs it."""
    return subprocess.run([sys.executable, "-m", "flowmod.runner", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd or repo_root())


def test_cli_bad_yaml_gives_one_line_naming_the_file(tmp_path, call_main, monkeypatch):
    from flowmod import runner

    monkeypatch.chdir(repo_root())
    bad = tmp_path / "broken.yaml"
    bad.write_text("profile: broken\nepochs: [1\nseed: 2\n")
    proc = call_main(runner.main, "--profile", bad, "--status")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert str(bad) in proc.stderr and "not valid YAML at line 3" in proc.stderr
    proc = call_main(runner.main, "--profile", "smoke", "--status", "--set",
                     "flow_methods=[nope")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "--set 'flow_methods=[nope'" in proc.stderr and "not a YAML value" in proc.stderr


def test_a_second_run_on_one_folder_stops_with_one_line_and_a_killed_holder_frees_it(tmp_path):
    """An OS file lock per run folder: a second runner names the process that holds it and
    stops before any work; kill -9 of the holder releases it (the kernel closes its file)."""
    import os
    import signal
    import time

    run_dir = tmp_path / "runs"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from flowmod.lock import folder_lock\n"
         f"with folder_lock({str(run_dir)!r}, 'a test holder'):\n"
         "    print('held', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        out = tmp_path / "executed"
        proc = _runner("--profile", "smoke", "--only", "00", "--out", out,
                       "--set", f"run_dir={run_dir}")
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr
        assert f"in use by pid {holder.pid} (a test holder" in lines[0]
        assert not out.exists(), "nothing ran"
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait()
    from flowmod.lock import folder_lock

    t0 = time.monotonic()
    with folder_lock(run_dir, "after the kill"):
        assert time.monotonic() - t0 < 1.0


def test_a_bad_override_is_blamed_on_set_not_on_the_profile(tmp_path):
    """Issue 41: ``--set epochs=-1`` was reported as an error of params/smoke.yaml."""
    from flowmod.params import ProfileError, load_profile

    with pytest.raises(ProfileError) as e:
        load_profile("smoke", epochs=-1)
    assert str(e.value).startswith("--set epochs=-1: ") and "smoke.yaml" not in str(e.value)
    bad = tmp_path / "bad.yaml"
    bad.write_text("profile: bad\nepochs: -1\n")
    with pytest.raises(ProfileError) as e:
        load_profile(bad, lr=-1.0)
    msg = str(e.value)
    assert msg.startswith("--set lr=-1.0: ") and f"{bad}: epochs=-1: " in msg


def test_runner_faults_are_one_line(tmp_path, monkeypatch, capsys):
    """Issue 41: a run folder that is a file, Ctrl-C and a full disk each end in one line
    naming the thing (no traceback); a dry --gc of a missing run folder creates nothing."""
    import errno

    from flowmod import runner

    afile = tmp_path / "afile"
    afile.write_text("")
    assert runner.main(["--profile", "smoke", "--set", f"run_dir={afile}", "--only", "00",
                        "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(afile) in err[0] and "a file stands where a folder" in err[0]
    nothere = tmp_path / "nothere"
    assert runner.main(["--profile", "smoke", "--set", f"run_dir={nothere}", "--gc",
                        "--dry-run"]) == 0
    assert not nothere.exists() and "nothing to free" in capsys.readouterr().out

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "run", interrupted)
    assert runner.main(["--profile", "smoke"]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "interrupted" in err[0] and "resumes" in err[0]
    full = OSError(errno.ENOSPC, "No space left on device", "/runs/demo/crops/x.npy")
    assert runner.os_error_line(full).startswith("no space left on the device of "
                                                 "/runs/demo/crops/x.npy")
    ro = OSError(errno.EROFS, "Read-only file system", "/mnt/ro/runs")
    assert "cannot write /mnt/ro/runs" in runner.os_error_line(ro)


def test_a_run_folder_that_is_a_file_is_one_line_before_any_work(tmp_path, call_main):
    """Issue 53: ``--status`` with run_dir a file printed a "missing" line per node (48);
    now it, ``--gc`` and a run each say once which file stands in the way, and a run with
    ``--out`` a file touches nothing (the file, the run folder)."""
    from flowmod import runner

    afile = tmp_path / "afile"
    afile.write_text("keep")
    want = (f"ProfileError: run_dir {afile}: a file stands where a folder is needed; remove "
            "it or give another folder (--set run_dir=...)\n")
    for mode in ("--status", "--gc"):
        proc = call_main(runner.main, "--profile", "smoke", "--set", f"run_dir={afile}", mode)
        assert (proc.returncode, proc.stdout, proc.stderr) == (2, "", want), mode
    below = afile / "runs"
    proc = call_main(runner.main, "--profile", "smoke", "--set", f"run_dir={below}", "--status")
    assert (proc.returncode, proc.stdout, proc.stderr) == (
        2, "", f"ProfileError: run_dir {below}: a file stands where a folder is needed (its "
        f"parent {afile}); remove it or give another folder (--set run_dir=...)\n")
    runs = tmp_path / "runs"
    proc = call_main(runner.main, "--profile", "smoke", "--set", f"run_dir={runs}", "--only",
                     "00", "--out", afile)
    assert (proc.returncode, proc.stderr) == (2, f"ProfileError: --out {afile}: a file stands "
                                              "where a folder is needed; remove it or give "
                                              "another folder (--out ...)\n")
    assert afile.read_text() == "keep" and not runs.exists()


@pytest.mark.parametrize(("values", "want"), [
    ({}, ["gt", "dis"]),                                      # the exact flow and DIS
    ({"flow_methods": ["farneback", "gt", "dis"]}, ["gt", "farneback"]),
    ({"flow_methods": ["dis"]}, ["dis"]),
    ({"input_scaling": "raw"}, []),                           # the recipe is raw already
    ({"raw_input_methods": []}, []),
])
def test_raw_input_methods_default_to_the_exact_flow_and_the_first_estimate(values, want):
    assert validate(values).raw_input_methods == want
