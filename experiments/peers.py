"""Peer integrators for the benchmarks: scipy and a compiled scalar Dormand-Prince 5(4).

Every peer integrates the same equation as `crank_jax.simulate` for a scene without loads
(`P = tau = 0`), from a hand-written scalar right-hand side, `acceleration_scalar`, that is
a line-by-line transcription of `crank_jax.model.dynamics` (M, K, q of the paper's eq. 30, with
the errata). The benchmarks check each peer against `crank_jax` at tight tolerance before
timing it.

- `scipy_solve(method, ...)`: `scipy.integrate.solve_ivp` (RK45, DOP853, LSODA) with a
  plain-Python RHS, which is how the equation would be written for scipy.
- `odeint_solve(...)`: `scipy.integrate.odeint` (LSODA, Fortran).
- `dp5_numba(...)`: the "compiled code" reference: a scalar adaptive Dormand-Prince 5(4)
  written in numba, with the standard error-per-step controller (RMS norm of the embedded
  error over `atol + rtol * max(|y0|, |y1|)`, safety 0.9, growth in [0.2, 10]), Hairer's
  starting step, and the 4th-order dense output of Shampine (the one scipy's RK45 uses)
  to sample the save times. numba is optional (`pip install crank-jax[bench]`);
  `HAVE_NUMBA` says whether it is importable.
- `dop853_numba(...)`: the compiled DOP853, transcribed from scipy's `DOP853` with scipy's
  own coefficients (`scipy.integrate._ivp.dop853_coefficients`), its controller (the
  combined 5th/3rd-order error norm, exponent -1/8, safety 0.9, growth in [0.2, 10], no
  growth right after a rejection), its starting step, and its 7th-order dense output (the
  three extra stages are computed only for steps that hold a save time). It agrees with
  scipy's DOP853 far within its tolerance (tests/test_benchmarks_smoke.py).
"""

from __future__ import annotations

import math

import numpy as np

try:
    import numba

    HAVE_NUMBA = True
except ImportError:  # numba is an optional benchmark dependency
    numba = None
    HAVE_NUMBA = False

__all__ = ["params_of", "acceleration_scalar", "rhs_py", "scipy_solve", "odeint_solve",
           "dp5_numba", "dop853_numba", "HAVE_NUMBA", "PARAM_ORDER"]

#: Order of the entries of the parameter tuple `p` used by every peer.
PARAM_ORDER = ("r", "L", "b", "s", "m_c", "m_p", "m_s", "I_c", "I_p", "k", "c", "g")


def params_of(mech) -> tuple[float, ...]:
    """A `SliderCrank`'s concrete values as a tuple of floats in [`PARAM_ORDER`][]."""
    d = mech.as_dict()
    return tuple(float(d[n]) for n in PARAM_ORDER)


def acceleration_scalar(phi, dphi, p):
    """phi'' = (q - K phi'^2) / M for scalar phi (rad), dphi (rad/s); no loads. rad/s^2."""
    r, L, b, s, m_c, m_p, m_s, I_c, I_p, k, c, g = p
    lam = r / L
    sphi = math.sin(phi)
    cphi = math.cos(phi)
    sd = lam * sphi
    cd = math.sqrt(1.0 - sd * sd)
    d1 = lam * cphi / cd
    d2 = lam * (d1 * cphi * sd - sphi * cd) / (cd * cd)
    cpd = cphi * cd - sphi * sd  # cos(phi + delta)
    spd = sphi * cd + cphi * sd  # sin(phi + delta)
    lever = r * sphi + L * d1 * sd  # -dx_s/dphi
    M = (m_c * s * s + I_c + m_p * (r * r - 2.0 * r * b * d1 * cpd + b * b * d1 * d1)
         + I_p * d1 * d1 + m_s * lever * lever)
    K = (m_p * (r * b * (d1 * (1.0 + d1) * spd - d2 * cpd) + b * b * d1 * d2)
         + I_p * d1 * d2 + m_s * lever * (r * cphi + L * (d2 * sd + d1 * d1 * cd)))
    q = g * (m_c * s * sphi + m_p * (r * sphi + b * d1 * sd) + m_s * lever) - k * phi - c * dphi
    return (q - K * dphi * dphi) / M


def rhs_py(p):
    """`f(t, y) -> [phi', phi'']` in plain Python, for scipy."""
    def f(t, y):
        return [y[1], acceleration_scalar(y[0], y[1], p)]
    return f


