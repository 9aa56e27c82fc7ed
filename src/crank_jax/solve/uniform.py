"""The `"dopri8-uniform"` solver: equal steps of a fused ERK (default Dopri8) within each
interval between uniform save times, for any vector field.

Why not `diffrax.diffeqsolve` for this path? For a state of a few scalars, a diffrax solve
on the CPU is bound by per-step overhead, not arithmetic: the adaptive controller, the
dense-output interpolation for `SaveAt(ts=...)`, and the stage loop. The stages here are
unrolled ([`FusedERK`][], diffrax's own tableau), and since the save times are uniform, an
integer number `m` of equal steps per save interval lands exactly on every save time: no
interpolation, and the step control is a cheap integer choice per interval.

The number of steps per interval, `m_i`, adapts interval by interval, and the result is
checked a posteriori (details in `solve_uniform`). The error measure is the method's
embedded local-error estimate (7th order for Dopri8), scaled by `atol + rtol |y|` and
*summed* over all steps, `E`, as an estimate of the global error; the solve succeeds when
`E <= 1`. A short pilot over the first save intervals measures the error rate and picks the
first `m`; then each interval aims at an equal share of the budget: a controller picks
`m_{i+1}` from interval i's error (`E_i ~ m^-(p-1)`), and an interval that overshoots its
share 4x is redone with more steps. If the whole pass still ends with `E > 1`, the shares
shrink and the pass repeats. So `m` follows the motion both ways: a decaying oscillation
(the torsional scene) drops to the stability floor instead of paying for its start all the
way. The sum of the lower-order estimates over-estimates the error of the solution (by
10-1000x on the presets), so the measured global error meets the tolerance with margin;
`tests/test_uniform.py` checks it on the presets.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import library_api as compat
from .erk import FusedERK, dopri8, packer, rms_error

__all__ = ["UniformERK", "solve_uniform", "uniform_grid"]

# Constant of the global-error model E ~ C T omega (omega h)^p-1 / rtol used for the first
# guess, fitted on the lab rig with Dopri8 (a wrong guess costs one more pass, never
# accuracy).
_C_MODEL = 6e-5
_MAX_PASSES = 8
# Step selection (see `solve_uniform`): every save interval aims at an equal share of
# E = _E_AIM, so that a controller lagging a little still passes the check E <= 1.
_PILOT_INTERVALS = 8
_PILOT_PASSES = 3
_E_AIM = 0.5
# |h omega| below which Dopri8 is stable on an undamped oscillation (its stability region
# reaches ~4.8 along the imaginary axis; kept well inside).
_STABLE_H_OMEGA = 3.0
# An interval is redone if its error exceeds _REJECT times its share (at most _TRIES runs).
_REJECT = 4.0
_TRIES = 4


def _no_grad(tree):
    return jax.tree_util.tree_map(lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x,
                                  tree)


def _all_finite(tree):
    ok = jnp.array(True)
    for x in jax.tree_util.tree_leaves(tree):
        ok = ok & jnp.all(jnp.isfinite(x))
    return ok


class _Pass(NamedTuple):
    """What one pass of [`_make_pass`][] gives: `ys` (n, N), the packed states (see
    `erk.packer`); `E = sum E_i`, the summed scaled error (inf if the solution is not
    finite); `steps`, its steps; `top`, whether some interval wanted more than `max_sub`."""

    ys: jax.Array
    E: jax.Array
    steps: jax.Array
    top: jax.Array


class _Interval(NamedTuple):
    """The state carried from one save interval to the next within a pass: the state `y`,
    the error so far `E`, the next interval's step count `m`, the steps so far, `top`."""

    y: object
    E: jax.Array
    m: jax.Array
    steps: jax.Array
    top: jax.Array


class _Try(NamedTuple):
    """An interval's tries (redone with more steps while its error overshoots): try `j`,
    its `m` steps, the state `y` reached, its error `Ei`, the steps so far."""

    j: jax.Array
    m: jax.Array
    y: object
    Ei: jax.Array
    steps: jax.Array


class _Pilot(NamedTuple):
    """The pilot's loop: the steps per interval `m_p` it ran, the first interval's `m` it
    predicts, the steps so far, pass `j`."""

    m_p: jax.Array
    m_pred: jax.Array
    steps: jax.Array
    j: jax.Array


class _Select(NamedTuple):
    """The full passes' loop: the per-interval share `aim`, the floor on `m`, the last
    pass (a [`_Pass`][]), pass `j`."""

    aim: jax.Array
    m_floor: jax.Array
    last: _Pass
    j: jax.Array


