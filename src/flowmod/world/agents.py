"""Sampling a whole scene description: vehicles and pedestrians, calibration, description text.

Holds the categories and their sizes and weights, the placement of traffic and
pedestrians (in view of the ego camera, free of collisions), :func:`sample_scene` (one scene's
JSON-able description, built on :mod:`~flowmod.world.layout`), :func:`sample_calibration`
(CAM_FRONT calibration) and the nuScenes-style description text.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from pyquaternion import Quaternion

from flowmod.params import TABLE1_CATEGORIES
from flowmod.world.layout import ego_plan, sample_layout, static_objects
from flowmod.world.scene import (
    arc_length,
    footprints,
    lane_across,
    park_across,
    profile_const,
    profile_ramp,
    rects_overlap,
    road_frames,
    road_point,
    speed_at,
    stack_rects,
    straight_path,
    traj_state,
    weighted_choice,
    wrap_angle,
)

# --------------------------------------------------------------------------------------------
# Categories (official nuScenes names) and typical sizes (w, l, h in m)
# --------------------------------------------------------------------------------------------

#: Mean sizes (w, l, h), m, roughly the nuScenes class means.
CATEGORY_SIZES: dict[str, tuple[float, float, float]] = {
    "vehicle.car": (1.95, 4.62, 1.72),
    "vehicle.emergency.ambulance": (2.30, 6.10, 2.60),
    "vehicle.emergency.police": (2.00, 5.00, 1.80),
    "vehicle.truck": (2.50, 7.00, 2.90),
    "vehicle.bus.bendy": (2.95, 17.50, 3.40),
    "vehicle.bus.rigid": (2.90, 11.20, 3.50),
    "vehicle.construction": (2.80, 6.40, 3.20),
    "vehicle.motorcycle": (0.80, 2.10, 1.50),
    "vehicle.bicycle": (0.60, 1.70, 1.30),
    "vehicle.trailer": (2.90, 10.00, 3.60),
    "human.pedestrian.adult": (0.67, 0.73, 1.77),
    "human.pedestrian.child": (0.50, 0.50, 1.25),
}

#: Category weights for vehicles driving in lanes.
DRIVING_WEIGHTS = {
    "vehicle.car": 0.66,
    "vehicle.truck": 0.09,
    "vehicle.bus.rigid": 0.05,
    "vehicle.bus.bendy": 0.02,
    "vehicle.emergency.police": 0.03,
    "vehicle.emergency.ambulance": 0.02,
    "vehicle.construction": 0.03,
    "vehicle.motorcycle": 0.03,
    "vehicle.bicycle": 0.02,
    "vehicle.trailer": 0.01,
}

#: Category weights for parked vehicles.
PARKED_WEIGHTS = {
    "vehicle.car": 0.72,
    "vehicle.truck": 0.08,
    "vehicle.construction": 0.04,
    "vehicle.emergency.police": 0.03,
    "vehicle.emergency.ambulance": 0.02,
    "vehicle.bus.rigid": 0.02,
    "vehicle.motorcycle": 0.02,
    "vehicle.trailer": 0.03,
}

#: Table 1 of the paper (the categories the motion task is about).
TARGET_CATEGORIES = frozenset(TABLE1_CATEGORIES)


# --------------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------------


def _size(rng: np.random.Generator, category: str) -> list[float]:
    w, length, h = CATEGORY_SIZES[category]
    f = rng.uniform(0.92, 1.08, size=3)
    if category in ("vehicle.truck", "vehicle.trailer"):
        f[1] = rng.uniform(0.7, 1.35)
    return [round(float(w * f[0]), 3), round(float(length * f[1]), 3), round(float(h * f[2]), 3)]


def _moving_profile(rng: np.random.Generator, duration: float, vmax: float = 14.0) -> dict:
    """A speed profile for traffic: cruising, rolling near 2 m/s, or crossing 2 m/s."""
    kind = weighted_choice(rng, {"const": 0.5, "roll": 0.16, "accel": 0.17, "brake": 0.17})
    if kind == "const":
        return profile_const(rng.uniform(2.6, vmax))
    if kind == "roll":
        return profile_const(rng.uniform(0.6, 3.6))
    t0 = rng.uniform(-1.0, max(duration - 1.5, 0.5))
    if kind == "accel":
        return profile_ramp(
            t0, rng.uniform(0.0, 1.4), rng.uniform(3.0, 9.0), rng.uniform(0.8, 2.2)
        )
    return profile_ramp(t0, rng.uniform(3.0, 9.0), rng.uniform(0.0, 1.2), rng.uniform(0.8, 2.5))


def _targeted_point(
    rng,
    road: dict,
    across: float,
    ego: dict,
    duration: float,
    d_range: tuple[float, float],
    box_h: float,
    fov: float = 0.5,
):
    """A point on the line ``across`` of ``road`` that is ``d`` m (3D, to a box centre at
    height box_h / 2) from the ego origin and within +-``fov`` rad of its heading at a random
    time t*. Returns (x, y, along, t*) or None."""
    t_star = float(rng.uniform(0.0, duration))
    d = float(rng.uniform(*d_range))
    r2 = d * d - (box_h / 2) ** 2
    st = traj_state(ego, t_star)
    px, py, ph = float(st["x"]), float(st["y"]), float(st["h"])
    ox = road["o"][0] + across * road["left"][0] - px
    oy = road["o"][1] + across * road["left"][1] - py
    b = ox * road["dir"][0] + oy * road["dir"][1]
    disc = b * b - (ox * ox + oy * oy) + r2
    if disc < 0:
        return None
    sols = []
    for a in (-b + math.sqrt(disc), -b - math.sqrt(disc)):
        x = road["o"][0] + a * road["dir"][0] + across * road["left"][0]
        y = road["o"][1] + a * road["dir"][1] + across * road["left"][1]
        if abs(float(wrap_angle(math.atan2(y - py, x - px) - ph))) < fov:
            sols.append((x, y, a))
    if not sols:
        return None
    x, y, a = sols[int(rng.integers(0, len(sols)))]
    return x, y, a, t_star


def _place(
    rng, road, across, heading, ego, duration, prof, box_h, d_range, free_x, p_target: float = 0.85
):
    """Straight trajectory on a road line: targeted (in view at 30-75 m at some time) with
    probability ``p_target``, else at along = ``free_x`` at t = 0 (None if p_target is 1 and
    no targeted point exists)."""
    if rng.random() < p_target:
        hit = _targeted_point(rng, road, across, ego, duration, d_range, box_h)
        if hit is not None:
            x, y, _, t_star = hit
            traj = {"path": straight_path(x, y, heading), "s0": 0.0, "speed": prof}
            traj["s0"] = float(-(arc_length(traj, t_star) - 0.0))
            traj["t_view"] = t_star  # placed in view, 30-75 m ahead, at this time (s)
            return traj
        if p_target >= 1.0:
            return None
    x, y = road_point(road, free_x, across)  # main road: along = x; cross road: along = y
    return {"path": straight_path(x, y, heading), "s0": 0.0, "speed": prof}


def _view_intervals(
    traj: dict, size, times: np.ndarray, cam: np.ndarray, cam_h: np.ndarray
) -> np.ndarray:
    """Per time: (distance from the camera, azimuth lo, azimuth hi) of a box footprint, (T, 3).

    Azimuths (rad) are relative to the camera heading; ``cam`` (T, 2) positions (m).
    """
    st = traj_state(traj, times)
    c, s_ = np.cos(st["h"])[:, None], np.sin(st["h"])[:, None]
    hl, hw = size[1] / 2, size[0] / 2
    cl = np.array([hl, hl, -hl, -hl])[None, :]
    cw = np.array([hw, -hw, hw, -hw])[None, :]
    xs = st["x"][:, None] + cl * c - cw * s_
    ys = st["y"][:, None] + cl * s_ + cw * c
    az = wrap_angle(np.arctan2(ys - cam[:, 1:2], xs - cam[:, 0:1]) - cam_h[:, None])
    d = np.hypot(st["x"] - cam[:, 0], st["y"] - cam[:, 1])
    return np.stack([d, az.min(axis=1), az.max(axis=1)], axis=1)


def _hides(near: np.ndarray, far: np.ndarray) -> np.ndarray:
    """Per time: ``near`` (..., T, 3) is nearer and covers > 15 % of ``far``'s azimuths."""
    overlap = np.minimum(near[..., 2], far[..., 2]) - np.maximum(near[..., 1], far[..., 1])
    return (near[..., 0] < far[..., 0]) & (
        overlap > 0.15 * np.maximum(far[..., 2] - far[..., 1], 1e-6)
    )


