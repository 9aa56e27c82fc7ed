"""Training a term of your own through the solver: the rig's bearing friction is unknown,
so a small neural network f(phi') (N*m, added to the generalised force) is trained on a
record with optax, by reverse-mode gradients through the ODE solve. A short run: see
experiments/ude_friction.py for the full one and its figure."""

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

import crank_jax as cj  # noqa: E402


def true_friction(t, phi, dphi):  # Coulomb + viscous, unknown to the model
    return -0.004 * jnp.tanh(dphi / 0.2) - 0.001 * dphi


class Friction(eqx.Module):
    mlp: eqx.nn.MLP

    def __call__(self, t, phi, dphi):  # odd in phi': friction opposes motion
        x = jnp.atleast_1d(dphi)
        return 0.01 * (self.mlp(x)[0] - self.mlp(-x)[0])


mech = cj.load_scene("lab-rig").mech.replace(c=0.0)  # all damping is in the unknown law
ts = jnp.linspace(0.0, 2.0, 201)
record = cj.simulate(mech, 0.8, 0.0, ts, force=true_friction).phi
record = record + 5e-4 * np.random.default_rng(0).standard_normal(ts.shape)

model = Friction(eqx.nn.MLP(1, 1, 8, 2, activation=jnp.tanh, key=jax.random.PRNGKey(0)))
params, static = eqx.partition(model, eqx.is_inexact_array)
opt = optax.adam(1e-2)
state = opt.init(params)


@eqx.filter_jit
def step(params, state):
    def loss(p):
        phi = cj.simulate(mech, 0.8, 0.0, ts, force=eqx.combine(p, static), rtol=1e-7,
                          atol=1e-9).phi
        return jnp.mean((phi - record) ** 2)

    value, grad = eqx.filter_value_and_grad(loss)(params)
    updates, state = opt.update(grad, state, params)
    return eqx.apply_updates(params, updates), state, value


for i in range(40):
    params, state, value = step(params, state)
    if i % 10 == 0 or i == 39:
        print(f"step {i:3d}: rms angle error {float(jnp.sqrt(value)):.3e} rad")
