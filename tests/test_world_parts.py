"""The world generator's parts pinned one by one (issue 53, item 10).

``test_world.py`` pins the tiny world's bytes, but five scenes draw only some of what the
generator can: no bus, no rain or few weathers, a handful of layouts. Fresh mutation draws of
``flowmod.world`` kept finding about one survivor in eight there (a bus window one pixel
narrower, rain streaks without anti-aliasing, a straight path's heading). Here every texture
painter, every vehicle category, the camera finish of every weather, the descriptions of
many scenes (layouts, agents' plans and their poses along the way) and the tiny world's exact
flow with its valid mask are hashed against a pin:
a change of what the generator draws anywhere changes a digest. Re-pin only for a deliberate
change of what the world draws (with ``GENERATOR_VERSION`` where readers care).

The digests are pinned per SIMD path of numpy (float32 transcendental functions round
differently with AVX-512 than with AVX2), as the tiny world's are, and computed in the test's
own process: mutmut's stats run records which generator functions each pin runs only there
(a pin computed in a subprocess counted as running nothing, so a mutant of, say, the rain
streaks was tested by no pin on an AVX-512 machine). A CPU with AVX-512 also checks the AVX2
pins in a subprocess (``NPY_DISABLE_CPU_FEATURES``), as the tiny world's second pin does.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from flowmod.environment import simd_path

#: sha256 (16 hex) of each part's outputs per SIMD path of numpy (numpy 1.26.4, OpenCV
#: 4.11.0).
PINS = {
    "avx2": {
        "textures": "36b452d5b13b4286",
        "vehicles": "3657b7de71b1d5c7",
        "finish": "03703fb2f0ebcdc1",
        "scenes": "bb88ba74358dd0f6",
        "truth": "67d689f3f683bb4f",
    },
    "avx512": {  # only the camera finish differs from the AVX2 path
        "textures": "36b452d5b13b4286",
        "vehicles": "3657b7de71b1d5c7",
        "finish": "03f449ebb9e0ec00",
        "scenes": "bb88ba74358dd0f6",
        "truth": "67d689f3f683bb4f",
    },
}


def _h(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype}{a.shape}".encode() + a.tobytes())
    return h.hexdigest()[:16]


def textures_digest() -> str:
    """Every texture painter at a fixed seed and small sizes."""
    from flowmod.world import textures as tx

    r = np.random.default_rng
    parts = [tx.asphalt(r(1), 96, v) for v in range(3)]
    parts += [tx.pavers(r(2), 96), tx.grass(r(3), 96), tx.clouds(r(4), 96)]
    parts += [tx.facade(r(5 + i), 12.0, 9.0, shop) for i, shop in enumerate((False, True))]
    parts += [tx.backdrop(r(s), 30.0, 8.0) for s in (7, 8, 9, 10)]  # both kinds
    parts += [*tx.foliage(r(11), 64), tx.bark(r(12)), tx.metal(r(13))]
    parts += [tx.hedge(r(14), 96, 24, wall) for wall in (False, True)]
    for s in (15, 16):
        for _face, (img, alpha) in sorted(tx.pedestrian_faces(r(s), (0.6, 0.5, 1.75)).items()):
            parts += [img, alpha]
    return _h(*parts)


def vehicles_digest() -> str:
    """Every vehicle category's faces, two liveries each, at the category's own size."""
    from flowmod.world import agents
    from flowmod.world import textures as tx

    parts = []
    for i, cat in enumerate(sorted(agents.CATEGORY_SIZES)):
        if not cat.startswith("vehicle."):
            continue
        for s in (0, 1):
            rng = np.random.default_rng([17, i, s])
            faces = tx.vehicle_faces(rng, cat, tuple(agents._size(rng, cat)))
            parts += [faces[k] for k in sorted(faces)]
    return _h(*parts)


def finish_digest() -> str:
    """The camera finish of every weather (lights at night, rain streaks and drops, noise,
    vignetting) on one textured frame; rain twice (where its drops fall is drawn: with one
    seed a drop's row one pixel off can land on the same rows)."""
    from flowmod.world import geometry as wg
    from flowmod.world import shading

    H, W = wg.H_IMG, wg.W_IMG
    yy, xx = np.mgrid[0:H, 0:W]
    base = np.stack([(xx * 7 + yy * 3) % 256, (xx // 4) % 256, (yy // 3) % 256], -1)
    K = np.array([[1260.0, 0.0, W / 2], [0.0, 1260.0, H / 2], [0.0, 0.0, 1.0]])
    parts = []
    for i, weather in enumerate(("clear", "overcast", "rain", "after_rain", "night", "rain")):
        fr = wg.Frame(img=base.astype(np.uint8), invz=np.zeros((H, W), np.float32),
                      sid=np.zeros((H, W), np.uint16), R_wc=np.eye(3), c=np.zeros(3), K=K,
                      lights=[(np.array([3.0, 0.5, 40.0]), (200, 220, 255), 0.3, 5),
                              (np.array([-2.0, 0.8, 25.0]), (40, 40, 255), 0.2, 6),
                              (np.array([1.0, 0.0, -5.0]), (255, 255, 255), 0.3, 7)])
        look = {"weather": weather, "gain": 0.9 + 0.05 * i,
                "white_balance": [1.0, 0.97, 1.03], "noise": 2.0}
        parts.append(shading.finish(fr, look, (3, i, 5), 1.1))
    return _h(*parts)


def scenes_digest() -> str:
    """The descriptions of 8 scenes of 10 vehicles, one for each of the ego's behaviours
    (``EGO_SCENES``; every weather, with and without sweeps), and every trajectory's pose at
    11 times: layouts, plans, placement, statics, looks, words."""
    from flowmod.world import agents
    from flowmod.world import scene as ws

    h = hashlib.sha256()
    weathers = ("clear", "overcast", "rain", "after_rain", "night", "clear")
    for j, (kind, i) in enumerate(EGO_SCENES.items()):
        sc = agents.sample_scene(7, i, 4, 10, weathers[j % 6], with_sweeps=j % 3 == 0,
                                 near_movers=2)
        assert sc["ego_kind"] == kind
        h.update(json.dumps(ws.json_ready(sc), sort_keys=True).encode())
        t = np.linspace(0.0, sc["duration"], 11)
        for traj in [sc["ego"]] + [a["traj"] for a in sc["agents"]]:
            st = ws.traj_state(traj, t)
            for k in sorted(st):
                h.update(np.round(np.asarray(st[k], np.float64), 9).tobytes())
    return h.hexdigest()[:16]


#: A scene index (world seed 7) for each of the ego's behaviours.
EGO_SCENES = {"stop_and_go": 0, "cruise": 1, "follow": 4, "go": 8, "turn_left": 17, "wait": 18,
              "brake": 25, "turn_right": 49}


def keyframes_by_scene(root: Path, version: str) -> dict[str, list[dict]]:
    """The CAM_FRONT keyframes' sample_data rows of a world, per scene token, in time order."""
    scene_of = {s["token"]: s["scene_token"]
                for s in json.loads((root / version / "sample.json").read_text())}
    frames: dict[str, list[dict]] = {}
    for r in json.loads((root / version / "sample_data.json").read_text()):
        if r["is_key_frame"] and r["filename"].startswith("samples/"):
            frames.setdefault(scene_of[r["sample_token"]], []).append(r)
    return {k: sorted(v, key=lambda r: r["timestamp"]) for k, v in sorted(frames.items())}


def truth_digest() -> str:
    """The exact flow and its valid mask of the tiny world's first keyframe pair of every
    scene (``FLOWMOD_TINY_WORLD``: its root), where vehicles hide parts of themselves and of
    each other: the same-surface and other-surface depth tolerances, the near and far limits
    and the fill of undefined pixels all show in these bytes."""
    from flowmod.world import gt_flow

    root, version = Path(os.environ["FLOWMOD_TINY_WORLD"]), "v1.0-synth"
    parts = []
    for a, b, *_ in keyframes_by_scene(root, version).values():
        parts += gt_flow(root, version, a["token"], b["token"])
    return _h(*parts)


DIGESTS = {"textures": textures_digest, "vehicles": vehicles_digest,
           "finish": finish_digest, "scenes": scenes_digest, "truth": truth_digest}


def avx2_digest(part: str) -> str:
    """``part``'s digest on numpy's AVX2 path, computed in a subprocess whose numpy may not
    use AVX-512."""
    from test_world import NO_AVX512

    code = ("import sys; sys.path.insert(0, 'tests'); import test_world_parts as t;"
            f"print(t.simd_path(), t.DIGESTS[{part!r}]())")
    env = {**os.environ, "NPY_DISABLE_CPU_FEATURES": NO_AVX512}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1], check=True).stdout.split()
    assert out[0] == "avx2"
    return out[1]


@pytest.mark.parametrize("part", sorted(DIGESTS))
def test_the_generator_s_parts_draw_as_pinned(part, tiny_world, monkeypatch):
    """Each part's digest, computed in this process, against the pin of this CPU's path."""
    path = simd_path()
    if path is None:
        pytest.skip("numpy runs neither SIMD path (AVX-512, AVX2) that the pins know")
    monkeypatch.setenv("FLOWMOD_TINY_WORLD", str(tiny_world[0]))
    assert DIGESTS[part]() == PINS[path][part]


@pytest.mark.parametrize("part", sorted(DIGESTS))
def test_the_generator_s_parts_draw_as_pinned_on_the_avx2_path_too(part, tiny_world,
                                                                    monkeypatch):
    """The other pin, where this CPU has AVX-512 (CI machines may lack it)."""
    if simd_path() != "avx512":
        pytest.skip("this CPU runs the AVX2 path already (the test above)")
    monkeypatch.setenv("FLOWMOD_TINY_WORLD", str(tiny_world[0]))
    assert avx2_digest(part) == PINS["avx2"][part]


def test_a_path_turns_a_quarter_circle_then_runs_straight_on_its_new_heading():
    """``path_pose`` over [arc, straight]: a left quarter circle of radius 10 m from the
    origin heading +x ends at (10, 10) heading +y; the next segment starts there and on
    that heading (the segment start pose advanced by the arc's length times its curvature)."""
    from flowmod.world import scene as ws

    r, quarter = 10.0, 10.0 * np.pi / 2
    path = {"x": 0.0, "y": 0.0, "h": 0.0, "segs": [[quarter, 1 / r], [5.0, 0.0], [4.0, -1 / r]]}
    x, y, h = ws.path_pose(path, np.array([quarter / 2, quarter, quarter + 5.0]))
    np.testing.assert_allclose(x, [r * np.sin(np.pi / 4), r, r], atol=1e-9)
    np.testing.assert_allclose(y, [r - r * np.cos(np.pi / 4), r, r + 5.0], atol=1e-9)
    np.testing.assert_allclose(h, [np.pi / 4, np.pi / 2, np.pi / 2], atol=1e-12)
    # the right-hand arc after the straight turns back by 4 / r
    _, _, h_end = ws.path_pose(path, quarter + 9.0)
    assert float(h_end) == pytest.approx(np.pi / 2 - 0.4, abs=1e-12)
    # from another heading (+y): the left quarter circle ends at (-10, 10) heading -x, and
    # the straight after it runs on from there
    north = {**path, "h": np.pi / 2}
    x, y, h = ws.path_pose(north, np.array([quarter, quarter + 5.0]))
    np.testing.assert_allclose(x, [-r, -r - 5.0], atol=1e-9)
    np.testing.assert_allclose(y, [r, r], atol=1e-9)
    np.testing.assert_allclose(h, [np.pi, np.pi], atol=1e-12)


def test_the_world_s_small_geometry_helpers():
    """A rectangle's corners (a building's or hedge's footprint, checked against the other
    roads) and the cross product of a face's normal, on numbers worked by hand."""
    from flowmod.world.layout import _rect_corners
    from flowmod.world.render import _cross

    xs, ys = _rect_corners(1.0, 2.0, 0.0, 4.0, 2.0)  # 4 m long along x, 2 m wide
    assert sorted(zip(xs.tolist(), ys.tolist(), strict=True)) == [(-1.0, 1.0), (-1.0, 3.0),
                                                                   (3.0, 1.0), (3.0, 3.0)]
    xs, ys = _rect_corners(0.0, 0.0, np.pi / 2, 4.0, 2.0)  # turned: long along y
    np.testing.assert_allclose(sorted(np.abs(xs)), [1, 1, 1, 1], atol=1e-12)
    np.testing.assert_allclose(sorted(np.abs(ys)), [2, 2, 2, 2], atol=1e-12)
    rng = np.random.default_rng(0)
    for a, b in rng.normal(size=(5, 2, 3)):
        np.testing.assert_allclose(_cross(a, b), np.cross(a, b), rtol=1e-12)


def test_the_flow_limit_is_decided_by_the_length_itself_near_its_square():
    """``truth._within_max_flow`` is ``hypot(du, dv) <= MAX_FLOW_PX`` exactly: on points of
    the limit's circle, where the squared length rounds to the other side for many, the
    cheap square is overruled by ``hypot``."""
    from flowmod.world import truth

    a = np.random.default_rng(0).uniform(0.0, 2 * np.pi, 20_000)
    du, dv = truth.MAX_FLOW_PX * np.cos(a), truth.MAX_FLOW_PX * np.sin(a)
    exact = np.hypot(du, dv) <= truth.MAX_FLOW_PX
    cheap = du * du + dv * dv <= truth.MAX_FLOW_PX ** 2
    assert (cheap != exact).sum() > 100  # the case the function exists for
    np.testing.assert_array_equal(truth._within_max_flow(du, dv), exact)
    far = np.array([0.0, 3.0, truth.MAX_FLOW_PX * 0.5])
    np.testing.assert_array_equal(truth._within_max_flow(far, far), [True, True, True])


def test_other_worlds_are_the_generated_ones_beside_this_one(tmp_path):
    """``source.other_worlds``: the folders under ``<dataroot>/worlds`` but the profile's own
    (none without that folder), which ``make gc`` offers to remove."""
    import conftest

    from flowmod.world import source

    p = conftest._smoke(tmp_path)
    assert source.other_worlds(p) == []
    own, a, b = p.dataroot_path, tmp_path / "worlds" / "a", tmp_path / "worlds" / "b"
    for d in (own, b, a):
        d.mkdir(parents=True)
    (tmp_path / "worlds" / "note.txt").write_text("a file, not a world")
    assert own.parent == tmp_path / "worlds"
    assert source.other_worlds(p) == [a, b]


def test_missing_nuscenes_tables_name_the_folder_and_both_fixes(tmp_path):
    """Real data that is not there: one line naming the version folder it looked for and the
    two ways out (the dataroot that holds it, or a generated world)."""
    from flowmod.params import load_profile
    from flowmod.world import WorldError, ensure_world

    p = load_profile("smoke", dataroot=str(tmp_path), version="v1.0-mini", synthetic=False)
    with pytest.raises(WorldError) as e:
        ensure_world(p, progress=False)
    assert str(e.value) == (
        f"nuScenes tables not found: {tmp_path / 'v1.0-mini'} does not exist (or has no "
        "scene.json). Set dataroot to the folder that holds v1.0-mini/, samples/ and sweeps/ "
        "(e.g. DATAROOT=/data/sets/nuscenes), or set synthetic: true to generate a synthetic "
        "world there.")


@pytest.mark.parametrize("seed", range(6))
def test_sweeps_go_to_usable_scenes_only_even_when_most_scenes_are_swept(seed):
    """``plan_weathers`` with 30 of 40 scenes swept: the special weathers are cut to the 10
    unswept places, and the sweeps still skip every night and rain scene (the selection
    drops those scenes, so their sweeps would make no generalisation pair)."""
    from flowmod.world import scene as ws

    weathers, sweep = ws.plan_weathers(40, 30, seed)
    assert sum(sweep) == 30 and len(weathers) == 40
    assert {"night", "rain"} <= set(weathers)
    assert not [w for w, s in zip(weathers, sweep, strict=True) if s and w in ("night", "rain")]


def test_unknown_tokens_are_named_by_the_exact_truth(tiny_world):
    """The world's exact answers refuse what is not in it with one line naming the token:
    an instance that is no agent, a frame that is no frame, two frames of two scenes."""
    from flowmod.world import WorldError, gt_flow, true_velocity

    root, version = tiny_world
    with pytest.raises(WorldError, match=r"^instance token 'nope' is not an agent of this world$"):
        true_velocity(root, version, "nope", 0)
    with pytest.raises(WorldError, match=r"^sample_data token 'nope' is not a frame of this "
                                         r"synthetic world$"):
        gt_flow(root, version, "nope", "nope")
    one, other = (frames[0] for frames in list(keyframes_by_scene(root, version).values())[:2])
    with pytest.raises(WorldError, match=r"^gt_flow needs two frames of the same scene"):
        gt_flow(root, version, one["token"], other["token"])


def test_real_data_is_fingerprinted_by_its_tables_alone(tiny_world, tmp_path):
    """A devkit data set that is not a generated world (no world description): its
    fingerprint is that of its tables, so a changed table changes it and a changed image
    does not (real data is not hashed frame by frame)."""
    import shutil

    from flowmod.params import validate
    from flowmod.world import source
    from flowmod.world.truth import WORLD_FILE

    root, version = tiny_world
    data = tmp_path / "data"
    shutil.copytree(root, data)
    p = validate({"profile": "smoke", "dataroot": str(data), "version": version,
                  "run_dir": str(tmp_path / "runs"), "synthetic": False})
    # while it is a generated world, its frames count, by a whole sha256 of their digests
    assert len(source.content(p)["images"]) == 64
    (data / version / WORLD_FILE).unlink()
    before = source.world_fingerprint(p)
    assert before is not None and before == source.world_fingerprint(p)
    frame = sorted((data / "samples").rglob("*.jpg"))[2]
    frame.write_bytes(frame.read_bytes()[:-10] + bytes(10))
    assert source.world_fingerprint(p) == before
    scenes = data / version / "scene.json"
    scenes.write_text(scenes.read_text().replace('"name": "', '"name": "x', 1))
    assert source.world_fingerprint(p) not in (before, None)
    # real data has no "edits since generated", though the generator's record is still there
    assert source.edits(p).startswith("edited since it was generated (tables scene.json")
    assert source.WorldSource().status(p) == ("up to date", "")


def test_the_world_s_progress_counts_its_scenes_out_of_their_number(monkeypatch, capsys):
    """Generating a world in this process shows "n/N scene" (the number of scenes known from
    the start); the scene jobs here are stand-ins (the counting is what is tested, each real
    job renders a scene)."""
    from flowmod.world import dataset

    monkeypatch.setattr(dataset, "scene_job", lambda i: {"index": i})
    out = dataset._run_jobs([(i,) for i in range(3)], 1, progress=True)
    assert out == [{"index": 0}, {"index": 1}, {"index": 2}]
    err = capsys.readouterr().err
    assert "synthetic world" in err and "3/3" in err and "scene/s" in err, err



def test_a_cruise_is_high_speed_on_an_arterial_and_city_driving_elsewhere():
    """A cruising ego's scene is, half the time (the rng's first draw under 0.5), described
    by its speed: "high speed" on an arterial road, "city driving" on another big street."""
    from flowmod.world.agents import _describe

    arterial = {"kind": "arterial", "main": {"lanes": 2}}
    urban = {"kind": "urban", "main": {"lanes": 3}}
    seen = set()
    for seed in range(6):
        said = np.random.default_rng(seed).random() < 0.5
        seen.add(said)
        for layout, words in ((arterial, "high speed"), (urban, "city driving")):
            got = _describe(np.random.default_rng(seed), "cruise", layout, [], "clear")
            assert got == ("Big street, " + words if said else "Big street"), (seed, got)
    assert seen == {True, False}
    # with nothing else to say, a scene is "City driving" (a cruise on a two-lane street,
    # described by its speed or not)
    two_lanes = {"kind": "urban", "main": {"lanes": 2}}
    for seed in range(4):
        assert _describe(np.random.default_rng(seed), "cruise", two_lanes, [], "clear") == (
            "City driving")


def test_an_agent_s_global_state_has_one_value_per_time():
    """``agent_state_global`` at three times: every quantity (x, y, z, yaw, speed, vx, vy,
    vz) an array of three; z is half the agent's height, vz zero."""
    from flowmod.world import agents
    from flowmod.world import scene as ws

    sc = agents.sample_scene(7, 1, 4, 10, "clear", with_sweeps=False, near_movers=2)
    agent = sc["agents"][0]
    st = ws.agent_state_global(sc, agent, np.array([0.0, 0.5, 1.0]))
    assert {k: np.shape(v) for k, v in st.items()} == {k: (3,) for k in (
        "x", "y", "z", "yaw", "speed", "vx", "vy", "vz")}
    np.testing.assert_array_equal(st["z"], np.full(3, agent["size"][2] / 2))
    np.testing.assert_array_equal(st["vz"], np.zeros(3))


def test_vehicles_are_placed_in_three_phases_by_their_tries():
    """``_placement_phase`` at its edges, 20 vehicles wanted: the best of 8 candidates, all
    aimed into view, while under 85 % placed and 40 tries a vehicle; then one candidate,
    85 % aimed; past 60 tries a vehicle, filling up."""
    from flowmod.world.agents import _placement_phase as phase

    first, second, fill = (8, 1.0, False), (1, 0.85, False), (1, 0.85, True)
    assert phase(0, 0, 20) == phase(799, 16, 20) == first
    assert phase(0, 17, 20) == phase(800, 0, 20) == phase(1200, 19, 20) == second
    assert phase(1201, 0, 20) == phase(1599, 19, 20) == fill


def test_world_scenes_are_made_by_worker_processes_in_their_order(monkeypatch):
    """With two jobs the scenes are made in two worker processes, come back in the order
    asked, and are counted as each arrives, not all at the end (the jobs here are
    stand-ins that say where and when they ran; the last takes 0.9 s)."""
    import time

    from flowmod.world import dataset

    counted = []

    class Bar:
        def update(self, n):
            counted.append(time.time())

        def close(self):
            pass

    monkeypatch.setattr(dataset, "bar", lambda **kw: Bar())
    monkeypatch.setattr(dataset, "scene_job",
                        lambda i: (i, os.getpid(), time.sleep(0.3 * i) or time.time()))
    out = dataset._run_jobs([(i,) for i in range(4)], 2, progress=True)
    assert [i for i, _, _ in out] == [0, 1, 2, 3] and len(counted) == 4
    assert os.getpid() not in {pid for _, pid, _ in out}
    assert counted[0] < out[-1][2]


def test_a_projected_box_holds_every_point_and_is_clipped_to_the_image():
    """``project_bbox``: pixels u = fx X / Z + cx (worked by hand), the box from the floor of
    the smallest to one past the ceiling of the largest, end-exclusive, clipped."""
    from flowmod.world.geometry import H_IMG, W_IMG, project_bbox

    K = np.array([[1260.0, 0.0, 800.0], [0.0, 1260.0, 450.0], [0.0, 0.0, 1.0]])
    pts = np.array([[0.31, -0.21, 7.0], [-1.13, 0.452, 9.0], [0.9, 0.1, 5.0]])
    uv, box = project_bbox(pts, K)
    np.testing.assert_allclose(uv, [[855.8, 412.2], [641.8, 513.28], [1026.8, 475.2]])
    assert box == (641, 1028, 412, 515)
    assert project_bbox(np.array([[9.0, -0.21, 7.0], [-1.13, 9.0, 9.0]]), K)[1] == (
        641, W_IMG, 412, H_IMG)


def test_an_agent_s_bounding_sphere_holds_its_faces_and_no_more():
    """The radius that culls an agent outside the view is its farthest face corner's
    distance from its centre: half its box's diagonal."""
    from flowmod.world import agents
    from flowmod.world import geometry as wg

    geo = wg.SceneGeometry(agents.sample_scene(7, 1, 4, 10, "clear", with_sweeps=False,
                                               near_movers=2))
    assert len(geo.agents) >= 5
    for obj in geo.agents:
        corners = [c for q in obj.quads for c in (q.p0, q.p0 + q.eu, q.p0 + q.ev,
                                                  q.p0 + q.eu + q.ev)]
        assert obj.radius == pytest.approx(max(np.linalg.norm(corners, axis=1)), rel=1e-9)


def test_objects_are_drawn_nearest_first_by_euclidean_distance():
    """``render.near_to_far`` orders by distance from the camera centre, whatever the
    side: an object 10 m behind comes after one 5 m ahead, and is stable for ties."""
    from flowmod.world.render import near_to_far

    c = np.array([1.0, 0.0, 1.5])
    posed = [("behind", None, np.array([-9.0, 0.0, 1.5])), ("ahead", None, np.array([6.0, 0, 1.5])),
             ("left", None, np.array([1.0, 7.0, 1.5])), ("right", None, np.array([1.0, -5.0, 1.5]))]
    assert [o[0] for o in near_to_far(posed, c)] == ["ahead", "right", "left", "behind"]


def _low_camera_frame(sid: int):
    """A 1600 x 900 frame of grey 200 seen by a level camera 5 cm above the ground at the
    origin, looking along +x; every pixel of surface ``sid``."""
    from flowmod.world import geometry as wg

    H, W = wg.H_IMG, wg.W_IMG
    K = np.array([[1260.0, 0.0, W / 2], [0.0, 1260.0, H / 2], [0.0, 0.0, 1.0]])
    R_wc = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return wg.Frame(img=np.full((H, W, 3), 200, np.uint8), invz=np.zeros((H, W), np.float32),
                    sid=np.full((H, W), sid, np.uint16), R_wc=R_wc, c=np.array([0, 0, 0.05]),
                    K=K)


def test_a_shadow_cut_to_a_triangle_by_the_near_plane_is_still_drawn_on_the_ground():
    """A vehicle beside and behind the camera with one footprint corner in front of it: the
    near plane leaves a triangle, which darkens the ground it covers by 45 % (200 -> 110)
    and nothing that is not ground."""
    from flowmod.world import geometry as wg
    from flowmod.world import shading

    yaw = np.pi / 4
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0, 0, 1]])
    ctr, size = np.array([-1.6, 0.0, 0.8]), (1.9, 4.5, 1.6)
    car = wg.Obj([], wg.SID_AGENT0, 3.0, agent={"kind": "vehicle", "size": size})
    fr = _low_camera_frame(wg.SID_GROUND)
    assert len(shading._footprint_uv(fr, size, R, ctr)) == 3
    fr.sid[:, 200:] = wg.SID_AGENT0 + 1
    shading.contact_shadows(fr, [(car, R, ctr)])
    dark = (fr.img < 200).any(axis=2)
    assert dark[:, :200].sum() > 10_000 and not dark[:, 200:].any()
    assert (fr.img[dark] == 110).all(axis=1).mean() > 0.9


