"""One BLAS thread while nanostage's fits run.

The fits (``scipy.optimize.least_squares``: an SVD of the Jacobian per iteration, the
covariance from ``JᵀJ``) work on tall, narrow matrices (tens of thousands of residual
samples by a dozen parameters), beside the core's simulation threads and, in a diagnosis,
several candidates fitted on Python threads at once. A multi-threaded BLAS splits each of
those small products over threads that wait for cores the simulations hold: on the
project's 2-core machine an SVD of a 20 000 × 11 Jacobian took about 100 ms with
OpenBLAS's two threads and 7 ms with one, under load (``benches/blas_threads.py``). One
thread per product is also what makes a fit's result independent of the machine's BLAS
thread count (a product reduced over two threads can differ from one thread's in the last
bit).

:func:`single_threaded_blas` limits every BLAS library loaded in the process
(``threadpoolctl``) for the body and restores the limits after. It is entered on the
thread that starts the fits (the diagnosis, the cross-fit, a friction fit, the EMPS
fit); the fits' worker threads, started inside, run with the limit. An executor's worker
in another process (``executor=``: a spawned process pool, a Dask cluster) calls
:func:`keep_one_blas_thread` before its first fit and keeps one BLAS thread from then on:
its fits give the same results to the last bit as the diagnosis's own."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from threadpoolctl import threadpool_info, threadpool_limits


@contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Run the body with one BLAS thread (a context manager, or a decorator:
    ``@single_threaded_blas()``); the process's limits are restored after, also when the
    body raises. Enter and leave it on one thread (module docstring)."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def keep_one_blas_thread() -> None:
    """Limit every BLAS library of the process to one thread from now on, unless they all
    run one already (for an executor's worker, module docstring: inside a diagnosis's own
    process the limit is in force and nothing changes; a worker process keeps the limit,
    as tasks running at once on its threads could not each restore their own)."""
    if any(int(i["num_threads"]) != 1 for i in threadpool_info() if i["user_api"] == "blas"):
        threadpool_limits(limits=1, user_api="blas")
