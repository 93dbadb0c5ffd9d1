"""Check the built book in headless Chromium: pages load, nothing is broken, nothing leaves.

    python -m flowmod.report.browser build/html [--screenshot PNG] [--screenshots DIR]

:func:`check_book` serves the book folder on 127.0.0.1 (a free port) and opens every page in
the system Chromium, driven by Playwright (no browser is downloaded). It reports:

* a page that does not load with HTTP 200;
* an element's file (``<img>``, video/audio/source/track, poster, ``<script src>``,
  ``<iframe>``, resource ``<link>``) that does not resolve (images must also decode), and any
  other request of the page that fails or answers HTTP >= 400;
* an internal link to a missing file, or to an anchor that is no ``id``/``name`` there
  (external links are listed, not followed);
* any request of the page, its frames or workers, and any resource element, outside
  127.0.0.1/localhost (``data:``/``blob:`` allowed). Such requests are aborted; a
  host-resolver rule stops anything the routing misses.

It saves a 1280x900 PNG of ``index.html`` and, given a folder, a full-page PNG of every page.
The CLI records a passing check beside the book (:func:`passed_stamp`) and does not reopen a
book whose files and screenshots are unchanged since (``make book`` with nothing changed).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import http.server
import json
import os
import shutil
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from html.parser import HTMLParser
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from playwright.sync_api import BrowserContext, Request, Response, Route, sync_playwright
from playwright.sync_api import Error as PlaywrightError
from playwright.sync_api import TimeoutError as PlaywrightTimeout

from flowmod.artefacts import atomic_path, file_digest, fingerprint, write_json
from flowmod.paths import repo_root

__all__ = ["BookReport", "BrowserError", "ChromiumNotFound", "Problem", "assert_book_ok",
           "check_book", "find_chromium", "in_ci", "main"]

#: Hosts that count as "this machine".
LOOPBACK = {"127.0.0.1", "localhost", "::1", "[::1]"}
#: URL schemes a page may use without a network request.
INLINE_SCHEMES = {"data", "blob", "about"}
#: ``<link rel=...>`` values that make the browser fetch ``href`` (or connect to its origin).
RESOURCE_RELS = ["apple-touch-icon", "dns-prefetch", "icon", "manifest", "mask-icon",
                 "modulepreload", "preconnect", "prefetch", "preload", "prerender", "shortcut",
                 "stylesheet"]
#: Top-level folders of a Sphinx build that hold assets, not pages.
ASSET_DIRS = {"_static", "_vendor", "_images", "_sources", "_downloads"}
VIEWPORT = {"width": 1280, "height": 900}
#: Playwright adds the headless switches (and repeats some of these); these suit a machine whose
#: network is closed, and are explicit so as not to depend on Playwright's defaults.
CHROMIUM_FLAGS = [
    "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--disable-quic",
    "--no-first-run", "--disable-background-networking", "--disable-component-update",
    "--disable-sync", "--no-proxy-server",
    # a safety net: even a request the routing did not see cannot leave the machine
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1, EXCLUDE localhost",
]

# Runs in each loaded page: what the checks need from the live DOM.
_COLLECT_JS = """
async ([imgTimeoutMs, resourceRels]) => {
  const all = (sel) => Array.from(document.querySelectorAll(sel));
  const imgs = all('img');
  for (const i of imgs) if (i.loading === 'lazy') i.loading = 'eager';
  await Promise.all(imgs.map((i) => i.complete || new Promise((r) => {
    for (const ev of ['load', 'error']) i.addEventListener(ev, r, {once: true});
    setTimeout(r, imgTimeoutMs);
  })));
  const abs = (v) => { try { return new URL(v, document.baseURI).href; } catch (e) { return v; } };
  const item = (e, attr, tag) => ({tag: tag || e.tagName.toLowerCase(),
    url: abs(e.getAttribute(attr)), width: e.naturalWidth, complete: e.complete});
  const pick = (sel, attr, tag) => all(sel).filter((e) => e.getAttribute(attr))
    .map((e) => item(e, attr, tag));
  const resources = [...pick('[src]', 'src'), ...pick('video[poster]', 'poster', 'video poster'),
                     ...pick('object[data]', 'data')];
  const links = pick('a[href], area[href]', 'href');
  for (const e of all('link[href]')) {
    const rels = (e.getAttribute('rel') || '').toLowerCase().split(/\\s+/);
    const rel = rels.find((r) => resourceRels.includes(r));
    (rel ? resources : links).push(item(e, 'href', rel ? 'link rel=' + rel : 'link'));
  }
  const ids = [...all('[id]').map((e) => e.id), ...all('a[name]').map((e) => e.name)];
  return {resources, links, ids};
}
"""


class ChromiumNotFound(RuntimeError):
    """No Chromium binary: install it (``make browser`` or ``apt-get install chromium``)."""


class BrowserError(RuntimeError):
    """Chromium failed to start or to answer (the message holds Playwright's account)."""


@dataclass(frozen=True, order=True)
class Problem:
    """One thing wrong with the book.

    ``page``: the page, relative to the book folder (``"index.html"``); ``kind``: ``"page"``
    (did not load), ``"resource"`` (an element's file does not resolve), ``"request"`` (another
    request of the page failed), ``"link"`` (broken internal link or anchor), ``"external"``
    (a request or resource outside localhost); ``target``: the URL, relative to the book
    folder for local ones (``"img/x.png"``, ``"a.html#sec"``); ``detail``: what was seen.
    """

    page: str
    kind: str
    target: str
    detail: str = field(default="", compare=False)

    def __str__(self) -> str:
        return f"{self.page}: {self.kind}: {self.target}" + (f" ({self.detail})" if self.detail
                                                               else "")


@dataclass
class BookReport:
    """What :func:`check_book` found. ``ok`` when there are no problems."""

    html_dir: Path
    pages: list[str] = field(default_factory=list)
    problems: list[Problem] = field(default_factory=list)
    #: every URL the pages requested (not data:/blob:), in first-seen order
    requests: list[str] = field(default_factory=list)
    #: (page, url) of links that leave the book: listed, not followed
    external_links: list[tuple[str, str]] = field(default_factory=list)
    #: (page, message) of uncaught JavaScript exceptions: listed, not failures
    js_errors: list[tuple[str, str]] = field(default_factory=list)
    #: the landing page's PNG
    screenshot: Path | None = None
    #: a full-page PNG per page, when a folder was given
    screenshots: list[Path] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.problems

    def format(self) -> str:
        """A readable summary: one line per problem."""
        lines = [f"browser check of {self.html_dir}: {len(self.pages)} pages, "
                 f"{len(self.requests)} distinct requests, {len(self.external_links)} external "
                 f"links (not followed), {self.seconds:.1f} s"]
        if self.problems:
            lines.append(f"{len(self.problems)} problem(s):")
            lines += [f"  {p}" for p in sorted(self.problems)]
        else:
            lines.append("no problems")
        if self.js_errors:
            lines.append(f"{len(self.js_errors)} JavaScript exception(s) (not counted):")
            lines += [f"  {page}: {msg}" for page, msg in self.js_errors]
        if self.screenshot:
            lines.append(f"screenshot: {self.screenshot}")
        if self.screenshots:
            lines.append(f"{len(self.screenshots)} page screenshots: {self.screenshots[0].parent}")
        return "\n".join(lines)


def in_ci() -> bool:
    """True under CI (``$CI`` set and not 0/false/no): there a missing Chromium is a failure,
    since ``make test`` installs it first (``make browser``), not a reason to skip."""
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def find_chromium() -> str:
    """Path of a Chromium binary: ``$FLOWMOD_CHROMIUM``, else ``chromium`` etc. on PATH."""
    env = os.environ.get("FLOWMOD_CHROMIUM")
    if env:
        if os.path.isfile(env) and os.access(env, os.X_OK):
            return env
        raise ChromiumNotFound(f"FLOWMOD_CHROMIUM={env!r} is not an executable file")
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    raise ChromiumNotFound(
        "no Chromium found (looked for $FLOWMOD_CHROMIUM, chromium, chromium-browser, "
        "google-chrome): install it with `make browser` or `sudo apt-get install -y chromium`, "
        "or set FLOWMOD_CHROMIUM to the binary"
    )


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - stdlib's name
        pass  # the browser records the requests


@contextlib.contextmanager
def _serve(html_dir: Path) -> Iterator[str]:
    """Serve ``html_dir`` on 127.0.0.1 (a free port) in a thread; yields the base URL."""
    handler = functools.partial(_QuietHandler, directory=str(html_dir))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, name="book-server", daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=5)


