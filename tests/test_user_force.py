"""A generalised force of the user's own (`simulate(..., force=...)`, `CrankField.force`):
it enters q exactly, works with every solver, and its parameters train through the solve
without recompiling."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj


class Damper(eqx.Module):
    """A viscous torque `-c phi'` written as a user term (its `c` is a pytree leaf)."""

    c: jax.Array

    def __call__(self, t, phi, dphi):
        return -self.c * dphi


@pytest.mark.parametrize("solver", ["dopri8-uniform", "tsit5"])
def test_user_term_equals_the_built_in_term(solver):
    # The user's viscous torque must give exactly the motion of the model's own c.
    mech = cj.load_scene("lab-rig").mech
    ts = jnp.linspace(0.0, 2.0, 101)
    built_in = cj.simulate(mech.replace(c=0.01), 1.0, 0.0, ts, solver=solver, rtol=1e-10)
    user = cj.simulate(mech.replace(c=0.0), 1.0, 0.0, ts, solver=solver, rtol=1e-10,
                       force=Damper(jnp.asarray(0.01)))
    np.testing.assert_allclose(user.phi, built_in.phi, atol=1e-9)
    np.testing.assert_allclose(user.dphi, built_in.dphi, atol=1e-8)


def test_user_term_enters_the_acceleration_and_the_derived_outputs():
    mech = cj.load_scene("lab-rig").mech
    torque = lambda t, phi, dphi: 0.3 + 0.0 * phi  # noqa: E731
    a0 = cj.model.acceleration(mech, 0.4, 0.2)
    a1 = cj.model.acceleration(mech, 0.4, 0.2, force=torque)
    np.testing.assert_allclose(a1 - a0, 0.3 / cj.model.mass(mech, 0.4), rtol=1e-12)
    field = cj.model.CrankField(mech, cj.NoLoad(), cj.NoLoad(), force=torque)
    np.testing.assert_allclose(field(0.0, (0.4, 0.2))[1], a1, rtol=1e-14)
    tr = cj.simulate(mech, 0.4, 0.2, jnp.linspace(0, 0.1, 3), force=torque,
                     outputs=("ddphi",))
    np.testing.assert_allclose(tr.extras["ddphi"][0], a1, rtol=1e-10)


class MLPTorque(eqx.Module):
    """A small network torque `f(phi') -> N*m`: its weights are leaves of the field."""

    mlp: eqx.nn.MLP

    def __call__(self, t, phi, dphi):
        return 0.01 * self.mlp(jnp.atleast_1d(dphi))[0]


def test_gradient_through_an_mlp_term_matches_finite_differences_without_retracing():
    mech = cj.load_scene("lab-rig").mech
    ts = jnp.linspace(0.0, 1.0, 51)
    model = MLPTorque(eqx.nn.MLP(1, 1, 4, 1, activation=jnp.tanh, key=jax.random.PRNGKey(0)))
    params, static = eqx.partition(model, eqx.is_inexact_array)

    def loss(p):
        return jnp.sum(cj.simulate(mech, 0.8, 0.0, ts, force=eqx.combine(p, static)).phi ** 2)

    g = jax.grad(loss)(params)
    h = 1e-5
    bias = params.mlp.layers[-1].bias

    def bump(d):
        return eqx.tree_at(lambda m: m.mlp.layers[-1].bias, params, bias + d)

    fd = (loss(bump(h)) - loss(bump(-h))) / (2 * h)
    np.testing.assert_allclose(g.mlp.layers[-1].bias[0], fd, rtol=1e-5)

    # New weights are new values, not a new program.
    counted = eqx.filter_jit(eqx.debug.assert_max_traces(loss, max_traces=1))
    counted(params)
    counted(bump(0.1))
