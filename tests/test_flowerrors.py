"""Controlled flow errors (issue 52): each kind reaches its requested error on a synthetic
field, the pull toward the still-world flow, matched levels, seeding; the three verdicts."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest

from flowmod.chapters.common import three_verdicts
from flowmod.extensions import flowerrors as fe

S, SCALE = 40, 3.0
RAYLEIGH_MEAN = np.sqrt(np.pi / 2)


def _boxes(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 4) frame-px boxes of far vehicles (8-40 px wide), some cut by the frame edge."""
    w = rng.uniform(8, 40, n)
    h = w * rng.uniform(0.5, 1.0, n)
    x0 = rng.uniform(-5, 1500, n)
    y0 = rng.uniform(300, 600, n)
    return np.stack([x0, y0, x0 + w, y0 + h], axis=1)


def _batch(n: int = 24, seed: int = 7) -> fe.CropBatch:
    """Synthetic crops: a smooth still world (a gradient with ripples) and, in each box, the
    still flow plus a vehicle's own motion (0 for every third object: still vehicles)."""
    rng = np.random.default_rng(seed)
    boxes = _boxes(n, rng)
    yy, xx = np.mgrid[0:S, 0:S] / S
    still = np.stack([1.5 * xx + 0.3 * np.sin(9 * yy), 0.5 * yy + 0.2 * np.cos(7 * xx)])
    still = np.repeat(still[None], n, axis=0) * rng.uniform(0.5, 2.0, (n, 1, 1, 1))
    box = fe.box_masks(boxes, S, SCALE)
    own = rng.uniform(-3, 3, (n, 2, 1, 1)) * (np.arange(n) % 3 != 0)[:, None, None, None]
    ripple = 0.4 * np.sin(2.1 * np.arange(S))[None, None, None, :]
    flow = still + (own + ripple) * box[:, None]
    return fe.crop_batch(flow, boxes, SCALE, still=still)


@pytest.fixture(scope="module")
def batch() -> fe.CropBatch:
    return _batch()


def test_box_masks_cover_the_middle_of_the_window() -> None:
    m = fe.box_masks(np.array([[100.0, 200.0, 129.0, 229.0]]), 30, 3.0)[0]  # window (72, 172), n = 87
    rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
    assert (rows[0], rows[-1], cols[0], cols[-1]) == (9, 19, 9, 19)
    assert m[9:20, 9:20].all() and m.sum() == 11 * 11


def test_noise_reaches_sigma_times_rayleigh_mean(batch: fe.CropBatch) -> None:
    e = fe.endpoint_errors(fe.white_noise(batch.flow, 0.8, 0), batch.flow, batch.box)
    assert e["box_mean"] == pytest.approx(0.8 * RAYLEIGH_MEAN, rel=0.03)
    assert e["ring_mean"] == pytest.approx(0.8 * RAYLEIGH_MEAN, rel=0.02)
    assert e["box"].shape == (len(batch.flow),)


def test_ring_noise_leaves_the_box_exact(batch: fe.CropBatch) -> None:
    out = fe.ring_noise(batch.flow, 2.0, batch.box, 3)
    inside = np.broadcast_to(batch.box[:, None], out.shape)
    assert np.array_equal(out[inside], batch.flow[inside])
    e = fe.endpoint_errors(out, batch.flow, batch.box)
    assert e["box_mean"] == 0.0
    assert e["ring_mean"] == pytest.approx(2.0 * RAYLEIGH_MEAN, rel=0.02)


