"""Run the study: execute ``notebooks/NN_*.ipynb`` in order with papermill.

    python -m flowmod.runner --profile demo                 # every notebook
    python -m flowmod.runner --profile smoke --only 00_setup
    python -m flowmod.runner --profile paper --set dataroot=/data/nuscenes --set epochs=2

The profile is validated (with the overrides) before anything runs. Each notebook receives only
the parameters its ``parameters`` cell declares; its executed copy goes to ``--out``
(``build/executed/`` by default). The run stops at the first failing notebook and prints its
error; ``run_info.json`` beside the executed notebooks records the profile, the parameters,
package versions, the git commit and the seconds each notebook took.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from flowmod import environment
from flowmod.artefacts import write_json
from flowmod.params import Params, ProfileError, load_profile, parse_overrides, profile_path
from flowmod.paths import repo_root


class NotebookFailed(RuntimeError):
    """A notebook raised; the message carries its name, the error and the executed copy."""


def notebooks(folder: Path | None = None) -> list[Path]:
    """The study's notebooks, ``NN_name.ipynb``, in order."""
    folder = folder or repo_root() / "notebooks"
    return sorted(p for p in folder.glob("[0-9][0-9]_*.ipynb"))


def declared_parameters(nb: Path) -> dict[str, dict[str, Any]]:
    """The parameters a notebook declares in its ``parameters`` cell (papermill's inference)."""
    import papermill

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
    return {k: values[k] for k in declared}


def run(
    profile: str,
    overrides: dict[str, Any] | None = None,
    *,
    out_dir: Path | None = None,
    only: list[str] | None = None,
    kernel: str = "python3",
    notebooks_dir: Path | None = None,
) -> dict[str, Any]:
    """Validate the profile, then execute the notebooks; returns the run record.

    Raises :class:`ProfileError` for a bad profile (before any notebook runs) and
    :class:`NotebookFailed` at the first notebook that fails.
    """
    import papermill

    p = load_profile(profile, **(overrides or {}))
    out_dir = Path(out_dir or repo_root() / "build" / "executed")
    selected = notebooks(notebooks_dir)
    if only:
        selected = [nb for nb in selected if any(nb.stem.startswith(o) for o in only)]
        if not selected:
            raise ProfileError(f"--only {only} matches no notebook in notebooks/")
    # Check every notebook's parameters before running the first one.
    plan = [(nb, notebook_parameters(nb, p)) for nb in selected]
    try:
        device = environment.device_info(p.device)
    except RuntimeError as e:
        raise ProfileError(f"device={p.device!r}: {e}") from None
    if not p.synthetic:  # real data must be there before the first notebook starts
        from flowmod.select import SelectionError, check_dataroot

        try:
            check_dataroot(p.dataroot_path, p.version)
        except SelectionError as e:
            raise ProfileError(f"dataroot={p.dataroot!r}, version={p.version!r}: {e}") from None

    out_dir.mkdir(parents=True, exist_ok=True)
    record: dict[str, Any] = {
        "profile": p.profile,
        "profile_file": str(profile_path(profile)),
        "overrides": overrides or {},
        "parameters": p.model_dump(),
        "commit": environment.git_commit(),
        "versions": environment.versions().set_index("package")["version"].to_dict(),
        "device": device,
        "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "notebooks": {},
        "status": "running",
    }
    info_path = out_dir / "run_info.json"
    if only and info_path.is_file():
        # a partial rerun with the same parameters keeps the other notebooks' records
        import json

        old = json.loads(info_path.read_text())
        if old.get("parameters") == record["parameters"] and old.get("status") == "ok":
            record["notebooks"] = {k: v for k, v in old["notebooks"].items()
                                   if k not in {nb.stem for nb, _ in plan}}
            record["started"] = old["started"]
    write_json(info_path, record)
    for nb, values in plan:
        target = out_dir / nb.name
        print(f"[flowmod] {nb.name} ...", flush=True)
        t0 = time.perf_counter()
        try:
            papermill.execute_notebook(
                str(nb), str(target), parameters=values, kernel_name=kernel,
                cwd=str(nb.parent), progress_bar=False, log_output=False,
            )
        except papermill.PapermillExecutionError as e:
            seconds = time.perf_counter() - t0
            record["notebooks"][nb.stem] = {"status": "failed", "seconds": round(seconds, 1)}
            record["status"] = "failed"
            write_json(info_path, record)
            raise NotebookFailed(
                f"{nb.name} failed in cell {e.exec_count}: {e.ename}: {e.evalue}\n"
                f"executed copy with the traceback: {target}"
            ) from None
        seconds = time.perf_counter() - t0
        record["notebooks"][nb.stem] = {"status": "ok", "seconds": round(seconds, 1)}
        write_json(info_path, record)
        print(f"[flowmod] {nb.name} ok ({seconds:.1f} s)", flush=True)
    record["status"] = "ok"
    record["finished"] = time.strftime("%Y-%m-%d %H:%M:%S %Z")
    write_json(info_path, record)
    return record


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m flowmod.runner", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--profile", default="demo", help="params/<name>.yaml or a YAML path")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a parameter (YAML value), repeatable")
    ap.add_argument("--only", action="append", default=None, metavar="NN",
                    help="run only notebooks whose name starts with this, repeatable")
    ap.add_argument("--out", type=Path, default=None, help="folder for executed notebooks")
    args = ap.parse_args(argv)
    try:
        run(args.profile, parse_overrides(args.overrides), out_dir=args.out, only=args.only)
    except ProfileError as e:
        print(f"ProfileError: {e}", file=sys.stderr)
        return 2
    except NotebookFailed as e:
        print(f"NotebookFailed: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
