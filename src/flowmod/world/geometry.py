"""What the renderer draws and through what: the camera, textures, objects and frame buffers.

Holds the image size and surface ids, the pinhole :class:`Camera` and its pose over time,
lazily generated textures (:class:`Tex`), textured quads and objects (:class:`Quad`,
:class:`Obj`), :class:`SceneGeometry` (the renderable form of a scene description), the render
output :class:`Frame` and the projection helpers that :mod:`~flowmod.world.shading` and
:mod:`~flowmod.world.render` share.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from pyquaternion import Quaternion

from flowmod.world import scene as ws
from flowmod.world import textures as wt

H_IMG, W_IMG = 900, 1600
Z_NEAR = 0.15  # m
SID_SKY, SID_GROUND, SID_STATIC0, SID_AGENT0 = 0, 1, 2, 20000
GROUND_MAX_DEPTH = 3000.0  # m; farther ground is drawn as horizon haze (sky)

# --------------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Camera:
    """Pinhole CAM_FRONT: intrinsics ``K`` (3, 3), pixels; camera->ego rotation ``R_ce`` (3, 3)
    and the camera centre ``t_ce`` (3,), m, in the ego frame (x forward, y left, z up)."""

    K: np.ndarray
    R_ce: np.ndarray
    t_ce: np.ndarray

    @staticmethod
    def from_calib(calib: dict) -> Camera:
        return Camera(
            K=np.asarray(calib["K"], np.float64),
            R_ce=Quaternion(calib["rotation"]).rotation_matrix,
            t_ce=np.asarray(calib["translation"], np.float64),
        )


def ego_pose_scene(scene: dict, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Ego pose at scene time ``t`` (s): rotation ego->scene (3, 3) and position (3,), m."""
    st = ws.traj_state(scene["ego"], t)
    h = float(st["h"])
    c, s = math.cos(h), math.sin(h)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return R, np.array([float(st["x"]), float(st["y"]), 0.0])