class _IdParser(HTMLParser):
    """Anchors (``id``, ``<a name>``) of an HTML file the browser did not open."""

    def __init__(self) -> None:
        super().__init__()
        self.ids: set[str] = set()

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.ids.update(v for k, v in attrs if v and (k == "id" or (tag == "a" and k == "name")))


def _pages(html_dir: Path) -> list[str]:
    """Every .html page under ``html_dir`` (not asset folders), ``index.html`` first."""
    pages = sorted(p.relative_to(html_dir).as_posix() for p in html_dir.rglob("*.html")
                   if p.relative_to(html_dir).parts[0] not in ASSET_DIRS)
    return sorted(pages, key=lambda p: p != "index.html")


def _is_loopback(url: str) -> bool:
    parts = urlsplit(url)
    if parts.scheme in INLINE_SCHEMES:
        return True
    return parts.scheme in ("http", "https", "ws", "wss") and (parts.hostname or "") in LOOPBACK


class _BookCheck:
    """One run of :func:`check_book`: a browser context on the book server, what was found."""

    def __init__(self, html_dir: Path, base: str, context: BrowserContext, report: BookReport,
                 page_timeout: float, idle_timeout: float):
        self.html_dir, self.base, self.netloc = html_dir, base, urlsplit(base).netloc
        self.report, self.page_timeout, self.idle_timeout = report, page_timeout, idle_timeout
        self.api = context.request  # asks the book server for files no request fetched
        self.current = ""  # the page being visited, and what its requests did:
        self.urls: list[str] = []  # every URL requested, in order
        self.failed: list[tuple[str, str]] = []  # (url, why) of requests that failed
        self.found: dict[tuple[str, str], Problem] = {}  # (page, target) -> first problem
        self.seen_requests: dict[str, None] = {}
        self.ids: dict[str, set[str]] = {}  # page -> anchors in its live DOM
        self.links: list[tuple[str, str, str]] = []  # (page, tag, url), checked at the end
        self.status_cache: dict[str, int] = {}
        # whatever leaves localhost is logged and aborted; the rest is only logged
        context.route(lambda url: not _is_loopback(url), self._block)
        context.route_web_socket(lambda url: not _is_loopback(url),
                                 lambda ws: (self.urls.append(ws.url), ws.close()))
        context.on("request", lambda r: self.urls.append(r.url))
        context.on("response", self._on_response)
        context.on("requestfailed", self._on_failed)
        self.page = context.new_page()
        self.page.on("websocket", lambda ws: self.urls.append(ws.url))
        self.page.on("pageerror", lambda e: self.report.js_errors.append(
            (self.current, (f"{e.name}: {e.message}" if e.name else e.message).splitlines()[0])))

    def _block(self, route: Route) -> None:
        self.urls.append(route.request.url)  # reported even if no request event came
        route.abort("blockedbyclient")

    def _on_response(self, resp: Response) -> None:
        if resp.status >= 400:
            self.failed.append((resp.url, f"HTTP {resp.status}"))

    def _on_failed(self, req: Request) -> None:
        if req.failure != "net::ERR_ABORTED":  # a request the page itself dropped
            self.failed.append((req.url, f"request failed: {req.failure}"))

    def rel(self, url: str) -> str:
        """A URL as the report shows it: relative to the book folder when local."""
        parts = urlsplit(url)
        if parts.netloc != self.netloc or parts.scheme not in ("http", "https"):
            return url
        out = unquote(parts.path).lstrip("/")
        return out + (f"#{unquote(parts.fragment)}" if parts.fragment else "")

    def add(self, page: str, kind: str, url: str, detail: str) -> None:
        """Record a problem, once per (page, target)."""
        key = (page, self.rel(url) if kind == "link" else self.rel(url.split("#")[0]))
        self.found.setdefault(key, Problem(page, kind, key[1], detail))

    def head(self, url: str) -> int:
        """HTTP status of ``url`` on the book server (0: no answer), asked once."""
        key = url.split("#")[0]
        if key not in self.status_cache:
            try:
                self.status_cache[key] = self.api.head(key, timeout=10_000).status
            except PlaywrightError:
                self.status_cache[key] = 0
        return self.status_cache[key]

    def visit(self, name: str, shot: Path | None, full: Path | None) -> None:
        """Open page ``name``, let it settle, check it; save PNGs to ``shot``/``full``."""
        self.current, self.urls, self.failed = name, [], []
        url = f"{self.base}/{name}"
        try:
            resp = self.page.goto(url, wait_until="load", timeout=self.page_timeout * 1000)
        except PlaywrightError as e:
            why = "did not load in time" if isinstance(e, PlaywrightTimeout) else "failed"
            self.add(name, "page", url, f"navigation {why}: {str(e).splitlines()[0]}")
            return
        with contextlib.suppress(PlaywrightTimeout):  # late requests, e.g. MathJax fonts
            self.page.wait_for_load_state("networkidle", timeout=self.idle_timeout * 1000)
        if resp is None or resp.status != 200:
            self.add(name, "page", url, f"HTTP {resp.status if resp else 'no response'}")
            return
        dom = self.page.evaluate(_COLLECT_JS, [int(self.page_timeout * 1000), RESOURCE_RELS])
        self.ids[name] = set(dom["ids"])
        self.check_resources(name, dom["resources"])
        self.check_requests(name)  # after: a known element names a problem better
        self.links.extend((name, item["tag"], item["url"]) for item in dom["links"])
        if shot is not None:
            with atomic_path(shot) as tmp:
                self.page.screenshot(path=tmp, type="png")
            self.report.screenshot = shot
        if full is not None:
            with atomic_path(full) as tmp:
                self.page.screenshot(path=tmp, type="png", full_page=True)
            self.report.screenshots.append(full)

    def check_requests(self, page: str) -> None:
        """Every request the page made stays on localhost and succeeds."""
        for u in self.urls:
            if urlsplit(u).scheme not in INLINE_SCHEMES:
                self.seen_requests.setdefault(u, None)
            if not _is_loopback(u):
                self.add(page, "external", u, "the page requested a URL outside localhost")
        for u, why in self.failed:
            # /favicon.ico: the browser's own guess where no <link rel=icon> names one
            if _is_loopback(u) and urlsplit(u).path != "/favicon.ico":
                self.add(page, "request", u, why)

    def check_resources(self, page: str, items: list[dict[str, Any]]) -> None:
        """Files named by the page's elements, fetched by the browser or not, resolve."""
        for item in items:
            u, tag = item["url"], item["tag"]
            if urlsplit(u).scheme in INLINE_SCHEMES:
                continue
            if not _is_loopback(u):
                self.add(page, "external", u, f"<{tag}> loads from outside localhost")
            elif tag in ("link rel=dns-prefetch", "link rel=preconnect"):
                continue
            elif urlsplit(u).netloc != self.netloc:
                self.add(page, "resource", u, f"<{tag}> points at another local server")
            elif (status := self.head(u)) != 200:
                self.add(page, "resource", u, f"<{tag}> HTTP {status or 'no answer'}")
            elif tag == "img" and not item["width"] and \
                    not urlsplit(u).path.lower().endswith(".svg"):
                why = "does not decode" if item["complete"] else "did not load in time"
                self.add(page, "resource", u, f"<img> {why} (naturalWidth 0)")

    def check_links(self) -> None:
        """Internal links point at files of the book and at anchors that exist there."""
        for page, tag, u in self.links:
            parts = urlsplit(u)
            if parts.scheme in ("mailto", "tel", "javascript", *INLINE_SCHEMES):
                continue
            if parts.scheme in ("http", "https") and (parts.hostname or "") not in LOOPBACK:
                if (page, u) not in self.report.external_links:
                    self.report.external_links.append((page, u))
                continue
            if parts.netloc != self.netloc or parts.scheme not in ("http", "https"):
                self.add(page, "link", u, f"<{tag}> points outside the book")
                continue
            path = self.html_dir / unquote(parts.path).lstrip("/")
            target = path / "index.html" if path.is_dir() else path
            if not target.is_file():
                self.add(page, "link", u, f"<{tag}>: no such file in the book")
                continue
            frag = unquote(parts.fragment)
            if not frag or frag == "top" or frag.startswith(":~:") or \
                    target.suffix.lower() not in (".html", ".htm"):
                continue
            target_page = target.relative_to(self.html_dir).as_posix()
            if target_page not in self.ids:
                parser = _IdParser()
                parser.feed(target.read_text(errors="replace"))
                self.ids[target_page] = parser.ids
            if frag not in self.ids[target_page]:
                self.add(page, "link", u, f"<{tag}>: no id or name {frag!r} on {target_page}")


