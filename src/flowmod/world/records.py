"""The nuScenes records of a generated world: the tables' constants, tokens and timestamps,
and one scene's job (render its frames, write its JPEGs, return its table rows), run in
worker processes by :func:`flowmod.world.dataset.generate_world`.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from flowmod.artefacts import atomic_path
from flowmod.world import agents as wa
from flowmod.world import geometry as wg
from flowmod.world import render as wr
from flowmod.world import scene as ws
from flowmod.world.shading import finish
from flowmod.world.truth import WorldError

CHANNEL = "CAM_FRONT"
KEYFRAME_US = 500_000
BASE_US = 1_533_000_000_000_000  # 2018-07-31, like nuScenes' era
ANNOTATION_RANGE = 100.0  # m, agents annotated within this distance of the ego
TABLES = (
    "attribute",
    "calibrated_sensor",
    "category",
    "ego_pose",
    "instance",
    "log",
    "map",
    "sample",
    "sample_annotation",
    "sample_data",
    "scene",
    "sensor",
    "visibility",
)

#: The official nuScenes categories (names; descriptions written for this world).
CATEGORIES = [
    ("human.pedestrian.adult", "Adult pedestrian."),
    ("human.pedestrian.child", "Child pedestrian."),
    ("human.pedestrian.wheelchair", "Person in a wheelchair."),
    ("human.pedestrian.stroller", "Person pushing a stroller."),
    ("human.pedestrian.personal_mobility", "Person on a scooter or similar."),
    ("human.pedestrian.police_officer", "Police officer."),
    ("human.pedestrian.construction_worker", "Construction worker."),
    ("animal", "Animal."),
    ("vehicle.car", "Passenger car, van, SUV."),
    ("vehicle.motorcycle", "Motorcycle or moped."),
    ("vehicle.bicycle", "Bicycle."),
    ("vehicle.bus.bendy", "Articulated bus."),
    ("vehicle.bus.rigid", "Rigid bus."),
    ("vehicle.truck", "Truck, lorry, pickup."),
    ("vehicle.construction", "Construction vehicle."),
    ("vehicle.emergency.ambulance", "Ambulance."),
    ("vehicle.emergency.police", "Police car."),
    ("vehicle.trailer", "Trailer."),
    ("movable_object.barrier", "Barrier."),
    ("movable_object.trafficcone", "Traffic cone."),
    ("movable_object.pushable_pullable", "Cart, bin."),
    ("movable_object.debris", "Debris."),
    ("static_object.bicycle_rack", "Bicycle rack."),
]

ATTRIBUTES = [
    ("vehicle.moving", "Vehicle is moving."),
    ("vehicle.stopped", "Vehicle with driver, temporarily stationary."),
    ("vehicle.parked", "Vehicle parked, no driver."),
    ("cycle.with_rider", "Cycle with a rider."),
    ("cycle.without_rider", "Cycle without a rider."),
    ("pedestrian.sitting_lying_down", "Pedestrian sitting or lying."),
    ("pedestrian.standing", "Pedestrian standing."),
    ("pedestrian.moving", "Pedestrian moving."),
]

VISIBILITY = [
    ("1", "v0-40", "visibility of whole object is between 0 and 40%"),
    ("2", "v40-60", "visibility of whole object is between 40 and 60%"),
    ("3", "v60-80", "visibility of whole object is between 60 and 80%"),
    ("4", "v80-100", "visibility of whole object is between 80 and 100%"),
]


# --------------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------------


def token(seed: int, *parts: Any) -> str:
    """A deterministic 32-hex nuScenes-style token."""
    key = "/".join(str(p) for p in ("flowmod-synth", seed, *parts))
    return hashlib.md5(key.encode()).hexdigest()


def yaw_quaternion(yaw: float) -> list[float]:
    """Rotation about z by ``yaw`` (rad) as [w, x, y, z]."""
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def visibility_token(fraction: float) -> str:
    """nuScenes visibility bin of a visible fraction in [0, 1]: '1'..'4'."""
    if fraction >= 0.8:
        return "4"
    if fraction >= 0.6:
        return "3"
    if fraction >= 0.4:
        return "2"
    return "1"


def write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_json(path: Path, obj: Any, indent: int | None = 1) -> None:
    """Write ``obj`` as JSON (and a newline) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=indent) + "\n")


