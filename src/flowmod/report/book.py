"""Assemble and build the HTML book from executed notebooks.

    python -m flowmod.report.book --executed build/executed --out build/html

Steps: check the run record (``run_info.json``) and every executed notebook (a notebook that
failed, or was not executed, is refused: it is never rendered as if it had passed); copy
``book/`` and the executed notebooks into a staging folder; write the Reproduce page from the
run record; vendor MathJax; run ``sphinx-build -W -n --keep-going``.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import nbformat
import pandas as pd

from flowmod.artefacts import DiskFull, disk_full
from flowmod.lock import FolderBusy, file_lock
from flowmod.paths import file_in_the_way, repo_root


class BookError(RuntimeError):
    """The book cannot be built from what was run; the message says what to do."""


@contextlib.contextmanager
def _room(folder: Path, doing: str) -> Iterator[None]:
    """A full disk under ``folder`` inside the block: :class:`BookError` with
    :class:`~flowmod.artefacts.DiskFull`'s line (the CLI prints a BookError as one line)."""
    try:
        with DiskFull.guard(folder, doing, "--out"):
            yield
    except DiskFull as e:
        raise BookError(f"{e}; the published book is unchanged") from e


def read_glue(nb_path: str | os.PathLike[str]) -> dict[str, Any]:
    """Values a notebook recorded with ``myst_nb.glue``: ``{key: python value}``.

    Reads the ``text/plain`` representation (``ast.literal_eval`` where possible, else the
    string): the recommenders-style hook through which tests assert on a notebook's results.
    """
    import ast

    nb = nbformat.read(str(nb_path), as_version=4)
    out: dict[str, Any] = {}
    for cell in nb.cells:
        for o in cell.get("outputs", []):
            meta = o.get("metadata", {}).get("scrapbook", {})
            if "name" not in meta:
                continue
            prefix = meta.get("mime_prefix", "")  # glue(..., display=False) hides it
            text = o.get("data", {}).get(prefix + "text/plain", "")
            try:
                out[meta["name"]] = ast.literal_eval(text)
            except (ValueError, SyntaxError):
                out[meta["name"]] = text.strip("'\"")
    return out


def check_executed(nb_path: Path) -> None:
    """Refuse a notebook that papermill did not run to completion."""
    nb = nbformat.read(str(nb_path), as_version=4)
    pm = nb.metadata.get("papermill")
    if pm is None:
        raise BookError(f"{nb_path} was not executed by papermill; run `make run` first")
    if pm.get("exception"):
        raise BookError(f"{nb_path} failed when it ran; fix it and rerun `make run`")
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        if any(o.get("output_type") == "error" for o in cell.get("outputs", [])):
            raise BookError(f"{nb_path} holds an error output; fix it and rerun `make run`")
        if cell.get("source", "").strip() and cell.get("execution_count") is None:
            raise BookError(f"{nb_path} has cells that never ran; rerun `make run`")


_DECLARED = re.compile(r"^(\w+)\s*:\s*[^=]+=\s*(.*?)\s*#\s*(.*)$")


def declared_comments(source: str) -> dict[str, str]:
    """``{name: comment}`` of a ``parameters`` cell's typed, commented assignments."""
    out = {}
    for line in source.splitlines():
        m = _DECLARED.match(line.strip())
        if m:
            out[m.group(1)] = m.group(3)
    return out


def injected_values(source: str) -> dict[str, Any]:
    """``{name: value}`` of papermill's injected-parameters cell (``name = literal``)."""
    import ast

    out: dict[str, Any] = {}
    for node in ast.parse(source).body:
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name):
            out[node.targets[0].id] = ast.literal_eval(node.value)
    return out


def parameters_html(values: dict[str, Any], comments: dict[str, str]) -> str:
    """One collapsed block: every parameter this chapter ran with, its value and meaning."""
    import html

    rows = "".join(
        f"<tr><td><code>{html.escape(k)}</code></td>"
        f"<td><code>{html.escape(json.dumps(v))}</code></td>"
        f"<td>{html.escape(comments.get(k, ''))}</td></tr>" for k, v in values.items())
    return (f'<details class="flowmod-parameters"><summary>The {len(values)} parameters this '
            "chapter ran with (injected by papermill; the profile's values and overrides)"
            "</summary>\n<table><thead><tr><th>parameter</th><th>value</th><th>meaning</th>"
            f"</tr></thead><tbody>{rows}</tbody></table></details>")


def for_the_page(nb: nbformat.NotebookNode) -> nbformat.NotebookNode:
    """An executed notebook as the book shows it: the declared ``parameters`` cell removed
    and papermill's injected cell replaced by one collapsed table of the values that ran,
    explained by the declared comments. Cells tagged ``remove-cell`` / ``remove-input`` are
    hidden by myst-nb itself."""
    comments: dict[str, str] = {}
    cells = []
    for cell in nb.cells:
        tags = cell.get("metadata", {}).get("tags", [])
        if "parameters" in tags:
            comments = declared_comments(cell.source)
            continue
        if "injected-parameters" in tags:  # a fixed id: a random one changes every page
            cell = nbformat.v4.new_markdown_cell(
                parameters_html(injected_values(cell.source), comments), id="parameters-ran")
        cells.append(cell)
    out = nbformat.from_dict(dict(nb))
    out.cells = cells
    return out