def check_book(html_dir: str | os.PathLike[str], screenshot: str | os.PathLike[str] | None = None,
               screenshots: str | os.PathLike[str] | None = None, *, page_timeout: float = 30,
               idle_timeout: float = 5, chromium: str | None = None) -> BookReport:
    """Open every page of the built book ``html_dir`` in headless Chromium; see the module doc.

    ``screenshot``: PNG of ``index.html``, 1280x900 px (default: ``book-screenshot.png`` beside
    ``html_dir``).
    ``screenshots``: folder for a full-page PNG (1280 px wide) of every page, named after it
    (``07_evaluation.html`` -> ``07_evaluation.png``); default: none.
    ``page_timeout`` (s): how long a page may take to fire ``load``; ``idle_timeout`` (s): how
    long to wait after that for the network to go quiet (no request for 0.5 s).
    ``chromium``: the browser binary (default :func:`find_chromium`). Raises
    :class:`ChromiumNotFound` or :class:`BrowserError`; what is wrong with the book goes into
    the report.
    """
    t0 = time.monotonic()
    html_dir = Path(html_dir).resolve()
    if not html_dir.is_dir():
        raise FileNotFoundError(f"{html_dir} is not a folder: build the book first (`make book`)")
    exe = chromium or find_chromium()
    shot = Path(screenshot) if screenshot is not None else html_dir.parent / "book-screenshot.png"
    report = BookReport(html_dir=html_dir, pages=_pages(html_dir))
    if "index.html" not in report.pages:
        report.problems.append(Problem("index.html", "page", "index.html",
                                       "the book has no landing page"))
    with _serve(html_dir) as base:
        try:
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=exe, args=CHROMIUM_FLAGS)
                # no service workers: their requests would bypass the routing
                context = browser.new_context(viewport=VIEWPORT, service_workers="block")
                check = _BookCheck(html_dir, base, context, report, page_timeout, idle_timeout)
                for name in report.pages:
                    full = Path(screenshots, name).with_suffix(".png") if screenshots else None
                    check.visit(name, shot if name == "index.html" else None, full)
                browser.close()
        except PlaywrightError as e:
            raise BrowserError(f"Chromium ({exe}) through Playwright: {e}") from e
    check.check_links()
    report.problems.extend(check.found.values())
    report.requests = list(check.seen_requests)
    report.seconds = time.monotonic() - t0
    return report


