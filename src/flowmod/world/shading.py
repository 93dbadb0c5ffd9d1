"""Colours of a rendered frame: ground and sky, road paint, contact shadows, camera effects.

Holds texture sampling and face brightness, the deferred shading of the pixels that still show
ground or sky (materials, lane paint, fog, clouds), soft contact shadows under vehicles and the
camera model of :func:`finish` (night lights, rain, exposure, vignetting, blur, noise).
"""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np

from flowmod.world import scene as ws
from flowmod.world import textures as wt
from flowmod.world.geometry import (
    H_IMG,
    SID_GROUND,
    SID_SKY,
    W_IMG,
    Z_NEAR,
    Frame,
    SceneGeometry,
    clip_near,
    kinv,
    pixel_uv,
    visible_sphere,
)

# --------------------------------------------------------------------------------------------
# Texture sampling and face brightness
# --------------------------------------------------------------------------------------------


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


def face_shade(normal_w: np.ndarray, sun: np.ndarray, look: dict) -> float:
    """Lambertian face brightness relative to the ground (1.0); ``normal_w`` any length."""
    if look["weather"] in ("clear", "after_rain"):
        amb, dif = 0.5, 0.6
    else:
        amb, dif = 0.8, 0.2
    n = normal_w / (math.sqrt(float(normal_w @ normal_w)) + 1e-12)
    lit = amb + dif * max(float(n @ sun), 0.0) + (0.1 if n[2] > 0.5 else 0.0)
    return lit / (amb + dif * max(float(sun[2]), 0.0))


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


def shade_background(geo: SceneGeometry, fr: Frame) -> None:
    """Colour the pixels still showing ground or sky (deferred shading)."""
    look = geo.look
    horizon, zenith, cloudiness, fog_dist, wet = WEATHER_LOOK[look["weather"]]
    horizon = np.array(horizon, np.float32)
    zenith = np.array(zenith, np.float32)
    img = fr.img.reshape(-1, 3)
    M = (fr.R_wc @ kinv(fr.K)).astype(np.float32)
    sid = fr.sid.ravel()

    gi = np.flatnonzero(sid == SID_GROUND)
    if gi.size:
        _put_rows(img, gi, _ground_colours(geo, fr, M, gi, horizon, fog_dist, wet))

    si = np.flatnonzero(sid == SID_SKY)
    if si.size:
        _put_rows(img, si, _sky_colours(geo, M, si, horizon, zenith, cloudiness))


def _put_rows(dst: np.ndarray, idx: np.ndarray, rows: np.ndarray) -> None:
    """``dst[idx] = rows`` for pixels (N, 3) and (n, 3): contiguous uint8 BGR rows move as
    one 3-byte item each (the same bytes, about 2.5 times faster than row indexing)."""
    if (dst.dtype == rows.dtype == np.uint8 and dst.shape[1:] == rows.shape[1:] == (3,)
            and dst.flags.c_contiguous and rows.flags.c_contiguous):
        dst.view("V3")[:, 0][idx] = rows.view("V3")[:, 0]
    else:
        dst[idx] = rows


