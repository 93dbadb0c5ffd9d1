"""executor: ray — the flow stage on a local Ray cluster (2 CPUs) gives the same files as the
local executor, resumes a local run (and the other way round), and the whole smoke study
built with it ends in the same metrics."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from test_flow import KW, _hand_set_fastflownet, make_dataroot

import flowmod.flow as fl
from flowmod.flow import distributed

#: The paper's chain (chapters 01-08): the extension chapters add nothing these tests check.
#: The chapters that compute flow and cut crops (and what they read).
FLOW_CHAPTERS = ["01", "02", "03", "05"]


@pytest.fixture(scope="module")
def ray_cluster():
    resources = distributed.connect("local", num_cpus=2)
    yield resources
    distributed.shutdown()


def _files(res: pd.DataFrame, pool) -> dict[str, bytes]:
    return {r.pair_id: (pool / r.file).read_bytes() for r in res.itertuples()}


@pytest.mark.parametrize("method, opts", [("dis", {"preset": "fast"}), ("farneback", {})])
def test_cpu_methods_on_ray_write_the_local_files(tmp_path, ray_cluster, method, opts):
    assert ray_cluster["CPU"] == 2
    root = tmp_path / "data"
    pairs = make_dataroot(root, n=5)
    kw = {**KW, "dataroot": root, "n_jobs": 2}
    local = fl.compute_flow(pairs, method, tmp_path / "local", **kw, **opts)
    remote = fl.compute_flow(pairs, method, tmp_path / "ray", executor="ray", **kw, **opts)
    assert remote["computed"].all()
    pd.testing.assert_frame_equal(remote.drop(columns=["seconds", "computed"]),
                                  local.drop(columns=["seconds", "computed"]))
    assert _files(remote, tmp_path / "ray") == _files(local, tmp_path / "local"), "bit-identical"
    assert (remote["seconds"] > 0).all()


def test_ray_and_local_resume_each_other(tmp_path, ray_cluster):
    root, pool = tmp_path / "data", tmp_path / "pool"
    pairs = make_dataroot(root, n=4)
    kw = {**KW, "dataroot": root, "n_jobs": 2}
    first = fl.compute_flow(pairs.iloc[:2], "dis", pool, executor="ray", **kw)
    assert first["computed"].all()
    both = fl.compute_flow(pairs, "dis", pool, **kw)  # local finishes what Ray began
    assert list(both["computed"]) == [False, False, True, True]
    again = fl.compute_flow(pairs, "dis", pool, executor="ray", **kw)
    assert not again["computed"].any()


def test_bad_image_on_ray_fails_before_any_work(tmp_path, ray_cluster):
    root = tmp_path / "data"
    pairs = make_dataroot(root, n=3)
    (root / pairs.path_1[2]).write_bytes(b"")
    with pytest.raises(fl.ImageError, match=pairs.path_1[2]):
        fl.compute_flow(pairs, "dis", tmp_path / "pool", dataroot=root, executor="ray", **KW)
    assert not list((tmp_path / "pool").rglob("*.npy"))


def test_error_inside_a_task_keeps_its_type(tmp_path, ray_cluster):
    """An image that passes the header check but fails in the worker: the error arrives as
    the library's own exception, naming the file, not as a bare RayTaskError."""
    root = tmp_path / "data"
    pairs = make_dataroot(root, n=2)
    other = make_dataroot(tmp_path / "small", n=1, size=(30, 40))
    (root / pairs.path_2[1]).write_bytes((tmp_path / "small" / other.path_2[0]).read_bytes())
    with pytest.raises(ValueError, match="size|shape"):
        fl.compute_flow(pairs, "dis", tmp_path / "pool", dataroot=root, executor="ray", **KW)


def test_network_actors_match_local_batches(tmp_path, ray_cluster):
    root = tmp_path / "data"
    pairs = make_dataroot(root, n=5, size=(50, 70))
    model = _hand_set_fastflownet(0.05, 0.0)
    kw = {**KW, "dataroot": root, "n_jobs": 2, "model": model, "device": "cpu",
          "batch_size": 2}
    local = fl.compute_flow(pairs, "fastflownet", tmp_path / "local", **kw)
    remote = fl.compute_flow(pairs, "fastflownet", tmp_path / "ray", executor="ray", **kw)
    assert remote["computed"].all()
    assert _files(remote, tmp_path / "ray") == _files(local, tmp_path / "local")


def test_unknown_executor_is_refused(tmp_path):
    root = tmp_path / "data"
    pairs = make_dataroot(root, n=1)
    with pytest.raises(ValueError, match="executor='dask'; allowed: local, ray"):
        fl.compute_flow(pairs, "dis", tmp_path / "pool", dataroot=root, executor="dask", **KW)


@pytest.mark.slow
def test_smoke_study_on_ray_gives_the_local_flow_and_crops(smoke_built, ray_cluster, tmp_path):
    """The smoke study's flow and crops chapters with executor: ray (and crops mode, the
    default of the demo and paper profiles: the crops stage computes every pair's flow on
    the cluster) in a fresh run folder: every kept flow file and every crop equals the local
    build's. The executor decides only where flow is computed; the classifiers read crops,
    so their metrics follow (test_crops.py checks them in crops mode)."""
    from flowmod import crops, pipeline, select
    from flowmod.chapters import common

    local = smoke_built
    p = local.model_copy(update={"executor": "ray", "ray_address": "local", "n_jobs": 2,
                                 "flow_store": "crops", "run_dir": str(tmp_path / "runs")})
    pipeline.build(p, chapters=FLOW_CHAPTERS)
    built = {n.stage for n in pipeline.nodes(p) if pipeline.recorded(p, n) is not None}
    assert {"flow", "crops"} <= built and "train" not in built
    for m in p.flow_methods:
        for part in select.PARTS:
            a, b = common.flow_reader(local, m, part), common.flow_reader(p, m, part)
            assert b.pair_ids and set(b.pair_ids) <= set(a.pair_ids)
            for pid in b.pair_ids:
                assert a.path(pid).read_bytes() == b.path(pid).read_bytes(), (m, part, pid)
            for split in crops.part_splits(part, p.folds):
                xa, ia = common.open_crops(local, m, split)
                xb, ib = common.open_crops(p, m, split)
                np.testing.assert_array_equal(xa, xb)
                pd.testing.assert_frame_equal(ia, ib)