def test_pull_leaves_a_still_vehicle_unchanged_and_erases_motion_at_one(
        batch: fe.CropBatch) -> None:
    assert batch.still is not None
    for alpha in (0.3, 1.0):
        same = fe.pull_to_still(batch.still, batch.still, alpha, batch.box)
        assert np.array_equal(same, batch.still)
    full = fe.pull_to_still(batch.flow, batch.still, 1.0)
    np.testing.assert_allclose(full, batch.still, atol=1e-6)
    boxed = fe.pull_to_still(batch.flow, batch.still, 1.0, batch.box)
    inside = np.broadcast_to(batch.box[:, None], boxed.shape)
    np.testing.assert_allclose(boxed[inside], batch.still[inside], atol=1e-6)
    assert np.array_equal(boxed[~inside], batch.flow[~inside])
    assert np.array_equal(fe.pull_to_still(batch.flow, batch.still, 0.0), batch.flow)
    moved = batch.flow + np.float32(0.3)  # the ring off the still world: left as it is
    ring = fe.pull_to_still(moved, batch.still, 1.0, batch.box)
    assert np.array_equal(ring[~inside], moved[~inside])
    half = fe.pull_to_still(batch.flow, batch.still, 0.5, batch.box)
    own = np.linalg.norm(batch.flow - batch.still, axis=1)
    err = np.linalg.norm(half - batch.flow, axis=1)
    np.testing.assert_allclose(err, 0.5 * own * batch.box, atol=1e-5)
    with pytest.raises(ValueError):
        fe.pull_to_still(batch.flow, batch.still, 1.5)


def test_scale_error_is_s_times_the_flow_length(batch: fe.CropBatch) -> None:
    out = fe.scale_error(batch.flow, 0.2)
    np.testing.assert_allclose(np.linalg.norm(out - batch.flow, axis=1),
                               0.2 * np.linalg.norm(batch.flow, axis=1), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError):
        fe.scale_error(batch.flow, -1.0)


def test_outliers_reach_p_times_their_length_and_nest(batch: fe.CropBatch) -> None:
    small = fe.outliers(batch.flow, 0.05, 11)
    large = fe.outliers(batch.flow, 0.2, 11)
    e = fe.endpoint_errors(large, batch.flow, batch.box)
    assert e["box_mean"] == pytest.approx(0.2 * fe.OUTLIER_PX, rel=0.08)
    err = np.linalg.norm(large - batch.flow, axis=1)
    assert set(np.round(np.unique(err), 3)) <= {0.0, fe.OUTLIER_PX}
    hit_small = np.linalg.norm(small - batch.flow, axis=1) > 1
    assert (err[hit_small] > 1).all()
    assert np.array_equal(fe.outliers(batch.flow, 0.0, 11), batch.flow)


@pytest.mark.parametrize("upsample", ["bilinear", "nearest"])
def test_lost_resolution_of_a_constant_field_is_a_no_op(batch: fe.CropBatch,
                                                         upsample: str) -> None:
    const = np.broadcast_to(np.array([1.25, -0.5], np.float32)[None, :, None, None],
                            batch.flow.shape)
    for k in (1.0, 2.5, 4.0, 16.0):
        out = fe.lost_resolution(const, k, batch.windows, upsample)
        np.testing.assert_allclose(out, const, atol=1e-6)
    np.testing.assert_allclose(fe.lost_resolution(const, 4.0, None, upsample), const,
                               atol=1e-6)


def test_lost_resolution_averages_cells_of_the_grid() -> None:
    f = np.random.default_rng(0).normal(size=(3, 2, 8, 8)).astype(np.float32)
    out = fe.lost_resolution(f, 4, upsample="nearest")
    cells = f.reshape(3, 2, 2, 4, 2, 4).mean(axis=(3, 5))
    np.testing.assert_allclose(out, np.repeat(np.repeat(cells, 4, 2), 4, 3), atol=1e-6)
    bil = fe.lost_resolution(f, 4)
    assert bil[:, :, :2, :2] == pytest.approx(np.broadcast_to(cells[:, :, :1, :1],
                                                              (3, 2, 2, 2)))
    np.testing.assert_allclose(bil.mean(), f.mean(), atol=0.2)
    # a linear field inside the cell centres is reproduced by bilinear upsampling
    ramp = np.broadcast_to(np.arange(16, dtype=np.float32)[None, None, None, :], (1, 2, 16, 16))
    np.testing.assert_allclose(fe.lost_resolution(ramp, 4)[..., 2:14], ramp[..., 2:14],
                               atol=1e-5)


