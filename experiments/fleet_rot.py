"""The rotating rig of the fleet bench (`bench_fit_many.py --rig rotating`): records with two
channels and the peer's right-hand side.

The rig is `misfit_bench.py`'s `rot`: the offset slider-crank of `rotating_rig.py` (slider
line offset e = 8 mm, mount tilted by 0.35 rad, no spring), driven by a constant torque
`tau0` against a viscous damping `c`. Each record is its own unit (tau0, c within +-5% of
0.2 N*m and 0.01 N*m*s, start angle anywhere, start speed 3-7 rad/s), 3 s at 200 Hz (about
nine turns), with two channels: the crank angle `phi` (noise 2e-3 rad) and the slide
position `x_s` (noise 5e-5 m). Free tau0, c, phi0, dphi0, started from the nominal scene.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

import crank_jax as cj

FREE = ("tau0", "c", "phi0", "dphi0")
NOISE = {"phi": 2e-3, "x_s": 5e-5}  # rad, m
SENSORS = (cj.Sensor("phi"), cj.Sensor("x_s"))
NOMINAL = dict(tau0=0.2, c=0.01, phi0=0.0, dphi0=5.0)
T1, RATE = 3.0, 200.0
RTOL, ATOL = 1e-8, 1e-10
#: The peer's finite-difference step (relative): above the ODE error, which the default
#: (~1.5e-8) is not.
DIFF_STEP = 1e-6
#: The peer's ODE tolerances: at RTOL its finite-difference Jacobian is noisy enough that
#: LM stops up to a standard error short of the minimum (measured: 5 of 6 records); at
#: these it reaches it, at about the same time per fit.
PEER_RTOL, PEER_ATOL = 1e-10, 1e-12
#: Order of the peer's parameter tuple.
PARAM_ORDER = ("r", "L", "b", "s", "m_c", "m_p", "m_s", "I_c", "I_p", "c", "g", "e",
               "gravity_angle")


def mech(**over) -> cj.SliderCrank:
    """The rig's mechanism (masses and geometry known), `over` replacing fields."""
    m = dict(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.1, m_p=0.05, m_s=0.1, I_c=2e-3, I_p=2e-4,
             k=0.0, c=NOMINAL["c"], g=9.81, e=0.008, gravity_angle=0.35)
    m.update(over)
    return cj.SliderCrank(**m)


def scene(tau0: float, c: float, phi0: float, dphi0: float) -> cj.Scene:
    return cj.Scene(mech(c=c), torque=cj.ConstantLoad(tau0), phi0=phi0, dphi0=dphi0, t1=T1,
                    sensors=SENSORS, rtol=RTOL, atol=ATOL, name="rotating-rig")


