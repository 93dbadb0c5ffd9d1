"""flowmod.browser: the headless-Chromium check, on small fake sites built in tmp.

Needs Chromium. Where it is missing the module is skipped, except under CI (``CI`` set), where
``make test`` installs it first (``make browser``), so a missing browser is a failure there.
"""

import struct
import zlib

import cv2
import numpy as np
import pytest

from flowmod.report import browser, video

pytestmark = pytest.mark.slow

try:
    browser.find_chromium()
except browser.ChromiumNotFound as e:
    if not browser.in_ci():
        pytest.skip(f"Chromium is not installed ({e}); `make browser` installs it",
                    allow_module_level=True)


def page(title, body, head=""):
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{title}</title>{head}"
            f"</head><body>{body}</body></html>")


def write(root, rel, text):
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def png(root, rel, w=40, h=30):
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.zeros((h, w, 3), np.uint8)
    img[:, :, 1] = 200
    cv2.imwrite(str(path), img)
    return path


def clip_frames(n=4, w=64, h=48):
    return [np.full((h, w, 3), 30 * i, np.uint8) for i in range(n)]


def make_site(root, broken):
    """A three-page site; ``broken`` adds exactly the four faults the checker must report."""
    png(root, "img/ok.png")
    write(root, "style.css", "body { font-family: sans-serif; }")
    write(root, "app.js", "document.body.dataset.ready = '1';")
    frames = clip_frames()
    video.write_mp4(frames, root / "media/clip.mp4")
    video.poster(frames, root / "media/clip.png")
    video.frame_strip(frames, root / "media/clip-strip.png", n=3)
    head = '<link rel="stylesheet" href="style.css"><script src="app.js" defer></script>'
    links = ('<a href="page2.html">next</a> <a href="page2.html#results">results</a> '
             '<a href="sub/page3.html">deeper</a> <a href="#intro">here</a> '
             '<a href="https://example.org/paper">the paper</a> <a href="#">menu</a>')
    if broken:
        links += ' <a href="missing.html">gone</a>'
    imgs = '<img src="img/ok.png" alt="ok">'
    if broken:
        imgs += ' <img src="img/missing.png" alt="missing">'
    write(root, "index.html", page("home", f'<h1 id="intro">Book</h1><p>{links}</p>{imgs}',
                                   head))
    mp4 = "media/missing.mp4" if broken else "media/clip.mp4"
    remote = '<img src="https://example.com/x.png" alt="remote">' if broken else ""
    write(root, "page2.html", page("two", (
        '<h2 id="results">Results</h2><a href="index.html">home</a> '
        '<a href="sub/page3.html#deep">deep</a>'
        + video.video_html(mp4, "media/clip.png", "media/clip-strip.png") + remote), head))
    write(root, "sub/page3.html", page("three", (
        '<h2 id="deep">Deep</h2><a href="../index.html#intro">home</a>'
        '<img src="../img/ok.png" alt="ok">')))
    # asset folders hold no pages: an HTML file there is not visited
    write(root, "_static/vendor-demo.html", page("x", '<img src="nowhere.png">'))
    return root


def keys(report):
    return {(p.page, p.kind, p.target) for p in report.problems}


def test_clean_site_passes_and_screenshot_is_written(tmp_path):
    site = make_site(tmp_path / "html", broken=False)
    report = browser.check_book(site)
    assert report.ok, report.format()
    assert report.pages == ["index.html", "page2.html", "sub/page3.html"]
    assert report.external_links == [("index.html", "https://example.org/paper")]
    assert all(browser._is_loopback(u) for u in report.requests)
    assert any(u.endswith("/img/ok.png") for u in report.requests)
    assert any(u.endswith("/style.css") for u in report.requests)
    shot = tmp_path / "book-screenshot.png"  # default: beside the book folder
    assert report.screenshot == shot
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    w, h = struct.unpack(">II", shot.read_bytes()[16:24])
    assert (w, h) == (1280, 900)
    assert zlib.crc32(shot.read_bytes()) and shot.stat().st_size > 1000


def test_broken_site_reports_exactly_its_faults(tmp_path):
    site = make_site(tmp_path / "html", broken=True)
    shot = tmp_path / "shots" / "landing.png"
    report = browser.check_book(site, screenshot=shot)
    assert keys(report) == {
        ("index.html", "link", "missing.html"),
        ("index.html", "resource", "img/missing.png"),
        ("page2.html", "external", "https://example.com/x.png"),
        ("page2.html", "resource", "media/missing.mp4"),
    }, report.format()
    assert not report.ok and shot.is_file()
    text = report.format()
    assert "4 problem(s)" in text and "HTTP 404" in text
    assert "https://example.com/x.png" in report.requests  # seen by the browser, not only the DOM
    with pytest.raises(AssertionError, match="missing.html"):
        browser.assert_book_ok(site, screenshot=shot)


