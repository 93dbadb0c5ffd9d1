"""Rendering of the synthetic world: one CAM_FRONT frame = textured planes under a pinhole camera.

Everything in the world is planar, so the renderer never ray-casts in Python:

* ground and sky: per-pixel *array* shading (no Python loop over pixels). Each pixel's ray
  ``d = R_wc K^-1 (u, v, 1)`` meets the ground z = 0 at depth ``Z = h_cam / -d_z``; ground
  materials, lane paint and mip level are closed-form functions of the hit point, textures are
  sampled with ``cv2.remap``. The sky is a function of the ray direction only (at infinity).
* objects (buildings, trees, poles, hedges, vehicles, pedestrians): boxes and billboards whose
  faces are textured quads. A quad is a homography of its texture (``cv2.warpPerspective``
  into the quad's bounding box), masked by ``cv2.fillConvexPoly`` and an inverse-depth test.
  Inverse depth is affine in the pixel coordinates for a plane, so the z-buffer is exact.

The same pass gives an inverse-depth map ``invz`` (1/m, 0 for sky) and a surface-id map ``sid``
(0 sky, 1 ground, 2 + j static object j, 20000 + i agent i), from which ground-truth flow and
visibility are computed. Pixel centres are at integer coordinates (OpenCV convention), like the
nuScenes projection ``view_points``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
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
# Frame buffers and drawing
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


def _clip_near(pts: np.ndarray, z_near: float = Z_NEAR) -> np.ndarray:
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


def _sample(img: np.ndarray, u: np.ndarray, v: np.ndarray, wrap: bool) -> np.ndarray:
    """Bilinear samples of ``img`` at float texture coordinates (n,) -> (n, C)."""
    n = u.size
    cols = 1024
    rows = max((n + cols - 1) // cols, 1)
    mu = np.zeros(rows * cols, np.float32)
    mv = np.zeros(rows * cols, np.float32)
    mu[:n], mv[:n] = u, v
    out = cv2.remap(
        img,
        mu.reshape(rows, cols),
        mv.reshape(rows, cols),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_WRAP if wrap else cv2.BORDER_REPLICATE,
    )
    return out.reshape(rows * cols, -1)[:n]


def _shade(normal_w: np.ndarray, sun: np.ndarray, look: dict) -> float:
    """Lambertian face brightness relative to the ground (1.0); ``normal_w`` any length."""
    if look["weather"] in ("clear", "after_rain"):
        amb, dif = 0.5, 0.6
    else:
        amb, dif = 0.8, 0.2
    n = normal_w / (math.sqrt(float(normal_w @ normal_w)) + 1e-12)
    lit = amb + dif * max(float(n @ sun), 0.0) + (0.1 if n[2] > 0.5 else 0.0)
    return lit / (amb + dif * max(float(sun[2]), 0.0))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _project_bbox(points_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, tuple[int, ...]]:
    """Project camera-frame points (N, 3) with K: pixel coordinates (N, 2) and their integer
    bounding box (x0, x1, y0, y1), end-exclusive, clipped to the image."""
    uvw = points_cam @ K.T
    uv = uvw[:, :2] / uvw[:, 2:3]
    x0 = max(int(math.floor(uv[:, 0].min())), 0)
    x1 = min(int(math.ceil(uv[:, 0].max())) + 1, W_IMG)
    y0 = max(int(math.floor(uv[:, 1].min())), 0)
    y1 = min(int(math.ceil(uv[:, 1].max())) + 1, H_IMG)
    return uv, (x0, x1, y0, y1)


def draw_quad(
    fr: Frame,
    corners_w: np.ndarray,
    q: Quad,
    sid: int,
    shade: float,
    textured: bool,
    normal_w: np.ndarray | None = None,
) -> None:
    """Draw one quad given its world corners (4, 3) [p0, p1, p2, p3] with the z-test.

    ``normal_w``: the outward normal (ev x eu), computed if not given.
    """
    eu_w = corners_w[1] - corners_w[0]
    ev_w = corners_w[3] - corners_w[0]
    n_w = _cross(ev_w, eu_w) if normal_w is None else normal_w
    if not q.double and float(n_w @ (fr.c - corners_w[0])) <= 0:
        return
    Xc = (corners_w - fr.c) @ fr.R_wc
    zmin, zmax = Xc[:, 2].min(), Xc[:, 2].max()
    if zmax < Z_NEAR:
        return
    poly = _clip_near(Xc) if zmin < Z_NEAR else Xc
    if len(poly) < 3:
        return
    K = fr.K
    uv, (x0, x1, y0, y1) = _project_bbox(poly, K)
    if x1 <= x0 or y1 <= y0:
        return
    w, h = x1 - x0, y1 - y0
    # inverse depth plane: 1/Z = g . (u, v, 1)
    R_cw = fr.R_wc.T
    n_c = R_cw @ n_w
    d = float(n_c @ Xc[0])
    if abs(d) < 1e-12:
        return
    g = _kinv(K).T @ n_c / d
    iz = (np.float32(g[0]) * _US[x0:x1])[None, :] + (
        np.float32(g[1]) * _VS[y0:y1] + np.float32(g[2])
    )[:, None]
    mask = np.zeros((h, w), np.uint8)
    pts = np.round((uv - [x0, y0]) * 16).astype(np.int32)
    cv2.fillConvexPoly(mask, pts, 1, cv2.LINE_8, 4)
    iz_roi = fr.invz[y0:y1, x0:x1]
    m = (mask > 0) & (iz > iz_roi)
    if not m.any():
        return
    if (textured or q.alpha) and q.tex is not None:
        levels = q.tex.levels if textured else None
        alphas = q.tex.alpha if q.alpha else None
        ref = levels if levels is not None else alphas
        th, tw_ = ref[0].shape[:2]
        # mip level from texels per image pixel at a representative depth
        zs = np.clip(poly[:, 2], Z_NEAR, None)
        zref = math.sqrt(float(zs.min()) * float(zs.max()))
        du = math.sqrt(math.sqrt(float(eu_w @ eu_w)) / tw_ * math.sqrt(float(ev_w @ ev_w)) / th)
        texel_px = du * K[0, 0] / zref
        lvl = int(
            min(max(math.floor(math.log2(max(1.0 / max(texel_px, 1e-9), 1.0))), 0), len(ref) - 1)
        )

        def warp(src: np.ndarray, interp: int) -> np.ndarray:
            sh, sw = src.shape[:2]
            eu = eu_w / sw
            ev = ev_w / sh
            p0 = corners_w[0] + 0.5 * eu + 0.5 * ev
            if q.flip:
                p0 = corners_w[1] - 0.5 * eu + 0.5 * ev
                eu = -eu
            Hm = K @ R_cw @ np.column_stack([eu, ev, p0 - fr.c])
            Hm[0] -= x0 * Hm[2]
            Hm[1] -= y0 * Hm[2]
            return cv2.warpPerspective(
                src,
                Hm,
                (w, h),
                flags=interp,
                borderMode=cv2.BORDER_WRAP if q.wrap else cv2.BORDER_REPLICATE,
            )

        if alphas is not None:
            a = warp(alphas[min(lvl, len(alphas) - 1)], cv2.INTER_LINEAR)
            m &= a >= 128
        if textured and levels is not None:
            col = warp(levels[min(lvl, len(levels) - 1)], cv2.INTER_LINEAR)
            if abs(shade - 1.0) > 1e-3:
                col = cv2.convertScaleAbs(col, alpha=shade)
            np.copyto(fr.img[y0:y1, x0:x1], col, where=m[..., None])
    np.copyto(iz_roi, iz, where=m)
    fr.sid[y0:y1, x0:x1][m] = sid


_US = np.arange(W_IMG, dtype=np.float32)
_VS = np.arange(H_IMG, dtype=np.float32)


@lru_cache(maxsize=8)
def _kinv_cached(k_key: tuple) -> np.ndarray:
    return np.linalg.inv(np.array(k_key).reshape(3, 3))


def _kinv(K: np.ndarray) -> np.ndarray:
    return _kinv_cached(tuple(K.ravel().tolist()))


@lru_cache(maxsize=1)
def _pixel_uv() -> tuple[np.ndarray, np.ndarray]:
    v, u = np.divmod(np.arange(H_IMG * W_IMG, dtype=np.int64), W_IMG)
    return u.astype(np.float32), v.astype(np.float32)


# --------------------------------------------------------------------------------------------
# Ground and sky
# --------------------------------------------------------------------------------------------

WEATHER_LOOK = {
    # horizon BGR, zenith BGR, cloudiness, fog distance (m), ground wetness factor
    "clear": ((225, 212, 200), (205, 150, 95), 0.5, 1800.0, 1.0),
    "overcast": ((200, 198, 196), (175, 170, 168), 0.9, 900.0, 1.0),
    "after_rain": ((205, 200, 195), (185, 165, 145), 0.8, 1000.0, 0.78),
    "rain": ((170, 168, 166), (140, 138, 136), 1.0, 260.0, 0.7),
    "night": ((60, 45, 40), (25, 15, 10), 0.3, 700.0, 1.0),
}


def _aa_band(x: np.ndarray, lo: float, hi: float, fp: np.ndarray) -> np.ndarray:
    """Anti-aliased indicator of lo <= x <= hi with pixel footprint ``fp`` (m)."""
    c, hw = 0.5 * (lo + hi), 0.5 * (hi - lo)
    return np.clip((hw - np.abs(x - c)) / fp + 0.5, 0.0, 1.0)


def _aa_stripes(
    x: np.ndarray, period: float, width: float, fp: np.ndarray, phase: float = 0.0
) -> np.ndarray:
    """Anti-aliased stripes of ``width`` every ``period`` (m), centred at phase + k * period."""
    y = (x - phase) * (1.0 / period)
    r = (y - np.floor(y + 0.5)) * period
    return np.clip((width / 2 - np.abs(r)) / fp + 0.5, 0.0, 1.0)


def _paint_line(
    alpha: np.ndarray,
    across: np.ndarray,
    fp: np.ndarray,
    pos: float,
    hw: float,
    along: np.ndarray | None = None,
    dash: tuple | None = None,
    where: np.ndarray | None = None,
) -> None:
    """max-composite a (dashed) line at across = pos, half width hw (m), into ``alpha``."""
    cand = np.abs(across - pos) < hw + fp
    if where is not None:
        cand &= where
    idx = np.flatnonzero(cand)
    if idx.size == 0:
        return
    a = _aa_band(across[idx], pos - hw, pos + hw, fp[idx])
    if dash is not None:
        a *= _aa_stripes(along[idx], dash[0], dash[1], fp[idx], dash[2])
    alpha[idx] = np.maximum(alpha[idx], a)


def _road_paint(geo: SceneGeometry, coords: list, fp: np.ndarray):
    """Lane paint over ground points: (white, yellow, kerb) alphas, each (n,) float32.

    ``coords``: per road the (along, across) arrays of the points (m).
    """
    n = fp.size
    white = np.zeros(n, np.float32)
    yellow = np.zeros(n, np.float32)
    kerb = np.zeros(n, np.float32)
    roads = geo.roads
    for i, r in enumerate(roads):
        along, across = coords[i]
        acr = np.abs(across)
        free = np.ones(n, bool)
        for j, o in enumerate(roads):
            if j == i:
                continue
            free &= np.abs(coords[j][1]) > max(o["kerb"])
            along_int = float(ws.road_coords(r, np.array(o["o"][0]), np.array(o["o"][1]))[0])
            k_o = max(o["kerb"])
            rel = along - np.float32(along_int)
            arel = np.abs(rel)
            # crosswalks on both sides of the intersection
            cw = np.flatnonzero((np.abs(arel - (k_o + 2.2)) <= 1.4) & (acr <= max(r["kerb"])))
            if cw.size:
                white[cw] = np.maximum(white[cw], _aa_stripes(across[cw], 1.1, 0.55, fp[cw]))
            # stop lines
            st = np.flatnonzero(
                (np.abs(arel - (k_o + 4.2)) < 0.2 + fp) & (acr <= r["inner"]) & (rel * across > 0)
            )
            if st.size:
                white[st] = np.maximum(white[st], _aa_band(arel[st], k_o + 4.0, k_o + 4.4, fp[st]))
        if r["center"] == "double_yellow":
            _paint_line(yellow, across, fp, 0.12, 0.06, where=free)
            _paint_line(yellow, across, fp, -0.12, 0.06, where=free)
        else:
            _paint_line(white, across, fp, 0.0, 0.07, along, (9.0, 3.0, 0.0), where=free)
        for k in range(1, r["lanes"]):
            off = r["median"] / 2 + k * r["lane_w"]
            _paint_line(white, acr, fp, off, 0.07, along, (9.0, 3.0, 1.5), where=free)
        _paint_line(white, acr, fp, r["inner"], 0.08, where=free)
        for side, sgn in ((0, -1.0), (1, 1.0)):
            sa = sgn * across
            if r["park"][side]:
                mid = r["inner"] + r["park_w"] / 2
                _paint_line(
                    white, sa, fp, mid, r["park_w"] / 2, along, (6.0, 0.12, 0.7), where=free
                )
            kb = r["kerb"][side]
            _paint_line(kerb, sa, fp, kb + 0.09, 0.09, where=free)
    return white, yellow, kerb


def _ground_depth(fr: Frame) -> None:
    """Analytic inverse depth of the ground plane z = 0 (affine in u, v); sky elsewhere."""
    Kinv = _kinv(fr.K)
    g = -(fr.R_wc[2] @ Kinv) / float(fr.c[2])  # invz = g . (u, v, 1)
    invz = (np.float32(g[0]) * _US)[None, :] + (np.float32(g[1]) * _VS + np.float32(g[2]))[:, None]
    ground = invz > np.float32(1.0 / GROUND_MAX_DEPTH)
    np.copyto(fr.invz, np.where(ground, invz, np.float32(0.0)))
    np.copyto(fr.sid, ground.astype(np.uint16))  # SID_GROUND = 1, SID_SKY = 0


def _shade_background(geo: SceneGeometry, fr: Frame) -> None:
    """Colour the pixels still showing ground or sky (deferred shading)."""
    look = geo.look
    horizon, zenith, cloudiness, fog_dist, wet = WEATHER_LOOK[look["weather"]]
    horizon = np.array(horizon, np.float32)
    zenith = np.array(zenith, np.float32)
    img = fr.img.reshape(-1, 3)
    f = float(fr.K[0, 0])
    M = (fr.R_wc @ _kinv(fr.K)).astype(np.float32)
    U, V = _pixel_uv()
    sid = fr.sid.ravel()

    gi = np.flatnonzero(sid == SID_GROUND)
    if gi.size:
        u, v = U[gi], V[gi]
        dx = M[0, 0] * u + M[0, 1] * v + M[0, 2]
        dy = M[1, 0] * u + M[1, 1] * v + M[1, 2]
        dz = M[2, 0] * u + M[2, 1] * v + M[2, 2]
        t = 1.0 / fr.invz.ravel()[gi]  # depth Z (m) = ray parameter (rays have camera z = 1)
        gx = np.float32(fr.c[0]) + t * dx
        gy = np.float32(fr.c[1]) + t * dy
        norm = np.sqrt(dx * dx + dy * dy + dz * dz)
        sin_g = np.maximum(-dz / norm, np.float32(0.02))
        fp = (t * norm / np.float32(f)) / np.sqrt(sin_g)  # pixel footprint on the ground, m
        coords = [ws.road_coords(r, gx, gy) for r in geo.roads]
        # materials: 0 asphalt, 1 sidewalk, 2 verge
        region = np.full(gi.size, 2, np.int8)
        for r, (_, acr) in zip(geo.roads, coords, strict=True):
            region[(acr >= -r["walk"][0]) & (acr <= r["walk"][1]) & (region == 2)] = 1
        for r, (_, acr) in zip(geo.roads, coords, strict=True):
            region[(acr >= -r["kerb"][0]) & (acr <= r["kerb"][1])] = 0
        level = np.floor(np.log2(np.maximum(fp * np.float32(1.0 / wt.GROUND_RES), 1.0))).astype(
            np.int8
        )
        col = np.empty((gi.size, 3), np.uint8)
        for m_id, tex in enumerate(geo.ground_tiles()):
            sel_m = region == m_id
            if not sel_m.any():
                continue
            levels = tex.levels
            lv = np.minimum(level, len(levels) - 1)
            size0 = levels[0].shape[0]
            idx_m = np.flatnonzero(sel_m)
            u0 = np.mod(gx[idx_m] * np.float32(1.0 / wt.GROUND_RES), size0)
            v0 = np.mod(gy[idx_m] * np.float32(1.0 / wt.GROUND_RES), size0)
            lv_m = lv[idx_m]
            for k in np.unique(lv_m):
                sel = np.flatnonzero(lv_m == k)
                s = np.float32(2.0**-k)
                col[idx_m[sel]] = _sample(
                    levels[k], (u0[sel] + 0.5) * s - 0.5, (v0[sel] + 0.5) * s - 0.5, True
                )
        colf = col.astype(np.float32)
        mval = _sample(
            geo.modulation_field(),
            np.mod(gx * np.float32(1.25), 256),
            np.mod(gy * np.float32(1.25), 256),
            True,
        )[:, 0]
        colf *= (1.0 + 0.12 * mval)[:, None]
        white, yellow, kerb = _road_paint(geo, coords, fp)
        for alpha, paint in (
            (white * 0.85, (222, 226, 228)),
            (yellow, (40, 165, 210)),
            (kerb, (170, 172, 175)),
        ):
            idx = np.flatnonzero(alpha > 0)
            if idx.size:
                colf[idx] += alpha[idx, None] * (np.array(paint, np.float32) - colf[idx])
        if wet != 1.0:
            colf *= np.where(region == 2, np.float32(0.9), np.float32(wet))[:, None]
        fog = 1.0 - np.exp(-t * norm * np.float32(1.0 / fog_dist))
        colf += fog[:, None] * (horizon - colf)
        img[gi] = np.clip(colf, 0, 255).astype(np.uint8)

    si = np.flatnonzero(sid == SID_SKY)
    if si.size:
        u, v = U[si], V[si]
        dx = M[0, 0] * u + M[0, 1] * v + M[0, 2]
        dy = M[1, 0] * u + M[1, 1] * v + M[1, 2]
        dz = M[2, 0] * u + M[2, 1] * v + M[2, 2]
        norm = np.sqrt(dx * dx + dy * dy + dz * dz)
        e = np.clip(dz / norm, 0.0, 1.0)
        mix = np.sqrt(e)[:, None]
        col = horizon * (1 - mix) + zenith * mix
        dzc = np.maximum(dz, 0.02 * norm)
        cu = np.mod(187.5 * dx / dzc, 512)
        cv = np.mod(187.5 * dy / dzc, 512)
        dens = _sample(geo.cloud_field(), cu, cv, True)[:, 0] * np.float32(cloudiness)
        dens *= np.clip(e * 6.0, 0, 1)
        cloud_col = np.array(
            [235, 235, 235] if look["weather"] != "night" else [50, 45, 40], np.float32
        )
        col += dens[:, None] * (cloud_col - col)
        img[si] = np.clip(col, 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _visible_sphere(
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


def object_corners(obj: Obj, R: np.ndarray, t: np.ndarray, q: Quad) -> np.ndarray:
    """World corners (4, 3) [p0, p1, p2, p3] of a quad of an object posed by (R, t)."""
    p0 = q.p0
    loc = np.array([p0, p0 + q.eu, p0 + q.eu + q.ev, p0 + q.ev])
    return loc @ R.T + t


def _static_cache(geo: SceneGeometry, obj: Obj) -> list[tuple]:
    """Per quad of a static object: (world corners, outward normal, shade); computed once."""
    if obj.cache is None:
        R = _yaw_matrix(obj.yaw)
        out = []
        for q in obj.quads:
            cw = object_corners(obj, R, obj.center, q)
            n = _cross(cw[3] - cw[0], cw[1] - cw[0])
            out.append((cw, n, _shade(n, geo.sun, geo.look)))
        obj.cache = out
    return obj.cache


def render(geo: SceneGeometry, t: float, textured: bool = True) -> Frame:
    """Render the scene at time ``t`` (s). Returns a :class:`Frame` (image before post)."""
    cam = geo.cam
    R_wc, c = camera_pose(geo.scene, cam, t)
    fr = Frame(
        img=np.empty((H_IMG, W_IMG, 3), np.uint8) if textured else None,
        invz=np.empty((H_IMG, W_IMG), np.float32),
        sid=np.empty((H_IMG, W_IMG), np.uint16),
        R_wc=R_wc,
        c=c,
        K=cam.K,
    )
    _ground_depth(fr)
    posed: list[tuple[Obj, np.ndarray | None, np.ndarray]] = []
    for i, obj in enumerate(geo.agents):
        R, ctr = geo.agent_pose(i, t)
        posed.append((obj, R, ctr))
    agents = list(posed)
    for obj in geo.statics:
        posed.append((obj, None, obj.center))
    # near to far: far objects hidden behind near ones fail the z-test early
    posed.sort(key=lambda o: float(np.sum((o[2] - c) ** 2)))
    for obj, R, ctr in posed:
        if not _visible_sphere(ctr, obj.radius, R_wc, c, cam.K):
            continue
        if R is None:
            for q, (cw, n, shade) in zip(obj.quads, _static_cache(geo, obj), strict=True):
                draw_quad(fr, cw, q, obj.sid, shade, textured, n)
            lights = [(pos + ctr, col, rad) for pos, col, rad in obj.lights]
        else:
            for q in obj.quads:
                cw = object_corners(obj, R, ctr, q)
                n = _cross(cw[3] - cw[0], cw[1] - cw[0])
                shade = _shade(n, geo.sun, geo.look) if textured else 1.0
                draw_quad(fr, cw, q, obj.sid, shade, textured, n)
            lights = [(R @ pos + ctr, col, rad) for pos, col, rad in obj.lights]
        fr.lights.extend((p, col, rad, obj.sid) for p, col, rad in lights)
    if textured:
        _shade_background(geo, fr)
        _contact_shadows(fr, agents)
    return fr


def _contact_shadows(fr: Frame, posed) -> None:
    """Darken the ground under vehicles (soft footprint), only where the ground is seen."""
    for obj, R, ctr in posed:
        a = obj.agent
        if a is None or a["kind"] != "vehicle":
            continue
        if not _visible_sphere(np.array([ctr[0], ctr[1], 0.0]), obj.radius, fr.R_wc, fr.c, fr.K):
            continue
        w, length, _ = a["size"]
        fpts = np.array(
            [
                [length / 2 + 0.2, w / 2 + 0.25, 0],
                [-length / 2 - 0.2, w / 2 + 0.25, 0],
                [-length / 2 - 0.2, -w / 2 - 0.25, 0],
                [length / 2 + 0.2, -w / 2 - 0.25, 0],
            ]
        )
        world = fpts @ R.T + np.array([ctr[0], ctr[1], 0.01])
        Xc = (world - fr.c) @ fr.R_wc
        if Xc[:, 2].max() < Z_NEAR:
            continue
        poly = _clip_near(Xc)
        if len(poly) < 3:
            continue
        uvw = poly @ fr.K.T
        uv = uvw[:, :2] / uvw[:, 2:3]
        x0 = max(int(uv[:, 0].min()) - 1, 0)
        x1 = min(int(uv[:, 0].max()) + 2, W_IMG)
        y0 = max(int(uv[:, 1].min()) - 1, 0)
        y1 = min(int(uv[:, 1].max()) + 2, H_IMG)
        if x1 <= x0 or y1 <= y0:
            continue
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(
            mask, np.round((uv - [x0, y0]) * 16).astype(np.int32), 255, cv2.LINE_AA, 4
        )
        mask = (mask.astype(np.float32) / 255.0) * (fr.sid[y0:y1, x0:x1] == SID_GROUND)
        roi = fr.img[y0:y1, x0:x1]
        roi[:] = (roi * (1.0 - 0.45 * mask[..., None])).astype(np.uint8)


# --------------------------------------------------------------------------------------------
# Camera effects
# --------------------------------------------------------------------------------------------


@lru_cache(maxsize=2)
def _noise_bank(which: int) -> np.ndarray:
    rng = np.random.default_rng(20240611 + which)
    return rng.standard_normal((H_IMG + 96, W_IMG + 96, 3), dtype=np.float32)


@lru_cache(maxsize=4)
def _vignette(k_key: tuple) -> np.ndarray:
    K = np.array(k_key).reshape(3, 3)
    v, u = np.mgrid[0:H_IMG, 0:W_IMG].astype(np.float32)
    r2 = ((u - K[0, 2]) ** 2 + (v - K[1, 2]) ** 2) / (K[0, 0] ** 2)
    return (1.0 / (1.0 + r2) ** 2)[..., None].astype(np.float32) ** 0.35


def finish(fr: Frame, look: dict, frame_seed: tuple[int, ...], exposure: float) -> np.ndarray:
    """Camera model: lights (night), rain streaks, exposure, vignetting, blur, noise.

    Returns the final (H, W, 3) uint8 BGR image; ``exposure`` is a gain (1 = nominal).
    """
    rng = np.random.default_rng(list(frame_seed))
    img = fr.img
    weather = look["weather"]
    if weather == "night":
        img = cv2.convertScaleAbs(img, alpha=0.28)
        _draw_lights(fr, img)
    if weather == "rain":
        img = _rain(img, rng)
    gain = np.float32(look["gain"] * exposure)
    wb = np.asarray(look["white_balance"], np.float32) * gain
    f = img.astype(np.float32)
    f *= _vignette(tuple(fr.K.ravel().tolist()))
    f *= wb[None, None, :]
    f = cv2.GaussianBlur(f, (0, 0), 0.6)
    sigma = look["noise"] * (2.2 if weather == "night" else 1.0)
    o1 = rng.integers(0, 96, 2)
    o2 = rng.integers(0, 96, 2)
    n1 = _noise_bank(0)[o1[0] : o1[0] + H_IMG, o1[1] : o1[1] + W_IMG]
    n2 = _noise_bank(1)[o2[0] : o2[0] + H_IMG, o2[1] : o2[1] + W_IMG]
    f += np.float32(sigma * 0.8) * n1
    f += np.float32(sigma * 0.6) * n2
    return np.clip(f, 0, 255).astype(np.uint8)


def _draw_lights(fr: Frame, img: np.ndarray) -> None:
    """Head/tail lights and street lamps as glows where they are not occluded."""
    layer = np.zeros_like(img)
    for pos, col, rad, sid in fr.lights:
        X = fr.R_wc.T @ (pos - fr.c)
        if X[2] < 1.0:
            continue
        u = fr.K[0, 0] * X[0] / X[2] + fr.K[0, 2]
        v = fr.K[1, 1] * X[1] / X[2] + fr.K[1, 2]
        if not (0 <= u < W_IMG and 0 <= v < H_IMG):
            continue
        iz = fr.invz[int(v), int(u)]
        if iz > 1.03 / X[2] and fr.sid[int(v), int(u)] != sid:
            continue
        r = max(int(rad * fr.K[0, 0] / X[2]), 1)
        cv2.circle(layer, (int(u), int(v)), r, col, -1, cv2.LINE_AA)
    if layer.any():
        glow = cv2.GaussianBlur(layer, (0, 0), 3)
        img[:] = cv2.add(cv2.add(img, layer), glow)


def _rain(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Rain: lower contrast, streaks, a few blurred drops."""
    out = cv2.addWeighted(img, 0.8, np.full_like(img, 120), 0.2, 0)
    layer = np.zeros(img.shape[:2], np.uint8)
    n = int(rng.integers(300, 700))
    xs = rng.uniform(0, W_IMG, n)
    ys = rng.uniform(0, H_IMG, n)
    ln = rng.uniform(15, 60, n)
    ang = rng.normal(1.45, 0.05, n)
    for x, y, L_, a in zip(xs, ys, ln, ang, strict=True):
        cv2.line(
            layer,
            (int(x), int(y)),
            (int(x + L_ * math.cos(a)), int(y + L_ * math.sin(a))),
            int(rng.integers(40, 90)),
            1,
            cv2.LINE_AA,
        )
    out = cv2.add(out, cv2.cvtColor(cv2.GaussianBlur(layer, (0, 0), 0.8), cv2.COLOR_GRAY2BGR))
    for _ in range(int(rng.integers(3, 10))):
        x, y = int(rng.uniform(40, W_IMG - 40)), int(rng.uniform(40, H_IMG - 40))
        r = int(rng.uniform(10, 35))
        x0, y0, x1, y1 = max(x - r, 0), max(y - r, 0), min(x + r, W_IMG), min(y + r, H_IMG)
        out[y0:y1, x0:x1] = cv2.GaussianBlur(out[y0:y1, x0:x1], (0, 0), 5)
    return out


