"""Short clips for the book: H.264 MP4 with a poster frame and a still-frame strip as fallback.

A notebook writes a clip three ways and displays :func:`video_html`::

    write_mp4(frames, media / "clip.mp4")      # H.264, yuv420p, faststart: plays in browsers
    poster(frames, media / "clip.png")         # what the page shows before "play"
    frame_strip(frames, media / "clip-strip.png")  # fallback where video cannot play
    display(HTML(video_html("media/clip.mp4", "media/clip.png", "media/clip-strip.png")))

Frames follow the OpenCV convention: (H, W, 3) uint8 BGR. Encoding uses the ffmpeg binary that
``imageio-ffmpeg`` ships (or ``$IMAGEIO_FFMPEG_EXE``); if there is none, :func:`write_mp4`
raises :class:`VideoUnavailable` and the caller shows the strip alone.
"""

from __future__ import annotations

import hashlib
import html
import os
import subprocess
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path

import cv2
import numpy as np

from flowmod.artefacts import atomic_path

__all__ = [
    "VideoUnavailable",
    "ffmpeg_exe",
    "frame_strip",
    "poster",
    "side_by_side",
    "video_html",
    "write_mp4",
]


class VideoUnavailable(RuntimeError):
    """No ffmpeg able to write H.264 here; the message says how to get one."""


def ffmpeg_exe() -> str:
    """Path of the ffmpeg binary bundled with ``imageio-ffmpeg`` (or ``$IMAGEIO_FFMPEG_EXE``)."""
    try:
        import imageio_ffmpeg
    except ImportError as e:
        raise VideoUnavailable(
            "imageio-ffmpeg is not installed, so there is no ffmpeg to write MP4: run "
            "`make env` (it is pinned in environment/requirements.txt) or set IMAGEIO_FFMPEG_EXE"
        ) from e
    try:
        exe = imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError as e:
        raise VideoUnavailable(
            f"imageio-ffmpeg found no ffmpeg binary ({e}); reinstall it (`make env`) or point "
            "IMAGEIO_FFMPEG_EXE at an ffmpeg built with libx264"
        ) from e
    if not (exe and os.access(exe, os.X_OK)):
        raise VideoUnavailable(f"ffmpeg {exe!r} is not executable; reinstall imageio-ffmpeg")
    return exe


def _as_bgr_frame(frame: np.ndarray, index: int) -> np.ndarray:
    """Check one frame: (H, W, 3) uint8 (or (H, W) uint8 grey, made BGR)."""
    a = np.asarray(frame)
    if a.dtype != np.uint8:
        raise ValueError(f"frame {index} has dtype {a.dtype}; frames must be uint8 (0..255)")
    if a.ndim == 2:
        a = cv2.cvtColor(a, cv2.COLOR_GRAY2BGR)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"frame {index} has shape {a.shape}; frames must be (H, W, 3) BGR")
    return a


def _pad_even(a: np.ndarray) -> np.ndarray:
    """Pad bottom/right by one replicated pixel where H or W is odd (yuv420p needs even sizes)."""
    h, w = a.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return a
    return cv2.copyMakeBorder(a, 0, h % 2, 0, w % 2, cv2.BORDER_REPLICATE)


