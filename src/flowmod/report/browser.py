"""Check the built book in headless Chromium: pages load, nothing is broken, nothing leaves.

    python -m flowmod.report.browser build/html [--screenshot build/book-screenshot.png]

:func:`check_book` serves the book folder on a loopback HTTP server (127.0.0.1, a free port),
opens every page in headless Chromium, driven over the Chrome DevTools Protocol (CDP), and
reports:

* a page that does not load with HTTP 200;
* an ``<img>``, ``<video>``/``<audio>``/``<source>``/``<track>``, video poster, ``<script src>``,
  ``<iframe>`` or resource ``<link>`` (stylesheet, icon, preload, ...) that does not resolve
  (HTTP 200; images must also decode, i.e. ``naturalWidth > 0``), and any other request of the
  page that failed;
* an internal link (``<a>``, ``<area>``, ``<link rel=next/prev/...>``) to a file that does not
  exist, or to an anchor that is not an ``id``/``name`` on the target page; external links are
  listed in the report, not followed;
* every request the page makes (seen through CDP ``Network`` events of the page and of its
  frames and workers) whose URL is not ``127.0.0.1``/``localhost`` (``data:`` and ``blob:``
  allowed), plus any resource element pointing outside, even one the browser did not fetch
  yet (``preload="none"``). Chromium's own background traffic is not the page's and is
  switched off; a host-resolver rule also stops any outside request from leaving the machine.

It also saves a PNG screenshot of ``index.html`` (default: ``<html_dir>/../book-screenshot.png``,
i.e. ``build/book-screenshot.png``). Chromium is found as ``$FLOWMOD_CHROMIUM``, ``chromium``,
``chromium-browser``, ``google-chrome``; ``make browser`` (or ``apt-get install chromium``)
installs it.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import functools
import http.server
import json
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from html.parser import HTMLParser
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from flowmod.artefacts import atomic_path

__all__ = [
    "BookReport",
    "BrowserError",
    "ChromiumNotFound",
    "Problem",
    "assert_book_ok",
    "check_book",
    "find_chromium",
    "in_ci",
    "main",
]

#: Hosts that count as "this machine".
LOOPBACK = {"127.0.0.1", "localhost", "::1", "[::1]"}
#: URL schemes a page may use without a network request.
INLINE_SCHEMES = {"data", "blob", "about"}
#: ``<link rel=...>`` values that make the browser fetch ``href`` (or connect to its origin).
RESOURCE_RELS = {"stylesheet", "icon", "shortcut", "apple-touch-icon", "mask-icon", "manifest",
                 "preload", "modulepreload", "prefetch", "prerender", "preconnect",
                 "dns-prefetch"}
#: Top-level folders of a Sphinx build that hold assets, not pages.
ASSET_DIRS = {"_static", "_vendor", "_images", "_sources", "_downloads"}

CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
    "--disable-quic", "--no-first-run", "--no-default-browser-check",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--disable-default-apps", "--disable-extensions", "--disable-domain-reliability",
    "--disable-client-side-phishing-detection", "--disable-breakpad", "--metrics-recording-only",
    "--disable-features=Translate,OptimizationHints,MediaRouter,InterestFeedContentSuggestions",
    "--password-store=basic", "--use-mock-keychain", "--mute-audio", "--hide-scrollbars",
    "--no-proxy-server",
    # a safety net: even a request the check failed to see cannot leave the machine
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1, EXCLUDE localhost",
    "--remote-debugging-port=0",
]

# Runs in each page once it has loaded: what the checks need from the live DOM.
_COLLECT_JS = """
(async (imgTimeoutMs, resourceRels) => {
  const abs = (v) => { try { return new URL(v, document.baseURI).href; } catch (e) { return v; } };
  const imgs = Array.from(document.images);
  for (const i of imgs) if (i.loading === 'lazy') i.loading = 'eager';
  await Promise.all(imgs.map((i) => i.complete ? null : new Promise((r) => {
    i.addEventListener('load', r, {once: true});
    i.addEventListener('error', r, {once: true});
    setTimeout(r, imgTimeoutMs);
  })));
  const out = {images: [], resources: [], links: [], ids: []};
  for (const i of imgs) {
    const a = i.getAttribute('src');
    if (a) out.images.push({url: abs(a), width: i.naturalWidth, complete: i.complete});
  }
  const res = (sel, attr, tag) => document.querySelectorAll(sel).forEach((e) => {
    const v = e.getAttribute(attr);
    if (v) out.resources.push({tag: tag || e.tagName.toLowerCase(), url: abs(v)});
  });
  res('video[src], audio[src], source[src], track[src], iframe[src], embed[src]', 'src');
  res('video[poster]', 'poster', 'video poster');
  res('script[src]', 'src');
  res('object[data]', 'data');
  document.querySelectorAll('link[href]').forEach((e) => {
    const rels = (e.getAttribute('rel') || '').toLowerCase().split(/\\s+/);
    const rel = rels.find((r) => resourceRels.includes(r));
    const url = abs(e.getAttribute('href'));
    if (rel) out.resources.push({tag: 'link rel=' + rel, url: url});
    else out.links.push({tag: 'link', url: url});
  });
  document.querySelectorAll('a[href], area[href]').forEach((e) =>
    out.links.push({tag: e.tagName.toLowerCase(), url: abs(e.getAttribute('href'))}));
  document.querySelectorAll('[id]').forEach((e) => out.ids.push(e.id));
  document.querySelectorAll('a[name]').forEach((e) => out.ids.push(e.getAttribute('name')));
  return out;
})
"""


class ChromiumNotFound(RuntimeError):
    """No Chromium binary: install it (``make browser`` or ``apt-get install chromium``)."""


class BrowserError(RuntimeError):
    """Chromium failed to start or to answer; the message holds the end of its log."""


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
    screenshot: Path | None = None
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.problems

    def format(self) -> str:
        """A readable summary: one line per problem."""
        head = (f"browser check of {self.html_dir}: {len(self.pages)} pages, "
                f"{len(self.requests)} distinct requests, {len(self.external_links)} external "
                f"links (not followed), {self.seconds:.1f} s")
        lines = [head]
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


# ---------------------------------------------------------------------------- the HTTP server


class _Handler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - stdlib's name
        pass  # quiet; requests are recorded through CDP


@contextlib.contextmanager
def _serve(html_dir: Path) -> Iterator[str]:
    """Serve ``html_dir`` on 127.0.0.1 (a free port) in a thread; yields the base URL."""
    handler = functools.partial(_Handler, directory=str(html_dir))
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


_NO_PROXY = urllib.request.build_opener(urllib.request.ProxyHandler({}))


def _http_status(url: str, timeout: float = 10) -> int:
    """HTTP status of a HEAD request to the book server (0 if it could not be reached)."""
    try:
        with _NO_PROXY.open(urllib.request.Request(url, method="HEAD"), timeout=timeout) as r:
            return r.status
    except urllib.error.HTTPError as e:
        return e.code
    except OSError:
        return 0


# ------------------------------------------------------------------------------ CDP, minimal


def _websocket() -> Any:
    """The ``websocket-client`` module (CDP speaks over a websocket)."""
    try:
        import websocket
    except ImportError as e:
        raise BrowserError(
            "the browser check needs websocket-client: run `make env` (it is pinned in "
            "environment/requirements.txt) or `pip install websocket-client`"
        ) from e
    return websocket


class _CDP:
    """A blocking CDP client on one websocket (flat sessions); events go to ``on_event``."""

    def __init__(self, ws: Any, on_event: Callable[[dict[str, Any]], None]):
        self.ws = ws
        self.on_event = on_event
        self._next = 0
        self._replies: dict[int, dict[str, Any]] = {}

    def send(self, method: str, params: dict[str, Any] | None = None,
             session: str | None = None) -> int:
        self._next += 1
        msg: dict[str, Any] = {"id": self._next, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        self.ws.send(json.dumps(msg))
        return self._next

    def call(self, method: str, params: dict[str, Any] | None = None,
             session: str | None = None, timeout: float = 30) -> dict[str, Any]:
        """Send a command and wait for its reply (handling events meanwhile)."""
        mid = self.send(method, params, session)
        if not self.pump_until(lambda: mid in self._replies, timeout):
            raise BrowserError(f"Chromium did not answer {method} within {timeout:.0f} s")
        reply = self._replies.pop(mid)
        if "error" in reply:
            raise BrowserError(f"{method} failed: {reply['error'].get('message', reply['error'])}")
        return reply.get("result", {})

    def pump_until(self, cond: Callable[[], bool], timeout: float) -> bool:
        """Handle messages until ``cond()`` holds (True) or ``timeout`` s pass (False)."""
        websocket = _websocket()
        deadline = time.monotonic() + timeout
        while not cond():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            # wait in short slices (cond() may turn true with time alone), then read one whole
            # message: a timeout inside a message is never needed
            try:
                ready, _, _ = select.select([self.ws.sock], [], [], min(left, 0.05))
                if not ready:
                    continue
                self.ws.settimeout(max(left, 10.0))
                raw = self.ws.recv()
            except websocket.WebSocketTimeoutException as e:
                raise BrowserError("Chromium stopped in the middle of a message") from e
            except (websocket.WebSocketConnectionClosedException, OSError, ValueError,
                    TypeError) as e:
                raise BrowserError(f"the connection to Chromium closed: {e}") from e
            msg = json.loads(raw)
            if "id" in msg:
                self._replies[msg["id"]] = msg
            else:
                self.on_event(msg)
        return True


@contextlib.contextmanager
def _chromium(exe: str, start_timeout: float = 30) -> Iterator[tuple[_CDP, list]]:
    """Start headless Chromium with a fresh profile; yields a connected client.

    The second item is a one-element list holding the event handler, to be set by the caller.
    """
    websocket = _websocket()

    with tempfile.TemporaryDirectory(prefix="flowmod-chromium-") as tmp:
        profile = Path(tmp) / "profile"
        log_path = Path(tmp) / "chromium.log"
        cmd = [exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"]
        with open(log_path, "wb") as log:
            proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                                    start_new_session=True)

        def log_tail() -> str:
            text = log_path.read_text(errors="replace") if log_path.exists() else ""
            keep = [ln for ln in text.splitlines() if "dbus" not in ln and ln.strip()]
            return "\n".join(keep[-15:])

        ws = None
        try:
            port_file = profile / "DevToolsActivePort"
            deadline = time.monotonic() + start_timeout
            lines: list[str] = []
            while True:
                if port_file.is_file():
                    lines = port_file.read_text().split()
                    if len(lines) >= 2:
                        break
                if proc.poll() is not None:
                    raise BrowserError(f"{exe} exited (status {proc.returncode}) on start:\n"
                                       f"{log_tail()}")
                if time.monotonic() > deadline:
                    raise BrowserError(f"{exe} opened no DevTools port within "
                                       f"{start_timeout:.0f} s:\n{log_tail()}")
                time.sleep(0.05)
            url = f"ws://127.0.0.1:{lines[0]}{lines[1]}"
            ws = websocket.create_connection(url, timeout=start_timeout, suppress_origin=True,
                                             http_no_proxy=["127.0.0.1", "localhost"])
            handler: list[Callable[[dict[str, Any]], None]] = [lambda msg: None]
            cdp = _CDP(ws, lambda msg: handler[0](msg))
            yield cdp, handler
            with contextlib.suppress(Exception):
                cdp.send("Browser.close")
                proc.wait(timeout=5)
        finally:
            if ws is not None:
                with contextlib.suppress(Exception):
                    ws.close()
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGTERM)  # our own group (start_new_session)
                try:
                    proc.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait(timeout=5)


# ------------------------------------------------------------------------------- the check


@dataclass
class _PageLog:
    """What CDP reported while one page was open."""

    requests: dict[str, str] = field(default_factory=dict)  # requestId -> url (last)
    urls: list[str] = field(default_factory=list)  # every url requested, in order
    status: dict[str, int] = field(default_factory=dict)  # requestId -> HTTP status
    failed: dict[str, str] = field(default_factory=dict)  # requestId -> error text
    doc_status: int | None = None
    js_errors: list[str] = field(default_factory=list)
    inflight: set[str] = field(default_factory=set)  # requestIds not finished yet
    last_event: float = field(default_factory=time.monotonic)  # of the last Network event

    def quiet(self, seconds: float) -> bool:
        """No request in flight and no network event for ``seconds``."""
        return not self.inflight and time.monotonic() - self.last_event >= seconds


class _Recorder:
    """CDP event handler: attaches to child targets and logs network events per page."""

    def __init__(self, cdp: _CDP):
        self.cdp = cdp
        self.main_frame = ""
        self.page_session = ""
        self.lifecycle: dict[str, set[str]] = {}  # loaderId -> event names (main frame)
        self.log = _PageLog()

    def __call__(self, msg: dict[str, Any]) -> None:
        method, p = msg.get("method", ""), msg.get("params", {})
        if method.startswith("Network."):
            self.log.last_event = time.monotonic()
        if method == "Target.attachedToTarget":
            child = p["sessionId"]
            self.cdp.send("Network.enable", {}, child)
            self.cdp.send("Network.setCacheDisabled", {"cacheDisabled": True}, child)
            self.cdp.send("Target.setAutoAttach", {"autoAttach": True, "flatten": True,
                                                   "waitForDebuggerOnStart": True}, child)
            self.cdp.send("Runtime.runIfWaitingForDebugger", {}, child)
        elif method == "Network.requestWillBeSent":
            url = p["request"]["url"]
            self.log.requests[p["requestId"]] = url
            self.log.urls.append(url)
            self.log.inflight.add(p["requestId"])
            if p.get("type") == "Document" and p.get("frameId") == self.main_frame:
                self.log.doc_status = None  # a new main document (or a redirect): not yet
        elif method == "Network.webSocketCreated":
            self.log.urls.append(p["url"])
        elif method == "Network.responseReceived":
            status = int(p["response"].get("status", 0))
            self.log.status[p["requestId"]] = status
            if p.get("type") == "Document" and p.get("frameId") == self.main_frame:
                self.log.doc_status = status
        elif method == "Network.loadingFinished":
            self.log.inflight.discard(p["requestId"])
        elif method == "Network.loadingFailed":
            self.log.inflight.discard(p["requestId"])
            if not p.get("canceled"):
                self.log.failed[p["requestId"]] = p.get("blockedReason") or p.get("errorText", "")
        elif method == "Page.lifecycleEvent" and p.get("frameId") == self.main_frame:
            self.lifecycle.setdefault(p["loaderId"], set()).add(p["name"])
        elif method == "Runtime.exceptionThrown" and msg.get("sessionId") == self.page_session:
            d = p.get("exceptionDetails", {})
            text = d.get("exception", {}).get("description") or d.get("text", "")
            self.log.js_errors.append(text.splitlines()[0] if text else "exception")


class _IdParser(HTMLParser):
    """Anchors (``id``, ``<a name>``) of an HTML file the browser did not open."""

    def __init__(self) -> None:
        super().__init__()
        self.ids: set[str] = set()

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        for k, v in attrs:
            if v and (k == "id" or (tag == "a" and k == "name")):
                self.ids.add(v)


def _pages(html_dir: Path) -> list[str]:
    """Every .html page under ``html_dir`` (not asset folders), ``index.html`` first."""
    pages = sorted(p.relative_to(html_dir).as_posix() for p in html_dir.rglob("*.html")
                   if p.relative_to(html_dir).parts[0] not in ASSET_DIRS)
    if "index.html" in pages:
        pages.remove("index.html")
        pages.insert(0, "index.html")
    return pages


def _is_loopback(url: str) -> bool:
    parts = urlsplit(url)
    if parts.scheme in INLINE_SCHEMES:
        return True
    return parts.scheme in ("http", "https", "ws", "wss") and (parts.hostname or "") in LOOPBACK


class _BookCheck:
    """One run of :func:`check_book`: the server's base URL, the CDP page, what was found."""

    def __init__(self, html_dir: Path, base: str, cdp: _CDP, rec: _Recorder, session: str,
                 report: BookReport, page_timeout: float, idle_timeout: float):
        self.html_dir, self.base, self.netloc = html_dir, base, urlsplit(base).netloc
        self.cdp, self.rec, self.session, self.report = cdp, rec, session, report
        self.page_timeout, self.idle_timeout = page_timeout, idle_timeout
        self.found: dict[tuple[str, str], Problem] = {}  # (page, target) -> first problem
        self.seen_requests: dict[str, None] = {}
        self.ids: dict[str, set[str]] = {}  # page -> anchors in its live DOM
        self.links: list[tuple[str, str, str]] = []  # (page, tag, url), checked at the end
        self.status_cache: dict[str, int] = {}

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
        key = url.split("#")[0]
        if key not in self.status_cache:
            self.status_cache[key] = _http_status(key)
        return self.status_cache[key]

    def local_file(self, url: str) -> Path:
        path = self.html_dir / unquote(urlsplit(url).path).lstrip("/")
        return path / "index.html" if path.is_dir() else path

    def visit(self, page: str, screenshot: Path | None) -> None:
        """Open ``page``, wait for it to settle, check its requests and resources."""
        cdp, rec, session = self.cdp, self.rec, self.session
        rec.log = log = _PageLog()
        url = f"{self.base}/{page}"
        nav = cdp.call("Page.navigate", {"url": url}, session, timeout=self.page_timeout)
        if nav.get("errorText"):
            self.add(page, "page", url, f"navigation failed: {nav['errorText']}")
            return
        loader = nav.get("loaderId", "")

        def settled(name: str) -> Callable[[], bool]:
            return lambda: name in rec.lifecycle.get(loader, set())

        if not cdp.pump_until(settled("load"), self.page_timeout):
            self.add(page, "page", url,
                     f"did not finish loading within {self.page_timeout:.0f} s")
            return
        cdp.pump_until(lambda: log.quiet(0.3), self.idle_timeout)  # late requests (fonts, ...)
        if log.doc_status != 200:
            self.add(page, "page", url, f"HTTP {log.doc_status}")
            return
        expr = (f"({_COLLECT_JS})({int(self.page_timeout * 1000)}, "
                f"{json.dumps(sorted(RESOURCE_RELS))})")
        dom = cdp.call("Runtime.evaluate", {"expression": expr, "awaitPromise": True,
                                            "returnByValue": True},
                       session, timeout=self.page_timeout + 5)
        if "exceptionDetails" in dom:
            raise BrowserError(f"collecting the DOM of {page} failed: "
                               f"{dom['exceptionDetails'].get('text')}")
        # requests started by images made eager report back before this round trip ends
        cdp.pump_until(lambda: log.quiet(0.1), 2.0)
        cdp.call("Runtime.evaluate", {"expression": "0"}, session)
        found = dom["result"]["value"]
        self.ids[page] = set(found["ids"])
        self.report.js_errors.extend((page, m) for m in log.js_errors)
        self.check_resources(page, [{"tag": "img", **i} for i in found["images"]]
                             + found["resources"])
        self.check_requests(page, log)  # after: a known element names a problem better
        self.links.extend((page, item["tag"], item["url"]) for item in found["links"])
        if screenshot is not None:
            png = cdp.call("Page.captureScreenshot", {"format": "png"}, session)
            with atomic_path(screenshot) as tmp:
                tmp.write_bytes(base64.b64decode(png["data"]))
            self.report.screenshot = screenshot

    def check_requests(self, page: str, log: _PageLog) -> None:
        """Every request the page made stays on localhost and succeeds."""
        for u in log.urls:
            if urlsplit(u).scheme not in INLINE_SCHEMES:
                self.seen_requests.setdefault(u, None)
            if not _is_loopback(u):
                self.add(page, "external", u, "the page requested a URL outside localhost")
        for rid, u in log.requests.items():
            if not _is_loopback(u) or urlsplit(u).scheme in INLINE_SCHEMES:
                continue
            if urlsplit(u).path == "/favicon.ico":
                continue  # the browser's own guess where no <link rel=icon> names one
            status = log.status.get(rid)
            if rid in log.failed and log.failed[rid] != "net::ERR_ABORTED":
                self.add(page, "request", u, f"request failed: {log.failed[rid]}")
            elif status is not None and status >= 400:
                self.add(page, "request", u, f"HTTP {status}")

    def check_resources(self, page: str, items: list[dict[str, Any]]) -> None:
        """Files named by the page's elements, fetched by the browser or not, resolve."""
        for item in items:
            u, tag = item["url"], item["tag"]
            if urlsplit(u).scheme in INLINE_SCHEMES:
                continue
            if not _is_loopback(u):
                self.add(page, "external", u, f"<{tag}> loads from outside localhost")
                continue
            if tag in ("link rel=dns-prefetch", "link rel=preconnect"):
                continue
            if urlsplit(u).netloc != self.netloc:
                self.add(page, "resource", u, f"<{tag}> points at another local server")
                continue
            status = self.head(u)
            if status != 200:
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
            target = self.local_file(u)
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
               *, page_timeout: float = 30, idle_timeout: float = 5,
               chromium: str | None = None) -> BookReport:
    """Open every page of the built book ``html_dir`` in headless Chromium; see the module doc.

    ``screenshot``: PNG of ``index.html``, 1280x900 px (default ``html_dir/../book-screenshot.png``).
    ``page_timeout`` (s): how long a page may take to fire ``load``; ``idle_timeout`` (s): how
    long to wait after that for the network to go quiet (late requests, e.g. MathJax fonts).
    ``chromium``: the browser binary (default :func:`find_chromium`). Raises
    :class:`ChromiumNotFound` when there is no browser; what is wrong goes into the report.
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
    with _serve(html_dir) as base, _chromium(exe) as (cdp, handler):
        target = cdp.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = cdp.call("Target.attachToTarget",
                           {"targetId": target, "flatten": True})["sessionId"]
        rec = _Recorder(cdp)
        rec.main_frame, rec.page_session = target, session  # a page's main frame id = its id
        handler[0] = rec
        for method, params in [
            ("Page.enable", {}), ("Page.setLifecycleEventsEnabled", {"enabled": True}),
            ("Network.enable", {}), ("Network.setCacheDisabled", {"cacheDisabled": True}),
            ("Runtime.enable", {}),
            ("Target.setAutoAttach", {"autoAttach": True, "waitForDebuggerOnStart": True,
                                      "flatten": True}),
            ("Emulation.setDeviceMetricsOverride", {"width": 1280, "height": 900,
                                                    "deviceScaleFactor": 1, "mobile": False}),
        ]:
            cdp.call(method, params, session)
        check = _BookCheck(html_dir, base, cdp, rec, session, report, page_timeout,
                           idle_timeout)
        for page in report.pages:
            check.visit(page, shot if page == "index.html" else None)
        check.check_links()
    report.problems.extend(check.found.values())
    report.requests = list(check.seen_requests)
    report.seconds = time.monotonic() - t0
    return report


def assert_book_ok(html_dir: str | os.PathLike[str],
                   screenshot: str | os.PathLike[str] | None = None) -> BookReport:
    """:func:`check_book`, raising ``AssertionError`` with the readable report on any problem."""
    report = check_book(html_dir, screenshot)
    if not report.ok:
        raise AssertionError(report.format())
    return report


def main(argv: list[str] | None = None) -> int:
    """CLI: 0 if the book is fine, 1 with the list of problems, 2 if it cannot be checked."""
    from flowmod.paths import repo_root

    ap = argparse.ArgumentParser(prog="python -m flowmod.report.browser",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("html_dir", type=Path, nargs="?", default=repo_root() / "build" / "html",
                    help="the built book (default build/html)")
    ap.add_argument("--screenshot", type=Path, default=None,
                    help="PNG of index.html (default: book-screenshot.png beside html_dir)")
    ap.add_argument("--page-timeout", type=float, default=30, help="seconds per page load")
    args = ap.parse_args(argv)
    try:
        report = check_book(args.html_dir, args.screenshot, page_timeout=args.page_timeout)
    except (ChromiumNotFound, BrowserError, FileNotFoundError) as e:
        print(f"{type(e).__name__}: {e}", file=sys.stderr)
        return 2
    print(report.format(), file=sys.stdout if report.ok else sys.stderr)
    return 0 if report.ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
