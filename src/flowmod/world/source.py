"""The world as the study's source stage: where the data is, its identity, and making it.

The ``world`` node is the data every other node reads: a world generated from the profile
(``synthetic: true`` and no real tables at the dataroot) or a nuScenes-format data set
(real nuScenes, or a generated world used as it is). Its fingerprint is that of its
generation parameters for a world generated from this profile and that of its tables'
content for any other data, so the identity of the data (another seed, another dataroot
holding other data) reaches every node below it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from flowmod import dag
from flowmod.artefacts import file_digest, fingerprint, read_manifest, write_manifest
from flowmod.params import Params
from flowmod.world.dataset import GENERATOR_VERSION, generate_world
from flowmod.world.truth import WORLD_FILE, WorldError, is_synthetic, world_params

#: The world's manifest, beside its tables (written by :func:`ensure_world`).
WORLD_MANIFEST = "flowmod.manifest.json"
NODE = dag.Node("world")


def is_generated_world(p: Params) -> bool:
    """True if the profile's data is (or will be made as) a generated world."""
    vdir = p.dataroot_path / p.version
    if (vdir / WORLD_FILE).is_file():
        return True
    return p.synthetic and not (vdir / "scene.json").is_file()


def tables_digest(p: Params) -> str:
    """sha256 over the content of every ``*.json`` table of ``<dataroot>/<version>``."""
    vdir = p.dataroot_path / p.version
    files = sorted(f for f in vdir.glob("*.json") if f.name != WORLD_MANIFEST)
    return fingerprint([(f.name, file_digest(f, dag.digest_cache(p))) for f in files], n=64)


def generation_payload(p: Params) -> dict[str, Any]:
    """What a world generated from ``p`` is the fingerprint of: its generation parameters."""
    return dag.payload(p, NODE, GENERATOR_VERSION, {})


def world_fingerprint(p: Params) -> str | None:
    """The world node's fingerprint now: generation parameters for a world generated (or
    about to be) from this profile, content of the tables for any other data; None when the
    data is missing."""
    vdir = p.dataroot_path / p.version
    generated = (vdir / WORLD_FILE).is_file()
    if (vdir / "scene.json").is_file() and not generated:
        return fingerprint({"stage": "world", "tables": tables_digest(p)})
    if p.synthetic:
        return fingerprint(generation_payload(p))
    if generated:  # someone's generated world, used as it is
        rec = read_manifest(vdir / WORLD_MANIFEST)
        return rec["fingerprint"] if rec else fingerprint({"stage": "world",
                                                            "tables": tables_digest(p)})
    return None


class WorldSource:
    """The world stage's :class:`flowmod.dag.Source`."""

    def location(self, p: Params) -> Path:
        return p.dataroot_path / p.version

    def fingerprint(self, p: Params) -> str | None:
        return world_fingerprint(p)

    def record(self, p: Params) -> dict[str, Any] | None:
        """The world's manifest; real data has none: its record is its content fingerprint."""
        rec = read_manifest(self.location(p) / WORLD_MANIFEST)
        if rec is None and not (p.synthetic and is_generated_world(p)):
            fp = world_fingerprint(p)
            return {"fingerprint": fp, "node": "world"} if fp else None
        return rec

    def why(self, p: Params, record: dict[str, Any] | None) -> tuple[str, str]:
        path = self.location(p)
        if world_fingerprint(p) is None:
            return "missing", f"no data at {path}"
        if record is None:
            return "missing", f"not generated yet at {path}"
        return "stale", "generated with other parameters: " + "; ".join(
            dag.diff(record.get("params", {}), dag.values(p, NODE)))

    def ensure(self, p: Params, progress: bool) -> None:
        ensure_world(p, progress=progress)


def ensure_world(params: Params, *, progress: bool = True) -> Path:
    """Make sure the profile's dataroot holds its nuScenes-format data; return the dataroot.

    * a real (non-generated) version folder: used as it is (its identity is its tables'
      content, :func:`world_fingerprint`);
    * synthetic, and a generated world with this profile's fingerprint (sizes, seed,
      generator version) present: reused; absent or made with other parameters: generated
      (in a temporary folder, swapped in when complete), then its manifest is written;
    * not synthetic and missing: :class:`WorldError` naming the path and the fix.
    """
    q = dag.StageParams(params, NODE)
    root, version = q.dataroot_path, q.version
    vdir = root / version
    fp = world_fingerprint(params)
    if fp is None:
        raise WorldError(
            f"nuScenes tables not found: {vdir} does not exist (or has no scene.json). Set "
            f"dataroot to the folder that holds {version}/, samples/ and sweeps/ (e.g. "
            f"DATAROOT=/data/sets/nuscenes), or set synthetic: true to generate a synthetic "
            f"world there."
        )
    if not is_generated_world(params) or not q.synthetic:
        return root
    manifest = vdir / WORLD_MANIFEST
    rec = read_manifest(manifest)
    if rec is not None and rec["fingerprint"] == fp and is_synthetic(root, version):
        return root
    sizes = {"n_scenes": q.world_scenes, "n_keyframes": q.world_keyframes,
             "n_sweep_scenes": q.world_sweep_scenes, "vehicles_per_scene": q.world_vehicles,
             "seed": q.seed}
    have = world_params(root, version) if is_synthetic(root, version) else {}
    same = all(have.get(k) == v for k, v in sizes.items()) and (
        have.get("generator_version") == GENERATOR_VERSION)
    if not same:  # a world from an earlier version of this code needs only its manifest
        manifest.unlink(missing_ok=True)
        generate_world(root, version, **sizes, n_jobs=q.n_jobs, progress=progress)
    write_manifest(manifest, {**generation_payload(params), "fingerprint": fp})
    return root


#: The world stage (chapter 01): the data itself.
STAGE = dag.Stage("world", GENERATOR_VERSION, "01", "",
                  "the data: a generated world or nuScenes tables",
                  nodes=lambda p: [NODE], source=WorldSource())
