"""The primitives of a scene description: trajectories, roads, collision checks, weather plan.

Holds analytic trajectories (paths, speed profiles), the road frames of a layout,
oriented-rectangle collision checks, the sampling building blocks shared by
:mod:`~flowmod.world.layout` and :mod:`~flowmod.world.agents`, the per-scene weather plan,
agents' global-frame states and :func:`json_ready`.

A scene is described by plain JSON-able data (dicts, lists, floats), sampled from a seeded
random generator by :func:`flowmod.world.agents.sample_scene`. Everything else (images,
nuScenes tables, ground-truth flow, true velocities) is derived from this description, so it is
stored beside the tables and GT is re-derived on demand.

Frames. Each scene has its own planar *scene frame* (metres, z up, ground at z = 0): the main
road runs along +x with its centre line at y = 0; an optional cross road runs along +y at
x = ``cross_x``. Traffic keeps right (lanes for +x travel at y < 0). The scene frame maps to the
nuScenes *global* frame by a yaw ``scene["global"]["yaw"]`` (rad) and a translation
``scene["global"]["xy"]`` (m).

Trajectories. A path is ``{"x", "y", "h", "segs": [[length_m, curvature_1/m], ...]}``: start
pose (m, m, rad) followed by straight (curvature 0) and circular segments, extended straight
before the start and after the end. A speed profile is ``{"t": [s...], "v": [m/s...]}``: speed
linear between knots, constant outside. An agent at time t (s, scene clock, 0 = first keyframe)
is at arc length ``s0 + integral_0^t v``. Position, heading and velocity are analytic.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from functools import lru_cache
from typing import Any

import numpy as np

NEAR_ZERO_SPEED = 0.2  # m/s, below this an agent counts as standing (for attributes)

# --------------------------------------------------------------------------------------------
# Trajectories
# --------------------------------------------------------------------------------------------


def path_pose(path: dict, s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pose at arc length ``s`` (m) along ``path``: x, y (m, scene frame), heading (rad).

    Shapes follow ``s``. Before the start and after the last segment the path is straight.
    """
    s = np.asarray(s, dtype=np.float64)
    x0, y0, h0 = float(path["x"]), float(path["y"]), float(path["h"])
    x = x0 + s * math.cos(h0)
    y = y0 + s * math.sin(h0)
    h = np.full_like(s, h0)
    start = 0.0
    xs, ys, hs = x0, y0, h0
    for length, k in path["segs"]:
        length, k = float(length), float(k)
        m = s >= start
        ds = np.clip(s - start, 0.0, length)
        if k == 0.0:
            px = xs + ds * math.cos(hs)
            py = ys + ds * math.sin(hs)
            ph = np.full_like(ds, hs)
        else:
            ph = hs + k * ds
            px = xs + (np.sin(ph) - math.sin(hs)) / k
            py = ys - (np.cos(ph) - math.cos(hs)) / k
        # beyond this segment: straight continuation (overwritten by later segments)
        rest = np.maximum(s - start - length, 0.0)
        x = np.where(m, px + rest * np.cos(ph), x)
        y = np.where(m, py + rest * np.sin(ph), y)
        h = np.where(m, ph, h)
        # advance the segment start pose
        he = hs + k * length
        if k == 0.0:
            xs, ys = xs + length * math.cos(hs), ys + length * math.sin(hs)
        else:
            xs, ys = xs + (math.sin(he) - math.sin(hs)) / k, ys - (math.cos(he) - math.cos(hs)) / k
        hs = he
        start += length
    return x, y, h


def speed_at(profile: dict, t: np.ndarray | float) -> np.ndarray:
    """Speed (m/s) at scene time ``t`` (s): linear between knots, constant outside."""
    return np.interp(np.asarray(t, dtype=np.float64), profile["t"], profile["v"])


