"""Simulation: agreement with an independent integrator and implementation, energy
conservation, transformations (jit, vmap, grad, jacfwd) and no recompilation."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import cumulative_simpson, solve_ivp

import crank_jax as cj


def _numpy_rhs(v, P, tau):
    """The equation of motion transcribed independently in NumPy from DESIGN.md §1."""
    r, L, b, s = v["r"], v["L"], v["b"], v["s"]

    def rhs(t, y):
        phi, dphi = y
        sd = r / L * np.sin(phi)
        cd = np.sqrt(1 - sd**2)
        d1 = r / L * np.cos(phi) / cd
        d2 = r / L * (d1 * np.cos(phi) * sd - np.sin(phi) * cd) / cd**2
        lever = r * np.sin(phi) + L * d1 * sd
        M = (v["m_c"] * s**2 + v["I_c"]
             + v["m_p"] * (r**2 - 2 * r * b * d1 * np.cos(phi + np.arcsin(sd)) + b**2 * d1**2)
             + v["I_p"] * d1**2 + v["m_s"] * lever**2)
        K = (v["m_p"] * (r * b * (d1 * (1 + d1) * np.sin(phi + np.arcsin(sd))
                                  - d2 * np.cos(phi + np.arcsin(sd))) + b**2 * d1 * d2)
             + v["m_s"] * lever * (r * np.cos(phi) + L * (d2 * sd + d1**2 * cd))
             + v["I_p"] * d1 * d2)
        q = (v["g"] * (v["m_c"] * s * np.sin(phi) + v["m_p"] * (r * np.sin(phi) + b * d1 * sd)
                       + v["m_s"] * lever)
             + P(t) * lever - v["k"] * phi - v["c"] * dphi + tau(t))
        return [dphi, (q - K * dphi**2) / M]

    return rhs


@pytest.mark.parametrize("scene", ["lab-rig", "near-buckling", "pendulum"])
def test_matches_scipy_dop853_on_independent_equations(scene):
    sc = cj.load_scene(scene)
    load = cj.HarmonicLoad(1.0, 2.0, 3.0, 0.5)
    torque = cj.HarmonicLoad(0.0, 0.05, 4.0, 0.0)
    ts = np.linspace(0.5, 5.5, 501)  # starts at t != 0
    tr = cj.simulate(sc.mech, 1.0, 0.5, ts, load=load, torque=torque, solver="dopri8",
                     rtol=1e-12, atol=1e-14)
    rhs = _numpy_rhs(sc.mech.as_dict(), lambda t: 1.0 + 2.0 * np.sin(6 * np.pi * t + 0.5),
                     lambda t: 0.05 * np.sin(8 * np.pi * t))
    ref = solve_ivp(rhs,
                    (ts[0], ts[-1]), [1.0, 0.5], method="DOP853", t_eval=ts, rtol=1e-12,
                    atol=1e-14)
    assert ref.success
    np.testing.assert_allclose(tr.phi, ref.y[0], atol=1e-8, rtol=0)
    np.testing.assert_allclose(tr.dphi, ref.y[1], atol=1e-7, rtol=0)
    assert tr.ts[0] == ts[0] and tr.phi[0] == 1.0


@pytest.mark.parametrize("solver", ["tsit5", "dopri8", "kvaerno5", "auto"])
def test_every_solver_meets_its_tolerance(solver):
    sc = cj.load_scene("lab-rig")
    ts = np.linspace(0, 2, 201)
    ref = cj.simulate(sc.mech, 1.0, 0.0, ts, solver="dopri8", rtol=1e-13, atol=1e-15)
    tr = cj.simulate(sc.mech, 1.0, 0.0, ts, solver=solver, rtol=1e-8, atol=1e-10)
    err = np.max(np.abs(np.asarray(tr.phi - ref.phi)))
    assert err < 1e-6, err  # global error within ~100x of the local tolerance
    assert bool(tr.ok)


def test_energy_conserved_over_100_periods_without_damping():
    sc = cj.load_scene("lab-rig")
    mech = sc.mech.replace(c=0.0)
    period = 2 * np.pi / float(cj.linearize(mech).omega_n)
    ts = np.linspace(0, 100 * period, 2001)
    tr = cj.simulate(mech, 1.0, 0.0, ts, solver="dopri8", rtol=1e-13, atol=1e-15,
                     outputs=("energy",))
    E = np.asarray(tr.extras["energy"])
    drift = np.max(np.abs(E - E[0])) / np.abs(E[0])
    assert drift <= 1e-9, drift


def test_energy_balance_with_damping_and_loads():
    # d(T+V)/dt = power_in: integrate the power along the trajectory and compare.
    sc = cj.load_scene("lab-rig")
    load, torque = cj.HarmonicLoad(2.0, 3.0, 2.0, 0.0), cj.HarmonicLoad(0.1, 0.2, 5.0, 1.0)
    ts = np.linspace(0, 2, 4001)
    tr = cj.simulate(sc.mech, 0.8, 0.0, ts, load=load, torque=torque, solver="dopri8",
                     rtol=1e-12, atol=1e-14, outputs=("energy",))
    p = np.asarray(cj.model.nonconservative_power(sc.mech, tr.phi, tr.dphi, tr.ts, load, torque))
    # Simpson's rule (error ~ h^4): the trapezoid rule's h^2 error would swamp the check.
    work = cumulative_simpson(p, x=ts, initial=0.0)
    E = np.asarray(tr.extras["energy"])
    np.testing.assert_allclose(E - E[0], work, atol=2e-6)
    assert np.max(np.abs(E - E[0])) > 1e-2  # the balance is not trivially zero


def test_derived_outputs_only_when_asked_and_consistent():
    sc = cj.load_scene("lab-rig")
    ts = np.linspace(0, 1, 11)
    plain = cj.simulate(sc.mech, 1.0, 0.0, ts)
    assert plain.extras == {}
    full = cj.simulate(sc.mech, 1.0, 0.0, ts, outputs=("reactions", "energy", "slider", "delta",
                                                       "ddphi", "loads"))
    columns = cj.solve.output_columns(list(cj.solve.OUTPUTS))
    assert list(full.columns()) == ["t", "phi", "dphi", *columns]
    np.testing.assert_allclose(full.extras["energy"],
                               cj.model.energy(sc.mech, full.phi, full.dphi))
    kin = cj.model.kinematics(sc.mech, full.phi, full.dphi, full.extras["ddphi"])
    np.testing.assert_allclose(full.extras["x_s"], kin.x_s)
    np.testing.assert_allclose(full.phi, plain.phi, rtol=0, atol=0)
    with pytest.raises(ValueError, match="unknown output"):
        cj.simulate(sc.mech, 1.0, 0.0, ts, outputs=("bogus",))


def test_vmap_over_a_batch_of_mechanisms():
    sc = cj.load_scene("lab-rig")
    ks = jnp.array([1.5, 2.0, 3.0])
    batch = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (3,)), sc.mech)
    batch = eqx.tree_at(lambda m: m.k, batch, ks)
    ts = jnp.linspace(0, 1, 51)
    phi = jax.vmap(lambda m: cj.simulate(m, 1.0, 0.0, ts).phi)(batch)
    for i, k in enumerate(ks):
        # "auto" is "dopri8-adaptive", whose vmap steps the batch in lockstep (one step
        # size for all, see solve/lockstep.py): each member meets the default rtol 1e-8
        # against a tight reference, as a single solve does.
        ref = cj.simulate(sc.mech.replace(k=k), 1.0, 0.0, ts, solver="dopri8", rtol=1e-13,
                          atol=1e-15)
        one = cj.simulate(sc.mech.replace(k=k), 1.0, 0.0, ts)
        np.testing.assert_allclose(phi[i], ref.phi, rtol=0, atol=1e-7)
        np.testing.assert_allclose(one.phi, ref.phi, rtol=0, atol=1e-7)


def test_mechanism_built_from_traced_values_inside_vmap():
    base = cj.load_scene("lab-rig").mech.as_dict()
    ts = jnp.linspace(0, 0.5, 11)

    def run(k):
        return cj.simulate(cj.SliderCrank(**{**base, "k": k}), 1.0, 0.0, ts).phi[-1]

    out = jax.jit(jax.vmap(run))(jnp.array([2.0, 2.5]))
    assert out.shape == (2,) and np.all(np.isfinite(out))


# ~55 s of compiling on 2 cores, kept out of the CI budget (run with -m slow). In CI the
# same derivatives are checked elsewhere: the default solver's reverse mode against its
# forward mode (test_adjoint.py) and finite differences (test_adaptive.py), and forward
# mode through it feeds test_stress_gradients.py.
@pytest.mark.slow
def test_grad_and_jacfwd_match_finite_differences():
    sc = cj.load_scene("lab-rig")
    ts = jnp.linspace(0, 1.0, 21)

    def loss(k, c, adjoint):
        tr = cj.simulate(sc.mech.replace(k=k, c=c), 1.0, 0.0, ts, solver="dopri8",
                         rtol=1e-12, atol=1e-14, adjoint=adjoint)
        return jnp.sum(tr.phi**2)

    g_rev = jax.grad(loss, argnums=(0, 1))(2.0, 0.01, "reverse")
    g_fwd = jax.jacfwd(loss, argnums=(0, 1))(2.0, 0.01, "forward")
    h = 1e-6
    fd_k = (loss(2.0 + h, 0.01, "reverse") - loss(2.0 - h, 0.01, "reverse")) / (2 * h)
    fd_c = (loss(2.0, 0.01 + h, "reverse") - loss(2.0, 0.01 - h, "reverse")) / (2 * h)
    np.testing.assert_allclose(g_rev, [fd_k, fd_c], rtol=1e-5)
    np.testing.assert_allclose(g_fwd, g_rev, rtol=1e-6)


class _CountingTorque(cj.AbstractLoad):
    """A zero torque that counts how often the vector field is traced (Python runs
    `__call__` only while tracing)."""

    value: jax.Array

    def __call__(self, t):
        _TRACES.append(1)
        return self.value * t

    def mean(self):
        return self.value


_TRACES: list = []


def test_no_recompilation_when_only_values_change():
    # Count traces of the vector field: a new value must reuse the compiled solve.
    _TRACES.clear()
    torque = _CountingTorque(jnp.asarray(0.0))
    mech = cj.load_scene("lab-rig").mech
    ts = jnp.linspace(0, 0.3, 7)
    cj.simulate(mech.replace(k=2.1), 0.9, 0.0, ts, torque=torque, solver="tsit5", rtol=1e-7)
    n = len(_TRACES)
    assert n > 0
    for k, phi0, rtol in [(2.2, 0.5, 1e-6), (3.0, 1.2, 1e-9), (2.05, -0.3, 1e-5)]:
        cj.simulate(mech.replace(k=k, c=0.02), phi0, 0.1, ts, torque=torque, solver="tsit5",
                    rtol=rtol)
    assert len(_TRACES) == n


def test_user_level_jit_traces_once():
    mech = cj.load_scene("lab-rig").mech
    ts = jnp.linspace(0, 0.3, 7)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def final_angle(m, phi0):
        return cj.simulate(m, phi0, 0.0, ts).phi[-1]

    for k in (2.0, 2.5, 3.0):
        final_angle(mech.replace(k=k), jnp.asarray(0.5 + k / 10))


def test_failed_solve_reports_instead_of_nan():
    sc = cj.load_scene("lab-rig")
    ts = jnp.linspace(0, 10, 11)
    tr = cj.simulate(sc.mech, 1.0, 0.0, ts, solver="tsit5", max_steps=10, throw=False)
    assert not bool(tr.ok)
    with pytest.raises(Exception, match="max_steps|maximum number of solver steps"):
        cj.simulate(sc.mech, 1.0, 0.0, ts, solver="tsit5", max_steps=10)


def test_bad_time_grid_rejected():
    mech = cj.load_scene("lab-rig").mech
    with pytest.raises(ValueError, match="increase strictly"):
        cj.simulate(mech, 1.0, 0.0, [0.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="at least 2"):
        cj.simulate(mech, 1.0, 0.0, [0.0])
    with pytest.raises(ValueError, match="unknown solver"):
        cj.simulate(mech, 1.0, 0.0, [0.0, 1.0], solver="euler")


@pytest.mark.parametrize("kw,match", [
    ({"rtol": 0.0}, "rtol must be a finite number >= 1e-15"),
    ({"rtol": float("nan")}, "rtol must be a finite number >= 1e-15"),
    ({"rtol": 1e-300}, "rtol must be a finite number >= 1e-15"),
    ({"atol": -1e-9}, "atol must be a finite number > 0"),
    ({"atol": float("inf")}, "atol must be a finite number > 0"),
    ({"atol": 0.0}, "atol must be a finite number > 0"),
])
def test_bad_tolerances_rejected_naming_the_argument(kw, match):
    mech = cj.load_scene("lab-rig").mech
    with pytest.raises(ValueError, match=match):
        cj.simulate(mech, 1.0, 0.0, [0.0, 1.0], **kw)


def test_batched_mechanism_outside_vmap_rejected():
    mech = cj.load_scene("lab-rig").mech
    with pytest.raises(ValueError, match=r"SliderCrank\.k has shape \(2,\).*jax\.vmap"):
        cj.simulate(mech.replace(k=jnp.array([1.0, 2.0])), 1.0, 0.0, [0.0, 1.0])
    with pytest.raises(ValueError, match=r"phi0 has shape \(2,\).*jax\.vmap"):
        cj.simulate(mech, jnp.array([1.0, 2.0]), 0.0, [0.0, 1.0])


@pytest.mark.parametrize("over", [
    {"k": 1e300},
    {"m_c": 1e-300, "m_p": 1e-300, "m_s": 1e-300, "I_c": 1e-300, "I_p": 1e-300},
])
def test_absurd_scales_named_with_a_fix(over):
    # Rows 12-13 of issue 10: one line naming the rate the values imply and what to check,
    # not "increase max_steps"; and no overflow RuntimeWarning from the solver chooser
    # (pytest turns warnings into errors).
    mech = cj.load_scene("lab-rig").mech.replace(**over)
    with pytest.raises(ValueError, match="fastest mode .* rad/s .* check the units") as e:
        cj.simulate(mech, 1.0, 0.0, jnp.linspace(0.0, 1.0, 11))
    assert "\n" not in str(e.value) and "max_steps" in str(e.value)
    assert "increase" not in str(e.value).lower()


def test_nan_parameter_inside_jit_names_the_parameter():
    # Inside jit the values are traced: the check runs in the program (eqx.error_if) and
    # its message names the field, under eqx.filter_jit and (inside JAX's callback error)
    # under jax.jit.
    mech = cj.load_scene("lab-rig").mech
    ts = jnp.linspace(0.0, 1.0, 11)

    def final(k):
        return cj.simulate(mech.replace(k=k), 1.0, 0.0, ts).phi[-1]

    with pytest.raises(eqx.EquinoxRuntimeError, match="SliderCrank.k is invalid"):
        eqx.filter_jit(final)(jnp.asarray(jnp.nan))
    with pytest.raises(Exception, match="SliderCrank.k is invalid"):
        jax.jit(final)(jnp.asarray(jnp.nan))


def test_gradient_with_respect_to_load_amplitudes():
    sc = cj.load_scene("lab-rig")
    ts = jnp.linspace(0, 1.0, 11)

    def final(amps):
        torque = cj.HarmonicLoad(amps[0], amps[1], 3.0, 0.2)
        load = cj.SampledLoad(jnp.array([0.0, 0.5, 1.0]), amps[2] * jnp.array([1.0, -1.0, 2.0]))
        tr = cj.simulate(sc.mech, 0.5, 0.0, ts, load=load, torque=torque, solver="dopri8",
                         rtol=1e-12, atol=1e-14)
        return tr.phi[-1]

    x = jnp.array([0.05, 0.1, 2.0])
    g = jax.grad(final)(x)
    h = 1e-6
    fd = [(final(x.at[i].add(h)) - final(x.at[i].add(-h))) / (2 * h) for i in range(3)]
    np.testing.assert_allclose(g, fd, rtol=1e-5)
    assert np.all(np.abs(g) > 1e-4)


def test_repeated_concrete_calls_reuse_the_host_plan_and_still_check(lab_rig, monkeypatch):
    # A concrete call keeps its host plan (checks, linearisation, solver) for calls with
    # the same mechanism, loads, save times and tolerances (the front door's memo of the
    # core's `host_plan`, crank_jax/simulation.py).
    # The plan must follow any change of those, and the checks that depend on the initial
    # state or on invalid parameters must still raise every time.
    import sys

    front = sys.modules["crank_jax.simulation"]
    calls = []
    real = front.linearize
    monkeypatch.setattr(front, "linearize", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(front, "_PLANS", type(front._PLANS)(front._PLANS.kept))
    ts = jnp.linspace(0.0, 1.0, 51)
    mech = lab_rig.mech
    a = cj.simulate(mech, 0.5, 0.0, ts)
    b = cj.simulate(mech, 0.3, 0.1, ts)  # another initial state: the same plan
    assert len(calls) == 1
    ref = cj.simulate(mech, 0.3, 0.1, jnp.linspace(0.0, 1.0, 51))  # new save times: new plan
    assert len(calls) == 2
    np.testing.assert_array_equal(b.phi, ref.phi)
    assert not np.array_equal(a.phi, b.phi)
    stiffer = mech.replace(k=3.0)  # a new value: a new plan
    s = cj.simulate(stiffer, 0.5, 0.0, ts)
    assert len(calls) == 3 and bool(s.ok) and not np.array_equal(s.phi, a.phi)
    # The initial state's check is per call.
    with pytest.raises(ValueError, match="turns from rest"):
        cj.simulate(mech, 1e300, 0.0, ts)
    with pytest.raises(eqx.EquinoxRuntimeError, match="initial state"):
        cj.simulate(mech, float("nan"), 0.0, ts)
    # An invalid parameter raises on every call, also once its plan is kept (built past
    # the constructor's own check, as a tree edit can).
    bad = eqx.tree_at(lambda m: m.m_s, mech, jnp.asarray(-1.0))
    for _ in range(2):
        with pytest.raises(eqx.EquinoxRuntimeError, match="SliderCrank.m_s is invalid"):
            cj.simulate(bad, 0.5, 0.0, ts)
    assert len(front._PLANS) <= front._PLANS.kept
