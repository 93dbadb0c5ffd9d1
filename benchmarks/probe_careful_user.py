"""Rerun issue 53's careful-user probes (items 1-9) on the smoke profile; print what a user sees.

    PYTHONPATH=src .venv/bin/python benchmarks/probe_careful_user.py [code pool frame ...]

Needs a built smoke study in runs/smoke, data/smoke and build/executed (+ build/html for
`bytes`): ``python -m flowmod.runner --profile smoke --set run_dir=$PWD/runs/smoke --set
dataroot=$PWD/data/smoke --out $PWD/build/executed``. Every destructive probe works on copies
under $PROBE_SCRATCH (default /tmp/careful_user); the worktree is never edited (the code probe
edits a copy of src/). `disk` mounts a 60 MB tmpfs (root) and unmounts it. One line per
finding, then ``VERDICT <probe>: ok|NOT OK``. Slow: bytes (~6 min), sigterm, annotation.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUN, DATA, EXE, HTML = (ROOT / "runs/smoke", ROOT / "data/smoke", ROOT / "build/executed",
                        ROOT / "build/html")
S = Path(os.environ.get("PROBE_SCRATCH", "/tmp/careful_user"))
PY = sys.executable


def sh(*cmd: object, src: Path = ROOT / "src", **kw: object) -> tuple[int, str]:
    """Run ``cmd`` with the package from ``src``; (exit code, stdout + stderr)."""
    env = {**os.environ, "PYTHONPATH": str(src), "FLOWMOD_ROOT": str(ROOT)}
    p = subprocess.run([str(c) for c in cmd], cwd=ROOT, env=env, capture_output=True, text=True,
                       **kw)
    return p.returncode, p.stdout + p.stderr


def runner(run: Path, *extra: object, data: Path = DATA, **kw: object) -> tuple[int, str]:
    return sh(PY, "-m", "flowmod.runner", "--profile", "smoke", "--set", f"run_dir={run}",
              "--set", f"dataroot={data}", *extra, **kw)


def status(run: Path, **kw: object) -> dict[str, str]:
    """``{node: 'state  why'}`` and ``{'': summary line}`` of ``--status``."""
    rc, out = runner(run, "--status", **kw)
    lines = out.strip().splitlines()
    rows = {ln.split()[1]: " ".join(ln.split()[2:]) for ln in lines if re.match(r"\d\d  ", ln)}
    return {**rows, "": f"rc={rc} {lines[-1] if lines else ''}"}


def copy(src: Path, name: str) -> Path:
    dst = S / name
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst, symlinks=True)
    return dst


def show(label: str, rc: int, out: str) -> None:
    """The last line, how many lines, whether a traceback was printed."""
    lines = [ln for ln in out.strip().splitlines() if "%|" not in ln]
    said = [ln for ln in lines if not ln.startswith("[flowmod]")] or lines[-1:]
    tb = ", TRACEBACK" if "Traceback" in out else ""
    print(f"  {label}: rc={rc}, {len(lines)} line(s){tb}: {' | '.join(said)[:400]}")


def sha(f: Path) -> str:
    return hashlib.sha256(f.read_bytes()).hexdigest()


def not_fresh(d: dict[str, str]) -> dict[str, str]:
    return {k: v for k, v in d.items() if k and not v.startswith("up to date")}


def verdict(name: str, ok: bool) -> None:
    print(f"VERDICT {name}: {'ok' if ok else 'NOT OK'}")


def npy_body(f: Path) -> int:
    """Offset of an .npy file's data (after its header)."""
    b = f.read_bytes()[:12]
    return 10 + int.from_bytes(b[8:10], "little") if b[6] == 1 else 12 + int.from_bytes(b[8:12], "little")


def world() -> Path:
    return next(p for p in (DATA / "worlds").iterdir() if p.is_dir())


# --- 1 ------------------------------------------------------------------------------------

