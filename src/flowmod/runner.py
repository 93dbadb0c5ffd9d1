"""Run the study: execute ``notebooks/NN_*.ipynb`` in order with papermill.

    python -m flowmod.runner --profile demo                 # every notebook
    python -m flowmod.runner --profile smoke --only 00_setup
    python -m flowmod.runner --profile paper --set dataroot=/data/nuscenes --set epochs=2
    python -m flowmod.runner --profile demo --status      # what is stale, and why; runs nothing

The profile is validated (with the overrides) before anything runs. Each notebook receives only
the parameters its ``parameters`` cell declares; its executed copy goes to ``--out``
(``build/executed/`` by default). The run stops at the first failing notebook and prints its
error; ``run_info.json`` beside the executed notebooks records the profile, the parameters,
package versions, the git commit, and when each notebook was executed and the seconds it took
(a reused executed copy keeps those of its execution, stamped in its metadata). While a notebook runs,
the progress of its stages (items done / total, rate, ETA) is echoed to the terminal through
:mod:`flowmod.progress`'s side channel; the book's pages never show it.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import hashlib
import json
import os
import re
import shutil
import signal
import sys
import tempfile
import threading
import time
import weakref
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import nbformat
import papermill
from jupyter_client.manager import AsyncKernelManager

from flowmod import codedigest, environment, pipeline, progress
from flowmod.artefacts import DiskFull, atomic_path, disk_full, fingerprint, write_json
from flowmod.chapters.ch06_training import ABLATION_RECORD, STEPS_RECORD
from flowmod.chapters.ch14_answers import REPLICATION_RECORD
from flowmod.flow.finetune import FINETUNE_RECORD
from flowmod.flow.networks import planned_methods
from flowmod.lock import FolderBusy, folder_lock
from flowmod.params import Params, ProfileError, load_profile, parse_overrides, profile_path
from flowmod.paths import file_in_the_way, repo_root
from flowmod.report.book import check_executed
from flowmod.select import SelectionError, check_dataroot
from flowmod.world import source as world_source

#: how run records and executed copies write times
TIME_FORMAT = "%Y-%m-%d %H:%M:%S %Z"


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the runner is, so that it unwinds as Ctrl-C does (no half-run
    copy stays; a node being built stays in its building folder)."""


#: The kernels this process started (:func:`_kernel_manager`): Ctrl-C and SIGTERM kill them.
KERNELS: weakref.WeakSet[AsyncKernelManager] = weakref.WeakSet()


class NotebookFailed(RuntimeError):
    """A notebook raised; the message carries its name, the error and the executed copy."""

    def __init__(self, message: str, seconds: float = 0.0) -> None:
        super().__init__(message)
        self.seconds = seconds


def notebooks(folder: Path | None = None) -> list[Path]:
    """The study's notebooks, ``NN_name.ipynb``, in order."""
    folder = folder or repo_root() / "notebooks"
    return sorted(p for p in folder.glob("[0-9][0-9]_*.ipynb"))


def declared_parameters(nb: Path) -> dict[str, dict[str, Any]]:
    """The parameters a notebook declares in its ``parameters`` cell (papermill's inference)."""
    params = papermill.inspect_notebook(str(nb))
    if not params:
        raise ProfileError(
            f"{nb.name} has no cell tagged 'parameters'; tag its first code cell 'parameters'"
        )
    return params


def notebook_parameters(nb: Path, p: Params) -> dict[str, Any]:
    """The values of ``p`` for the parameters ``nb`` declares; unknown names are an error."""
    declared = declared_parameters(nb)
    unknown = sorted(set(declared) - set(Params.model_fields))
    if unknown:
        raise ProfileError(
            f"{nb.name} declares parameters that are not Params fields: {', '.join(unknown)}; "
            "add them to flowmod.params.Params"
        )
    values = p.model_dump()
    if p.dataroot:  # the notebooks read the data where the run put it (a world's own folder)
        values["dataroot"] = str(p.dataroot_path)
    return {k: values[k] for k in declared}


#: Terminal control sequences (tqdm moves the cursor for nested bars).
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


