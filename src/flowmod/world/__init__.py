"""A procedural driving world written in the nuScenes v1.0 on-disk format (CAM_FRONT only).

The official devkit loads it, so the pipeline runs unchanged on it and on real nuScenes.
Modules, from the bottom up: :mod:`~flowmod.world.scene` (trajectories, roads, weather),
:mod:`~flowmod.world.layout` (the street and the ego's plan), :mod:`~flowmod.world.agents`
(vehicles and pedestrians placed where the camera sees them), :mod:`~flowmod.world.textures`
(procedural textures), :mod:`~flowmod.world.geometry` (camera, surfaces, projection),
:mod:`~flowmod.world.shading` (background, light, weather, sensor look),
:mod:`~flowmod.world.render` (frames, depth and surface ids as homographies),
:mod:`~flowmod.world.truth` (reading a world back: :func:`is_synthetic`, exact
:func:`gt_flow` and :func:`true_velocity`), :mod:`~flowmod.world.records` (the nuScenes
records of one scene) and :mod:`~flowmod.world.dataset` (writing the tables and JPEGs:
:func:`generate_world`) and :mod:`~flowmod.world.source` (the world as the study's source
stage: :func:`ensure_world`). ``python -m flowmod.world --profile demo`` builds a profile's world.
"""

from flowmod.world.dataset import GENERATOR_VERSION, generate_world
from flowmod.world.source import ensure_world, is_generated_world, world_fingerprint
from flowmod.world.truth import (
    WORLD_FILE,
    WorldError,
    agent_boxes,
    flow_between,
    gt_flow,
    is_synthetic,
    scene_of,
    true_velocity,
    world_params,
)

__all__ = [
    "GENERATOR_VERSION",
    "WORLD_FILE",
    "WorldError",
    "agent_boxes",
    "ensure_world",
    "flow_between",
    "generate_world",
    "gt_flow",
    "is_generated_world",
    "is_synthetic",
    "scene_of",
    "true_velocity",
    "world_fingerprint",
    "world_params",
]