class UniformERK(eqx.Module):
    """A uniform-step solver's step, in diffrax's shape: [`init`][] makes a pass's state at
    the first save time and [`step`][] takes it over one save interval (the unit of this
    solver: `m` equal steps that land on the next save time, redone with more while their
    error overshoots). One loop drives them, the scan of a pass over the save intervals
    (`_make_pass`), for the pilot and every full pass of [`solve_uniform`][] alike.
    `UniformDopri8` is one.

    **Field:** `erk`, the method, a [`FusedERK`][] (default Dopri8, `dopri8()`). The step
    counts' law (each interval's share of the error budget, its rejection at `_REJECT`
    times the share, at most `_TRIES` tries) is this module's; the tolerances come with
    each solve."""

    erk: FusedERK = eqx.field(default_factory=dopri8)

    def init(self, y0, m1, dtype) -> _Interval:
        """The `_Interval` state at the first save time: state `y0`, no error, no
        steps, `m1` steps for the first interval."""
        return _Interval(y0, jnp.zeros((), dtype), m1, jnp.zeros((), m1.dtype),
                         jnp.array(False))

    def step(self, f, args, c: _Interval, t0, t1, rtol, atol, aim, m_floor, max_sub: int,
             kind: str) -> _Interval:
        """One save interval (t0, t1] from `c`: `c.m` equal steps of `erk` on
        `f(t, y, args)`, redone with more while the interval's error overshoots `_REJECT`
        times its share `aim`, and the next interval's `m` (at least `m_floor`, at most
        `max_sub`; see `_make_pass`). `kind`: the `compat.while_loop` kind."""
        erk = self.erk
        dtype = t0.dtype
        expo = 1 / (erk.order - 1)

        def run(m, y):
            h = (t1 - t0) / m.astype(dtype)

            def body(cc):
                i, yy, Ei = cc
                y1, err = erk.step(f, t0 + i.astype(dtype) * h, yy, args, h)
                # The estimate only picks the step: stop_gradient keeps its arithmetic
                # (and its tangents) out of every derivative.
                e = rms_error(*jax.lax.stop_gradient((err, yy, y1)), rtol, atol)
                return i + 1, y1, Ei + e

            _, y1, Ei = compat.while_loop(lambda cc: cc[0] < m, body,
                                          (jnp.array(0), y, jnp.zeros((), dtype)),
                                          max_steps=max_sub, kind=kind)
            return y1, jnp.where(_all_finite(y1), Ei, jnp.inf)

        def grow_to(m, Ei):
            fac = (Ei / aim) ** expo
            return jnp.where(jnp.isfinite(fac), jnp.ceil(m * fac), 4.0 * m)

        # An interval whose error overshoots its share by _REJECT is redone with more
        # steps, as an adaptive solver rejects a step: the relative scale atol + rtol |y|
        # jumps where a component crosses zero, which the previous interval cannot
        # predict.
        def try_cond(t: _Try):
            return (t.j == 0) | ((t.Ei > _REJECT * aim) & (t.m < max_sub) & (t.j < _TRIES))

        def try_body(t: _Try):  # every try starts from the interval's start, c.y
            m = jnp.where(t.j == 0, t.m, jnp.minimum(jnp.maximum(grow_to(t.m, t.Ei),
                                                                 t.m + 1),
                                                     max_sub).astype(t.m.dtype))
            y1, Ei = run(m, c.y)
            return _Try(t.j + 1, m, y1, Ei, t.steps + m)

        t = compat.while_loop(try_cond, try_body,
                              _Try(jnp.array(0), c.m, c.y, jnp.zeros((), dtype), c.steps),
                              max_steps=_TRIES, kind=kind)
        want = grow_to(t.m, t.Ei)
        want = jnp.maximum(want, jnp.maximum(m_floor, (t.m + 1) // 2))
        return _Interval(t.y, c.E + t.Ei, jnp.minimum(want, max_sub).astype(t.m.dtype),
                         t.steps, c.top | (want > max_sub))


def _make_pass(solver: UniformERK, f, args, rtol, atol, max_sub, kind):
    """`one_pass(y0, ts, m1, aim, m_floor) -> _Pass`: the loop that drives `solver`'s
    `init` and `step` over the save intervals.

    Integrates `dy/dt = f(t, y, args)` over `ts` with `m_i` equal steps of `solver.erk` in
    save interval i. `m1` is the first interval's; then `m_{i+1}` comes from interval i's error,
    as a step-size controller would pick it: the summed scaled error estimate of an
    interval, `E_i`, goes as `m^-(p-1)` (p = `erk.order`), so
    `m_{i+1} = ceil(m_i (E_i / aim)^(1/(p-1)))`, which aims every interval at the same share
    `aim` of the global budget. `m` at most halves per interval (a slow fall lets a growing
    instability show in `E_i` before it matters) and never goes below `m_floor` or above
    `max_sub`. Returns a [`_Pass`][].
    """

    def one_pass(y0, ts, m1, aim, m_floor) -> _Pass:
        dtype = ts.dtype
        pack, _ = packer(y0)

        def scanned(c: _Interval, tt):
            c = solver.step(f, args, c, tt[0], tt[1], rtol, atol, aim, m_floor, max_sub,
                            kind)
            return c, pack(c.y)

        last, ys = jax.lax.scan(scanned, solver.init(y0, m1, dtype), (ts[:-1], ts[1:]))
        ys = jnp.concatenate([pack(y0)[None].astype(ys.dtype), ys])
        # A non-finite solution (an unstable step) counts as a failed pass.
        E = jnp.where(_all_finite(jax.lax.stop_gradient(ys)), last.E, jnp.inf)
        return _Pass(ys, E, last.steps, last.top)

    return one_pass


def _first_m(pilot_pass, y0, ts, rtol, m_model, m_floor0, max_sub, expo):
    """Step 1 of `solve_uniform`: the pilot on the first `_PILOT_INTERVALS` intervals with
    a constant `m` (floor `m_p`, aim inf: the per-interval control of `_make_pass` is off).

    **Returns:** `(m1, steps)`: the first interval's predicted `m`, the pilot's steps."""
    sg = jax.lax.stop_gradient
    dtype = ts.dtype
    n_int = ts.shape[0] - 1
    k = min(n_int, _PILOT_INTERVALS)
    ts_p, y0_p = sg(ts[: k + 1]), sg(y0)
    aim0 = jnp.asarray(_E_AIM / n_int, dtype)

    def predict(m_p, E_p):
        # Per-interval error E_p / k at m_p; aim at aim0. An unstable pilot: 4x m_p.
        fac = jnp.where(jnp.isfinite(E_p), (jnp.maximum(E_p / k, 1e-300) / aim0) ** expo, 4.0)
        return jnp.clip(jnp.ceil(m_p * fac), m_floor0, max_sub).astype(jnp.int32)

    def pilot_cond(c: _Pilot):
        far = (c.m_pred > 2 * c.m_p) | (2 * c.m_pred < c.m_p)
        return (c.j == 0) | ((c.j < _PILOT_PASSES) & far & (c.m_p < max_sub))

    def pilot_body(c: _Pilot):
        m_p = jnp.where(c.j == 0, c.m_p, c.m_pred)
        got = pilot_pass(y0_p, ts_p, m_p, jnp.asarray(jnp.inf, dtype), m_p)
        return _Pilot(m_p, predict(m_p, got.E), c.steps + got.steps, c.j + 1)

    m_p0 = jnp.clip(jnp.ceil(m_model / 2), m_floor0, max_sub).astype(jnp.int32)
    out = jax.lax.while_loop(pilot_cond, pilot_body,
                             _Pilot(m_p0, m_p0, jnp.zeros((), jnp.int32), jnp.array(0)))
    return out.m_pred, out.steps


def solve_uniform(field, y0, ts, rtol, atol, args=None, *, rate, max_steps, kind,
                  solver: UniformERK | None = None):
    """Integrate `dy/dt = field(t, y, args)` with `m_i` equal steps of `solver.erk` in save
    interval i, chosen to meet the tolerance.

    **Arguments:**

    - `field`: the vector field `field(t, y, args) -> dy/dt`, a callable pytree (e.g. an
      `eqx.Module`); its inexact-array leaves are differentiable parameters.
    - `y0`: the initial state, a pytree of arrays (small: the stages are unrolled per leaf).
    - `ts` (n,): uniform save times; `rtol`, `atol`: tolerances (scalars).
    - `args`: passed to `field`; its inexact-array leaves are differentiable too.
    - `rate`: a rate scale of the motion, 1/s (e.g. a natural frequency plus a decay
      rate): it sets the first guess and the stability floor on the steps. A guess only:
      the step counts are measured.
    - `max_steps`: the step budget; `kind`, the `compat.while_loop` kind that
      sets which autodiff works: `"lax"` (forward), `"checkpointed"` (reverse),
      `"bounded"` (both). JAX differentiates the loop itself (no rule of its own: see
      the module docstring).
    - `solver`: the [`UniformERK`][] whose `init` and `step` the passes drive (default
      `UniformERK()`, Dopri8).

    **Returns:** `(ys, result, num_steps)`: `ys` a pytree like `y0` with a leading axis n;
    `num_steps` counts the steps of every pass (the pilot passes included). `result` is
    `max_steps_reached` if meeting the tolerance would need more than `max_steps` steps.

    The global budget is `E <= 1`, `E` the summed scaled error estimate (module docstring);
    each save interval gets the share `_E_AIM / (n - 1)` of it:

    1. A pilot over the first `_PILOT_INTERVALS` intervals with a constant `m_p` measures
       the error rate and predicts the first interval's `m` (`E ~ m^-(p-1)`). `m_p` starts
       at half the model guess from `rate` (the guess alone was up to 4x too large). If the
       pilot is unstable or its prediction is more than 2x away from `m_p` (outside the
       asymptotic range), it is repeated at the prediction (at most `_PILOT_PASSES`).
    2. The full pass adapts `m_i` interval by interval (see `_make_pass`): honest in both
       directions, so a decaying motion (the torsional scene) stops paying for its start.
    3. The a-posteriori check: if the full pass ended with `E > 1` (or not finite), the
       per-interval share shrinks by the overrun (and, after an unstable pass, the floor
       on `m` doubles) and the pass repeats, at most `_MAX_PASSES` times.

    The floor `m >= dt rate / _STABLE_H_OMEGA` keeps a decayed, tiny motion from taking
    steps beyond the method's stability limit. The step choice runs on values
    (`stop_gradient`): `m` is an integer and carries no derivative.
    """
    import diffrax

    n = ts.shape[0]
    n_int = n - 1
    # Static bound on steps per interval, from the caller's overall step budget.
    max_sub = max(1, int(max_steps) // n_int)
    dtype = ts.dtype
    solver = UniformERK() if solver is None else solver
    expo = 1 / (solver.erk.order - 1)
    sg = jax.lax.stop_gradient
    one_pass = _make_pass(solver, field, args, rtol, atol, max_sub, kind)
    # The pilot never carries tangents, so a plain lax loop is fine in every adjoint mode.
    pilot_pass = _make_pass(solver, *_no_grad((field, args)), sg(rtol), sg(atol), max_sub, "lax")

    # Model guess from E ~ C T omega (omega h)^(p-1) / rtol <= 1/2 (see `_C_MODEL`).
    span = sg(ts[-1] - ts[0])
    dt = sg(jnp.max(jnp.diff(ts)))
    om = jnp.maximum(sg(jnp.asarray(rate, dtype)), 1e-3 / span)
    om_h = (0.5 * sg(rtol) / (_C_MODEL * span * om)) ** expo
    m_model = jnp.ceil(dt * om / om_h)
    m_floor0 = jnp.clip(jnp.ceil(dt * om / _STABLE_H_OMEGA), 1, max_sub).astype(jnp.int32)
    m1, pilot_steps = _first_m(pilot_pass, y0, ts, rtol, m_model, m_floor0, max_sub, expo)

    # 2.-3. Adaptive full passes until E <= 1. A single copy of the pass in the program
    # keeps compile time down.
    def sel_cond(c: _Select):
        return (c.j == 0) | ((c.last.E > 1) & ~c.last.top & (c.j < _MAX_PASSES))

    def sel_body(c: _Select):
        E = c.last.E
        bad = ~jnp.isfinite(E)
        aim = jnp.where(c.j == 0, c.aim,
                        jnp.where(bad, c.aim, c.aim * _E_AIM / jnp.maximum(E, 1)))
        m_floor = jnp.where((c.j > 0) & bad, jnp.minimum(2 * c.m_floor, max_sub), c.m_floor)
        got = one_pass(y0, ts, jnp.maximum(m1, m_floor), aim, m_floor)
        return _Select(aim, m_floor, got._replace(steps=c.last.steps + got.steps), c.j + 1)

    pack, unpack = packer(y0)
    ys0 = jnp.zeros((n,) + pack(y0).shape, dtype)
    init = _Select(jnp.asarray(_E_AIM / n_int, dtype), m_floor0,
                   _Pass(ys0, jnp.asarray(jnp.inf, dtype), pilot_steps, jnp.array(False)),
                   jnp.array(0))
    last = compat.while_loop(sel_cond, sel_body, init, max_steps=_MAX_PASSES, kind=kind).last
    result = diffrax.RESULTS.where(last.E <= 1, diffrax.RESULTS.successful,
                                   diffrax.RESULTS.max_steps_reached)
    return unpack(last.ys), result, last.steps


def uniform_grid(ts: np.ndarray, rtol: float = 1e-9) -> bool:
    """True if the concrete times `ts` are equally spaced (to `rtol` of the spacing)."""
    d = np.diff(np.asarray(ts, dtype=float))
    return d.size > 0 and bool(np.all(np.abs(d - d.mean()) <= rtol * abs(d.mean()) + 1e-300))
