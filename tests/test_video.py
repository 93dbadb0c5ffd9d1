"""flowmod.video: H.264 MP4 that browsers play, poster, frame strip, the HTML snippet."""

import re
import subprocess

import cv2
import numpy as np
import pytest

from flowmod.report import video


def synthetic_clip(n=12, w=320, h=180):
    """``n`` BGR frames: a red square moving right over a grey ramp; frame i has i/n blue."""
    frames = []
    ramp = np.tile(np.linspace(40, 200, w, dtype=np.uint8), (h, 1))
    for i in range(n):
        f = np.dstack([ramp, ramp, ramp]).copy()
        x = 10 + i * (w - 60) // max(1, n - 1)
        f[h // 3: h // 3 + 40, x: x + 40] = (0, 0, 255)  # BGR red
        frames.append(f)
    return frames


def probe(path):
    """``ffmpeg -i`` stderr: the stream line names codec and pixel format."""
    proc = subprocess.run([video.ffmpeg_exe(), "-hide_banner", "-i", str(path)],
                          capture_output=True, text=True)
    return proc.stderr


def read_back(path):
    import imageio_ffmpeg

    gen = imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24")
    meta = next(gen)
    w, h = meta["size"]
    frames = [np.frombuffer(b, np.uint8).reshape(h, w, 3) for b in gen]
    return meta, frames


def test_write_mp4_is_h264_yuv420p_and_reads_back(tmp_path):
    clip = synthetic_clip()
    out = video.write_mp4(clip, tmp_path / "clip.mp4", fps=6)
    assert out == tmp_path / "clip.mp4" and out.stat().st_size > 1000
    info = probe(out)
    stream = next(line for line in info.splitlines() if "Video:" in line)
    assert "h264" in stream and "yuv420p" in stream and "320x180" in stream
    meta, frames = read_back(out)
    assert meta["size"] == (320, 180) and len(frames) == 12
    assert meta["fps"] == pytest.approx(6, abs=0.01)
    # colours survive the BGR -> RGB hand-over: the square is red in RGB order
    r, g, b = frames[0][180 // 3 + 20, 10 + 20].astype(int)
    assert r > 180 and g < 80 and b < 80
    # faststart: the index (moov) comes before the media data (mdat)
    head = out.read_bytes()
    assert 0 <= head.find(b"moov") < head.find(b"mdat")
    # no temporary file left beside it
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]


def test_odd_sizes_are_padded_to_even(tmp_path):
    clip = [f[:179, :317] for f in synthetic_clip(n=4)]
    out = video.write_mp4(clip, tmp_path / "odd.mp4")
    meta, frames = read_back(out)
    assert meta["size"] == (318, 180) and len(frames) == 4
    assert "318x180" in probe(out)


def test_failing_frame_source_leaves_no_file(tmp_path):
    def frames():
        yield from synthetic_clip(n=3)
        raise RuntimeError("camera unplugged")

    target = tmp_path / "broken.mp4"
    with pytest.raises(RuntimeError, match="camera unplugged"):
        video.write_mp4(frames(), target)
    assert list(tmp_path.iterdir()) == []
    # an existing clip is kept when the rewrite fails
    video.write_mp4(synthetic_clip(n=2), target)
    before = target.read_bytes()
    with pytest.raises(RuntimeError, match="camera unplugged"):
        video.write_mp4(frames(), target)
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["broken.mp4"]


def test_bad_frames_are_refused_with_the_frame_named(tmp_path):
    clip = synthetic_clip(n=3)
    with pytest.raises(ValueError, match="frame 2 is 100x180 px"):
        video.write_mp4([clip[0], clip[1], clip[2][:, :100]], tmp_path / "a.mp4")
    with pytest.raises(ValueError, match="frame 0 has dtype float32"):
        video.write_mp4([clip[0].astype(np.float32)], tmp_path / "a.mp4")
    with pytest.raises(ValueError, match="no frames"):
        video.write_mp4([], tmp_path / "a.mp4")
    with pytest.raises(ValueError, match="ending in .mp4"):
        video.write_mp4(clip, tmp_path / "a.avi")
    assert list(tmp_path.iterdir()) == []


def test_missing_ffmpeg_raises_a_clear_error(tmp_path, monkeypatch):
    import imageio_ffmpeg

    def none():
        raise RuntimeError("No ffmpeg exe could be found")

    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", none)
    with pytest.raises(video.VideoUnavailable, match="IMAGEIO_FFMPEG_EXE"):
        video.write_mp4(synthetic_clip(n=2), tmp_path / "a.mp4")
    assert list(tmp_path.iterdir()) == []


def test_poster_and_strip_shapes(tmp_path):
    clip = synthetic_clip(n=12)
    p = video.poster(clip, tmp_path / "poster.png")
    img = cv2.imread(str(p))
    assert img.shape == (180, 320, 3) and np.array_equal(img, clip[0])
    last = cv2.imread(str(video.poster(clip, tmp_path / "last.png", index=-1)))
    assert np.array_equal(last, clip[-1])

    s = cv2.imread(str(video.frame_strip(clip, tmp_path / "strip.png", n=6, gap=4)))
    assert s.shape == (180, 6 * 320 + 5 * 4, 3)
    assert np.array_equal(s[:, :320], clip[0]) and np.array_equal(s[:, -320:], clip[-1])
    small = cv2.imread(str(video.frame_strip(clip, tmp_path / "s.png", n=3, gap=0, height=90)))
    assert small.shape == (90, 3 * 160, 3)
    few = cv2.imread(str(video.frame_strip(clip[:2], tmp_path / "f.png", n=6, gap=0)))
    assert few.shape == (180, 2 * 320, 3)


def test_side_by_side_keeps_height_and_colour_order():
    frame = np.zeros((180, 320, 3), np.uint8)
    flow = np.zeros((90, 100, 3), np.uint8)
    flow[..., 0] = 255  # RGB red
    out = video.side_by_side(frame, flow)
    assert out.shape == (180, 320 + 200, 3) and out.dtype == np.uint8
    assert tuple(out[50, 400]) == (0, 0, 255)  # red again, now in BGR order
    grey = video.side_by_side(np.zeros((90, 50), np.uint8), flow)
    assert grey.shape == (90, 150, 3)


def test_video_html_names_the_three_files():
    snippet = video.video_html("media/clip.mp4", "media/clip.png", "media/clip-strip.png")
    assert re.search(r'<video[^>]*\bcontrols\b', snippet)
    assert 'preload="none"' in snippet and 'poster="media/clip.png"' in snippet
    assert '<source src="media/clip.mp4" type="video/mp4">' in snippet
    assert re.search(r'<img src="media/clip-strip.png"[^>]*>\s*</video>', snippet)
    escaped = video.video_html('a"b.mp4', "p.png", "s.png")
    assert 'src="a&quot;b.mp4"' in escaped
