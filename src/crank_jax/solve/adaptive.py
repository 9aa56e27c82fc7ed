"""The `"dopri8-adaptive"` solver: adaptive fused Dopri8 steps with dense output, for any
vector field.

Why not `diffrax.diffeqsolve`? The method and its tolerance semantics are diffrax's (the
Dopri8 tableau, its 7th-order embedded estimate in diffrax's RMS norm, an integral
controller like scipy's DOP853 and diffrax's `PIDController` default, diffrax's Dopri8
dense output), but for a state of two scalars a step on the CPU is bound by per-kernel
overhead, not arithmetic (about two kernels per stage, and more per loop iteration once
the loop carries more than 512 bytes, when XLA's CPU runtime stops running the body's
kernels one after the other in the calling thread; docs/benchmarks/design-figures.md).
So:

- the stages are unrolled ([`FusedERK`][]) and the first stage is the previous step's last
  (first same as last);
- `unroll` step attempts run per loop iteration, so the loop condition and the output
  update are paid once per block of attempts, not per step;
- the dense output is evaluated once per block, for a window of `window` pending save
  times: each save time takes the coefficients of the accepted attempt that covers it (a
  select per attempt), one polynomial evaluation for the window, and one update of the
  output. An attempt is shortened so that the block never passes the window's last save
  time; this binds only where the saves are denser than the steps;
- the step loop writes to a buffer of `chunk + window` save times (512 bytes for the
  crank), and an outer loop copies each chunk to the n outputs: a step loop that carried
  the outputs themselves cost more per step (docs/benchmarks/design-figures.md).

Unlike `"dopri8-uniform"` the step count follows the motion, not the save grid: the error
is controlled per step (`rtol`, `atol` mean what they mean for diffrax's `PIDController`).
The steps are chosen on values (`stop_gradient`), so forward mode (`jax.jvp`,
`jax.jacfwd`) differentiates the solution along the chosen steps.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from . import library_api as compat
from .controller import PIDController
from .dense_output import dopri8_dense, window_values
from .erk import FusedERK, dopri8, packer

__all__ = ["AdaptiveERK", "solve_adaptive", "outcome", "Recorder"]

# Step attempts per loop iteration, and save times one block may write. Measured on the
# lab rig (10 s, 1001 saves, rtol 1e-8): one trajectory costs the same per step with 1, 4
# or 8 attempts per iteration (within the noise of a shared machine); a 10^4 batch in
# lockstep costs 397 us per trajectory with 1 attempt and a window of 4, 475 us with a
# window of 24 and 674 us with 4 attempts (each attempt selects its coefficients for the
# whole window, which a batch pays per member).
UNROLL = 1
WINDOW = 4
# Save times per chunk (see `solve_adaptive`'s body): CHUNK + WINDOW rows of a (2,) state
# are 512 bytes. (A state with its sensitivities, variational.py, is larger; 2 or 28 save
# times per chunk measured the same for the crank's 10-parameter Jacobian.)
CHUNK = 28


def _rms(x):
    """RMS over the state (the last axis), kept as a trailing axis of size 1: one error
    per member of a batch, each member controlling its own step."""
    return jnp.sqrt(jnp.mean(x * x, axis=-1, keepdims=True))


def _error_norm(x, error_size):
    """The step control's norm of a scaled local error `x` (..., N): the RMS over its
    first `error_size` components (all for None), or, for `error_size = (n, q)` (a state
    of n components followed by its (n, q) sensitivities, row-major: variational.py), the
    largest of the state's RMS and each sensitivity column's, as CVODES measures a state
    with its sensitivities (`errconS`). Shape (..., 1)."""
    if not isinstance(error_size, tuple):
        return _rms(x[..., :error_size])
    n, q = error_size
    cols = x[..., n:n + n * q].reshape(x.shape[:-1] + (n, q))
    worst = jnp.max(jnp.sqrt(jnp.mean(cols * cols, axis=-2)), axis=-1, keepdims=True)
    return jnp.maximum(_rms(x[..., :n]), worst)


def _initial_step(f, t0, y0, k0, rtol, atol, order, span, error_size=None):
    """Hairer, Norsett & Wanner's starting step (as diffrax's and scipy's), on packed
    (..., N) states, measured on their first `error_size` components (for `(n, q)`, the
    first n): shape (..., 1), one per member of a batch."""
    E = error_size[0] if isinstance(error_size, tuple) else error_size
    scale = atol + rtol * jnp.abs(y0[..., :E])
    d0, d1 = _rms(y0[..., :E] / scale), _rms(k0[..., :E] / scale)
    h0 = jnp.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / d1)
    h0 = jnp.minimum(h0, span)
    k1 = f(t0 + h0, y0 + h0 * k0)
    d2 = _rms((k1 - k0)[..., :E] / scale) / h0
    h1 = jnp.where(jnp.maximum(d1, d2) <= 1e-15, jnp.maximum(1e-6, h0 * 1e-3),
                   (0.01 / jnp.maximum(d1, d2)) ** (1.0 / order))
    return jnp.minimum(jnp.minimum(100 * h0, h1), span)


class _Step(NamedTuple):
    """The step loop's state. Batched, every field but `y` and `k` has shape (B, 1): each
    member of a lockstep batch has its own time, step size and step count.

    - `t`: the time reached (s); `y`, `k`: the packed state there and `f(t, y)` (first
      same as last);
    - `h`: the controller's next step size (s);
    - `steps`: step attempts so far, accepted and rejected (stops at the budget);
    - `rejected`: whether the last attempt was rejected (no growth right after one)."""

    t: jax.Array
    y: jax.Array
    k: jax.Array
    h: jax.Array
    steps: jax.Array
    rejected: jax.Array
    # The step attempts that `record` (a [`Recorder`][]) has pending; None without it.
    log: object = None
    # The step-size controller's state (`PIDController.init`; None for an integral one).
    control: object = None


class Recorder(NamedTuple):
    """What `solve_adaptive`'s `record` does with the step attempts (the discrete
    adjoint's log, steplog.py), in two parts: the step loop writes each attempt to a small
    `pending` buffer, and the loop around it (once per chunk of save times) moves what is
    pending to the full `log`. Why two parts: under XLA's defaults the runtime runs a loop
    body's kernels one after the other in the calling thread only while every buffer they
    touch is <= 512 bytes; a step loop that carried the full log slowed the forward pass
    (docs/benchmarks/design-figures.md).

    - `log0`, `pending0`: the log at the start, and an empty pending buffer;
    - `write(pending, rec) -> pending`: log one step attempt `rec` (an `_Attempt`);
    - `room(pending, k) -> bool`: whether `k` more attempts fit in the buffer (the step
      loop stops, and the outer loop moves the buffer to the log, when they do not);
    - `flush(log, pending) -> (log, pending)`: the log with the pending attempts moved to
      it, and an empty buffer."""

    log0: object
    pending0: object
    write: object
    room: object
    flush: object


class _Attempt(NamedTuple):
    """One step attempt, for the dense output: accepted (`ok`), from `t` to `t1` with step
    `h`, starting at `y`; `ks` the stages, the last `f(t1, y1)`."""

    ok: jax.Array
    t: jax.Array
    t1: jax.Array
    h: jax.Array
    y: jax.Array
    ks: list


class AdaptiveERK(eqx.Module):
    """An adaptive explicit Runge-Kutta solver's step, in diffrax's shape: [`init`][] makes
    the step loop's state at the start and [`step`][] one step attempt from a state;
    [`solve_adaptive`][]'s loop drives them (one loop for every such solver, a lockstep
    batch and the discrete adjoint's logged solve included). `AdaptiveDopri8` is one.

    **Fields:** `erk`, the method, a [`FusedERK`][] (default Dopri8, `dopri8()`; its last
    stage must be `f(t1, y1)`, first same as last); `controller`, the step-size law, a
    [`PIDController`][] (default: an integral controller, as diffrax's default)."""

    erk: FusedERK = eqx.field(default_factory=dopri8)
    controller: PIDController = eqx.field(default_factory=PIDController)

    def init(self, f, ts, y0p, rtol, atol, error_size=None, log=None) -> _Step:
        """The `_Step` at the first save time: the packed state `y0p` (..., N) there,
        `f(t0, y0p)`, Hairer's starting step (within the span of the save times `ts`,
        (n,), or a batch's own, (n, B, 1)), no step taken; times and step sizes with
        shape (..., 1), one per member; `log`, the recorder's empty pending buffer (or
        None)."""
        sg = jax.lax.stop_gradient
        lead = y0p.shape[:-1] + (1,)
        t0 = jnp.broadcast_to(sg(ts[0]), lead)
        k0 = f(t0, y0p)
        h0 = _initial_step(f, t0, sg(y0p), sg(k0), sg(rtol), sg(atol), self.erk.order,
                           sg(ts[-1]) - sg(ts[0]), error_size)
        return _Step(t0, y0p, k0, h0, jnp.zeros(lead, int), jnp.zeros(lead, bool), log,
                     self.controller.init(lead, y0p.dtype))

    def step(self, f, c: _Step, t_lim, rtol, atol, max_steps: int, error_size=None,
             record=None) -> tuple[_Step, _Attempt]:
        """One step attempt of `erk` on the packed field `f(t, y)` per member, from `c`,
        shortened to end at `t_lim`, with diffrax's error norm and the step size from
        `controller`: `(state, attempt)` (a `_Step` and an `_Attempt`; with a
        [`Recorder`][] `record`, the attempt is written to the state's log). A member is
        inactive (takes no step, its state frozen) once `t >= t_lim` or its budget
        `max_steps` is spent."""
        sg = jax.lax.stop_gradient
        erk, n_st = self.erk, self.erk.num_stages
        t, y, k, h, steps, rejected = c[:6]
        # The steps are chosen on values: t and h carry no derivative.
        active = (t < t_lim) & (steps < max_steps)
        h_try = sg(jnp.where(active, jnp.minimum(h, t_lim - t), 1.0))
        ks = erk.stages(lambda tt, yy, _: f(tt, yy), t, y, None, h_try, k0=k)[:n_st]
        y1 = erk.solution(y, h_try, ks)
        E = None if isinstance(error_size, tuple) else error_size
        scale = atol + rtol * jnp.maximum(jnp.abs(sg(y[..., :E])), jnp.abs(sg(y1[..., :E])))
        err = _error_norm(sg(erk.error(h_try, [k[..., :E] for k in ks])) / scale,
                          error_size)
        # A non-finite estimate (a step too long for stability) is a rejection.
        ok = active & (err <= 1.0)
        t1 = jnp.where(h_try == t_lim - t, t_lim, t + h_try)
        k1 = f(t1, y1)
        fac, control = self.controller.factor(sg(err), ok, rejected, erk.order, c.control)
        # A step shortened to end at the window (or the end) and accepted leaves the
        # controller's proposal `h` valid: the next step may take it again.
        h_next = jnp.where(ok & (h_try < h), jnp.maximum(h_try * fac, h), h_try * fac)
        rec = _Attempt(ok, t, t1, h_try, y, ks + [k1])
        new = _Step(jnp.where(ok, t1, t), jnp.where(ok, y1, y), jnp.where(ok, k1, k),
                    jnp.where(active, sg(h_next), h), steps + active,
                    jnp.where(active, ~ok, rejected),
                    c.log if record is None else record.write(c.log, rec), control)
        return new, rec


def solve_adaptive(field, y0, ts, rtol, atol, args=None, *, max_steps: int,
                   solver: AdaptiveERK | None = None, unroll: int = UNROLL,
                   window: int = WINDOW, chunk: int = CHUNK, batched: bool = False,
                   error_size: int | None = None, record=None):
    """Integrate `dy/dt = field(t, y, args)` with adaptive steps of `solver`, saving at
    `ts` through Dopri8's dense output: the loop that drives the solver's `init` and
    `step`.

    **Arguments:**

    - `field`: the vector field `field(t, y, args) -> dy/dt`, a callable pytree; its
      inexact-array leaves are differentiable parameters. Batched, `t` has shape (B,).
    - `y0`: the state at `ts[0]`, a pytree of arrays (small: the stages are unrolled).
    - `ts` (n,): increasing save times, any spacing, whose last may repeat (the loop
      stops at the first and writes no repeat: [`adaptive_solve`][] gives them its
      value); batched, also (B, n), each member's own (its i-th sample at its own i-th
      time).
    - `rtol`, `atol`: tolerances of the local error per step as diffrax's `PIDController`
      scales them (RMS over the state of `err / (atol + rtol max(|y0|, |y1|))`; a step is
      accepted when it is <= 1).
    - `args`: passed to `field`; its inexact-array leaves are differentiable too.
    - `max_steps`: the budget of step attempts (accepted and rejected), static. The loop
      is a plain `lax` loop: forward mode goes through it; reverse mode does not (see
      `lockstep.py`, whose backward pass is the discrete adjoint of adjoint.py).
    - `solver`: an [`AdaptiveERK`][] (its method and step-size controller), default
      `AdaptiveERK()`: Dopri8, whose dense output (`dopri8_dense()`) this loop writes.
    - `unroll`, `window`: step attempts per loop iteration; save times one iteration may
      write (a step is shortened so that the iteration writes no more).
    - `chunk`: save times the step loop records before the outer loop copies them out.
    - `error_size`: the step control sees the first `error_size` components of the packed
      state only (default all); or `(n, q)`: the state's n components are followed by
      their (n, q) sensitivities, and a step must meet the tolerance on the state and on
      each sensitivity column (`_error_norm`; `variational.py`).
    - `batched`: the leaves of `y0` (and of `field`, `args` where they vary) carry a
      leading batch axis (B,): the batch runs in one loop (lockstep), but each member has
      its own time, step size, accept/reject decisions, step budget and outcome, as if
      solved alone; a member that is done, or out of budget, is frozen while the others
      go on (see `lockstep.py`).
    - `record`: a [`Recorder`][]: the solve logs each step attempt `rec` (its `ok`, `t`,
      `t1`, `h`, `y` on the packed state) with it (the discrete adjoint's record of the
      steps, adjoint.py).

    **Returns:** `(ys, result, num_steps)`: `ys` a pytree like `y0` with a leading axis n
    (batched: leaves (n, B)); `result` a `diffrax.RESULTS` (`max_steps_reached` if the
    budget ran out before `ts[-1]`; batched: shape (B,)); `num_steps`, the step attempts,
    accepted and rejected (batched: (B,)). With `record`, the final log comes fourth.
    """
    solver = AdaptiveERK() if solver is None else solver
    n = ts.shape[-1]
    dtype = ts.dtype
    pack, unpack = packer(y0, 1 if batched else 0)
    sg = jax.lax.stop_gradient
    rtol, atol = jnp.asarray(rtol, dtype), jnp.asarray(atol, dtype)

    def f(t, yp):
        # One packed (N,) array: fewer, larger fusions than the state's leaves. `t` is
        # (..., 1), one time per member of a batch.
        return pack(field(t[..., 0], unpack(yp), args)).astype(dtype)

    y0p = pack(y0).astype(dtype)
    if ts.ndim > 1:  # each member's own save times, (B, n): as rows (n, B, 1)
        ts = jnp.moveaxis(ts, -1, 0)[..., None]
    state0 = solver.init(f, ts, y0p, rtol, atol, error_size,
                         None if record is None else record.pending0)

    def attempt(state, t_lim):
        return solver.step(f, state, t_lim, rtol, atol, max_steps, error_size, record)

    state, out, log = _step_loop(attempt, state0, y0p, ts, window, unroll, chunk, max_steps,
                                 record)
    t_end = sg(ts[-1])
    done = state.t >= t_end
    import diffrax

    outcome_of = lambda d: diffrax.RESULTS.where(  # noqa: E731
        d, diffrax.RESULTS.successful, diffrax.RESULTS.max_steps_reached)
    # One outcome per member (`RESULTS.where` takes a scalar predicate).
    for _ in range(done.ndim - 1):
        outcome_of = jax.vmap(outcome_of)
    result = outcome_of(done[..., 0])
    # Save times a member never reached (a failed solve) hold inf, as diffrax leaves them.
    reached = _rows(ts, y0p.ndim) <= state.t[None]
    ys = jnp.where(reached, out[:n], jnp.inf)
    if record is not None:
        return unpack(ys), result, state.steps[..., 0], log
    return unpack(ys), result, state.steps[..., 0]


class _Chunk(NamedTuple):
    """The step loop's state within one chunk of save times (see [`_step_loop`][]): `j`,
    the save times of the chunk written so far; `i0`, the chunk's first save index; the
    [`_Step`][] `state`; `buf`, the chunk's outputs ((chunk + window,) + the packed
    state's shape); `tc`, its save times."""

    j: jax.Array
    i0: jax.Array
    state: _Step
    buf: jax.Array
    tc: jax.Array


def _step_loop(attempt, state0: _Step, y0p, ts, window, unroll, chunk, max_steps,
               record=None):
    """The step attempts from `state0` to `ts[-1]`, recording the dense output at `ts`
    (and, with a [`Recorder`][] `record`, logging the attempts).

    **Returns:** `(state, out, log)`: the last [`_Step`][], the outputs, (n + chunk +
    window,) + the packed state's shape (rows past a member's last time are not valid),
    and the log (None without `record`)."""
    dense = dopri8_dense()
    n, dtype = ts.shape[0], ts.dtype  # ts: (n,), or each member's own, (n, B, 1)
    W, K, CH = int(window), int(unroll), int(chunk)
    t_end = jax.lax.stop_gradient(ts[-1])
    # Pending save times padded with +inf and outputs with CH + W rows, so that a chunk at
    # any pending index stays in range.
    ts_pad = jnp.concatenate([ts, jnp.full((CH + W,) + ts.shape[1:], jnp.inf, dtype)])
    out0 = jnp.zeros((n + CH + W,) + y0p.shape, dtype).at[0].set(y0p)

    def waiting(state):
        # Members still to step: neither at the end nor out of budget.
        return (state.t < t_end) & (state.steps < max_steps)

    def chunk_cond(c: _Chunk):
        go = (c.j < CH) & (c.i0 + c.j < n) & jnp.any(waiting(c.state))
        return go if record is None else go & record.room(c.state.log, K)

    def chunk_body(c: _Chunk):
        j, i0, state, buf, tc = c
        tw = jax.lax.dynamic_slice_in_dim(tc, j, W)
        # The block may not step past its window's last save time (nor the end).
        t_lim = jnp.minimum(tw[-1], t_end)
        taken = []
        for _ in range(K):
            state, rec = attempt(state, t_lim)
            taken.append(rec)
        twr = _rows(tw, y0p.ndim)  # against the members' times
        values, covered = window_values(dense, taken, twr)
        # Rows from j on are pending: each member's covered rows are written, the others
        # keep what an earlier block wrote (members step on their own).
        old = jax.lax.dynamic_slice_in_dim(buf, j, W)
        buf = jax.lax.dynamic_update_slice_in_dim(buf, jnp.where(covered, values, old), j, 0)
        # The window moves on past the save times every member still stepping has reached.
        past = (twr <= state.t[None]) | ~waiting(state)[None]
        past = jnp.all(past.reshape(W, -1), axis=1)
        reached = jnp.sum(past & (i0 + j + jnp.arange(W) < n))
        return _Chunk(j + reached, i0, state, buf, tc)

    def cond(c):
        return (c[0] < n) & jnp.any(waiting(c[1]))

    def body(c):
        # One chunk: the step attempts that reach the next CH save times (or the end, or
        # the budget), written to a small buffer, then to the output; why two loops: see
        # the module docstring (the step loop must not carry the n outputs).
        i0, state, out, log = c
        tc = jax.lax.dynamic_slice_in_dim(ts_pad, i0, CH + W)
        buf = jax.lax.dynamic_slice_in_dim(out, i0, CH + W)
        j, _, state, buf, _ = jax.lax.while_loop(
            chunk_cond, chunk_body, _Chunk(jnp.array(0), i0, state, buf, tc))
        out = jax.lax.dynamic_update_slice_in_dim(out, buf, i0, 0)
        if record is not None:  # the step loop's pending attempts, to the log
            log, pending = record.flush(log, state.log)
            state = state._replace(log=pending)
        return i0 + j, state, out, log

    log0 = None if record is None else record.log0
    _, state, out, log = jax.lax.while_loop(cond, body, (jnp.array(1), state0, out0, log0))
    return state, out, log


def _rows(ts, ndim):
    """Save times (n,) as rows against the state's times, (n, 1, ..., 1) (`ndim` ones);
    a batch's own save times, (n, B, 1), as they are."""
    return ts.reshape(ts.shape + (1,) * ndim) if ts.ndim == 1 else ts


def outcome(code: jax.Array, steps: jax.Array) -> tuple:
    """`(result, steps)` from the arrays a `custom_jvp`, `custom_vjp` or `custom_vmap` solve
    returns (such a rule returns arrays, so the `diffrax.RESULTS` travels as its code):
    the code as a `diffrax.RESULTS` again, both with no derivative (equinox's checks on
    the result cannot take one through it)."""
    code, steps = jax.lax.stop_gradient(code), jax.lax.stop_gradient(steps)
    return compat.result_from_code(code), steps
