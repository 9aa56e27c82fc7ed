"""The arithmetic sin, cos and 1/sqrt of model/trig.py against NumPy's (glibc's) and
against their derivative identities."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from crank_jax.model.trig import rsqrt, sin, sincos

_sincos = jax.jit(sincos)
_rsqrt = jax.jit(rsqrt)


def _ulps(got, want):
    return np.abs(got - want) / np.spacing(np.abs(want))


@pytest.mark.parametrize("span, max_ulp", [(1.0, 1), (10.0, 1), (1e3, 1), (1e6, 2)])
def test_sincos_is_within_an_ulp_or_two_of_numpy(span, max_ulp):
    x = np.random.default_rng(0).uniform(-span, span, 400_000)
    s, c = map(np.asarray, _sincos(jnp.asarray(x)))
    assert _ulps(s, np.sin(x)).max() <= max_ulp
    assert _ulps(c, np.cos(x)).max() <= max_ulp


def test_sincos_at_the_quadrant_edges_and_tiny_angles():
    k = np.arange(-40, 41)
    x = np.concatenate([k * np.pi / 4, np.nextafter(k * np.pi / 4, np.inf),
                        np.nextafter(k * np.pi / 4, -np.inf), [0.0, 1e-300, -1e-20, 3e-9]])
    s, c = map(np.asarray, _sincos(jnp.asarray(x)))
    # Also where sin or cos is nearly zero (x near k pi/2): the three-part reduction keeps
    # the reduced angle's digits, so the error stays relative.
    assert _ulps(s, np.sin(x)).max() <= 1
    assert _ulps(c, np.cos(x)).max() <= 1
    assert np.all(s * s + c * c - 1 <= 4e-16)


def test_sincos_derivatives_are_the_identities():
    x = jnp.linspace(-20.0, 20.0, 101)
    s, c = _sincos(x)
    np.testing.assert_array_equal(jax.vmap(jax.grad(sin))(x), c)
    np.testing.assert_array_equal(jax.vmap(jax.grad(lambda v: sincos(v)[1]))(x), -s)
    np.testing.assert_array_equal(jax.vmap(jax.grad(jax.grad(sin)))(x), -s)
    _, ds = jax.jvp(sincos, (x,), (2.0 * jnp.ones_like(x),))
    np.testing.assert_array_equal(ds[0], 2.0 * c)


def test_rsqrt_is_within_two_ulp_of_numpy_and_nan_where_it_has_no_value():
    u = np.exp(np.random.default_rng(1).uniform(np.log(1e-300), np.log(1e300), 400_000))
    u = np.concatenate([u, [1.0, 0.25, 4.0, np.nextafter(1.0, 0.0)]])
    assert _ulps(np.asarray(_rsqrt(jnp.asarray(u))), 1 / np.sqrt(u)).max() <= 2
    assert np.all(np.isnan(np.asarray(_rsqrt(jnp.asarray([0.0, -1.0, -1e-300])))))
    x = jnp.linspace(0.1, 10.0, 50)
    np.testing.assert_allclose(jax.vmap(jax.grad(rsqrt))(x), -0.5 * x**-1.5, rtol=4e-16 * 6)


def test_other_float_types_take_jax_s_own_functions():
    x = jnp.linspace(-3.0, 3.0, 7, dtype=jnp.float32)
    s, c = sincos(x)
    assert s.dtype == c.dtype == jnp.float32
    np.testing.assert_array_equal(s, jnp.sin(x))
    np.testing.assert_array_equal(rsqrt(x + 4), jax.lax.rsqrt(x + 4))
