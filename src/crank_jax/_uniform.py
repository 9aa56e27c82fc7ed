"""The `"dopri8-uniform"` solver: Dopri8 steps of constant size between uniform save times.

Why not `diffrax.diffeqsolve` for this path? The equation has a 2-vector state, so on the
CPU a diffrax solve is bound by per-step overhead, not arithmetic: the adaptive controller,
the dense-output interpolation for `SaveAt(ts=...)`, and the stage loop (diffrax runs the
Runge-Kutta stages in a `while_loop`, so each stage is several small XLA kernels). Measured
in `experiments/bench_work_precision.py`, that is ~8 us per Dopri8 step. Here the stages of
diffrax's own Dopri8 tableau are unrolled into straight-line code and the right-hand side is
written so that XLA fuses each stage into about three kernels (one `rsqrt` and a single
division; see [`fused_acceleration`][]), which makes a step ~2.5x cheaper. And since the
save times are uniform, an integer number `m` of equal steps per save interval lands exactly
on every save time: no interpolation and no controller.

The step is chosen a priori, then checked: a first `m` comes from the linearised natural
frequency and the tolerance; one pass over the whole interval accumulates Dopri8's embedded
(7th-order) local-error estimate, scaled by `atol + rtol |y|` and *summed* over all steps,
as an estimate of the global error. If that sum exceeds 1, `m` grows (error ~ h^7 for the
sum) and the pass is repeated. The sum of the 7th-order estimates over-estimates the error
of the 8th-order solution (by 10-300x on the presets), so the measured global error meets
the tolerance with margin; `tests/test_uniform.py` checks it on the presets.
"""

from __future__ import annotations

import diffrax
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np

from ._dynamics import Structure
from ._loads import NoLoad
from ._params import SliderCrank

__all__ = ["fused_acceleration", "solve_uniform"]

_TAB = diffrax.Dopri8.tableau
# Dopri8's 14th stage (at y1) has zero weight in both the solution and the error estimate;
# it only serves as the next step's first stage. Recomputing that stage costs the same as
# carrying it, so the 13 stages below are all there is.
assert _TAB.b_sol[-1] == 0 and _TAB.b_error[-1] == 0
_NS = 13
_A = [tuple(float(x) for x in row) for row in _TAB.a_lower[: _NS - 1]]
_C = [0.0] + [float(x) for x in _TAB.c[: _NS - 1]]
_B = [float(x) for x in _TAB.b_sol[:_NS]]
_E = [float(x) for x in _TAB.b_error[:_NS]]
_ORDER = 8
# Constant of the global-error model E ~ C T omega (omega h)^7 / rtol used for the first
# guess, fitted on the lab rig (a wrong guess costs one more pass, never accuracy).
_C_MODEL = 6e-5
_MAX_PASSES = 8


def fused_acceleration(mech: SliderCrank, phi, dphi, t, load, torque,
                       structure: Structure):
    """phi'' = (q - K phi'^2) / M, rad/s^2: the same function as `acceleration`, written
    for XLA's CPU fusion.

    `acceleration` computes cos(delta) with a `sqrt` and delta', delta'' and phi'' with
    three divisions. XLA does not duplicate such "expensive" ops into several consumers, so
    each becomes its own kernel: ~4 kernels per evaluation, ~9 per Runge-Kutta stage once the
    stage sums are counted. Here `w = 1/cos(delta)` is one `rsqrt`, everything else is a
    product of it, and the only division is the last one, so a stage is ~3 kernels.
    Equal to `acceleration` to rounding (tested); `structure` skips terms as there.
    """
    has_P = not isinstance(load, NoLoad)
    sphi, cphi = jnp.sin(phi), jnp.cos(phi)
    M = mech.m_c * mech.s**2 + mech.I_c
    K = jnp.zeros_like(phi)
    q = jnp.zeros_like(phi)
    if structure.coupler or structure.slider or has_P:
        r, L = mech.r, mech.L
        lam = r / L  # loop-invariant: XLA hoists it
        sd = lam * sphi
        u = 1.0 - sd * sd
        w = jax.lax.rsqrt(u)
        cd = u * w
        d1 = lam * cphi * w
        d2 = lam * (d1 * cphi * sd - sphi * cd) * (w * w)
        lever = r * sphi + L * d1 * sd
    if structure.coupler:
        b = mech.b
        cpd = cphi * cd - sphi * sd
        spd = sphi * cd + cphi * sd
        M = M + mech.m_p * (r * r - 2 * r * b * d1 * cpd + b * b * d1 * d1) + mech.I_p * d1 * d1
        K = K + mech.m_p * (r * b * (d1 * (1 + d1) * spd - d2 * cpd) + b * b * d1 * d2)
        K = K + mech.I_p * d1 * d2
    if structure.slider:
        M = M + mech.m_s * lever * lever
        K = K + mech.m_s * lever * (r * cphi + L * (d2 * sd + d1 * d1 * cd))
    if structure.gravity:
        arm = mech.m_c * mech.s * sphi
        if structure.coupler:
            arm = arm + mech.m_p * (r * sphi + mech.b * d1 * sd)
        if structure.slider:
            arm = arm + mech.m_s * lever
        q = q + mech.g * arm
    if has_P:
        q = q + load(t) * lever
    if structure.spring:
        q = q - mech.k * phi
    if structure.damper:
        q = q - mech.c * dphi
    if not isinstance(torque, NoLoad):
        q = q + torque(t)
    return (q - K * dphi * dphi) / M


def _combine(y, h, coeffs, ks, j):
    acc = None
    for a, k in zip(coeffs, ks):
        if a != 0.0:
            term = a * k[j]
            acc = term if acc is None else acc + term
    return y[j] + h * acc if acc is not None else y[j]


