"""make weights: torchvision's own download (offline here: one clear line), what is present."""

import os
import subprocess
import sys

from flowmod import weights


def test_offline_download_fails_with_one_line_and_leaves_nothing(tmp_path):
    env = {**os.environ, "TORCH_HOME": str(tmp_path),
           # a closed local port: no network whatever the machine can reach
           "https_proxy": "http://127.0.0.1:9", "HTTPS_PROXY": "http://127.0.0.1:9"}
    proc = subprocess.run([sys.executable, "-m", "flowmod.weights"], env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("make weights:")]
    assert len(errors) == 1 and "needs internet" in errors[0]
    assert "raft_large_C_T_SKHT_K_V1" in errors[0]
    assert not list(tmp_path.rglob("*.pth")), "no partial checkpoint left behind"


def test_status_lists_the_files_the_flow_stage_looks_for(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    assert weights.available_networks() == []
    folder = tmp_path / "hub" / "checkpoints"
    folder.mkdir(parents=True)
    (folder / "fastflownet_ft_kitti.pth").write_bytes(b"placeholder")
    rows = weights.status()
    assert ("fastflownet", str(folder / "fastflownet_ft_kitti.pth"), True) in rows
    assert {m for m, _, _ in rows} == {"raft", "raft_small", "fastflownet"}
    assert weights.available_networks() == ["fastflownet"]


def test_paper_profile_names_the_networks_whose_weights_are_present(tmp_path, monkeypatch):
    from flowmod import runner

    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    data = tmp_path / "nuscenes"
    data.mkdir()
    said: list[str] = []
    p = runner.resolve_profile("paper", {"dataroot": str(data)}, say=said.append)
    assert p.flow_networks == ["raft", "fastflownet"]
    assert p.flow_methods == ["dis", "farneback"], "no weights: nothing added"
    assert len(said) == 2 and all("left out: no weights" in s for s in said)
    assert "raft_weights" in said[0] and "raft_large_C_T_SKHT_K_V1" in said[0]
    assert str(tmp_path / "hub" / "checkpoints") in said[1]

    folder = tmp_path / "hub" / "checkpoints"
    folder.mkdir(parents=True)
    (folder / "fastflownet_ft_kitti.pth").write_bytes(b"placeholder")
    raft = tmp_path / "raft-kitti.pth"
    raft.write_bytes(b"placeholder")
    said.clear()
    p = runner.resolve_profile("paper", {"dataroot": str(data), "raft_weights": str(raft)},
                               say=said.append)
    assert p.flow_methods == ["dis", "farneback", "raft", "fastflownet"]
    assert said == [f"flow_networks: raft added to flow_methods (weights {raft})",
                    f"flow_networks: fastflownet added to flow_methods (weights "
                    f"{folder / 'fastflownet_ft_kitti.pth'})"]
    # a weights parameter naming a missing file leaves the method out, never falls back
    p = runner.resolve_profile("paper", {"dataroot": str(data),
                                         "raft_weights": str(tmp_path / "gone.pth")},
                               say=said.append)
    assert p.flow_methods == ["dis", "farneback", "fastflownet"]
    assert f"raft left out: raft_weights={tmp_path / 'gone.pth'} is not a file" in said[-2]
