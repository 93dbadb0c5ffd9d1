"""The static-world flow prediction and the residual baseline, against hand-computed cases."""

import warnings

import numpy as np
import pandas as pd
import pytest

from flowmod import geometry

K = np.array([[1266.0, 0.0, 816.0], [0.0, 1266.0, 491.0], [0.0, 0.0, 1.0]])


def translation(t):
    m = np.eye(4)
    m[:3, 3] = t
    return m


def test_static_flow_forward_motion_matches_pinhole_formula():
    xy = np.array([[1000.0, 600.0], [816.0, 491.0], [100.0, 800.0]])
    Z = np.array([40.0, 25.0, 10.0])
    d = 1.5  # camera moves 1.5 m along its optical axis
    flow = geometry.static_flow(xy, Z, K, np.eye(4), translation([0, 0, d]))
    X = (xy[:, 0] - 816.0) * Z / 1266.0
    Y = (xy[:, 1] - 491.0) * Z / 1266.0
    expect = np.stack([816.0 + 1266.0 * X / (Z - d), 491.0 + 1266.0 * Y / (Z - d)], 1) - xy
    np.testing.assert_allclose(flow, expect, atol=1e-9)
    np.testing.assert_allclose(flow[1], [0.0, 0.0], atol=1e-9)  # focus of expansion


def test_static_flow_lateral_motion_is_inverse_depth():
    xy = np.array([[500.0, 500.0], [500.0, 500.0]])
    Z = np.array([10.0, 50.0])
    flow = geometry.static_flow(xy, Z, K, np.eye(4), translation([1.0, 0, 0]))
    np.testing.assert_allclose(flow[:, 0], -1266.0 * 1.0 / Z)
    np.testing.assert_allclose(flow[:, 1], 0.0, atol=1e-9)


def test_box_residual_zero_for_static_and_recovers_own_motion():
    h, w = 900, 1600
    T1, T2 = np.eye(4), translation([0.2, 0.0, 1.0])
    center = np.array([3.0, 0.5, 40.0])  # camera frame = global here
    u, v = 816 + 1266 * 3.0 / 40, 491 + 1266 * 0.5 / 40
    box = np.array([u - 20, v - 12, u + 20, v + 12])
    ys, xs = np.mgrid[0:h, 0:w]
    xy = np.stack([xs.ravel(), ys.ravel()], 1).astype(float)
    flow = geometry.static_flow(xy, np.full(len(xy), 40.0), K, T1, T2).reshape(h, w, 2)
    samples = geometry.box_samples(flow, box[None])[0]
    res_px, _ = geometry.box_residual(samples, box, center, K, T1, T2, dt_s=0.5)
    assert res_px == pytest.approx(0.0, abs=0.02)
    moved = geometry.box_samples(flow + np.array([4.0, 0.0]), box[None])[0]  # own motion
    res_px, res_speed = geometry.box_residual(moved, box, center, K, T1, T2, dt_s=0.5)
    assert res_px == pytest.approx(4.0, abs=0.05)
    assert res_speed == pytest.approx(4.0 * 40.0 / 1266.0 / 0.5, rel=0.02)


