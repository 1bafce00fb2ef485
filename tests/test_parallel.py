"""ms_drake.parallel: local pool and Ray give every result; failures are reported, not fatal."""

import os

import pytest

from ms_drake.parallel import run_jobs


def square(x):
    if x == 3:
        raise ValueError("three is not allowed")
    return x * x, os.getpid()


def test_serial_and_local_pool_give_every_result():
    for workers in (1, 2):
        results = list(run_jobs(square, range(6), workers=workers))
        assert sorted(r.job for r in results) == list(range(6))
        ok = {r.job: r.value[0] for r in results if r.ok}
        assert ok == {0: 0, 1: 1, 2: 4, 4: 16, 5: 25}
        (bad,) = [r for r in results if not r.ok]
        assert bad.job == 3 and "three is not allowed" in bad.error
        pids = {r.value[1] for r in results if r.ok}
        if workers == 1:  # a short serial run stays in this process
            assert pids == {os.getpid()}
        else:
            assert os.getpid() not in pids


def test_workers_are_replaced_after_max_tasks():
    """Leaked Drake diagrams die with their workers: fresh workers every workers x
    max_tasks_per_child jobs, also in a long serial run, which then leaves this process."""
    results = list(run_jobs(square, [0, 1, 2, 4, 5, 6], workers=2, max_tasks_per_child=1))
    assert sorted(r.value[0] for r in results) == [0, 1, 4, 16, 25, 36]
    assert len({r.value[1] for r in results}) >= 3  # three batches of two jobs, one pool each
    serial = list(run_jobs(square, [0, 1, 2, 4], workers=1, max_tasks_per_child=2))
    pids = [r.value[1] for r in serial]
    assert os.getpid() not in pids and len(set(pids)) == 2
    with pytest.raises(ValueError, match="max_tasks_per_child=0"):
        list(run_jobs(square, [0], max_tasks_per_child=0))


def die(x):
    if x == 1:
        os._exit(3)
    return x


def test_a_dying_worker_is_reported():
    results = list(run_jobs(die, [0, 1, 2], workers=2))
    assert len(results) == 3
    assert any("died" in r.error for r in results if not r.ok)


def test_ray_local_cluster():
    ray = pytest.importorskip("ray", reason="the optional ray extra is not installed")
    from ms_drake.parallel import probe

    try:
        results = list(run_jobs(probe, [0, 1, 2, -1, 4], workers=2, use_ray=True))
    finally:
        ray.shutdown()
    assert sorted(r.job for r in results) == [-1, 0, 1, 2, 4]
    assert {r.job: r.value[0] for r in results if r.ok} == {0: 0, 1: 1, 2: 4, 4: 16}
    (bad,) = [r for r in results if not r.ok]
    assert bad.job == -1 and "negative input" in bad.error
    assert all(r.value[1] != os.getpid() for r in results if r.ok)


def worker_env(name):
    return os.environ.get(name)


def test_pool_workers_use_one_render_thread_each(monkeypatch):
    """Each pool worker renders with one llvmpipe thread (else 2 workers fight over 2 cores),
    unless the user exported a value."""
    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    assert {r.value for r in run_jobs(worker_env, ["LP_NUM_THREADS"] * 2, workers=2)} == {"1"}
    monkeypatch.setenv("LP_NUM_THREADS", "3")
    assert {r.value for r in run_jobs(worker_env, ["LP_NUM_THREADS"] * 2, workers=2)} == {"3"}


def blas_threads(_):
    """OpenBLAS's thread count in the job (as numpy loaded it) and inside the job's limit."""
    import numpy  # noqa: F401 - loads OpenBLAS
    from threadpoolctl import threadpool_info

    return max((d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"), default=0), \
        os.environ.get("OPENBLAS_NUM_THREADS")


def test_jobs_run_with_one_blas_thread(monkeypatch):
    """A pool worker starts with OPENBLAS_NUM_THREADS=1 in its environment (numpy loads OpenBLAS
    when the job is unpickled, before it runs, so setting it then would be too late), and every job,
    serial ones in this process too, runs under a one-thread BLAS limit; the parent's environment
    is left as it was."""
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    assert {r.value for r in run_jobs(blas_threads, range(2), workers=2)} == {(1, "1")}
    assert {r.value for r in run_jobs(blas_threads, range(2), workers=1)} == {(1, None)}
    assert "OPENBLAS_NUM_THREADS" not in os.environ
