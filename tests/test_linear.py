"""Linearisation (eq. 33, corrected) against autodiff of the nonlinear equation, the
paper's erratum, and the cubic convergence of small oscillations."""

import jax
import numpy as np
import pytest
from conftest import random_mech

import crank_jax as cj


def _nonlinear_rhs(mech, P):
    # M phi'' = q - K phi'^2; the linearisation is its Jacobian at (0, 0).
    def f(phi, dphi):
        return (cj.model.generalized_force(mech, phi, dphi, 0.0, load=P)
                - cj.model.coriolis(mech, phi) * dphi**2)
    return f


def test_linearization_equals_jacobian_of_nonlinear_equation(rng):
    for _ in range(20):
        mech = random_mech(rng)
        P = rng.uniform(-5, 5)
        lin = cj.linearize(mech, cj.ConstantLoad(P))
        f = _nonlinear_rhs(mech, P)
        dq_dphi, dq_ddphi = jax.jacfwd(f, argnums=(0, 1))(0.0, 0.0)
        np.testing.assert_allclose(lin.mu, cj.model.mass(mech, 0.0), rtol=1e-13)
        np.testing.assert_allclose(lin.xi, -dq_dphi, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(lin.chi, -dq_ddphi, rtol=1e-13)
        np.testing.assert_allclose(lin.k_crit, mech.k - lin.xi, rtol=1e-12)


def test_harmonic_slider_force_enters_xi_by_its_mean():
    mech = cj.load_scene("lab-rig").mech
    a = cj.linearize(mech, cj.HarmonicLoad(2.0, 5.0, 3.0, 0.2))
    b = cj.linearize(mech, cj.ConstantLoad(2.0))
    np.testing.assert_allclose(a.xi, b.xi, rtol=1e-15)
    assert float(b.xi) < float(cj.linearize(mech).xi)  # a compressive P softens the crank


def test_paper_coupler_term_erratum_is_not_computed():
    mech = cj.load_scene("lab-rig").mech
    v = mech.as_dict()
    r, L, b, g = v["r"], v["L"], v["b"], v["g"]
    common = v["k"] - g * (v["m_c"] * v["s"] + v["m_s"] * r * (1 + r / L))
    paper = common - g * v["m_p"] * r * (1 + b / L)  # as printed in eq. 33
    corrected = common - g * v["m_p"] * r * (1 + r * b / L**2)
    xi = float(cj.linearize(mech).xi)
    np.testing.assert_allclose(xi, corrected, rtol=1e-14)
    assert abs(xi - paper) > 1e-3 * abs(xi)


def test_derived_quantities():
    lin = cj.linearize(cj.load_scene("lab-rig").mech)
    np.testing.assert_allclose(lin.omega_n, np.sqrt(lin.xi / lin.mu), rtol=1e-15)
    np.testing.assert_allclose(lin.zeta, lin.chi / (2 * np.sqrt(lin.xi * lin.mu)), rtol=1e-15)
    assert bool(lin.stable)
    assert 4.0 < float(lin.omega_n) / (2 * np.pi) < 5.0  # "about 4.5 Hz"
    fallen = cj.linearize(cj.load_scene("pendulum").mech)
    assert not bool(fallen.stable) and np.isnan(fallen.omega_n)


def _linear_free_response(lin, phi0, t):
    """Exact solution of mu x'' + chi x' + xi x = 0, x(0) = phi0, x'(0) = 0 (underdamped)."""
    mu, chi, xi = (float(x) for x in (lin.mu, lin.chi, lin.xi))
    a = chi / (2 * mu)
    wd = np.sqrt(xi / mu - a * a)
    return phi0 * np.exp(-a * t) * (np.cos(wd * t) + a / wd * np.sin(wd * t))


@pytest.mark.parametrize("scene", ["lab-rig", "torsional"])
def test_small_oscillations_converge_to_linear_like_amplitude_cubed(scene):
    sc = cj.load_scene(scene)
    lin = cj.linearize(sc.mech)
    period = 2 * np.pi / float(lin.omega_n)
    ts = np.linspace(0, 3 * period, 301)
    errors = []
    amplitudes = [4e-2, 2e-2, 1e-2, 5e-3]
    for A in amplitudes:
        tr = cj.simulate(sc.mech, A, 0.0, ts, solver="dopri8", rtol=1e-13, atol=1e-17)
        errors.append(np.max(np.abs(np.asarray(tr.phi) - _linear_free_response(lin, A, ts))))
    slopes = np.diff(np.log(errors)) / np.diff(np.log(amplitudes))
    np.testing.assert_allclose(slopes, 3.0, atol=0.1)