def test_residual_scores_are_each_objects_box_residual_in_its_pairs_cameras():
    """Objects of two pairs, interleaved, one without a 3D box (NaN size: the centre's depth):
    every row is box_residual with its own pair's cameras and time step, in the objects'
    order and index."""
    from pyquaternion import Quaternion

    rng = np.random.default_rng(3)
    T = {"a": (np.eye(4), translation([0.0, 0.0, 1.0]), 0.5),
         "b": (np.eye(4), translation([0.3, 0.0, 2.0]), 0.25)}
    pairs = pd.DataFrame([{"pair_id": k, "intrinsic": K.ravel().tolist(),
                           "cam2global_1": t1.ravel().tolist(), "cam2global_2": t2.ravel().tolist(),
                           "timestamp_1": 0, "timestamp_2": int(dt * 1e6)}
                          for k, (t1, t2, dt) in T.items()])
    q = Quaternion(axis=[0, 1, 0], degrees=30.0).elements
    rows = []
    for i, pid in enumerate(["a", "b", "a", "b"]):
        c = np.array([2.0 * i - 3.0, 0.5, 30.0 + 5 * i])
        u, v = 816 + 1266 * c[0] / c[2], 491 + 1266 * c[1] / c[2]
        rows.append({"pair_id": pid, "xmin": u - 30, "ymin": v - 15, "xmax": u + 30,
                     "ymax": v + 15, "center_x": c[0], "center_y": c[1], "center_z": c[2],
                     "size_w": np.nan if i == 1 else 1.9, "size_l": 4.5, "size_h": 1.5,
                     "qw": q[0], "qx": q[1], "qy": q[2], "qz": q[3]})
    objects = pd.DataFrame(rows, index=[10, 11, 12, 13])
    samples = rng.normal(0.0, 3.0, (4, geometry.GRID ** 2, 2))
    pairs["timestamp_1"] += 7_000_000  # times are differences: the frame gap counts
    pairs["timestamp_2"] += 7_000_000
    got = geometry.residual_scores(objects, pairs, samples)
    assert list(got.index) == [10, 11, 12, 13]
    assert list(got.columns) == ["residual_px", "residual_speed"]
    for i, o in enumerate(rows):
        t1, t2, dt = T[o["pair_id"]]
        box = None if i == 1 else (np.array([1.9, 4.5, 1.5]), q)
        want = geometry.box_residual(
            samples[i], np.array([o["xmin"], o["ymin"], o["xmax"], o["ymax"]]),
            np.array([o["center_x"], o["center_y"], o["center_z"]]), K, t1, t2, dt,
            *(box or (None, None)))
        assert got.iloc[i].tolist() == pytest.approx(list(want), rel=1e-12), i
    centre_only = objects.drop(columns=["size_w", "size_l", "size_h", "qw", "qx", "qy", "qz"])
    again = geometry.residual_scores(centre_only, pairs, samples)
    assert again.iloc[1].tolist() == pytest.approx(got.iloc[1].tolist(), rel=1e-12)
    assert again.iloc[0, 0] != pytest.approx(got.iloc[0, 0], rel=1e-6)  # the box's depths count


def test_depth_where_the_ray_meets_the_3d_box_removes_the_parallax_of_a_near_oblique_car():
    """A still car 12 m ahead, seen obliquely (its 4.5 m length at 60 degrees to the view):
    its pixels' depths differ by metres, so one depth (the centre's) leaves a residual that a
    still car should not have; the depth where each ray meets the annotated box leaves none."""
    from pyquaternion import Quaternion

    T1, T2 = np.eye(4), translation([0.0, 0.0, 1.5])  # the camera drives 1.5 m forward
    c, s_ = np.cos(np.radians(60)), np.sin(np.radians(60))
    R = np.array([[c, -s_, 0.0], [0.0, 0.0, -1.0], [s_, c, 0.0]])  # box x (length) oblique
    center, wlh = np.array([2.5, 0.7, 12.0]), np.array([1.9, 4.5, 1.5])
    q = Quaternion(matrix=R).elements
    corners = center + (R @ (np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
                             * [wlh[1] / 2, wlh[0] / 2, wlh[2] / 2]).T).T
    uv = (K @ corners.T)[:2] / corners[:, 2]
    box = np.array([uv[0].min(), uv[1].min(), uv[0].max(), uv[1].max()])
    xy = geometry.box_lattice(box)
    depth = geometry.ray_box_depth(xy, K, center, wlh, R)
    assert np.nanmax(depth) - np.nanmin(depth) > 2.0, "the car's surface spans metres in depth"
    samples = geometry.static_flow(xy, np.where(np.isfinite(depth), depth, 60.0), K, T1, T2)
    with_box, _ = geometry.box_residual(samples, box, center, K, T1, T2, 0.5, wlh, q)
    centre_only, _ = geometry.box_residual(samples, box, center, K, T1, T2, 0.5)
    assert with_box == pytest.approx(0.0, abs=1e-6)
    assert centre_only > 3.0, centre_only