def scipy_solve(method: str, p, y0, ts, rtol: float, atol: float):
    """`solve_ivp` on [ts[0], ts[-1]] sampled at `ts`; returns (phi (n,), nfev)."""
    from scipy.integrate import solve_ivp

    sol = solve_ivp(rhs_py(p), (ts[0], ts[-1]), list(y0), method=method, t_eval=ts,
                    rtol=rtol, atol=atol)
    if not sol.success:
        raise RuntimeError(f"scipy {method} failed: {sol.message}")
    return sol.y[0], int(sol.nfev)


def odeint_solve(p, y0, ts, rtol: float, atol: float):
    """`scipy.integrate.odeint` (LSODA) at `ts`; returns (phi (n,), nfev)."""
    from scipy.integrate import odeint

    ys, info = odeint(rhs_py(p), list(y0), ts, rtol=rtol, atol=atol, tfirst=True,
                      full_output=True, mxstep=1_000_000)
    return ys[:, 0], int(info["nfe"][-1])


# --- compiled scalar Dormand-Prince 5(4) ------------------------------------------------

_C = np.array([0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0])
_A = np.array([
    [0, 0, 0, 0, 0],
    [1 / 5, 0, 0, 0, 0],
    [3 / 40, 9 / 40, 0, 0, 0],
    [44 / 45, -56 / 15, 32 / 9, 0, 0],
    [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729, 0],
    [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656],
])
_B = np.array([35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84])
_E = np.array([-71 / 57600, 0, 71 / 16695, -71 / 1920, 17253 / 339200, -22 / 525, 1 / 40])
# Shampine's 4th-order continuous extension: y(t0 + th h) = y0 + h sum_i K_i P_i(th).
_P = np.array([
    [1, -8048581381 / 2820520608, 8663915743 / 2820520608, -12715105075 / 11282082432],
    [0, 0, 0, 0],
    [0, 131558114200 / 32700410799, -68118460800 / 10900136933, 87487479700 / 32700410799],
    [0, -1754552775 / 470086768, 14199869525 / 1410260304, -10690763975 / 1880347072],
    [0, 127303824393 / 49829197408, -318862633887 / 49829197408,
     701980252875 / 199316789632],
    [0, -282668133 / 205662961, 2019193451 / 616988883, -1453857185 / 822651844],
    [0, 40617522 / 29380423, -110615467 / 29380423, 69997945 / 29380423],
])


def _dp5(p, y0, ts, rtol, atol, max_steps):
    n = ts.shape[0]
    out = np.empty((n, 2))
    out[0, 0] = y0[0]
    out[0, 1] = y0[1]
    K = np.empty((7, 2))
    t = ts[0]
    t_end = ts[-1]
    y = np.empty(2)
    y[0] = y0[0]
    y[1] = y0[1]
    ynew = np.empty(2)
    yi = np.empty(2)
    K[0, 0] = y[1]
    K[0, 1] = _acc(y[0], y[1], p)
    # Hairer & Wanner's starting step (as in scipy's select_initial_step), order 5.
    d0 = 0.0
    d1 = 0.0
    for j in range(2):
        sc = atol + abs(y[j]) * rtol
        d0 += (y[j] / sc) ** 2
        d1 += (K[0, j] / sc) ** 2
    d0 = math.sqrt(d0 / 2)
    d1 = math.sqrt(d1 / 2)
    h0 = 1e-6 if (d0 < 1e-5 or d1 < 1e-5) else 0.01 * d0 / d1
    h0 = min(h0, t_end - t)
    yi[0] = y[0] + h0 * K[0, 0]
    yi[1] = y[1] + h0 * K[0, 1]
    f1a = yi[1]
    f1b = _acc(yi[0], yi[1], p)
    d2 = 0.0
    sc0 = atol + abs(y[0]) * rtol
    sc1 = atol + abs(y[1]) * rtol
    d2 = math.sqrt((((f1a - K[0, 0]) / sc0) ** 2 + ((f1b - K[0, 1]) / sc1) ** 2) / 2) / h0
    if d1 <= 1e-15 and d2 <= 1e-15:
        h1 = max(1e-6, h0 * 1e-3)
    else:
        h1 = (0.01 / max(d1, d2)) ** (1 / 5)
    h = min(100 * h0, h1)
    nsteps = 0
    isave = 1
    while t < t_end and nsteps < max_steps:
        if t + h > t_end:
            h = t_end - t
        for s in range(1, 6):
            for j in range(2):
                acc_j = 0.0
                for q in range(s):
                    acc_j += _A[s, q] * K[q, j]
                yi[j] = y[j] + h * acc_j
            K[s, 0] = yi[1]
            K[s, 1] = _acc(yi[0], yi[1], p)
        for j in range(2):
            acc_j = 0.0
            for q in range(6):
                acc_j += _B[q] * K[q, j]
            ynew[j] = y[j] + h * acc_j
        K[6, 0] = ynew[1]
        K[6, 1] = _acc(ynew[0], ynew[1], p)
        err = 0.0
        for j in range(2):
            e = 0.0
            for q in range(7):
                e += _E[q] * K[q, j]
            sc = atol + max(abs(y[j]), abs(ynew[j])) * rtol
            err += (h * e / sc) ** 2
        err = math.sqrt(err / 2)
        nsteps += 1
        if err <= 1.0:
            t_new = t + h
            # Dense output for every save time in (t, t_new].
            while isave < n and ts[isave] <= t_new:
                th = (ts[isave] - t) / h
                for j in range(2):
                    v = 0.0
                    for q in range(7):
                        v += K[q, j] * (th * (_P[q, 0] + th * (_P[q, 1] + th * (
                            _P[q, 2] + th * _P[q, 3]))))
                    out[isave, j] = y[j] + h * v
                isave += 1
            t = t_new
            y[0] = ynew[0]
            y[1] = ynew[1]
            K[0, 0] = K[6, 0]  # first same as last
            K[0, 1] = K[6, 1]
            fac = 10.0 if err == 0.0 else min(10.0, 0.9 * err ** -0.2)
        else:
            fac = max(0.2, 0.9 * err ** -0.2)
        h *= fac
    if isave < n:
        out[isave:, :] = np.nan
    return out, nsteps


