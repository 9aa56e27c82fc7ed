"""Solvers as objects and `solve`, the one entry point (solve/solvers.py, solve/names.py):
a user's own vector field against the analytic solution and diffrax, `simulate` through
the entry, and the policy returning the table's objects."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.model.dynamics import CrankField
from crank_jax.solve.names import TABLE, name_of

TS = jnp.linspace(0.0, 3.0, 61)  # uniform, for "dopri8-uniform" too


def oscillator(t, y, w):
    """x'' = -w^2 x as (x, v): x = cos(w t) from (1, 0)."""
    x, v = y
    return v, -(w**2) * x


@pytest.mark.parametrize("name", ["dopri8-adaptive", "dopri8-uniform", "dopri8", "tsit5"])
def test_a_users_field_matches_the_analytic_solution_and_diffrax(name):
    w = jnp.asarray(2.0)
    sol = jax.jit(lambda w: cj.solve.solve(oscillator, cj.solve.solver_named(name), TS,
                                     (jnp.asarray(1.0), jnp.asarray(0.0)), w,
                                     rtol=1e-10, atol=1e-12))(w)
    assert bool(sol.result == diffrax.RESULTS.successful) and int(sol.num_steps) > 0
    x, v = sol.ys
    assert x.shape == v.shape == TS.shape
    np.testing.assert_allclose(x, np.cos(2.0 * TS), atol=1e-8)
    np.testing.assert_allclose(v, -2.0 * np.sin(2.0 * TS), atol=2e-8)
    # diffrax as a user would write it, on a (2,) state.
    ref = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, y, w: jnp.stack(oscillator(t, (y[0], y[1]), w))),
        diffrax.Dopri8(), TS[0], TS[-1], None, jnp.array([1.0, 0.0]), w,
        saveat=diffrax.SaveAt(ts=TS),
        stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-14), max_steps=10**5)
    np.testing.assert_allclose(x, ref.ys[:, 0], atol=1e-8)


def test_the_diffrax_wrapper_is_diffrax_itself():
    # Same solver, controller and save times: the same numbers as diffeqsolve on a (2,)
    # state (the wrapper stacks a state of scalars into one array).
    w = jnp.asarray(2.0)
    sol = cj.solve.solve(oscillator, cj.Diffrax(diffrax.Tsit5()), TS,
                   (jnp.asarray(1.0), jnp.asarray(0.0)), w, rtol=1e-8, atol=1e-10)
    ref = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, y, w: jnp.stack(oscillator(t, (y[0], y[1]), w))),
        diffrax.Tsit5(), TS[0], TS[-1], None, jnp.array([1.0, 0.0]), w,
        saveat=diffrax.SaveAt(ts=TS),
        stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-10))
    np.testing.assert_array_equal(jnp.stack(sol.ys, axis=1), ref.ys)
    assert int(sol.num_steps) == int(ref.stats["num_steps"] + ref.stats["num_rejected_steps"])


def test_derivatives_through_args_in_both_modes():
    # dx/dw = -t sin(w t): forward mode (the variational equation, with `args` bound into
    # the field) and reverse mode (the discrete adjoint).
    solver = cj.solve.solver_named("dopri8-adaptive")
    y0 = (jnp.asarray(1.0), jnp.asarray(0.0))

    def x(w, adjoint):
        return cj.solve.solve(oscillator, solver, TS, y0, w, rtol=1e-11, atol=1e-13,
                        adjoint=adjoint).ys[0]

    w = jnp.asarray(2.0)
    exact = -TS * jnp.sin(2.0 * TS)
    np.testing.assert_allclose(jax.jacfwd(lambda w: x(w, "forward"))(w), exact, atol=1e-7)
    g = jax.grad(lambda w: jnp.sum(x(w, "reverse")))(w)
    np.testing.assert_allclose(g, jnp.sum(exact), rtol=1e-7)


def test_a_pytree_state_through_diffrax_and_the_fused_solver():
    # A state that is not a tuple of scalars: diffrax steps it ravelled.
    def field(t, y, args):
        return {"x": y["v"], "v": -y["x"]}

    y0 = {"x": jnp.array([1.0, 2.0]), "v": jnp.zeros(2)}
    for name in ("dopri8", "dopri8-adaptive"):
        sol = cj.solve.solve(field, cj.solve.solver_named(name), TS, y0, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(sol.ys["x"], np.cos(TS)[:, None] * np.array([1.0, 2.0]),
                                   atol=1e-8)


@pytest.mark.parametrize("name", sorted(TABLE))
def test_simulate_is_the_entry_on_the_crank_field(name, lab_rig):
    # `simulate` runs `solve` on the crank's field: the same numbers, bit for bit.
    m, ts = lab_rig.mech, jnp.linspace(0.0, 1.0, 101)
    tr = cj.simulate(m, 1.0, 0.0, ts, solver=name)
    crank = CrankField(m, cj.NoLoad(), cj.NoLoad(), cj.model.ModelTerms.of(m))
    sol = eqx.filter_jit(lambda c: cj.solve.solve(
        c, cj.solve.solver_named(name), ts, (jnp.asarray(1.0), jnp.asarray(0.0)),
        rtol=jnp.asarray(1e-8), atol=jnp.asarray(1e-10), max_steps=200_000,
        prepare=CrankField.packed, rate=_rate(c), throw=False))(crank)
    np.testing.assert_array_equal(tr.phi, sol.ys[0])
    np.testing.assert_array_equal(tr.dphi, sol.ys[1])
    assert int(tr.num_steps) == int(sol.num_steps)


def _rate(crank):
    from crank_jax.solve.trajectory import _rate

    return jax.lax.stop_gradient(_rate(crank))


def test_the_policy_returns_the_tables_objects(lab_rig):
    m = lab_rig.mech
    assert set(cj.solve.SOLVERS) == {"auto", *TABLE}
    for name in TABLE:
        obj = cj.solve.resolve_solver(name, m, 1e-8)
        assert obj is cj.solve.solver_named(name) and name_of(obj) == name
    assert isinstance(cj.solve.resolve_solver("auto", m, 1e-8), cj.AdaptiveDopri8)
    own = cj.Diffrax(diffrax.Bosh3())
    assert cj.solve.resolve_solver(own, m, 1e-8) is own  # an object is taken as given
    assert cj.solve.solver_named("kvaerno5").implicit
    assert not cj.solve.solver_named("dopri8").implicit
    tr = cj.simulate(m, 1.0, 0.0, jnp.linspace(0.0, 1.0, 11), solver=own)
    assert bool(tr.ok)


def test_bad_solver_and_adjoint_are_one_line_errors():
    y0 = (jnp.asarray(1.0), jnp.asarray(0.0))
    with pytest.raises(TypeError, match="solver must be a crank_jax solver object"):
        cj.solve.solve(oscillator, "dopri8", TS, y0, 2.0)
    with pytest.raises(ValueError, match=r"adjoint must be an adjoint object \(Discrete"):
        cj.solve.solve(oscillator, cj.solve.solver_named("dopri8"), TS, y0, 2.0,
                       adjoint="backward")
    with pytest.raises(ValueError, match="unknown solver 'rk4'"):
        cj.solve.solver_named("rk4")


def test_the_dopri8_tableau_is_diffraxs():
    # The default solver's tableau is a copy of diffrax's numbers (importing diffrax to
    # read them cost 0.6-1.0 s of every warm process): bit for bit the same, every run.
    from crank_jax.solve.erk import as_tableau, dopri8

    assert dopri8().tableau == as_tableau(diffrax.Dopri8.tableau)
    assert dopri8(True).tableau == as_tableau(diffrax.Dopri8.tableau)


def test_the_default_solver_is_made_without_importing_diffrax():
    # A warm `crank-jax fit` (its programs from the store) runs nothing of diffrax; it
    # imported diffrax, lineax and optimistix (0.6-1.0 s) only to read the Dopri8 tableau
    # when the policy made the default solver.
    from conftest import loaded_after

    made = ("from crank_jax.solve.names import solver_named; "
            "solver_named('dopri8-adaptive').with_loop_stages()")
    assert loaded_after(made, ("diffrax", "lineax", "optimistix")) == []