def p_code() -> None:
    """Crop window x1.25 in a copy of src/: exactly the stages importing crops.py (and their
    readers) go stale; a docstring edit changes nothing."""
    src = copy(ROOT / "src", "src-code")
    crops = src / "flowmod/crops.py"
    text = crops.read_text()
    line = "    n = np.maximum(1, _round_half_up(scale * np.maximum(w, h)))"
    crops.write_text(text.replace(line, line.replace("scale *", "1.25 * scale *")))
    st = status(RUN, src=src)
    code_of = json.loads(sh(PY, "-c", "import json; from flowmod import pipeline; print(json."
                            "dumps({s.name: 'crops.py' in s.code() for s in pipeline.STAGES}))",
                            src=src)[1])
    said = {n.split("[")[0] for n, v in st.items() if "code changed since built: crops.py" in v}
    want = {s for s, uses in code_of.items() if uses}
    print(f"  edited: {st['']}; 'code changed since built: crops.py' on stages {sorted(said)}")
    print(f"  stale but not importing crops.py: {sorted(k for k, v in not_fresh(st).items() if k.split('[')[0] not in want)}")
    crops.write_text(text.replace('"""Square crop windows for boxes.', '"""Square crop windows, boxes.'))
    doc = status(RUN, src=src)[""]
    back = status(RUN)[""]
    print(f"  docstring only: {doc}; unedited: {back}")
    verdict("1 code", said == want and doc.endswith("47 of 47 up to date")
            and back.endswith("47 of 47 up to date"))


# --- 2 ------------------------------------------------------------------------------------

def p_pool() -> None:
    run = copy(RUN, "run-pool")
    exe = copy(EXE, "exe-pool")
    man = json.loads((run / "flow/dis/keyframe/manifest.json").read_text())
    rel = next(k for k in man["files"] if "/pool/" in k)
    f = (run / "flow/dis/keyframe" / rel).resolve()
    orig, off = f.read_bytes(), npy_body(f)
    f.write_bytes(orig[:off] + bytes(len(orig) - off))
    print(f"  zeroed {f.relative_to(run)} ({len(orig)} bytes, header kept)")
    print(f"  status: flow[dis/keyframe] {status(run)['flow[dis/keyframe]']}")
    show("crops rebuild, crop_size=32", *runner(run, "--only", "05", "--set", "crop_size=32",
                                                "--out", S / "exe-pool32"))
    before = {p: p.stat().st_mtime_ns for p in f.parent.glob("*.npy")}
    rc, out = runner(run, "--out", exe)
    show("normal run", rc, out)
    redone = [p.name for p, t in before.items() if p.stat().st_mtime_ns != t]
    same = f.read_bytes() == orig
    print(f"  pool files rewritten: {redone}; bytes equal the original: {same}; {status(run)['']}")
    f.unlink()
    print(f"  deleted: flow[dis/keyframe] {status(run)['flow[dis/keyframe]']}")
    rc2, out2 = runner(run, "--only", "03", "--out", exe)
    show("runner --only 03", rc2, out2)
    back = f.is_file() and f.read_bytes() == orig
    print(f"  file back with its bytes: {back}; {status(run)['']}")
    verdict("2 pool", same and redone == [f.name] and back and "Traceback" not in out + out2)


# --- 3 ------------------------------------------------------------------------------------

def p_frame() -> None:
    run, data = copy(RUN, "run-frame"), copy(DATA, "data-frame")
    base = status(run, data=data)
    print(f"  copied world, before the edit: {base['']}")
    img = sorted((data / "worlds" / world().name / "samples/CAM_FRONT").glob("*.jpg"))[5]
    b = bytearray(img.read_bytes())  # 16 quantisation steps + 3: other pixels, still a JPEG
    q = b.find(b"\xff\xdb") + 5
    b[q:q + 16] = bytes(min(x + 3, 254) if x else x for x in b[q:q + 16])
    img.write_bytes(bytes(b))
    st = status(run, data=data)
    print(f"  edited {img.name} (its quantisation table, same size, still decodes)")
    print(f"  world: {st['world'][:300]}")
    print(f"  {st['']}; still up to date: {[k for k in st if k and k not in not_fresh(st)]}")
    pools = {p: p.stat().st_mtime_ns for p in (run / "flow").rglob("pool/*/*.npy")}
    show("runner --only 01 02 03", *runner(run, "--only", "01", "--only", "02", "--only", "03",
                                           "--out", copy(EXE, "exe-frame"), data=data))
    redone = [p for p in (run / "flow").rglob("pool/*/*.npy") if pools.get(p) != p.stat().st_mtime_ns]
    print(f"  pool files written: {sorted(str(p.relative_to(run / 'flow')).split('/')[0] for p in redone)}")
    verdict("3 frame", img.name in st["world"] and len(not_fresh(st)) == 46)