def test_a_shadow_s_box_is_one_pixel_around_and_none_outside_the_image():
    """``shading._shadow_box``: floor - 1 to int + 2 of the footprint's pixels, clipped; a
    footprint whose top lies one and a half pixels below the image has no box (OpenCV would
    refuse the empty one)."""
    from flowmod.world.geometry import H_IMG, W_IMG
    from flowmod.world.shading import _shadow_box

    assert _shadow_box(np.array([[10.5, 20.5], [30.2, 40.7], [12.0, 45.0]])) == (9, 32, 19, 47)
    assert _shadow_box(np.array([[-5.0, 880.2], [1700.0, 899.5]])) == (0, W_IMG, 879, H_IMG)
    assert _shadow_box(np.array([[10.5, H_IMG + 1.5], [30.2, H_IMG + 40.0]])) is None
    assert _shadow_box(np.array([[W_IMG + 1.5, 20.5], [W_IMG + 9.0, 40.7]])) is None


def test_removing_a_world_holds_its_lock_saying_so(tmp_path, monkeypatch):
    """``remove_world`` deletes the folder under the world's lock (beside it), whose record
    tells a second run what holds it: "world <name>: removing it"."""
    import shutil

    from flowmod.world import source

    folder = tmp_path / "worlds" / "abc"
    (folder / "v1.0-synth").mkdir(parents=True)
    seen, real_rmtree = [], shutil.rmtree

    def rmtree(path):
        seen.append(json.loads((path.parent / f".{path.name}.lock").read_text())["command"])
        real_rmtree(path)

    monkeypatch.setattr(source.shutil, "rmtree", rmtree)
    source.remove_world(folder)
    assert seen == ["world abc: removing it"] and not folder.exists()


