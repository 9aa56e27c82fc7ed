"""The minimal form M, K, q against independent derivations: autodiff, the global
Newton-Euler form, a potential, and the kinematics' own time derivatives."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_mech

import crank_jax as cj

N_CASES = 25


def _cases(rng):
    for _ in range(N_CASES):
        mech = random_mech(rng)
        phi = rng.uniform(-2 * np.pi, 2 * np.pi)
        dphi = rng.uniform(-20, 20)
        t = rng.uniform(0, 5)
        yield mech, phi, dphi, t


def test_K_is_half_dM_dphi(rng):
    for mech, phi, _, _ in _cases(rng):
        K = cj.model.coriolis(mech, phi)
        dM = jax.grad(lambda p: cj.model.mass(mech, p))(phi)
        np.testing.assert_allclose(K, 0.5 * dM, rtol=1e-11, atol=1e-14)


def test_M_K_q_equal_projection_of_global_newton_euler_form(rng):
    load = cj.HarmonicLoad(3.0, 2.0, 1.5, 0.3)
    torque = cj.HarmonicLoad(-0.2, 0.5, 2.5, 1.0)
    for mech, phi, dphi, t in _cases(rng):
        gf = cj.model.newton_euler_form(mech, phi, dphi, t, load, torque)
        np.testing.assert_allclose(gf.J @ gf.Mbar @ gf.J, cj.model.mass(mech, phi), rtol=1e-12)
        np.testing.assert_allclose(gf.J @ gf.qbar_c, cj.model.coriolis(mech, phi) * dphi**2,
                                   rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(
            gf.J @ gf.qbar_e, cj.model.generalized_force(mech, phi, dphi, t, load, torque),
            rtol=1e-11, atol=1e-12)


def test_conservative_q_is_minus_grad_potential(rng):
    for mech, phi, _, _ in _cases(rng):
        q_cons = cj.model.generalized_force(mech.replace(c=0.0), phi, 0.0)
        dV = jax.grad(lambda p: cj.model.potential_energy(mech, p))(phi)
        np.testing.assert_allclose(q_cons, -dV, rtol=1e-11, atol=1e-12)


def test_slider_force_does_work_minus_P_dx_s(rng):
    # P acts along -x on the slider: its generalised force is -P dx_s/dphi.
    P = 7.5
    for mech, phi, _, _ in _cases(rng):
        m0 = mech.replace(g=0.0, k=0.0, c=0.0)
        q = cj.model.generalized_force(m0, phi, 0.0, load=P)
        dxs = jax.grad(lambda p: cj.model.kinematics(mech, p, 0.0, 0.0).x_s)(phi)
        np.testing.assert_allclose(q, -P * dxs, rtol=1e-11, atol=1e-12)


def test_kinetic_energy_from_body_velocities(rng):
    # T = sum m v^2/2 + I w^2/2 over the three bodies, computed from the kinematics.
    for mech, phi, dphi, _ in _cases(rng):
        kin = cj.model.kinematics(mech, phi, dphi, 0.0)
        T = 0.5 * (mech.m_c * jnp.sum(kin.v_c**2) + mech.m_p * jnp.sum(kin.v_p**2)
                   + mech.m_s * kin.v_s**2 + mech.I_c * dphi**2 + mech.I_p * kin.ddelta**2)
        np.testing.assert_allclose(cj.model.kinetic_energy(mech, phi, dphi), T, rtol=1e-12)


def test_kinematics_are_time_derivatives(rng):
    # Along phi(t) = phi + dphi t + ddphi t^2/2, velocities and accelerations must be the
    # time derivatives of positions; this checks erratum 2 (the sign in a_p's y component).
    for mech, phi, dphi, _ in _cases(rng):
        ddphi = rng.uniform(-50, 50)
        path = lambda t: phi + dphi * t + 0.5 * ddphi * t**2  # noqa: E731
        pos = lambda t: cj.model.kinematics(mech, path(t), 0.0, 0.0)  # noqa: E731
        vel = lambda t: cj.model.kinematics(mech, path(t), dphi + ddphi * t, 0.0)  # noqa: E731
        kin = cj.model.kinematics(mech, phi, dphi, ddphi)
        _, dpos = jax.jvp(pos, (0.0,), (1.0,))
        _, dvel = jax.jvp(vel, (0.0,), (1.0,))
        for name in ("c", "p"):
            np.testing.assert_allclose(getattr(kin, f"v_{name}"), getattr(dpos, f"r_{name}"),
                                       rtol=1e-11, atol=1e-12)
            np.testing.assert_allclose(getattr(kin, f"a_{name}"), getattr(dvel, f"v_{name}"),
                                       rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(kin.v_s, dpos.x_s, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(kin.a_s, dvel.v_s, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(kin.ddelta, dpos.delta, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(kin.dddelta, dvel.ddelta, rtol=1e-10, atol=1e-10)


def test_closure_wrist_pin_on_slider_line(rng):
    for mech, phi, _, _ in _cases(rng):
        ca = cj.model.coupler_angle(mech, phi)
        y_B = mech.r * jnp.sin(phi) - mech.L * ca.sin
        np.testing.assert_allclose(y_B, 0.0, atol=1e-15)
        np.testing.assert_allclose(jnp.sin(ca.delta), ca.sin, rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(ca.d1,
                                   jax.grad(lambda p: cj.model.coupler_angle(mech, p).delta)(phi),
                                   rtol=1e-11, atol=1e-14)
        np.testing.assert_allclose(ca.d2,
                                   jax.grad(lambda p: cj.model.coupler_angle(mech, p).d1)(phi),
                                   rtol=1e-10, atol=1e-13)


def test_reduced_structure_matches_full_terms_for_crank_only():
    mech = cj.load_scene("pendulum").mech
    st = cj.model.ModelTerms.of(mech)
    assert st == cj.model.ModelTerms(coupler=False, slider=False, spring=False, offset=False,
                               crank_coulomb=False, slider_damper=False,
                               slider_coulomb=False, tilt=False)
    phis = jnp.linspace(-4, 4, 17)
    np.testing.assert_allclose(cj.model.mass(mech, phis, st), cj.model.mass(mech, phis),
                               rtol=1e-15)
    np.testing.assert_allclose(cj.model.coriolis(mech, phis, st), cj.model.coriolis(mech, phis),
                               atol=0)
    np.testing.assert_allclose(cj.model.acceleration(mech, phis, 0.3, 0.0, structure=st),
                               cj.model.acceleration(mech, phis, 0.3, 0.0), rtol=1e-14)


@pytest.mark.parametrize("phi", [0.0, 0.7, np.pi / 2, 3.0])
def test_mass_is_positive_and_matches_hand_value_at_zero(phi):
    mech = cj.load_scene("lab-rig").mech
    assert float(cj.model.mass(mech, phi)) > 0
    if phi == 0.0:
        v = mech.as_dict()
        lam = v["r"] / v["L"]
        hand = (v["m_c"] * v["s"] ** 2 + v["I_c"] + v["m_p"] * (v["r"] - v["b"] * lam) ** 2
                + v["I_p"] * lam**2)
        np.testing.assert_allclose(cj.model.mass(mech, 0.0), hand, rtol=1e-14)


def test_packed_field_is_the_field_and_differentiates_alike(rng):
    """`CrankField.packed()` (the coefficients formed once, in one array) evaluates the
    same acceleration as the field, for every structure, and carries the same parameter
    derivatives through its packed leaf."""
    load, torque = cj.HarmonicLoad(3.0, 2.0, 1.5, 0.3), cj.HarmonicLoad(-0.2, 0.5, 2.5, 1.0)
    for mech, phi, dphi, t in list(_cases(rng))[:8]:
        mech = mech.replace(e=0.3 * (mech.L - mech.r) * rng.uniform(-1, 1),
                            T_c=rng.uniform(0, 0.1), c_s=rng.uniform(0, 1),
                            F_s=rng.uniform(0, 1))
        for st in (cj.model.ModelTerms(), cj.model.ModelTerms.of(mech.replace(e=0.0, T_c=0.0)),
                   cj.model.ModelTerms.of(cj.load_scene("pendulum").mech)):
            m = mech if st.offset else mech.replace(e=0.0)
            field = cj.model.CrankField(m, load, torque, st)
            ref = field(t, (phi, dphi))
            got = field.packed()(t, (phi, dphi))
            np.testing.assert_allclose(got, ref, rtol=1e-13, atol=1e-13)

            def accel(k, packed, st=st, m=m):
                f = cj.model.CrankField(m.replace(k=k), load, torque, st)
                return (f.packed() if packed else f)(t, (phi, dphi))[1]

            np.testing.assert_allclose(jax.grad(accel)(m.k, True), jax.grad(accel)(m.k, False),
                                       rtol=1e-12)


def test_equation_residual_vanishes_on_the_model_and_is_M_K_q(rng):
    # The regressor's residual M phi'' + K phi'^2 - q: zero at the model's own acceleration
    # (an independent path: acceleration divides by M once), and the three functions'
    # combination elsewhere.
    from crank_jax.model.dynamics import equation_residual

    load = cj.HarmonicLoad(3.0, 2.0, 1.5, 0.3)
    torque = cj.HarmonicLoad(-0.2, 0.5, 2.5, 1.0)
    for mech, phi, dphi, t in _cases(rng):
        dd = cj.model.acceleration(mech, phi, dphi, t, load, torque)
        M = cj.model.mass(mech, phi)
        assert abs(equation_residual(mech, phi, dphi, dd, t, load, torque)) <= 1e-11 * (
            abs(M * dd) + abs(cj.model.generalized_force(mech, phi, dphi, t, load, torque)))
        expect = (M * 1.7 + cj.model.coriolis(mech, phi) * dphi**2
                  - cj.model.generalized_force(mech, phi, dphi, t, load, torque))
        np.testing.assert_allclose(equation_residual(mech, phi, dphi, 1.7, t, load, torque),
                                   expect, rtol=1e-12, atol=1e-12)