def write_mp4(frames: Iterable[np.ndarray], path: str | os.PathLike[str], fps: float = 6,
              crf: int = 23) -> Path:
    """Encode ``frames`` ((H, W, 3) uint8 BGR, all the same size) as an H.264 MP4 at ``fps``.

    The file is yuv420p with the index at the front (``-movflags +faststart``) so browsers
    start playing before it is fully loaded; an odd H or W is padded by one pixel to even.
    Written atomically: if a frame (or ffmpeg) fails, no file is left at ``path``. ``crf`` is
    x264's quality (lower is better and larger). Returns ``path``.
    """
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"{path}: write_mp4 writes MP4; give a path ending in .mp4")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    exe = ffmpeg_exe()
    it = iter(frames)
    try:
        first = _pad_even(_as_bgr_frame(next(it), 0))
    except StopIteration:
        raise ValueError(f"{path}: no frames to write") from None
    h, w = first.shape[:2]
    with atomic_path(path) as tmp, tempfile.TemporaryFile() as log:
        cmd = [exe, "-hide_banner", "-loglevel", "error", "-y",
               "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}", "-r", f"{fps}",
               "-i", "-", "-an", "-c:v", "libx264", "-preset", "medium", "-crf", str(crf),
               "-pix_fmt", "yuv420p", "-movflags", "+faststart", "-f", "mp4", str(tmp)]
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                stderr=log)
        assert proc.stdin is not None
        n = 0
        try:
            frame = first
            while True:
                if frame.shape[:2] != (h, w):
                    raise ValueError(
                        f"frame {n} is {frame.shape[1]}x{frame.shape[0]} px but frame 0 is "
                        f"{w}x{h} px (after padding to even); all frames must be the same size"
                    )
                try:
                    proc.stdin.write(np.ascontiguousarray(frame[:, :, ::-1]).tobytes())
                except BrokenPipeError:
                    break  # ffmpeg stopped: its log says why (below)
                n += 1
                try:
                    frame = _pad_even(_as_bgr_frame(next(it), n))
                except StopIteration:
                    break
            try:
                proc.stdin.close()
            except BrokenPipeError:
                pass
            rc = proc.wait()
        except BaseException:
            proc.kill()
            proc.wait()
            raise
        if rc != 0:
            log.seek(0)
            msg = log.read().decode(errors="replace").strip()[-2000:]
            hint = (" (this ffmpeg has no libx264: install imageio-ffmpeg, whose binary has it)"
                    if "libx264" in msg else "")
            raise VideoUnavailable(f"ffmpeg failed writing {path} (exit {rc}){hint}:\n{msg}")
    return path


def _frame_list(frames: Sequence[np.ndarray] | np.ndarray | Iterable[np.ndarray]) -> list:
    out = list(frames)
    if not out:
        raise ValueError("no frames given")
    return out


def poster(frames: Sequence[np.ndarray] | np.ndarray, path: str | os.PathLike[str],
           index: int = 0) -> Path:
    """Save frame ``index`` (default the first) of ``frames`` ((H, W, 3) uint8 BGR) as PNG."""
    fl = _frame_list(frames)
    if not -len(fl) <= index < len(fl):
        raise IndexError(f"poster frame {index} out of range for {len(fl)} frames")
    return _write_png(path, _as_bgr_frame(fl[index], index))


def frame_strip(frames: Sequence[np.ndarray] | np.ndarray, path: str | os.PathLike[str],
                n: int = 6, gap: int = 4, height: int | None = None) -> Path:
    """Save ``n`` evenly spaced frames side by side as one PNG (the fallback for a video).

    Frames are (H, W, 3) uint8 BGR; first and last frames are always included (fewer than
    ``n`` frames: all of them). ``gap`` px of white separate them; ``height`` (px) rescales
    each frame first. The strip is ``height or H`` px high and ``k*W' + (k-1)*gap`` px wide.
    """
    fl = _frame_list(frames)
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    idx = np.unique(np.linspace(0, len(fl) - 1, min(n, len(fl))).round().astype(int))
    tiles = [_as_bgr_frame(fl[i], int(i)) for i in idx]
    if height is not None:
        tiles = [cv2.resize(t, (max(1, round(t.shape[1] * height / t.shape[0])), height),
                            interpolation=cv2.INTER_AREA) for t in tiles]
    h = tiles[0].shape[0]
    if any(t.shape[0] != h for t in tiles):
        raise ValueError("frames differ in height; give height= to rescale them")
    sep = np.full((h, gap, 3), 255, np.uint8)
    parts: list[np.ndarray] = []
    for i, t in enumerate(tiles):
        if i and gap:
            parts.append(sep)
        parts.append(t)
    return _write_png(path, np.hstack(parts))


