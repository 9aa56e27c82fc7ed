"""The "dopri8-adaptive" solver (the default): accuracy against a tight reference on the
presets, the solver policy, lockstep batches under `jax.vmap`, autodiff in every mode and
through vmap, no retracing, failures."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.solve.names import name_of


def _reference(mech, ts, phi0=1.0, dphi0=0.0, **kw):
    # The default max_steps: the same compiled program as other dopri8 calls (compiling
    # dominates these tests' time on 2 cores).
    return np.asarray(cj.simulate(mech, phi0, dphi0, ts, solver="dopri8", rtol=1e-13,
                                  atol=1e-15, **kw).phi)


@pytest.mark.parametrize("name", [
    "lab-rig",
    # ~40 s each on 2 cores: run with -m slow.
    pytest.param("torsional", marks=pytest.mark.slow),
    pytest.param("near-buckling", marks=pytest.mark.slow),
    pytest.param("pendulum", marks=pytest.mark.slow),
])
def test_presets_as_accurate_as_diffrax_dopri8(name):
    # The method and the error control are diffrax's Dopri8 with its PIDController (local
    # error per step, RMS over the state): at the same tolerances the global error must be
    # no worse than diffrax's own, against a tight reference, and within the tolerance's
    # order on the lab rig (measured 1.7x rtol at 1e-8).
    scene = cj.load_scene(name)
    ts = scene.ts()
    ref = np.asarray(scene.simulate(ts, solver="dopri8", rtol=1e-13, atol=1e-15).phi)
    for rtol in (1e-9,):
        kw = dict(rtol=rtol, atol=rtol * 1e-2)
        ours = np.max(np.abs(np.asarray(scene.simulate(ts, solver="dopri8-adaptive",
                                                        **kw).phi) - ref))
        theirs = np.max(np.abs(np.asarray(scene.simulate(ts, solver="dopri8", **kw).phi)
                               - ref))
        assert ours <= 2 * theirs + 1e-13, (name, rtol, ours, theirs)
        if name == "lab-rig":
            assert ours <= 10 * rtol, (rtol, ours)


def test_policy_picks_adaptive_except_stiff_or_sampled(lab_rig):
    ts = lab_rig.ts()
    mech = lab_rig.mech
    assert name_of(cj.solve.resolve_solver("auto", mech, 1e-8, ts=ts)) == "dopri8-adaptive"
    uneven = jnp.concatenate([ts[:10], ts[10::2]])
    assert name_of(cj.solve.resolve_solver("auto", mech, 1e-8, ts=uneven)) == "dopri8-adaptive"
    # Traced parameters and Coulomb friction too.
    friction = mech.replace(T_c=0.004)
    assert name_of(cj.solve.resolve_solver("auto", friction, 1e-8, ts=ts)) == "dopri8-adaptive"
    sampled = cj.SampledLoad(jnp.linspace(0, 10, 11), jnp.zeros(11))
    assert name_of(cj.solve.resolve_solver("auto", mech, 1e-8, load=sampled, ts=ts)) == "dopri8"
    assert name_of(cj.solve.resolve_solver("auto", mech.replace(k=1e8, c=50.0), 1e-8,
                                     ts=ts)) == "kvaerno5"
    # The default run is that solver, on an uneven grid too.
    a, b = lab_rig.simulate(uneven), lab_rig.simulate(uneven, solver="dopri8-adaptive")
    assert int(a.num_steps) == int(b.num_steps)
    np.testing.assert_array_equal(a.phi, b.phi)


def test_coulomb_friction_and_failures(lab_rig):
    ts = jnp.linspace(0, 5, 501)
    mech = lab_rig.mech.replace(T_c=0.004)
    traj = cj.simulate(mech, 1.0, 0.0, ts)
    np.testing.assert_allclose(traj.phi, _reference(mech, ts), rtol=0, atol=1e-6)
    bad = cj.simulate(mech, 1.0, 0.0, ts, max_steps=50, throw=False)
    assert not bool(bad.ok) and int(bad.num_steps) <= 64
    assert np.all(np.isfinite(bad.phi))
    with pytest.raises(eqx.EquinoxRuntimeError, match="steps"):
        cj.simulate(mech, 1.0, 0.0, ts, max_steps=50)


def test_vmap_steps_in_lockstep(lab_rig):
    # One loop for the batch, but each member with its own steps: its step count is what
    # it takes alone, or a few more where its steps are cut at the end of the save window
    # that the slowest member holds back.
    ts = jnp.linspace(0, 3, 301)
    ks = jnp.array([1.5, 2.0, 3.0])
    phis = jnp.array([0.5, 1.0, -1.0])
    mech = lab_rig.mech
    out = jax.jit(jax.vmap(lambda k, p: cj.simulate(mech.replace(k=k), p, 0.0, ts).phi))(
        ks, phis)
    steps = jax.vmap(lambda k: cj.simulate(mech.replace(k=k), 1.0, 0.0, ts).num_steps)(ks)
    alone = [int(cj.simulate(mech.replace(k=k), 1.0, 0.0, ts).num_steps) for k in ks]
    assert np.all(np.asarray(steps) >= 0.99 * np.array(alone))
    assert np.all(np.asarray(steps) <= 1.25 * np.array(alone))
    for i in range(3):
        ref = _reference(mech.replace(k=ks[i]), ts, phis[i])
        np.testing.assert_allclose(out[i], ref, rtol=0, atol=1e-7)


def _grouped(lab_rig, monkeypatch):
    from crank_jax.solve import lockstep

    monkeypatch.setattr(lockstep, "CHUNK", 2)
    ts = jnp.linspace(0, 3, 301)
    ks = jnp.array([1.5, 2.0, 3.0, 2.5, 8.0])
    rtols = jnp.array([1e-10, 1e-10, 1e-8, 1e-8, 1e-10])

    def one(k, rtol, adjoint="reverse"):
        sol = cj.simulate(lab_rig.mech.replace(k=k), 1.0, 0.0, ts, rtol=rtol,
                          atol=rtol * 1e-2, adjoint=adjoint)
        return sol.phi, sol.num_steps

    return ts, ks, rtols, one


def test_a_large_batch_steps_in_groups(lab_rig, monkeypatch):
    # On the CPU a batch larger than lockstep.CHUNK steps in groups of that many members,
    # one group after another; the last group is padded. Groups of 2 here, for 5
    # members with their own tolerances: every member as accurate as alone, and its step
    # count its own (the padding copies change nothing).
    ts, ks, rtols, one = _grouped(lab_rig, monkeypatch)
    phi, steps = jax.jit(jax.vmap(one))(ks, rtols)
    assert len(set(np.asarray(steps).tolist())) == 5
    for i in range(5):
        np.testing.assert_allclose(phi[i], _reference(lab_rig.mech.replace(k=ks[i]), ts),
                                   rtol=0, atol=2e3 * float(rtols[i]))


@pytest.mark.slow  # ~25 s of compiling
def test_forward_mode_through_groups(lab_rig, monkeypatch):
    _, ks, rtols, one = _grouped(lab_rig, monkeypatch)
    final = jax.jit(jax.vmap(lambda k, r: one(k, r, "forward")[0][-1]))
    jac = jax.jit(jax.jacfwd(final))(ks, rtols)
    assert np.count_nonzero(np.asarray(jac) - np.diag(np.diag(jac))) == 0
    eps = 1e-6
    fd = (final(ks + eps, rtols) - final(ks - eps, rtols)) / (2 * eps)
    np.testing.assert_allclose(np.diag(jac), fd, rtol=1e-4)


def test_vmap_with_save_times_per_member(lab_rig, monkeypatch):
    # Members with their own save times (other spans, starts and spacings, one jittered,
    # as multiple shooting's segments and sampled records have them) step in lockstep
    # too, each writing its own samples; groups of 2 here (lockstep.CHUNK), so the times
    # are split with the members. Each as accurate as alone.
    from crank_jax.solve import lockstep

    monkeypatch.setattr(lockstep, "CHUNK", 2)
    seen = []
    inner = lockstep._lockstep
    monkeypatch.setattr(lockstep, "_lockstep", lambda *a: seen.append(a) or inner(*a))
    ts = np.linspace(0, 3, 301)
    jitter = np.random.default_rng(0).uniform(-2e-3, 2e-3, ts.size)
    tss = jnp.asarray(np.stack([ts, 0.5 + ts * 1.1, ts * 0.9, ts + jitter * (ts > 0)]))
    ks = jnp.array([1.5, 2.0, 3.0, 2.5])
    mech = lab_rig.mech
    out = jax.jit(jax.vmap(lambda k, t: cj.simulate(mech.replace(k=k), 1.0, 0.0, t).phi))(
        ks, tss)
    assert seen, "per-member save times should step in lockstep, not a plain vmap"
    for i in range(4):
        ref = _reference(mech.replace(k=ks[i]), tss[i] - tss[i, 0])
        np.testing.assert_allclose(out[i], ref, rtol=0, atol=1e-7)


def test_gradients_in_every_mode(lab_rig):
    ts = jnp.linspace(0.0, 2.0, 201)
    mech = lab_rig.mech

    def final(k, adjoint="reverse", solver="auto"):
        return cj.simulate(mech.replace(k=k), 1.0, 0.0, ts, adjoint=adjoint,
                           solver=solver, rtol=1e-10, atol=1e-12).phi[-1]

    k0, eps = 2.0, 1e-5
    fd = (final(k0 + eps, solver="dopri8") - final(k0 - eps, solver="dopri8")) / (2 * eps)
    g_rev = jax.grad(final)(k0)
    g_fwd = jax.jacfwd(lambda k: final(k, "forward"))(k0)
    np.testing.assert_allclose(g_rev, fd, rtol=1e-6)
    np.testing.assert_allclose(g_fwd, fd, rtol=1e-6)


@pytest.mark.slow
def test_gradients_through_vmap(lab_rig):
    # grad of a vmap (the lockstep batch), vmap of grad and of jacfwd (JAX differentiates
    # first, then batches through the custom_vmap's JVP rule), jacfwd of a vmap: ~2 min of
    # compiling on 2 cores.
    ts = jnp.linspace(0.0, 2.0, 201)

    def final(k, adjoint="reverse"):
        return cj.simulate(lab_rig.mech.replace(k=k), 1.0, 0.0, ts, adjoint=adjoint,
                           rtol=1e-10, atol=1e-12).phi[-1]

    ks = jnp.array([1.8, 2.0, 2.2])
    g1 = jax.grad(lambda ks: jnp.sum(jax.vmap(final)(ks)))(ks)
    g3 = jnp.diag(jax.jacfwd(jax.vmap(lambda k: final(k, "forward")))(ks))
    np.testing.assert_allclose(g3, g1, rtol=1e-6)
    np.testing.assert_allclose(jax.vmap(jax.grad(final))(ks), g1, rtol=1e-6)
    np.testing.assert_allclose(jax.vmap(jax.jacfwd(lambda k: final(k, "forward")))(ks), g1,
                               rtol=1e-6)


def test_new_values_do_not_retrace(lab_rig):
    ts = jnp.linspace(0, 1, 101)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(mech, phi0):
        return cj.simulate(mech, phi0, 0.0, ts).phi

    run(lab_rig.mech, jnp.array(1.0))
    run(lab_rig.mech.replace(k=3.0, c=0.01), jnp.array(0.5))


@pytest.mark.parametrize("mode", ["reverse", "forward"])
def test_repeats_of_the_last_save_time_take_its_value_and_its_derivative(mode):
    # A fit pads its rows with repeats of the last save time: the solve stops at the first
    # and gives the repeats its value, with no step of their own; each derivative sends a
    # repeat's share to the first (reverse mode: the discrete adjoint sees only the rows
    # the step loop wrote, so a repeat's cotangent was lost until the copy moved outside
    # the solve's derivative rules).
    from crank_jax.solve import solve, solver_named

    def field(t, y, a):
        return jnp.stack([y[1], -a[0] * jnp.sin(y[0]) - a[1] * y[1]])

    solver, y0, a = solver_named("dopri8-adaptive"), jnp.array([1.0, 0.0]), jnp.array([4.0, 0.1])
    ts = jnp.linspace(0.0, 2.0, 21)
    padded = jnp.concatenate([ts, jnp.full(9, 2.0)])

    def run(t, a):
        return solve(field, solver, t, y0, a, adjoint=mode, checks=False)

    plain, rep = run(ts, a), run(padded, a)
    np.testing.assert_array_equal(np.asarray(rep.ys[:21]), np.asarray(plain.ys))
    np.testing.assert_array_equal(np.asarray(rep.ys[21:]),
                                  np.broadcast_to(np.asarray(plain.ys[-1]), (9, 2)))
    assert int(rep.num_steps) == int(plain.num_steps)
    d = jax.grad if mode == "reverse" else jax.jacfwd
    got = d(lambda a: jnp.sum(run(padded, a).ys[:, 0] ** 2))(a)
    want = d(lambda a: jnp.sum(run(ts, a).ys[:, 0] ** 2) + 9 * run(ts, a).ys[-1, 0] ** 2)(a)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-12)
