"""Ray as the flow stage's distributed engine (``executor: ray``).

The flow stage hands its per-pair calls to :func:`ray_results` instead of running them in
local processes. CPU methods (DIS, Farneback, ``gt``) run as one Ray task per pair, at most
a few per CPU in flight; networks run in a pool of actors, one per GPU of the cluster (one per
CPU slot without GPUs), each building its estimator (weights loaded) once and flowing chunks
of pairs in batches. Every worker writes its pair's file into the same pool folder, atomically,
under the same key as the local executor, so a Ray run and a local run resume each other and
give the same files. The pool folder (``run_dir``) and ``dataroot`` must therefore be visible
at the same path on every node (a shared file system).

Ray is imported only here and only when asked for (``import ray`` costs seconds).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

#: Tasks in flight per CPU of the cluster (bounds the scheduler's and the object store's load).
IN_FLIGHT_PER_CPU = 4
#: Object store of a local cluster started here: the calls pass paths and return tuples.
LOCAL_OBJECT_STORE = 256 * 1024**2

Result = tuple[str, float, tuple[int, ...]]


class RayUnavailableError(RuntimeError):
    """``executor: ray`` was asked for but Ray cannot be imported or reached."""


def _ray() -> Any:
    try:
        import ray
    except ImportError:
        raise RayUnavailableError(
            "executor: ray needs the ray package: `make env` installs it (environment/"
            "requirements.txt), or use executor: local") from None
    return ray


def connect(address: str = "local", num_cpus: int | None = None) -> dict[str, float]:
    """Join (or start) a Ray cluster once per process; returns its resources.

    ``address``: ``local`` starts a cluster of ``num_cpus`` CPUs inside this machine (for
    tests and single boxes); ``auto`` joins the cluster of this node (``ray start --head`` /
    ``ray start --address=...`` ran before); anything else is a head address
    (``host:6379`` or ``ray://host:10001``). A process already connected keeps its cluster.
    """
    ray = _ray()
    if not ray.is_initialized():
        quiet = {"include_dashboard": False, "log_to_driver": False,
                 "logging_level": logging.WARNING, "configure_logging": True}
        try:
            if address == "local":
                ray.init(num_cpus=num_cpus, object_store_memory=LOCAL_OBJECT_STORE, **quiet)
            else:
                ray.init(address=address, **quiet)
        except ConnectionError as e:
            raise RayUnavailableError(
                f"cannot reach the Ray cluster at ray_address={address!r} ({e}); start one "
                "(`ray start --head` on the head node) or use ray_address: local") from None
    return {k: float(v) for k, v in ray.cluster_resources().items()}


def _unwrap(ray: Any, fn: Callable[[], Any]) -> Any:
    """``fn()``, with an exception raised inside a task re-raised as its own type."""
    try:
        return fn()
    except ray.exceptions.RayTaskError as e:
        raise e.as_instanceof_cause() from None


def _task_results(ray: Any, fn: Callable[..., Result], calls: Sequence[tuple],
                  cpus: float) -> Iterator[Result]:
    """One task per call (``fn(*call)``), at most ``IN_FLIGHT_PER_CPU * cpus`` pending; the
    estimator (each call's first argument, the same object) is put in the object store once."""
    remote = ray.remote(num_cpus=1, max_retries=0)(fn)
    est_ref = ray.put(calls[0][0]) if calls else None
    window = max(2, int(IN_FLIGHT_PER_CPU * max(cpus, 1)))
    todo = iter(calls)
    pending: list[Any] = []
    while True:
        for call in todo:
            pending.append(remote.remote(est_ref, *call[1:]))
            if len(pending) >= window:
                break
        if not pending:
            return
        done, pending = ray.wait(pending, num_returns=1)
        yield _unwrap(ray, lambda d=done: ray.get(d[0]))


#: One pair's job for networks: (key, image 1, image 2, output file, extra).
Job = tuple[str, str, str, Path, Any]
#: ``batched(est, jobs, writer) -> Iterator[Result]``: the local executor's network loop.
Batched = Callable[[Any, list[Job], Any], Iterator[Result]]


class FlowWorker:
    """A Ray actor's body: one estimator (``cls(**options)``), built once, flowing chunks of
    pairs with the local executor's own loop ``batched``."""

    def __init__(self, cls: type, options: Mapping[str, Any], writer: Any,
                 batched: Batched) -> None:
        self.est = cls(**options)
        self.writer, self.batched = writer, batched

    def run(self, jobs: list[Job]) -> list[Result]:
        return list(self.batched(self.est, jobs, self.writer))


def _actor_results(ray: Any, cls: type, options: Mapping[str, Any],
                   jobs: Sequence[Job], writer: Any,
                   batched: Batched, batch_size: int, resources: Mapping[str, float],
                   n_cpu_actors: int) -> Iterator[Result]:
    """Networks: an actor per GPU (else ``n_cpu_actors`` one-CPU actors), chunks of
    ``4 * batch_size`` pairs handed to whichever actor is free."""
    from ray.util import ActorPool

    gpus = int(resources.get("GPU", 0))
    if gpus:
        actor_cls = ray.remote(num_gpus=1, num_cpus=1)(FlowWorker)
        n = gpus
    else:
        actor_cls = ray.remote(num_cpus=1)(FlowWorker)
        n = max(1, min(n_cpu_actors, int(resources.get("CPU", 1))))
    step = 4 * max(1, batch_size)
    chunks = [list(jobs[i : i + step]) for i in range(0, len(jobs), step)]
    n = min(n, len(chunks))
    actors = [actor_cls.remote(cls, dict(options), writer, batched) for _ in range(n)]
    log.info("flow %s: %d Ray actor(s) (%s)", getattr(cls, "name", cls), n,
             "GPU" if gpus else "CPU")
    pool = ActorPool(actors)
    results = pool.map_unordered(lambda a, c: a.run.remote(c), chunks)
    try:
        while True:
            try:
                chunk_results = _unwrap(ray, lambda: next(results))
            except StopIteration:
                return
            yield from chunk_results
    finally:
        for a in actors:
            ray.kill(a)


def ray_results(fn: Callable[..., Result], calls: Sequence[tuple], *, cls: type,
                options: Mapping[str, Any], cpu_bound: bool, writer: Any,
                batched: Batched, batch_size: int, address: str,
                n_jobs: int) -> Iterator[Result]:
    """The results of the flow stage's per-pair ``calls`` computed on a Ray cluster, in the
    order they finish (see the module docstring). ``calls`` are the local executor's
    argument tuples ``(est, key, a, b, out, writer, extra, threads)`` for ``fn``; networks
    (``cpu_bound`` False) instead build ``cls(**options)`` in each actor and run ``batched``."""
    ray = _ray()
    resources = connect(address, num_cpus=n_jobs)
    if cpu_bound:
        calls = [(*c[:-1], 1) for c in calls]  # one OpenCV thread per task
        yield from _task_results(ray, fn, calls, resources.get("CPU", 1))
    else:
        jobs = [(c[1], c[2], c[3], c[4], c[6]) for c in calls]
        yield from _actor_results(ray, cls, options, jobs, writer, batched, batch_size,
                                  resources, n_jobs)


def shutdown() -> None:
    """Leave the Ray cluster (stops a local one started by :func:`connect`)."""
    if "ray" in sys.modules:
        import ray

        if ray.is_initialized():
            ray.shutdown()