def camera_pose(scene: dict, cam: Camera, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera pose in the scene frame at time ``t``: R_wc (camera->scene, 3x3), centre c (3,)."""
    R_we, p = ego_pose_scene(scene, t)
    return R_we @ cam.R_ce, p + R_we @ cam.t_ce


@lru_cache(maxsize=2)
def _pixel_rays(k_key: tuple) -> np.ndarray:
    """K^-1 (u, v, 1) for every pixel, (3, H*W) float64, row-major pixel order."""
    K = np.array(k_key).reshape(3, 3)
    v, u = np.mgrid[0:H_IMG, 0:W_IMG].astype(np.float64)
    pts = np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    out = np.linalg.inv(K) @ pts
    out[2] = 1.0
    return out


def pixel_rays(K: np.ndarray) -> np.ndarray:
    """Cached K^-1 (u, v, 1) of all pixels: (3, H*W) float64 (camera z component = 1)."""
    return _pixel_rays(tuple(np.asarray(K, np.float64).ravel().tolist()))


# --------------------------------------------------------------------------------------------
# Textures (lazy, with mip levels)
# --------------------------------------------------------------------------------------------


class Tex:
    """A lazily generated texture with mip levels. ``factory() -> (bgr | None, alpha | None)``."""

    def __init__(self, factory: Callable[[], tuple[np.ndarray | None, np.ndarray | None]]):
        self._factory = factory
        self._levels: list[np.ndarray] | None = None
        self._alpha: list[np.ndarray] | None = None
        self._done = False

    def _build(self) -> None:
        if not self._done:
            bgr, alpha = self._factory()
            self._levels = wt.pyramid(bgr) if bgr is not None else None
            self._alpha = wt.pyramid(alpha) if alpha is not None else None
            self._done = True

    @property
    def levels(self) -> list[np.ndarray] | None:
        self._build()
        return self._levels

    @property
    def alpha(self) -> list[np.ndarray] | None:
        self._build()
        return self._alpha


@dataclass
class Quad:
    """A textured parallelogram in its object's frame: corner ``p0`` and edge vectors ``eu``
    (texture u, left->right) and ``ev`` (texture v, top->bottom), m; outward normal ev x eu."""

    p0: np.ndarray
    eu: np.ndarray
    ev: np.ndarray
    tex: Tex | None
    double: bool = False
    wrap: bool = False
    alpha: bool = False
    flip: bool = False  # mirror the texture horizontally


@dataclass
class Obj:
    """An object: quads in its local frame, a surface id, a bounding radius (m)."""

    quads: list[Quad]
    sid: int
    radius: float
    agent: dict | None = None
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw: float = 0.0
    lights: list = field(default_factory=list)
    cache: list | None = None


def box_faces(w: float, length: float, h: float, top: bool = True) -> dict[str, tuple]:
    """Faces of a box centred at the origin (x along ``length``, y along ``w``, z up).

    Returns {name: (p0, eu, ev)} for front (+x), back (-x), left (+y), right (-y) and top,
    oriented so that the texture appears upright and unmirrored from outside.
    """
    L, W, H = length / 2, w / 2, h / 2
    faces = {
        "front": ((L, -W, H), (L, W, H), (L, -W, -H)),
        "back": ((-L, W, H), (-L, -W, H), (-L, W, -H)),
        "left": ((L, W, H), (-L, W, H), (L, W, -H)),
        "right": ((-L, -W, H), (L, -W, H), (-L, -W, -H)),
    }
    if top:
        faces["top"] = ((-L, W, H), (L, W, H), (-L, -W, H))
    out = {}
    for k, (p0, p1, p3) in faces.items():
        p0, p1, p3 = np.array(p0, float), np.array(p1, float), np.array(p3, float)
        out[k] = (p0, p1 - p0, p3 - p0)
    return out


def _rng(*seed: int) -> np.random.Generator:
    return np.random.default_rng([int(s) & 0x7FFFFFFF for s in seed])


def _facade_factory(
    kind: str, seed: int, face: int, width_m: float, height_m: float, shop: bool
) -> Callable[[], tuple[np.ndarray, None]]:
    """Texture factory of one building / backdrop face (generated on first use)."""

    def make() -> tuple[np.ndarray, None]:
        if kind == "building":
            return wt.facade(_rng(seed, face), width_m, height_m, shop), None
        return wt.backdrop(_rng(seed, face), width_m, height_m), None

    return make


# --------------------------------------------------------------------------------------------
# Scene geometry
# --------------------------------------------------------------------------------------------


class SceneGeometry:
    """Renderable form of a scene description (see :mod:`flowmod.world.scene`)."""

    def __init__(self, scene: dict):
        self.scene = scene
        self.cam = Camera.from_calib(scene["calib"])
        self.roads = ws.road_frames(scene["layout"])
        look = scene["look"]
        self.look = look
        if len(scene["statics"]) > SID_AGENT0 - SID_STATIC0:
            raise ValueError(f"too many static objects ({len(scene['statics'])}) for the ids")
        self.statics = [self._static(j, o) for j, o in enumerate(scene["statics"])]
        self.agents = [self._agent(i, a) for i, a in enumerate(scene["agents"])]
        seed = look["textures"]
        self.ground_tex = [
            Tex(lambda: (wt.asphalt(_rng(seed, 1), 1024, look["asphalt"]), None)),
            Tex(lambda: (wt.pavers(_rng(seed, 2)), None)),
            Tex(
                lambda: (
                    wt.grass(_rng(seed, 3))
                    if scene["layout"]["kind"] != "urban"
                    else wt.pavers(_rng(seed, 4)),
                    None,
                )
            ),
        ]
        self._mod: np.ndarray | None = None
        self._clouds: np.ndarray | None = None
        sun_az, sun_el = look["sun_azimuth"], look["sun_elevation"]
        self.sun = np.array(
            [
                math.cos(sun_az) * math.cos(sun_el),
                math.sin(sun_az) * math.cos(sun_el),
                math.sin(sun_el),
            ]
        )

    # -- builders ------------------------------------------------------------------------
    def _static(self, j: int, o: dict) -> Obj:
        w, length, h = o["size"]
        seed = o["tex"]
        kind = o["kind"]
        quads: list[Quad] = []
        lights = []
        if kind in ("building", "backdrop"):
            for i, (name, (p0, eu, ev)) in enumerate(box_faces(w, length, h, top=False).items()):
                width_m = float(np.linalg.norm(eu))
                shop = name in ("left", "right") and self.scene["layout"]["kind"] == "urban"
                quads.append(
                    Quad(p0, eu, ev, Tex(_facade_factory(kind, seed, i, width_m, h, shop)))
                )
        elif kind == "tree":
            trunk_h = h * 0.45
            tw = max(0.18, h * 0.03)
            bark = Tex(lambda s=seed: (wt.bark(_rng(s, 0)), None))
            for _name, (p0, eu, ev) in box_faces(tw, tw, trunk_h, top=False).items():
                off = np.array([0.0, 0.0, trunk_h / 2 - h / 2])
                quads.append(Quad(p0 + off, eu, ev, bark))
            crown = Tex(lambda s=seed: wt.foliage(_rng(s, 1)))
            cw = w
            z0, z1 = h * 0.3 - h / 2, h / 2
            for ang in (0.0, math.pi / 2):
                d = np.array([math.cos(ang), math.sin(ang), 0.0]) * cw
                p0 = np.array([0.0, 0.0, z1]) - d / 2
                quads.append(
                    Quad(p0, d, np.array([0.0, 0.0, z0 - z1]), crown, double=True, alpha=True)
                )
        elif kind == "pole":
            tex = Tex(lambda s=seed: (wt.metal(_rng(s, 0)), None))
            for _name, (p0, eu, ev) in box_faces(w, length, h, top=False).items():
                quads.append(Quad(p0, eu, ev, tex))
            lights.append((np.array([0.0, 0.0, h / 2 + 0.1]), (150, 200, 230), 0.3))
        else:  # hedge / wall
            for i, (_name, (p0, eu, ev)) in enumerate(box_faces(w, length, h, top=True).items()):
                wpx = max(int(np.linalg.norm(eu) / 0.05), 4)
                hpx = max(int(np.linalg.norm(ev) / 0.05), 4)
                tex = Tex(
                    lambda s=seed, i=i, a=wpx, b=hpx, wall=(kind == "wall"): (
                        wt.hedge(_rng(s, i), a, b, wall),
                        None,
                    )
                )
                quads.append(Quad(p0, eu, ev, tex))
        return Obj(
            quads,
            SID_STATIC0 + j,
            float(0.5 * math.sqrt(w * w + length * length + h * h)),
            center=np.array(o["c"], float),
            yaw=float(o["yaw"]),
            lights=lights,
        )

    def _agent(self, i: int, a: dict) -> Obj:
        w, length, h = a["size"]
        seed = a["tex"]
        quads: list[Quad] = []
        faces = box_faces(w, length, h, top=True)
        if a["kind"] == "pedestrian":
            cache: dict = {}

            def ped(face, s=seed, size=(w, length, h), cache=cache):
                if not cache:
                    cache.update(wt.pedestrian_faces(_rng(s, 0), size))
                return cache[face]

            for name, (p0, eu, ev) in faces.items():
                key = {"left": "side", "right": "side"}.get(name, name)
                quads.append(
                    Quad(p0, eu, ev, Tex(lambda k=key: ped(k)), alpha=True, flip=(name == "left"))
                )
            lights = []
        else:
            cache = {}

            def veh(face, s=seed, cat=a["category"], size=(w, length, h), cache=cache):
                if not cache:
                    cache.update(wt.vehicle_faces(_rng(s, 0), cat, size))
                return cache[face], None

            for name, (p0, eu, ev) in faces.items():
                key = {"left": "side", "right": "side"}.get(name, name)
                quads.append(Quad(p0, eu, ev, Tex(lambda k=key: veh(k)), flip=(name == "left")))
            zl = -0.1 * h
            lights = [
                (np.array([length / 2 + 0.02, 0.36 * w, zl]), (200, 225, 240), 0.11),
                (np.array([length / 2 + 0.02, -0.36 * w, zl]), (200, 225, 240), 0.11),
                (np.array([-length / 2 - 0.02, 0.39 * w, zl]), (20, 20, 200), 0.08),
                (np.array([-length / 2 - 0.02, -0.39 * w, zl]), (20, 20, 200), 0.08),
            ]
        return Obj(
            quads,
            SID_AGENT0 + i,
            float(0.5 * math.sqrt(w * w + length * length + h * h)),
            agent=a,
            lights=lights,
        )

    # -- per-time poses ------------------------------------------------------------------
    def agent_pose(self, i: int, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Agent i at time t in the scene frame: rotation (3, 3) local->scene, centre (3,)."""
        a = self.agents[i].agent
        st = ws.traj_state(a["traj"], t)
        h = float(st["h"])
        c, s = math.cos(h), math.sin(h)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return R, np.array([float(st["x"]), float(st["y"]), a["size"][2] / 2])

    def ground_tiles(self) -> list[Tex]:
        return self.ground_tex

    def modulation_field(self) -> np.ndarray:
        if self._mod is None:
            r = _rng(self.look["textures"], 9)
            self._mod = wt.value_noise(r, 256, 256, 16, periodic=True) * 0.5
        return self._mod

    def cloud_field(self) -> np.ndarray:
        if self._clouds is None:
            self._clouds = wt.clouds(_rng(self.look["textures"], 10))
        return self._clouds


# --------------------------------------------------------------------------------------------
# Frame buffers and projection helpers
# --------------------------------------------------------------------------------------------


@dataclass
class Frame:
    """Render output. ``img`` (H, W, 3) uint8 BGR or None; ``invz`` (H, W) float32, 1/m
    (0 = sky); ``sid`` (H, W) uint16 surface ids; camera pose R_wc (3, 3), c (3,) (scene)."""

    img: np.ndarray | None
    invz: np.ndarray
    sid: np.ndarray
    R_wc: np.ndarray
    c: np.ndarray
    K: np.ndarray
    lights: list = field(default_factory=list)


def clip_near(pts: np.ndarray, z_near: float = Z_NEAR) -> np.ndarray:
    """Sutherland-Hodgman clip of a camera-frame polygon (n, 3) against z >= z_near."""
    out = []
    n = len(pts)
    for i in range(n):
        a, b = pts[i], pts[(i + 1) % n]
        ina, inb = a[2] >= z_near, b[2] >= z_near
        if ina:
            out.append(a)
        if ina != inb:
            s = (z_near - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.array(out).reshape(-1, 3)


def project_bbox(points_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, tuple[int, ...]]:
    """Project camera-frame points (N, 3) with K: pixel coordinates (N, 2) and their integer
    bounding box (x0, x1, y0, y1), end-exclusive, clipped to the image."""
    uvw = points_cam @ K.T
    uv = uvw[:, :2] / uvw[:, 2:3]
    x0 = max(int(math.floor(uv[:, 0].min())), 0)
    x1 = min(int(math.ceil(uv[:, 0].max())) + 1, W_IMG)
    y0 = max(int(math.floor(uv[:, 1].min())), 0)
    y1 = min(int(math.ceil(uv[:, 1].max())) + 1, H_IMG)
    return uv, (x0, x1, y0, y1)


#: u (px) of every image column, (W,) float32.
U_COLS = np.arange(W_IMG, dtype=np.float32)
#: v (px) of every image row, (H,) float32.
V_ROWS = np.arange(H_IMG, dtype=np.float32)


@lru_cache(maxsize=8)
def _kinv_cached(k_key: tuple) -> np.ndarray:
    return np.linalg.inv(np.array(k_key).reshape(3, 3))


def kinv(K: np.ndarray) -> np.ndarray:
    """Cached inverse of the intrinsics ``K`` (3, 3)."""
    return _kinv_cached(tuple(K.ravel().tolist()))


@lru_cache(maxsize=1)
def pixel_uv() -> tuple[np.ndarray, np.ndarray]:
    """(u, v) of every pixel (px), each (H*W,) float32, row-major pixel order (cached)."""
    v, u = np.divmod(np.arange(H_IMG * W_IMG, dtype=np.int64), W_IMG)
    return u.astype(np.float32), v.astype(np.float32)


def yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation (3, 3) about z by ``yaw`` (rad)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def visible_sphere(
    center: np.ndarray, radius: float, R_wc: np.ndarray, c: np.ndarray, K: np.ndarray
) -> bool:
    """Bounding sphere (scene frame) intersects the view frustum (near plane and 4 sides)."""
    p = (center - c) @ R_wc
    if p[2] + radius < Z_NEAR:
        return False
    for n in _frustum_normals(tuple(K.ravel().tolist())):
        if n[0] * p[0] + n[1] * p[1] + n[2] * p[2] > radius:
            return False
    return True


@lru_cache(maxsize=8)
def _frustum_normals(k_key: tuple) -> np.ndarray:
    K = np.array(k_key).reshape(3, 3)
    planes = np.array(
        [
            (1.0, 0.0, -(W_IMG + 2 - K[0, 2]) / K[0, 0]),
            (-1.0, 0.0, -(K[0, 2] + 2) / K[0, 0]),
            (0.0, 1.0, -(H_IMG + 2 - K[1, 2]) / K[1, 1]),
            (0.0, -1.0, -(K[1, 2] + 2) / K[1, 1]),
        ]
    )
    return planes / np.linalg.norm(planes, axis=1, keepdims=True)