def _write_png(path: str | os.PathLike[str], image: np.ndarray) -> Path:
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"{path}: give a path ending in .png")
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"OpenCV could not encode {path}")
    data = buf.tobytes()
    if not (path.is_file() and path.read_bytes() == data):  # the same picture: left alone
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
    return path


def side_by_side(frame_bgr: np.ndarray, flow_rgb: np.ndarray) -> np.ndarray:
    """A frame ((H, W, 3) uint8 BGR, or (H, W) grey) beside its flow picture ((h, w, 3) RGB,
    as :func:`flowmod.flow.flow_to_color` draws it), as one (H, W + w', 3) uint8 BGR frame.

    The flow picture is rescaled to height H (aspect kept) if its height differs.
    """
    left = _as_bgr_frame(frame_bgr, 0)
    right = np.asarray(flow_rgb)
    if right.dtype != np.uint8 or right.ndim != 3 or right.shape[2] != 3:
        raise ValueError(f"flow_rgb must be (H, W, 3) uint8 RGB, got {right.dtype} {right.shape}")
    right = cv2.cvtColor(right, cv2.COLOR_RGB2BGR)
    h = left.shape[0]
    if right.shape[0] != h:
        w = max(1, round(right.shape[1] * h / right.shape[0]))
        right = cv2.resize(right, (w, h), interpolation=cv2.INTER_AREA)
    return np.hstack([left, right])


def video_html(mp4_rel: str, poster_rel: str, strip_rel: str, alt: str = "frames of the clip",
               width: int | None = None) -> str:
    """HTML that plays ``mp4_rel`` (poster ``poster_rel``), with the strip image as fallback.

    Paths are URLs relative to the page (e.g. ``"media/clip.mp4"``); the files must end up
    in the built book beside the page. ``width`` (px) caps the displayed width.
    """
    q = lambda s: html.escape(str(s), quote=True)  # noqa: E731
    style = f"max-width:{int(width)}px;width:100%" if width else "max-width:100%"
    return (
        f'<video controls preload="none" playsinline poster="{q(poster_rel)}" '
        f'style="{style}">\n'
        f'  <source src="{q(mp4_rel)}" type="video/mp4">\n'
        f'  <img src="{q(strip_rel)}" alt="{q(alt)}" style="max-width:100%">\n'
        f"</video>"
    )


def publish(frames: Sequence[np.ndarray], media_dir: str | os.PathLike[str], name: str,
            fps: float = 6) -> str:
    """Write ``name``.mp4, ``name``-poster.png and ``name``-strip.png into ``media_dir`` and
    return the HTML that shows them from a book page (paths ``media/<file>``: the book copies
    ``<run_dir>/figures/media`` to ``<html>/media``). Without ffmpeg, only the strip."""
    media_dir = Path(media_dir)
    poster(frames, media_dir / f"{name}-poster.png")
    frame_strip(frames, media_dir / f"{name}-strip.png")
    mp4, stamp = media_dir / f"{name}.mp4", media_dir / f".{name}.mp4.sha256"
    digest = hashlib.sha256(str(fps).encode())
    for fr in frames:
        digest.update(np.ascontiguousarray(fr).tobytes())
    if not (mp4.is_file() and stamp.is_file() and stamp.read_text() == digest.hexdigest()):
        try:  # the same frames: the video is left alone
            write_mp4(frames, mp4, fps=fps)
        except VideoUnavailable:
            return f'<img src="media/{name}-strip.png" alt="frames of {html.escape(name)}">'
        with atomic_path(stamp) as tmp:
            tmp.write_text(digest.hexdigest())
    return video_html(f"media/{name}.mp4", f"media/{name}-poster.png", f"media/{name}-strip.png")