# --- 4 ------------------------------------------------------------------------------------

def p_disk() -> None:
    mnt = S / "tmpfs"
    mnt.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=60m", "tmpfs", mnt], check=True)
    try:
        rc, out = runner(mnt / "run", "--out", S / "exe-disk")
        show("smoke run, run_dir on 60 MB", rc, out)
        st = status(mnt / "run")
        bad = {k: v for k, v in st.items() if "damaged" in v}
        print(f"  then: {st['']}; damaged: {bad}")
        hidden = sorted(str(p.relative_to(mnt)) for p in mnt.rglob(".*") if ".lock" not in p.name)
        sizes = {p.stat().st_size for p in mnt.rglob("pool/*/*.npy")}
        print(f"  hidden files left: {hidden[:6]}; pool files kept: "
              f"{len(list(mnt.rglob('pool/*/*.npy')))}, sizes {sorted(sizes)}")
        verdict("4 disk", rc != 0 and "Traceback" not in out and "DiskFull: no space left in "
                f"{mnt / 'run'}" in out and not bad and len(sizes) <= 2)
    finally:
        subprocess.run(["umount", mnt], check=True)


# --- 5 ------------------------------------------------------------------------------------

def p_bookout() -> None:
    S.mkdir(exist_ok=True)
    f = S / "book-out.txt"
    f.write_text("my notes\n")
    rc, out = sh(PY, "-m", "flowmod.report.book", "--executed", EXE, "--out", f)
    show("book --out <a file>", rc, out)
    left = sorted(p.name for p in S.glob(".book-out*"))
    kept = f.is_file() and f.read_text() == "my notes\n"
    print(f"  file untouched: {kept}; hidden leftovers: {left}")
    verdict("5 book --out", rc != 0 and len(out.strip().splitlines()) == 1 and kept and not left)


# --- 6 ------------------------------------------------------------------------------------

def p_predict() -> None:
    frames = sorted((world() / "samples/CAM_FRONT").glob("*.jpg"))[:2]
    boxes = S / "boxes.csv"
    S.mkdir(exist_ok=True)
    boxes.write_text("xmin,ymin,xmax,ymax\n100,100,140,140\n")
    good = RUN / "models/dis/f0s0"
    rec = json.loads((good / "manifest.json").read_text())
    cases = {"good model": (rec, "auto"),
             "manifest without node": ({k: v for k, v in rec.items() if k != "node"}, "auto"),
             "without node and recipe": ({k: v for k, v in rec.items()
                                          if k not in ("node", "recipe")}, "auto"),
             "recipe crop_size null": ({**rec, "recipe": {**rec["recipe"], "crop_size": None}},
                                       "auto"),
             "--device cuda": (rec, "cuda"), "--device foo": (rec, "foo")}
    ok = True
    for name, (manifest, device) in cases.items():
        model = copy(good, "model-predict")
        (model / "manifest.json").write_text(json.dumps(manifest))
        rc, out = sh(PY, "-m", "flowmod.predict", *frames, "--boxes", boxes, "--model",
                     model / "best.pt", "--device", device)
        show(name, rc, out)
        ok &= "Traceback" not in out and (rc == 0 or len(out.strip().splitlines()) == 1)
    verdict("6 predict", ok)


# --- 7 ------------------------------------------------------------------------------------