def test_box_in_camera_undoes_the_camera_pose():
    """A global box pose seen from a turned and displaced camera: the centre is the camera's
    inverse rotation of (centre - camera position), the rotation the camera's inverse
    quaternion times the box's (the devkit's translate-then-rotate, in quaternions)."""
    from pyquaternion import Quaternion

    q_cam = Quaternion(axis=[0.2, -0.5, 1.0], degrees=35.0)
    cam2global = np.eye(4)
    cam2global[:3, :3], cam2global[:3, 3] = q_cam.rotation_matrix, [410.0, 1180.5, 1.7]
    centre, q_box = np.array([425.0, 1170.0, 0.9]), Quaternion(axis=[0, 0, 1], degrees=-70.0)
    c, rot = geometry.box_in_camera(cam2global, centre, q_box.elements)
    np.testing.assert_allclose(c, q_cam.inverse.rotate(centre - [410.0, 1180.5, 1.7]),
                               atol=1e-9)
    np.testing.assert_allclose(rot, (q_cam.inverse * q_box).rotation_matrix, atol=1e-12)


def test_ray_box_depth_on_faces_edges_and_corners_without_warnings():
    """The box is closed: a ray running along a face or an edge meets it where it enters the
    remaining slab, and one that only touches a corner meets it there; rays parallel to a face
    (a 0/0 or x/0 slab) raise no floating-point warning."""
    eye = np.eye(3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # principal ray (0, 0, 1) along the edge x = 0, y = 0 of the 2 m cube x in [-2, 0],
        # y in [0, 2], z in [9, 11]
        along_edge = geometry.ray_box_depth([[816.0, 491.0]], K, [-1.0, 1.0, 10.0],
                                            np.array([2.0, 2.0, 2.0]), eye)
        # ray (1, 0, 1) (focal length 1 px) through the corner (4, 0, 4) of x in [2, 4],
        # z in [4, 6]: entering and leaving at the same depth
        corner = geometry.ray_box_depth([[1.0, 0.0]], eye, [3.0, 0.0, 5.0],
                                        np.array([2.0, 2.0, 2.0]), eye)
    np.testing.assert_array_equal(along_edge, [9.0])
    np.testing.assert_array_equal(corner, [4.0])


def test_ray_box_depth_within_a_metre_of_the_camera_and_not_at_it():
    """A 20 cm box half a metre ahead is met at 0.5 m (depths under 1 m are depths); a box
    whose face lies in the camera's own plane (depth 0) or around the camera is not met."""
    eye = np.eye(3)
    near = geometry.ray_box_depth([[816.0, 491.0]], K, [0.0, 0.0, 0.6],
                                  np.array([0.2, 0.2, 0.2]), eye)
    np.testing.assert_allclose(near, [0.5])
    at_camera = geometry.ray_box_depth([[816.0, 491.0], [816.0, 491.0]], K, [0.0, 0.0, 1.0],
                                       np.array([2.0, 2.0, 2.0]), eye)
    around = geometry.ray_box_depth([[816.0, 491.0]], K, [0.0, 0.0, 0.5],
                                    np.array([2.0, 2.0, 2.0]), eye)
    assert np.isnan(at_camera).all() and np.isnan(around).all()


def test_box_geometry_is_float64_for_extended_precision_inputs():
    """Box centres and sizes given as np.longdouble give exactly the float64 results of the
    same values in float64 (which parquet and torch can hold; they have no wider float)."""
    eye = np.eye(3)
    centre, size = np.array([0.5, -0.25, 12.0]), np.array([1.5, 4.0, 2.0])
    xy = np.array([[816.0, 491.0], [850.0, 480.0], [100.0, 100.0]])
    want = geometry.ray_box_depth(xy, K, centre, size, eye)
    assert np.isfinite(want[:2]).all() and np.isnan(want[2])
    for c, s in [(centre.astype(np.longdouble), size), (centre, size.astype(np.longdouble))]:
        got = geometry.ray_box_depth(xy, K, c, s, eye)
        assert got.dtype == np.float64
        np.testing.assert_array_equal(got, want)
    cam2global = translation([1.0, 2.0, 0.5])
    c64, _ = geometry.box_in_camera(cam2global, [3.0, 4.0, 1.0], [1.0, 0.0, 0.0, 0.0])
    cld, _ = geometry.box_in_camera(cam2global, np.array([3.0, 4.0, 1.0], np.longdouble),
                                    [1.0, 0.0, 0.0, 0.0])
    assert cld.dtype == np.float64
    np.testing.assert_array_equal(cld, c64)
    np.testing.assert_array_equal(c64, [2.0, 2.0, 0.5])


#: A camera 1.5 m above the ground (global z = 0), looking along global +x: camera x (right)
#: is global -y, camera y (down) is global -z, camera z (forward) is global +x.
FORWARD = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.5],
                    [0.0, 0.0, 0.0, 1.0]])