def _write_if_changed(path: Path, text: str) -> None:
    """Write ``text`` unless ``path`` holds it already (Sphinx rebuilds only what changed)."""
    if not (path.is_file() and path.read_text() == text):
        path.write_text(text)


def reproduce_page(info: dict[str, Any]) -> str:
    """Markdown of the Reproduce page from a run record."""
    params = pd.DataFrame(
        [{"parameter": k, "value": json.dumps(v)} for k, v in info["parameters"].items()]
    )
    versions = pd.DataFrame(
        [{"package": k, "version": v} for k, v in info["versions"].items()]
    )
    runs = info["notebooks"]
    timings = pd.DataFrame(
        [{"notebook": k, "executed": v.get("executed") or "not recorded",
          "seconds": v["seconds"]} for k, v in runs.items()]
    )
    total = sum(v["seconds"] for v in runs.values())
    times = sorted(v["executed"] for v in runs.values() if v.get("executed"))
    executed = f"{times[0]} to {times[-1]}" if times else "not recorded"
    over = " ".join(f"--set {k}={json.dumps(v)}" for k, v in info.get("overrides", {}).items())
    device = ", ".join(f"{k}: {v}" for k, v in info["device"].items())
    return f"""# Reproduce

This page is written from the record of the run that produced this book
(`build/executed/run_info.json`).

| | |
|---|---|
| profile | `{info["profile"]}` |
| git commit | `{info["commit"]}` |
| notebooks executed | {executed} |
| device | {device} |
| notebooks, total | {total:.0f} s |

## Commands

```bash
make book PROFILE={info["profile"]}
# or, notebook by notebook:
.venv/bin/python -m flowmod.runner --profile {info["profile"]} {over}
.venv/bin/python -m flowmod.report.book
```

## Seconds per notebook

A notebook is executed again only when something it depends on changed (its cells, its
parameters, the library's code, the data it reads); otherwise its executed copy is reused, and
its row gives when that copy was executed and the seconds it took then. So this page changes
only with what it reports.

{timings.to_markdown(index=False)}

## Parameters

{params.to_markdown(index=False)}

## Package versions

{versions.to_markdown(index=False)}
"""


def find_mathjax() -> Path | None:
    """The vendored ``mathjax@3`` ``es5/`` folder (``make env`` installs it), if present."""
    for base in (os.environ.get("FLOWMOD_VENDOR"), repo_root() / "build" / "vendor"):
        if base:
            es5 = Path(base) / "node_modules" / "mathjax" / "es5"
            if (es5 / "tex-chtml.js").is_file():
                return es5
    return None


def assemble(executed: Path, staging: Path) -> dict[str, Any]:
    """Check the run and fill ``staging`` with the book sources; returns the run record."""
    info_path = executed / "run_info.json"
    if not info_path.is_file():
        raise BookError(f"{info_path} not found: run the notebooks first (`make run`)")
    info = json.loads(info_path.read_text())
    if info.get("status") != "ok":
        raise BookError(
            f"the run recorded in {info_path} did not finish (status {info.get('status')!r}); "
            "fix the failing notebook and rerun `make run`"
        )
    sources = sorted((repo_root() / "notebooks").glob("[0-9][0-9]_*.ipynb"))
    missing = [nb.stem for nb in sources if nb.stem not in info["notebooks"]]
    if missing:
        raise BookError(
            f"notebooks not executed in this run: {', '.join(missing)}; run `make run` "
            "(all notebooks) before `make book`"
        )
    with _room(staging, "staging the book's sources"):
        _sync(repo_root() / "book", staging,
              keep={nb.name for nb in sources} | {"reproduce.md"})
        for nb in sources:
            done = executed / nb.name
            if not done.is_file():
                raise BookError(f"{done} is missing; rerun `make run`")
            check_executed(done)
            page = for_the_page(nbformat.read(str(done), as_version=4))
            _write_if_changed(staging / nb.name, nbformat.writes(page))
        _write_if_changed(staging / "reproduce.md", reproduce_page(info))
    return info


def _sync(src: Path, dst: Path, keep: set[str]) -> None:
    """Make ``dst`` a copy of ``src`` (plus the files named in ``keep``), touching only files
    whose content differs, so that Sphinx rebuilds only pages that changed."""
    dst.mkdir(parents=True, exist_ok=True)
    wanted = {p.relative_to(src) for p in src.rglob("*") if p.is_file()}
    for rel in wanted:
        target = dst / rel
        if not (target.is_file() and target.read_bytes() == (src / rel).read_bytes()):
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / rel, target)
    for p in sorted(dst.rglob("*"), reverse=True):
        rel = p.relative_to(dst)
        if p.is_file() and rel not in wanted and str(rel) not in keep:
            p.unlink()


