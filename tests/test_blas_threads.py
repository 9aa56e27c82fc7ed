"""The fit's host linear algebra runs on one BLAS thread, for the call only
(runtime/blas.py): inside, NumPy's and SciPy's OpenBLAS report one thread; after the call,
and after a call that raises, they report what they did before; importing the package
changes nothing."""

import subprocess
import sys

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

import crank_jax as cj
from crank_jax.runtime.blas import one_blas_thread


def _blas_threads() -> dict[str, int]:
    return {d["filepath"]: d["num_threads"] for d in threadpool_info()
            if d["user_api"] == "blas"}


def test_one_thread_inside_and_restored_after_even_on_error():
    import scipy.linalg  # noqa: F401  both OpenBLAS copies loaded

    seen = []

    @one_blas_thread
    def work(fail):
        seen.append(_blas_threads())
        if fail:
            raise RuntimeError("inside")
        return np.linalg.svd(np.eye(3))[1]

    with threadpool_limits(limits=2, user_api="blas"):  # a known state, whatever the host
        before = _blas_threads()
        assert before and all(n == 2 for n in before.values())
        np.testing.assert_array_equal(work(False), np.ones(3))
        assert _blas_threads() == before
        with pytest.raises(RuntimeError, match="inside"):
            work(True)
        assert _blas_threads() == before
    assert len(seen) == 2 and all(set(s.values()) == {1} for s in seen), seen
    assert set(seen[0]) == set(before)  # NumPy's and SciPy's libraries alike


class _Stop(Exception):
    pass


def test_the_identification_entry_points_run_on_one_thread(monkeypatch, lab_rig):
    # fit: its plan (the first host linear algebra) sees one thread, and a call that stops
    # there leaves the caller's count; validate, posterior and design carry the same limit.
    import crank_jax.identify.fit as fit_module

    seen = []

    def stop(req):
        seen.append(_blas_threads())
        raise _Stop

    monkeypatch.setattr(fit_module, "make_plan", stop)
    data = cj.synthesize(lab_rig, t1=1.0, rate=100.0, noise_std=1e-3, seed=0)
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        with pytest.raises(_Stop):
            cj.fit(lab_rig, data, free=("k",), progress=False, warn=False)
        assert _blas_threads() == before
    assert seen and set(seen[0].values()) == {1}, seen
    for entry in (cj.fit, cj.validate, cj.posterior, cj.design):
        assert entry.__code__ is one_blas_thread(len).__code__, entry  # the limit's wrapper


def test_importing_the_package_changes_no_thread_count():
    code = ("import numpy, scipy.linalg; from threadpoolctl import threadpool_info as i; "
            "a = [d['num_threads'] for d in i()]; import crank_jax; "
            "b = [d['num_threads'] for d in i()]; assert a == b, (a, b); print(a)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
