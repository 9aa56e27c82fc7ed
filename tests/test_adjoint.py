"""Reverse mode of the default solver (`"dopri8-adaptive"`, `adjoint="reverse"`) is the
discrete adjoint of its steps (solve/adjoint.py): the exact gradient of the computed
solution, so it equals the forward-mode Jacobian through the same steps to rounding.

The reference is `jax.jacfwd` through `simulate(adjoint="direct")`: JAX's tangents
carried through the same solve's steps (the step sizes and decisions are values there
too), contracted with the loss's weights."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.solve import DiscreteAdjoint, adjoint, steplog

PARAMS = ("L", "b", "s", "m_c", "m_p", "m_s", "I_c", "I_p", "k", "c")


def _problem(torque=None, t1=2.0, samples=201):
    mech = cj.load_scene("lab-rig").mech.replace(c=1e-3)
    ts = jnp.linspace(0.0, t1, samples)
    theta0 = jnp.array([float(getattr(mech, n)) for n in PARAMS] + [0.3])
    weights = jnp.stack([jnp.sin(jnp.arange(samples) * 0.7), jnp.cos(jnp.arange(samples))])

    def traj(theta, adjoint):
        m = mech.replace(**dict(zip(PARAMS, theta[:-1])))
        tq = None if torque is None else cj.HarmonicLoad(0.0, theta[-1], torque)
        sol = cj.simulate(m, 1.0, 0.0, ts, torque=tq, rtol=1e-8, atol=1e-10,
                          adjoint=adjoint)
        return jnp.stack([sol.phi, sol.dphi])

    def loss(theta, adjoint="reverse"):
        return jnp.sum(weights * traj(theta, adjoint))

    return theta0, weights, traj, loss


def _forward_gradient(theta0, weights, traj):
    jac = jax.jit(jax.jacfwd(lambda th: traj(th, "direct")))(theta0)  # (2, n, P)
    return jnp.einsum("cn,cnp->p", weights, jac)


def _close(g, ref, tol=1e-8):
    # Relative to the largest component (the components span five orders of magnitude).
    # Exact to rounding (measured 3e-12) when both programs take the same steps; but the
    # grad's forward pass (the solve with its log) and jacfwd's solve are two programs that
    # XLA rounds differently, and a step whose error estimate sits at the acceptance edge
    # can go either way in them (measured 4e-9 on this problem, 2026-11-26): the
    # tolerance allows that, no more (an error of the adjoint itself is O(1)).
    np.testing.assert_allclose(g, ref, rtol=tol, atol=tol * float(jnp.max(jnp.abs(ref))))


# Each gradient compiles a backward pass (~30 s of CPU under XLA's defaults): the lab
# rig's (with a batch under `vmap`) runs in the quick suite, the others are slow.
@pytest.mark.parametrize("torque", [None, pytest.param(1.3, marks=pytest.mark.slow)],
                         ids=["lab-rig", "torque-load"])
def test_reverse_mode_is_the_transposed_forward_jacobian(torque):
    theta0, weights, traj, loss = _problem(torque)
    grad = jax.jit(jax.grad(loss))
    g = grad(theta0)
    _close(g, _forward_gradient(theta0, weights, traj))
    if torque is not None:
        assert abs(float(g[-1])) > 0  # the torque's amplitude has its own derivative
        return
    # A batch of gradients under `jax.vmap`: each member's its own, as computed alone.
    thetas = jnp.stack([theta0, theta0.at[8].mul(3.0), theta0.at[9].mul(50.0)])
    batch = jax.jit(jax.vmap(jax.grad(loss)))(thetas)
    for i in range(3):
        _close(batch[i], grad(thetas[i]), tol=1e-8)


@pytest.mark.slow
def test_a_solve_longer_than_the_log_reruns_its_segments(monkeypatch):
    # A log of 64 steps: the backward pass takes the last segment from the forward pass
    # and reruns the forward solve for each earlier one, with the same result.
    monkeypatch.setattr(adjoint, "LOG_ROWS", 64)
    theta0, weights, traj, loss = _problem(t1=1.0, samples=11)
    grad = jax.jit(jax.grad(loss))  # one program for every single gradient below
    g = grad(theta0)
    steps = cj.simulate(cj.load_scene("lab-rig").mech.replace(c=1e-3), 1.0, 0.0,
                        jnp.linspace(0.0, 1.0, 11), rtol=1e-8, atol=1e-10).num_steps
    assert int(steps) > 2 * 64  # at least three segments
    _close(g, _forward_gradient(theta0, weights, traj))
    # A batch of gradients whose members need different numbers of segments (a stiffer
    # spring takes more steps): each member's its own, as computed alone.
    thetas = jnp.stack([theta0, theta0.at[8].mul(4.0)])
    batch = jax.jit(jax.vmap(jax.grad(loss)))(thetas)
    for i in range(2):
        _close(batch[i], grad(thetas[i]), tol=1e-8)


@pytest.mark.parametrize("backward", ["loop", "blocks"], ids=["step-by-step", "blocks"])
def test_both_backward_programs_trace(backward):
    # The fast tier's check of both backward programs: traced, not compiled (a compile
    # of the step-by-step program under XLA's defaults takes ~45 s; the slow tests below
    # compare their numbers with forward mode). The CLI's program is "loop" (it sets the
    # CPU flags), which no fast test ran: a renamed attribute in it (`erk.numstages`,
    # 2026-11-28, while the blocks' adjoint moved to its own module) passed the fast and
    # the full tier and failed every gradient taken with the flags.
    theta0, _, _, loss = _problem(t1=0.2, samples=3)
    jaxpr = jax.make_jaxpr(jax.grad(lambda th: loss(th, DiscreteAdjoint(backward))))(theta0)
    # One float64 cotangent per parameter.
    assert [(a.shape, a.dtype) for a in jaxpr.out_avals] == [(theta0.shape, theta0.dtype)]


@pytest.mark.slow
@pytest.mark.parametrize("backward", ["loop", "blocks"], ids=["step-by-step", "blocks"])
def test_both_backward_programs_give_the_forward_jacobian(backward):
    # The backward pass is one of two programs (`DiscreteAdjoint.backward`, which the
    # edges choose from the CPU flags): the step-by-step VJP of the step and the
    # vectorised blocks' hand-written adjoint of the stages must both give the
    # forward-mode Jacobian.
    theta0, weights, traj, loss = _problem(t1=1.0, samples=11)
    g = jax.jit(jax.grad(lambda th: loss(th, DiscreteAdjoint(backward))))(theta0)
    _close(g, _forward_gradient(theta0, weights, traj))


@pytest.mark.slow
@pytest.mark.parametrize("rows,torque", [(50, None), (4096, 1.3)], ids=["short-log", "load"])
def test_the_deferred_parameter_pass(monkeypatch, rows, torque):
    # With the CPU flags' program (adjoint._deferred) the parameters' cotangents come
    # from the stage points after each block's loop, in chunks of points: a log of 50
    # rows (blocks of 50 steps, 700 stage points, not a multiple of the 64-point chunk;
    # several segments rerun), and a torque whose amplitude is a parameter of the field's
    # time-dependent part: the forward-mode gradient still (measured 9e-16 and 3e-16).
    monkeypatch.setattr(adjoint, "LOG_ROWS", rows)
    theta0, weights, traj, loss = _problem(torque=torque, t1=1.0, samples=11)
    g = jax.jit(jax.grad(lambda th: loss(th, DiscreteAdjoint("loop"))))(theta0)
    _close(g, _forward_gradient(theta0, weights, traj))


@pytest.mark.slow
@pytest.mark.parametrize("backward", ["loop", "blocks"], ids=["step-by-step", "blocks"])
def test_a_solve_longer_than_the_log_with_a_load(monkeypatch, backward):
    # A harmonic torque whose amplitude is a parameter, over a log of 50 steps (three
    # segments, two rerun): the forward-mode gradient (measured 7e-16, 1.7e-15; 3.9e-5 and
    # 3e-4 before the forward pass's barrier, its reruns then taking other steps).
    # Cleared caches: no program traced by an earlier test (this one passed so).
    jax.clear_caches()
    monkeypatch.setattr(adjoint, "LOG_ROWS", 50)
    theta0, weights, traj, loss = _problem(torque=1.3, t1=1.0, samples=11)
    g = jax.jit(jax.grad(lambda th: loss(th, DiscreteAdjoint(backward))))(theta0)
    _close(g, _forward_gradient(theta0, weights, traj))


@pytest.mark.slow
def test_a_rerun_that_takes_other_steps_is_an_error(monkeypatch):
    # The backward pass checks that each rerun segment joins the next bit for bit: a
    # rerun with another tolerance (other steps) fails loudly, not with a wrong gradient.
    jax.clear_caches()
    monkeypatch.setattr(adjoint, "LOG_ROWS", 64)
    real = adjoint.forward

    def skewed(field, y0, ts, rtol, atol, *, upto=None, **kw):
        return real(field, y0, ts, rtol if upto is None else 2 * rtol, atol, upto=upto, **kw)

    monkeypatch.setattr(adjoint, "forward", skewed)
    theta0, _, _, loss = _problem(t1=1.0, samples=11)
    with pytest.raises(Exception, match="did not take the forward pass's steps"):
        jax.block_until_ready(jax.jit(jax.grad(loss))(theta0))


def test_the_pending_steps_reach_their_ring_rows():
    # The step loop's buffer of P steps goes to ring rows count % S, ... by two in-place
    # writes (the second for the steps that wrap to row 0), none from `upto` on, and the
    # rows that get no step keep theirs: against the rows written one by one. Step `upto`
    # goes to the mark.
    S, P, N = 5, 3, 2
    rng = np.random.default_rng(0)
    flush = jax.jit(steplog.flush)
    for count in range(0, 12):
        for n in range(P + 1):
            for upto in (count, count + 1, count + P, 100):
                rows = rng.normal(size=(S + P, 3 + N))
                cols = rng.normal(size=(P, 3 + N))
                p = steplog.Pending((*(jnp.asarray(cols[:, i]) for i in range(3)),
                                     jnp.asarray(cols[:, 3:])), jnp.asarray(n, jnp.int32))
                mark = rng.normal(size=3 + N)
                log = steplog.Log(jnp.asarray(rows), jnp.asarray(count, jnp.int32),
                                  jnp.asarray(upto, jnp.int32), jnp.asarray(mark))
                out, empty = flush(log, p)
                ref = rows.copy()
                for j in range(n):
                    if count + j < upto:
                        ref[(count + j) % S] = cols[j]
                np.testing.assert_array_equal(np.asarray(out.rows)[:S], ref[:S])
                assert int(out.count) == count + n and int(empty.n) == 0
                # Step `upto`, the first not written, is the mark, if it is pending.
                j = upto - count
                np.testing.assert_array_equal(out.mark, cols[j] if 0 <= j < n else mark)


class _Forced(eqx.Module):
    """A damped oscillator under a harmonic load (y = (x, v)): a small field with a
    time-dependent term whose parameters are arrays."""

    k: jax.Array
    load: cj.HarmonicLoad

    def __call__(self, t, y, args):
        return jnp.stack([y[1], -self.k * y[0] - 0.1 * y[1] + self.load(t)])


def test_a_rerun_takes_the_forward_pass_steps(monkeypatch):
    # The backward pass reruns the forward solve for each earlier segment of the log, with
    # the field's leaves, the save times and tolerances as run-time values (its residuals);
    # the forward pass under `jit(grad)` saw those it does not differentiate as constants
    # that XLA folds. Both must take the same steps bit for bit (a harmonic force's were
    # not: the gradient 4e-5 off, 2026-11-28). Cleared caches: no program from before.
    jax.clear_caches()
    S = 32  # at least steplog.PENDING
    field = _Forced(jnp.asarray(400.0), cj.HarmonicLoad(0.0, 1.3, 1.7))
    y0, ts = jnp.array([1.0, 0.0]), jnp.linspace(0.0, 10.0, 11)
    tol = jnp.asarray(1e-8), jnp.asarray(1e-10)
    # The forward pass, everything a constant, its every step logged.
    _, _, _, full = jax.jit(lambda: adjoint.forward(field, y0, ts, *tol, max_steps=4096))()
    count = int(full.count)
    assert count > 3 * S  # several segments
    monkeypatch.setattr(adjoint, "LOG_ROWS", S)

    @jax.jit
    def rerun(field, y0, ts, rtol, atol, m):
        return adjoint.forward(field, y0, ts, rtol, atol, max_steps=4096, upto=(m + 1) * S)[3]

    for m in range(count // S):
        log = rerun(field, y0, ts, *tol, m)
        assert int(log.count) == count
        np.testing.assert_array_equal(log.rows[:S], full.rows[m * S:(m + 1) * S])
        np.testing.assert_array_equal(log.mark, full.rows[(m + 1) * S])


def test_a_python_number_is_differentiated_as_an_array_is():
    # `jax.grad(f)(2.0)` hands custom rules a literal, not an array: the discrete
    # adjoint's backward pass took it for a constant and returned a gradient of 0.0
    # (exit 0), and forward mode's variational solve raised an AttributeError.
    from crank_jax.solve import solve, solver_named

    ts = jnp.linspace(0.0, 2.0, 21)
    y0 = (jnp.asarray(1.0), jnp.asarray(0.0))
    solver = solver_named("dopri8-adaptive")

    def osc(t, y, w):
        return (y[1], -w**2 * y[0])

    def loss(w, mode):
        return jnp.sum(solve(osc, solver, ts, y0, w, adjoint=mode).ys[0] * jnp.sin(ts))

    for mode, derivative in (("reverse", jax.grad), ("forward", jax.jacfwd)):
        want = derivative(loss)(jnp.asarray(2.0), mode)
        assert abs(float(want)) > 1.0
        assert derivative(loss)(2.0, mode) == want, mode

    def from_state(v):  # a number in the initial state
        return jnp.sum(solve(osc, solver, ts, (jnp.asarray(1.0), v), 2.0).ys[0])

    assert jax.grad(from_state)(0.5) == jax.grad(from_state)(jnp.asarray(0.5)) != 0.0