def build(executed: Path, out: Path, staging: Path | None = None, wait: bool = False) -> Path:
    """Assemble and run Sphinx (warnings are errors); returns ``out/index.html``.

    ``out`` must be a folder or absent (:class:`BookError` before any work otherwise). One
    build per ``out`` at a time (a lock file beside it; ``wait``: wait for the other build
    instead of :class:`FolderBusy`). Its working folders (the staged sources, the vendored
    MathJax, the media, myst-nb's output folder) live in one hidden folder beside ``out``,
    ``.<out>.work``, never loose in ``out``'s parent (a user's ``--out ~/Desktop/book``). The
    book is built into a copy of ``out`` there (modification times kept, so Sphinx rewrites
    only what changed) that replaces ``out`` only when Sphinx succeeds: a build that fails or
    is killed leaves the published book as it was.
    """
    out = Path(out).resolve()
    blocker = file_in_the_way(out)
    if blocker is not None:
        raise BookError(f"--out {out}: {blocker} is a file, not a folder; give a folder for "
                        "the HTML book (it is made if absent) or move the file away")
    work_root = out.with_name(f".{out.name}.work")
    staging = Path(staging or work_root / "src").resolve()
    with file_lock(out.with_name(f".{out.name}.lock"), "python -m flowmod.report.book",
                   wait=wait, what=out):
        info = assemble(Path(executed), staging)
        es5 = find_mathjax()
        if es5 is None:
            raise BookError(
                "MathJax is not vendored (build/vendor/node_modules/mathjax/es5 missing): run "
                "`make env` (it runs `npm install --prefix build/vendor mathjax@3`)"
            )
        work = work_root / "html"  # myst-nb writes beside it: ``work_root/jupyter_execute``
        shutil.rmtree(work, ignore_errors=True)  # what a killed build left
        try:
            with _room(out, "building the book"):
                if out.is_dir():
                    shutil.copytree(out, work, symlinks=True)
                _sphinx(staging, work, _sphinx_env(work_root, es5, info))
        except BaseException:
            shutil.rmtree(work, ignore_errors=True)
            raise
        _publish(work, out, work_root / "old")
    return out / "index.html"


def _sphinx_env(work_root: Path, es5: Path, info: dict[str, Any]) -> dict[str, str]:
    """The environment Sphinx runs in: where the vendored MathJax and the run's media are
    (copied into ``work_root/extra`` and ``work_root/media``)."""
    extra = work_root / "extra"
    _sync(es5, extra / "_vendor" / "mathjax", keep=set())
    env = {**os.environ, "FLOWMOD_MATHJAX_EXTRA": str(extra)}
    # videos (and their posters) that notebooks show as raw HTML under media/
    media = Path(info["parameters"]["run_dir"])
    media = (media if media.is_absolute() else repo_root() / media) / "figures" / "media"
    if media.is_dir():
        pages_extra = work_root / "media"
        _sync(media, pages_extra / "media", keep=set())
        env["FLOWMOD_PAGES_EXTRA"] = str(pages_extra)
    return env


def _sphinx(staging: Path, out: Path, env: dict[str, str]) -> None:
    """sphinx-build of ``staging`` into ``out`` (doctrees in ``out/.doctrees``)."""
    cmd = [sys.executable, "-m", "sphinx", "-W", "-n", "--keep-going", "-q", "-b", "html"]
    # Into an empty folder, Sphinx links myst-nb's stylesheet before the file exists, so
    # without its ``?v=`` checksum; a later build adds it and rewrites every page (and a
    # rewritten book sends the browser check over it again). A fresh build therefore writes
    # every page a second time (``-a``), so that a rerun with nothing changed finds them.
    passes = [[]] if (out / ".doctrees").is_dir() else [[], ["-a"]]
    for extra in passes:
        proc = subprocess.run([*cmd, *extra, str(staging), str(out)], env=env,
                              stderr=subprocess.PIPE, text=True, errors="replace")
        if proc.returncode != 0 and disk_full(proc.stderr):  # not Sphinx's page of report
            raise OSError(errno.ENOSPC, f"sphinx-build: {os.strerror(errno.ENOSPC)}")
        sys.stderr.write(proc.stderr)  # its warnings
        if proc.returncode != 0:
            raise BookError(f"sphinx-build failed (exit {proc.returncode}); "
                            "see the warnings above; the published book is unchanged")


def _publish(work: Path, out: Path, old: Path) -> None:
    """Swap the built ``work`` in as ``out``; the previous book (moved to ``old``) is removed
    only after."""
    shutil.rmtree(old, ignore_errors=True)
    if out.exists():
        os.replace(out, old)
    os.replace(work, out)
    shutil.rmtree(old, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m flowmod.report.book", description=__doc__.split("\n\n")[0])
    root = repo_root()
    ap.add_argument("--executed", type=Path, default=root / "build" / "executed")
    ap.add_argument("--out", type=Path, default=root / "build" / "html",
                    help="folder of the HTML book (made if absent)")
    ap.add_argument("--wait", action="store_true",
                    help="if another build holds --out, wait for it instead of stopping")
    args = ap.parse_args(argv)
    try:
        index = build(args.executed, args.out, wait=args.wait)
    except (BookError, FolderBusy) as e:
        print(f"{type(e).__name__}: {e}", file=sys.stderr)
        return 1
    print(f"book: {index}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