def frame_times(
    seed: int, index: int, n_keyframes: int, with_sweeps: bool, t0_us: int
) -> list[dict]:
    """Camera frame timestamps of a scene: [{"ts": us, "key": bool, "k": keyframe index}].

    Keyframes every 0.5 s (+-2.5 ms jitter, the first exactly at ``t0_us``); with sweeps, the
    ~12 Hz frames in between: 5 per gap (+-4 ms jitter), one dropped in ~12 % of gaps. A
    sweep's ``k`` is the index of the NEXT keyframe (the sample it belongs to in nuScenes).
    """
    rng = np.random.default_rng([int(seed), int(index), 303])
    kts = [t0_us]
    for _k in range(1, n_keyframes):
        kts.append(t0_us + _k * KEYFRAME_US + int(rng.integers(-2500, 2501)))
    frames = []
    for k, ts in enumerate(kts):
        if with_sweeps and k > 0:
            prev = kts[k - 1]
            gap = ts - prev
            js = [1, 2, 3, 4, 5]
            if rng.random() < 0.12:
                js.pop(int(rng.integers(0, 5)))
            for j in js:
                t = prev + int(round(gap * j / 6)) + int(rng.integers(-4000, 4001))
                frames.append({"ts": int(t), "key": False, "k": k})
        frames.append({"ts": int(ts), "key": True, "k": k})
    return frames


def _exposures(seed: int, index: int, times: np.ndarray) -> np.ndarray:
    """Per-frame exposure gains (slow drift, auto-exposure steps, small jitter)."""
    rng = np.random.default_rng([int(seed), int(index), 404])
    phase = rng.uniform(0, 2 * math.pi)
    e = 1.0 + 0.05 * np.sin(2 * math.pi * times / rng.uniform(4, 9) + phase)
    for _ in range(int(rng.integers(0, 3))):
        t_step = rng.uniform(times.min() if times.size else 0, times.max() + 1 if times.size else 1)
        e = e + rng.uniform(-0.08, 0.08) * (times >= t_step)
    return e * (1.0 + rng.normal(0, 0.008, times.shape))


# --------------------------------------------------------------------------------------------
# One scene (runs in a worker process)
# --------------------------------------------------------------------------------------------


def _scene_description(
    seed: int, index: int, n_keyframes: int, vehicles: int, weather: str, with_sweeps: bool,
    near_movers: int = wa.NEAR_MOVERS,
) -> dict:
    scene = wa.sample_scene(seed, index, n_keyframes, vehicles, weather, with_sweeps,
                            near_movers)
    scene["name"] = f"synth-{index:04d}"
    scene["token"] = token(seed, "scene", index)
    scene["t0_us"] = BASE_US + index * 3_600_000_000
    frames = frame_times(seed, index, n_keyframes, with_sweeps, scene["t0_us"])
    for j, f in enumerate(frames):
        f["sd_token"] = token(seed, "sample_data", index, j)
    scene["frames"] = frames
    for i, a in enumerate(scene["agents"]):
        a["instance_token"] = token(seed, "instance", index, i)
    return ws.json_ready(scene)


def _attribute(agent: dict, speed: float) -> str:
    cat = agent["category"]
    moving = speed > ws.NEAR_ZERO_SPEED
    if cat.startswith("human"):
        return "pedestrian.moving" if moving else "pedestrian.standing"
    if cat in ("vehicle.bicycle", "vehicle.motorcycle"):
        return (
            "cycle.with_rider" if (moving or agent["role"] != "parked") else "cycle.without_rider"
        )
    if moving:
        return "vehicle.moving"
    return "vehicle.parked" if agent["role"] == "parked" else "vehicle.stopped"


