"""A procedural driving world written in the nuScenes v1.0 on-disk format (CAM_FRONT only).

The official devkit (``nuscenes.nuscenes.NuScenes``) loads it, so the pipeline runs unchanged on
it and on real nuScenes. What the world contains, per scene (``synth-0000``, ...):

* a main road with 1-3 lanes per direction, parking lanes, sidewalks, buildings or front
  yards with hedges and trees, poles, a distant skyline; often a cross road (intersection with
  crosswalks and stop lines);
* the ego car cruising, following, in stop-and-go traffic, braking to a stop, waiting at or
  leaving an intersection, or turning left/right into the cross road;
* ~``vehicles_per_scene`` vehicles of the seven Table-1 categories and some others
  (motorcycles, bicycles, trailers) with realistic sizes: parked at the kerb, queued at the
  cross road (some start moving), driving with, against and across the ego lane, far ahead
  moving radially, accelerating or braking through 2 m/s, rolling near 2 m/s; pedestrians;
* weather and light: clear, overcast, after rain (wet ground), rain (streaks, haze) and night
  (dark, lights), named in the scene description (``"Night, big street, parked cars"``).

Frames are 1600x900 JPEGs of a nuScenes-like CAM_FRONT (fx = fy ~ 1266 px, camera ~1.5 m up,
~1.7 m ahead of the ego origin). Keyframes (samples) come every ~0.5 s; ``n_sweep_scenes``
scenes also get the ~12 Hz frames in between (sweeps; 4-5 per gap, jittered timestamps, an
occasional dropped frame) and about three more vehicles driving with or against the ego
nearer than 30 m (the generalisation set's near movers). Annotations (sample_annotation) exist on keyframes for every agent
within 100 m; visibility tokens '1'..'4' come from the rendered visible fraction of the box's
silhouette inside the image (0-40, 40-60, 60-80, 80-100 %).

Ground truth is exact and re-derived on demand from the world's own description, stored as
JSON beside the tables (``<dataroot>/<version>/synth_world.json``): :func:`gt_flow` renders
the depth / surface-id maps of two frames and moves every pixel's 3D point with its surface's
rigid motion; :func:`true_velocity` differentiates the analytic trajectories.

Public API: :func:`generate_world` (:func:`flowmod.world.source.ensure_world` makes a
profile's world), :func:`is_synthetic`,
:func:`gt_flow`, :func:`true_velocity` (chapter 01's tables and figures are in
:mod:`flowmod.chapters.ch01_world`, the naive rule in :mod:`flowmod.difficulty`).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

from flowmod.params import GENERATOR_VERSION
from flowmod.progress import bar
from flowmod.world import scene as ws
from flowmod.world.agents import NEAR_MOVERS
from flowmod.world.records import (
    CHANNEL,
    TABLES,
    scene_job,
    static_tables,
    token,
    write_bytes,
    write_json,
)
from flowmod.world.truth import WORLD_FILE, WorldError, load_world


def _check_dataroot(root: Path, version: str) -> None:
    """Refuse to write into a dataroot that holds real (non-synthetic) nuScenes tables."""
    if not root.exists():
        return
    for d in sorted(p for p in root.iterdir() if p.is_dir()):
        if (d / "scene.json").is_file() and not (d / WORLD_FILE).is_file():
            raise WorldError(
                f"{root} holds a real (non-synthetic) nuScenes version {d.name!r}; the synthetic "
                f"world will not write into it. Choose another dataroot for the synthetic world "
                f"(e.g. data/demo), or set synthetic: false to use the real data."
            )


def generate_world(
    dataroot: str | os.PathLike[str],
    version: str = "v1.0-synth",
    *,
    n_scenes: int,
    n_keyframes: int,
    n_sweep_scenes: int,
    vehicles_per_scene: int,
    seed: int = 0,
    n_jobs: int = 2,
    progress: bool = True,
    near_movers: int = NEAR_MOVERS,
) -> Path:
    """Generate the synthetic world into ``<dataroot>/<version>`` (+ samples/, sweeps/, maps/).

    Images are written first (each atomically); the tables are built in a hidden folder and
    renamed into place last, so a version folder exists only for a finished world. An existing
    synthetic version folder is replaced; a real one is never touched (:class:`WorldError`).
    Returns the dataroot. Deterministic: same seed and sizes give byte-identical files.
    """
    _check_sizes(n_scenes, n_keyframes, n_sweep_scenes, vehicles_per_scene)
    root = Path(dataroot).expanduser().resolve()
    _check_dataroot(root, version)
    root.mkdir(parents=True, exist_ok=True)
    weathers, sweeps = ws.plan_weathers(n_scenes, n_sweep_scenes, seed)
    args = [
        (str(root), int(seed), i, int(n_keyframes), int(vehicles_per_scene), weathers[i], sweeps[i],
         int(near_movers))
        for i in range(n_scenes)
    ]
    results = _run_jobs(args, n_jobs, progress)

    tables, scenes = _scene_tables(results)
    map_filename = f"maps/synth-{token(seed, 'map')}.png"
    tables.update(static_tables(seed, n_scenes, map_filename))
    _write_map(root / map_filename)

    params = {
        "n_scenes": int(n_scenes),
        "n_keyframes": int(n_keyframes),
        "n_sweep_scenes": int(n_sweep_scenes),
        "vehicles_per_scene": int(vehicles_per_scene),
        "near_movers": int(near_movers),
        "seed": int(seed),
        "generator_version": GENERATOR_VERSION,
    }
    world = {
        "format": "flowmod-synth-world",
        "params": params,
        "version": version,
        "image_size": [1600, 900],
        "channel": CHANNEL,
        "complete": True,
        "scenes": scenes,
    }
    old_files = _install_tables(root, version, tables, world)
    _remove_stale_frames(root, old_files, tables["sample_data"])
    load_world.cache_clear()
    return root


def _check_sizes(
    n_scenes: int, n_keyframes: int, n_sweep_scenes: int, vehicles_per_scene: int
) -> None:
    """Refuse sizes the world cannot have (:class:`WorldError`)."""
    for name, v, lo in (
        ("n_scenes", n_scenes, 1),
        ("n_keyframes", n_keyframes, 2),
        ("vehicles_per_scene", vehicles_per_scene, 1),
        ("n_sweep_scenes", n_sweep_scenes, 0),
    ):
        if int(v) < lo:
            raise WorldError(f"{name}={v} must be >= {lo}")
    if n_sweep_scenes > n_scenes:
        raise WorldError(f"n_sweep_scenes={n_sweep_scenes} must be <= n_scenes={n_scenes}")


def _scene_tables(results: list[dict]) -> tuple[dict[str, list], list[dict]]:
    """The per-scene tables (rows of every scene, in scene order) and the scene descriptions
    of the scene jobs' ``results``."""
    tables: dict[str, list] = {
        n: []
        for n in (
            "scene",
            "sample",
            "sample_data",
            "ego_pose",
            "sample_annotation",
            "instance",
            "calibrated_sensor",
        )
    }
    scenes = []
    for res in results:
        for n in tables:
            tables[n].extend(res["rows"][n])
        scenes.append(res["scene"])
    return tables, scenes