@contextlib.contextmanager
def _echo_progress(path: Path, name: str, every: float = 10.0) -> Iterator[None]:
    """Point :mod:`flowmod.progress` at ``path`` and echo its latest bar to the terminal: when
    a new bar starts, when one finishes, and every ``every`` seconds in between."""
    path.write_text("")
    old = os.environ.get(progress.ENV)
    os.environ[progress.ENV] = str(path)
    stop = threading.Event()

    def loop() -> None:
        pos, shown, last = 0, {"": ""}, 0.0
        while True:
            stopping = stop.wait(1.0)
            chunk = ""
            with contextlib.suppress(OSError), open(path, encoding="utf-8") as f:
                f.seek(pos)
                chunk = f.read()
                pos = f.tell()
            latest: dict[str, str] = {}  # each bar's last state in this chunk, in order
            for seg in re.split(r"[\r\n]", _ANSI.sub("", chunk)):
                if seg.strip():
                    latest[seg.split(":", 1)[0].strip()] = seg.strip()
            now = time.monotonic()
            for i, (desc, line) in enumerate(latest.items()):
                new_bar = desc not in shown
                final = i < len(latest) - 1 or "100%" in line or stopping
                if line != shown.get(desc) and (new_bar or final or now - last >= every):
                    print(f"[flowmod]   {name}: {line}", flush=True)
                    shown[desc], last = line, now
            if stopping:
                return

    t = threading.Thread(target=loop, daemon=True)
    t.start()
    try:
        yield
    finally:
        stop.set()
        t.join(timeout=5)
        if old is None:
            os.environ.pop(progress.ENV, None)
        else:
            os.environ[progress.ENV] = old


def code_digest() -> str:
    """Fingerprint of the library's code (every ``src/flowmod/**/*.py``, each by
    :func:`flowmod.codedigest.source_digest`: a docstring or comment edit re-executes
    nothing)."""
    return fingerprint(list(codedigest.source_digests().items()))


#: Committed records that chapters show (dated benchmark runs), by chapter: their content
#: enters that chapter's fingerprint, so a new record re-executes it instead of reusing a copy.
RECORDS = {"06": (ABLATION_RECORD, STEPS_RECORD), "13": (FINETUNE_RECORD,),
           "14": (REPLICATION_RECORD,)}


def records_digest(chapter: str) -> dict[str, str | None]:
    """sha256 of each of the records ``chapter`` shows (:data:`RECORDS`; None where absent)."""
    out = {}
    for rel in RECORDS.get(chapter, ()):
        f = repo_root() / rel
        out[rel] = hashlib.sha256(f.read_bytes()).hexdigest() if f.is_file() else None
    return out


def notebook_fingerprint(nb: Path, values: dict[str, Any], p: Params,
                         device: dict[str, Any]) -> str | None:
    """What an executed chapter depends on: its source cells, the parameters it received,
    the fingerprints of every node of its and earlier chapters (:mod:`flowmod.dag`) and
    whether each is built, the library's code, the records chapters show (:data:`RECORDS`)
    and the device; None while one of those
    nodes cannot be known yet."""
    chapter = nb.stem[:2]
    exp = {n: fp for n, fp in pipeline.expected(p).items() if pipeline.chapter(n) <= chapter}
    if any(fp is None for fp in exp.values()):
        return None
    # and whether each is built and intact: a chapter that shows what is built (chapter 10
    # without extension_build) is stale once someone builds more, and the chapter that
    # builds a damaged node runs again to rebuild it
    nodes = {}
    for n, fp in exp.items():
        rec = pipeline.recorded(p, n) or {}
        nodes[str(n)] = [fp, rec.get("fingerprint") == fp and pipeline.damaged(p, n, rec) is None]
    cells = [(c.cell_type, c.source, sorted(c.metadata.get("tags", [])))
             for c in nbformat.read(str(nb), as_version=4).cells]
    return fingerprint({"cells": cells, "parameters": values, "nodes": nodes,
                        "code": code_digest(), "records": records_digest(chapter),
                        "device": device})