def _in_band(iv: np.ndarray, lo: float = 30.0, hi: float = 70.0, fov: float = 0.55) -> np.ndarray:
    """Per time: 30-70 m from the camera (roughly the ego distance) and inside the image width."""
    return (iv[:, 0] >= lo - 1.7) & (iv[:, 0] <= hi - 1.7) & (iv[:, 1] > -fov) & (iv[:, 2] < fov)


#: Distances (m) from the ego at which a targeted vehicle is placed in view.
_NEAR = (30.0, 72.0)
#: Distances (m) at which a swept scene's extra near traffic is placed in view.
_CLOSE = (8.0, 28.0)
#: Vehicles driving near the ego that a scene with sweeps gets besides the others by default
#: (``world_near_movers``): the generalisation set's near movers (chapters 08 and 11).
NEAR_MOVERS = 3

#: A candidate agent: (category, size (w, l, h) in m, role, trajectory or None).
Candidate = tuple[str, list[float], str, dict | None]


def _agent_candidate(
    rng: np.random.Generator,
    roads: list[dict],
    ego: dict,
    duration: float,
    cross_x: float | None,
    vmax: float,
    p_target: float = 0.85,
) -> Candidate | None:
    """One candidate vehicle: (category, size, role, trajectory) or None.

    ``p_target``: probability of placing it in view 30-72 m ahead at some time (1 = always,
    None when impossible)."""
    main = roads[0]
    ego_x0 = float(traj_state(ego, 0.0)["x"])
    ego_x1 = float(traj_state(ego, duration)["x"])
    x_span = (min(ego_x0, ego_x1), max(ego_x0, ego_x1))
    role, category = _vehicle_role(rng, main, cross_x)
    size = _size(rng, category)
    if role in ("parked", "cross_parked"):
        return _parked_candidate(rng, role, category, size, roads, ego, duration, x_span, p_target)
    if role == "halt":  # standing in a lane (waiting, double-parked); may drive off
        traj = _halted_traj(rng, size, main, ego, duration, x_span, p_target)
        return category, size, "stopped", traj
    if role in ("same", "far", "convoy", "roll", "oncoming"):
        traj = _lane_traj(rng, role, size, main, ego, duration, vmax, x_span, p_target)
        return category, size, "moving", traj
    return _cross_candidate(rng, role, category, size, roads, ego, duration, vmax, p_target)


