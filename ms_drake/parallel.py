"""Run independent jobs in parallel: a local process pool by default, Ray on request.

`run_jobs(fn, jobs, workers=..., ray_address=None, use_ray=False)` yields `JobResult`s in
completion order. A job that raises, or whose worker process dies, yields a result with
`error` set; the others go on (on a dead local worker the pool reports the jobs it
lost; run again to redo them). `fn` must be a
module-level function (it is pickled to the workers).

Workers are replaced every `workers * max_tasks_per_child` jobs (default `MAX_TASKS_PER_CHILD`): a
Drake Diagram built from Python LeafSystems is never freed (pybind11 keep-alive cycles through
C++ that Python's garbage collector cannot see), so a worker that builds one station per job
grows by ~25 MB per 15-object search rollout (3 GB after 100; measured 2026-11-22, commit bf0b8f6).
A fresh worker costs ~2 s of imports, i.e. ~2 % of 20 rollouts.
"""

from __future__ import annotations

import multiprocessing
import os
from contextlib import contextmanager
import socket
import traceback
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator

from threadpoolctl import threadpool_limits

from ms_drake.errors import MsDrakeError


@dataclass
class JobResult:
    job: Any
    value: Any = None
    error: str = ""

    @property
    def ok(self) -> bool:
        return not self.error


def probe(x):
    """A tiny job for checking a pool or cluster: (x squared, worker pid, host); raises on
    negative x so error reporting can be checked too."""
    if x < 0:
        raise ValueError(f"probe({x}): negative input")
    return x * x, os.getpid(), socket.gethostname()


