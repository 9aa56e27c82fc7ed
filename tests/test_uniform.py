"""The "dopri8-uniform" solver: its right-hand side, its accuracy against its tolerance on
the presets, autodiff in every adjoint mode and failures (by name: "auto" now picks
"dopri8-adaptive")."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.model.dynamics import Structure, acceleration


@pytest.mark.parametrize("loads", [False, True])
def test_crank_field_equals_acceleration(rng, loads):
    # The field the solvers step is the equation of motion: phi' = dphi, phi'' = a.
    from conftest import random_mech

    load = cj.HarmonicLoad(3.0, 2.0, 1.5, 0.3) if loads else cj.NoLoad()
    torque = cj.ConstantLoad(0.2) if loads else cj.NoLoad()
    phi = jnp.asarray(rng.uniform(-7, 7, 50))
    dphi = jnp.asarray(rng.uniform(-20, 20, 50))
    t = jnp.asarray(rng.uniform(0, 5, 50))
    for i in range(6):
        over = [{}, {"m_p": 0.0, "I_p": 0.0}, {"m_s": 0.0}, {"g": 0.0}, {"k": 0.0, "c": 0.0},
                {"m_p": 0.0, "I_p": 0.0, "m_s": 0.0}][i]
        mech = random_mech(rng, **over)
        st = Structure.of(mech)
        a = acceleration(mech, phi, dphi, t, load, torque, st)
        v, b = cj.model.CrankField(mech, load, torque, st)(t, (phi, dphi))
        np.testing.assert_array_equal(v, dphi)
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * float(jnp.max(jnp.abs(a))))


class _Oscillator(eqx.Module):
    # A damped linear oscillator on a dict state: nothing about a crank.
    omega: jax.Array
    zeta: jax.Array

    def __call__(self, t, y, args):
        return {"x": y["v"], "v": -(self.omega**2) * y["x"] - 2 * self.zeta * self.omega * y["v"]
                + args * jnp.cos(t)}


def _oscillator_exact(omega, zeta, F, x0, ts):
    # x'' + 2 zeta omega x' + omega^2 x = F cos t: particular + homogeneous solution.
    w2 = omega**2
    den = (w2 - 1.0) ** 2 + (2 * zeta * omega) ** 2
    A, B = F * (w2 - 1.0) / den, F * 2 * zeta * omega / den  # x_p = A cos t + B sin t
    wd = omega * jnp.sqrt(1 - zeta**2)
    c1 = x0 - A
    c2 = (0.0 - B + zeta * omega * c1) / wd
    env = jnp.exp(-zeta * omega * ts)
    return (env * (c1 * jnp.cos(wd * ts) + c2 * jnp.sin(wd * ts)) + A * jnp.cos(ts)
            + B * jnp.sin(ts))


def test_generic_solver_on_another_field():
    # The fused solver takes any vector field and pytree state: a forced, damped oscillator
    # on a dict state, against its closed form, values and forward sensitivities (to the
    # field's leaves, to `args` and to y0) against jacfwd of the closed form.
    from crank_jax.solve.uniform import solve_uniform

    ts = jnp.linspace(0.0, 5.0, 51)

    def solve(p):
        field = _Oscillator(p[0], p[1])
        ys, result, _ = solve_uniform(field, {"x": p[3], "v": jnp.zeros(())}, ts, 1e-10,
                                      1e-12, p[2], rate=p[0], max_steps=10**5, kind="lax")
        assert result == diffrax.RESULTS.successful
        return ys["x"]

    p = jnp.array([3.0, 0.1, 0.7, 1.2])
    exact = lambda p: _oscillator_exact(p[0], p[1], p[2], p[3], ts)  # noqa: E731
    np.testing.assert_allclose(solve(p), exact(p), atol=1e-9)
    np.testing.assert_allclose(jax.jacfwd(solve)(p), jax.jacfwd(exact)(p), atol=1e-8)


def test_the_solver_steps_with_the_method_it_holds():
    # UniformDopri8 holds its method (`erk`), whose init/step the passes drive: another
    # tableau (Tsit5, order 5) meets the tolerance on the oscillator with more steps than
    # Dopri8, and a field that is not a FusedERK is refused.
    from crank_jax.solve import solve
    from crank_jax.solve.erk import FusedERK

    ts = jnp.linspace(0.0, 5.0, 51)
    field = _Oscillator(jnp.asarray(3.0), jnp.asarray(0.1))
    y0 = {"x": jnp.asarray(1.2), "v": jnp.asarray(0.0)}
    exact = _oscillator_exact(3.0, 0.1, 0.7, 1.2, ts)
    steps = {}
    for name, solver in [("dopri8", cj.UniformDopri8()),
                         ("tsit5", cj.UniformDopri8(erk=FusedERK(diffrax.Tsit5.tableau, 5)))]:
        sol = solve(field, solver, ts, y0, jnp.asarray(0.7), rtol=1e-9, atol=1e-11,
                    rate=3.0, max_steps=10**5)
        np.testing.assert_allclose(sol.ys["x"], exact, atol=1e-7)
        steps[name] = int(sol.num_steps)
    assert steps["tsit5"] > 2 * steps["dopri8"], steps
    with pytest.raises(TypeError, match="FusedERK"):
        cj.UniformDopri8(erk="tsit5")


def test_no_solver_module_imports_the_mechanism():
    # Solvers know vector fields: only trajectory.py (which builds the CrankField and the
    # derived outputs) and policy.py (the stiffness test) import crank_jax.model.
    import ast
    from pathlib import Path

    solve_dir = Path(cj.__file__).parent / "solve"
    for path in solve_dir.glob("*.py"):
        if path.name in ("trajectory.py", "policy.py"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                mod = "." * node.level + (node.module or "")
                # model/trig.py is numerics, not the mechanism: how sin and cos are traced
                # (the field's and the solvers' batched steps choose it).
                if mod == "..model" and [a.name for a in node.names] == ["trig"]:
                    continue
                assert "model" not in mod, (path.name, mod)


def _reference(scene, ts):
    # Adaptive Dopri8 far tighter than any tolerance tested below.
    return np.asarray(scene.simulate(ts, solver="dopri8", rtol=1e-13, atol=1e-15,
                                     max_steps=10**6).phi)


@pytest.mark.parametrize("name", list(cj.presets()))
@pytest.mark.parametrize("rtol", [1e-6, 1e-9])
def test_error_meets_tolerance_on_presets(name, rtol):
    scene = cj.load_scene(name)
    ts = scene.ts()
    atol = rtol * 1e-2
    traj = scene.simulate(ts, solver="dopri8-uniform", rtol=rtol, atol=atol)
    assert bool(traj.ok)
    ref = _reference(scene, ts)
    err = np.max(np.abs(np.asarray(traj.phi) - ref))
    # The contract: the global error in phi is within the tolerance on its scale.
    assert err <= atol + rtol * np.max(np.abs(ref)), (name, rtol, err)


@pytest.mark.parametrize("adjoint", [
    # "dopri8-uniform" is no longer the default (by name and for sweeps, which do not
    # differentiate); its JVP also runs in CI through bench_gradients' smoke test.
    pytest.param("forward", marks=pytest.mark.slow),
    # Compiling the reverse passes of the nested loops takes ~20-40 s.
    pytest.param("reverse", marks=pytest.mark.slow),
    pytest.param("direct", marks=pytest.mark.slow),
])
def test_gradients(lab_rig, adjoint):
    ts = jnp.linspace(0.0, 2.0, 201)

    def final(k, adjoint):
        mech = lab_rig.mech.replace(k=k)
        return cj.simulate(mech, 1.0, 0.0, ts, solver="dopri8-uniform", rtol=1e-10,
                           atol=1e-12, adjoint=adjoint).phi[-1]

    k = lab_rig.mech.k
    h = 1e-5
    fd = (final(k + h, "forward") - final(k - h, "forward")) / (2 * h)
    g = (jax.jacfwd if adjoint == "forward" else jax.grad)(final)(k, adjoint)
    assert abs(float(g) - float(fd)) <= 1e-6 * abs(float(fd))


@pytest.mark.slow  # ~9 s; sweeps run this solver under vmap in test_sweep.py
def test_vmap_and_no_retrace(lab_rig):
    ts = jnp.linspace(0.0, 1.0, 101)
    ks = jnp.linspace(1.8, 2.2, 4)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def batch(ks, rtol):
        return jax.vmap(lambda k: cj.simulate(lab_rig.mech.replace(k=k), 1.0, 0.0, ts,
                                              solver="dopri8-uniform", rtol=rtol).phi)(ks)

    out = batch(ks, jnp.asarray(1e-8))
    batch(ks + 0.01, jnp.asarray(1e-9))
    for i, k in enumerate(ks):
        one = cj.simulate(lab_rig.mech.replace(k=k), 1.0, 0.0, ts, solver="dopri8-uniform")
        np.testing.assert_allclose(out[i], one.phi, atol=1e-9)


def test_step_budget(lab_rig):
    ts = lab_rig.ts()
    with pytest.raises(Exception, match="maximum number of solver steps"):
        lab_rig.simulate(ts, solver="dopri8-uniform", rtol=1e-12, max_steps=1000)
    traj = lab_rig.simulate(ts, solver="dopri8-uniform", rtol=1e-12, max_steps=1000,
                            throw=False)
    assert traj.result == diffrax.RESULTS.max_steps_reached
    assert np.all(np.isfinite(np.asarray(traj.phi)))


def test_steps_follow_the_tolerance_both_ways():
    # The torsional scene over 10 s at 100 samples/s: its 100 Hz mode decays within ~1 s.
    # The old one-m-for-the-span choice took 24 steps per interval at rtol 1e-4 (and 86 at
    # 1e-8); per-interval control drops to the stability floor once the motion has decayed.
    scene = cj.load_scene("torsional")
    ts = jnp.linspace(0.0, 10.0, 1001)
    steps = [int(scene.simulate(ts, solver="dopri8-uniform", rtol=r, atol=r * 1e-2).num_steps)
             for r in (1e-4, 1e-8, 1e-10)]
    assert steps[0] < steps[1] < steps[2], steps
    assert steps[0] <= 8 * 1000 and steps[1] <= 20 * 1000, steps


@pytest.mark.slow  # ~18 s, mostly compiling two Jacobians; test_gradients[forward] is fast
def test_jacobian_matches_diffrax_forward_mode(lab_rig):
    # JAX's forward mode through dopri8-uniform's loop (it has no rule of its own since
    # issue 26): compare with diffrax's Dopri8 differentiated step by step, far tighter,
    # for parameters, the initial angle and a load amplitude at once.
    ts = jnp.linspace(0.0, 2.0, 201)

    def phi(x, solver, rtol, adjoint="forward"):
        mech = lab_rig.mech.replace(k=x[0], c=x[1], m_s=x[2])
        return cj.simulate(mech, x[3], 0.0, ts, load=cj.HarmonicLoad(0.0, x[4], 3.0),
                           solver=solver, rtol=rtol, atol=rtol * 1e-2, adjoint=adjoint).phi

    m = lab_rig.mech
    x0 = jnp.array([float(m.k), float(m.c), float(m.m_s), 1.0, 2.0])
    J = np.asarray(jax.jacfwd(phi)(x0, "dopri8-uniform", 1e-9))
    ref = np.asarray(jax.jacfwd(phi)(x0, "dopri8", 1e-12))
    scale = np.max(np.abs(ref), axis=0)
    assert np.max(np.abs(J - ref) / scale) < 1e-7
    # Reverse mode through the checkpointed loop: the same derivative of the same steps.
    g = jax.grad(lambda x: phi(x, "dopri8-uniform", 1e-9, "reverse")[-1])(x0)
    np.testing.assert_allclose(np.asarray(g), J[-1], rtol=1e-10, atol=1e-14)
