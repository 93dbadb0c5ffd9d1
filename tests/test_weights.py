"""make weights: torchvision's own download (offline here: one clear line), what is present."""

import os
import subprocess
import sys

from flowmod import weights
from flowmod.paths import repo_root


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


# --- the one home of the weights (flowmod.flowweights) -------------------------------------------

def test_the_catalog_names_each_networks_parameter_and_the_shipped_default():
    import hashlib

    from flowmod.flowweights import CATALOG, FASTFLOWNET_SYNTH, SHIPPED_FASTFLOWNET
    from flowmod.params import Params

    fields = Params.model_fields
    for method, entry in CATALOG.items():
        assert entry.method == method and entry.param in fields, entry
        assert entry.cache_names or entry.torchvision_arch, f"{method}: looked up nowhere"
    assert SHIPPED_FASTFLOWNET == "weights/fastflownet_synth/weights.pt"
    for name in ("fastflownet_weights", "selfflow_init", "shipped_weights"):
        assert fields[name].default == SHIPPED_FASTFLOWNET, name
    m = FASTFLOWNET_SYNTH.manifest()
    shipped = repo_root() / SHIPPED_FASTFLOWNET
    assert m["sha256"] == hashlib.sha256(shipped.read_bytes()).hexdigest()
    assert shipped.stat().st_size <= 10 * 2**20  # float16, at most 10 MB
    assert FASTFLOWNET_SYNTH.is_shipped(SHIPPED_FASTFLOWNET) and FASTFLOWNET_SYNTH.is_shipped(shipped)
    assert not FASTFLOWNET_SYNTH.is_shipped("weights/other.pt")
    assert not CATALOG["raft"].is_shipped(SHIPPED_FASTFLOWNET) and CATALOG["raft"].manifest() is None


def test_the_networks_look_up_the_catalogs_files():
    from flowmod.flow import architectures as fn
    from flowmod.flow.networks import cache_files
    from flowmod.flowweights import CATALOG

    assert cache_files("fastflownet") == [fn.hub_checkpoint_dir() / n
                                          for n in CATALOG["fastflownet"].cache_names]
    assert cache_files("fastflownet")[0].name == "fastflownet_ft_kitti.pth"  # the paper's first
    assert [f.name for f in cache_files("raft")] == [
        f for _, f in fn.torchvision_weight_files("raft_large")]
    assert weights.RAFT_WEIGHTS == (("raft_large", "C_T_SKHT_K_V1"), ("raft_small", "C_T_V2"))


def test_no_module_but_the_catalog_names_the_shipped_weights_folder():
    """No string in the code (docstrings and comments aside) names the shipped folder
    outside :mod:`flowmod.flowweights`: every reader asks the catalog."""
    import ast

    src = repo_root() / "src" / "flowmod"
    offenders = []
    for f in src.rglob("*.py"):
        tree = ast.parse(f.read_text())
        docs = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr)}
        if f.name != "flowweights.py" and any(
                isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs
                and "fastflownet_synth" in n.value for n in ast.walk(tree)):
            offenders.append(str(f.relative_to(src)))
    assert not offenders, f"the shipped weights' folder named outside flowweights.py: {offenders}"
