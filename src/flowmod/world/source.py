"""The world as the study's source stage: where the data is, its identity, and making it.

The ``world`` node is the data every other node reads: a world generated from the profile
(``synthetic: true``), in its own folder ``<dataroot>/worlds/<world_id>`` (so that the worlds
of other parameters never overwrite each other), or a nuScenes-format data set (real
nuScenes, ``synthetic: false``). Its fingerprint is its **content**, for both: the tables'
digests and, for a generated world, its camera frames' (sha256 of every image). Any edit of
the data (an annotation moved, an image cut short or changed in place at the same size)
therefore makes exactly the nodes that read it stale; nothing is known below a world that
is not there yet. Digests are cached by (size, mtime, ctime), so a status costs a stat call
per file. (Real nuScenes keeps the fingerprint of its tables alone: its 1.4 million images
are identified where they are read, by the image flow methods' per-pair keys.)
"""

from __future__ import annotations

import contextlib
import shutil
from pathlib import Path
from typing import Any

from flowmod import dag
from flowmod.artefacts import file_digest, file_digests, fingerprint, read_manifest, write_manifest
from flowmod.lock import file_lock
from flowmod.params import WORLD_FILE, WORLD_MANIFEST, Params
from flowmod.world.dataset import generate_world
from flowmod.world.truth import WorldError, is_synthetic

NODE = dag.Node("world")


def is_generated_world(p: Params) -> bool:
    """True if the profile's data is (or will be made as) a generated world."""
    vdir = p.dataroot_path / p.version
    return (vdir / WORLD_FILE).is_file() or (p.synthetic and not (vdir / "scene.json").is_file())


def table_digests(p: Params) -> dict[str, str]:
    """sha256 of every ``*.json`` table of ``<dataroot>/<version>`` (cached by stat)."""
    vdir = p.dataroot_path / p.version
    return {f.name: file_digest(f, dag.digest_cache(p))
            for f in sorted(vdir.glob("*.json")) if f.name != WORLD_MANIFEST}


def image_digests(p: Params) -> dict[str, str]:
    """``{relative path: sha256}`` of a generated world's camera images (``samples/``,
    ``sweeps/``), cached by stat in the run's digest cache: any edit of a frame, a
    same-size one included, changes it."""
    root = p.dataroot_path
    files = sorted(f for sub in ("samples", "sweeps") for f in (root / sub).rglob("*.jpg"))
    return dict(zip((f.relative_to(root).as_posix() for f in files),
                    file_digests(files, dag.digest_cache(p)), strict=True))


def content(p: Params) -> dict[str, Any]:
    """What the world's fingerprint is the hash of: its tables' digests and, for a
    generated world, its images' (one digest of :func:`image_digests`)."""
    out: dict[str, Any] = {"tables": table_digests(p)}
    if (p.dataroot_path / p.version / WORLD_FILE).is_file():
        out["images"] = fingerprint(image_digests(p), n=64)
    return out


def world_fingerprint(p: Params) -> str | None:
    """The world node's fingerprint now: its content's (None when the data is missing).
    Real data keeps the fingerprint of its tables alone."""
    if not (p.dataroot_path / p.version / "scene.json").is_file():
        return None
    c = content(p)
    if "images" not in c:
        return fingerprint({"stage": "world", "tables": fingerprint(
            sorted(c["tables"].items()), n=64)})
    return fingerprint({"stage": "world", **c})


def edits(p: Params) -> str:
    """What changed in a generated world since it was generated (tables and images named),
    or ``""``."""
    rec = read_manifest(p.dataroot_path / p.version / WORLD_MANIFEST)
    if not rec or "tables" not in rec:
        return ""
    now = table_digests(p)
    tables = sorted(k for k in set(rec["tables"]) | set(now) if rec["tables"].get(k) != now.get(k))
    images = []
    if isinstance(rec.get("images"), dict):
        now_images = image_digests(p)
        images = sorted(k for k in set(rec["images"]) | set(now_images)
                        if rec["images"].get(k) != now_images.get(k))
    if not tables and not images:
        return ""
    what = ([f"tables {', '.join(tables)}"] if tables else []) + (
        [f"{len(images)} image(s), e.g. {images[0]}"] if images else [])
    return (f"edited since it was generated ({'; '.join(what)}): its readers rebuild from "
            f"the edited data; remove {p.dataroot_path} to generate it again")