def _vehicle_role(rng: np.random.Generator, main: dict, cross_x: float | None) -> tuple[str, str]:
    """A vehicle's role (parked, halt, same, ...; the cross-road roles only with a cross road)
    and its category (no bus rolling near 2 m/s)."""
    has_park = [main["park"][0], main["park"][1]]
    roles = {
        "parked": 0.34 if any(has_park) else 0.0,
        "halt": 0.09,
        "same": 0.18,
        "oncoming": 0.13,
        "far": 0.03,
        "convoy": 0.05,
        "roll": 0.06,
    }
    if cross_x is not None:
        roles.update({"cross": 0.08, "queue": 0.05, "cross_parked": 0.05})
    role = weighted_choice(rng, roles)
    if role in ("parked", "cross_parked"):
        category = weighted_choice(rng, PARKED_WEIGHTS)
    else:
        category = weighted_choice(rng, DRIVING_WEIGHTS)
        if role == "roll" and category.startswith("vehicle.bus"):
            category = "vehicle.car"
    return role, category


def _parked_candidate(
    rng: np.random.Generator,
    role: str,
    category: str,
    size: list[float],
    roads: list[dict],
    ego: dict,
    duration: float,
    x_span: tuple[float, float],
    p_target: float,
) -> Candidate | None:
    """A vehicle parked at a kerb of the main road (role ``parked``) or of the cross road
    (``cross_parked``); None when that road has no parking lane. ``x_span``: the ego's x range
    over the scene (m)."""
    main = roads[0]
    road = main if role == "parked" else roads[1]
    sides = [i for i in (0, 1) if road["park"][i]]
    if not sides:
        return None
    side = int(rng.choice(sides))
    across = park_across(road, side) + rng.uniform(-0.25, 0.25)
    h = road["h"] + (0.0 if side == 0 else math.pi)
    if rng.random() < 0.15:
        h += math.pi  # parked facing the other way
    h += rng.normal(0, 0.03)
    if road is main:
        free = rng.uniform(x_span[0] + 5.0, x_span[1] + 140.0)
    else:
        free = float(rng.choice([-1, 1])) * rng.uniform(max(main["walk"]) + 3, 120)
    traj = _place(
        rng, road, across, h, ego, duration, profile_const(0.0), size[2], _NEAR, free, p_target
    )
    return category, size, "parked", traj