def assert_book_ok(html_dir: str | os.PathLike[str],
                   screenshot: str | os.PathLike[str] | None = None,
                   screenshots: str | os.PathLike[str] | None = None) -> BookReport:
    """:func:`check_book`, raising ``AssertionError`` with the readable report on any problem."""
    report = check_book(html_dir, screenshot, screenshots)
    if not report.ok:
        raise AssertionError(report.format())
    return report


def passed_stamp(html_dir: Path) -> Path:
    """Where the CLI records the last passing check of ``html_dir`` (beside it)."""
    return html_dir.parent / f".{html_dir.name}.browser-check.json"


def _chromium_or_none() -> str | None:
    try:
        return find_chromium()
    except ChromiumNotFound:
        return None


def check_key(html_dir: Path, outputs: list[Path | None]) -> dict[str, Any]:
    """What a passing check vouches for: every file of the book by content (``_sources``,
    downloads a page only links to, and ``.doctrees``, Sphinx's cache, by name: Sphinx
    rewrites them on every build), the browser binary, and the screenshots it wrote."""
    files = sorted(p for p in html_dir.rglob("*") if p.is_file())
    by_name = {"_sources", ".doctrees"}
    shots = [p for o in outputs if o is not None
             for p in ([o] if o.suffix == ".png" else sorted(o.rglob("*.png")))]
    rel = [p.relative_to(html_dir) for p in files]
    return {"book": fingerprint([(r.as_posix(), "" if r.parts[0] in by_name
                                  else file_digest(p)) for r, p in zip(rel, files, strict=True)],
                                 n=64),
            "chromium": _chromium_or_none(),
            "screenshots": fingerprint([(str(p), file_digest(p)) for p in shots
                                        if p.is_file()], n=64),
            "outputs": [str(o) for o in outputs]}