@lru_cache(maxsize=4096)
def _knots(t_key: tuple, v_key: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A speed profile's knot times (s), speeds (m/s) and cumulative distances (m) at the
    knots, as float64 arrays; computed once per profile (read-only)."""
    tk = np.asarray(t_key, dtype=np.float64)
    vk = np.asarray(v_key, dtype=np.float64)
    seg = 0.5 * (vk[1:] + vk[:-1]) * np.diff(tk)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    for a in (tk, vk, cum):
        a.flags.writeable = False
    return tk, vk, cum


def _profile_knots(profile: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_knots` of a speed profile ``{"t": [s...], "v": [m/s...]}``."""
    return _knots(tuple(profile["t"]), tuple(profile["v"]))


@lru_cache(maxsize=4096)
def _knot_lists(t_key: tuple, v_key: tuple) -> tuple[list, list, list]:
    """:func:`_knots` as lists of Python floats (the scalar path of :func:`_antiderivative`)."""
    return tuple(a.tolist() for a in _knots(t_key, v_key))  # type: ignore[return-value]


def _antiderivative_scalar(profile: dict, t: float) -> float:
    """:func:`_antiderivative` at one time ``t`` (s) in plain floats: the same operations in
    the same order, so the same IEEE double (m)."""
    tk, vk, cum = _knot_lists(tuple(profile["t"]), tuple(profile["v"]))
    n = len(tk)
    if not t >= tk[0]:  # before the first knot (or NaN, which the array form maps to 0)
        return vk[0] * (t - tk[0]) if t < tk[0] else 0.0
    i = min(bisect_right(tk, t) - 1, n - 1)
    if i == n - 1:
        return cum[-1] + vk[-1] * (t - tk[-1])
    dt = t - tk[i]
    span = tk[i + 1] - tk[i]
    a = (vk[i + 1] - vk[i]) / span if span > 0 else 0.0
    return cum[i] + vk[i] * dt + 0.5 * a * dt * dt


def _antiderivative(profile: dict, t: np.ndarray) -> np.ndarray:
    """Integral of the speed from the first knot to ``t`` (m); negative before it."""
    tk, vk, cum = _profile_knots(profile)
    t = np.asarray(t, dtype=np.float64)
    i = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(tk) - 1)
    dt = t - tk[i]
    v_i = vk[i]
    nxt = np.minimum(i + 1, len(tk) - 1)
    span = tk[nxt] - tk[i]
    a = np.where(span > 0, (vk[nxt] - v_i) / np.where(span > 0, span, 1.0), 0.0)
    inside = (t >= tk[0]) & (i < len(tk) - 1)
    out = np.where(inside, cum[i] + v_i * dt + 0.5 * a * dt * dt, 0.0)
    out = np.where(t < tk[0], vk[0] * (t - tk[0]), out)
    out = np.where((t >= tk[0]) & (i == len(tk) - 1), cum[-1] + vk[-1] * (t - tk[-1]), out)
    return out


def arc_length(traj: dict, t: np.ndarray | float) -> np.ndarray:
    """Arc length (m) along the path at scene time ``t`` (s). One time (a number or a 0-d
    array) takes a plain-float path with the same arithmetic: a float64 scalar."""
    speed = traj["speed"]
    if np.ndim(t) == 0:
        t0 = _antiderivative_scalar(speed, float(t))
        return np.float64(float(traj["s0"]) + t0 - _antiderivative_scalar(speed, 0.0))
    t = np.asarray(t, dtype=np.float64)
    return (
        float(traj["s0"])
        + _antiderivative(speed, t)
        - _antiderivative(speed, np.zeros(()))
    )


def traj_state(traj: dict, t: np.ndarray | float) -> dict[str, np.ndarray]:
    """Scene-frame state at time ``t`` (s): x, y (m), heading (rad), speed (m/s), vx, vy (m/s)."""
    s = arc_length(traj, t)
    x, y, h = path_pose(traj["path"], s)
    v = speed_at(traj["speed"], t)
    return {"x": x, "y": y, "h": h, "v": v, "vx": v * np.cos(h), "vy": v * np.sin(h)}


def scene_to_global(scene: dict, x: np.ndarray, y: np.ndarray, h: np.ndarray | None = None):
    """Scene-frame (x, y[, heading]) -> global frame (m, m[, rad])."""
    g = scene["global"]
    c, s = math.cos(g["yaw"]), math.sin(g["yaw"])
    gx = g["xy"][0] + c * np.asarray(x) - s * np.asarray(y)
    gy = g["xy"][1] + s * np.asarray(x) + c * np.asarray(y)
    if h is None:
        return gx, gy
    return gx, gy, np.asarray(h) + g["yaw"]


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


