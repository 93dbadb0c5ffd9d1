"""Sampling the stage of a scene: the road layout, the static objects and the ego's plan.

Holds :func:`sample_layout` (main road and optional cross road), :func:`static_objects`
(buildings, trees, poles, hedges and walls along the roads, and a distant backdrop) and
:func:`ego_plan` (the ego's behaviour and trajectory on the main road), all in the scene frame
of :mod:`~flowmod.world.scene`; :func:`flowmod.world.agents.sample_scene` calls them.
"""

from __future__ import annotations

import math

import numpy as np

from flowmod.world.scene import (
    arc_length,
    lane_across,
    profile_ramp,
    road_coords,
    road_frames,
    road_point,
    straight_path,
    weighted_choice,
)

# --------------------------------------------------------------------------------------------
# Sampling the ego plan, the layout and the static objects
# --------------------------------------------------------------------------------------------


def ego_plan(
    rng: np.random.Generator, duration: float, roads: list[dict], cross_x: float | None
) -> tuple[str, int, dict]:
    """The ego's behaviour name, lane and trajectory: lanes of the main road, travelling +x.

    ``duration``: of the scene (s); ``cross_x``: the cross road's x (m), None without one.
    """
    main = roads[0]
    kind, lane, y = _ego_behaviour(rng, main, cross_x)
    kerb_c = max(roads[1]["kerb"]) if len(roads) > 1 else 0.0
    stop_x = cross_x - kerb_c - 4.5 if cross_x is not None else None
    if kind in ("turn_left", "turn_right"):
        return kind, lane, _turn_plan(rng, kind, duration, roads[1], cross_x, y)
    return kind, lane, _lane_plan(rng, kind, duration, main, y, stop_x)


def _ego_behaviour(
    rng: np.random.Generator, main: dict, cross_x: float | None
) -> tuple[str, int, float]:
    """The ego's behaviour name, its lane of the main road and that lane's across offset (m);
    the behaviours at the cross road only when there is one."""
    lane = int(rng.integers(0, main["lanes"]))
    y = lane_across(main, +1, lane)

    options = {"cruise": 0.3, "stop_and_go": 0.1, "follow": 0.1}
    if cross_x is not None:
        options.update(
            {"wait": 0.14, "brake": 0.12, "go": 0.1, "turn_left": 0.07, "turn_right": 0.07}
        )
    kind = weighted_choice(rng, options)
    if kind == "turn_left":
        lane = 0
        y = lane_across(main, +1, lane)
    if kind == "turn_right":
        lane = main["lanes"] - 1
        y = lane_across(main, +1, lane)
    return kind, lane, y


def _lane_plan(
    rng: np.random.Generator,
    kind: str,
    duration: float,
    main: dict,
    y: float,
    stop_x: float | None,
) -> dict:
    """The ego's trajectory along its lane (across offset ``y``, m) for every behaviour but
    the turns; ``stop_x``: the stop line before the cross road (m), None without one."""
    if kind in ("cruise", "follow"):
        v = rng.uniform(2.5, 11.0) if main["lanes"] < 3 else rng.uniform(4.0, 14.0)
        prof = profile_ramp(rng.uniform(0, duration), v, v + rng.uniform(-2.5, 2.5), 0.6)
        prof["v"][1] = max(prof["v"][1], 1.0)
        return {"path": straight_path(0.0, y, 0.0), "s0": 0.0, "speed": prof}
    if kind == "stop_and_go":
        n = 4
        ts = np.sort(rng.uniform(-0.5, duration + 0.5, n))
        vs = rng.uniform(0.0, 7.0, n)
        vs[::2] = rng.uniform(0.0, 1.5, len(vs[::2]))
        return {
            "path": straight_path(0.0, y, 0.0),
            "s0": 0.0,
            "speed": {"t": [float(a) for a in ts], "v": [float(a) for a in vs]},
        }
    if kind == "wait":
        t_go = rng.uniform(duration * 0.7, duration + 8.0)
        prof = profile_ramp(t_go, 0.0, rng.uniform(6, 10), rng.uniform(1.5, 2.5))
        x0 = stop_x - rng.uniform(0.0, 1.5)
        return {"path": straight_path(x0, y, 0.0), "s0": 0.0, "speed": prof}
    if kind == "go":
        t_go = rng.uniform(0.0, duration * 0.4)
        prof = profile_ramp(t_go, 0.0, rng.uniform(7, 12), rng.uniform(1.2, 2.5))
        x0 = stop_x - rng.uniform(0.0, 1.5)
        return {"path": straight_path(x0, y, 0.0), "s0": 0.0, "speed": prof}
    # brake: to a stop at the stop line
    v0 = rng.uniform(5.0, 12.0)
    dec = rng.uniform(1.5, 3.0)
    t_b = rng.uniform(0.5, max(duration - v0 / dec, 1.0))
    prof = profile_ramp(t_b, v0, 0.0, dec)
    stop_dist = v0 * t_b + v0 * v0 / (2 * dec)
    x0 = stop_x - rng.uniform(0.0, 1.5) - stop_dist
    return {"path": straight_path(x0, y, 0.0), "s0": 0.0, "speed": prof}