def _halted_traj(
    rng: np.random.Generator,
    size: list[float],
    main: dict,
    ego: dict,
    duration: float,
    x_span: tuple[float, float],
    p_target: float,
) -> dict | None:
    """Trajectory of a vehicle standing in a lane of the main road that may drive off (None
    when it must be in view and cannot be)."""
    direction = int(rng.choice([-1, 1]))
    lane = int(rng.integers(0, main["lanes"]))
    across = lane_across(main, direction, lane) + rng.normal(0, 0.15)
    h = 0.0 if direction > 0 else math.pi
    t_go = rng.uniform(0.0, duration * 2.0)
    prof = profile_ramp(t_go, 0.0, rng.uniform(3.0, 8.0), rng.uniform(0.8, 2.0))
    free = rng.uniform(x_span[0] + 10.0, x_span[1] + 120.0)
    return _place(rng, main, across, h, ego, duration, prof, size[2], _NEAR, free, p_target)


def _lane_traj(
    rng: np.random.Generator,
    role: str,
    size: list[float],
    main: dict,
    ego: dict,
    duration: float,
    vmax: float,
    x_span: tuple[float, float],
    p_target: float,
    near: tuple[float, float] | None = None,
) -> dict | None:
    """Trajectory of a vehicle driving in a lane of the main road: with the ego (``same``,
    ``far``, ``convoy``, ``roll``) or against it (``oncoming``); ``vmax`` in m/s. ``near``:
    place it in view at these distances (m) instead of its role's."""
    x_lo, x_hi = x_span
    direction = -1 if role == "oncoming" else 1
    lane = int(rng.integers(0, main["lanes"]))
    across = lane_across(main, direction, lane) + rng.normal(0, 0.15)
    h = 0.0 if direction > 0 else math.pi
    d_range = _NEAR
    if role == "far":
        prof = profile_const(rng.uniform(6.0, vmax))
        free = rng.uniform(x_lo + 60.0, x_hi + 130.0)
        d_range = (55.0, 110.0)
    elif role == "convoy":
        f = rng.uniform(0.85, 1.15)
        prof = {"t": list(ego["speed"]["t"]), "v": [float(v * f) for v in ego["speed"]["v"]]}
        free = rng.uniform(x_lo + 12.0, x_lo + 90.0)
    elif role == "roll":
        prof = profile_const(rng.uniform(0.5, 3.8))
        free = rng.uniform(x_lo + 10.0, x_hi + 90.0)
    elif role == "oncoming":
        prof = _moving_profile(rng, duration, vmax)
        free = rng.uniform(x_lo + 20.0, x_hi + 220.0)
    else:
        prof = _moving_profile(rng, duration, vmax)
        if rng.random() < 0.4 and len(prof["v"]) == 1:  # travelling with the ego
            v_ego = float(np.mean(speed_at(ego["speed"], np.linspace(0, duration, 5))))
            prof = profile_const(max(v_ego + rng.normal(0, 1.5), 0.6))
        free = rng.uniform(x_lo - 10.0, x_hi + 110.0)
    return _place(rng, main, across, h, ego, duration, prof, size[2], near or d_range, free,
                  p_target)


def _cross_candidate(
    rng: np.random.Generator,
    role: str,
    category: str,
    size: list[float],
    roads: list[dict],
    ego: dict,
    duration: float,
    vmax: float,
    p_target: float,
) -> Candidate | None:
    """A vehicle on the cross road: crossing the main road (role ``cross``) or queued before
    its stop line, maybe starting during the scene (``queue``; None when it must be in view)."""
    main, cross = roads[0], roads[1]
    direction = int(rng.choice([-1, 1]))
    lane = int(rng.integers(0, cross["lanes"]))
    across = lane_across(cross, direction, lane)
    h = cross["h"] + (0.0 if direction > 0 else math.pi)
    kerb_m = max(main["kerb"])
    if role == "cross":
        v = rng.uniform(3.0, vmax)
        t_c = rng.uniform(-3.0, duration + 3.0)  # time at the main road's centre line
        free = -direction * v * t_c
        traj = _place(
            rng, cross, across, h, ego, duration, profile_const(v), size[2], _NEAR, free, p_target
        )
        return category, size, "moving", traj
    # queue before the stop line on the cross road; may start during the scene
    if p_target >= 1.0:
        return None
    slot = int(rng.integers(0, 5))
    dist = kerb_m + 4.5 + size[1] / 2 + slot * (size[1] + rng.uniform(1.5, 3.0))
    along = -direction * dist
    x, y = road_point(cross, along, across)
    t_go = rng.uniform(0.0, duration + 6.0)
    prof = profile_ramp(t_go, 0.0, rng.uniform(5.0, 10.0), rng.uniform(1.0, 2.5))
    return category, size, "queue", {"path": straight_path(x, y, h), "s0": 0.0, "speed": prof}