# --- compiled DOP853 (scipy's coefficients and controller) -------------------------------

def _dop853_coefficients():
    from scipy.integrate._ivp import dop853_coefficients as co

    return (np.ascontiguousarray(co.A, dtype=float), np.ascontiguousarray(co.B, dtype=float),
            np.ascontiguousarray(co.C, dtype=float), np.ascontiguousarray(co.E3, dtype=float),
            np.ascontiguousarray(co.E5, dtype=float), np.ascontiguousarray(co.D, dtype=float))


_A8, _B8, _C8, _E3, _E5, _D8 = _dop853_coefficients()


def _dop853_error_norm(K, h, y, ynew, rtol, atol):
    # scipy's DOP853._estimate_error_norm.
    e5 = 0.0
    e3 = 0.0
    for j in range(2):
        sc = atol + max(abs(y[j]), abs(ynew[j])) * rtol
        a5 = 0.0
        a3 = 0.0
        for q in range(13):
            a5 += _E5[q] * K[q, j]
            a3 += _E3[q] * K[q, j]
        e5 += (a5 / sc) ** 2
        e3 += (a3 / sc) ** 2
    if e5 == 0.0 and e3 == 0.0:
        return 0.0
    return abs(h) * e5 / math.sqrt((e5 + 0.01 * e3) * 2)


def _dop853_stages(p, K, y, t, h, first, last, yi):
    # Stages first..last-1 into K (scipy's rk_step / _dense_output_impl).
    for s in range(first, last):
        for j in range(2):
            acc_j = 0.0
            for q in range(s):
                acc_j += _A8[s, q] * K[q, j]
            yi[j] = y[j] + h * acc_j
        K[s, 0] = yi[1]
        K[s, 1] = _acc(yi[0], yi[1], p)