def test_lost_resolution_cells_are_those_of_the_frame_grid() -> None:
    """A crop that shrinks its window twofold: each crop pixel takes the mean of the crop
    pixels in its frame cell (cell c: frame pixels 4c .. 4c + 3), located as the crop's
    resize locates them (:func:`flowmod.geometry.window_lattice`)."""
    from flowmod.geometry import window_lattice

    f = np.random.default_rng(3).normal(size=(1, 2, 8, 8)).astype(np.float32)
    window = np.array([1, 5, 16])
    xy = window_lattice(window, 8).reshape(8, 8, 2)
    cell = np.floor((xy + 0.5) / 4).astype(int)
    key = cell[..., 1] * 100 + cell[..., 0]
    expected = np.empty_like(f)
    for c in np.unique(key):
        expected[0, :, key == c] = f[0, :, key == c].mean(axis=0)  # (pixels, 2)
    out = fe.lost_resolution(f, 4, window[None], "nearest")
    np.testing.assert_allclose(out, expected, atol=1e-6)


def test_lost_resolution_grows_with_the_cell(batch: fe.CropBatch) -> None:
    errs = [fe.realised_error("resolution", batch, k) for k in (2.0, 6.0, 20.0)]
    assert 0 < errs[0] < errs[1] < errs[2]


@pytest.mark.parametrize("kind", list(fe.KINDS))
def test_each_kind_is_matched_to_a_requested_box_error(batch: fe.CropBatch, kind: str) -> None:
    level = fe.match_level(kind, batch, 0.4, seed=5, tol=0.01)
    assert fe.KINDS[kind].lo <= level <= fe.KINDS[kind].hi
    assert fe.realised_error(kind, batch, level, 5) == pytest.approx(0.4, rel=0.01)


def test_a_target_the_range_s_first_level_already_exceeds_is_out_of_reach(
        batch: fe.CropBatch, monkeypatch) -> None:
    """The level is bisected between the grid's last level below the target and its first
    at or above it; a kind whose error at the range's first level already reaches the
    target has no level below it, so the target is out of reach (never a bisection from
    the range's far end)."""
    monkeypatch.setattr(fe, "realised_error", lambda kind, b, v, seed=0, stat="mean": 0.5 + v)
    with pytest.raises(ValueError, match=r"^noise: a mean box error of 0\.4 px is out of reach "
                       r"over sigma \(px\) in \[0\.0, 20\.0\] \(0\.5 to 20\.5 px\)$"):
        fe.match_level("noise", batch, 0.4)
    assert fe.match_level("noise", batch, 0.75) == pytest.approx(0.25, abs=0.01 * 0.75)


def test_levels_are_matched_across_kinds(batch: fe.CropBatch) -> None:
    levels = fe.match_levels(batch, [0.2, 0.5], kinds=["noise", "scale", "outliers"], seed=2)
    for kind, ls in levels.items():
        got = [fe.realised_error(kind, batch, v, 2) for v in ls]
        np.testing.assert_allclose(got, [0.2, 0.5], rtol=0.01)
    assert levels["noise"][0] == pytest.approx(0.2 / RAYLEIGH_MEAN, rel=0.05)
    assert np.isnan(fe.match_levels(batch, [500.0], kinds=["pull"])["pull"][0])


def test_an_unreachable_error_raises(batch: fe.CropBatch) -> None:
    with pytest.raises(ValueError, match="out of reach"):
        fe.match_level("pull", batch, 100.0)
    with pytest.raises(ValueError):
        fe.match_level("blur", batch, 1.0)
    with pytest.raises(ValueError):
        fe.match_level("noise", batch, 0.0)