def _turn_plan(
    rng: np.random.Generator, kind: str, duration: float, cross: dict, cross_x: float, y: float
) -> dict:
    """The ego's trajectory turning (``kind`` turn_left / turn_right) from its lane of the
    main road (across offset ``y``, m) onto the ``cross`` road at x = ``cross_x`` (m)."""
    if kind == "turn_left":
        x_t = cross_x + cross["median"] / 2 + 0.5 * cross["lane_w"]
        radius = max(x_t - (cross_x - max(cross["kerb"])), 6.0)
        k = 1.0 / radius
    else:
        x_t = cross_x - cross["median"] / 2 - (cross["lanes"] - 0.5) * cross["lane_w"]
        radius = float(np.clip(x_t - (cross_x - max(cross["kerb"])) + 2.0, 5.5, 12.0))
        k = -1.0 / radius
    x_s = x_t - radius
    v_a = rng.uniform(6.0, 10.0)
    v_t = min(rng.uniform(3.5, 5.5), math.sqrt(2.5 * radius))
    t_turn = rng.uniform(1.0, max(duration - 4.0, 1.5))
    dec = rng.uniform(1.2, 2.5)
    t_dec = max(t_turn - (v_a - v_t) / dec, -5.0)
    arc_len = radius * math.pi / 2
    t_exit = t_turn + arc_len / v_t
    v_e = rng.uniform(6.0, 10.0)
    prof = {
        "t": [t_dec, t_turn, t_exit, t_exit + (v_e - v_t) / 1.8],
        "v": [v_a, v_t, v_t, v_e],
    }
    prof = {"t": [float(a) for a in prof["t"]], "v": [float(a) for a in prof["v"]]}
    # the arc starts at x_s when t = t_turn: position the start so that s(t_turn) = x_s - x0
    tmp = {"path": straight_path(0.0, y, 0.0), "s0": 0.0, "speed": prof}
    s_turn = float(arc_length(tmp, t_turn))
    x0 = x_s - s_turn
    path = {"x": x0, "y": y, "h": 0.0, "segs": [[x_s - x0, 0.0], [arc_len, k]]}
    return {"path": path, "s0": 0.0, "speed": prof}


def sample_layout(rng: np.random.Generator, with_cross: bool) -> dict:
    kind = weighted_choice(rng, {"urban": 0.5, "suburban": 0.3, "arterial": 0.2})
    lanes = int(rng.choice([1, 2, 2, 2, 3])) if kind != "arterial" else int(rng.choice([2, 3]))
    main = {
        "o": [0.0, 0.0],
        "h": 0.0,
        "lanes": lanes,
        "lane_w": round(float(rng.uniform(3.1, 3.7)), 2),
        "median": round(float(rng.choice([0.3, 0.3, 1.0, 3.0])), 2),
        "park": [bool(rng.random() < 0.9), bool(rng.random() < 0.8)],
        "park_w": round(float(rng.uniform(2.2, 2.6)), 2),
        "walk_w": round(float(rng.uniform(2.0, 5.0)), 2),
        "setback": [round(float(rng.uniform(0.0, 8.0)), 2), round(float(rng.uniform(0.0, 8.0)), 2)],
        "center": str(rng.choice(["double_yellow", "dashed_white"])),
    }
    layout = {"kind": kind, "main": main, "cross": None}
    if with_cross:
        layout["cross"] = {
            "o": [0.0, 0.0],  # x set by the caller
            "h": math.pi / 2,
            "lanes": int(rng.choice([1, 1, 2])),
            "lane_w": round(float(rng.uniform(3.0, 3.6)), 2),
            "median": 0.3,
            "park": [bool(rng.random() < 0.6), bool(rng.random() < 0.6)],
            "park_w": round(float(rng.uniform(2.2, 2.6)), 2),
            "walk_w": round(float(rng.uniform(2.0, 4.0)), 2),
            "setback": [
                round(float(rng.uniform(0.0, 6.0)), 2),
                round(float(rng.uniform(0.0, 6.0)), 2),
            ],
            "center": str(rng.choice(["double_yellow", "dashed_white"])),
        }
    return layout