def p_mtime() -> None:
    run = copy(RUN, "run-mtime")
    status(run)  # the digest cache holds every file now
    f = sorted((run / "crops/dis/keyframe").rglob("*.npy"))[0]
    st0 = f.stat()
    b = bytearray(f.read_bytes())
    b[-100:] = bytes(100)
    f.write_bytes(bytes(b))
    os.utime(f, ns=(st0.st_atime_ns, st0.st_mtime_ns))
    st = status(run)
    print(f"  {f.relative_to(run)} changed, mtime put back: crops[dis/keyframe] "
          f"{st['crops[dis/keyframe]'][:200]}")
    ok = "damaged" in st["crops[dis/keyframe]"]
    for bad in ('{"x": 5}', "[1, 2]", "not json", json.dumps({str(f): [1, "a"]})):
        (run / ".digests.json").write_text(bad)
        rc, out = runner(run, "--status")
        last = out.strip().splitlines()[-1]
        print(f"  .digests.json = {bad[-40:]}: rc={rc}, traceback: {'Traceback' in out}; {last}")
        ok &= rc == 0 and "Traceback" not in out and last.startswith("46 of 47")
    verdict("7 mtime/digests", ok)


# --- 8 ------------------------------------------------------------------------------------

def digest_tree(root: Path, pattern: str) -> dict[str, str]:
    return {str(p.relative_to(root)): sha(p) for p in sorted(root.rglob(pattern)) if p.is_file()}


def p_bytes() -> None:
    exe, html = copy(EXE, "exe-bytes"), copy(HTML, "html-bytes")
    before = digest_tree(exe, "*.ipynb"), digest_tree(html, "*.html"), digest_tree(html, "_sources/*")
    show("runner again", *runner(RUN, "--out", exe))  # same run_dir: the copies stay reusable
    show("book again", *sh(PY, "-m", "flowmod.report.book", "--executed", exe, "--out", html))
    after = digest_tree(exe, "*.ipynb"), digest_tree(html, "*.html"), digest_tree(html, "_sources/*")
    changed = [k for b, a in zip(before, after, strict=True) for k in set(b) | set(a) if b.get(k) != a.get(k)]
    print(f"  notebooks/pages/_sources: {[len(b) for b in before]}; changed: {changed}")
    run = copy(RUN, "run-bytes")
    pt = run / "models/dis/f0s0/best.pt"
    old = sha(pt)
    pt.unlink()
    show("best.pt deleted, runner --only 06", *runner(run, "--only", "06", "--out",
                                                      copy(EXE, "exe-bytes06")))
    same = pt.is_file() and sha(pt) == old
    print(f"  rebuilt best.pt has the same bytes: {same}")
    verdict("8 bytes", not changed and same)


# --- 9 ------------------------------------------------------------------------------------

