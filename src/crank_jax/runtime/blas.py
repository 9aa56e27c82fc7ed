"""The host's linear algebra on one BLAS thread while a fit runs.

Why: a fit's host-side linear algebra (the Gauss-Newton step's SVD, the uncertainty's
QR and SVD) works on small dense matrices, e.g. the lab record's multiple-shooting
Jacobian of 1318 x 26, between calls of XLA programs. OpenBLAS (NumPy's and SciPy's) splits
such a factorisation over a thread per core, whose barriers stall whenever another process
holds a core: one thread is as fast on an idle machine and never stalls on a busy one
(measured by experiments/fit_blas_threads.py: the table at the end of "End to end" in
docs/benchmarks/performance.md; a busy machine's slow fit, docs/benchmarks/design-figures.md).

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