def static_objects(rng: np.random.Generator, layout: dict, x_range: tuple[float, float]) -> list:
    """Buildings, trees, poles and hedges along the roads (boxes in the scene frame).

    Each object: ``{"kind", "c": [x, y, z_centre], "yaw", "size": [w, l, h], "tex": seed}``,
    a box in the nuScenes convention (local x along ``l``, y along ``w``, z up), yaw in rad.
    ``x_range``: the span of the main road to fill (m).
    """
    roads = road_frames(layout)
    objs: list[dict] = []
    urban = layout["kind"] == "urban"
    for ri in range(len(roads)):
        if ri == 0:
            a_lo, a_hi = x_range
        else:
            a_lo, a_hi = -250.0, 250.0
        for side in (0, 1):
            objs += _buildings(rng, roads, ri, side, a_lo, a_hi, urban)
            objs += _sidewalk_objects(rng, roads, ri, side, a_lo, a_hi)
            objs += _yard_hedges(rng, roads, ri, side, a_lo, a_hi)
    objs += _backdrop(rng, x_range)
    return objs


def _inside_other_road(
    roads: list[dict], ri: int, xs: np.ndarray, ys: np.ndarray, pad: float
) -> bool:
    """True if the points (xs, ys) (m) overlap the corridor (sidewalks + ``pad`` m) of a road
    other than road ``ri``."""
    for rj, other in enumerate(roads):
        if rj == ri:
            continue
        _, acr = road_coords(other, xs, ys)
        half = max(other["walk"]) + pad
        if acr.max() > -half and acr.min() < half:  # footprint overlaps the corridor
            return True
    return False


def _rect_corners(
    cx: float, cy: float, yaw: float, length: float, width: float
) -> tuple[np.ndarray, np.ndarray]:
    """x and y (m), each (4,), of the corners of a rectangle centred at (cx, cy), its length
    along ``yaw`` (rad)."""
    c, s = math.cos(yaw), math.sin(yaw)
    pts = np.array(
        [
            [length / 2, width / 2],
            [length / 2, -width / 2],
            [-length / 2, width / 2],
            [-length / 2, -width / 2],
        ]
    )
    return cx + c * pts[:, 0] - s * pts[:, 1], cy + s * pts[:, 0] + c * pts[:, 1]


def _buildings(
    rng: np.random.Generator,
    roads: list[dict],
    ri: int,
    side: int,
    a_lo: float,
    a_hi: float,
    urban: bool,
) -> list[dict]:
    """A row of buildings behind the sidewalk (and set-back) of one side (0 right, 1 left)
    of road ``ri``, from along = ``a_lo`` to ``a_hi`` (m): dense or sparse."""
    road = roads[ri]
    objs: list[dict] = []
    sign = -1.0 if side == 0 else 1.0
    line = road["walk"][side] + road["setback"][side]
    dense = urban or rng.random() < 0.4
    a = a_lo + rng.uniform(0, 10)
    while a < a_hi:
        if dense:
            length = rng.uniform(10, 35)
            depth = rng.uniform(10, 25)
            height = rng.uniform(8, 40) if urban else rng.uniform(5, 12)
            gap = rng.uniform(0, 6) if urban else rng.uniform(3, 20)
        else:
            length = rng.uniform(8, 18)
            depth = rng.uniform(8, 14)
            height = rng.uniform(4, 9)
            gap = rng.uniform(10, 35)
        along = a + length / 2
        across = sign * (line + depth / 2)
        cx, cy = road_point(road, along, across)
        xs, ys = _rect_corners(cx, cy, road["h"], length, depth)
        if not _inside_other_road(roads, ri, xs, ys, 1.0):
            objs.append(
                {
                    "kind": "building",
                    "c": [float(cx), float(cy), float(height / 2)],
                    "yaw": float(road["h"]),
                    "size": [float(depth), float(length), float(height)],
                    "tex": int(rng.integers(0, 2**31 - 1)),
                }
            )
        a += length + gap
    return objs