def records(n: int, seed: int = 0):
    """The nominal scene and `n` records: (Data, its true tau0, c, phi0, dphi0)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        tau0 = NOMINAL["tau0"] * (1 + 0.05 * rng.uniform(-1, 1))
        c = NOMINAL["c"] * (1 + 0.05 * rng.uniform(-1, 1))
        phi0, dphi0 = rng.uniform(-math.pi, math.pi), rng.uniform(3.0, 7.0)
        d = cj.synthesize(scene(tau0, c, phi0, dphi0), rate=RATE, noise_std=dict(NOISE),
                          sensors=SENSORS, seed=seed * 100_003 + i)
        # The record keeps no torque (the synthesiser stores the scene's): tau0 is fitted.
        d = dataclasses.replace(d, torque=None)
        out.append((d, (tau0, c, phi0, dphi0)))
    return scene(**NOMINAL), out


def acceleration(phi, dphi, tau0, p):
    """phi'' of the offset slider-crank under a constant torque `tau0` (N*m), viscous
    damping and gravity along (-cos gamma, -sin gamma); `p` in [`PARAM_ORDER`][]. rad/s^2.
    M phi'' + (sum m J.H + I_p d1 d2) phi'^2 = -dV/dphi + tau0 - c phi', with J, H the
    first and second phi-derivatives of each centre of mass."""
    r, L, b, s, m_c, m_p, m_s, I_c, I_p, c, g, e, gam = p
    sp, cp = math.sin(phi), math.cos(phi)
    sd = (r * sp - e) / L
    cd = math.sqrt(1.0 - sd * sd)
    d1 = r * cp / (L * cd)
    d2 = (L * sd * d1 * d1 - r * sp) / (L * cd)
    jcx, jcy, hcx, hcy = -s * sp, s * cp, -s * cp, -s * sp
    jpx, jpy = -r * sp - b * sd * d1, r * cp - b * cd * d1
    hpx = -r * cp - b * (cd * d1 * d1 + sd * d2)
    hpy = -r * sp - b * (-sd * d1 * d1 + cd * d2)
    jsx = -r * sp - L * sd * d1
    hsx = -r * cp - L * (cd * d1 * d1 + sd * d2)
    M = (m_c * (jcx * jcx + jcy * jcy) + m_p * (jpx * jpx + jpy * jpy) + m_s * jsx * jsx
         + I_c + I_p * d1 * d1)
    K = (m_c * (jcx * hcx + jcy * hcy) + m_p * (jpx * hpx + jpy * hpy) + m_s * jsx * hsx
         + I_p * d1 * d2)
    dV = g * (math.cos(gam) * (m_c * jcx + m_p * jpx + m_s * jsx)
              + math.sin(gam) * (m_c * jcy + m_p * jpy))
    return (tau0 - c * dphi - dV - K * dphi * dphi) / M


def slide(phi, p):
    """x_s = r cos(phi) + L cos(delta), m, for an array of phi."""
    r, L, e = p[0], p[1], p[11]
    sd = (r * np.sin(phi) - e) / L
    return r * np.cos(phi) + L * np.sqrt(1.0 - sd * sd)


def numba_rhs():
    """The peer's right-hand side `f(t, y, tau0, p)`, compiled by numba (plain Python where
    numba is missing)."""
    from peers import HAVE_NUMBA

    if not HAVE_NUMBA:
        return lambda t, y, tau0, p: np.array([y[1], acceleration(y[0], y[1], tau0, p)])
    import numba

    acc = numba.njit(cache=True)(acceleration)

    @numba.njit(cache=True)
    def rhs(t, y, tau0, p):
        return np.array([y[1], acc(y[0], y[1], tau0, p)])

    return rhs


def peer_fit(rhs, scene, data, x0=None):
    """scipy least_squares (LM, finite-difference Jacobian) over solve_ivp DOP853 with the
    numba right-hand side, both channels' residuals divided by their noise, started from
    the scene's tau0, c and the record's first samples (or from `x0`). Returns the
    estimates (tau0, c, phi0, dphi0) and the final cost (half the sum of squares)."""
    from scipy.integrate import solve_ivp
    from scipy.optimize import least_squares

    d = scene.mech.as_dict()
    base = [float(d[k]) for k in PARAM_ORDER]
    ic = PARAM_ORDER.index("c")
    ts, phi, xs = (np.asarray(data.ts), np.asarray(data.channels["phi"]),
                  np.asarray(data.channels["x_s"]))

    def residuals(x):
        p = base.copy()
        p[ic] = x[1]
        sol = solve_ivp(rhs, (ts[0], ts[-1]), [x[2], x[3]], method="DOP853", t_eval=ts,
                        rtol=PEER_RTOL, atol=PEER_ATOL, args=(x[0], tuple(p)))
        if not sol.success:
            return np.full(2 * ts.size, 1e3)
        return np.concatenate([(sol.y[0] - phi) / NOISE["phi"],
                               (slide(sol.y[0], p) - xs) / NOISE["x_s"]])

    if x0 is None:
        dphi0 = float(np.polyfit(ts[:5] - ts[0], phi[:5], 1)[0])
        x0 = [float(scene.torque.value), float(scene.mech.c), float(phi[0]), dphi0]
    sol = least_squares(residuals, x0, method="lm", x_scale="jac", diff_step=DIFF_STEP)
    return sol.x, float(sol.cost), 0.5 * float(np.sum(residuals(np.asarray(x0)) ** 2))