def scene_job(*args: Any) -> dict:
    """Worker entry: :func:`_render_scene` with OpenCV single-threaded (restored after)."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return _render_scene(*args)
    finally:
        cv2.setNumThreads(threads)


def _render_scene(
    dataroot: str,
    seed: int,
    index: int,
    n_keyframes: int,
    vehicles: int,
    weather: str,
    with_sweeps: bool,
    near_movers: int = wa.NEAR_MOVERS,
) -> dict:
    """Render one scene's frames to ``dataroot`` and return its table rows and description."""
    scene = _scene_description(seed, index, n_keyframes, vehicles, weather, with_sweeps,
                               near_movers)
    geo = wg.SceneGeometry(scene)
    root = Path(dataroot)
    t0 = scene["t0_us"]
    cs_token = token(seed, "calibrated_sensor", index)
    sample_tokens = [token(seed, "sample", index, k) for k in range(n_keyframes)]
    frames = scene["frames"]
    times = np.array([(f["ts"] - t0) / 1e6 for f in frames])
    expo = _exposures(seed, index, times)
    rows: dict[str, list] = {
        "sample": [],
        "sample_data": [],
        "ego_pose": [],
        "sample_annotation": [],
        "instance": [],
    }
    ann_by_agent: dict[int, list[dict]] = {}
    statics_occ = _static_occluders(scene)
    for j, f in enumerate(frames):
        t = float(times[j])
        fr = wr.render(geo, t, textured=True)
        filename = _write_frame(root, scene, fr, j, (seed, index, j, 505), float(expo[j]))
        ego = ws.traj_state(scene["ego"], t)
        rows["ego_pose"].append(_ego_pose_row(scene, f, ego))
        rows["sample_data"].append(_sample_data_row(frames, j, filename, sample_tokens, cs_token))
        if not f["key"]:
            continue
        rows["sample"].append(_sample_row(scene, f, sample_tokens))
        posed = _posed_agents(scene, geo, t)
        for i, ann in _keyframe_annotations(
            seed, index, scene, fr, t, f["k"], sample_tokens, ego, posed, statics_occ
        ):
            ann_by_agent.setdefault(i, []).append(ann)
    rows["instance"] = _link_annotations(seed, scene, ann_by_agent)
    rows["sample_annotation"] = _in_sample_order(ann_by_agent, sample_tokens)
    rows["calibrated_sensor"] = [_calibrated_sensor_row(seed, scene, cs_token)]
    rows["scene"] = [_scene_row(seed, index, scene, sample_tokens)]
    return {"rows": rows, "scene": scene}


def _static_occluders(scene: dict) -> list[tuple]:
    """The static boxes that can hide an agent outside the image: (centre (3,) m, yaw rad,
    (w, l, h) m) of the buildings, hedges and walls."""
    return [
        (np.array(o["c"]), o["yaw"], tuple(o["size"]))
        for o in scene["statics"]
        if o["kind"] in ("building", "hedge", "wall")
    ]


def _write_frame(
    root: Path, scene: dict, fr: wg.Frame, j: int, frame_seed: tuple[int, ...], exposure: float
) -> str:
    """Finish frame ``j`` of the scene (camera model, ``exposure`` gain), write it as a JPEG
    under ``root`` and return its filename relative to ``root``."""
    look = scene["look"]
    f = scene["frames"][j]
    img = finish(fr, look, frame_seed, exposure)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(look["jpeg_quality"])])
    if not ok:
        raise WorldError(f"JPEG encoding failed for scene {scene['name']} frame {j}")
    folder = "samples" if f["key"] else "sweeps"
    filename = f"{folder}/{CHANNEL}/{scene['name']}__{CHANNEL}__{f['ts']}.jpg"
    write_bytes(root / filename, buf.tobytes())
    return filename


def _ego_pose_row(scene: dict, f: dict, ego: dict) -> dict:
    """The ego_pose record of frame ``f``: the ego's scene-frame state ``ego`` in the global
    frame (m, quaternion)."""
    gx, gy, gh = ws.scene_to_global(scene, ego["x"], ego["y"], ego["h"])
    return {
        "token": f["sd_token"],
        "timestamp": f["ts"],
        "rotation": yaw_quaternion(float(gh)),
        "translation": [float(gx), float(gy), 0.0],
    }


def _sample_data_row(
    frames: list[dict], j: int, filename: str, sample_tokens: list[str], cs_token: str
) -> dict:
    """The sample_data record of frame ``j`` (linked to its neighbours and its sample)."""
    f = frames[j]
    return {
        "token": f["sd_token"],
        "sample_token": sample_tokens[f["k"]],
        "ego_pose_token": f["sd_token"],
        "calibrated_sensor_token": cs_token,
        "timestamp": f["ts"],
        "fileformat": "jpg",
        "is_key_frame": bool(f["key"]),
        "height": wg.H_IMG,
        "width": wg.W_IMG,
        "filename": filename,
        "prev": frames[j - 1]["sd_token"] if j > 0 else "",
        "next": frames[j + 1]["sd_token"] if j + 1 < len(frames) else "",
    }


