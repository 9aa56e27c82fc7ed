"""The arithmetic sin, cos and 1/sqrt of trig.py against NumPy's (glibc's) and
against their derivative identities; where they are used (a lockstep batch) and where not,
and the choice of form as a static field (`trig.traced_as`)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.model import CrankField, trig
from crank_jax.model.trig import ARITHMETIC, rsqrt, sincos


def _sin(x):
    return trig.sin(x, ARITHMETIC)


_sincos = jax.jit(lambda x: sincos(x, ARITHMETIC))
_rsqrt = jax.jit(lambda u: rsqrt(u, ARITHMETIC))


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
    np.testing.assert_array_equal(jax.jit(jax.vmap(jax.grad(_sin)))(x), c)
    np.testing.assert_array_equal(jax.jit(jax.vmap(jax.grad(lambda v: _sincos(v)[1])))(x), -s)
    np.testing.assert_array_equal(jax.jit(jax.vmap(jax.grad(jax.grad(_sin))))(x), -s)
    ds = jax.jit(lambda x: jax.jvp(_sincos, (x,), (2.0 * jnp.ones_like(x),))[1])(x)
    np.testing.assert_array_equal(ds[0], 2.0 * c)


def test_rsqrt_is_within_two_ulp_of_numpy_and_nan_where_it_has_no_value():
    u = np.exp(np.random.default_rng(1).uniform(np.log(1e-300), np.log(1e300), 400_000))
    u = np.concatenate([u, [1.0, 0.25, 4.0, np.nextafter(1.0, 0.0)]])
    assert _ulps(np.asarray(_rsqrt(jnp.asarray(u))), 1 / np.sqrt(u)).max() <= 2
    assert np.all(np.isnan(np.asarray(_rsqrt(jnp.asarray([0.0, -1.0, -1e-300])))))
    x = jnp.linspace(0.1, 10.0, 50)
    np.testing.assert_allclose(jax.jit(jax.vmap(jax.grad(_rsqrt)))(x), -0.5 * x**-1.5,
                               rtol=4e-16 * 6)


def test_other_float_types_take_jax_s_own_functions():
    x = jnp.linspace(-3.0, 3.0, 7, dtype=jnp.float32)
    s, c = sincos(x, ARITHMETIC)
    assert s.dtype == c.dtype == jnp.float32
    np.testing.assert_array_equal(s, jnp.sin(x))
    np.testing.assert_array_equal(rsqrt(x + 4, ARITHMETIC), jax.lax.rsqrt(x + 4))


def test_a_lockstep_batch_traces_the_arithmetic_forms_and_a_single_solve_jax_s(lab_rig):
    # The loads' sines too: the batch sets the form in the field's loads (`traced_as`).
    ts = jnp.linspace(0.0, 0.5, 11)
    load = cj.HarmonicLoad(0.5, 2.0, 3.0, 0.2)
    torque = cj.MultiSineLoad(jnp.array([0.01, 0.02]), jnp.array([2.0, 5.0]),
                              jnp.array([0.0, 1.0]))

    def phi(k):
        return cj.simulate(lab_rig.mech.replace(k=k), 1.0, 0.0, ts, load=load,
                           torque=torque, solver="dopri8-adaptive").phi

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


def _loads():
    return (cj.HarmonicLoad(0.5, 2.0, 3.0, 0.2),
            cj.MultiSineLoad(jnp.array([0.01]), jnp.array([2.0]), jnp.array([0.0])))


def test_traced_as_sets_the_form_in_a_field_and_its_loads_and_nothing_else(lab_rig):
    field = CrankField(lab_rig.mech, *_loads())
    assert field.trig == field.load.trig == field.torque.trig == trig.LIBRARY
    packed = trig.traced_as(field.packed(), ARITHMETIC)
    assert packed.trig == packed.load.trig == packed.torque.trig == ARITHMETIC
    assert trig.traced_as(field, ARITHMETIC).packed().trig == ARITHMETIC
    assert field.packed().trig == trig.LIBRARY  # the original is unchanged
    # Inside a wrapper, and a partitioned field (None for its arrays, as the variational
    # field holds its parts): no constructor runs, and the parts still combine.
    dyn, static = eqx.partition((field.packed(), 1.0), eqx.is_array)
    dyn, static = trig.traced_as(dyn, ARITHMETIC), trig.traced_as(static, ARITHMETIC)
    assert eqx.combine(dyn, static)[0].load.trig == ARITHMETIC
    # A user's field offers no choice: stepped as it is.
    user = lambda t, y, args: y  # noqa: E731
    assert trig.traced_as(user, ARITHMETIC) is user
    # The arithmetic form is the same field to an ulp or two.
    y = (jnp.array(0.7), jnp.array(-1.3))
    lib, ari = field.packed()(0.3, y)[1], packed(0.3, y)[1]
    np.testing.assert_allclose(ari, lib, rtol=1e-14)


def test_the_form_is_an_enum_resolved_at_construction(lab_rig):
    # A module made with the form's name holds the enum: the field is one type wherever
    # it was made, and a name and its enum give the same static structure (one program).
    by_name = CrankField(lab_rig.mech, *_loads(), trig="arithmetic")
    by_enum = CrankField(lab_rig.mech, *_loads(), trig=trig.Trig.ARITHMETIC)
    assert type(by_name.trig) is trig.Trig and by_name.trig is trig.Trig.ARITHMETIC
    assert by_name.trig == "arithmetic"  # still equal to its name
    assert type(cj.HarmonicLoad(0.5, 2.0, 3.0, trig="arithmetic").trig) is trig.Trig
    assert jax.tree.structure(by_name) == jax.tree.structure(by_enum)
    assert type(trig.traced_as(CrankField(lab_rig.mech, *_loads()), "arithmetic").trig
                ) is trig.Trig


@pytest.mark.parametrize("make", [
    lambda m: CrankField(m, *_loads(), trig="fast"),
    lambda m: cj.HarmonicLoad(0.5, 2.0, 3.0, trig="fast"),
    lambda m: trig.traced_as(CrankField(m, *_loads()), "fast"),
])
def test_an_unknown_form_is_refused_by_name(lab_rig, make):
    with pytest.raises(ValueError, match="trig must be one of"):
        make(lab_rig.mech)
