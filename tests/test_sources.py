"""Conventions of the notebook sources and the environment files."""

import os
import re
from importlib import metadata
from pathlib import Path

import nbformat
import papermill
import pytest
import yaml

from flowmod.params import Params, load_profile
from flowmod.paths import repo_root
from flowmod.runner import notebooks

NOTEBOOKS = notebooks()
MAX_CELL_LINES = 15  # longer logic belongs in src/flowmod


def test_there_are_notebooks():
    assert NOTEBOOKS and NOTEBOOKS[0].name == "00_setup.ipynb"


@pytest.mark.parametrize("nb_path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_is_stored_without_outputs(nb_path):
    nb = nbformat.read(nb_path, as_version=4)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert not cell.outputs, f"{nb_path.name} cell {i} has stored outputs"
            assert cell.execution_count is None, f"{nb_path.name} cell {i} has a count"
    assert "papermill" not in nb.metadata, f"{nb_path.name} is an executed copy"


@pytest.mark.parametrize("nb_path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_parameters_are_typed_documented_and_demo_defaults(nb_path):
    nb = nbformat.read(nb_path, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert "parameters" in code[0].metadata.get("tags", []), "first code cell must be tagged"
    declared = papermill.inspect_notebook(str(nb_path))
    assigned = [ln for ln in code[0].source.splitlines() if re.match(r"^[a-z_]+\s*:", ln)]
    assert len(assigned) == len(declared), (
        f"{nb_path.name}: papermill parsed {len(declared)} of {len(assigned)} parameters "
        "(avoid '=' and quotes in the comments)"
    )
    demo = load_profile("demo").model_dump()
    for name, spec in declared.items():
        assert name in Params.model_fields, f"{nb_path.name}: {name} is not a Params field"
        assert spec["inferred_type_name"] != "None", f"{nb_path.name}: {name} has no type hint"
        assert spec["help"], f"{nb_path.name}: {name} has no comment"
        assert yaml.safe_load(spec["default"].replace("None", "null")) == demo[name], (
            f"{nb_path.name}: default of {name} differs from the demo profile"
        )


@pytest.mark.parametrize("nb_path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_cells_are_short(nb_path):
    nb = nbformat.read(nb_path, as_version=4)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code" and "parameters" not in cell.metadata.get("tags", []):
            n = len(cell.source.strip().splitlines())
            assert n <= MAX_CELL_LINES, f"{nb_path.name} cell {i}: {n} lines; move logic to src"


def _pins(lines):
    pins = {}
    for line in lines:
        m = re.match(r"^\s*(?:- )?([A-Za-z0-9_.\-]+)==([^\s#]+)", line)
        if m:
            pins[m.group(1).lower()] = m.group(2)
    return pins


def test_requirements_pinned_and_conda_twin_agrees():
    env = repo_root() / "environment"
    req_lines = [
        ln for ln in (env / "requirements.txt").read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    ]
    assert all("==" in ln for ln in req_lines), "every requirement must be pinned with =="
    req = _pins(req_lines)
    conda = _pins((env / "environment.yml").read_text().splitlines())
    assert req == conda
    assert req["numpy"].startswith("1."), "nuscenes-devkit 1.2.0 needs numpy<2"
    assert req["nuscenes-devkit"] == "1.2.0"
    assert (req["torch"], req["torchvision"]) == ("2.14.1", "0.29.1")


def test_installed_versions_match_the_pins():
    req = _pins((repo_root() / "environment" / "requirements.txt").read_text().splitlines())
    wrong = {}
    for name, pin in req.items():
        have = metadata.version(name)
        if have.split("+")[0] != pin:
            wrong[name] = (pin, have)
    assert not wrong, f"installed versions differ from requirements.txt (run make env): {wrong}"


@pytest.mark.parametrize("nb_path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_declares_every_parameter_its_stages_read(nb_path):
    """A chapter that builds a stage must receive every parameter the stage reads, or the
    stage would silently fingerprint (and use) the demo default instead of the profile's."""
    from flowmod import dag, pipeline

    p = load_profile("demo")
    declared = set(papermill.inspect_notebook(str(nb_path)))
    for node in pipeline.nodes(p, [nb_path.stem[:2]]):
        missing = set(dag.reads(node)) - declared
        assert not missing, f"{nb_path.name} builds {node} but does not declare {sorted(missing)}"
        if node.stage != "world":
            assert "force" in declared, f"{nb_path.name} builds {node}: declare force"
        if node.method:
            assert "flow_methods" in declared, f"{nb_path.name} builds {node}: flow_methods"
        if node.stage in ("train", "evaluate", "generalise"):
            assert "seeds" in declared, f"{nb_path.name} builds {node}: declare seeds"


#: Widest code line the book's page shows without cutting it (sphinx-book-theme at 1280 px).
MAX_LINE = 76


def _shown_code_cells(nb):
    for i, cell in enumerate(nb.cells):
        tags = cell.metadata.get("tags", [])
        if cell.cell_type == "code" and not {"parameters", "remove-cell", "remove-input"} & set(
                tags):
            yield i, cell


@pytest.mark.parametrize("nb_path", NOTEBOOKS, ids=lambda p: p.stem)
def test_code_on_the_page_fits_its_width(nb_path):
    nb = nbformat.read(nb_path, as_version=4)
    for i, cell in _shown_code_cells(nb):
        for line in cell.source.splitlines():
            assert len(line) <= MAX_LINE, f"{nb_path.name} cell {i}: {len(line)} chars: {line}"


@pytest.mark.parametrize("nb_path", NOTEBOOKS, ids=lambda p: p.stem)
def test_figures_have_captions_and_bookkeeping_is_hidden(nb_path):
    import ast

    nb = nbformat.read(nb_path, as_version=4)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type != "code" or "parameters" in cell.metadata.get("tags", []):
            continue
        if "viz.show(" in cell.source:
            caption = cell.metadata.get("mystnb", {}).get("figure", {}).get("caption", "")
            assert len(caption.split()) >= 8, f"{nb_path.name} cell {i}: a figure needs a caption"
            assert cell.source.count("viz.show(") == 1, f"{nb_path.name} cell {i}: one figure"
        body = ast.parse(cell.source).body
        shows_nothing = (not body or not isinstance(body[-1], ast.Expr)) and (
            "display(" not in cell.source)
        if "glue(" in cell.source and shows_nothing and "viz.show(" not in cell.source:
            assert "remove-cell" in cell.metadata.get("tags", []), (
                f"{nb_path.name} cell {i} only records numbers: tag it remove-cell")


def try_it_commands(nb_path) -> list[str]:
    """The commands of a chapter's closing "Try it" section."""
    nb = nbformat.read(nb_path, as_version=4)
    last = nb.cells[-1]
    assert last.cell_type == "markdown" and last.source.startswith("## Try it"), (
        f"{nb_path.name} must end with a '## Try it' section")
    fenced = False
    for line in last.source.splitlines():
        fenced ^= line.startswith("```")
        assert not fenced or len(line) <= MAX_LINE, f"{nb_path.name}: too wide: {line}"
    text = last.source.replace("\\\n", " ")  # shell line continuations
    return [" ".join(ln.split()) for ln in text.splitlines()
            if ln.strip().startswith(".venv/bin/python -m flowmod.runner")]


@pytest.mark.parametrize("nb_path", NOTEBOOKS, ids=lambda p: p.stem)
def test_every_chapter_ends_with_try_it(nb_path):
    cmds = try_it_commands(nb_path)
    assert cmds, f"{nb_path.name}: 'Try it' gives no runner command"
    for cmd in cmds:
        assert "--profile demo" in cmd and ("--only" in cmd or "--status" in cmd), cmd
        assert "--set" in cmd, f"{cmd}: a 'Try it' changes one parameter"


def _venv_state() -> dict[str, tuple[bytes, int]]:
    """What ``make lab`` could rewrite in the venv: its kernelspecs and the editable
    install's files (which checkout the venv's flowmod points to)."""
    import sys

    prefix = Path(sys.prefix)
    files = [*prefix.glob("share/jupyter/kernels/*/kernel.json"),
             *prefix.glob("lib/python*/site-packages/*flowmod*"),
             *prefix.glob("lib/python*/site-packages/flowmod-*.dist-info/*")]
    return {str(f): (f.read_bytes(), f.stat().st_mtime_ns) for f in files if f.is_file()}


def test_make_lab_serves_the_notebooks_with_the_venvs_kernel(tmp_path):
    """``make lab`` starts JupyterLab on notebooks/ whose python3 kernel is this venv's. The
    test leaves the environment as it found it: the kernelspec goes to a scratch folder
    (``LAB_KERNELS``) and ``make -o env`` does not reinstall the venv (from a second
    checkout sharing it, that would re-point its editable flowmod)."""
    import json
    import os
    import re
    import signal
    import socket
    import subprocess
    import sys
    import time
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "JUPYTER_RUNTIME_DIR": str(tmp_path / "rt")}
    before = _venv_state()
    proc = subprocess.Popen(["make", "--no-print-directory", "-o", "env", "lab",
                             f"LAB_PORT={port}", f"LAB_KERNELS={tmp_path / 'kernels'}"],
                            cwd=repo_root(), env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        token, lines, t0 = None, [], time.monotonic()
        while token is None and time.monotonic() - t0 < 120:
            line = proc.stdout.readline()
            lines.append(line)
            m = re.search(rf"127\.0\.0\.1:{port}/lab\?token=(\w+)", line)
            token = m.group(1) if m else None
        assert token, "".join(lines[-20:])

        def get(path: str) -> dict:
            url = f"http://127.0.0.1:{port}{path}?token={token}"
            for attempt in range(10):  # the URL is printed as the server starts listening
                try:
                    return json.loads(urllib.request.urlopen(url, timeout=30).read())
                except urllib.error.URLError:
                    if attempt == 9:
                        raise
                    time.sleep(1)
            raise AssertionError("unreachable")

        spec = get("/api/kernelspecs")["kernelspecs"]["python3"]["spec"]
        assert spec["argv"][0] == sys.executable, spec["argv"]  # the venv's interpreter
        names = {c["name"] for c in get("/api/contents/")["content"]}
        assert {nb.name for nb in notebooks()} <= names
        assert (tmp_path / "kernels" / "share/jupyter/kernels/python3/kernel.json").is_file()
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
    assert _venv_state() == before, "make lab's test changed the venv"


def test_the_package_imports_without_the_heavy_optional_libraries():
    """Every notebook and CLI process imports the pipeline and the chapter backends; the
    devkit (with matplotlib and scikit-learn), torch (1.2-1.8 s), torchvision (with
    torch._dynamo) and Ray cost seconds at import and exit each, so the package imports them
    where they are used: torch where a model is built, trained or predicts (the book executes
    15 kernels and the tests ~50)."""
    import subprocess
    import sys

    code = ("import importlib, pkgutil, sys\n"
            "import flowmod.chapters, flowmod.pipeline, flowmod.runner, flowmod.report.viz\n"
            "for m in pkgutil.iter_modules(flowmod.chapters.__path__):\n"
            "    importlib.import_module('flowmod.chapters.' + m.name)\n"
            "print(sorted({n.split('.')[0] for n in sys.modules}"
            " & {'nuscenes', 'torch', 'torchvision', 'sklearn', 'ray'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_every_pt_file_is_written_by_the_one_checkpoint_writer():
    """``torch.save`` to a path puts the temporary file's random name into the zip, so the
    package writes ``.pt`` files only through ``artefacts.save_checkpoint`` (equal tensors,
    equal bytes). Two known exceptions, no stage's published file, are left until they
    switch to it (then this set is ``{"artefacts.py"}``): flow/pretrain.py (the shipped
    weights, made outside the stage graph) and flow/selftrain.py (``last.pt``, resumable,
    removed when its node is published)."""
    import ast

    def saves(f: Path) -> bool:
        return any(isinstance(n, ast.Call) and ast.unparse(n.func) == "torch.save"
                   for n in ast.walk(ast.parse(f.read_text())))

    pkg = repo_root() / "src" / "flowmod"
    writers = {str(f.relative_to(pkg)) for f in pkg.rglob("*.py") if saves(f)}
    assert writers == {"artefacts.py", "flow/pretrain.py", "flow/selftrain.py"}


def test_each_xdist_worker_computes_on_one_thread_of_every_pool():
    """``make test`` runs two pytest-xdist workers on two cores: each worker's torch, OpenCV
    and BLAS compute on one thread (tests/conftest.py). numpy's OpenBLAS, started before the
    limit with a thread per core, spun on the other worker's core (its notebooks ran about
    twice as long)."""
    import cv2
    import torch
    from threadpoolctl import threadpool_info

    if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) < 2:
        pytest.skip("one process: the thread pools keep their defaults")
    pools = {(i["internal_api"], i["filepath"]): i["num_threads"] for i in threadpool_info()}
    assert any(api == "openblas" for api, _ in pools), pools
    assert set(pools.values()) == {1}, pools
    assert (torch.get_num_threads(), cv2.getNumThreads()) == (1, 1)
