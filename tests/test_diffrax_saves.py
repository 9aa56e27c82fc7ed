"""diffrax's explicit solvers in forward mode with the save times checked by the caller
(`solve(checks=False)`, the fit's solves) save at `ts` inside their steps (solve/saves.py)
instead of through `SaveAt(ts)`, whose check of the save times is a host callback that
kept the fit's programs out of the program store. The same numbers, bit for bit: the
reference is the `SaveAt(ts)` path, forced by making `Diffrax.unchecked` a no-op.

(The store itself: tests/test_persistent.py, a fit on `"dopri5"` in two processes.)"""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.identify.problem import build_problem
from crank_jax.identify.programs import jacobian_at, residuals_at
from crank_jax.model.sampled import SampledLoad
from crank_jax.solve.solvers import Diffrax

CALLBACK = "python_cpu_callback"  # XLA:CPU's custom call into Python


def _problem(name: str, segments: int, torque):
    scene = cj.load_scene("lab-rig")
    data = cj.synthesize(scene, t1=2.0, rate=100.0, noise_std=1e-3, seed=1)
    prob = build_problem(scene.mech, [(data, scene.load, torque, 1.0, 0.0)],
                         ("k", "c", "phi0", "dphi0"), {"k": 2.0, "c": 0.002}, [segments],
                         solver=cj.solve.solver_named(name), rtol=1e-8, atol=1e-10,
                         max_steps=32768)
    z = jnp.concatenate([jnp.asarray(prob.to_z([2.1, 0.0025, 1.0, 0.0])),
                         0.5 * jnp.ones(prob.n_extra)])
    return prob, z


def _programs(prob, z):
    """Each fit program's outputs and lowered text, compiled afresh (not from the
    programs' in-process caches, which would hand back the other path's program)."""
    out = {}
    for program in (residuals_at, jacobian_at):
        f = jax.jit(lambda z, program=program: program.fn(prob, z))
        out[program.name] = ([np.asarray(x) for x in f(z)], f.lower(z).as_text())
    return out


TK = np.linspace(0.0, 2.0, 41)


# Sampled torques put the field's kinks (`step_ts`) and jumps (`jump_ts`) in the step
# control; four segments put the solve under `vmap`.
@pytest.mark.parametrize("name, segments, torque", [
    ("dopri5", 1, None),
    ("dopri8", 4, SampledLoad(TK, 0.3 * np.sin(3 * TK), "zoh")),
    pytest.param("tsit5", 1, SampledLoad(TK, 0.3 * np.sin(3 * TK), "cubic"),
                 marks=pytest.mark.slow),
], ids=["dopri5", "dopri8-segments-jumps", "tsit5-kinks"])
def test_fit_programs_hold_no_callback_and_equal_saveat_ts(monkeypatch, name, segments,
                                                            torque):
    prob, z = _problem(name, segments, cj.NoLoad() if torque is None else torque)
    new = _programs(prob, z)
    with monkeypatch.context() as m:
        m.setattr(Diffrax, "unchecked", lambda self: self)
        old = _programs(prob, z)
    for program, (values, text) in new.items():
        assert CALLBACK not in text, program
        assert CALLBACK in old[program][1], program  # the check the old form holds
        assert int(values[1]) == 0  # no failed sample: the comparison is of solutions
        for a, b in zip(values, old[program][0]):
            np.testing.assert_array_equal(a, b, err_msg=program)


def _oscillator(t, y, w):
    x, v = y
    return v, -(w**2) * x


TS = jnp.linspace(0.0, 3.0, 61)
Y0 = (jnp.asarray(1.0), jnp.asarray(0.0))


@pytest.mark.parametrize("max_steps", [10_000, 12], ids=["solved", "out-of-budget"])
def test_solve_unchecked_equals_saveat_ts_with_its_tangents(max_steps):
    # `solve` itself, forward mode: values and tangents bit for bit, a failed solve's
    # samples (inf after the failure) and result included.
    solver = Diffrax(diffrax.Dopri5())

    def run(w, checks):
        sol = cj.solve.solve(_oscillator, solver, TS, Y0, w, rtol=1e-8, atol=1e-10,
                       max_steps=max_steps, adjoint="forward", throw=False, checks=checks)
        return jnp.stack(sol.ys), (sol.result == diffrax.RESULTS.successful, sol.num_steps)

    w, dw = jnp.asarray(2.0), jnp.asarray(1.0)
    out = {c: jax.jit(lambda w, dw, c=c: jax.jvp(lambda w: run(w, c), (w,), (dw,),
                                                  has_aux=True))(w, dw)
           for c in (True, False)}
    (ys, dys, aux), (ys0, dys0, aux0) = out[False], out[True]
    np.testing.assert_array_equal(ys, ys0)
    np.testing.assert_array_equal(dys, dys0)
    assert bool(aux[0]) == bool(aux0[0]) == (max_steps > 12)
    assert int(aux[1]) == int(aux0[1])
    if max_steps == 12:
        assert np.isinf(np.asarray(ys)[:, -1]).all()  # never reached
    else:
        np.testing.assert_allclose(ys[0], np.cos(2.0 * TS), atol=1e-7)


def test_reverse_mode_and_implicit_solvers_keep_saveat_ts():
    # `checks=False` changes only what it can: reverse mode (the save loop has no reverse
    # mode) and implicit solvers go through `SaveAt(ts)` and still differentiate.
    def loss(w, solver, adjoint):
        sol = cj.solve.solve(_oscillator, solver, TS, Y0, w, rtol=1e-8, atol=1e-10,
                       adjoint=adjoint, checks=False)
        return jnp.sum(sol.ys[0] ** 2)

    w = jnp.asarray(2.0)
    g = jax.grad(loss)(w, Diffrax(diffrax.Tsit5()), "reverse")
    fwd = jax.jacfwd(loss)(w, Diffrax(diffrax.Tsit5()), "forward")
    np.testing.assert_allclose(g, fwd, rtol=1e-5)
    implicit = jax.jacfwd(loss)(w, Diffrax(diffrax.Kvaerno5()), "forward")
    np.testing.assert_allclose(implicit, fwd, rtol=1e-3)


def test_unchecked_is_the_same_solver_but_for_the_check():
    solver = cj.solve.solver_named("dopri5")
    assert solver.unchecked() == Diffrax(diffrax.Dopri5(), checks=False) != solver
    assert solver.unchecked().solver is solver.solver
    fused = cj.solve.solver_named("dopri8-adaptive")
    assert fused.unchecked() is fused