# --------------------------------------------------------------------------------------------
# Roads
# --------------------------------------------------------------------------------------------


def road_frames(layout: dict) -> list[dict]:
    """The roads of a layout in a common form.

    Each road: origin ``o`` (x, y), heading ``h`` (rad), unit ``dir`` and ``left`` vectors,
    ``kerb`` = (right, left) half widths of the carriageway incl. parking (m), ``walk`` =
    (right, left) outer edges of the sidewalks (m), lanes per direction, lane width, median.
    """
    roads = []
    for r in [layout["main"]] + ([layout["cross"]] if layout.get("cross") else []):
        h = float(r["h"])
        d = (math.cos(h), math.sin(h))
        left = (-d[1], d[0])
        inner = r["median"] / 2 + r["lanes"] * r["lane_w"]
        kerb = tuple(inner + (r["park_w"] if p else 0.0) for p in r["park"])
        walk = tuple(k + r["walk_w"] for k in kerb)
        roads.append({**r, "dir": d, "left": left, "inner": inner, "kerb": kerb, "walk": walk})
    return roads


def road_coords(road: dict, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(along, across) coordinates (m) of scene points in a road's frame (across > 0: left)."""
    dx = x - road["o"][0]
    dy = y - road["o"][1]
    return dx * road["dir"][0] + dy * road["dir"][1], dx * road["left"][0] + dy * road["left"][1]


def lane_across(road: dict, direction: int, lane: int) -> float:
    """Across offset (m) of a lane centre: direction +1 travels along ``dir`` (right side)."""
    off = road["median"] / 2 + (lane + 0.5) * road["lane_w"]
    return -off if direction > 0 else off


def park_across(road: dict, side: int) -> float:
    """Across offset (m) of the parking-lane centre on side 0 (right) or 1 (left)."""
    off = road["inner"] + road["park_w"] / 2
    return -off if side == 0 else off


def road_point(road: dict, along: float, across: float) -> tuple[float, float]:
    """Scene (x, y) of a point given in a road's (along, across) coordinates."""
    return (
        road["o"][0] + along * road["dir"][0] + across * road["left"][0],
        road["o"][1] + along * road["dir"][1] + across * road["left"][1],
    )


# --------------------------------------------------------------------------------------------
# Collision checks (oriented rectangles over time)
# --------------------------------------------------------------------------------------------


def footprints(
    traj: dict,
    size: tuple[float, float, float],
    times: np.ndarray,
    margin: float,
    margin_l: float | None = None,
):
    """Oriented rectangles over time: (x, y, heading, half length, half width); margins in m."""
    st = traj_state(traj, times)
    hl = size[1] / 2 + (margin if margin_l is None else margin_l)
    hw = size[0] / 2 + margin * 0.6
    return st["x"], st["y"], st["h"], hl, hw


def rects_overlap(a, b) -> np.ndarray:
    """Separating-axis test of two oriented rectangles per time step: (T,) bool; ``b`` may
    hold N rectangles (:func:`stack_rects`): (N, T)."""
    ax, ay, ah, al, aw = a
    bx, by, bh, bl, bw = b
    dx, dy = bx - ax, by - ay
    overlap = np.ones(np.broadcast_shapes(np.shape(ax), np.shape(bx)), dtype=bool)
    ca, sa, cb, sb = np.cos(ah), np.sin(ah), np.cos(bh), np.sin(bh)  # once, not per axis
    for ux, uy in ((ca, sa), _cos_sin(ah + math.pi / 2), (cb, sb), _cos_sin(bh + math.pi / 2)):
        ra = al * np.abs(ca * ux + sa * uy) + aw * np.abs(-sa * ux + ca * uy)
        rb = bl * np.abs(cb * ux + sb * uy) + bw * np.abs(-sb * ux + cb * uy)
        overlap &= np.abs(dx * ux + dy * uy) <= ra + rb
    return overlap


def _cos_sin(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cos, sin) of the angles ``h`` (rad)."""
    return np.cos(h), np.sin(h)


def stack_rects(rects: list) -> tuple:
    """N rectangles over the same T times (:func:`footprints`) as one: x, y, heading (N, T),
    half length and half width (N, 1); :func:`rects_overlap` tests against all at once."""
    x, y, h = (np.array([r[i] for r in rects], dtype=np.float64) for i in range(3))
    hl, hw = (np.array([[r[i]] for r in rects], dtype=np.float64) for i in (3, 4))
    return x, y, h, hl, hw


# --------------------------------------------------------------------------------------------
# Sampling building blocks (shared by the layout and the agents)
# --------------------------------------------------------------------------------------------


def weighted_choice(rng: np.random.Generator, weights: dict[str, float]) -> str:
    """One key of ``weights`` drawn with probability proportional to its weight."""
    keys = list(weights)
    p = np.array([weights[k] for k in keys], dtype=np.float64)
    return keys[int(rng.choice(len(keys), p=p / p.sum()))]


def profile_const(v: float) -> dict:
    """A constant speed profile at ``v`` (m/s)."""
    return {"t": [0.0], "v": [float(v)]}


def profile_ramp(t0: float, v0: float, v1: float, accel: float) -> dict:
    """Constant v0 until t0, then constant acceleration magnitude ``accel`` to v1."""
    dur = abs(v1 - v0) / max(accel, 1e-6)
    return {"t": [float(t0), float(t0 + dur)], "v": [float(v0), float(v1)]}


def straight_path(x: float, y: float, h: float) -> dict:
    """A straight path from (x, y) (m, scene frame) with heading ``h`` (rad)."""
    return {"x": float(x), "y": float(y), "h": float(h), "segs": []}


# --------------------------------------------------------------------------------------------
# Weather plan, global-frame states and JSON
# --------------------------------------------------------------------------------------------


WEATHERS = ("clear", "overcast", "night", "rain", "after_rain")


def plan_weathers(n_scenes: int, n_sweep_scenes: int, seed: int) -> tuple[list[str], list[bool]]:
    """Weather per scene and which scenes get sweeps (only usable, non night/rain scenes).

    About 8 % night, 5 % rain, 5 % after rain (at least one night scene when n >= 2) and
    a few overcast. Deterministic in (n_scenes, seed).
    """
    rng = np.random.default_rng([int(seed), 977, int(n_scenes)])
    n_night = max(1, round(0.08 * n_scenes)) if n_scenes >= 2 else 0
    n_rain = round(0.05 * n_scenes)
    n_after = max(1, round(0.05 * n_scenes)) if n_scenes >= 3 else 0
    n_over = round(0.15 * n_scenes)
    weathers = (
        ["night"] * n_night + ["rain"] * n_rain + ["after_rain"] * n_after + ["overcast"] * n_over
    )
    weathers = weathers[: max(n_scenes - max(n_sweep_scenes, 1), 0)]
    weathers += ["clear"] * (n_scenes - len(weathers))
    order = rng.permutation(n_scenes)
    weathers = [weathers[i] for i in order]
    usable = [i for i, w in enumerate(weathers) if w not in ("night", "rain")]
    sweep = [False] * n_scenes
    for i in usable[::-1][:n_sweep_scenes]:
        sweep[i] = True
    return weathers, sweep


def agent_state_global(scene: dict, agent: dict, t: np.ndarray | float) -> dict[str, np.ndarray]:
    """Global-frame state of an agent: x, y, z (box centre, m), yaw (rad), vx, vy, vz (m/s)."""
    st = traj_state(agent["traj"], t)
    gx, gy, gh = scene_to_global(scene, st["x"], st["y"], st["h"])
    yaw = scene["global"]["yaw"]
    c, s = math.cos(yaw), math.sin(yaw)
    return {
        "x": gx,
        "y": gy,
        "z": np.full_like(np.asarray(gx, dtype=np.float64), agent["size"][2] / 2),
        "yaw": gh,
        "speed": st["v"],
        "vx": c * st["vx"] - s * st["vy"],
        "vy": s * st["vx"] + c * st["vy"],
        "vz": np.zeros_like(np.asarray(gx, dtype=np.float64)),
    }


def json_ready(obj: Any) -> Any:
    """Convert numpy scalars/arrays inside ``obj`` to plain Python for JSON."""
    if isinstance(obj, dict):
        return {k: json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
