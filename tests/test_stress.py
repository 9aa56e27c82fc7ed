"""Numerical stress tests (fast versions; the long ones are experiments/stress_*.py):
stiffness and the auto-solver switch, geometry and motion extremes, energy drift, and that
no NaN ever leaves `simulate` or `sweep`."""

import os
import subprocess
import sys
import textwrap

import diffrax
import jax
import numpy as np
import pytest

import crank_jax as cj


def _shaft(mech, k, zeta=0.05):
    """A shaft of stiffness k with material damping ratio zeta (c grows with sqrt(k))."""
    mu = float(cj.linearize(mech).mu)
    return mech.replace(k=k, c=0.01 + 2 * zeta * np.sqrt(k * mu))


# --- the auto-solver switch -------------------------------------------------------------

def test_switch_point_follows_the_documented_rule(lab_rig):
    m = lab_rig.mech
    # Damped stiff shaft over 2 s: the rule ln(1/rtol)/decay < span/140 puts the switch
    # near k = 1e6 N*m/rad.
    assert cj.solve.choose_solver(_shaft(m, 3e5), 1e-8, span=2.0) == "dopri8"
    assert cj.solve.choose_solver(_shaft(m, 3e6), 1e-8, span=2.0) == "kvaerno5"
    # A longer span lets the transient matter less: the switch moves to softer shafts.
    assert cj.solve.choose_solver(_shaft(m, 3e5), 1e-8, span=20.0) == "kvaerno5"
    # The switch is exactly where the rule says.
    for k in (1e4, 1e5, 1e6, 1e7):
        rate, decay = cj.solve.fastest_mode_rates(cj.linearize(_shaft(m, k)))
        stiff = decay * 2.0 > 140 * np.log(1e8)
        assert (cj.solve.choose_solver(_shaft(m, k), 1e-8, span=2.0) == "kvaerno5") == stiff
    # An undamped fast mode must be resolved: never implicit, however stiff.
    assert cj.solve.choose_solver(m.replace(k=1e7, c=0.0), 1e-8, span=2.0) == "dopri8"
    # Over-damped (real, well separated modes) is stiff; a falling crank is not.
    assert cj.solve.choose_solver(m.replace(c=10.0), 1e-8, span=10.0) == "kvaerno5"
    assert cj.solve.choose_solver(m.replace(k=0.01, c=5.0), 1e-8, span=10.0) == "kvaerno5"
    assert cj.solve.choose_solver(m.replace(k=0.01, c=0.01), 1e-8, span=10.0) == "dopri8"
    assert cj.solve.choose_solver(m, 1e-6, span=10.0) == "tsit5"


def test_auto_solves_a_stiff_shaft_that_explicit_solvers_cannot_afford(lab_rig):
    mech = _shaft(lab_rig.mech, 1e7)
    ts = np.linspace(0.0, 2.0, 21)
    auto = cj.simulate(mech, 0.01, 0.0, ts, max_steps=20_000, throw=False)
    tsit = cj.simulate(mech, 0.01, 0.0, ts, solver="tsit5", max_steps=20_000, throw=False)
    assert bool(auto.ok) and int(auto.num_steps) < 6000
    assert tsit.result == diffrax.RESULTS.max_steps_reached
    # After the transient the shaft rests at phi = 0 (to the tolerance).
    assert abs(float(auto.phi[-1])) < 1e-8


def test_a_sweep_over_ten_decades_of_stiffness_has_no_failures(lab_rig):
    ks = np.logspace(-2, 7, 10)
    mu = float(cj.linearize(lab_rig.mech).mu)
    c = 0.01 + 0.1 * np.sqrt(ks * mu)
    r = cj.run_sweep(lab_rig, {"k": ks, "c": c, "phi0": 0.01}, ("peak_phi", "final_phi"),
                 t1=2.0, num_saves=21, chunk_size=3, max_steps=50_000)
    assert np.all(r.ok), r.counts()
    assert cj.solve.SOLVERS[r.solver[-1]] == "kvaerno5"
    assert cj.solve.SOLVERS[r.solver[0]] != "kvaerno5"
    # Explicit up to the switch (k ~ 1e6: ~2e4 Dopri8 steps), then flat: the stiffest
    # shaft costs less than the one just below the switch.
    assert r.num_steps.max() < 30_000 and r.num_steps[-1] < r.num_steps[-2] / 3


# --- geometry and motion extremes -------------------------------------------------------

@pytest.mark.parametrize("ratio", [0.01, 0.5, 0.999])
def test_extreme_crank_to_coupler_ratios_conserve_energy(lab_rig, ratio):
    m = lab_rig.mech.replace(L=lab_rig.mech.r / ratio, b=0.3 * lab_rig.mech.r / ratio, c=0.0)
    ts = np.linspace(0.0, 1.0, 101)
    tr = cj.simulate(m, 1.0, 0.0, ts, rtol=1e-10, atol=1e-12)
    e = np.asarray(cj.model.energy(m, tr.phi, tr.dphi))
    assert np.all(np.isfinite(tr.phi))
    assert np.max(np.abs(e - e[0])) < 1e-7 * (abs(e[0]) + 1)


