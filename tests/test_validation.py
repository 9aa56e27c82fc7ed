"""Bad input gets a clear error naming the field and the rule."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj

GOOD = cj.load_scene("lab-rig").mech.as_dict()

BAD = [
    ("r", {"r": 0.0}, "r must be > 0"),
    ("r", {"r": -0.1}, "r must be > 0"),
    ("L", {"L": 0.05}, "L must be > r"),
    ("L", {"L": 0.01}, "L must be > r"),
    ("b", {"b": -0.01}, "0 <= b <= L"),
    ("b", {"b": 0.5}, "0 <= b <= L"),
    ("s", {"s": -0.01}, "s must be >= 0"),
    ("m_c", {"m_c": -1.0}, "m_c must be >= 0"),
    ("m_p", {"m_p": -0.5}, "m_p must be >= 0"),
    ("m_s", {"m_s": -0.4}, "m_s must be >= 0"),
    ("I_c", {"I_c": -1e-4}, "I_c must be >= 0"),
    ("I_p", {"I_p": -1e-4}, "I_p must be >= 0"),
    ("I_c", {"m_c": 0.0, "I_c": 0.0}, "m_c\\*s\\^2 \\+ I_c must be > 0"),
    ("k", {"k": -1.0}, "k must be >= 0"),
    ("c", {"c": -0.01}, "c must be >= 0"),
    ("g", {"g": float("nan")}, "g must be finite"),
    ("k", {"k": float("inf")}, "k must be finite"),
    ("m_p", {"m_p": float("nan")}, "m_p must be finite"),
    ("k", {"k": 10**400}, "k must be finite"),
    ("c", {"c": -(10**400)}, "c must be finite"),
    ("L", {"e": 0.16}, "L must be > r \\+ \\|e\\|"),
    ("L", {"e": -0.16}, "L must be > r \\+ \\|e\\|"),
    ("e", {"e": float("inf")}, "e must be finite"),
    ("T_c", {"T_c": -0.1}, "T_c must be >= 0"),
    ("c_s", {"c_s": -1.0}, "c_s must be >= 0"),
    ("F_s", {"F_s": -1.0}, "F_s must be >= 0"),
    ("w_c", {"w_c": 0.0}, "w_c must be > 0"),
    ("w_s", {"w_s": -1e-3}, "w_s must be > 0"),
]


@pytest.mark.parametrize("field,change,rule", BAD)
def test_invalid_concrete_field_named(field, change, rule):
    with pytest.raises(ValueError, match=rf"SliderCrank\.{field} .*{rule}"):
        cj.SliderCrank(**{**GOOD, **change})


def test_zero_masses_are_a_valid_absent_body():
    cj.SliderCrank(**{**GOOD, "m_p": 0.0, "I_p": 0.0, "m_s": 0.0, "k": 0.0, "c": 0.0})


@pytest.mark.parametrize("field,change,rule", BAD[:6])
def test_invalid_traced_field_raises_inside_jit(field, change, rule):
    ts = jnp.linspace(0, 0.1, 3)

    @jax.jit
    def run(x):
        m = cj.SliderCrank(**{**GOOD, field: x})
        return cj.simulate(m, 0.1, 0.0, ts).phi

    run(jnp.asarray(GOOD[field]))  # valid: fine
    with pytest.raises(Exception, match=rf"SliderCrank\.{field} is invalid"):
        run(jnp.asarray(change[field]))


@pytest.mark.parametrize("field,change,rule", BAD[-8:])
def test_invalid_traced_offset_and_friction_raise_inside_jit(field, change, rule):
    # The same rules as at construction, from the same list, checked by eqx.error_if.
    name = next(iter(change))

    @jax.jit
    def check(x):
        # Every checked field is returned: an unused error_if would be compiled away.
        return jax.tree_util.tree_leaves(cj.SliderCrank(**{**GOOD, name: x}).checked())

    check(jnp.asarray(0.0 if name == "e" else 0.5))  # valid: fine
    with pytest.raises(Exception, match=rf"SliderCrank\.{field} is invalid: {rule}"):
        check(jnp.asarray(change[name]))


def test_offset_within_bounds_is_valid():
    slack = GOOD["L"] - GOOD["r"]
    for e in (0.99 * slack, -0.99 * slack):
        cj.SliderCrank(**{**GOOD, "e": e})


def test_fields_that_do_not_broadcast_are_refused():
    with pytest.raises(ValueError, match=r"do not broadcast.*L \(2,\).*k \(3,\)"):
        cj.SliderCrank(**{**GOOD, "k": jnp.ones(3), "L": jnp.full(2, 0.2)})
    cj.SliderCrank(**{**GOOD, "k": jnp.ones(3), "L": jnp.full(3, 0.2)})  # one batch: fine
    cj.SliderCrank(**{**GOOD, "k": jnp.ones((2, 1)), "L": jnp.full(3, 0.2)})  # broadcasts


def test_nonfinite_initial_state_raises():
    mech = cj.SliderCrank(**GOOD)
    with pytest.raises(Exception, match="initial state"):
        cj.simulate(mech, float("nan"), 0.0, np.linspace(0, 1, 3))


def test_replace_rejects_unknown_field():
    with pytest.raises(ValueError, match="unknown SliderCrank field"):
        cj.SliderCrank(**GOOD).replace(stiffness=3.0)


def test_checked_is_identity_on_valid_values():
    mech = cj.SliderCrank(**GOOD)
    assert eqx.tree_equal(mech.checked(), mech)


def test_sampled_load_validation():
    with pytest.raises(ValueError, match="increase strictly"):
        cj.SampledLoad([0.0, 1.0, 1.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="equal length"):
        cj.SampledLoad([0.0, 1.0], [1.0, 2.0, 3.0])