class WorldSource:
    """The world stage's :class:`flowmod.dag.Source`."""

    def location(self, p: Params) -> Path:
        return p.dataroot_path / p.version

    def fingerprint(self, p: Params) -> str | None:
        return world_fingerprint(p)

    def record(self, p: Params) -> dict[str, Any] | None:
        fp = world_fingerprint(p)
        return {"fingerprint": fp, "node": "world"} if fp else None

    def status(self, p: Params) -> tuple[str, str]:
        if world_fingerprint(p) is not None:
            return "up to date", edits(p) if is_generated_world(p) else ""
        path = self.location(p)
        if is_generated_world(p):
            return "missing", f"not generated yet at {path}"
        return "missing", f"no data at {path}"

    def ensure(self, p: Params, progress: bool) -> None:
        ensure_world(p, progress=progress)


def ensure_world(params: Params, *, progress: bool = True) -> Path:
    """Make sure the profile's data is there; return its root (``params.dataroot_path``).

    * real data (``synthetic: false``, or real tables at the dataroot): used as it is;
      missing: :class:`WorldError` naming the path and the fix;
    * a generated world: made in its own folder unless there (under a lock, so two runs
      never generate the same world at once), then its manifest records what was generated
      (:func:`edits` compares the data with it). A world present is used as it is, edits
      included: its content is its identity.
    """
    q = dag.StageParams(params, NODE)
    root, version = q.dataroot_path, q.version
    if not is_generated_world(params):
        if not (root / version / "scene.json").is_file():
            raise WorldError(
                f"nuScenes tables not found: {root / version} does not exist (or has no "
                f"scene.json). Set dataroot to the folder that holds {version}/, samples/ and "
                "sweeps/ (e.g. DATAROOT=/data/sets/nuscenes), or set synthetic: true to "
                "generate a synthetic world there.")
        return root
    if is_synthetic(root, version):
        return root
    with _world_lock(root, "generating it"):
        if not is_synthetic(root, version):  # another run may have made it meanwhile
            _generate(params, root, version, progress)
    return root


def _generate(p: Params, root: Path, version: str, progress: bool) -> None:
    """Generate the world of ``p`` into ``root`` and write its manifest."""
    g = p.world_generation()
    generate_world(root, version, n_scenes=g["world_scenes"], n_keyframes=g["world_keyframes"],
                   n_sweep_scenes=g["world_sweep_scenes"],
                   vehicles_per_scene=g["world_vehicles"], seed=g["seed"], n_jobs=p.n_jobs,
                   progress=progress, near_movers=g["world_near_movers"])
    write_manifest(root / version / WORLD_MANIFEST, {
        "node": "world", "world_id": p.world_id, "generation": g,
        "tables": table_digests(p), "images": image_digests(p),
        "fingerprint": world_fingerprint(p)})


def other_worlds(p: Params) -> list[Path]:
    """The generated worlds under ``p``'s dataroot other than ``p``'s own
    (``<dataroot>/worlds/<id>``)."""
    base = p.path(p.dataroot) / "worlds"
    own = p.dataroot_path
    return sorted(d for d in base.iterdir() if d.is_dir() and d != own) if base.is_dir() else []


def _world_lock(root: Path, doing: str) -> contextlib.AbstractContextManager[None]:
    """The lock of a generated world's folder (a file beside it, never inside)."""
    return file_lock(root.parent / f".{root.name}.lock", f"world {root.name}: {doing}",
                     what=root)


def remove_world(folder: Path) -> None:
    """Remove a generated world's folder, unless a run holds it (generating it)."""
    with _world_lock(folder, "removing it"):
        shutil.rmtree(folder)


#: The world stage (chapter 01): the data itself.
STAGE = dag.Stage("world", 1, "01", "", "the data: a generated world or nuScenes tables",
                  nodes=lambda p: [NODE], source=WorldSource())