def p_minor() -> None:
    S.mkdir(exist_ok=True)
    (S / "afile").write_text("x")
    rc, out = runner(S / "afile", "--status")
    show("--status, run_dir a file", rc, out)
    ok = len(out.strip().splitlines()) == 1
    # two book builds at once: the second's FolderBusy line, and is its --wait real?
    html = copy(HTML, "html-busy")
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    first = subprocess.Popen([PY, "-m", "flowmod.report.book", "--executed", EXE, "--out", html],
                             cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(3)
    rc, out = sh(PY, "-m", "flowmod.report.book", "--executed", EXE, "--out", html)
    first.wait()
    helps = "--wait" in sh(PY, "-m", "flowmod.report.book", "--help")[1]
    show("second book build", rc, out)
    print(f"  book --help has --wait: {helps}")
    ok &= "FolderBusy" in out and "--wait" in out and helps
    # a stale failed/NN.ipynb after a later good run
    exe = copy(EXE, "exe-failed")
    (exe / "failed").mkdir(exist_ok=True)
    shutil.copy(exe / "05_preprocessing.ipynb", exe / "failed/05_preprocessing.ipynb")
    (exe / "05_preprocessing.ipynb").unlink()
    show("failed/05 planted, runner --only 05", *runner(copy(RUN, "run-failed"), "--only", "05",
                                                        "--out", exe))
    print(f"  failed/05_preprocessing.ipynb still there: {(exe / 'failed/05_preprocessing.ipynb').exists()}")
    ok &= not (exe / "failed/05_preprocessing.ipynb").exists()
    exe = copy(EXE, "exe-failed-reused")  # the same when the good copy is reused
    (exe / "failed").mkdir(exist_ok=True)
    shutil.copy(exe / "04_labeling.ipynb", exe / "failed/04_labeling.ipynb")
    show("failed/04 planted, runner --only 04", *runner(RUN, "--only", "04", "--out", exe))
    print(f"  failed/04_labeling.ipynb still there: {(exe / 'failed/04_labeling.ipynb').exists()}")
    ok &= not (exe / "failed/04_labeling.ipynb").exists()
    # papermill directly, with a value out of range
    rc, out = sh(ROOT / ".venv/bin/papermill", "notebooks/00_setup.ipynb", S / "out.ipynb",
                 "-p", "seed", "-1", "-p", "run_dir", RUN, "-p", "dataroot", DATA)
    kernel = out[out.find("Exception encountered"):] if "Exception encountered" in out else out
    print(f"  papermill seed=-1: rc={rc}, {len(out.strip().splitlines())} lines; "
          f"kernel part names seed: {'seed' in kernel}; last: {out.strip().splitlines()[-1][:200]}")
    verdict("9 minor (status file, book busy, failed/, papermill)", ok)


def p_sigterm() -> None:
    run = copy(RUN, "run-term")
    (run / "models/dis/f0s0/best.pt").unlink()  # so chapter 06 has a model to train
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    proc = subprocess.Popen([PY, "-m", "flowmod.runner", "--profile", "smoke", "--set",
                             f"run_dir={run}", "--set", f"dataroot={DATA}", "--only", "06",
                             "--out", copy(EXE, "exe-term")], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    time.sleep(25)
    proc.send_signal(signal.SIGTERM)
    out = proc.communicate()[0]
    show("SIGTERM after 25 s", proc.returncode, out)
    st = status(run)
    print(f"  then: {st['']}; not up to date: {not_fresh(st)}")
    verdict("9 SIGTERM", "Traceback" not in out and "SIGTERM" in out and len(not_fresh(st)) == 1)


def p_annotation() -> None:
    """Move one sample_annotation by 2 m: no gt and no dis pool file is computed again."""
    run, data = copy(RUN, "run-ann"), copy(DATA, "data-ann")
    tables = data / "worlds" / world().name / "v1.0-synth"
    anns = json.loads((tables / "sample_annotation.json").read_text())
    anns[len(anns) // 2]["translation"][0] += 2.0
    (tables / "sample_annotation.json").write_text(json.dumps(anns))
    def pool(m: str) -> dict[str, int]:
        return {p.name: p.stat().st_mtime_ns for p in (run / "flow" / m / "pool").rglob("*.npy")}
    pools = {m: pool(m) for m in ("gt", "dis")}
    print(f"  world after the edit: {status(run, data=data)['world'][:200]}")
    show("runner --only 01 02 03", *runner(run, "--only", "01", "--only", "02", "--only", "03",
                                           "--out", copy(EXE, "exe-ann"), data=data))
    new = {m: sum(pools[m].get(k) != t for k, t in pool(m).items()) for m in pools}
    print(f"  pool files written (new or rewritten): {new}")
    verdict("9 annotation", not any(new.values()))


PROBES = {"code": p_code, "pool": p_pool, "frame": p_frame, "disk": p_disk,
          "bookout": p_bookout, "predict": p_predict, "mtime": p_mtime, "bytes": p_bytes,
          "minor": p_minor, "sigterm": p_sigterm, "annotation": p_annotation}

if __name__ == "__main__":
    for name in sys.argv[1:] or list(PROBES):
        print(f"== {name}", flush=True)
        PROBES[name]()
        sys.stdout.flush()