def test_seeds_make_degradations_reproducible(batch: fe.CropBatch) -> None:
    for kind in ("noise", "outliers", "ring"):
        a = fe.degrade(kind, batch, 0.3, seed=4)
        assert np.array_equal(a, fe.degrade(kind, batch, 0.3, seed=4))
        assert np.array_equal(a, fe.degrade(kind, batch, 0.3, np.random.default_rng(4)))
        assert not np.array_equal(a, fe.degrade(kind, batch, 0.3, seed=5))
    a = fe.match_level("noise", batch, 0.5, seed=np.random.default_rng(9))
    assert a == fe.match_level("noise", batch, 0.5, seed=np.random.default_rng(9))


def test_the_pull_needs_the_still_world_flow(batch: fe.CropBatch) -> None:
    with pytest.raises(ValueError, match="still-world"):
        fe.degrade("pull", fe.CropBatch(batch.flow, batch.box), 0.5)
    with pytest.raises(ValueError):
        fe.white_noise(batch.flow[:, 0], 1.0, 0)


@pytest.mark.parametrize(("ci", "expected"), [
    ((0.5, 3.0), "decided"), ((-4.0, -0.1), "decided"),
    ((-0.8, 0.9), "equivalent"), ((-0.5, 4.0), "inconclusive"), ((-3.0, 0.2), "inconclusive"),
    ((0.0, 0.5), "equivalent"), ((0.0, 2.0), "inconclusive"), ((-0.5, 0.0), "equivalent"),
    ((-1.0, 0.5), "inconclusive"), ((-0.5, 1.0), "inconclusive"), ((1e-9, 0.5), "decided"),
    ((float("nan"), float("nan")), "inconclusive"),
])
def test_three_verdicts(ci: tuple[float, float], expected: str) -> None:
    assert three_verdicts(ci, 1.0) == expected


@pytest.mark.parametrize("delta", [0.0, -1.0, float("nan")])
def test_three_verdicts_needs_a_positive_delta(delta: float) -> None:
    with pytest.raises(ValueError):
        three_verdicts((-0.1, 0.1), delta)
    with pytest.raises(ValueError):
        three_verdicts((0.5, 0.1), 1.0)


# --- the experiment's plan (stages elevels, etrain, eevaluate) -------------------------------


def test_the_experiment_plans_an_exact_arm_and_each_kind_at_each_target() -> None:
    from flowmod import pipeline
    from flowmod.params import load_profile

    p = load_profile("demo")
    arms = fe.arms(p)
    assert arms[0] == (fe.EXACT, 0)
    assert len(arms) == 1 + len(p.error_kinds) * len(p.error_targets)
    keys = [fe.arm_key(*a) for a in arms]
    assert len(set(keys)) == len(keys) and all(fe.parse_arm(k) == a for k, a in zip(keys, arms, strict=True))
    train = [n for n in pipeline.nodes(p) if n.stage == "etrain"]
    assert len(train) == len(arms) * p.error_folds
    reads = {str(n): {str(i) for i in pipeline.inputs(n, p)} for n in train}
    assert reads["etrain[gt/exact/f0]"] == {"crops[gt/keyframe]"}
    assert reads["etrain[gt/pull/1/f0]"] == {"crops[gt/keyframe]", "context[keyframe]",
                                             "elevels[gt/pull]"}
    assert reads["etrain[gt/ring/0/f0]"] == {"crops[gt/keyframe]", "elevels[gt/ring]"}
    assert fe.arms(p.model_copy(update={"flow_methods": ["dis"]})) == []
    assert fe.arms(p.model_copy(update={"error_kinds": []})) == []


def test_an_arm_trains_with_the_seed_of_table_3_s_fold_model() -> None:
    """The experiment's fold-k model has the same seed (initialisation and data order) as
    Table 3's seed-0 model of fold k: arms differ from each other only in their input."""
    from flowmod.params import load_profile
    from flowmod.train import part_seed_offset, seed_parts

    p = load_profile("demo")
    for k, part in enumerate(fe.error_parts(p.model_copy(update={"error_folds": 3}))):
        assert part_seed_offset(f"noise/1/{part}") == part_seed_offset(seed_parts(p)[3 * k])
    assert fe.error_parts(p.model_copy(update={"folds": 1})) == ["s0"]


