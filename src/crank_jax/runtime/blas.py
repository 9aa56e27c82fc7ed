"""The host's linear algebra on one BLAS thread while a fit runs.

Why: a fit's host-side linear algebra (the Gauss-Newton step's SVD, the uncertainty's
QR and SVD) works on small dense matrices, e.g. the lab record's multiple-shooting
Jacobian of 1318 x 26, between calls of XLA programs. OpenBLAS (NumPy's and SciPy's) splits
such a factorisation over a thread per core, whose barriers stall whenever another process
holds a core. Measured on a 2-core VM (experiments/fit_blas_threads.py, its
SVD 30 times, the warm lab fit 4 times, alternated):

| busy processes | SVD, default: median (worst) | one thread | warm fit, default | one thread |
|---|---|---|---|---|
| 0 | 1.32 ms (2.6 ms) | 1.04 ms (1.4 ms) | 0.192 s | 0.187 s |
| 1 | 1.03 ms (142 ms) | 0.77 ms (4.8 ms) | 0.325 s | 0.226 s |
| 2 | 0.93 ms (103 ms) | 0.85 ms (4.9 ms) | 0.330 s | 0.283 s |

A warm `crank-jax fit`, run while another job used the machine, took 2.73 s, three of its
SVDs 0.31-0.34 s each; rerun at once with one BLAS thread (`OPENBLAS_NUM_THREADS=1`) it
took 1.42 s, those SVDs 1.4 ms each.

The limit holds for the call only (`threadpoolctl`, the library scikit-learn uses for
this), and is restored after, also when the call raises: importing crank-jax changes
nothing. A matrix large enough to gain from threads would be a fit of very long records;
its factorisations still run, on one thread.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

__all__ = ["one_blas_thread"]

F = TypeVar("F", bound=Callable)


def one_blas_thread(fn: F) -> F:
    """`fn` with NumPy's and SciPy's BLAS limited to one thread while it runs (see the
    module docstring for why and for the measurement)."""

    @functools.wraps(fn)
    def limited(*args, **kwargs):
        import scipy.linalg  # noqa: F401  SciPy's own OpenBLAS loaded, so limited as well
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return limited  # type: ignore[return-value]