def _executed_stamp(target: Path) -> dict[str, Any]:
    """What an executed copy was stamped with: its ``fingerprint``, the ``seconds`` its
    execution took and when it ``executed`` (empty if absent, unreadable or failed)."""
    if not target.is_file():
        return {}
    try:
        nb = nbformat.read(str(target), as_version=4)
        check_executed(target)
    except Exception:  # noqa: BLE001 - any unreadable or failed copy is simply not reusable
        return {}
    return dict(nb.metadata.get("flowmod", {}))


def _running_copy(target: Path) -> Path:
    """Where a notebook is executed before it replaces ``target`` (same folder, hidden)."""
    return target.with_name(f".{target.stem}.running.ipynb")


def stable_cell_ids(nb: nbformat.NotebookNode) -> None:
    """Give every cell of ``nb`` an id derived from its position, type and source (12 hex
    digits), in place: papermill's injected-parameters cell gets a random id each run,
    which would change the executed copy, and the book's pages, on every execution."""
    nb.nbformat_minor = max(nb.nbformat_minor, 5)  # cell ids came with nbformat 4.5
    for i, cell in enumerate(nb.cells):
        key = f"{i}\0{cell.cell_type}\0{cell.source}".encode()
        cell["id"] = hashlib.sha256(key).hexdigest()[:12]


def _stamp(target: Path, fp: str | None, seconds: float, executed: str) -> None:
    nb = nbformat.read(str(target), as_version=4)
    stable_cell_ids(nb)
    nb.metadata["flowmod"] = {"fingerprint": fp, "seconds": seconds, "executed": executed}
    with atomic_path(target) as tmp:
        nbformat.write(nb, str(tmp))


def _kernel_manager(folder: Path) -> type:
    """A kernel manager whose kernels talk over local IPC sockets in ``folder`` rather than
    TCP ports (nothing listens on the network, and ipykernel has nothing to warn about)."""
    class IPCKernelManager(AsyncKernelManager):
        def __init__(self, **kw: Any) -> None:
            kw.setdefault("transport", "ipc")
            kw.setdefault("ip", str(folder / "kernel"))
            super().__init__(**kw)
            KERNELS.add(self)

        async def _async_interrupt_kernel(self) -> None:
            # jupyter_client interrupts a kernel before shutting it down; after a finished
            # notebook there is nothing to interrupt, and the kernel would log
            # "KeyboardInterrupt caught in kernel" into a successful run's output
            if not self.shutting_down:
                await super()._async_interrupt_kernel()

    return IPCKernelManager


@dataclass
class Plan:
    """What a run will do, checked before anything runs: the profile, the notebooks with
    the parameters each receives, where executed copies go, and the device."""

    p: Params
    notebooks: list[tuple[Path, dict[str, Any]]]
    out_dir: Path
    device: dict[str, Any]


def preflight(profile: str | Path, overrides: dict[str, Any] | None, out_dir: Path | None,
              only: list[str] | None, notebooks_dir: Path | None) -> Plan:
    """Validate the profile, every selected notebook's parameters, the device and (for real
    data) the dataroot; :class:`ProfileError` in one line for the first problem."""
    p = resolve_profile(profile, overrides)
    out = Path(out_dir or repo_root() / "build" / "executed").resolve()
    check_folders(p, out)
    selected = notebooks(notebooks_dir)
    if only:
        selected = [nb for nb in selected if any(nb.stem.startswith(o) for o in only)]
        if not selected:
            raise ProfileError(f"--only {only} matches no notebook in notebooks/")
    plan = [(nb, notebook_parameters(nb, p)) for nb in selected]
    try:
        device = environment.device_info(p.device)
    except RuntimeError as e:
        raise ProfileError(f"device={p.device!r}: {e}") from None
    if not p.synthetic:  # real data must be there before the first notebook starts
        try:
            check_dataroot(p.dataroot_path, p.version)
        except SelectionError as e:
            raise ProfileError(f"dataroot={p.dataroot!r}, version={p.version!r}: {e}") from None
    return Plan(p, plan, out, device)