@pytest.mark.parametrize("bad, words", [({"error_folds": 4}, "error_folds=4 must be <="),
                                        ({"error_targets": [1.0, 0.0]}, "must be > 0 px")])
def test_bad_experiment_settings_are_refused(bad: dict, words: str) -> None:
    from flowmod.params import load_profile

    with pytest.raises(Exception, match=words):
        load_profile("demo", **bad)


def test_each_split_draws_its_own_error_and_the_same_one_in_every_node() -> None:
    a = fe._split_rng(0, "noise", 1, "f0").standard_normal(5)
    assert np.array_equal(a, fe._split_rng(0, "noise", 1, "f0").standard_normal(5))
    for other in [(1, "noise", 1, "f0"), (0, "ring", 1, "f0"), (0, "noise", 2, "f0"),
                  (0, "noise", 1, "f1")]:
        assert not np.array_equal(a, fe._split_rng(*other).standard_normal(5))


# --- chapter 13's reading of the real methods' errors --------------------------------------


def test_the_error_profile_names_what_each_kind_makes(batch: fe.CropBatch) -> None:
    from flowmod.chapters.ch13_flow_errors import error_profile

    exact, still, box = batch.flow, batch.still, batch.box
    clean = error_profile(exact, exact, still, box)
    assert np.allclose(clean[["epe_box", "epe_ring", "scatter", "bias", "lost"]], 0.0)
    noisy = error_profile(fe.white_noise(exact, 1.0, 3), exact, still, box)
    assert noisy["scatter"].mean() == pytest.approx(RAYLEIGH_MEAN, rel=0.05)
    assert noisy["bias"].mean() < 0.25
    pulled = error_profile(fe.pull_to_still(exact, still, 0.5, box), exact, still, box)
    movers = clean["motion"].to_numpy() >= 0.25
    assert np.allclose(pulled["lost"][movers], 0.5 * clean["motion"][movers], rtol=1e-4)
    assert np.allclose(pulled["lost"][~movers], 0.0)
    assert pulled["scatter"].mean() < 0.5 * pulled["lost"][movers].mean()
    scaled = error_profile(fe.scale_error(exact, 0.1), exact, still, box)
    box_mean = (exact * box[:, None]).sum((2, 3)) / box.sum((1, 2))[:, None]
    assert np.allclose(scaled["bias"], 0.1 * np.linalg.norm(box_mean, axis=1), rtol=1e-4)
    ring = error_profile(fe.ring_noise(exact, 1.0, box, 3), exact, still, box)
    assert np.allclose(ring["epe_box"], 0.0) and ring["epe_ring"].mean() > 1.0


def test_the_cost_per_px_is_the_slope_through_the_origin() -> None:
    from flowmod.chapters.ch13_flow_errors import slope_through_origin

    err = np.array([0.5, 1.0, 2.0])
    reps = np.stack([3.0 * err + d for d in (-0.5, 0.0, 0.5)], axis=1)
    slope, lo, hi = slope_through_origin(err, 3.0 * err, np.repeat(reps, 40, axis=1))
    assert slope == pytest.approx(3.0)
    assert lo < 3.0 < hi and hi - lo == pytest.approx(2 * 0.5 * err.sum() / (err @ err), rel=0.05)
    assert np.isnan(slope_through_origin(err, err, np.full((3, 4), np.nan))[1])


