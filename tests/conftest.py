"""Shared fixtures: the smoke synthetic world (generated once per test session)."""

from __future__ import annotations

from pathlib import Path

import pytest

from flowmod.params import load_profile

#: Version folder of the smoke world.
SMOKE_VERSION = "v1.0-synth"


@pytest.fixture(scope="session")
def smoke_world(tmp_path_factory) -> tuple[Path, str]:
    """(dataroot, version) of a tiny world with the smoke profile's sizes (4 scenes x 4
    keyframes, 1 sweep scene, ~16 vehicles, one night scene); a few seconds to generate."""
    from flowmod.world import generate_world

    p = load_profile("smoke")
    root = tmp_path_factory.mktemp("smoke_world")
    generate_world(
        root,
        SMOKE_VERSION,
        n_scenes=p.world_scenes,
        n_keyframes=p.world_keyframes,
        n_sweep_scenes=p.world_sweep_scenes,
        vehicles_per_scene=p.world_vehicles,
        seed=p.seed,
        n_jobs=1,
        progress=False,
    )
    return root, SMOKE_VERSION


@pytest.fixture(scope="session")
def smoke_nusc(smoke_world):
    """The smoke world loaded by the official devkit (``NuScenes``, verbose=False)."""
    from nuscenes.nuscenes import NuScenes

    root, version = smoke_world
    return NuScenes(version=version, dataroot=str(root), verbose=False)
