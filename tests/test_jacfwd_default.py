"""Issue 40: `jax.jacfwd` through `cj.simulate` with its default adjoint ("reverse", a
`custom_vjp`) failed with JAX's "can't apply forward-mode autodiff (jvp) to a custom_vjp
function"; under forward-mode differentiation it now runs as `adjoint="forward"`."""

import jax
import jax.numpy as jnp
import numpy as np

import crank_jax as cj


def test_jacfwd_through_the_default_adjoint():
    scene = cj.load_scene("lab-rig")
    ts = jnp.linspace(0.0, 0.2, 5)

    def phi(k, c, **kw):
        return cj.simulate(scene.mech.replace(k=k, c=c), 1.0, 0.0, ts, **kw).phi

    want = jax.jacfwd(lambda k, c: phi(k, c, adjoint="forward"), argnums=(0, 1))(2.0, 0.002)
    got = jax.jacfwd(phi, argnums=(0, 1))(2.0, 0.002)
    for g, w in zip(got, want):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-12, atol=1e-15)
    assert float(jnp.max(jnp.abs(want[0]))) > 0.1  # a real sensitivity, not zeros
    # With jax.jit outside jax.jacfwd too (the tracers inside are still forward ones).
    jitted = jax.jit(jax.jacfwd(phi, argnums=(0, 1)))(2.0, 0.002)
    for g, w in zip(jitted, want):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-10, atol=1e-13)