def test_a_profile_is_priced_by_the_kinds_that_make_its_parts() -> None:
    from flowmod.chapters.ch13_flow_errors import predictions

    prof = pd.DataFrame({"method": ["a", "b"], "epe_box": [1.0, 2.0], "epe_ring": [1.0, 0.0],
                         "scatter": [0.5, 1.0], "bias": [0.2, 0.0], "lost": [0.1, 0.3],
                         "measured": [1.0, 2.0], "measured_lo": [0.0, 1.0],
                         "measured_hi": [2.0, 3.0]})
    cost = pd.DataFrame({"kind": ["noise", "pull", "scale", "ring"],
                         "F1 points lost per px": [2.0, 10.0, 1.0, 0.5]})
    pred = predictions(prof, cost)
    assert pred["by end-point error"].tolist() == [2.0, 4.0]
    assert pred["by profile"].tolist() == pytest.approx([1.0 + 1.0 + 0.2 + 0.5, 2.0 + 3.0])
    assert pred["measured"].tolist() == [1.0, 2.0]
    half = predictions(prof, cost[cost["kind"] != "ring"])
    assert half["by profile"].isna().all()


def test_orderings_count_the_pairs_they_get_right() -> None:
    from flowmod.chapters.ch13_flow_errors import _pairs_agree

    assert _pairs_agree(np.array([1, 2, 3.0]), np.array([10, 20, 30.0])) == (3, 3)
    assert _pairs_agree(np.array([3, 2, 1.0]), np.array([10, 20, 30.0])) == (0, 3)
    assert _pairs_agree(np.array([1, 3, 2.0]), np.array([10, 20, 30.0])) == (2, 3)


def test_the_answer_names_the_kinds_that_cost_and_says_the_others_do_not() -> None:
    from flowmod.chapters.ch13_flow_errors import answer

    cost = pd.DataFrame({"kind": ["pull", "ring", "noise"],
                         "F1 points lost per px": [9.0, 1.0, -0.5],
                         "95% CI": ["7.0 to 11.0", "-0.5 to 2.5", "-2.0 to 1.0"],
                         "ci_lo": [7.0, -0.5, -2.0], "ci_hi": [11.0, 2.5, 1.0]})
    words = answer(cost)
    assert words.startswith("Per pixel of end-point error, only movers' motion pulled toward "
                            "the still world (9.0, 7.0 to 11.0) costs")
    assert "the other 2 kinds (white noise around the box only, white noise in the box)" in words
    assert "(from -2.0 to 2.5)" in words and "erases a vehicle's own motion" in words
    both = answer(cost.assign(ci_lo=[7.0, 0.5, -2.0]))
    assert "; white noise around the box only (1.0, -0.5 to 2.5) costs" in both
    assert "its kind, not its size" in both and "the other 1 kinds" in both
    none = answer(cost.assign(ci_lo=[-1.0, -0.5, -2.0]))
    assert none.startswith("No kind of error costs") and "between -2.0 and 11.0" in none
    assert "Too few" in answer(cost.iloc[:1])