# The environment of every pool / Ray worker process: one worker per core, so the libraries that
# start their own threads (Mesa llvmpipe renders with one thread per core; OpenMP/BLAS) use one
# each instead of competing with the other workers (2 workers vs 1 went from 1.48x to 1.93x on 12
# heaps, 2 cores). A value the user exported wins. It is given to the processes when they start
# (OpenBLAS reads it when numpy loads, which unpickling a job already does), and every job also
# runs under threadpoolctl's BLAS limit of one thread: the jobs' BLAS calls are small products
# ((N, 3) points by a 3x3 rotation), where a second OpenBLAS thread only spins (7-40 ms of CPU
# instead of 0.5 ms for 10^5 points on the 2-core machine).
WORKER_ENV = {"LP_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


@contextmanager
def worker_environ():
    """os.environ with WORKER_ENV's defaults while the block runs (processes started in it inherit
    them); restored afterwards."""
    added = {k: v for k, v in WORKER_ENV.items() if k not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)

#: Jobs per worker process before it is replaced (bounds the memory of leaked Drake diagrams).
MAX_TASKS_PER_CHILD = 20


def _call(fn, job, worker_env: bool = False):
    if worker_env:
        for k, v in WORKER_ENV.items():
            os.environ.setdefault(k, v)
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            return JobResult(job, fn(job))
    except Exception as e:  # noqa: BLE001 - reported to the caller, the run goes on
        return JobResult(job, None, f"{type(e).__name__}: {e}\n{traceback.format_exc(limit=3)}")


def _run_local(fn, jobs: list, workers: int, max_tasks: int) -> Iterator[JobResult]:
    if workers <= 1 and len(jobs) <= max_tasks:  # short serial runs stay in this process
        for job in jobs:
            yield _call(fn, job)
        return
    # At most `workers` jobs in flight; after `workers * max_tasks` submissions the pool is shut
    # down without waiting (its running jobs finish, then its processes exit) and new jobs go to
    # a fresh pool, so there is no barrier between pools. (Python 3.11's own
    # ProcessPoolExecutor(max_tasks_per_child=...) hung now and then in tests/test_parallel.py.)
    # A dead worker breaks only its pool: the jobs it had in flight are reported, the rest go on.
    workers = max(1, workers)
    ctx = multiprocessing.get_context("spawn")  # Drake and VTK are not fork-safe
    pending, inflight = list(reversed(jobs)), {}
    pool, submitted = None, 0
    try:
        while pending or inflight:
            with worker_environ():  # the pool's processes start on submit and inherit it
                while pending and len(inflight) < workers:
                    if pool is None or submitted >= workers * max_tasks:
                        if pool is not None:
                            pool.shutdown(wait=False)
                        pool, submitted = ProcessPoolExecutor(max_workers=workers, mp_context=ctx), 0
                    job = pending.pop()
                    try:
                        inflight[pool.submit(_call, fn, job, True)] = (job, pool)
                        submitted += 1
                    except BrokenProcessPool:  # broken by a death noticed meanwhile: a fresh pool
                        pending.append(job)
                        pool.shutdown(wait=False)
                        pool = None
            done, _ = wait(set(inflight), return_when=FIRST_COMPLETED)
            for f in done:
                job, owner = inflight.pop(f)
                try:
                    yield f.result()
                except BrokenProcessPool:  # a worker died: this job (and others in flight) fail
                    yield JobResult(job, None, "worker process died (BrokenProcessPool)")
                    if owner is pool:
                        pool.shutdown(wait=False)
                        pool = None
    finally:
        if pool is not None:
            pool.shutdown(wait=True)


def _run_ray(fn, jobs: list, workers: int, address: str | None, max_tasks: int) -> Iterator[JobResult]:
    try:
        import ray
    except ImportError:
        raise MsDrakeError("Ray is not installed; install the extra with `pip install -e '.[ray]'` "
                           "or run without --ray") from None
    if not ray.is_initialized():
        env = {k: os.environ.get(k, v) for k, v in WORKER_ENV.items()}
        if address:
            ray.init(address=address, ignore_reinit_error=True, log_to_driver=False,
                     runtime_env={"env_vars": env})
        else:
            ray.init(num_cpus=max(1, workers), ignore_reinit_error=True, log_to_driver=False, runtime_env={"env_vars": env},
                     include_dashboard=False)
    remote = ray.remote(num_cpus=1, max_retries=0, max_calls=max_tasks)(_call)
    refs = {remote.remote(fn, job, True): job for job in jobs}
    not_done = list(refs)
    while not_done:
        done, not_done = ray.wait(not_done, num_returns=1)
        for r in done:
            try:
                yield ray.get(r)
            except Exception as e:  # noqa: BLE001 - a dead worker or actor
                yield JobResult(refs[r], None, f"ray worker failed: {type(e).__name__}: {e}")


def run_jobs(fn: Callable, jobs: Iterable, workers: int = 1, use_ray: bool = False,
             ray_address: str | None = None, max_tasks_per_child: int = MAX_TASKS_PER_CHILD) -> Iterator[JobResult]:
    """Run `fn(job)` for every job; yields JobResults as they complete. Local pools are
    replaced by fresh worker processes every `workers * max_tasks_per_child` jobs (Ray: a
    worker retires after `max_tasks_per_child` calls); a serial run (workers=1) of more jobs
    than that also goes to one-process pools."""
    if max_tasks_per_child < 1:
        raise ValueError(f"max_tasks_per_child={max_tasks_per_child}: must be >= 1")
    jobs = list(jobs)
    if use_ray or ray_address:
        yield from _run_ray(fn, jobs, workers, ray_address, max_tasks_per_child)
    else:
        yield from _run_local(fn, jobs, workers, max_tasks_per_child)


def run_shard_jobs(fn: Callable, jobs: Iterable, res: dict, sums=(), progress=None, **run_kwargs) -> dict:
    """Run dataset shard jobs (`run_jobs(fn, jobs, **run_kwargs)`; a job's shard index is job[1]) and
    count them into `res`: a written shard adds 1 to res["written"] and its value's `sums` keys to
    res's; a failed one is appended to res["failed"] as (shard index, [last line of its error]).
    progress(result) after each. Returns `res`."""
    for r in run_jobs(fn, jobs, **run_kwargs):
        if r.ok:
            res["written"] += 1
            for key in sums:
                res[key] += r.value.get(key, 0)
        else:
            res["failed"].append((r.job[1], (r.error or "").strip().splitlines()[-1:]))
        if progress is not None:
            progress(r)
    return res