def check_folders(p: Params, out_dir: Path | None = None) -> None:
    """:class:`ProfileError` when a file stands where the run folder (``run_dir``) or the
    folder of executed notebooks (``--out``) must be a folder (before any work)."""
    for what, folder, fix in (("run_dir", p.run_path, "--set run_dir=..."),
                              ("--out", out_dir, "--out ...")):
        blocker = None if folder is None else file_in_the_way(folder)
        if blocker is not None:
            under = "" if blocker == folder else f" (its parent {blocker})"
            raise ProfileError(f"{what} {folder}: a file stands where a folder is needed"
                               f"{under}; remove it or give another folder ({fix})")


def _record(plan: Plan, profile: str | Path, overrides: dict[str, Any] | None,
            partial: bool) -> dict[str, Any]:
    """The run record (``run_info.json``); a partial rerun with the same parameters keeps
    the other notebooks' records of the previous one."""
    record: dict[str, Any] = {
        "profile": plan.p.profile, "profile_file": str(profile_path(profile)),
        "overrides": overrides or {}, "parameters": plan.p.model_dump(),
        "commit": environment.git_commit(),
        "versions": environment.versions().set_index("package")["version"].to_dict(),
        "device": plan.device, "started": time.strftime(TIME_FORMAT),
        "notebooks": {}, "status": "running",
    }
    info_path = plan.out_dir / "run_info.json"
    if partial and info_path.is_file():
        old = json.loads(info_path.read_text())
        if old.get("parameters") == record["parameters"] and old.get("status") == "ok":
            record["notebooks"] = {k: v for k, v in old["notebooks"].items()
                                   if k not in {nb.stem for nb, _ in plan.notebooks}}
            record["started"] = old["started"]
    return record


def execute(nb: Path, values: dict[str, Any], plan: Plan, kernel: str, ipc: Path
            ) -> dict[str, Any]:
    """Execute one notebook into ``plan.out_dir`` (or reuse its executed copy when its
    fingerprint matches); returns its record. :class:`NotebookFailed` if a cell raised."""
    target, p = plan.out_dir / nb.name, plan.p
    fp = notebook_fingerprint(nb, values, p, plan.device)
    stamp = _executed_stamp(target)
    if fp is not None and not p.force and stamp.get("fingerprint") == fp:
        print(f"[flowmod] {nb.name} up to date (executed copy reused)", flush=True)
        (plan.out_dir / "failed" / nb.name).unlink(missing_ok=True)  # a good copy stands
        return {"status": "ok", "seconds": stamp.get("seconds", 0.0),
                "executed": stamp.get("executed"), "reused": True}
    print(f"[flowmod] {nb.name} ...", flush=True)
    t0 = time.perf_counter()
    running, failed = _running_copy(target), plan.out_dir / "failed" / nb.name
    try:
        with _echo_progress(plan.out_dir / ".progress.log", nb.stem):
            papermill.execute_notebook(
                str(nb), str(running), parameters=values, kernel_name=kernel,
                cwd=str(nb.parent), progress_bar=False, log_output=False,
                kernel_manager_class=_kernel_manager(ipc))
    except papermill.PapermillExecutionError as e:
        failed.parent.mkdir(exist_ok=True)
        os.replace(running, failed)
        kept = "; the previous good copy is kept" if target.is_file() else ""
        raise NotebookFailed(
            f"{nb.name} failed in cell {e.exec_count}: {cell_error(e, p.run_path)}\n"
            f"executed copy with the traceback: {failed}{kept}",
            round(time.perf_counter() - t0, 1)) from None
    except BaseException:  # interrupted or papermill itself failed: no half-run copy stays
        running.unlink(missing_ok=True)
        raise
    seconds, executed = round(time.perf_counter() - t0, 1), time.strftime(TIME_FORMAT)
    _stamp(running, notebook_fingerprint(nb, values, p, plan.device), seconds, executed)
    os.replace(running, target)  # the good copy is replaced only by a good copy
    failed.unlink(missing_ok=True)
    print(f"[flowmod] {nb.name} ok ({seconds:.1f} s)", flush=True)
    return {"status": "ok", "seconds": seconds, "executed": executed}