def _rolled(degrees: float) -> np.ndarray:
    """FORWARD turned about its optical axis: the ground's depth then depends on the column."""
    roll = np.eye(4)
    a = np.radians(degrees)
    roll[:3, :3] = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    return FORWARD @ roll


ROLLED = _rolled(8.0)


def test_ground_depth_below_the_horizon_and_none_above():
    xy = np.array([[816.0, 491.0 + 95.0], [300.0, 491.0 + 38.0], [816.0, 400.0],
                   [816.0, 491.0]])
    d = geometry.plane_depth(xy, K, FORWARD, 0.0)
    np.testing.assert_allclose(d[:2], [1.5 * 1266.0 / 95.0, 1.5 * 1266.0 / 38.0])
    assert np.isnan(d[2:]).all(), "above the horizon and on it the ray never meets the ground"


def test_plane_depth_near_the_plane_and_from_on_it():
    """The ground 0.3 m below the camera is met within a metre by a steep ray; a camera on
    the plane itself (depth 0) meets it nowhere, and the rays parallel to it (0/0, x/0)
    raise no floating-point warning."""
    xy = np.array([[816.0, 491.0 + 633.0], [816.0, 491.0], [300.0, 600.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        below = geometry.plane_depth(xy, K, FORWARD, 1.2)
        on_plane = geometry.plane_depth(xy, K, FORWARD, 1.5)
    np.testing.assert_allclose(below[0], 0.3 * 1266.0 / 633.0)
    assert np.isnan(below[1]) and below[2] == pytest.approx(0.3 * 1266.0 / 109.0)
    assert np.isnan(on_plane).all()


def test_scene_depth_takes_the_nearest_surface():
    """A 2 m tall box 20 m ahead hides the ground behind it; beside it the ground, above the
    horizon the far plane."""
    centre = np.array([0.0, 0.5, 20.0])  # camera frame: its middle 1 m above the ground
    rot = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # length along z
    xy = np.array([[816.0, 491.0 + 40.0], [1500.0, 491.0 + 40.0], [816.0, 300.0]])
    depth, source = geometry.scene_depth(xy, K, FORWARD, [(centre, np.array([1.8, 4.0, 2.0]),
                                                           rot)], 0.0, far=500.0)
    assert list(source) == [geometry.BOX, geometry.GROUND, geometry.FAR]
    np.testing.assert_allclose(depth, [18.0, 1.5 * 1266.0 / 40.0, 500.0])


def test_scene_depth_keeps_the_nearer_of_two_boxes_in_either_order():
    """Two boxes on the principal ray, 9 m and 19 m away: the nearer one hides the farther
    one whichever is listed first."""
    near = (np.array([0.0, 0.0, 10.0]), np.array([2.0, 2.0, 2.0]), np.eye(3))
    far = (np.array([0.0, 0.0, 20.0]), np.array([2.0, 2.0, 2.0]), np.eye(3))
    xy = np.array([[816.0, 491.0]])
    for boxes in ([near, far], [far, near]):
        depth, source = geometry.scene_depth(xy, K, FORWARD, boxes, 0.0)
        np.testing.assert_array_equal(depth, [9.0])
        assert source.tolist() == [geometry.BOX]


def test_scene_depth_keeps_the_ground_where_a_box_is_no_nearer():
    """A box resting on the ground with its front face 3 m ahead, and a ray (focal length
    1 px) through its bottom front edge: box and ground are met at the same 3 m, and the
    ray stays marked ground (a box replaces only a farther surface); sources are int8."""
    box = (np.array([0.0, 1.0, 4.0]), np.array([1.0, 2.0, 2.0]), np.eye(3))  # y in [0.5, 1.5]
    depth, source = geometry.scene_depth(np.array([[0.0, 0.5]]), np.eye(3), FORWARD, [box],
                                         0.0)
    np.testing.assert_array_equal(depth, [3.0])
    assert source.dtype == np.int8 and source.tolist() == [geometry.GROUND]


def test_window_lattice_is_where_the_crop_samples_the_frame():
    """Crop a frame whose two channels are its own x and y coordinates: each crop pixel holds
    the point of the frame it was resampled from, which the lattice must name."""
    from flowmod.crops import crop_image, crop_windows

    h, w = 300, 400
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    coords = np.dstack([xs, ys])
    boxes = np.array([[100.0, 80.0, 140.0, 110.0], [250.5, 150.2, 270.1, 171.0]])
    got = crop_image(coords, boxes, size=24, scale=3.0)
    for win, crop in zip(crop_windows(boxes, 3.0), got, strict=True):
        np.testing.assert_allclose(geometry.window_lattice(win, 24), crop.reshape(-1, 2),
                                   atol=2e-3)


def test_static_flow_crop_equals_the_crop_of_the_static_flow_field():
    """Driving 1 m forward and turning 1 degree over a flat ground: the static flow at the
    crop's pixels is the crop of the whole frame's static flow (up to the bilinear resize)."""
    from flowmod.crops import crop_boxes, crop_windows

    a = np.radians(1.0)
    turn = np.eye(4)
    turn[:3, :3] = [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]
    T2 = turn @ FORWARD
    T2[0, 3] += 1.0
    h, w = 900, 1600
    ys, xs = np.mgrid[0:h, 0:w]
    xy = np.stack([xs.ravel(), ys.ravel()], 1).astype(float)
    depth, _ = geometry.scene_depth(xy, K, FORWARD, [], 0.0)
    field = geometry.static_flow(xy, depth, K, FORWARD, T2).reshape(h, w, 2)
    # the third and fourth windows leave the frame (right, bottom-left): edge-padded alike
    boxes = np.array([[1100.0, 560.0, 1160.0, 600.0], [400.0, 600.0, 470.0, 650.0],
                      [1550.0, 500.0, 1600.0, 540.0], [0.0, 840.0, 60.0, 890.0]])
    want = crop_boxes(field.astype(np.float32), boxes, 32)
    for win, crop in zip(crop_windows(boxes, 3.0), want, strict=True):
        got = geometry.static_flow_crop(win, 32, K, FORWARD, T2, [], 0.0, image_size=(w, h))
        assert got.shape == (2, 32, 32) and got.dtype == np.float32
        np.testing.assert_allclose(got, crop, atol=0.05)
        assert np.abs(crop).max() > 5.0, "the test needs flow worth the name"


def test_static_flow_crop_puts_the_sky_at_the_given_far_depth():
    """A crop of the sky (no box, above the horizon) as the camera drives 1 m forward: every
    pixel gets the flow of a point at ``far`` = 50 m, (p - c) / (50 - 1) px."""
    T2 = FORWARD.copy()
    T2[0, 3] += 1.0  # global x is the camera's forward axis
    win = np.array([700.0, 100.0, 64.0])
    got = geometry.static_flow_crop(win, 8, K, FORWARD, T2, [], 0.0, far=50.0)
    xy = geometry.window_lattice(win, 8)
    want = ((xy - [816.0, 491.0]) / 49.0).reshape(8, 8, 2).transpose(2, 0, 1)
    np.testing.assert_allclose(got, want, atol=1e-4)


def test_static_crops_explain_the_exact_flow_of_still_vehicles(smoke_built):
    """On the generated world the exact flow of a still vehicle and of the ground around it
    is the camera's own motion: the static-world crop from the two poses, the annotated box
    and the ground plane leaves hundredths of a pixel of it, while movers keep their own."""
    from flowmod import crops, dag, pipeline
    from flowmod.chapters import common

    p = smoke_built
    pairs = pd.read_parquet(pipeline.published(p, dag.Node("select")) / "pairs.parquet")
    x, idx = common.open_crops(p, "gt", "train")
    still = idx["true_speed"].to_numpy() < 0.01
    assert still.sum() >= 5 and (~still).sum() >= 5
    both = crops.static_crops(idx, pairs, p.crop_size, p.crop_scale, depths=("ground", "boxes"))
    static = crops.static_crops(idx, pairs, p.crop_size, p.crop_scale)["boxes"]
    np.testing.assert_array_equal(both["boxes"], static)  # one pass, same crops
    wins_ = crops.crop_windows(idx[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float),
                               p.crop_scale)
    row0 = pairs.set_index("pair_id").loc[idx["pair_id"].iloc[0]]
    np.testing.assert_array_equal(both["ground"][0], geometry.static_flow_crop(
        wins_[0], p.crop_size, *geometry.pair_cameras(row0), [], 0.0,
        image_size=crops.IMAGE_SIZE, box2d=idx[["xmin", "ymin", "xmax", "ymax"]].to_numpy(
            float)[0]))
    with pytest.raises(ValueError, match="unknown static-world depth"):
        crops.static_crops(idx.head(1), pairs, p.crop_size, p.crop_scale, depths=("lidar",))
    wins = crops.crop_windows(idx[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float),
                              p.crop_scale)
    on_box, rest, raw = [], [], []
    for i in np.flatnonzero(still):
        o, row = idx.iloc[i], pairs.set_index("pair_id").loc[idx["pair_id"].iloc[i]]
        c, rot = geometry.box_in_camera(
            np.asarray(row["cam2global_1"], float).reshape(4, 4),
            o[["center_x", "center_y", "center_z"]].to_numpy(float),
            o[["qw", "qx", "qy", "qz"]].to_numpy(float))
        _, src = geometry.scene_depth(
            geometry.window_lattice(wins[i], p.crop_size),
            np.asarray(row["intrinsic"], float).reshape(3, 3),
            np.asarray(row["cam2global_1"], float).reshape(4, 4),
            [(c, o[["size_w", "size_l", "size_h"]].to_numpy(float), rot)], 0.0)
        err = np.linalg.norm(np.asarray(x[i], np.float32) - static[i], axis=0).ravel()
        on_box.append(np.median(err[src == geometry.BOX]))
        rest.append(np.median(err[src == geometry.GROUND]))
        raw.append(np.median(np.linalg.norm(np.asarray(x[i], np.float32), axis=0)))
    raw, on_box, rest = np.array(raw), np.array(on_box), np.array(rest)
    seen = raw > 1.0  # the camera moved enough to matter (smoke egos also stand still)
    assert seen.sum() >= 5, raw
    assert np.median(on_box[seen]) < 0.05 and np.median(rest[seen]) < 0.1, (on_box, rest)
    assert np.median(on_box[seen] / raw[seen]) < 0.02
    movers = np.linalg.norm(np.asarray(x[~still], np.float32) - static[~still], axis=1)
    assert np.median(movers) > 10 * np.median(on_box)


def test_deployed_depth_puts_the_target_at_its_2d_boxs_ground_contact():
    """A car 18 m ahead on flat ground (rear face 1.8 m wide, as tall as the camera is high)
    seen as the camera drives 1 m forward. From its 2D box alone (bottom edge on the
    ground: 18 m) the deployable static flow inside the box is the annotated 3D box's; off
    the box it is the ground's; the ground alone would put the box's pixels at the far
    plane."""
    T2 = FORWARD.copy()
    T2[0, 3] += 1.0
    f, z = 1266.0, 18.0
    box2d = np.array([816.0 - f * 0.9 / z, 491.0, 816.0 + f * 0.9 / z, 491.0 + f * 1.5 / z])
    assert geometry.contact_depth(box2d, K, FORWARD, 0.0) == pytest.approx(z)
    assert np.isnan(geometry.contact_depth(np.array([700.0, 300.0, 900.0, 480.0]), K,
                                           FORWARD, 0.0)), "bottom edge above the horizon"
    c, rot = geometry.box_in_camera(FORWARD, np.array([z + 2.25, 0.0, 0.75]),
                                    np.array([1.0, 0.0, 0.0, 0.0]))
    annotated = [(c, np.array([1.8, 4.5, 1.5]), rot)]
    win = np.array([816.0 - 150.0, 430.0, 300.0])
    deployed = geometry.static_flow_crop(win, 30, K, FORWARD, T2, annotated, 0.0, box2d=box2d)
    oracle = geometry.static_flow_crop(win, 30, K, FORWARD, T2, annotated, 0.0)
    ground = geometry.static_flow_crop(win, 30, K, FORWARD, T2, [], 0.0)
    xy = geometry.window_lattice(win, 30)
    inside = ((xy[:, 0] > box2d[0] + 1) & (xy[:, 0] < box2d[2] - 1) & (xy[:, 1] > box2d[1] + 1)
              & (xy[:, 1] < box2d[3] - 1)).reshape(30, 30)
    assert inside.sum() >= 20
    np.testing.assert_allclose(deployed[:, inside], oracle[:, inside], atol=0.02)
    assert np.abs(ground[:, inside] - oracle[:, inside]).max() > 1.0
    np.testing.assert_allclose(deployed[:, ~inside & (xy[:, 1] > 600).reshape(30, 30)],
                               ground[:, ~inside & (xy[:, 1] > 600).reshape(30, 30)])


def test_residual_scores_refuse_misaligned_samples_and_need_a_whole_3d_box():
    """A row count that differs is one clear error; sizes without rotations are no 3D box
    (the centre's depth)."""
    pairs = pd.DataFrame([{"pair_id": "a", "intrinsic": K.ravel().tolist(),
                           "cam2global_1": np.eye(4).ravel().tolist(),
                           "cam2global_2": translation([0.0, 0.0, 1.0]).ravel().tolist(),
                           "timestamp_1": 0, "timestamp_2": 500_000}])
    obj = pd.DataFrame([{"pair_id": "a", "xmin": 780.0, "ymin": 470.0, "xmax": 850.0,
                         "ymax": 510.0, "center_x": 0.5, "center_y": 0.2, "center_z": 30.0,
                         "size_w": 1.9, "size_l": 4.5, "size_h": 1.5}])
    samples = np.ones((1, geometry.GRID ** 2, 2))
    with pytest.raises(ValueError, match=r"^3 flow samples for 1 objects$"):
        geometry.residual_scores(obj, pairs, np.ones((3, geometry.GRID ** 2, 2)))
    got = geometry.residual_scores(obj, pairs, samples)
    centre = geometry.residual_scores(obj.drop(columns=["size_w", "size_l", "size_h"]), pairs,
                                      samples)
    pd.testing.assert_frame_equal(got, centre)


def test_the_deployable_depth_on_a_rolled_camera_and_at_the_box_edges():
    """contact_depth is the ground depth under the middle of the box's bottom edge (on a
    camera rolled about its axis, that depends on the column too); deployed_depth puts the
    box's edges themselves at that depth and the sky at ``far``."""
    cam = ROLLED
    box = np.array([1000.0, 560.0, 1200.0, 640.0])
    want = geometry.plane_depth(np.array([[1100.0, 640.0]]), K, cam, 0.0)[0]
    assert np.isfinite(want) and geometry.contact_depth(box, K, cam, 0.0) == pytest.approx(want)
    assert geometry.contact_depth(box, K, cam, 0.0) != pytest.approx(
        geometry.plane_depth(np.array([[900.0, 640.0]]), K, cam, 0.0)[0])
    edges = np.array([[1000.0, 600.0], [1200.0, 600.0], [1100.0, 560.0], [1100.0, 640.0],
                      [999.0, 600.0], [1100.0, 100.0]])
    d = geometry.deployed_depth(edges, box, K, cam, 0.0, far=500.0)
    assert d[:4] == pytest.approx([want] * 4) and d[4] != pytest.approx(want)
    assert d[5] == 500.0  # above the horizon: the far plane given
    win = np.array([1000.0, 0.0, 200.0])
    crop = geometry.static_flow_crop(win, 8, K, cam, translation([0, 0, 1.0]) @ cam, [], 0.0,
                                     far=500.0, box2d=box)
    xy = geometry.window_lattice(win, 8)
    flow = geometry.static_flow(xy, geometry.deployed_depth(xy, box, K, cam, 0.0, far=500.0),
                                K, cam, translation([0, 0, 1.0]) @ cam)
    np.testing.assert_allclose(crop, flow.reshape(8, 8, 2).transpose(2, 0, 1), atol=1e-4)


def test_box_samples_take_the_nearest_pixel_clipped_to_the_image_as_float32():
    """A box that leaves the frame on every side samples the edge pixels (columns 0 and
    w - 1, rows 0 and h - 1); samples are float32 at any grid; box_residual reads its grid
    from the number of samples."""
    h, w = 6, 8
    ys, xs = np.mgrid[0:h, 0:w]
    flow = np.stack([xs, ys], axis=-1).astype(np.float64)  # each pixel holds its (x, y)
    got = geometry.box_samples(flow, np.array([[-3.0, -2.0, 10.0, 9.0]]), grid=3)
    assert got.dtype == np.float32 and got.shape == (1, 9, 2)
    assert got[0].tolist() == [[0, 0], [4, 0], [7, 0], [0, 4], [4, 4], [7, 4], [0, 5], [4, 5],
                               [7, 5]]  # the middle: 3.5 rounds to 4
    inside = geometry.box_samples(flow, [1.0, 1.0, 5.0, 3.0], grid=5)
    assert inside.shape == (1, 25, 2) and inside[0, -1].tolist() == [5.0, 3.0]
    center = np.array([0.0, 0.0, 40.0])
    box = np.array([800.0, 480.0, 832.0, 502.0])
    for grid in (3, 5):
        res_px, _ = geometry.box_residual(np.full((grid * grid, 2), 2.0), box, center, K,
                                          np.eye(4), np.eye(4), dt_s=0.5)
        assert res_px == pytest.approx(np.hypot(2.0, 2.0))


def test_the_deployable_box_is_bounded_by_its_own_columns_and_rows():
    """deployed_depth: a pixel right of the box (within its rows) and one on its bottom edge
    away from the middle: the ground outside, the contact depth inside."""
    cam = ROLLED
    box = np.array([1000.0, 560.0, 1200.0, 640.0])
    contact = geometry.contact_depth(box, K, cam, 0.0)
    xy = np.array([[1201.0, 600.0], [1050.0, 640.0]])
    d = geometry.deployed_depth(xy, box, K, cam, 0.0)
    ground = geometry.plane_depth(xy, K, cam, 0.0)
    assert d[0] == pytest.approx(ground[0]) and d[0] != pytest.approx(contact)
    assert d[1] == pytest.approx(contact) and ground[1] != pytest.approx(contact)