def _pedestrian_candidate(rng, roads, ego, duration):
    road = roads[int(rng.integers(0, len(roads)))]
    side = int(rng.integers(0, 2))
    sign = -1.0 if side == 0 else 1.0
    across = sign * (road["kerb"][side] + rng.uniform(0.5, road["walk_w"] - 0.3))
    ego_x0 = float(traj_state(ego, 0.0)["x"])
    if road is roads[0]:
        along = rng.uniform(ego_x0 + 5, ego_x0 + 120)
    else:
        along = rng.uniform(-60, 60)
    category = "human.pedestrian.adult" if rng.random() < 0.85 else "human.pedestrian.child"
    size = _size(rng, category)
    x, y = road_point(road, along, across)
    if rng.random() < 0.3:
        v = 0.0
        h = road["h"] + rng.uniform(-math.pi, math.pi)
    else:
        v = rng.uniform(0.7, 1.7)
        h = road["h"] + (0.0 if rng.random() < 0.5 else math.pi)
    if rng.random() < 0.2 and len(roads) > 1:
        # crossing the main road at the crosswalk
        cross = roads[1]
        kerb = max(cross["kerb"])
        along_c = float(rng.choice([-1, 1])) * (kerb + 2.2)
        start_y = -max(roads[0]["walk"]) * float(rng.choice([-1, 1]))
        x = float(cross["o"][0] - along_c)
        y = float(start_y)
        h = math.pi / 2 if start_y < 0 else -math.pi / 2
        v = rng.uniform(0.9, 1.6)
        t_start = rng.uniform(-4, duration)
        prof = profile_ramp(t_start, 0.0, v, 5.0)
        traj = {"path": straight_path(x, y, h), "s0": 0.0, "speed": prof}
        return category, size, "walking", traj
    return (
        category,
        size,
        ("walking" if v > 0 else "standing"),
        {"path": straight_path(x, y, h), "s0": 0.0, "speed": profile_const(v)},
    )


def sample_scene(
    seed: int,
    index: int,
    n_keyframes: int,
    n_vehicles: int,
    weather: str,
    with_sweeps: bool,
    near_movers: int = NEAR_MOVERS,
) -> dict:
    """Sample one scene's description (JSON-able dict). Deterministic in (seed, index, sizes).
    ``near_movers``: vehicles driving near the ego that a scene with sweeps gets besides."""
    rng = np.random.default_rng([int(seed), int(index), 101])
    duration = (n_keyframes - 1) * 0.5
    layout, roads, cross_x = _sample_streets(rng)
    ego_kind, _ego_lane, ego = ego_plan(rng, duration, roads, cross_x)
    # the intersection relative to the ego: shift the cross road so the plan fits it
    vmax = 15.0 if layout["kind"] == "arterial" else 12.0
    placed = _start_placement(roads, ego, duration, cross_x, vmax, n_keyframes)
    agents = _place_vehicles(rng, placed, n_vehicles, n_keyframes)
    _add_pedestrians(rng, placed, agents)
    if with_sweeps and near_movers:  # its own stream: the rest is as without them
        _add_near_movers(np.random.default_rng([int(seed), int(index), 303]), placed, agents,
                         near_movers)

    ego_x = traj_state(ego, np.array([0.0, duration]))["x"]
    x_range = (float(min(ego_x) - 40.0), float(max(ego_x) + 330.0))
    statics = static_objects(rng, layout, x_range)

    look = _sample_look(rng, weather)
    description = _describe(rng, ego_kind, layout, agents, weather)
    return {
        "index": int(index),
        "duration": duration,
        "layout": layout,
        "ego_kind": ego_kind,
        "ego": ego,
        "agents": agents,
        "statics": statics,
        "look": look,
        "description": description,
        "with_sweeps": bool(with_sweeps),
        "calib": sample_calibration(seed, index),
        "global": {
            "yaw": float(rng.uniform(-math.pi, math.pi)),
            "xy": [float(rng.uniform(300.0, 2000.0)), float(rng.uniform(300.0, 2000.0))],
        },
    }


def _sample_streets(rng: np.random.Generator) -> tuple[dict, list[dict], float | None]:
    """The layout, its road frames and the cross road's x on the main road (m; 75 % of
    scenes have one, else None)."""
    want_cross = rng.random() < 0.75
    layout = sample_layout(rng, want_cross)
    roads = road_frames(layout)
    cross_x = None
    if want_cross:
        cross_x = round(float(rng.uniform(35.0, 110.0)), 2)
        layout["cross"]["o"] = [cross_x, 0.0]
        roads = road_frames(layout)
    return layout, roads, cross_x


