"""Time the fits' linear algebra with the process's BLAS threads and with one
(``nanostage.blas.single_threaded_blas``), in one run, and print the medians and the ratio.

Each repeat runs, on two Python threads at once (as a diagnosis fits two candidates), an
SVD of a tall Jacobian (``--rows`` × ``--cols``, the shape of a 12-experiment diagnosis's
fit: position and command samples by the free parameters) and a bounded
``scipy.optimize.least_squares`` (``trf``) of a linear model of that shape. Run it alone or
beside other work: a multi-threaded BLAS suffers most when the cores are busy, as they are
in a diagnosis (the core's simulation threads).

    python benches/blas_threads.py [--rows 20000] [--cols 11] [--repeats 15]
"""

from __future__ import annotations

import argparse
import statistics
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.linalg
from scipy.optimize import least_squares
from threadpoolctl import threadpool_info

from nanostage.blas import single_threaded_blas


def work(jac: np.ndarray, y: np.ndarray) -> None:
    scipy.linalg.svd(jac, full_matrices=False)
    least_squares(lambda x: jac @ x - y, np.zeros(jac.shape[1]), bounds=(-10, 10), max_nfev=8)


def timed(jac: np.ndarray, y: np.ndarray, repeats: int) -> float:
    times = []
    with ThreadPoolExecutor(max_workers=2) as pool:
        for _ in range(repeats):
            t0 = time.perf_counter()
            list(pool.map(lambda _: work(jac, y), range(2)))
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=20000)
    ap.add_argument("--cols", type=int, default=11)
    ap.add_argument("--repeats", type=int, default=15)
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    jac = rng.normal(size=(a.rows, a.cols))
    y = jac @ rng.normal(size=a.cols) + 0.01 * rng.normal(size=a.rows)
    threads = sorted({int(i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"})
    timed(jac, y, 2)  # warm up the libraries and their thread pools
    default = timed(jac, y, a.repeats)
    with single_threaded_blas():
        one = timed(jac, y, a.repeats)
    print(f"{a.rows} x {a.cols}, two fits at once, median of {a.repeats}:")
    print(f"  BLAS threads {threads}: {default * 1e3:8.1f} ms")
    print(f"  one BLAS thread:      {one * 1e3:8.1f} ms")
    print(f"  ratio: {default / one:.1f}x")


if __name__ == "__main__":
    main()