def _ray_dirs(M: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scene-frame ray directions (dx, dy, dz), each (n,) float32, of the pixels ``idx``
    (flat indices); ``M`` = R_wc K^-1 (3, 3) float32, so the rays have camera z = 1."""
    U, V = pixel_uv()
    u, v = U[idx], V[idx]
    dx = M[0, 0] * u + M[0, 1] * v + M[0, 2]
    dy = M[1, 0] * u + M[1, 1] * v + M[1, 2]
    dz = M[2, 0] * u + M[2, 1] * v + M[2, 2]
    return dx, dy, dz


def _ground_colours(
    geo: SceneGeometry,
    fr: Frame,
    M: np.ndarray,
    gi: np.ndarray,
    horizon: np.ndarray,
    fog_dist: float,
    wet: float,
) -> np.ndarray:
    """Colours (n, 3) uint8 BGR of the ground pixels ``gi`` (flat indices): material
    textures, lane paint, wetness (factor ``wet``) and fog towards ``horizon`` (``fog_dist``
    m)."""
    f = float(fr.K[0, 0])
    dx, dy, dz = _ray_dirs(M, gi)
    t = 1.0 / fr.invz.ravel()[gi]  # depth Z (m) = ray parameter (rays have camera z = 1)
    gx = np.float32(fr.c[0]) + t * dx
    gy = np.float32(fr.c[1]) + t * dy
    norm = np.sqrt(dx * dx + dy * dy + dz * dz)
    sin_g = np.maximum(-dz / norm, np.float32(0.02))
    fp = (t * norm / np.float32(f)) / np.sqrt(sin_g)  # pixel footprint on the ground, m
    coords = [ws.road_coords(r, gx, gy) for r in geo.roads]
    region = _ground_regions(geo, coords, gi.size)
    colf = _ground_albedo(geo, region, fp, gx, gy)  # (3, n): one contiguous row a channel
    white, yellow, kerb = _road_paint(geo, coords, fp)
    for alpha, paint in (
        (white * 0.85, (222, 226, 228)),
        (yellow, (40, 165, 210)),
        (kerb, (170, 172, 175)),
    ):
        idx = np.flatnonzero(alpha > 0)
        if idx.size:
            a = alpha[idx]
            for ch, p in zip(colf, np.array(paint, np.float32), strict=True):
                c = ch[idx]
                ch[idx] = c + a * (p - c)
    if wet != 1.0:
        colf *= np.where(region == 2, np.float32(0.9), np.float32(wet))
    fog = 1.0 - np.exp(-t * norm * np.float32(1.0 / fog_dist))
    colf += fog * (horizon[:, None] - colf)
    return _planes_to_u8_rows(colf)


def _planes_to_u8_rows(planes: np.ndarray) -> np.ndarray:
    """Channel planes (3, n) float32 clipped to [0, 255] and truncated to uint8 pixel rows
    (n, 3), C-contiguous. The shading works on planes, not (n, 3) rows: per element the
    same float32 operations, without numpy's slow broadcasting over a last axis of 3."""
    u8 = np.clip(planes, 0, 255).astype(np.uint8)
    n = u8.shape[1]
    return cv2.merge([c.reshape(n, 1) for c in u8]).reshape(n, 3)  # interleaved by OpenCV


def _ground_regions(geo: SceneGeometry, coords: list, n: int) -> np.ndarray:
    """Material of ``n`` ground points, (n,) int8: 0 asphalt, 1 sidewalk, 2 verge.

    ``coords``: per road the (along, across) arrays of the points (m).
    """
    region = np.full(n, 2, np.int8)
    for r, (_, acr) in zip(geo.roads, coords, strict=True):
        region[(acr >= -r["walk"][0]) & (acr <= r["walk"][1]) & (region == 2)] = 1
    for r, (_, acr) in zip(geo.roads, coords, strict=True):
        region[(acr >= -r["kerb"][0]) & (acr <= r["kerb"][1])] = 0
    return region


def _ground_albedo(
    geo: SceneGeometry, region: np.ndarray, fp: np.ndarray, gx: np.ndarray, gy: np.ndarray
) -> np.ndarray:
    """Texture colours (3, n) float32 BGR planes of ground points (gx, gy) (m) of materials
    ``region``, sampled at the mip level of their footprint ``fp`` (m), with a slow
    brightness modulation."""
    level = np.floor(np.log2(np.maximum(fp * np.float32(1.0 / wt.GROUND_RES), 1.0))).astype(
        np.int8
    )
    col = np.empty((region.size, 3), np.uint8)
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
            _put_rows(col, idx_m[sel], _sample(
                levels[k], (u0[sel] + 0.5) * s - 0.5, (v0[sel] + 0.5) * s - 0.5, True
            ))
    colf = np.ascontiguousarray(col.T, dtype=np.float32)
    mval = _sample(
        geo.modulation_field(),
        np.mod(gx * np.float32(1.25), 256),
        np.mod(gy * np.float32(1.25), 256),
        True,
    )[:, 0]
    colf *= 1.0 + 0.12 * mval
    return colf


def _sky_colours(
    geo: SceneGeometry,
    M: np.ndarray,
    si: np.ndarray,
    horizon: np.ndarray,
    zenith: np.ndarray,
    cloudiness: float,
) -> np.ndarray:
    """Colours (n, 3) uint8 BGR of the sky pixels ``si`` (flat indices): a gradient from
    ``horizon`` to ``zenith`` with clouds (density scaled by ``cloudiness``)."""
    dx, dy, dz = _ray_dirs(M, si)
    norm = np.sqrt(dx * dx + dy * dy + dz * dz)
    e = np.clip(dz / norm, 0.0, 1.0)
    mix = np.sqrt(e)
    col = horizon[:, None] * (1 - mix) + zenith[:, None] * mix  # (3, n) planes
    dzc = np.maximum(dz, 0.02 * norm)
    cu = np.mod(187.5 * dx / dzc, 512)
    cv = np.mod(187.5 * dy / dzc, 512)
    dens = _sample(geo.cloud_field(), cu, cv, True)[:, 0] * np.float32(cloudiness)
    dens *= np.clip(e * 6.0, 0, 1)
    cloud_col = np.array(
        [235, 235, 235] if geo.look["weather"] != "night" else [50, 45, 40], np.float32
    )
    col += dens * (cloud_col[:, None] - col)
    return _planes_to_u8_rows(col)


# --------------------------------------------------------------------------------------------
# Contact shadows
# --------------------------------------------------------------------------------------------


def contact_shadows(fr: Frame, posed) -> None:
    """Darken the ground under vehicles (soft footprint), only where the ground is seen."""
    for obj, R, ctr in posed:
        a = obj.agent
        if a is None or a["kind"] != "vehicle":
            continue
        if not visible_sphere(np.array([ctr[0], ctr[1], 0.0]), obj.radius, fr.R_wc, fr.c, fr.K):
            continue
        uv = _footprint_uv(fr, a["size"], R, ctr)
        box = None if uv is None else _shadow_box(uv)
        if box is None:
            continue
        x0, x1, y0, y1 = box
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(
            mask, np.round((uv - [x0, y0]) * 16).astype(np.int32), 255, cv2.LINE_AA, 4
        )
        mask = (mask.astype(np.float32) / 255.0) * (fr.sid[y0:y1, x0:x1] == SID_GROUND)
        roi = fr.img[y0:y1, x0:x1]
        roi[:] = (roi * (1.0 - 0.45 * mask[..., None])).astype(np.uint8)


def _footprint_uv(fr: Frame, size, R: np.ndarray, ctr: np.ndarray) -> np.ndarray | None:
    """The pixel polygon (n, 2) of a vehicle's shadow footprint (its ``size`` (w, l, h) m
    and 0.2-0.25 m around, 1 cm above the ground at pose ``R``, ``ctr``), clipped at the
    near plane; None when fewer than 3 corners remain in front of the camera."""
    w, length, _ = size
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
        return None
    poly = clip_near(Xc)
    if len(poly) < 3:
        return None
    uvw = poly @ fr.K.T
    return uvw[:, :2] / uvw[:, 2:3]


def _shadow_box(uv: np.ndarray) -> tuple[int, int, int, int] | None:
    """The pixel box (x0, x1, y0, y1), end-exclusive, one pixel around the polygon ``uv``
    (n, 2) px and clipped to the image; None when nothing of it is left in the image."""
    x0 = max(int(uv[:, 0].min()) - 1, 0)
    x1 = min(int(uv[:, 0].max()) + 2, W_IMG)
    y0 = max(int(uv[:, 1].min()) - 1, 0)
    y1 = min(int(uv[:, 1].max()) + 2, H_IMG)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, x1, y0, y1


# --------------------------------------------------------------------------------------------
# Camera effects
# --------------------------------------------------------------------------------------------


@lru_cache(maxsize=2)
def _noise_bank(which: int) -> np.ndarray:
    rng = np.random.default_rng(20240611 + which)
    return rng.standard_normal((H_IMG + 96, W_IMG + 96, 3), dtype=np.float32)


@lru_cache(maxsize=2)
def _vignette(k_key: tuple) -> np.ndarray:
    """The vignetting gain of every pixel, (H, W, 3) float32, the same in each channel
    (stored per channel: a frame multiplies by it without broadcasting; 17 MB a camera)."""
    K = np.array(k_key).reshape(3, 3)
    v, u = np.mgrid[0:H_IMG, 0:W_IMG].astype(np.float32)
    r2 = ((u - K[0, 2]) ** 2 + (v - K[1, 2]) ** 2) / (K[0, 0] ** 2)
    gain = (1.0 / (1.0 + r2) ** 2)[..., None].astype(np.float32) ** 0.35
    return np.ascontiguousarray(np.broadcast_to(gain, (H_IMG, W_IMG, 3)))


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
    # per channel: one float32 product each, as f *= wb would broadcast (3 times faster)
    cv2.multiply(f, (float(wb[0]), float(wb[1]), float(wb[2]), 0.0), dst=f)
    f = cv2.GaussianBlur(f, (0, 0), 0.6)
    sigma = look["noise"] * (2.2 if weather == "night" else 1.0)
    o1 = rng.integers(0, 96, 2)
    o2 = rng.integers(0, 96, 2)
    n1 = _noise_bank(0)[o1[0] : o1[0] + H_IMG, o1[1] : o1[1] + W_IMG]
    n2 = _noise_bank(1)[o2[0] : o2[0] + H_IMG, o2[1] : o2[1] + W_IMG]
    # in place, one scratch buffer: the same float32 operations as f += a * n, fewer copies
    tmp = np.multiply(n1, np.float32(sigma * 0.8))
    f += tmp
    f += np.multiply(n2, np.float32(sigma * 0.6), out=tmp)
    return np.clip(f, 0, 255, out=f).astype(np.uint8)


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