def _sidewalk_objects(
    rng: np.random.Generator, roads: list[dict], ri: int, side: int, a_lo: float, a_hi: float
) -> list[dict]:
    """Trees and poles on the sidewalk of one side (0 right, 1 left) of road ``ri``, from
    along = ``a_lo`` to ``a_hi`` (m), evenly spaced with jitter."""
    road = roads[ri]
    objs: list[dict] = []
    sign = -1.0 if side == 0 else 1.0
    a = a_lo + rng.uniform(0, 8)
    spacing = rng.uniform(8, 16) if rng.random() < 0.75 else rng.uniform(20, 40)
    while a < a_hi:
        across = sign * (road["kerb"][side] + rng.uniform(0.8, max(road["walk_w"] - 0.6, 0.9)))
        cx, cy = road_point(road, a, across)
        if not _inside_other_road(roads, ri, np.array([cx]), np.array([cy]), 2.0):
            if rng.random() < 0.7:
                h = rng.uniform(4, 11)
                objs.append(
                    {
                        "kind": "tree",
                        "c": [float(cx), float(cy), float(h / 2)],
                        "yaw": float(rng.uniform(0, math.pi)),
                        "size": [float(h * rng.uniform(0.4, 0.7))] * 2 + [float(h)],
                        "tex": int(rng.integers(0, 2**31 - 1)),
                    }
                )
            else:
                h = rng.uniform(5, 9)
                objs.append(
                    {
                        "kind": "pole",
                        "c": [float(cx), float(cy), float(h / 2)],
                        "yaw": float(road["h"]),
                        "size": [0.22, 0.22, float(h)],
                        "tex": int(rng.integers(0, 2**31 - 1)),
                    }
                )
        a += spacing * rng.uniform(0.7, 1.3)
    return objs


def _yard_hedges(
    rng: np.random.Generator, roads: list[dict], ri: int, side: int, a_lo: float, a_hi: float
) -> list[dict]:
    """Hedges and low walls at the back of the sidewalk of one side (0 right, 1 left) of road
    ``ri``, in front of set-back buildings (sometimes), from along = ``a_lo`` to ``a_hi`` (m)."""
    road = roads[ri]
    objs: list[dict] = []
    sign = -1.0 if side == 0 else 1.0
    if road["setback"][side] > 2.0 and rng.random() < 0.6:
        a = a_lo
        while a < a_hi:
            length = rng.uniform(6, 25)
            across = sign * (road["walk"][side] + 0.5)
            cx, cy = road_point(road, a + length / 2, across)
            xs, ys = _rect_corners(cx, cy, road["h"], length, 0.6)
            if not _inside_other_road(roads, ri, xs, ys, 1.0):
                h = rng.uniform(0.8, 1.8)
                objs.append(
                    {
                        "kind": "hedge" if rng.random() < 0.7 else "wall",
                        "c": [float(cx), float(cy), float(h / 2)],
                        "yaw": float(road["h"]),
                        "size": [0.6, float(length), float(h)],
                        "tex": int(rng.integers(0, 2**31 - 1)),
                    }
                )
            a += length + rng.uniform(2, 12)
    return objs


def _backdrop(rng: np.random.Generator, x_range: tuple[float, float]) -> list[dict]:
    """A distant backdrop (skyline, tree line) across the far end of the main road, 350-600 m
    beyond ``x_range[1]`` (m)."""
    objs: list[dict] = []
    for _ in range(int(rng.integers(3, 7))):
        dist = rng.uniform(350, 600)
        off = rng.uniform(-250, 250)
        w_ = rng.uniform(40, 160)
        h = rng.uniform(15, 60)
        objs.append(
            {
                "kind": "backdrop",
                "c": [float(x_range[1] + dist), float(off), float(h / 2)],
                "yaw": 0.0,
                "size": [float(w_), float(rng.uniform(20, 40)), float(h)],
                "tex": int(rng.integers(0, 2**31 - 1)),
            }
        )
    return objs