def main(argv: list[str] | None = None) -> int:
    """CLI: 0 if the book is fine, 1 with the list of problems, 2 if it cannot be checked.
    A book whose every file, and whose screenshots, are as when it last passed is not
    opened again (``--force`` reopens it)."""
    ap = argparse.ArgumentParser(prog="python -m flowmod.report.browser",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("html_dir", type=Path, nargs="?", default=repo_root() / "build" / "html",
                    help="the built book (default build/html)")
    ap.add_argument("--screenshot", type=Path, default=None, metavar="PNG",
                    help="PNG of index.html (default: book-screenshot.png beside html_dir)")
    ap.add_argument("--screenshots", type=Path, default=None, metavar="DIR",
                    help="folder for a full-page PNG of every page, named after it "
                         "(default: none; `make book` uses build/screenshots)")
    ap.add_argument("--page-timeout", type=float, default=30, help="seconds per page load")
    ap.add_argument("--force", action="store_true",
                    help="check even a book unchanged since it last passed")
    args = ap.parse_args(argv)
    html = args.html_dir.resolve()
    shot = args.screenshot or html.parent / "book-screenshot.png"
    stamp, outputs = passed_stamp(html), [shot, args.screenshots]
    if not args.force and html.is_dir() and stamp.is_file():
        with contextlib.suppress(ValueError):
            if json.loads(stamp.read_text()) == check_key(html, outputs):
                print(f"browser check: {html} is as when it last passed (its files and "
                      "screenshots): not reopened; --force reopens it")
                return 0
    try:
        report = check_book(args.html_dir, args.screenshot, args.screenshots,
                            page_timeout=args.page_timeout)
    except (ChromiumNotFound, BrowserError, FileNotFoundError) as e:
        print(f"{type(e).__name__}: {e}", file=sys.stderr)
        return 2
    print(report.format(), file=sys.stdout if report.ok else sys.stderr)
    if report.ok:
        write_json(stamp, check_key(html, outputs))
    else:
        stamp.unlink(missing_ok=True)
    return 0 if report.ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
