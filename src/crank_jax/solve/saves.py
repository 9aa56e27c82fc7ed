"""Save times for diffrax's explicit solvers without `SaveAt(ts=...)`'s runtime check.

`diffeqsolve(..., saveat=SaveAt(ts=ts))` checks its save times with two `eqx.error_if`s
(increasing; within `[t0, t1]`), which become host callbacks once the times are traced, as
the fit's data are (diffrax 0.7.2, `_check_subsaveat_ts` in `_integrate.py`). JAX's
persistent cache and the program store (`persistent.py`) refuse a program holding one, so
a fit on diffrax's solvers compiled its programs in every process.

[`saving`][] wraps a diffrax solver (diffrax's public `AbstractWrappedSolver`) so that
each step also evaluates its dense output at the save times the step reaches, into a
buffer in the solver's state: the arithmetic diffrax's `SaveAt(ts)` does inside its step
loop (the solver's `interpolation_cls` over the step `[t0, t1]`, the times `<= t1` not
yet saved, in order). diffrax keeps a step's solver state only if the step is accepted,
and the solve saves that state at its end (`SaveAt(t1=True, solver_state=True)`), so the
buffer holds what `SaveAt(ts)` would (inf where a failed solve never reached: diffrax's
fill too); the same numbers, bitwise on the fit's programs (tests/test_diffrax_saves.py).
The other public form, dense output (`SaveAt(dense=True)`), holds buffers of `max_steps`
steps: a multiple-shooting fit's programs ran many times slower
(experiments/diffrax_callbacks.py; its figures on docs/benchmarks/design-figures.md).

Limits, where `Diffrax.run` keeps `SaveAt(ts)`:

- the caller must have checked the save times (strictly increasing): nothing in the
  program does (`solve(checks=False)`, which the fit's solves and `simulate`'s host mode
  use, their times checked on the host);
- forward mode or none (`adjoint="forward"`): the save loop is a `lax.while_loop`, which
  has no reverse mode;
- explicit solvers: diffrax sets an implicit solver's root-finder tolerances through its
  fields, and an implicit solver's forward mode holds another host callback, lineax's
  check in optimistix's implicit JVP, that no public argument removes.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

__all__ = ["saving", "saved"]


class _Saving(diffrax.AbstractWrappedSolver):
    """`solver`, with the state at the save times `ts` (n,) kept in its solver state:
    `(inner state, ys (n, N) (inf until saved), the next save time's index)`."""

    solver: diffrax.AbstractSolver
    ts: jax.Array

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def interpolation_cls(self):  # pyright: ignore
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    @property
    def scan_kind(self):
        # diffrax's `ForwardMode` sets a Runge-Kutta solver's `scan_kind` to "lax" when it
        # is None; `saving` has done that to the wrapped solver already.
        return self.solver.scan_kind

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)

    def init(self, terms, t0, t1, y0, args):
        ys = jnp.full((self.ts.shape[0],) + jnp.shape(y0), jnp.inf, jnp.result_type(y0))
        return self.solver.init(terms, t0, t1, y0, args), ys, jnp.zeros((), jnp.int32)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        inner, ys, i = solver_state
        y1, y_error, dense_info, inner, result = self.solver.step(
            terms, t0, t1, y0, args, inner, made_jump)
        interpolation = self.solver.interpolation_cls(t0=t0, t1=t1, **dense_info)
        ts, n = self.ts, self.ts.shape[0]

        def more(c):  # as diffrax's save loop: the next save time, if the step reaches it
            return (c[0] < n) & (ts[jnp.minimum(c[0], n - 1)] <= t1)

        def save(c):
            j, out = c
            return j + 1, out.at[j].set(interpolation.evaluate(ts[j]))

        i, ys = jax.lax.while_loop(more, save, (i, ys))
        return y1, y_error, dense_info, (inner, ys, i), result


def saving(solver, ts):
    """The diffrax solver `solver` (explicit) saving the solution at `ts` (n,) in its
    solver state, for `diffeqsolve(..., saveat=SaveAt(t1=True, solver_state=True))` in
    forward mode (`diffrax.ForwardMode`); [`saved`][] reads the result."""
    if isinstance(solver, diffrax.AbstractRungeKutta) and solver.scan_kind is None:
        # What `ForwardMode` does to a Runge-Kutta solver (it cannot see through the
        # wrapper to do it): its stages in a plain `lax` loop, which forward mode takes.
        solver = eqx.tree_at(lambda s: s.scan_kind, solver, "lax",
                             is_leaf=lambda x: x is None)
    return _Saving(solver, ts)


def saved(sol):
    """The states at the save times (n, N) of a solve with a [`saving`][] solver."""
    return sol.solver_state[1]