def test_the_far_agents_boxes_are_their_silhouettes_within_the_range(tiny_world):
    """``agent_boxes``: (N, 4) float32 boxes inside the image, each around some agent's
    silhouette; a narrower depth range keeps a subset, an empty one none."""
    from flowmod.world import agent_boxes
    from flowmod.world.geometry import H_IMG, W_IMG

    root, version = tiny_world
    frames = [f[0]["token"] for f in keyframes_by_scene(root, version).values()]
    boxes = {sd: agent_boxes(root, version, sd, 0.0, 1e9) for sd in frames}
    most = max(boxes.values(), key=len)
    assert most.dtype == np.float32 and most.ndim == 2 and most.shape[1] == 4
    assert len(most) >= 2
    assert (most[:, 0] >= 0).all() and (most[:, 2] <= W_IMG).all()
    assert (most[:, 1] >= 0).all() and (most[:, 3] <= H_IMG).all()
    assert (most[:, 2] > most[:, 0]).all() and (most[:, 3] > most[:, 1]).all()
    sd = next(k for k, v in boxes.items() if v is most)
    kept = [agent_boxes(root, version, sd, near, 1e9) for near in (0.0, 20.0, 40.0, 80.0)]
    assert [len(k) for k in kept] == sorted((len(k) for k in kept), reverse=True)
    assert len(kept[0]) > len(kept[-1])
    for narrower, wider in zip(kept[1:], kept[:-1], strict=True):
        assert {tuple(b) for b in narrower} <= {tuple(b) for b in wider}
    assert agent_boxes(root, version, sd, 5.0, 4.0).shape == (0, 4)
