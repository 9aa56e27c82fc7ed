"""Adjoints as objects (solve/adjoints.py): each owns its derivative rule, the shorthand
names give the objects' numbers bit for bit, the discrete adjoint's backward program is
a static field chosen at the edge from the XLA flags, and a stored program is never
served for the other program."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
import crank_jax.simulation as front_door
from crank_jax.runtime import persistent
from crank_jax.runtime.xla_flags import SMALL_LOOP_BYTES, backward_program
from crank_jax.solve import DirectAdjoint, DiscreteAdjoint, ForwardSensitivities
from crank_jax.solve.adjoints import as_adjoint

TS = jnp.linspace(0.0, 0.3, 16)


def _phi(mech, k, adjoint, solver):
    return cj.simulate(mech.replace(k=k), 1.0, 0.0, TS, solver=solver, adjoint=adjoint).phi


CASES = [("forward", ForwardSensitivities(), "dopri8-adaptive", "jacfwd"),
         ("reverse", DiscreteAdjoint(backward_program()), "tsit5", "grad"),
         ("direct", DirectAdjoint(), "dopri8-uniform", "value")]
# `solve`'s own: "reverse" is `DiscreteAdjoint()` there (the caller of `solve` picks the
# backward program); its program holds the discrete adjoint's rule.
SOLVE_CASES = [CASES[0], ("reverse", DiscreteAdjoint(), "dopri8-adaptive", "value"),
               CASES[2]]


def _oscillator(t, y, w):
    return y[1], -(w**2) * y[0]


@pytest.mark.parametrize("name,obj,solver,how", SOLVE_CASES, ids=[c[0] for c in CASES])
def test_solve_takes_a_name_as_its_object(name, obj, solver, how):
    # `solve`'s shorthand: the same program (traced, not compiled: the same program gives
    # the same numbers bit for bit; the crank's numbers are compared below, slow).
    ts, y0 = jnp.linspace(0.0, 1.0, 11), (jnp.asarray(1.0), jnp.asarray(0.0))

    def x(w, adjoint):
        return cj.solve.solve(_oscillator, cj.solve.solver_named(solver), ts, y0, w,
                              adjoint=adjoint).ys[0]

    f = {"jacfwd": jax.jacfwd(x), "grad": jax.grad(lambda w, a: jnp.sum(x(w, a))),
         "value": x}[how]
    by_name = jax.make_jaxpr(f, static_argnums=1)(2.0, name)
    assert str(by_name) == str(jax.make_jaxpr(f, static_argnums=1)(2.0, obj))
    other = DirectAdjoint() if name == "forward" else ForwardSensitivities()
    assert str(by_name) != str(jax.make_jaxpr(f, static_argnums=1)(2.0, other))


# The crank through `simulate`'s front door: two compiled programs of the crank each (30-110
# s on the loaded 2-core machine), so in the full suite.
@pytest.mark.slow
@pytest.mark.parametrize("name,obj,solver,how", CASES, ids=[c[0] for c in CASES])
def test_a_shorthand_name_gives_its_objects_numbers_bit_for_bit(lab_rig, name, obj, solver,
                                                                 how):
    mech = lab_rig.mech
    k = jnp.asarray(float(mech.k))

    def run(adjoint):
        f = {"jacfwd": lambda k: jax.jacfwd(lambda k: _phi(mech, k, adjoint, solver))(k),
             "grad": jax.grad(lambda k: jnp.sum(jnp.sin(_phi(mech, k, adjoint, solver)))),
             "value": lambda k: _phi(mech, k, adjoint, solver)}[how]
        return np.asarray(jax.jit(f)(k))

    by_name = run(name)
    assert np.all(np.isfinite(by_name)) and np.any(by_name != 0)
    np.testing.assert_array_equal(by_name, run(obj))


def test_the_solvers_ask_the_adjoint():
    # What each solver family takes from its adjoint (solvers.py reads no names).
    import diffrax

    assert [a.loop_kind for a in (DiscreteAdjoint(), ForwardSensitivities(),
                                  DirectAdjoint())] == ["checkpointed", "lax", "bounded"]
    assert isinstance(DiscreteAdjoint().diffrax_adjoint(), diffrax.RecursiveCheckpointAdjoint)
    assert isinstance(ForwardSensitivities().diffrax_adjoint(), diffrax.ForwardMode)
    assert isinstance(DirectAdjoint().diffrax_adjoint(), diffrax.DirectAdjoint)
    assert [a.forward_only for a in (DiscreteAdjoint(), ForwardSensitivities(),
                                     DirectAdjoint())] == [False, True, False]
    assert as_adjoint("reverse", backward="loop") == DiscreteAdjoint("loop")
    assert as_adjoint(DirectAdjoint()) == DirectAdjoint()


def test_a_bad_adjoint_names_the_field(lab_rig):
    with pytest.raises(ValueError, match=r"backward must be one of \('blocks', 'loop'\)"):
        DiscreteAdjoint(backward="fast")
    with pytest.raises(ValueError, match="adjoint must be an adjoint object"):
        cj.solve.solve(lambda t, y, a: -y, cj.solve.solver_named("tsit5"), TS, 1.0,
                       adjoint="sideways")
    with pytest.raises(ValueError, match="adjoint must be an adjoint object"):
        cj.simulate(lab_rig.mech, 1.0, 0.0, TS, adjoint="sideways")


def test_the_backward_program_is_chosen_at_the_edge(lab_rig, monkeypatch):
    # The core reads no flags: the front door turns "reverse" into a DiscreteAdjoint whose
    # backward program suits this process (the loop where XLA:CPU hoists it).
    flags = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold="
    monkeypatch.setenv("XLA_FLAGS", flags + str(SMALL_LOOP_BYTES))
    assert backward_program() == "loop"
    monkeypatch.setenv("XLA_FLAGS", flags + "1024")
    assert backward_program() == "blocks"
    monkeypatch.delenv("XLA_FLAGS")
    assert backward_program() == "blocks"

    seen = []

    def spy(*args, adjoint, **kw):
        seen.append(adjoint)
        raise RuntimeError("seen")

    monkeypatch.setattr(front_door, "solve_trajectory", spy)
    monkeypatch.setattr(front_door, "backward_program", lambda: "loop")
    with pytest.raises(RuntimeError, match="seen"):  # traced: the user's adjoint
        jax.jit(lambda k: cj.simulate(lab_rig.mech.replace(k=k), 1.0, 0.0, TS))(1.0)
    assert seen == [DiscreteAdjoint("loop")]


def _which(x, adjoint):
    # A program that differs by the backward program, as the fit's programs do.
    return (x + (1.0 if adjoint.backward == "loop" else 2.0),)


def test_a_stored_program_is_never_served_for_the_other_backward_program(tmp_path,
                                                                        monkeypatch):
    monkeypatch.setattr(persistent, "program_store_dir", lambda: tmp_path)
    x = jnp.asarray(1.0)
    first = persistent.PersistentProgram(_which, "adjoint-key")
    assert float(first(x, DiscreteAdjoint("loop"))[0]) == 2.0
    # A fresh process's program (nothing in memory), the other choice: not the stored one.
    fresh = persistent.PersistentProgram(_which, "adjoint-key")
    assert float(fresh(x, DiscreteAdjoint("blocks"))[0]) == 3.0
    assert float(fresh(x, DiscreteAdjoint("loop"))[0]) == 2.0
    assert len(list(tmp_path.glob("adjoint-key-*.xla"))) == 2