def _step(f, t, y, h):
    """One Dopri8 step of size h from (t, y): returns (y1, scaled-error numerator)."""
    ks = [f(t, y)]
    for i in range(1, _NS):
        yi = (_combine(y, h, _A[i - 1], ks, 0), _combine(y, h, _A[i - 1], ks, 1))
        ks.append(f(t + _C[i] * h, yi))
    y1 = (_combine(y, h, _B, ks, 0), _combine(y, h, _B, ks, 1))
    err = tuple(h * sum(e * k[j] for e, k in zip(_E, ks) if e != 0.0) for j in range(2))
    return y1, err


def _omega(mech: SliderCrank, load) -> jax.Array:
    """A rate scale of the motion, rad/s, from the linearisation: |omega_n| plus damping."""
    from ._linear import linearize

    lin = linearize(mech, load)
    mu = jnp.abs(lin.mu)
    return jnp.sqrt(jnp.abs(lin.xi) / mu) + jnp.abs(lin.chi) / mu


def solve_uniform(mech, load, torque, y0, ts, rtol, atol, *, structure, max_steps, kind):
    """Integrate with `m` Dopri8 steps per save interval, `m` chosen to meet the tolerance.

    **Arguments:** as `_simulate._solve`; `y0` (2,), `ts` (n,); `kind` is the
    `equinox.internal.while_loop` kind that sets which autodiff works: `"lax"` (forward),
    `"checkpointed"` (reverse), `"bounded"` (both).

    **Returns:** `(ys (n, 2), result, num_steps)`. `num_steps` counts the steps of every
    pass, including rejected ones. `result` is `max_steps_reached` if meeting the tolerance
    would need more than `max_steps` steps in all.
    """
    n = ts.shape[0]
    # Static bound on steps per interval, from the caller's overall step budget.
    max_sub = max(1, int(max_steps) // (n - 1))
    dtype = ts.dtype

    def f(t, y):
        return (y[1], fused_acceleration(mech, y[0], y[1], t, load, torque, structure))

    def one_pass(m):
        mf = m.astype(dtype)

        def interval(carry, tt):
            y, E = carry
            t0, t1 = tt
            h = (t1 - t0) / mf

            def cond(c):
                return c[0] < m

            def body(c):
                i, y, E = c
                y1, err = _step(f, t0 + i.astype(dtype) * h, y, h)
                # diffrax's RMS norm of the error, scaled as its PID controller scales it.
                sc = [atol + rtol * jnp.maximum(jnp.abs(y[j]), jnp.abs(y1[j])) for j in range(2)]
                e = jnp.sqrt(0.5 * ((err[0] / sc[0]) ** 2 + (err[1] / sc[1]) ** 2))
                return i + 1, y1, E + e

            _, y, E = eqxi.while_loop(cond, body, (jnp.array(0), y, E), max_steps=max_sub,
                                      kind=kind)
            return (y, E), jnp.stack(y)

        (_, E), ys = jax.lax.scan(interval, ((y0[0], y0[1]), jnp.zeros((), dtype)),
                                  (ts[:-1], ts[1:]))
        ys = jnp.concatenate([y0[None], ys])
        # A non-finite solution (an unstable step) counts as a failed pass.
        E = jnp.where(jnp.all(jnp.isfinite(ys)), E, jnp.inf)
        return ys, E

    # First guess from E ~ C T omega (omega h)^7 / rtol <= 1/2 (see `_C_MODEL`). Computed
    # from values, not traced into the gradient: m is an integer.
    sg = jax.lax.stop_gradient
    span = sg(ts[-1] - ts[0])
    dt = sg(jnp.max(jnp.diff(ts)))
    om = jnp.maximum(sg(_omega(mech, load)), 1e-3 / span)
    r = sg(rtol)
    om_h = (0.5 * r / (_C_MODEL * span * om)) ** (1 / (_ORDER - 1))
    m0 = jnp.clip(jnp.ceil(dt * om / om_h), 1, max_sub).astype(jnp.int32)

    def grow(m, E):
        # E ~ h^7; aim at E = 1/2. An unstable pass (E = inf) quadruples m.
        fac = jnp.where(jnp.isfinite(E), (2 * E) ** (1 / (_ORDER - 1)), 4.0)
        m_new = jnp.maximum(jnp.ceil(m * fac), m + 1)
        return jnp.minimum(m_new, max_sub).astype(jnp.int32)

    # One pass per iteration; the first runs with m0. A single copy of the pass in the
    # program keeps compile time down.
    def sel_cond(c):
        m, _, E, _, k = c
        return (k == 0) | ((E > 1) & (m < max_sub) & (k < _MAX_PASSES))

    def sel_body(c):
        m, _, E, steps, k = c
        m = jnp.where(k == 0, m, grow(m, E))
        ys, E = one_pass(m)
        return m, ys, E, steps + m * (n - 1), k + 1

    init = (m0, jnp.zeros((n, 2), dtype), jnp.asarray(jnp.inf, dtype), jnp.zeros((), m0.dtype),
            jnp.array(0))
    m, ys, E, steps, _ = eqxi.while_loop(sel_cond, sel_body, init, max_steps=_MAX_PASSES,
                                         kind=kind)
    ok = E <= 1
    result = diffrax.RESULTS.where(ok, diffrax.RESULTS.successful,
                                   diffrax.RESULTS.max_steps_reached)
    return ys, result, steps


def uniform_grid(ts: np.ndarray, rtol: float = 1e-9) -> bool:
    """True if the concrete times `ts` are equally spaced (to `rtol` of the spacing)."""
    d = np.diff(np.asarray(ts, dtype=float))
    return d.size > 0 and bool(np.all(np.abs(d - d.mean()) <= rtol * abs(d.mean()) + 1e-300))
