"""The arithmetic sin, cos and 1/sqrt of trig.py against NumPy's (glibc's) and
against their derivative identities; where they are used (a lockstep batch) and where not."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.model.trig import arithmetic, rsqrt, sin, sincos


def _arith(fn):
    """`fn` traced with the arithmetic forms (its own trace: a fresh function per call)."""
    def run(*args):
        with arithmetic():
            return jax.jit(lambda *a: fn(*a))(*args)
    return run


_sincos = _arith(sincos)
_rsqrt = _arith(rsqrt)


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
    np.testing.assert_array_equal(_arith(jax.vmap(jax.grad(sin)))(x), c)
    np.testing.assert_array_equal(_arith(jax.vmap(jax.grad(lambda v: sincos(v)[1])))(x), -s)
    np.testing.assert_array_equal(_arith(jax.vmap(jax.grad(jax.grad(sin))))(x), -s)
    ds = _arith(lambda x: jax.jvp(sincos, (x,), (2.0 * jnp.ones_like(x),))[1])(x)
    np.testing.assert_array_equal(ds[0], 2.0 * c)


def test_rsqrt_is_within_two_ulp_of_numpy_and_nan_where_it_has_no_value():
    u = np.exp(np.random.default_rng(1).uniform(np.log(1e-300), np.log(1e300), 400_000))
    u = np.concatenate([u, [1.0, 0.25, 4.0, np.nextafter(1.0, 0.0)]])
    assert _ulps(np.asarray(_rsqrt(jnp.asarray(u))), 1 / np.sqrt(u)).max() <= 2
    assert np.all(np.isnan(np.asarray(_rsqrt(jnp.asarray([0.0, -1.0, -1e-300])))))
    x = jnp.linspace(0.1, 10.0, 50)
    np.testing.assert_allclose(_arith(jax.vmap(jax.grad(rsqrt)))(x), -0.5 * x**-1.5,
                               rtol=4e-16 * 6)


def test_other_float_types_take_jax_s_own_functions():
    x = jnp.linspace(-3.0, 3.0, 7, dtype=jnp.float32)
    with arithmetic():
        s, c = sincos(x)
    assert s.dtype == c.dtype == jnp.float32
    np.testing.assert_array_equal(s, jnp.sin(x))
    with arithmetic():
        np.testing.assert_array_equal(rsqrt(x + 4), jax.lax.rsqrt(x + 4))


def test_a_lockstep_batch_traces_the_arithmetic_forms_and_a_single_solve_jax_s(lab_rig):
    ts = jnp.linspace(0.0, 0.5, 11)

    def phi(k):
        return cj.simulate(lab_rig.mech.replace(k=k), 1.0, 0.0, ts).phi

    single = _primitives(jax.make_jaxpr(phi)(2.0).jaxpr)
    batch = _primitives(jax.make_jaxpr(jax.vmap(phi))(jnp.array([2.0, 2.1])).jaxpr)
    assert {"sin", "rsqrt"} <= single
    assert not {"sin", "cos", "rsqrt"} & batch


def _primitives(jaxpr) -> set[str]:
    """The primitives of a jaxpr and of every jaxpr inside it. (Matching " cos " in the
    printed jaxpr also matched a variable that the printer happened to name `cos`.)"""
    out = set()
    for eqn in jaxpr.eqns:
        out.add(eqn.primitive.name)
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            out |= _primitives(sub)
    return out