def _install_tables(root: Path, version: str, tables: dict[str, list], world: dict) -> set[str]:
    """Write the tables and the world description to a hidden folder and swap it in as
    ``<root>/<version>``; return the frame filenames of the synthetic world it replaced."""
    final = root / version
    tmp = root / f".{version}.partial-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    for n in TABLES:
        write_json(tmp / f"{n}.json", tables[n])
    write_json(tmp / WORLD_FILE, world, indent=None)
    old_files: set[str] = set()
    if final.exists():
        if not (final / WORLD_FILE).is_file():
            shutil.rmtree(tmp)
            raise WorldError(f"{final} exists and is not a synthetic world; not replacing it")
        try:
            old_files = {
                r["filename"] for r in json.loads((final / "sample_data.json").read_text())
            }
        except (OSError, ValueError):
            old_files = set()
        aside = root / f".{version}.old-{os.getpid()}"
        os.replace(final, aside)
        os.replace(tmp, final)
        shutil.rmtree(aside, ignore_errors=True)
    else:
        os.replace(tmp, final)
    return old_files


def _remove_stale_frames(root: Path, old_files: set[str], sample_data: list[dict]) -> None:
    """Delete the replaced world's frames (``old_files``, relative to ``root``) that the new
    world's ``sample_data`` does not name."""
    new_files = {r["filename"] for r in sample_data}
    for stale in sorted(old_files - new_files):
        p = root / stale
        if p.is_file() and p.name.startswith("synth-"):
            p.unlink()


def _write_map(path: Path) -> None:
    """A blank 64 x 64 PNG as the map image the map table names."""
    img = np.full((64, 64), 255, np.uint8)
    ok, buf = cv2.imencode(".png", img)
    write_bytes(path, buf.tobytes())


def _run_jobs(args: list[tuple], n_jobs: int, progress: bool) -> list[dict]:
    """:func:`scene_job` of every argument tuple, in order: in this process or ``n_jobs``
    worker processes."""
    pbar = bar(total=len(args), desc="synthetic world", unit="scene", disable=not progress)
    out = []
    try:
        if n_jobs <= 1 or len(args) == 1:
            for a in args:
                out.append(scene_job(*a))
                pbar.update(1)
        else:
            # here, not at the top: joblib takes ~0.1 s to import and only parallel
            # generation needs it
            from joblib import Parallel, delayed

            gen = Parallel(n_jobs=n_jobs, return_as="generator")(
                delayed(scene_job)(*a) for a in args
            )
            for res in gen:
                out.append(res)
                pbar.update(1)
    finally:
        pbar.close()
    return out