def cell_error(e: papermill.PapermillExecutionError, run_path: Path) -> str:
    """``ename: evalue`` of a cell's error; a full disk that the stage driver did not name
    (a chapter's own write, or one in a chained error) as :class:`DiskFull`'s line for the
    run folder, the kernels' place of writing."""
    text = _ANSI.sub("", "\n".join([str(e.evalue), *e.traceback]))
    if e.ename != DiskFull.__name__ and disk_full(text):
        return f"{DiskFull.__name__}: {DiskFull.at(run_path, text)}"
    return f"{e.ename}: {e.evalue}"


def run(
    profile: str,
    overrides: dict[str, Any] | None = None,
    *,
    out_dir: Path | None = None,
    only: list[str] | None = None,
    kernel: str = "python3",
    notebooks_dir: Path | None = None,
    wait: bool = False,
) -> dict[str, Any]:
    """Validate the profile, then execute the notebooks; returns the run record.

    Raises :class:`ProfileError` for a bad profile (before any notebook runs),
    :class:`flowmod.lock.FolderBusy` when another run holds the run folder or the folder of
    executed notebooks (``wait``: wait for it), and :class:`NotebookFailed` at the first
    notebook that fails.
    """
    plan = preflight(profile, overrides, out_dir, only, notebooks_dir)
    command = f"runner --profile {profile}"
    with folder_lock(plan.p.run_path, command, wait), folder_lock(plan.out_dir, command, wait):
        with DiskFull.guard(plan.out_dir, "writing executed notebooks", "--out"):
            return _execute_all(plan, profile, overrides, only, kernel)


def _execute_all(plan: Plan, profile: str | Path, overrides: dict[str, Any] | None,
                 only: list[str] | None, kernel: str) -> dict[str, Any]:
    """Execute the plan's notebooks in order, keeping ``run_info.json`` current."""
    plan.out_dir.mkdir(parents=True, exist_ok=True)
    record = _record(plan, profile, overrides, partial=bool(only))
    info_path = plan.out_dir / "run_info.json"
    write_json(info_path, record)
    ipc = Path(tempfile.mkdtemp(prefix="flowmod-kernel-"))
    try:
        for nb, values in plan.notebooks:
            try:
                record["notebooks"][nb.stem] = execute(nb, values, plan, kernel, ipc)
            except NotebookFailed as e:
                record["notebooks"][nb.stem] = {"status": "failed", "seconds": e.seconds}
                record["status"] = "failed"
                raise
            finally:
                write_json(info_path, record)
    finally:
        shutil.rmtree(ipc, ignore_errors=True)
    record["status"] = "ok"
    record["finished"] = time.strftime(TIME_FORMAT)
    write_json(info_path, record)
    return record


def resolve_profile(profile: str | Path, overrides: dict[str, Any] | None = None,
                    say: Any = print) -> Params:
    """The validated profile with its ``flow_networks`` whose weights are present added to
    ``flow_methods`` (one line each said, added or not)."""
    p = load_profile(profile, **(overrides or {}))
    methods, notes = planned_methods(p)
    for line in notes:
        say(line)
    if methods != p.flow_methods:
        p = load_profile(profile, **{**(overrides or {}), "flow_methods": methods})
    return p


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m flowmod.runner", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--profile", default="demo", help="params/<name>.yaml or a YAML path")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a parameter (YAML value), repeatable")
    ap.add_argument("--only", action="append", default=None, metavar="NN",
                    help="run only notebooks whose name starts with this, repeatable")
    ap.add_argument("--out", type=Path, default=None, help="folder for executed notebooks")
    ap.add_argument("--wait", action="store_true",
                    help="if another run holds the run folder, wait for it instead of stopping")
    ap.add_argument("--status", action="store_true",
                    help="print, per stage, whether its artefacts are up to date and why not; "
                         "run nothing")
    ap.add_argument("--gc", action="store_true",
                    help="remove per-pair cache files no node of the profile can read (other "
                         "worlds, options, crop geometries); run nothing")
    ap.add_argument("--dry-run", action="store_true", help="with --gc: only say what it frees")
    ap.add_argument("--variants", action="store_true",
                    help="with --gc: also drop kept earlier results (switching back to their "
                         "parameters then recomputes) and the cache files only they read")
    ap.add_argument("--worlds", action="store_true",
                    help="with --gc: also remove the generated worlds under the dataroot "
                         "other than this profile's (another run may still want them)")
    return ap


