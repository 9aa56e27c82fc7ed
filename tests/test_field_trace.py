"""The solvers' field traces the acceleration once per program (`model/dynamics.py`,
`_traced_once`): fewer traces, the same compiled numbers, and no cached trace for a
user's code, decided on the loads' objects alone (`model/loads.py`, `only_own_loads`):
exactly one of crank-jax's load kinds, with plain static values, or the plain path."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.model import HarmonicLoad
from crank_jax.model import dynamics as dyn
from crank_jax.model.structure import Structure
from crank_jax.solve import ForwardSensitivities, solver_named
from crank_jax.solve.trajectory import solve_crank

SCENE = cj.load_scene("lab-rig")
TS = jnp.linspace(0.0, 0.5, 51)


class _Drag(eqx.Module):
    """A user's force term (a class from outside crank-jax)."""

    a: jax.Array

    def __call__(self, t, phi, dphi):
        return -self.a * dphi * jnp.abs(dphi)


def _solve(k, *, force=None, adjoint=ForwardSensitivities(), solver="dopri8-adaptive",
           torque=None):
    mech = SCENE.mech.replace(k=k)
    torque = torque if torque is not None else cj.model.NoLoad()
    return solve_crank(mech, SCENE.load, torque, force, jnp.array([0.5, 0.0]), TS,
                       jnp.asarray(1e-8), jnp.asarray(1e-10), solver=solver_named(solver),
                       max_steps=4096, adjoint=adjoint,
                       structure=Structure.of(mech).union(Structure.of(SCENE.mech))).phi


def _count_geometry(monkeypatch) -> list:
    """Count the acceleration's traces (each calls `geometry_terms` once)."""
    calls = []
    real = dyn.geometry_terms

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(dyn, "geometry_terms", counted)
    return calls


def test_a_jacobian_traces_the_acceleration_at_most_once(monkeypatch):
    # A harmonic torque of a value used nowhere else: this trace's shapes and static
    # data are new to the cache (a cached one would count 0, which is also "at most once").
    calls = _count_geometry(monkeypatch)
    torque = HarmonicLoad(0.0123, 0.0456, 0.789)
    jax.make_jaxpr(jax.jacfwd(lambda k: _solve(k, torque=torque)))(2.0)
    # Traced afresh at every evaluation site, the same Jacobian takes 7 traces.
    assert len(calls) <= 1


def test_a_users_force_is_traced_afresh_at_every_site(monkeypatch):
    calls = _count_geometry(monkeypatch)
    jax.make_jaxpr(lambda k: _solve(k, force=_Drag(jnp.asarray(0.01))))(2.0)
    assert not dyn._own_code(SCENE.load, SCENE.load, _Drag(jnp.asarray(0.01)))
    assert len(calls) > 1


class _Doubled(HarmonicLoad):
    """A user's subclass of one of crank-jax's loads: its code is the user's."""

    def __call__(self, t):
        return 2.0 * super().__call__(t)


def _own_kinds():
    """One load of every kind of the table, each with its nested parts (a spline's
    coefficients, an input's signal, an angle table's record and period)."""
    from crank_jax.model import AngleLoad, InputLoad, MultiSineLoad, SampledLoad

    ts, vs = np.linspace(0.0, 1.0, 6), np.arange(6.0)
    return [cj.model.NoLoad(), cj.model.ConstantLoad(1.5), HarmonicLoad(0.0, 1.0, 2.0),
            MultiSineLoad([1.0, 2.0], [1.0, 3.0], [0.0, 0.5]), SampledLoad(ts, vs),
            SampledLoad(ts, vs, "zoh"), InputLoad(gain=1.0, column="u").bind(ts, vs),
            AngleLoad.from_samples(np.linspace(0.0, 7.0, 6), vs, ts=ts, period=2 * np.pi)]


def test_crank_jax_own_loads_take_the_cached_trace():
    for load in _own_kinds():
        assert dyn._own_code(load, HarmonicLoad(0.1, 0.2, 0.3), None), type(load).__name__
        assert dyn._own_code(cj.model.NoLoad(), load, None), type(load).__name__


