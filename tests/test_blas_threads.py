"""The fits' BLAS thread limit (nanostage.blas): one thread inside, for the threads
started inside too, and the process's own limits restored after."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

import nanostage.blas
from nanostage.blas import keep_one_blas_thread, single_threaded_blas


def _blas_threads() -> list[int]:
    return [int(i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"]


@pytest.fixture
def two_blas_threads():  # type: ignore[no-untyped-def]
    """The process at two BLAS threads (the project machine's default), restored after."""
    np.ones((2, 2)) @ np.ones((2, 2))  # the BLAS library is loaded
    if not _blas_threads():
        pytest.skip("no BLAS library reported by threadpoolctl")
    with threadpool_limits(limits=2, user_api="blas"):
        if not all(n == 2 for n in _blas_threads()):
            pytest.skip("BLAS cannot run two threads on this machine")
        yield


def test_one_blas_thread_inside_and_the_process_limits_restored_after(
    two_blas_threads: None,
) -> None:
    before = _blas_threads()
    assert all(n == 2 for n in before)
    with single_threaded_blas():
        assert all(n == 1 for n in _blas_threads())
        with single_threaded_blas():  # re-entrant
            assert all(n == 1 for n in _blas_threads())
        assert all(n == 1 for n in _blas_threads())
    assert _blas_threads() == before

    @single_threaded_blas()
    def inside() -> list[int]:
        return _blas_threads()

    assert all(n == 1 for n in inside())
    assert _blas_threads() == before
    with pytest.raises(ZeroDivisionError), single_threaded_blas():
        _ = 1 / 0
    assert _blas_threads() == before


def test_the_fits_worker_threads_run_with_the_limit(two_blas_threads: None) -> None:
    """Threads started inside (the candidates' fits) see one BLAS thread."""
    with single_threaded_blas(), ThreadPoolExecutor(max_workers=2) as pool:
        seen = list(pool.map(lambda _: _blas_threads(), range(4)))
    assert seen and all(all(n == 1 for n in s) for s in seen)


def test_products_inside_equal_the_single_threaded_ones(two_blas_threads: None) -> None:
    """Inside the limit a Gram product is the one-thread product bit for bit, whatever the
    process's limit (the fits' covariance does not depend on the machine's BLAS threads)."""
    j = np.random.default_rng(3).normal(size=(30_000, 1))
    with threadpool_limits(limits=1, user_api="blas"):
        reference = j.T @ j
    with single_threaded_blas():
        assert np.array_equal(j.T @ j, reference)


def _worker_blas_threads() -> list[int]:
    keep_one_blas_thread()
    return _blas_threads()


def test_an_executors_worker_process_keeps_one_blas_thread() -> None:
    """A spawned worker (its own BLAS, at the machine's default) runs one thread after the
    call; in a process already at one thread the call changes nothing."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        seen = pool.submit(_worker_blas_threads).result(timeout=120)
    assert seen and all(n == 1 for n in seen)


def test_keep_one_blas_thread_sets_no_limit_where_one_is_in_force(
    monkeypatch: pytest.MonkeyPatch, two_blas_threads: None
) -> None:
    """Inside a diagnosis (one thread in force) the call sets nothing that would outlive it."""
    calls: list[object] = []
    monkeypatch.setattr(nanostage.blas, "threadpool_limits", lambda **kw: calls.append(kw))
    with threadpool_limits(limits=1, user_api="blas"):
        keep_one_blas_thread()
    assert calls == []
    keep_one_blas_thread()  # at two threads
    assert calls == [{"limits": 1, "user_api": "blas"}]
