"""Forward mode of the default solver through the variational equation (solve/variational.py):
the same derivatives as tangents carried through the solve, only the differentiated columns,
reverse mode by transposition, lockstep batches, the fallback for many parameters."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.model.coefficients import Coefficients
from crank_jax.model.dynamics import CrankField, Structure
from crank_jax.model.loads import as_load
from crank_jax.solve import variational
from crank_jax.solve.adaptive import solve_adaptive

RTOL, ATOL = 1e-9, 1e-11
TS = jnp.linspace(0.0, 2.0, 101)
# Every kind of term: offset, crank and slider friction, the coupler and the slider.
NAMES = ("L", "m_p", "k", "c", "e", "T_c", "c_s", "F_s")


@pytest.fixture(scope="module")
def smooth():
    # No Coulomb friction: sensitivities well conditioned (see the friction test).
    return cj.load_scene("lab-rig").mech.replace(c=2e-3, e=0.01, c_s=0.05)


SMOOTH = ("L", "m_p", "k", "c", "e", "c_s")


@pytest.fixture(scope="module")
def rig():
    return cj.load_scene("lab-rig").mech.replace(c=2e-3, e=0.01, T_c=2e-3, c_s=0.05,
                                                 F_s=0.02)


@pytest.fixture
def solution_steps(monkeypatch):
    # The variational solve on the solution's steps (its step control blind to the
    # sensitivities): then its Jacobian is the derivative of the same discrete solution as
    # tangents through the solve, to rounding, which checks its arithmetic. By default the
    # steps also meet the tolerance on the sensitivities (see the friction test), and the
    # two agree to the tolerance only. The flag is read when the solve is traced, and
    # JAX keeps the traces of the jitted functions inside: clear them on both sides.
    jax.clear_caches()
    monkeypatch.setattr(variational, "CONTROL_SENSITIVITIES", False)
    yield
    jax.clear_caches()


def _phi(mech, theta, y0, names=NAMES):
    m = mech.replace(**dict(zip(names, theta)))
    return cj.simulate(m, y0[0], y0[1], TS, rtol=RTOL, atol=ATOL, adjoint="forward").phi


def _phi_through_the_loop(mech, theta, y0, names=NAMES):
    # The same solver with JAX's tangents carried through its steps (no variational path).
    m = mech.replace(**dict(zip(names, theta)))
    field = CrankField(m, as_load(None), as_load(None), Structure.of(m), None).packed()
    (phi, _), _, _ = solve_adaptive(field, (y0[0], y0[1]), TS, RTOL, ATOL, max_steps=4096)
    return phi


def _theta(mech, names=NAMES):
    return jnp.array([float(getattr(mech, n)) for n in names])


def test_jacobian_equals_tangents_through_the_solve(smooth, solution_steps):
    # Both are the derivative of the same discrete solution (the same steps): they agree to
    # rounding, for the parameters and the initial state.
    mech, names = smooth, SMOOTH
    theta, y0 = _theta(mech, names), jnp.array([1.0, 0.3])
    for argnum in (0, 1):
        ours = jax.jit(jax.jacfwd(lambda th, y: _phi(mech, th, y, names), argnum))(theta, y0)
        ref = jax.jit(jax.jacfwd(lambda th, y: _phi_through_the_loop(mech, th, y, names),
                                 argnum))(theta, y0)
        scale = np.max(np.abs(ref), axis=0)
        assert np.all(scale > 0)
        np.testing.assert_allclose(ours / scale, ref / scale, rtol=0, atol=1e-10)


def test_jacobian_with_friction_as_accurate_as_tangents_through_the_solve(rig):
    # With Coulomb friction (tanh of width 0.01 rad/s) tangents carried through the solve
    # are ~5e-6 off a tight reference (the steps, chosen on the solution, do not resolve
    # the spike of f_y where the velocity crosses zero). The variational solve's steps
    # meet the tolerance on the sensitivities too: 2.2e-5 off before they did, 2.4e-8 now.
    theta, y0 = _theta(rig), jnp.array([1.0, 0.3])
    ours = jax.jit(jax.jacfwd(lambda th: _phi(rig, th, y0)))(theta)
    loop = jax.jit(jax.jacfwd(lambda th: _phi_through_the_loop(rig, th, y0)))(theta)
    m = lambda th: rig.replace(**dict(zip(NAMES, th)))  # noqa: E731
    tight = jax.jit(jax.jacfwd(lambda th: cj.simulate(
        m(th), 1.0, 0.3, TS, solver="dopri8", rtol=1e-12, atol=1e-14,
        adjoint="forward").phi))(theta)
    scale = np.max(np.abs(tight), axis=0)
    err_ours = np.max(np.abs(ours - tight) / scale)
    err_loop = np.max(np.abs(loop - tight) / scale)
    assert err_ours < 1e-4
    assert err_ours <= 2 * err_loop


def test_a_column_alone_equals_its_column_of_the_full_jacobian(smooth, solution_steps):
    # One column per differentiated parameter: the others do not change it.
    mech, names = smooth, SMOOTH
    theta, y0 = _theta(mech, names), (1.0, 0.3)
    full = jax.jit(jax.jacfwd(lambda th: _phi(mech, th, y0, names)))(theta)
    i = names.index("e")
    alone = jax.jit(jax.jacfwd(lambda x: _phi(mech, x, y0, ("e",))))(theta[i:i + 1])
    np.testing.assert_allclose(alone[:, 0], full[:, i], rtol=0,
                               atol=1e-10 * np.max(np.abs(full[:, i])))


def test_only_the_coefficients_the_field_reads_enter_the_chain_rule(rig):
    # The lab rig without friction reads no friction coefficient; with friction it does.
    # (A coefficient wrongly left out would drop its parameters' sensitivities.)
    def read(mech):
        field = CrankField(mech, as_load(None), as_load(None), Structure.of(mech), None)
        packed = field.packed()
        live, rest = eqx.partition(packed, eqx.is_inexact_array)

        def f(xs, live):
            return (eqx.combine(live, rest)(0.1, xs, None)[1],)

        return {Coefficients._fields[i]
                for i in variational._read_elements(f, (jnp.array(1.0), jnp.array(0.2)),
                                                    live)}

    plain = read(cj.load_scene("lab-rig").mech)
    assert {"k", "c", "cM0", "lam"} <= plain
    assert not {"T_c", "inv_wc", "c_s", "F_s", "inv_ws", "eL"} & plain
    assert {"T_c", "inv_wc", "c_s", "F_s", "inv_ws", "eL"} <= read(rig)


def test_read_elements_is_conservative_on_plain_slices():
    # Without coefficients.unpack's single stack, every element counts as read.
    def f(xs, live):
        return (xs[0] * live[2],)

    assert variational._read_elements(f, (jnp.array(1.0),), jnp.ones(4)) == (0, 1, 2, 3)


def test_reverse_mode_with_forward_adjoint_transposes_the_sensitivities(smooth):
    theta, y0 = _theta(smooth, SMOOTH), (1.0, 0.3)
    g_fwd = jax.jit(jax.grad(lambda th: jnp.sum(_phi(smooth, th, y0, SMOOTH) ** 2)))(theta)
    m = lambda th: smooth.replace(**dict(zip(SMOOTH, th)))  # noqa: E731
    g_rev = jax.jit(jax.grad(lambda th: jnp.sum(cj.simulate(
        m(th), 1.0, 0.3, TS, rtol=RTOL, atol=ATOL).phi ** 2)))(theta)
    np.testing.assert_allclose(g_fwd, g_rev, rtol=1e-6)


def test_a_batch_of_jacobians_steps_in_lockstep(smooth):
    # vmap of jacfwd: the augmented states of the members step together (lockstep.py);
    # each member's Jacobian equals its own to the tolerance.
    ks = jnp.array([1.8, 2.0, 2.4])
    names = ("k", "c")

    def jac(k):
        return jax.jacfwd(lambda th: _phi(smooth, th, (1.0, 0.3), names))(
            jnp.stack([k, jnp.asarray(smooth.c)]))

    batch = jax.jit(jax.vmap(jac))(ks)
    one = jax.jit(jac)
    for i, k in enumerate(ks):
        ref = one(k)
        scale = np.max(np.abs(ref), axis=0)
        np.testing.assert_allclose(batch[i] / scale, ref / scale, rtol=0, atol=1e-7)


def test_many_parameters_fall_back_to_tangents_through_the_solve(smooth, monkeypatch,
                                                                solution_steps):
    # Above MAX_COLUMNS the JVP carries the tangents through the solve (on the solution's
    # steps, which the variational solve then takes too): the same result.
    theta, y0 = _theta(smooth, SMOOTH), (1.0, 0.3)
    fast = jax.jit(jax.jacfwd(lambda th: _phi(smooth, th, y0, SMOOTH)))(theta)
    monkeypatch.setattr(variational, "MAX_COLUMNS", 4)
    slow = jax.jit(jax.jacfwd(lambda th: _phi(smooth, th, y0, SMOOTH)))(theta)
    scale = np.max(np.abs(slow), axis=0)
    np.testing.assert_allclose(fast / scale, slow / scale, rtol=0, atol=1e-10)


def test_load_parameters_are_columns_too(smooth, solution_steps):
    # A load's parameters are leaves of the prepared field beside the packed coefficients
    # (not gathered by one stack, so all their elements count as read).
    def phi(p, through_loop):
        load, m = cj.HarmonicLoad(p[0], p[1], p[2], 0.0), smooth.replace(k=p[3])
        if not through_loop:
            return cj.simulate(m, 1.0, 0.3, TS, load=load, rtol=RTOL, atol=ATOL,
                               adjoint="forward").phi
        field = CrankField(m, as_load(load), as_load(None), Structure.of(m), None).packed()
        return solve_adaptive(field, (1.0, 0.3), TS, RTOL, ATOL, max_steps=4096)[0][0]

    p = jnp.array([0.5, 2.0, 1.3, 2.0])
    ours = jax.jit(jax.jacfwd(lambda p: phi(p, False)))(p)
    ref = jax.jit(jax.jacfwd(lambda p: phi(p, True)))(p)
    scale = np.max(np.abs(ref), axis=0)
    np.testing.assert_allclose(ours / scale, ref / scale, rtol=0, atol=1e-10)


def test_new_values_do_not_retrace_the_jacobian(smooth):
    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def jac(mech, theta, y0):
        return jax.jacfwd(lambda th: _phi(mech, th, y0, ("k", "c")))(theta)

    jac(smooth, jnp.array([2.0, 2e-3]), jnp.array([1.0, 0.3]))
    jac(smooth.replace(m_p=0.6), jnp.array([2.5, 3e-3]), jnp.array([0.8, 0.0]))


def test_rolled_stages_equal_the_unrolled_ones_and_trace_the_field_once():
    """`FusedERK(rolled=True)` (the variational solve's stages, in a loop): the same stage
    derivatives as the unrolled stages, to rounding, with the field traced once, not once
    per stage."""
    from crank_jax.solve.erk import dopri8

    traced = []

    def f(t, y, args):
        traced.append(1)
        return {"a": y["b"] * jnp.cos(t), "b": -jnp.sin(y["a"]) - 0.1 * y["b"] ** 3}

    y = {"a": jnp.array([0.3, -1.2]), "b": jnp.array([2.0, 0.5])}
    t, h = jnp.array(0.4), jnp.array(0.05)
    plain = dopri8().stages(f, t, y, None, h)
    n_plain = len(traced)
    traced.clear()
    rolled = dopri8(rolled=True).stages(f, t, y, None, h)
    assert len(rolled) == len(plain) == dopri8().num_stages
    assert n_plain == dopri8().num_stages and len(traced) == 2  # the first stage, the loop
    for kp, kr in zip(plain, rolled):
        for leaf in ("a", "b"):
            np.testing.assert_allclose(kr[leaf], kp[leaf], rtol=1e-14, atol=1e-15)
    y1p, y1r = dopri8().solution(y, h, plain), dopri8().solution(y, h, rolled)
    np.testing.assert_allclose(y1r["a"], y1p["a"], rtol=1e-15)


def test_jacobian_with_its_stages_in_a_loop_equals_the_unrolled_one(smooth, solution_steps):
    """`AdaptiveDopri8(loop_stages=True)`, the fit's solver (`pick_solver`): the same
    Jacobian, for the parameters and the initial state, and under `vmap` over members
    with their own save times (multiple shooting's segments, in lockstep), on the same
    steps. (With the step control on the sensitivities, the stages' rounding can flip an
    accept/reject decision: 406 against 405 steps, 7e-10 apart, both 2e-9 off a tight
    reference, 2026-11-28.)"""
    from crank_jax.identify.problem import pick_solver
    from crank_jax.solve.solvers import AdaptiveDopri8

    mech, names = smooth, SMOOTH
    assert pick_solver(mech, None, RTOL, "dopri8-adaptive") == AdaptiveDopri8(loop_stages=True)
    theta, y0 = _theta(mech, names), jnp.array([1.0, 0.3])

    def phi(th, y, ts, solver):
        m = mech.replace(**dict(zip(names, th)))
        return cj.simulate(m, y[0], y[1], ts, rtol=RTOL, atol=ATOL, adjoint="forward",
                           solver=solver).phi

    looped = AdaptiveDopri8(loop_stages=True)
    for argnum in (0, 1):
        ref = jax.jit(jax.jacfwd(lambda th, y: phi(th, y, TS, "dopri8-adaptive"), argnum))(
            theta, y0)
        ours = jax.jit(jax.jacfwd(lambda th, y: phi(th, y, TS, looped), argnum))(theta, y0)
        scale = np.max(np.abs(ref), axis=0)
        np.testing.assert_allclose(ours / scale, ref / scale, rtol=0, atol=1e-12)
    # Two segments with their own save times.
    tss = jnp.stack([TS[:51], TS[50:]])
    y0s = jnp.array([[1.0, 0.3], [0.5, -0.2]])

    def segments(th, solver):
        return jax.vmap(lambda y, ts: phi(th, y, ts, solver))(y0s, tss)

    ref = jax.jit(jax.jacfwd(lambda th: segments(th, "dopri8-adaptive")))(theta)
    ours = jax.jit(jax.jacfwd(lambda th: segments(th, looped)))(theta)
    scale = np.max(np.abs(ref), axis=(0, 1))
    # Segments step in lockstep (lockstep.py), where the field's sin and cos are
    # arithmetic (trig.py) and the batch's stages round otherwise than one member's: the
    # second segment's columns then moved by 2.0e-11 of their largest entry (4.2e-12 with
    # the plain sin and cos; the same with save times shared by the members, so not the
    # members' own times: 2026-11-28), against 2.4e-14 solved alone, above. Two orders of
    # magnitude inside the tolerance (rtol 1e-9) still.
    np.testing.assert_allclose(ours / scale, ref / scale, rtol=0, atol=1e-10)
