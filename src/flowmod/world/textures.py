"""Procedural textures of the synthetic world (uint8 BGR images, optional alpha).

Optical flow methods need texture at several scales, so every surface mixes structure
(lane paint, paving joints, windows, wheels, lights) with multi-octave value noise. All
functions are pure: the same generator state gives the same image. Resolutions are stated per
function in metres per texture pixel; the renderer maps textures onto planes by homographies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

# --------------------------------------------------------------------------------------------
# Noise
# --------------------------------------------------------------------------------------------


def value_noise(
    rng: np.random.Generator, h: int, w: int, cell: float, periodic: bool = False
) -> np.ndarray:
    """Smooth noise (h, w) float32, roughly unit variance, feature size ``cell`` pixels.

    With ``periodic`` (and h, w multiples of ``cell``) the field tiles seamlessly.
    """
    if cell <= 1:
        return rng.standard_normal((h, w), dtype=np.float32)
    gh = max(int(math.ceil(h / cell)), 1)
    gw = max(int(math.ceil(w / cell)), 1)
    g = rng.standard_normal((gh, gw), dtype=np.float32)
    pad = 2
    g = np.pad(g, pad, mode="wrap" if periodic else "reflect")
    big = cv2.resize(
        g, (int((gw + 2 * pad) * cell), int((gh + 2 * pad) * cell)), interpolation=cv2.INTER_CUBIC
    )
    o = int(pad * cell)
    return np.ascontiguousarray(big[o : o + h, o : o + w])


def fbm(
    rng: np.random.Generator,
    h: int,
    w: int,
    octaves: list[tuple[float, float]],
    periodic: bool = False,
) -> np.ndarray:
    """Sum of value-noise octaves ``[(cell_px, amplitude), ...]``: (h, w) float32."""
    out = np.zeros((h, w), np.float32)
    for cell, amp in octaves:
        out += amp * value_noise(rng, h, w, cell, periodic)
    return out


def to_u8(img: np.ndarray) -> np.ndarray:
    """Clip a float image to [0, 255] and convert to uint8."""
    return np.clip(img, 0, 255).astype(np.uint8)


def colorize(gray: np.ndarray, bgr: tuple[float, float, float]) -> np.ndarray:
    """(h, w) float intensity around 0 plus a base colour -> (h, w, 3) float32."""
    return gray[..., None] + np.asarray(bgr, np.float32)[None, None, :]


def pyramid(img: np.ndarray, min_side: int = 4) -> list[np.ndarray]:
    """Mip levels: level k has size (ceil(w / 2^k), ceil(h / 2^k)), INTER_AREA."""
    levels = [img]
    while min(levels[-1].shape[:2]) >= 2 * min_side:
        h, w = levels[-1].shape[:2]
        levels.append(
            cv2.resize(levels[-1], ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA)
        )
    return levels


# --------------------------------------------------------------------------------------------
# Ground tiles (periodic)
# --------------------------------------------------------------------------------------------

GROUND_RES = 0.02  # m per texture pixel of the ground tiles


def asphalt(rng: np.random.Generator, size: int = 1024, variant: int = 0) -> np.ndarray:
    """Periodic asphalt tile, ``GROUND_RES`` m/px: blotches, grain, speckle, patches, cracks."""
    base = [(92, 92, 95), (80, 82, 84), (104, 102, 100), (86, 88, 94)][variant % 4]
    g = fbm(rng, size, size, [(256, 9), (64, 6), (16, 5), (4, 5), (1, 7)], periodic=True)
    speck = rng.random((size, size), dtype=np.float32)
    g += np.where(speck > 0.985, 28.0, 0.0) - np.where(speck < 0.01, 20.0, 0.0)
    img = colorize(g, base)
    canvas = to_u8(img)
    # repairs and cracks, drawn at wrapped offsets so the tile stays seamless
    overlay = canvas.copy()
    for _ in range(int(rng.integers(1, 4))):
        cx, cy = rng.uniform(0, size, 2)
        w, h = rng.uniform(40, 260, 2)
        ang = rng.uniform(0, 180)
        box = cv2.boxPoints(((float(cx), float(cy)), (float(w), float(h)), float(ang)))
        tone = float(rng.uniform(-25, 12))
        for ox in (-size, 0, size):
            for oy in (-size, 0, size):
                pts = (box + [ox, oy]).astype(np.int32)
                cv2.fillConvexPoly(
                    overlay, pts, tuple(float(np.clip(b + tone, 0, 255)) for b in base)
                )
    canvas = cv2.addWeighted(canvas, 0.45, overlay, 0.55, 0)
    for _ in range(int(rng.integers(3, 9))):
        p = rng.uniform(0, size, 2)
        pts = [p.copy()]
        ang = rng.uniform(0, 2 * math.pi)
        for _ in range(int(rng.integers(5, 25))):
            ang += rng.normal(0, 0.5)
            p = p + 8 * np.array([math.cos(ang), math.sin(ang)])
            pts.append(p.copy())
        arr = np.array(pts, np.float32)
        for ox in (-size, 0, size):
            for oy in (-size, 0, size):
                cv2.polylines(
                    canvas, [(arr + [ox, oy]).astype(np.int32)], False, (40, 40, 42), 1, cv2.LINE_AA
                )
    return canvas


def pavers(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Periodic paving slabs, ``GROUND_RES`` m/px (slabs 0.32-0.64 m, dark joints)."""
    sx, sy = [(32, 32), (32, 16), (16, 16), (32, 32)][int(rng.integers(0, 4))]
    base = np.array(
        [(150, 152, 155), (140, 145, 155), (120, 130, 150), (160, 160, 158)][
            int(rng.integers(0, 4))
        ],
        np.float32,
    )
    tone = rng.normal(0, 9, (size // sy, size // sx)).astype(np.float32)
    tone = cv2.resize(tone, (size, size), interpolation=cv2.INTER_NEAREST)
    g = tone + fbm(rng, size, size, [(128, 6), (8, 4), (1, 6)], periodic=True)
    yy, xx = np.mgrid[0:size, 0:size]
    joint = ((xx % sx) < 2) | ((yy % sy) < 2)
    g = np.where(joint, g - 45, g)
    return to_u8(colorize(g, tuple(base)))


def grass(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Periodic grass tile, ``GROUND_RES`` m/px: blades (streaks), clumps and dirt."""
    g = fbm(rng, size, size, [(128, 10), (32, 8), (4, 6)], periodic=True)
    blades = rng.standard_normal((size // 4, size), dtype=np.float32)
    blades = cv2.resize(blades, (size, size), interpolation=cv2.INTER_LINEAR) * 14
    dirt = value_noise(rng, size, size, 64, periodic=True)
    img = colorize(g + blades, (45, 110, 75))
    img = np.where((dirt > 1.2)[..., None], colorize(g, (70, 95, 115)), img)
    return to_u8(img)


def clouds(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Periodic cloud density tile (size, size) float32 in [0, 1]."""
    c = fbm(rng, size, size, [(128, 1.0), (64, 0.5), (16, 0.25), (4, 0.1)], periodic=True)
    return np.clip((c - 0.2) * 0.8, 0, 1).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Buildings and vegetation
# --------------------------------------------------------------------------------------------

FACADE_RES = 0.05  # m per pixel

WALLS = [
    (60, 70, 150),
    (140, 160, 185),
    (170, 175, 180),
    (210, 215, 220),
    (110, 120, 130),
    (80, 100, 120),
    (150, 130, 110),
    (95, 110, 165),
    (190, 200, 205),
    (120, 85, 60),
]


def facade(
    rng: np.random.Generator, width_m: float, height_m: float, shop: bool, res: float = FACADE_RES
) -> np.ndarray:
    """A building facade (BGR uint8), ``res`` m/px: wall, window grid, shop fronts, grime."""
    w = max(int(round(width_m / res)), 8)
    h = max(int(round(height_m / res)), 8)
    wall = np.array(WALLS[int(rng.integers(0, len(WALLS)))], np.float32)
    g = fbm(rng, h, w, [(200, 8), (40, 6), (6, 4), (1, 5)])
    img = colorize(g, tuple(wall))
    floor_h = rng.uniform(3.0, 3.8) / res
    bay_w = rng.uniform(2.2, 4.5) / res
    win_w = bay_w * rng.uniform(0.4, 0.75)
    win_h = floor_h * rng.uniform(0.4, 0.65)
    glass = np.array(
        [(70, 60, 50), (90, 80, 60), (60, 60, 60), (110, 95, 70)][int(rng.integers(0, 4))],
        np.float32,
    )
    frame_col = tuple(float(c) for c in np.clip(wall * rng.uniform(0.6, 1.4), 0, 255))
    n_floors = int(h // floor_h)
    n_bays = int(w // bay_w)
    x_off = (w - n_bays * bay_w) / 2
    grad = np.linspace(40, -20, 64, dtype=np.float32)
    for f in range(n_floors):
        y_top = h - (f + 1) * floor_h + (floor_h - win_h) * 0.55
        if shop and f == 0:
            continue
        for b in range(n_bays):
            x0 = int(x_off + b * bay_w + (bay_w - win_w) / 2)
            x1, y0, y1 = int(x0 + win_w), int(y_top), int(y_top + win_h)
            if y0 < 0 or x1 <= x0 or y1 <= y0:
                continue
            cv2.rectangle(img, (x0 - 2, y0 - 2), (x1 + 1, y1 + 1), frame_col, -1)
            tone = glass + rng.normal(0, 12, 3).astype(np.float32)
            if rng.random() < 0.08:
                tone = np.array([120, 190, 230], np.float32)  # lit / curtain
            pane = tone[None, None, :] + cv2.resize(grad[:, None], (x1 - x0, y1 - y0))[..., None]
            img[y0:y1, x0:x1] = pane
            if rng.random() < 0.5:  # mullion
                xm = (x0 + x1) // 2
                cv2.line(img, (xm, y0), (xm, y1), frame_col, 2)
    if shop:
        y0 = int(h - floor_h * 0.95)
        y1 = int(h - 0.15 / res)
        gh = max(y1 - y0, 1)
        refl = np.linspace(70, 5, gh, dtype=np.float32)[:, None, None]
        inside = fbm(rng, gh, w, [(30, 14), (6, 9), (1, 4)])[..., None]
        tint = np.array([75, 70, 62], np.float32) + rng.normal(0, 8, 3).astype(np.float32)
        img[y0:y1] = tint + refl + inside
        step = rng.uniform(1.2, 2.6) / res
        for xm in np.arange(rng.uniform(0, step), w, step):
            cv2.line(img, (int(xm), y0), (int(xm), y1), frame_col, 3)
        x = 0.0
        while x < w:
            sw_ = rng.uniform(4, 9) / res
            col = rng.uniform(30, 230, 3)
            sy0 = int(y0 - 0.9 / res)
            cv2.rectangle(
                img, (int(x), sy0), (int(x + sw_ - 6), y0), tuple(float(c) for c in col), -1
            )
            for _ in range(int(rng.integers(3, 9))):  # "lettering"
                lx = int(x + rng.uniform(0.1, 0.8) * sw_)
                cv2.rectangle(
                    img,
                    (lx, sy0 + 4),
                    (lx + int(rng.uniform(4, 14)), y0 - 4),
                    tuple(float(c) for c in 255 - col),
                    -1,
                )
            cv2.rectangle(img, (int(x + sw_ - 8), y0), (int(x + sw_ - 2), y1), frame_col, -1)
            x += sw_
    # horizontal bands and grime
    for f in range(1, n_floors):
        yb = int(h - f * floor_h)
        cv2.line(img, (0, yb), (w, yb), tuple(float(c) * 0.85 for c in frame_col), 2)
    ramp = np.linspace(-8, 12, h, dtype=np.float32)[:, None, None]
    streak = value_noise(rng, 1, w, 12)[0][None, :, None] * 6
    img = img - ramp - streak
    return to_u8(img)


def backdrop(rng: np.random.Generator, width_m: float, height_m: float) -> np.ndarray:
    """A distant skyline or tree line (BGR uint8), 0.25 m/px."""
    if rng.random() < 0.5:
        return facade(rng, width_m, height_m, False, res=0.25)
    w, h = max(int(width_m / 0.25), 8), max(int(height_m / 0.25), 8)
    g = fbm(rng, h, w, [(40, 12), (8, 10), (1, 8)])
    return to_u8(colorize(g, (50, 80, 60)))


def foliage(rng: np.random.Generator, size: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """A tree crown billboard: (BGR uint8 (size, size, 3), alpha uint8 (size, size))."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    r = np.hypot((xx - size / 2) / (size * 0.46), (yy - size * 0.45) / (size * 0.44))
    n = fbm(rng, size, size, [(24, 0.35), (6, 0.2), (2, 0.12)])
    alpha = ((1.0 - r + n) > 0.15).astype(np.uint8) * 255
    g = fbm(rng, size, size, [(16, 14), (4, 12), (1, 14)]) - 20 * (yy / size)
    base = [(40, 100, 60), (35, 90, 75), (45, 120, 70), (30, 75, 55)][int(rng.integers(0, 4))]
    return to_u8(colorize(g, base)), alpha


def bark(rng: np.random.Generator, w: int = 16, h: int = 128) -> np.ndarray:
    """Trunk texture (BGR uint8), vertical streaks."""
    g = cv2.resize(rng.standard_normal((h // 8, w), dtype=np.float32), (w, h)) * 14
    return to_u8(colorize(g, (45, 60, 80)))


def hedge(rng: np.random.Generator, w: int, h: int, wall: bool) -> np.ndarray:
    """A hedge (leafy) or a low wall (panels) texture, 0.05 m/px."""
    if wall:
        g = fbm(rng, h, w, [(20, 6), (1, 5)])
        img = colorize(g, (150, 160, 170))
        for x in range(0, w, 40):
            cv2.line(img, (x, 0), (x, h), (110, 115, 120), 1)
        return to_u8(img)
    g = fbm(rng, h, w, [(10, 14), (3, 12), (1, 12)])
    return to_u8(colorize(g, (40, 95, 55)))


def metal(rng: np.random.Generator, w: int = 8, h: int = 128) -> np.ndarray:
    """Grey pole texture."""
    g = fbm(rng, h, w, [(16, 6), (1, 4)])
    return to_u8(colorize(g, (115, 118, 120)))


# --------------------------------------------------------------------------------------------
# Vehicles and pedestrians (box faces)
# --------------------------------------------------------------------------------------------

VEHICLE_RES = 0.025  # m per pixel

PAINTS = [
    (235, 235, 235),
    (25, 25, 28),
    (170, 172, 175),
    (110, 110, 112),
    (140, 60, 30),
    (40, 40, 170),
    (60, 110, 40),
    (180, 180, 170),
    (30, 60, 110),
    (200, 200, 205),
    (50, 150, 210),
    (90, 60, 50),
]


def _body(rng, w: int, h: int, col) -> np.ndarray:
    g = fbm(rng, h, w, [(40, 4), (8, 3), (1, 3)])
    shade = np.linspace(14, -14, h, dtype=np.float32)[:, None]
    return colorize(g + shade, col)


def _rect(img, x0, y0, x1, y1, col) -> None:
    cv2.rectangle(img, (int(x0), int(y0)), (int(x1), int(y1)), tuple(float(c) for c in col), -1)


def _glass(img, x0, y0, x1, y1, rng) -> None:
    x0, y0, x1, y1 = int(x0), int(y0), int(x1), int(y1)
    if x1 <= x0 or y1 <= y0:
        return
    base = np.array([55, 45, 40], np.float32) + rng.normal(0, 6, 3).astype(np.float32)
    grad = np.linspace(45, -5, y1 - y0, dtype=np.float32)[:, None, None]
    refl = value_noise(rng, y1 - y0, x1 - x0, 10)[..., None] * 10
    img[y0:y1, x0:x1] = base + grad + refl


def _wheel(img, cx, cy, r) -> None:
    cv2.circle(img, (int(cx), int(cy)), int(r), (22, 22, 24), -1, cv2.LINE_AA)
    cv2.circle(img, (int(cx), int(cy)), int(r * 0.55), (150, 150, 155), -1, cv2.LINE_AA)
    cv2.circle(img, (int(cx), int(cy)), int(r * 0.2), (60, 60, 62), -1, cv2.LINE_AA)


def _livery(category: str, rng) -> tuple[tuple, tuple | None]:
    if category == "vehicle.emergency.ambulance":
        return (235, 238, 240), (30, 60, 220) if rng.random() < 0.5 else (20, 160, 240)
    if category == "vehicle.emergency.police":
        return (
            ((240, 240, 240), (150, 40, 10))
            if rng.random() < 0.6
            else ((20, 20, 20), (240, 240, 240))
        )
    if category == "vehicle.construction":
        return (20, 170, 230) if rng.random() < 0.6 else (20, 120, 230), (20, 20, 20)
    if category.startswith("vehicle.bus"):
        return PAINTS[int(rng.integers(0, len(PAINTS)))], tuple(rng.uniform(30, 230, 3))
    return PAINTS[int(rng.integers(0, len(PAINTS)))], None


#: Texture pixels per metre of the vehicle textures.
_PX = 1.0 / VEHICLE_RES
#: Tyres, bumpers and grilles (BGR).
_DARK = (28, 28, 30)


@dataclass
class _Faces:
    """A vehicle's face textures being painted, float32 BGR at ``VEHICLE_RES`` m/px: ``side``
    (H, L, 3) with the vehicle's front at the right, ``front`` and ``back`` (H, W, 3), ``top``
    (W, L, 3); the body colour and the livery stripe colour (BGR; None: no stripe)."""

    side: np.ndarray
    front: np.ndarray
    back: np.ndarray
    top: np.ndarray
    body: tuple
    stripe: tuple | None

    @property
    def size_px(self) -> tuple[int, int, int]:
        """(L, W, H): the vehicle's length, width and height in texture pixels."""
        return self.side.shape[1], self.front.shape[1], self.side.shape[0]

    @property
    def wheel(self) -> tuple[float, float]:
        """The wheel radius and the row of the wheel centres on the side (px)."""
        H = self.side.shape[0]
        r_wheel = min(0.36 * _PX, H * 0.22)
        return r_wheel, H - r_wheel * 0.95


def vehicle_faces(
    rng: np.random.Generator, category: str, size: tuple[float, float, float]
) -> dict[str, np.ndarray]:
    """Textures of a vehicle box's faces at ``VEHICLE_RES`` m/px.

    Keys: ``side`` (front of the vehicle at the texture's right; mirrored for the other side),
    ``front``, ``back``, ``top``. BGR uint8.
    """
    w_m, l_m, h_m = size
    L = max(int(round(l_m / VEHICLE_RES)), 8)
    W = max(int(round(w_m / VEHICLE_RES)), 8)
    H = max(int(round(h_m / VEHICLE_RES)), 8)
    body, stripe = _livery(category, rng)
    side = _body(rng, L, H, body)
    front = _body(rng, W, H, body)
    back = _body(rng, W, H, body)
    top = _body(rng, L, W, body)
    f = _Faces(side, front, back, top, body, stripe)
    if category in ("vehicle.car", "vehicle.emergency.police", "vehicle.emergency.ambulance"):
        _paint_car(f, rng, category)
    elif category in ("vehicle.truck", "vehicle.construction", "vehicle.trailer"):
        _paint_truck(f, rng, category, l_m)
    elif category.startswith("vehicle.bus"):
        _paint_bus(f, rng, category)
    else:  # two-wheelers: dark frame and a rider
        _paint_two_wheeler(f, rng)
    if not category.startswith(("vehicle.bicycle", "vehicle.motorcycle")):
        _paint_lights(f)
    faces = (("side", f.side), ("front", f.front), ("back", f.back), ("top", f.top))
    return {k: to_u8(v) for k, v in faces}


def _paint_car(f: _Faces, rng: np.random.Generator, category: str) -> None:
    """Cars, police cars and ambulances (boxy vans): windows, wheels, livery stripes."""
    side, front, back, top, body, stripe = f.side, f.front, f.back, f.top, f.body, f.stripe
    L, W, H = f.size_px
    r_wheel, wy = f.wheel
    boxy = category == "vehicle.emergency.ambulance"
    g0 = int(H * (0.12 if boxy else 0.08))
    g1 = int(H * (0.45 if boxy else 0.50))
    # side windows (front at right); boxy vans have windows only in the cab
    wx0 = int(L * (0.72 if boxy else 0.2))
    _glass(side, wx0, g0, L * 0.86, g1, rng)
    if not boxy:
        for xp in np.linspace(wx0, L * 0.86, 3)[1:-1]:
            _rect(side, xp - 3, g0, xp + 3, g1, body)
    cv2.line(
        side, (int(L * 0.5), g1), (int(L * 0.5), int(H * 0.85)), tuple(c * 0.7 for c in body), 1
    )
    _rect(side, 0, H * 0.86, L, H, _DARK)
    for fx in (0.17, 0.8):
        _wheel(side, L * fx, wy, r_wheel)
    _glass(front, W * 0.06, H * 0.08, W * 0.94, H * 0.42, rng)
    _glass(back, W * 0.1, H * 0.1, W * 0.9, H * (0.45 if not boxy else 0.35), rng)
    _rect(top, L * 0.25, W * 0.12, L * 0.8, W * 0.88, tuple(c * 0.85 for c in body))
    if stripe is not None:
        _rect(side, 0, H * 0.55, L, H * 0.68, stripe)
        if boxy or category == "vehicle.emergency.police":
            for k, x in enumerate(range(0, L, max(int(0.5 * _PX), 4))):
                if k % 2 == 0:
                    _rect(side, x, H * 0.55, x + 0.5 * _PX, H * 0.68, (240, 240, 240))
        _rect(front, 0, H * 0.5, W, H * 0.6, stripe)
        _rect(back, 0, H * 0.55, W, H * 0.65, stripe)
        _rect(top, L * 0.45, W * 0.1, L * 0.55, W * 0.45, (30, 30, 230))
        _rect(top, L * 0.45, W * 0.55, L * 0.55, W * 0.9, (230, 60, 30))


def _paint_truck(f: _Faces, rng: np.random.Generator, category: str, l_m: float) -> None:
    """Trucks, construction vehicles and trailers (``l_m`` long, m): cargo box, cab, axles."""
    side, front, back, top, body, stripe = f.side, f.front, f.back, f.top, f.body, f.stripe
    L, W, H = f.size_px
    r_wheel, wy = f.wheel
    cab = 0.0 if category == "vehicle.trailer" else min(2.4 * _PX / L, 0.4)
    cargo = tuple(rng.uniform(120, 250, 3)) if rng.random() < 0.6 else body
    _rect(side, 0, 0, L * (1 - cab), H * 0.8, cargo)
    for y in np.arange(H * 0.1, H * 0.8, 0.4 * _PX):
        cv2.line(
            side, (0, int(y)), (int(L * (1 - cab)), int(y)), tuple(c * 0.85 for c in cargo), 1
        )
    if rng.random() < 0.5:
        _rect(side, L * 0.15, H * 0.2, L * 0.55, H * 0.5, tuple(rng.uniform(20, 230, 3)))
    if cab > 0:
        _glass(side, L * (1 - cab * 0.8), H * 0.1, L * 0.97, H * 0.42, rng)
        _glass(front, W * 0.06, H * 0.1, W * 0.94, H * 0.4, rng)
    else:
        _rect(front, 0, 0, W, H * 0.8, cargo)
    _rect(back, W * 0.03, H * 0.03, W * 0.97, H * 0.8, tuple(c * 0.9 for c in cargo))
    cv2.line(back, (W // 2, int(H * 0.05)), (W // 2, int(H * 0.8)), _DARK, 2)
    _rect(side, 0, H * 0.8, L, H, _DARK)
    if stripe is not None:  # hazard stripes
        for x in range(0, L, 16):
            cv2.line(side, (x, int(H * 0.72)), (x + 8, int(H * 0.8)), stripe, 4)
    n_axles = 2 if l_m < 8 else 3
    xs = [0.12, 0.3, 0.85] if n_axles == 3 else [0.15, 0.82]
    if category == "vehicle.trailer":
        xs = [0.08, 0.2]
    for fx in xs:
        _wheel(side, L * fx, wy, r_wheel * 1.15)
    _rect(top, 0, 0, L, W, tuple(c * 0.9 for c in cargo))


def _paint_bus(f: _Faces, rng: np.random.Generator, category: str) -> None:
    """Rigid and bendy buses: a band of windows, a door, the joint, destination sign, roof."""
    side, front, back, top, body, stripe = f.side, f.front, f.back, f.top, f.body, f.stripe
    L, W, H = f.size_px
    r_wheel, wy = f.wheel
    _glass(side, L * 0.03, H * 0.18, L * 0.97, H * 0.55, rng)
    for x in np.arange(L * 0.03, L * 0.97, 1.3 * _PX):
        _rect(side, x - 3, H * 0.18, x + 3, H * 0.55, body)
    _glass(side, L * 0.86, H * 0.18, L * 0.93, H * 0.9, rng)  # door
    if category == "vehicle.bus.bendy":
        xm = L * 0.5
        for k in range(8):
            cv2.line(side, (int(xm - 20 + 5 * k), 0), (int(xm - 20 + 5 * k), H), _DARK, 2)
    if stripe is not None:
        _rect(side, 0, H * 0.6, L, H * 0.7, stripe)
    _rect(side, 0, H * 0.9, L, H, _DARK)
    for fx in [0.12, 0.4, 0.6, 0.85] if category == "vehicle.bus.bendy" else [0.18, 0.8]:
        _wheel(side, L * fx, wy, r_wheel * 1.1)
    _glass(front, W * 0.05, H * 0.08, W * 0.95, H * 0.55, rng)
    _rect(front, W * 0.15, H * 0.02, W * 0.85, H * 0.08, (20, 200, 255))  # destination
    _glass(back, W * 0.15, H * 0.15, W * 0.85, H * 0.4, rng)
    _rect(top, 0, 0, L, W, (170, 170, 170))
    for x in np.arange(L * 0.2, L * 0.8, 3 * _PX):
        _rect(top, x, W * 0.25, x + 1.5 * _PX, W * 0.75, (140, 140, 145))


def _paint_two_wheeler(f: _Faces, rng: np.random.Generator) -> None:
    """Motorcycles and bicycles: new faces, a dark frame with two wheels and a rider."""
    L, W, H = f.size_px
    r_wheel, _wy = f.wheel
    side = _body(rng, L, H, (40, 40, 45))
    rider = tuple(rng.uniform(20, 200, 3))
    _rect(side, L * 0.35, H * 0.0, L * 0.65, H * 0.6, rider)
    cv2.circle(side, (int(L * 0.5), int(H * 0.08)), int(H * 0.08), (60, 60, 70), -1)
    for fx in (0.15, 0.85):
        _wheel(side, L * fx, H - r_wheel * 0.9, r_wheel)
    f.side = side
    f.front = _body(rng, W, H, rider)
    f.back = f.front.copy()
    f.top = _body(rng, L, W, rider)


def _paint_lights(f: _Faces) -> None:
    """Head and tail lights, number plates, grille and bumpers of a four-wheeler."""
    front, back = f.front, f.back
    _L, W, H = f.size_px
    ly0, ly1 = H * 0.55, H * 0.66
    _rect(front, W * 0.05, ly0, W * 0.2, ly1, (235, 245, 250))
    _rect(front, W * 0.8, ly0, W * 0.95, ly1, (235, 245, 250))
    _rect(front, W * 0.28, ly0, W * 0.72, H * 0.75, (35, 35, 38))
    _rect(front, W * 0.4, H * 0.78, W * 0.6, H * 0.85, (230, 230, 230))
    _rect(back, W * 0.04, ly0, W * 0.18, ly1, (30, 30, 200))
    _rect(back, W * 0.82, ly0, W * 0.96, ly1, (30, 30, 200))
    _rect(back, W * 0.4, H * 0.7, W * 0.6, H * 0.78, (230, 230, 230))
    _rect(front, 0, H * 0.9, W, H, (28, 28, 30))
    _rect(back, 0, H * 0.9, W, H, (28, 28, 30))


def pedestrian_faces(
    rng: np.random.Generator, size: tuple[float, float, float]
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Silhouette billboards of a pedestrian box: {face: (BGR, alpha)} at ``VEHICLE_RES``."""
    w_m, l_m, h_m = size
    H = max(int(round(h_m / VEHICLE_RES)), 16)
    out = {}
    shirt = tuple(float(c) for c in rng.uniform(20, 230, 3))
    trousers = tuple(float(c) for c in rng.uniform(20, 120, 3))
    skin = (90, 130, 180) if rng.random() < 0.5 else (60, 90, 130)
    for face, width_m in (("front", w_m), ("side", l_m)):
        W = max(int(round(width_m / VEHICLE_RES)), 8)
        img = np.zeros((H, W, 3), np.float32) + 128
        alpha = np.zeros((H, W), np.uint8)
        head_r = H * 0.065
        cx = W / 2
        cv2.circle(img, (int(cx), int(head_r * 1.3)), int(head_r), skin, -1)
        cv2.circle(alpha, (int(cx), int(head_r * 1.3)), int(head_r), 255, -1)
        tw = W * (0.8 if face == "front" else 0.55)
        _rect(img, cx - tw / 2, H * 0.14, cx + tw / 2, H * 0.52, shirt)
        _rect(alpha, cx - tw / 2, H * 0.14, cx + tw / 2, H * 0.52, (255,))
        lw = W * (0.3 if face == "front" else 0.35)
        for dx in (-0.22, 0.22) if face == "front" else (-0.12, 0.12):
            x = cx + dx * W
            _rect(img, x - lw / 2, H * 0.52, x + lw / 2, H, trousers)
            _rect(alpha, x - lw / 2, H * 0.52, x + lw / 2, H, (255,))
        img += fbm(rng, H, W, [(6, 6), (1, 4)])[..., None]
        out[face] = (to_u8(img), alpha)
    top = np.full(
        (max(int(l_m / VEHICLE_RES), 4), max(int(w_m / VEHICLE_RES), 4), 3), shirt, np.float32
    )
    out["top"] = (to_u8(top), np.full(top.shape[:2], 255, np.uint8))
    out["back"] = out["front"]
    return out