@dataclass
class _Placement:
    """Placing a scene's agents: the street and the ego, the times checked for collisions,
    the keyframe cameras, and what is accepted so far."""

    roads: list[dict]  # main road first
    ego: dict  # the ego's trajectory
    duration: float  # s
    cross_x: float | None  # the cross road's x (m), None without one
    vmax: float  # top speed of traffic (m/s)
    times: np.ndarray  # (T,) s, collision checks
    kf_times: np.ndarray  # (K,) s, the keyframes
    cam_xy: np.ndarray  # (K, 2) m, camera positions at the keyframes
    cam_h: np.ndarray  # (K,) rad, camera headings at the keyframes
    fp: list = field(default_factory=list)  # accepted footprints over ``times`` (ego first)
    iv: list = field(default_factory=list)  # per accepted vehicle: view intervals (K, 3)
    good: list = field(default_factory=list)  # per accepted vehicle: well seen, (K,) bool


def _start_placement(
    roads: list[dict],
    ego: dict,
    duration: float,
    cross_x: float | None,
    vmax: float,
    n_keyframes: int,
) -> _Placement:
    """The placement state before any agent: the ego's footprint (from its rear-axle
    reference point) and the camera positions at the keyframes, for view-aware placement."""
    times = np.arange(-0.5, duration + 0.75, 0.25)
    ego_fp = footprints(ego, (1.9, 4.8, 1.6), times, 0.6)
    # ego reference point is the rear axle: shift the footprint forward by 1.4 m
    ego_fp = (ego_fp[0] + 1.4 * np.cos(ego_fp[2]), ego_fp[1] + 1.4 * np.sin(ego_fp[2]), *ego_fp[2:])
    # the keyframes' camera positions, for view-aware placement
    kf_times = np.arange(n_keyframes) * 0.5
    ego_kf = traj_state(ego, kf_times)
    cam_h = ego_kf["h"]
    cam_xy = np.stack([ego_kf["x"] + 1.7 * np.cos(cam_h), ego_kf["y"] + 1.7 * np.sin(cam_h)], 1)
    return _Placement(
        roads, ego, duration, cross_x, vmax, times, kf_times, cam_xy, cam_h, fp=[ego_fp]
    )