def _dop853(p, y0, ts, rtol, atol, max_steps):
    n = ts.shape[0]
    out = np.empty((n, 2))
    out[0, 0] = y0[0]
    out[0, 1] = y0[1]
    K = np.empty((16, 2))
    F = np.empty((7, 2))
    y = np.empty(2)
    ynew = np.empty(2)
    yi = np.empty(2)
    t = ts[0]
    t_end = ts[-1]
    y[0] = y0[0]
    y[1] = y0[1]
    K[0, 0] = y[1]
    K[0, 1] = _acc(y[0], y[1], p)
    # scipy's select_initial_step with the error estimator's order, 7.
    d0 = 0.0
    d1 = 0.0
    for j in range(2):
        sc = atol + abs(y[j]) * rtol
        d0 += (y[j] / sc) ** 2
        d1 += (K[0, j] / sc) ** 2
    d0 = math.sqrt(d0 / 2)
    d1 = math.sqrt(d1 / 2)
    h0 = 1e-6 if (d0 < 1e-5 or d1 < 1e-5) else 0.01 * d0 / d1
    h0 = min(h0, t_end - t)
    yi[0] = y[0] + h0 * K[0, 0]
    yi[1] = y[1] + h0 * K[0, 1]
    f1a = yi[1]
    f1b = _acc(yi[0], yi[1], p)
    sc0 = atol + abs(y[0]) * rtol
    sc1 = atol + abs(y[1]) * rtol
    d2 = math.sqrt((((f1a - K[0, 0]) / sc0) ** 2 + ((f1b - K[0, 1]) / sc1) ** 2) / 2) / h0
    if d1 <= 1e-15 and d2 <= 1e-15:
        h1 = max(1e-6, h0 * 1e-3)
    else:
        h1 = (0.01 / max(d1, d2)) ** (1 / 8)
    h_abs = min(100 * h0, h1)
    nsteps = 0
    isave = 1
    while t < t_end and nsteps < max_steps:
        rejected = False
        while True:
            t_new = min(t + h_abs, t_end)
            h = t_new - t
            _dop853_stages(p, K, y, t, h, 1, 12, yi)
            for j in range(2):
                acc_j = 0.0
                for q in range(12):
                    acc_j += _B8[q] * K[q, j]
                ynew[j] = y[j] + h * acc_j
            K[12, 0] = ynew[1]
            K[12, 1] = _acc(ynew[0], ynew[1], p)
            err = _dop853_error_norm(K, h, y, ynew, rtol, atol)
            nsteps += 1
            if err < 1.0:
                fac = 10.0 if err == 0.0 else min(10.0, 0.9 * err ** (-1 / 8))
                if rejected:
                    fac = min(1.0, fac)
                h_abs *= fac
                break
            h_abs *= max(0.2, 0.9 * err ** (-1 / 8))
            rejected = True
            if nsteps >= max_steps:
                break
        if err >= 1.0:
            break
        if isave < n and ts[isave] <= t_new:
            # The 7th-order dense output: three more stages, then scipy's F rows.
            _dop853_stages(p, K, y, t, h, 13, 16, yi)
            for j in range(2):
                dy = ynew[j] - y[j]
                F[0, j] = dy
                F[1, j] = h * K[0, j] - dy
                F[2, j] = 2 * dy - h * (K[12, j] + K[0, j])
                for r in range(4):
                    acc_j = 0.0
                    for q in range(16):
                        acc_j += _D8[r, q] * K[q, j]
                    F[3 + r, j] = h * acc_j
            while isave < n and ts[isave] <= t_new:
                x = (ts[isave] - t) / h
                for j in range(2):
                    v = 0.0
                    for i in range(7):
                        v += F[6 - i, j]
                        v *= x if i % 2 == 0 else 1 - x
                    out[isave, j] = y[j] + v
                isave += 1
        t = t_new
        y[0] = ynew[0]
        y[1] = ynew[1]
        K[0, 0] = K[12, 0]
        K[0, 1] = K[12, 1]
    if isave < n:
        out[isave:, :] = np.nan
    return out, nsteps


# numba resolves the global `_acc` when it compiles `_dp5`, so the loop calls compiled code.
_acc = acceleration_scalar
if HAVE_NUMBA:
    _acc = numba.njit(cache=True)(acceleration_scalar)
    _dp5_nb = numba.njit(cache=True)(_dp5)
    _dop853_error_norm = numba.njit(cache=True)(_dop853_error_norm)
    _dop853_stages = numba.njit(cache=True)(_dop853_stages)
    _dop853_nb = numba.njit(cache=True)(_dop853)


def dp5_numba(p, y0, ts, rtol: float, atol: float, max_steps: int = 10_000_000):
    """The compiled scalar DP5(4): returns (ys (n, 2) at `ts`, number of steps tried).

    Raises `RuntimeError` if numba is missing.
    """
    if not HAVE_NUMBA:
        raise RuntimeError("numba is not installed: pip install 'crank-jax[bench]'")
    ys, nsteps = _dp5_nb(tuple(float(x) for x in p), np.asarray(y0, dtype=float),
                         np.asarray(ts, dtype=float), float(rtol), float(atol), max_steps)
    return ys, int(nsteps)


def dop853_numba(p, y0, ts, rtol: float, atol: float, max_steps: int = 10_000_000):
    """The compiled DOP853 (scipy's method, in numba): returns (ys (n, 2) at `ts`, number of
    steps tried).

    Raises `RuntimeError` if numba is missing.
    """
    if not HAVE_NUMBA:
        raise RuntimeError("numba is not installed: pip install 'crank-jax[bench]'")
    ys, nsteps = _dop853_nb(tuple(float(x) for x in p), np.asarray(y0, dtype=float),
                            np.asarray(ts, dtype=float), float(rtol), float(atol), max_steps)
    return ys, int(nsteps)