def test_requests_made_by_scripts_and_styles_are_caught(tmp_path):
    """What no static parse sees: fetch(), CSS url(), a worker, a missing style and script,
    an anchor that does not exist, a page that is not there."""
    root = tmp_path / "html"
    png(root, "img/ok.png")
    write(root, "worker.js", "fetch('https://worker.example.net/w.json').catch(() => 0);")
    write(root, "style.css", "body { background: url(https://cdn.example.com/bg.png); }")
    head = ('<link rel="stylesheet" href="style.css"><link rel="stylesheet" href="gone.css">'
            '<script src="gone.js"></script>')
    script = ("<script>fetch('https://api.example.net/track').catch(() => 0);"
              "new Worker('worker.js');</script>")
    write(root, "index.html", page("home", (
        '<div style="width:10px;height:10px"></div><a href="two.html#nosuch">bad anchor</a>'
        '<a href="two.html#there">good anchor</a>' + script), head))
    write(root, "two.html", page("two", '<p id="there">x</p><a href="index.html">home</a>'))
    report = browser.check_book(root, screenshot=tmp_path / "s.png")
    assert keys(report) == {
        ("index.html", "external", "https://api.example.net/track"),
        ("index.html", "external", "https://cdn.example.com/bg.png"),
        ("index.html", "external", "https://worker.example.net/w.json"),
        ("index.html", "resource", "gone.css"),
        ("index.html", "resource", "gone.js"),
        ("index.html", "link", "two.html#nosuch"),
    }, report.format()


def test_cli_lists_problems_and_exits_nonzero(tmp_path, capsys):
    site = make_site(tmp_path / "html", broken=True)
    (site / "page2.html").unlink()  # now index.html's links to it break too
    rc = browser.main([str(site), "--screenshot", str(tmp_path / "cli.png"),
                       "--screenshots", str(tmp_path / "shots")])
    err = capsys.readouterr().err
    assert rc == 1
    assert sorted(p.relative_to(tmp_path / "shots").as_posix()
                  for p in (tmp_path / "shots").rglob("*.png")) == ["index.png", "sub/page3.png"]
    assert "index.html: link: missing.html" in err
    assert "index.html: link: page2.html" in err and "index.html: link: page2.html#results" in err
    assert (tmp_path / "cli.png").is_file()
    assert browser.main([str(tmp_path / "nothing-here")]) == 2


def test_cli_does_not_reopen_a_book_unchanged_since_it_passed(tmp_path, capsys):
    site = make_site(tmp_path / "html", broken=False)
    args = [str(site), "--screenshot", str(tmp_path / "s.png"),
            "--screenshots", str(tmp_path / "shots")]
    assert browser.main(args) == 0 and "not reopened" not in capsys.readouterr().out
    assert browser.main(args) == 0 and "not reopened" in capsys.readouterr().out
    (tmp_path / "shots" / "index.png").unlink()
    assert browser.main(args) == 0 and "not reopened" not in capsys.readouterr().out
    assert (tmp_path / "shots" / "index.png").is_file(), "the check ran and made it again"
    (site / "page2.html").unlink()  # an edited book is checked again, and fails
    assert browser.main(args) == 1 and not browser.passed_stamp(site).exists()
    make_site(tmp_path / "html", broken=False)
    assert browser.main(args) == 0
    assert browser.main([*args, "--force"]) == 0
    assert "not reopened" not in capsys.readouterr().out


def png_size(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR", path
    return struct.unpack(">II", data[16:24])


def test_every_page_gets_a_full_page_screenshot(tmp_path):
    site = make_site(tmp_path / "html", broken=False)
    write(site, "07_evaluation.html", page("long", '<p id="top-of-it">x</p>'
                                           '<div style="height:3000px;background:#cde"></div>'))
    shots = tmp_path / "screenshots"
    report = browser.check_book(site, screenshot=tmp_path / "landing.png", screenshots=shots)
    assert report.ok, report.format()
    names = ["index.png", "07_evaluation.png", "page2.png", "sub/page3.png"]
    assert report.screenshots == [shots / n for n in names]
    assert sorted(p.relative_to(shots).as_posix() for p in shots.rglob("*")
                  if p.is_file()) == sorted(names)  # one per page, none for _static/
    for path in report.screenshots:
        w, h = png_size(path)
        assert w == 1280 and h >= 900, (path, w, h)
        img = cv2.imread(str(path))
        assert img is not None and img.shape[:2] == (h, w)
    assert png_size(shots / "07_evaluation.png")[1] >= 3000  # the whole page, not the viewport
    assert png_size(tmp_path / "landing.png") == (1280, 900)  # the landing shot stays as it was
    assert f"4 page screenshots: {shots}" in report.format()


def test_missing_chromium_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv("FLOWMOD_CHROMIUM", str(tmp_path / "no-such-browser"))
    with pytest.raises(browser.ChromiumNotFound, match="FLOWMOD_CHROMIUM"):
        browser.find_chromium()
    monkeypatch.delenv("FLOWMOD_CHROMIUM")
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(browser.ChromiumNotFound, match="make browser"):
        browser.check_book(make_site(tmp_path / "html", broken=False))