def test_each_bad_setting_is_one_error_naming_the_value(batch: fe.CropBatch) -> None:
    """Every refused setting names what is wrong and the value given."""
    f = batch.flow
    cases = [
        (lambda: fe.white_noise(f, -0.5, 0), r"^sigma must be >= 0 px, got -0\.5$"),
        (lambda: fe.scale_error(f, -1.5), r"^scale error s must be > -1, got -1\.5$"),
        (lambda: fe.pull_to_still(f, batch.still, 1.5), r"^alpha must lie in \[0, 1\], got 1\.5$"),
        (lambda: fe.pull_to_still(f, batch.still[:2], 0.5),
         r"^still-world flow \(2, 2, 40, 40\) does not fit flow \(24, 2, 40, 40\)$"),
        (lambda: fe.outliers(f, 1.5, 0), r"^outlier share p must lie in \[0, 1\], got 1\.5$"),
        (lambda: fe.lost_resolution(f, 0.5), r"^cell side k must be >= 1 px, got 0\.5$"),
        (lambda: fe.lost_resolution(f, 2.0, upsample="cubic"),
         r"^upsample must be 'bilinear' or 'nearest', got 'cubic'$"),
        (lambda: fe.lost_resolution(f, 2.0, batch.windows[:3]), r"^3 windows for 24 crops$"),
        (lambda: fe.degrade("blur", batch, 1.0),
         r"^unknown kind of flow error 'blur'; known: \['noise', "),
        (lambda: fe.match_level("blur", batch, 1.0),
         r"^unknown kind of flow error 'blur'; known: \['noise', "),
        (lambda: fe.match_level("noise", batch, 0.0), r"^target error must be > 0 px, got 0\.0$"),
        (lambda: fe.realised_error("noise", batch, 1.0, stat="mode"),
         r"^stat must be 'mean' or 'median', got 'mode'$"),
        (lambda: fe.endpoint_errors(f, f[:2], batch.box),
         r"^degraded \(24, 2, 40, 40\) and clean \(2, 2, 40, 40\) crops differ in shape$"),
        (lambda: fe.degrade("pull", fe.CropBatch(f, batch.box), 0.5),
         r"^the pull needs the batch's still-world flow \(CropBatch\.still\)$"),
    ]
    # crops of another shape, each clause of (N, 2, S, S) on its own
    for shape in [(3, 2, 8), (1, 2, 8, 8, 1), (3, 3, 8, 8), (3, 2, 8, 9)]:
        cases.append((lambda shape=shape: fe.scale_error(np.zeros(shape), 0.5),
                      rf"^flow crops must be \(N, 2, S, S\), got {re.escape(str(shape))}$"))
    for call, words in cases:
        with pytest.raises(ValueError, match=words):
            call()
    assert fe.outliers(f, 1.0, 0).shape == f.shape  # both ends of [0, 1] are allowed


def test_the_simple_kinds_add_exactly_their_error_in_float32(batch: fe.CropBatch) -> None:
    """A scale error multiplies by 1 + s; white noise adds sigma times the seed's float32
    standard normals where the mask holds; a median is a stat too; everything float32."""
    f = batch.flow
    np.testing.assert_array_equal(fe.scale_error(f, 0.25), f * np.float32(1.25))
    z = np.random.default_rng(3).standard_normal(f.shape, dtype=np.float32)
    noisy = fe.white_noise(f, 0.5, 3, batch.box)
    np.testing.assert_array_equal(noisy, f + np.float32(0.5) * z * batch.box[:, None])
    assert noisy.dtype == np.float32
    ring = fe.ring_noise(f, 0.5, batch.box, 3)
    np.testing.assert_array_equal(ring, f + np.float32(0.5) * z * ~batch.box[:, None])
    out = fe.outliers(f, 0.3, 5, mask=batch.box)
    assert out.dtype == np.float32
    moved = np.linalg.norm(out - f, axis=1) > 1e-3
    assert moved.any() and not moved[~batch.box].any(), "only inside the mask"
    e = fe.endpoint_errors(noisy, f, batch.box)
    assert fe.realised_error("noise", batch, 0.5, 3, "median") == pytest.approx(
        fe.endpoint_errors(fe.degrade("noise", batch, 0.5, 3), f, batch.box)["box_median"])
    assert e["ring_mean"] == 0.0


