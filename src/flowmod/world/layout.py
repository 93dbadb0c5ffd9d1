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


def ego_plan(rng: np.random.Generator, duration: float, roads: list[dict], cross_x: float | None):
    """Ego trajectory and behaviour name. Lanes of the main road, travelling +x."""
    main = roads[0]
    lane = int(rng.integers(0, main["lanes"]))
    y = lane_across(main, +1, lane)
    kerb_c = max(roads[1]["kerb"]) if len(roads) > 1 else 0.0
    stop_x = cross_x - kerb_c - 4.5 if cross_x is not None else None

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

    if kind in ("cruise", "follow"):
        v = rng.uniform(2.5, 11.0) if main["lanes"] < 3 else rng.uniform(4.0, 14.0)
        prof = profile_ramp(rng.uniform(0, duration), v, v + rng.uniform(-2.5, 2.5), 0.6)
        prof["v"][1] = max(prof["v"][1], 1.0)
        return kind, lane, {"path": straight_path(0.0, y, 0.0), "s0": 0.0, "speed": prof}
    if kind == "stop_and_go":
        n = 4
        ts = np.sort(rng.uniform(-0.5, duration + 0.5, n))
        vs = rng.uniform(0.0, 7.0, n)
        vs[::2] = rng.uniform(0.0, 1.5, len(vs[::2]))
        return (
            kind,
            lane,
            {
                "path": straight_path(0.0, y, 0.0),
                "s0": 0.0,
                "speed": {"t": [float(a) for a in ts], "v": [float(a) for a in vs]},
            },
        )
    if kind == "wait":
        t_go = rng.uniform(duration * 0.7, duration + 8.0)
        prof = profile_ramp(t_go, 0.0, rng.uniform(6, 10), rng.uniform(1.5, 2.5))
        x0 = stop_x - rng.uniform(0.0, 1.5)
        return kind, lane, {"path": straight_path(x0, y, 0.0), "s0": 0.0, "speed": prof}
    if kind == "go":
        t_go = rng.uniform(0.0, duration * 0.4)
        prof = profile_ramp(t_go, 0.0, rng.uniform(7, 12), rng.uniform(1.2, 2.5))
        x0 = stop_x - rng.uniform(0.0, 1.5)
        return kind, lane, {"path": straight_path(x0, y, 0.0), "s0": 0.0, "speed": prof}
    if kind == "brake":
        v0 = rng.uniform(5.0, 12.0)
        dec = rng.uniform(1.5, 3.0)
        t_b = rng.uniform(0.5, max(duration - v0 / dec, 1.0))
        prof = profile_ramp(t_b, v0, 0.0, dec)
        stop_dist = v0 * t_b + v0 * v0 / (2 * dec)
        x0 = stop_x - rng.uniform(0.0, 1.5) - stop_dist
        return kind, lane, {"path": straight_path(x0, y, 0.0), "s0": 0.0, "speed": prof}
    # turns: from the main road onto the cross road
    cross = roads[1]
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
    return kind, lane, {"path": path, "s0": 0.0, "speed": prof}


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
    """
    roads = road_frames(layout)
    objs: list[dict] = []
    urban = layout["kind"] == "urban"

    def inside_other_road(ri: int, xs: np.ndarray, ys: np.ndarray, pad: float) -> bool:
        for rj, other in enumerate(roads):
            if rj == ri:
                continue
            _, acr = road_coords(other, xs, ys)
            half = max(other["walk"]) + pad
            if acr.max() > -half and acr.min() < half:  # footprint overlaps the corridor
                return True
        return False

    def corners(cx, cy, yaw, length, width):
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

    for ri, road in enumerate(roads):
        if ri == 0:
            a_lo, a_hi = x_range
        else:
            a_lo, a_hi = -250.0, 250.0
        for side in (0, 1):
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
                xs, ys = corners(cx, cy, road["h"], length, depth)
                if not inside_other_road(ri, xs, ys, 1.0):
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
            # trees / poles / hedges on the sidewalk and in front yards
            a = a_lo + rng.uniform(0, 8)
            spacing = rng.uniform(8, 16) if rng.random() < 0.75 else rng.uniform(20, 40)
            while a < a_hi:
                across = sign * (
                    road["kerb"][side] + rng.uniform(0.8, max(road["walk_w"] - 0.6, 0.9))
                )
                cx, cy = road_point(road, a, across)
                if not inside_other_road(ri, np.array([cx]), np.array([cy]), 2.0):
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
            # hedges / walls in front of set-back buildings
            if road["setback"][side] > 2.0 and rng.random() < 0.6:
                a = a_lo
                while a < a_hi:
                    length = rng.uniform(6, 25)
                    across = sign * (road["walk"][side] + 0.5)
                    cx, cy = road_point(road, a + length / 2, across)
                    xs, ys = corners(cx, cy, road["h"], length, 0.6)
                    if not inside_other_road(ri, xs, ys, 1.0):
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
    # a distant backdrop across the far end of the main road
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