def _sample_row(scene: dict, f: dict, sample_tokens: list[str]) -> dict:
    """The sample record of keyframe ``f`` (linked to its neighbours)."""
    k = f["k"]
    return {
        "token": sample_tokens[k],
        "timestamp": f["ts"],
        "prev": sample_tokens[k - 1] if k > 0 else "",
        "next": sample_tokens[k + 1] if k + 1 < len(sample_tokens) else "",
        "scene_token": scene["token"],
    }


def _posed_agents(scene: dict, geo: wg.SceneGeometry, t: float) -> list[tuple]:
    """Every agent at time ``t`` (s): (index, agent, box centre (3,) m, yaw rad), scene frame."""
    posed = []
    for i, a in enumerate(scene["agents"]):
        R, ctr = geo.agent_pose(i, t)
        posed.append((i, a, ctr, math.atan2(R[1, 0], R[0, 0])))
    return posed


def _keyframe_annotations(
    seed: int,
    index: int,
    scene: dict,
    fr: wg.Frame,
    t: float,
    k: int,
    sample_tokens: list[str],
    ego: dict,
    posed: list[tuple],
    statics_occ: list[tuple],
) -> list[tuple[int, dict]]:
    """The sample_annotation records of keyframe ``k`` (rendered as ``fr`` at ``t`` s): one
    per agent within :data:`ANNOTATION_RANGE` of the ego, as (agent index, record)."""
    ego_xyz = np.array([float(ego["x"]), float(ego["y"]), 0.0])
    out = []
    for i, a, ctr, yaw in posed:
        dist = float(np.linalg.norm(ctr - ego_xyz))
        if dist > ANNOTATION_RANGE:
            continue
        frac = _visible_fraction(fr, i, a, ctr, yaw, dist, posed, ego_xyz, statics_occ)
        ann = _annotation(seed, index, scene, a, i, k, t, sample_tokens[k], frac, dist)
        out.append((i, ann))
    return out


def _visible_fraction(
    fr: wg.Frame,
    i: int,
    a: dict,
    ctr: np.ndarray,
    yaw: float,
    dist: float,
    posed: list[tuple],
    ego_xyz: np.ndarray,
    statics_occ: list[tuple],
) -> float:
    """Visible fraction of agent ``i``'s box (centre ``ctr`` m, ``yaw`` rad, ``dist`` m from
    the ego): from the rendered silhouette, or for a box outside the image from rays past the
    nearby agents and static boxes."""
    corners = wr.box_corners(ctr, yaw, tuple(a["size"]))
    frac, _px = wr.silhouette_fraction(fr, corners, wg.SID_AGENT0 + i)
    if not np.isfinite(frac):
        pts = np.vstack([ctr[None], ctr + 0.85 * (corners - ctr)])
        occ = [
            (c2, y2, tuple(a2["size"]))
            for i2, a2, c2, y2 in posed
            if i2 != i and np.linalg.norm(c2 - ego_xyz) < dist + 10
        ]
        occ += [o for o in statics_occ if np.linalg.norm(o[0][:2] - ego_xyz[:2]) < dist + 40]
        frac = wr.ray_visibility(fr.c, pts, occ)
    return frac


def _annotation(
    seed: int,
    index: int,
    scene: dict,
    a: dict,
    i: int,
    k: int,
    t: float,
    sample_token: str,
    frac: float,
    dist: float,
) -> dict:
    """The sample_annotation record of agent ``a`` (index ``i``) at keyframe ``k`` (``t`` s):
    global box, attribute, visibility bin of ``frac``, lidar and radar points at ``dist`` m
    (prev/next linked later)."""
    st = ws.agent_state_global(scene, a, t)
    speed = float(st["speed"])
    w, length, h = a["size"]
    lidar = int(round(frac * 2500.0 * (w * h + length * h) / max(dist, 1.0) ** 2))
    return {
        "token": token(seed, "sample_annotation", index, i, k),
        "sample_token": sample_token,
        "instance_token": a["instance_token"],
        "visibility_token": visibility_token(frac),
        "attribute_tokens": [token(seed, "attribute", _attribute(a, speed))],
        "translation": [float(st["x"]), float(st["y"]), float(st["z"])],
        "size": [float(w), float(length), float(h)],
        "rotation": yaw_quaternion(float(ws.wrap_angle(st["yaw"]))),
        "prev": "",
        "next": "",
        "num_lidar_pts": lidar,
        "num_radar_pts": int(a["kind"] == "vehicle" and dist < 70 and frac > 0.3) * 3,
    }