def test_a_users_code_anywhere_takes_the_plain_path():
    from crank_jax.model import InputLoad

    own = HarmonicLoad(0.0, 1.0, 2.0)
    users = {
        "a user's force": (own, own, _Drag(jnp.asarray(0.01))),
        "a user's subclass of an own load": (_Doubled(0.0, 1.0, 2.0), own, None),
        "the same as the torque": (own, _Doubled(0.0, 1.0, 2.0), None),
        # `column` is a static field: a function there would be hashed, never traced
        "a callable in a static field": (InputLoad(gain=1.0, column=len), own, None),
        "a user's object in an array field": (eqx.tree_at(lambda x: x.X1, own, object()),
                                              own, None),
        "an array of objects": (eqx.tree_at(lambda x: x.X1, own,
                                            np.array([_Drag(jnp.asarray(1.0))], dtype=object)),
                                own, None),
    }
    for what, (load, torque, force) in users.items():
        assert not dyn._own_code(load, torque, force), what


def test_a_users_subclass_is_traced_afresh_at_every_site(monkeypatch):
    calls = _count_geometry(monkeypatch)
    jax.make_jaxpr(lambda k: _solve(k, torque=_Doubled(0.01, 0.02, 0.7)))(2.0)
    assert len(calls) > 1


def test_a_users_load_nested_in_a_crank_jax_load_is_not_cached():
    """A user's class anywhere in the loads (here the input signal of crank-jax's
    `InputLoad`) counts as user code, as the program store counts it."""
    from crank_jax.model import InputLoad

    class Ramp(cj.model.AbstractLoad):
        def __call__(self, t):
            return 0.1 * t

        def mean(self):
            return jnp.asarray(0.0)

    nested = InputLoad(gain=1.0, column="u", signal=Ramp())
    assert not dyn._own_code(nested, cj.model.NoLoad(), None)
    assert dyn._own_code(InputLoad(gain=1.0, column="u"), HarmonicLoad(0.0, 1.0, 2.0), None)


def _bits(x) -> bytes:
    return b"".join(np.asarray(v).tobytes() for v in jax.tree_util.tree_leaves(x))


def _same_bits(monkeypatch, make, exact=True):
    """`make()` (a fresh function to jit) gives the same bits with the cached trace and
    with the acceleration traced in place at every site; with `exact=False`, the same
    numbers up to rounding (1e-13 of the largest magnitude)."""
    cached = jax.jit(make())(2.0)
    monkeypatch.setattr(dyn, "_traced_once", dyn._acceleration)
    plain = jax.jit(make())(2.0)
    if exact:
        assert _bits(cached) == _bits(plain)
    else:
        scale = float(np.max(np.abs(plain)))
        np.testing.assert_allclose(cached, plain, rtol=0, atol=1e-13 * scale)


def test_the_forward_solve_gives_the_same_bits(monkeypatch):
    _same_bits(monkeypatch, lambda: (lambda k: _solve(k)))


@pytest.mark.parametrize("mode", ["jacfwd", "grad", "vmap"])
def test_derivatives_and_batches_give_the_same_numbers(monkeypatch, mode):
    torque = HarmonicLoad(0.01, 0.02, 0.7)
    if mode == "jacfwd":
        def make():
            return jax.jacfwd(lambda k: _solve(k, torque=torque))
    elif mode == "grad":
        def make():
            return jax.grad(lambda k: jnp.sum(_solve(k, torque=torque,
                                                     adjoint=cj.solve.DiscreteAdjoint()) ** 2))
    else:
        def make():
            return lambda k: jax.vmap(lambda kk: _solve(kk, torque=torque))(
                k * jnp.linspace(0.8, 1.2, 4))
    # A lockstep batch's program fuses the inlined call differently here (a harmonic
    # torque's argument reduction lands in another kernel): its rounding differs by
    # ~1e-15 of the angle's scale, where the other programs (and `simulate`'s batch on
    # the lab rig) are bit for bit the same.
    _same_bits(monkeypatch, make, exact=mode != "vmap")