def test_full_revolutions_leave_phi_unbounded(lab_rig):
    m = lab_rig.mech.replace(k=0.0, c=0.0)  # no spring to stop it: the crank keeps turning
    ts = np.linspace(0.0, 2.0, 201)
    tr = cj.simulate(m, 0.0, 30.0, ts, rtol=1e-10, atol=1e-12)
    assert float(tr.phi[-1]) > 4 * np.pi  # several turns, not wrapped to (-pi, pi]
    e = np.asarray(cj.model.energy(m, tr.phi, tr.dphi))
    assert np.max(np.abs(e - e[0])) < 1e-8 * abs(e[0])


def test_a_crank_with_negative_xi_falls_over(lab_rig):
    m = lab_rig.mech.replace(k=0.1, c=0.02)
    assert not bool(cj.linearize(m).stable)
    tr = cj.simulate(m, 1e-3, 0.0, np.linspace(0.0, 5.0, 101))
    assert np.max(np.abs(np.asarray(tr.phi))) > 1.0  # leaves phi = 0 by far


# --- energy drift -----------------------------------------------------------------------

def test_energy_drift_shrinks_with_the_tolerance(lab_rig):
    m = lab_rig.mech.replace(c=0.0)
    ts = np.linspace(0.0, 20.0, 201)  # about 90 periods
    drift = {}
    for rtol in (1e-6, 1e-10):
        tr = cj.simulate(m, 1.0, 0.0, ts, rtol=rtol, atol=rtol * 1e-2, solver="dopri8")
        e = np.asarray(cj.model.energy(m, tr.phi, tr.dphi))
        drift[rtol] = np.max(np.abs(e - e[0])) / abs(e[0])
    assert drift[1e-10] < 1e-8
    assert drift[1e-10] < drift[1e-6] / 100


# --- no NaN ever leaves simulate or sweep -----------------------------------------------

SOLVERS_UNDER_TEST = ("dopri8", "auto")


def test_failed_solve_with_throw_false_holds_the_last_state(lab_rig):
    ts = np.linspace(0.0, 1.0, 11)
    for solver in SOLVERS_UNDER_TEST:
        tr = cj.simulate(lab_rig.mech, 1.0, 0.0, ts, max_steps=20, throw=False,
                         outputs=("energy", "reactions"), solver=solver)
        assert tr.result == diffrax.RESULTS.max_steps_reached and not bool(tr.ok)
        for v in (tr.phi, tr.dphi, *tr.extras.values()):
            assert np.all(np.isfinite(np.asarray(v)))
        if solver == "dopri8":  # diffrax's adaptive path stops early: the state is held
            assert float(tr.phi[-1]) == float(tr.phi[-2])
        with pytest.raises(Exception, match="max_steps"):
            cj.simulate(lab_rig.mech, 1.0, 0.0, ts, max_steps=20, solver=solver)


def test_huge_stiffness_without_damping_ends_in_a_result_code(lab_rig):
    m = lab_rig.mech.replace(k=1e12, c=0.0)
    tr = cj.simulate(m, 1.0, 0.0, np.linspace(0.0, 1.0, 11), max_steps=1000, throw=False)
    assert not bool(tr.ok) and np.all(np.isfinite(np.asarray(tr.phi)))


def test_nan_parameters_inside_vmap_raise_naming_the_field(lab_rig):
    ks = np.array([2.0, np.nan, 3.0])
    ts = np.linspace(0.0, 0.1, 5)

    def run(k):
        return cj.simulate(lab_rig.mech.replace(k=k), 1.0, 0.0, ts, solver="tsit5").phi

    with pytest.raises(Exception, match=r"SliderCrank\.k is invalid: k must be finite"):
        jax.vmap(run)(ks)
    with pytest.raises(Exception, match="initial state"):
        cj.simulate(lab_rig.mech, np.nan, 0.0, ts, solver="tsit5")


def test_coupler_no_longer_than_crank_is_rejected(lab_rig):
    with pytest.raises(ValueError, match="L must be > r"):
        lab_rig.mech.replace(L=lab_rig.mech.r)


# --- float32 ----------------------------------------------------------------------------

def test_float32_warns_once_with_the_fix(tmp_path):
    script = textwrap.dedent("""
        import warnings
        import numpy as np
        import crank_jax as cj
        m = cj.load_scene("lab-rig").mech
        ts = np.linspace(0.0, 1.0, 11)
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            tr = cj.simulate(m, 1.0, 0.0, ts, rtol=1e-6, atol=1e-8)
            cj.simulate(m, 1.0, 0.0, ts, rtol=1e-6, atol=1e-8)
        assert tr.phi.dtype == np.float32, tr.phi.dtype
        msgs = [str(x.message) for x in w if "float64" in str(x.message)]
        print(len(msgs)); print(msgs[0])
    """)
    env = dict(os.environ, JAX_ENABLE_X64="0", JAX_PLATFORMS="cpu", CRANK_JAX_NO_CACHE="1")
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    count, msg = proc.stdout.strip().split("\n", 1)
    assert count == "1"
    assert "float32" in msg and "jax_enable_x64" in msg and "rtol" in msg