def _gc(args: argparse.Namespace) -> None:
    p = resolve_profile(args.profile, parse_overrides(args.overrides))
    check_folders(p)
    if not p.run_path.exists():  # nothing to free, and a dry run creates nothing
        print(f"{p.run_path}: no run folder; nothing to free")
        return
    with folder_lock(p.run_path, "runner --gc", wait=args.wait):
        n, size = pipeline.collect_garbage(p, dry_run=args.dry_run, variants=args.variants,
                                           worlds=args.worlds)
    verb = "would free" if args.dry_run else "freed"
    print(f"{p.run_path}: {n} cache files/folders no node reads; {verb} {size / 1e6:.1f} MB")
    others = world_source.other_worlds(p)
    if others and not args.worlds:
        print(f"{len(others)} other generated world(s) under {others[0].parent} "
              "(--gc --worlds removes them)")


def kill_kernels() -> None:
    """SIGKILL the process group of every kernel this process started that still runs (its
    own session: a Ctrl-C in the terminal never reaches it). Left to die with the runner,
    a kernel stopped mid-cell prints a ZMQ traceback over the runner's one line; killed,
    it leaves what ``kill -9`` leaves (building folders the next run resumes)."""
    for km in list(KERNELS):
        proc = getattr(km.provisioner, "process", None)
        if proc is not None and proc.poll() is None:
            with contextlib.suppress(OSError):
                group = os.getpgid(proc.pid)
                if group != os.getpgrp():  # never the runner's own group
                    os.killpg(group, signal.SIGKILL)


@contextlib.contextmanager
def stop_signals() -> Iterator[None]:
    """For the block, Ctrl-C (SIGINT) and SIGTERM kill the running kernels
    (:func:`kill_kernels`) and raise KeyboardInterrupt and :class:`Terminated` where the
    runner is, so that it unwinds alike for both (in the main thread; elsewhere nothing
    changes); the previous handlers are put back after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        kill_kernels()
        raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt

    old = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        with stop_signals():
            if args.gc:
                _gc(args)
            elif args.status:
                p = resolve_profile(args.profile, parse_overrides(args.overrides))
                check_folders(p)
                print(pipeline.format_status(p))
            else:
                run(args.profile, parse_overrides(args.overrides), out_dir=args.out,
                    only=args.only, wait=args.wait)
    except (ProfileError, FolderBusy) as e:
        print(f"{type(e).__name__}: {e}", file=sys.stderr)
        return 2
    except NotebookFailed as e:
        print(f"NotebookFailed: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as e:
        how = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted (Ctrl-C)"
        print(f"{how}: python -m flowmod.runner --profile {args.profile} stopped; the "
              "published results are untouched and the same command resumes", file=sys.stderr)
        return 143 if isinstance(e, Terminated) else 130
    except OSError as e:
        print(os_error_line(e), file=sys.stderr)
        return 2
    return 0


def os_error_line(e: OSError) -> str:
    """One line for an unusable folder or file: what, where, and what to do."""
    if isinstance(e, DiskFull):
        return str(e)
    where = e.filename or "a file of the run"
    if e.errno == errno.ENOSPC:
        return (f"no space left on the device of {where}: free some (make gc, or remove old "
                "runs) or point run_dir / --out elsewhere, then rerun: finished work is kept")
    if e.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        return (f"cannot write {where} ({e.strerror}): give a writable run_dir (--set "
                "run_dir=...) or --out")
    if e.errno in (errno.ENOTDIR, errno.EEXIST):
        return (f"{where}: a file stands where a folder is needed ({e.strerror}); remove it "
                "or choose another run_dir / --out")
    return f"{where}: {e.strerror or e}"


if __name__ == "__main__":
    raise SystemExit(main())