def test_endpoint_errors_of_one_pixel_and_of_no_pixel() -> None:
    """An object whose box is one pixel: its error is that pixel's; an object without a box
    pixel has none (NaN), and the means over objects skip it; all undefined: NaN, no
    warning."""
    import warnings

    clean = np.zeros((2, 2, 3, 3), np.float32)
    noisy = clean.copy()
    noisy[0, 0, 1, 1] = 3.0
    noisy[0, 1, 1, 1] = 4.0
    noisy[:, 0, 0, 0] += 1.0
    box = np.zeros((2, 3, 3), bool)
    box[0, 1, 1] = True
    e = fe.endpoint_errors(noisy, clean, box)
    assert e["box"][0] == 5.0 and np.isnan(e["box"][1])
    assert e["box_mean"] == 5.0 and e["box_median"] == 5.0
    assert e["ring"].tolist() == [pytest.approx(1 / 8), pytest.approx(1 / 9)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        none = fe.endpoint_errors(noisy, clean, np.zeros((2, 3, 3), bool))
    assert np.isnan(none["box_mean"]) and np.isnan(none["box_median"])


def test_match_level_scans_the_grid_then_bisects_to_the_tolerance(batch: fe.CropBatch,
                                                                  monkeypatch) -> None:
    """The defaults (seed 0, the mean, 1 % tolerance, 16 steps): the levels it tries are
    first the 17 of the kind's range, then midpoints of the first bracket that reaches the
    target, stopping at the first within tolerance; a Generator seed is first turned into
    one integer seed; with no tolerance it bisects 60 times and returns the midpoint."""
    tried = []
    real = fe.realised_error

    def spy(kind, b, level, seed=0, stat="mean"):
        tried.append((level, seed, stat))
        return real(kind, b, level, seed, stat)

    monkeypatch.setattr(fe, "realised_error", spy)
    level = fe.match_level("noise", batch, 0.4)
    grid = np.linspace(0.0, 20.0, 17)
    assert [t[0] for t in tried[:17]] == grid.tolist()
    assert {t[1:] for t in tried} == {(0, "mean")}
    errs = [real("noise", batch, v, 0) for v in grid]
    i = next(j for j, e in enumerate(errs) if e >= 0.4)
    lo, hi = grid[i - 1], grid[i]
    for mid, *_ in tried[17:]:
        assert mid == (lo + hi) / 2
        e = real("noise", batch, mid, 0)
        if abs(e - 0.4) <= 0.01 * 0.4:
            break
        lo, hi = (mid, hi) if e < 0.4 else (lo, mid)
    assert level == tried[-1][0]
    assert real("noise", batch, level, 0) == pytest.approx(0.4, rel=0.01)
    assert level == fe.match_level("noise", batch, 0.4, 0, "mean", 0.01, 16)
    tried.clear()
    s = int(np.random.default_rng(9).integers(2**62))
    assert fe.match_level("noise", batch, 0.4, np.random.default_rng(9)) == \
        fe.match_level("noise", batch, 0.4, s)
    assert {t[1] for t in tried} == {s}
    med = fe.match_level("scale", batch, 0.4, 0, "median")  # objects' errors differ widely
    assert real("scale", batch, med, 0, "median") == pytest.approx(0.4, rel=0.01)
    assert real("scale", batch, med, 0, "mean") != pytest.approx(0.4, rel=0.01)
    exact = fe.match_level("scale", batch, 0.3, tol=0.0)
    assert real("scale", batch, exact, 0) == pytest.approx(0.3, rel=1e-5)  # float32 errors
    with pytest.raises(ValueError, match=r"^pull: a mean box error of 100 px is out of reach "
                       r"over alpha in \[0\.0, 1\.0\] \(0 to [0-9.]+ px\)$"):
        fe.match_level("pull", batch, 100.0)


def test_match_levels_default_to_every_kind_with_its_seed_and_tolerance(
        batch: fe.CropBatch) -> None:
    """Every kind of KINDS by default, in its order; the seed (default 0) and the tolerance
    are passed on to each match."""
    got = fe.match_levels(batch, [0.3], kinds=None, tol=0.2)
    assert list(got) == list(fe.KINDS)
    assert got["noise"] == [fe.match_level("noise", batch, 0.3, 0, "mean", 0.2)]
    assert got["noise"] != [fe.match_level("noise", batch, 0.3, 0, "mean", 0.01)]
    assert fe.match_levels(batch, [0.3], ["noise"], tol=1e-4) == {
        "noise": [fe.match_level("noise", batch, 0.3, 0, "mean", 1e-4)]}
    assert fe.match_levels(batch, [0.3], ["noise"], tol=1e-4) != {
        "noise": [fe.match_level("noise", batch, 0.3, 1, "mean", 1e-4)]}