def _link_annotations(seed: int, scene: dict, ann_by_agent: dict[int, list[dict]]) -> list[dict]:
    """Link each annotated agent's annotations (prev/next, in place) and return the instance
    records, in agent order."""
    instances = []
    for i in sorted(ann_by_agent):
        anns = ann_by_agent[i]
        for n, ann in enumerate(anns):
            ann["prev"] = anns[n - 1]["token"] if n > 0 else ""
            ann["next"] = anns[n + 1]["token"] if n + 1 < len(anns) else ""
        a = scene["agents"][i]
        instances.append(
            {
                "token": a["instance_token"],
                "category_token": token(seed, "category", a["category"]),
                "nbr_annotations": len(anns),
                "first_annotation_token": anns[0]["token"],
                "last_annotation_token": anns[-1]["token"],
            }
        )
    return instances


def _in_sample_order(ann_by_agent: dict[int, list[dict]], sample_tokens: list[str]) -> list[dict]:
    """All annotations in sample order (like nuScenes: grouped by sample), then by token."""
    all_anns = [a for i in sorted(ann_by_agent) for a in ann_by_agent[i]]
    order = {tok: n for n, tok in enumerate(sample_tokens)}
    all_anns.sort(key=lambda a: (order[a["sample_token"]], a["token"]))
    return all_anns


def _calibrated_sensor_row(seed: int, scene: dict, cs_token: str) -> dict:
    """The scene's CAM_FRONT calibrated_sensor record."""
    calib = scene["calib"]
    return {
        "token": cs_token,
        "sensor_token": token(seed, "sensor", CHANNEL),
        "translation": calib["translation"],
        "rotation": calib["rotation"],
        "camera_intrinsic": calib["K"],
    }


def _scene_row(seed: int, index: int, scene: dict, sample_tokens: list[str]) -> dict:
    """The scene record (4 scenes per log)."""
    return {
        "token": scene["token"],
        "log_token": token(seed, "log", index // 4),
        "nbr_samples": len(sample_tokens),
        "first_sample_token": sample_tokens[0],
        "last_sample_token": sample_tokens[-1],
        "name": scene["name"],
        "description": scene["description"],
    }


# --------------------------------------------------------------------------------------------
# Whole world
# --------------------------------------------------------------------------------------------


def static_tables(seed: int, n_scenes: int, map_filename: str) -> dict[str, list]:
    """The tables shared by all scenes: category, attribute, visibility, sensor, log (one per
    4 scenes) and map (``map_filename``, relative to the dataroot)."""
    n_logs = (n_scenes + 3) // 4
    logs = [
        {
            "token": token(seed, "log", li),
            "logfile": f"synth-log-{li:04d}",
            "vehicle": "synth-ego",
            "date_captured": time.strftime("%Y-%m-%d", time.gmtime(BASE_US / 1e6 + li * 86400)),
            "location": ("synth-city-east", "synth-city-west")[li % 2],
        }
        for li in range(n_logs)
    ]
    return {
        "category": [
            {"token": token(seed, "category", n), "name": n, "description": d}
            for n, d in CATEGORIES
        ],
        "attribute": [
            {"token": token(seed, "attribute", n), "name": n, "description": d}
            for n, d in ATTRIBUTES
        ],
        "visibility": [{"token": t, "level": lv, "description": d} for t, lv, d in VISIBILITY],
        "sensor": [
            {"token": token(seed, "sensor", CHANNEL), "channel": CHANNEL, "modality": "camera"}
        ],
        "log": logs,
        "map": [
            {
                "token": token(seed, "map"),
                "log_tokens": [lg["token"] for lg in logs],
                "category": "semantic_prior",
                "filename": map_filename,
            }
        ],
    }