# --------------------------------------------------------------------------------------------
# Visibility
# --------------------------------------------------------------------------------------------


def silhouette_fraction(fr: Frame, corners_scene: np.ndarray, sid: int) -> tuple[float, int]:
    """Visible fraction of a box in this frame: (visible px / silhouette px, silhouette px).

    ``corners_scene``: (8, 3) box corners in the scene frame. Only the part of the silhouette
    inside the image counts (other cameras would see the rest). Returns (nan, 0) if none of
    the silhouette is in the image.
    """
    Xc = (corners_scene - fr.c) @ fr.R_wc
    if Xc[:, 2].max() < Z_NEAR:
        return float("nan"), 0
    if Xc[:, 2].min() < Z_NEAR:
        # clip every face; the silhouette is the hull of the clipped faces' vertices
        faces = [(0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (2, 3, 7, 6), (0, 3, 7, 4), (1, 2, 6, 5)]
        pts = [_clip_near(Xc[list(f)]) for f in faces]
        Xc = np.concatenate([p for p in pts if len(p)], axis=0)
    uv, (x0, x1, y0, y1) = _project_bbox(Xc, fr.K)
    if x1 <= x0 or y1 <= y0:
        return float("nan"), 0
    hull = cv2.convexHull(np.round((uv - [x0, y0]) * 16).astype(np.int32))
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(mask, hull, 1, cv2.LINE_8, 4)
    total = int(mask.sum())
    if total == 0:
        return float("nan"), 0
    vis = int(np.count_nonzero((fr.sid[y0:y1, x0:x1] == sid) & (mask > 0)))
    return min(vis / total, 1.0), total


def box_corners(center: np.ndarray, yaw: float, size: tuple[float, float, float]) -> np.ndarray:
    """(8, 3) corners of a box (devkit order: front 4 then back 4; size w, l, h)."""
    w, length, h = size
    x = np.array([1, 1, 1, 1, -1, -1, -1, -1]) * length / 2
    y = np.array([1, -1, -1, 1, 1, -1, -1, 1]) * w / 2
    z = np.array([1, 1, -1, -1, 1, 1, -1, -1]) * h / 2
    return np.stack([x, y, z], 1) @ _yaw_matrix(yaw).T + center


def ray_visibility(c: np.ndarray, target: np.ndarray, occluders: list[tuple]) -> float:
    """Fraction of sample points of a box seen from ``c`` past other boxes (analytic).

    ``target``: (P, 3) sample points; ``occluders``: list of (center, yaw, (w, l, h)).
    Used for boxes outside the camera image (their tokens do not affect CAM_FRONT work).
    """
    if not occluders:
        return 1.0
    P = target.shape[0]
    seen = np.ones(P, bool)
    d = target - c
    for ctr, yaw, (w, length, h) in occluders:
        R = _yaw_matrix(yaw)
        o = (c - ctr) @ R
        dl = d @ R
        half = np.array([length / 2, w / 2, h / 2])
        dl = np.where(np.abs(dl) < 1e-12, 1e-12, dl)
        t1 = (-half - o) / dl
        t2 = (half - o) / dl
        tmin = np.minimum(t1, t2).max(axis=1)
        tmax = np.maximum(t1, t2).min(axis=1)
        hit = (tmax >= tmin) & (tmin < 0.98) & (tmax > 0.0)
        seen &= ~hit
    return float(seen.mean())