def _place_vehicles(
    rng: np.random.Generator, placed: _Placement, n_vehicles: int, n_keyframes: int
) -> list[dict]:
    """About ``n_vehicles`` vehicles (+-15 %) free of collisions, in three phases: placed in
    view (best of 8 candidates), then any placement, then filling up."""
    min_gain = max(2, n_keyframes // 2)
    agents: list[dict] = []
    n_target = max(1, int(round(n_vehicles * rng.uniform(0.85, 1.15))))
    attempts = 0
    n_vehicles_now = 0
    while n_vehicles_now < n_target and attempts < 80 * n_target:
        n_tries, p_target, fill_up = _placement_phase(attempts, n_vehicles_now, n_target)
        best = _best_candidate(rng, placed, n_tries, p_target)
        attempts += n_tries
        if best is None:
            continue
        if not _wanted(rng, best, min_gain, fill_up):
            continue
        _accept(placed, best)
        category, size, role, traj = best[2]
        agents.append(_agent_record(rng, "vehicle", category, size, role, traj))
        n_vehicles_now += 1
    return agents


def _placement_phase(attempts: int, n_now: int, n_target: int) -> tuple[int, float, bool]:
    """(candidates to try, their share aimed into view, fill up) after ``attempts`` tries
    with ``n_now`` of ``n_target`` vehicles placed. Phase 1, while under 85 % of the target
    and 40 tries a vehicle: the best of 8, all aimed into view; phase 2: one, 85 % aimed;
    phase 3, past 60 tries a vehicle: as phase 2, and a candidate that hides up to 6
    keyframes of the others is taken too (:func:`_wanted`)."""
    phase1 = n_now < 0.85 * n_target and attempts < 40 * n_target
    return (8, 1.0, False) if phase1 else (1, 0.85, attempts > 60 * n_target)


def _best_candidate(
    rng: np.random.Generator, placed: _Placement, n_tries: int, p_target: float
) -> tuple | None:
    """The best scored of ``n_tries`` vehicle candidates (see :func:`_score_candidate`), or
    None if none could be placed free of collisions."""
    best = None
    for _ in range(n_tries):
        cand = _agent_candidate(
            rng, placed.roads, placed.ego, placed.duration, placed.cross_x, placed.vmax, p_target
        )
        if cand is None or cand[3] is None:
            continue
        scored = _score_candidate(rng, placed, cand)
        if scored is None:
            continue
        if best is None or scored[0] > best[0]:
            best = scored
    return best


def _score_candidate(rng: np.random.Generator, placed: _Placement, cand: Candidate) -> tuple | None:
    """``(score, targeted, cand, footprint, view intervals (K, 3), well seen (K,) bool)`` of a
    candidate, None if it collides with an accepted agent. The score: keyframes where a
    targeted vehicle is well seen, less the keyframes it hides of accepted ones."""
    category, size, role, traj = cand
    margin_l = rng.uniform(2.5, 7.0) if role == "parked" else None
    fp = footprints(traj, size, placed.times, 0.5, margin_l)
    if rects_overlap(fp, stack_rects(placed.fp)).any():
        return None
    iv = _view_intervals(traj, size, placed.kf_times, placed.cam_xy, placed.cam_h)
    good = _in_band(iv)
    if placed.iv:
        acc = np.asarray(placed.iv)  # (N, T, 3)
        good &= ~_hides(acc, iv[None]).any(axis=0)
        damage = int((_hides(iv[None], acc) & np.asarray(placed.good)).sum())
    else:
        damage = 0
    targeted = "t_view" in traj and category in TARGET_CATEGORIES
    score = int(good.sum()) - damage if targeted else -damage
    return score, targeted, cand, fp, iv, good


def _wanted(rng: np.random.Generator, best: tuple, min_gain: int, phase3: bool) -> bool:
    """Whether to accept the best candidate: a targeted one that gains ``min_gain`` keyframes,
    one that hides little of the others, sometimes one that hides more."""
    score, targeted, _cand, _fp, _iv, good = best
    damage = int(good.sum()) - score if targeted else -score
    if targeted:
        wanted = score >= min_gain or (rng.random() < 0.1 and damage <= 3)
    else:
        wanted = damage <= 2 or (rng.random() < 0.1 and damage <= 5)
    return wanted or (phase3 and damage <= 6)


def _accept(placed: _Placement, best: tuple) -> None:
    """Record an accepted vehicle: its footprint and view, and what it hides of the others."""
    _score, targeted, _cand, fp, iv, good = best
    if placed.iv:
        hidden = _hides(iv[None], np.asarray(placed.iv))
        placed.good = [g & ~h for g, h in zip(placed.good, hidden, strict=True)]
    placed.iv.append(iv)
    placed.good.append(good if targeted else np.zeros_like(good))
    placed.fp.append(fp)


def _agent_record(
    rng: np.random.Generator, kind: str, category: str, size: list[float], role: str, traj: dict
) -> dict:
    """An agent of the scene description, with its texture seed."""
    return {
        "kind": kind,
        "category": category,
        "size": size,
        "role": role,
        "traj": traj,
        "tex": int(rng.integers(0, 2**31 - 1)),
    }


def _add_pedestrians(rng: np.random.Generator, placed: _Placement, agents: list[dict]) -> None:
    """Append 2-8 pedestrians free of collisions to ``agents`` (fewer if they do not fit)."""
    n_peds = int(rng.integers(2, 9))
    for _ in range(6 * n_peds):
        if sum(a["kind"] == "pedestrian" for a in agents) >= n_peds:
            break
        category, size, role, traj = _pedestrian_candidate(
            rng, placed.roads, placed.ego, placed.duration
        )
        fp = footprints(traj, size, placed.times, 0.3)
        if rects_overlap(fp, stack_rects(placed.fp)).any():
            continue
        placed.fp.append(fp)
        agents.append(_agent_record(rng, "pedestrian", category, size, role, traj))


def _add_near_movers(rng: np.random.Generator, placed: _Placement, agents: list[dict],
                     n: int) -> None:
    """Append up to ``n`` vehicles driving with or against the ego that are in view nearer
    than 30 m at two keyframes or more, free of collisions and hiding at most 6 keyframe
    views of the others (a near vehicle hides some far ones, as on a real road)."""
    main = placed.roads[0]
    ego_x = traj_state(placed.ego, np.array([0.0, placed.duration]))["x"]
    x_span = (float(min(ego_x)), float(max(ego_x)))
    added = 0
    for _ in range(60 * n):
        if added >= n:
            break
        role = "same" if rng.random() < 0.6 else "oncoming"
        category = weighted_choice(rng, DRIVING_WEIGHTS)
        size = _size(rng, category)
        traj = _lane_traj(rng, role, size, main, placed.ego, placed.duration, placed.vmax,
                          x_span, 1.0, near=_CLOSE)
        scored = None if traj is None else _score_candidate(
            rng, placed, (category, size, "moving", traj))
        if scored is None:
            continue
        score, targeted, _cand, _fp, iv, good = scored
        damage = int(good.sum()) - score if targeted else -score
        close = (iv[:, 0] < 30.0) & (iv[:, 1] > -0.55) & (iv[:, 2] < 0.55)
        if close.sum() < 2 or damage > 6:  # a near vehicle hides some far ones
            continue
        _accept(placed, scored)
        agents.append(_agent_record(rng, "vehicle", category, size, "moving", traj))
        added += 1


def _sample_look(rng: np.random.Generator, weather: str) -> dict:
    """The scene's look: sun direction (rad), camera gain, white balance and noise, JPEG
    quality, asphalt variant and texture seed."""
    sun_az = float(rng.uniform(-math.pi, math.pi))
    return {
        "weather": weather,
        "sun_azimuth": sun_az,
        "sun_elevation": float(rng.uniform(0.25, 1.1)),
        "gain": float(rng.uniform(0.85, 1.15)),
        "white_balance": [float(a) for a in rng.uniform(0.93, 1.07, 3)],
        "noise": float(rng.uniform(1.5, 3.0)),
        "jpeg_quality": int(rng.integers(85, 91)),
        "asphalt": int(rng.integers(0, 4)),
        "textures": int(rng.integers(0, 2**31 - 1)),
    }


#: nuScenes CAM_FRONT: camera->ego rotation (camera z forward, x right, y down).
CAM_R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def sample_calibration(seed: int, index: int) -> dict:
    """CAM_FRONT calibration like nuScenes: K (3x3, px), rotation (w, x, y, z; camera->ego),
    translation (m, ego frame), with small per-scene variations."""
    rng = np.random.default_rng([int(seed), int(index), 202])
    yaw, pitch, roll = rng.uniform(-0.005, 0.005, 3)
    cz, sz = math.cos(yaw), math.sin(yaw)
    cy, sy = math.cos(pitch), math.sin(pitch)
    cx, sx = math.cos(roll), math.sin(roll)
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    R = Rz @ Ry @ Rx @ CAM_R0
    q = Quaternion(matrix=R)
    if q.w < 0:
        q = -q
    f = 1266.417 * rng.uniform(0.996, 1.004)
    return {
        "K": [
            [float(f), 0.0, float(816.267 + rng.uniform(-3, 3))],
            [0.0, float(f), float(491.507 + rng.uniform(-3, 3))],
            [0.0, 0.0, 1.0],
        ],
        "rotation": [float(v) for v in q.elements],
        "translation": [
            float(1.70 + rng.uniform(-0.03, 0.03)),
            float(0.016 + rng.uniform(-0.01, 0.01)),
            float(1.51 + rng.uniform(-0.02, 0.02)),
        ],
    }


def _describe(rng, ego_kind: str, layout: dict, agents: list[dict], weather: str) -> str:
    """A nuScenes-style description: comma-separated items."""
    items: list[str] = []
    names = {
        "wait": "Wait at intersection",
        "turn_left": "turn left",
        "turn_right": "turn right",
        "brake": "stop at intersection",
        "go": "leave intersection",
        "stop_and_go": "congestion",
        "follow": "following traffic",
    }
    if ego_kind in names:
        items.append(names[ego_kind])
    if layout["kind"] == "arterial" or layout["main"]["lanes"] >= 3:
        items.append("big street")
    elif layout["main"]["lanes"] == 1:
        items.append("narrow street")
    if layout.get("cross") and ego_kind not in ("wait",):
        items.append("intersection")
    cats = [a["category"] for a in agents]
    if sum(a["role"] == "parked" for a in agents) >= 5:
        items.append("parked cars")
    if any(c.startswith("human") for c in cats):
        items.append("peds")
    for cat, word in (
        ("vehicle.bus.rigid", "bus"),
        ("vehicle.bus.bendy", "bendy bus"),
        ("vehicle.truck", "truck"),
        ("vehicle.construction", "construction vehicle"),
        ("vehicle.emergency.ambulance", "ambulance"),
        ("vehicle.emergency.police", "police car"),
    ):
        if cat in cats:
            items.append(word)
    if layout["kind"] == "suburban":
        items.append("trees")
    if ego_kind == "cruise" and rng.random() < 0.5:
        items.append("high speed" if layout["kind"] == "arterial" else "city driving")
    weather_item = {"night": "night", "rain": "rain", "after_rain": "after rain"}.get(weather)
    if weather_item:
        if rng.random() < 0.5:
            items.insert(0, weather_item.capitalize())
        else:
            items.append(weather_item)
        if weather == "rain" and rng.random() < 0.3:
            items.append("lightning")
    if not items:
        items.append("city driving")
    items[0] = items[0][0].upper() + items[0][1:]
    return ", ".join(items)
