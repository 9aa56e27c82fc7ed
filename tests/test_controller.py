"""The fused adaptive solver states its numerics (solve/controller.py, solve/solvers.py):
its tableau and its step-size controller are fields of `AdaptiveDopri8`, the defaults
take the steps they always took, and another controller takes other steps, meets the
tolerance and is differentiated through its own steps."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from crank_jax.solve import adjoint
from crank_jax.solve.controller import PIDController
from crank_jax.solve.erk import FusedERK, dopri8
from crank_jax.solve.names import name_of, solver_named
from crank_jax.solve.solvers import AdaptiveDopri8, solve

TS = jnp.linspace(0.0, 3.0, 31)
Y0 = (jnp.asarray(1.0), jnp.asarray(0.0))


def oscillator(t, y, w):
    """x'' = -w^2 x as (x, v): x = cos(w t) from (1, 0)."""
    x, v = y
    return v, -(w**2) * x


def _solve(controller, w=2.0, adjoint="reverse", ts=TS):
    return solve(oscillator, AdaptiveDopri8(controller=controller), ts, Y0, jnp.asarray(w),
                 rtol=1e-10, atol=1e-12, adjoint=adjoint)


def test_the_solver_holds_its_tableau_and_controller_by_default():
    s = AdaptiveDopri8()
    assert s.erk == dopri8() and s.controller == PIDController()
    assert s == solver_named("dopri8-adaptive") and name_of(s) == "dopri8-adaptive"
    assert hash(s) == hash(AdaptiveDopri8())  # a key of compiled programs
    assert s.with_loop_stages().controller == s.controller
    assert name_of(AdaptiveDopri8(controller=PIDController(safety=0.8))) is None


def test_another_controller_takes_other_steps_and_meets_the_tolerance():
    exact = np.cos(2.0 * TS)
    steps = {}
    for name, c in [("default", PIDController()), ("cautious", PIDController(safety=0.5)),
                    ("PID", PIDController(pcoeff=0.3, icoeff=0.4, dcoeff=0.1))]:
        sol = jax.jit(_solve)(c)
        assert bool(sol.result == diffrax.RESULTS.successful), name
        np.testing.assert_allclose(sol.ys[0], exact, atol=1e-8, err_msg=name)
        steps[name] = int(sol.num_steps)
    assert steps["cautious"] > 1.3 * steps["default"], steps
    assert len(set(steps.values())) == 3, steps


def test_controller_values_as_arrays_are_the_same_numbers_without_recompiling():
    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(c):
        return _solve(c).ys[0]

    as_float = jax.jit(_solve)(PIDController(safety=0.8)).ys[0]
    np.testing.assert_array_equal(run(PIDController(safety=jnp.asarray(0.8))), as_float)
    run(PIDController(safety=jnp.asarray(0.9)))  # a new value, the same program


@pytest.mark.slow  # ~60 s on 2 loaded cores: a backward pass's compilation
def test_reverse_mode_follows_the_controllers_steps(monkeypatch):
    # The discrete adjoint's forward pass and its reruns (a log shorter than the solve)
    # must take the controller's steps: a rerun that does not fails loudly, and a
    # forward pass with other steps gives another gradient than JAX's tangents through
    # the same solve (`adjoint="direct"`).
    monkeypatch.setattr(adjoint, "LOG_ROWS", 50)
    c = PIDController(pcoeff=0.4, icoeff=0.3)

    ts = jnp.linspace(0.0, 20.0, 41)

    def loss(w, mode):
        sol = _solve(c, w, mode, ts)
        return jnp.sum(sol.ys[0] * jnp.sin(ts)), sol.num_steps

    w = jnp.asarray(2.0)
    g, steps = jax.grad(loss, has_aux=True)(w, "reverse")
    assert steps > 2 * 50  # two segments rerun
    want = jax.jacfwd(loss, has_aux=True)(w, "direct")[0]
    np.testing.assert_allclose(g, want, rtol=1e-12)


@pytest.mark.parametrize("make, match", [
    (lambda: PIDController(factormin=0.0), "factormin"),
    (lambda: PIDController(factormax=0.5), "factormax"),
    (lambda: PIDController(safety=1.5), "safety"),
    (lambda: PIDController(icoeff=-1.0), "icoeff"),
    (lambda: AdaptiveDopri8(erk=FusedERK(diffrax.Tsit5.tableau, 5)), "erk"),
    (lambda: AdaptiveDopri8(controller=diffrax.PIDController(rtol=1e-8, atol=1e-8)),
     "controller"),
])
def test_bad_numerics_are_refused_by_name(make, match):
    with pytest.raises((ValueError, TypeError), match=match):
        make()


def test_a_traced_proportional_coefficient_is_refused():
    # pcoeff and dcoeff decide the program (whether earlier errors are carried): static.
    with pytest.warns(UserWarning, match="static"), pytest.raises(TypeError, match="pcoeff"):
        PIDController(pcoeff=jnp.asarray(0.1))
