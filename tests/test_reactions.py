"""Joint reactions: each body's Newton-Euler equations balance, reactions do no virtual
work, and the whole mechanism obeys Newton's second law with only external forces."""

import jax.numpy as jnp
import numpy as np
from conftest import random_mech

import crank_jax as cj

LOAD = cj.HarmonicLoad(4.0, 3.0, 2.0, 0.1)
TORQUE = cj.HarmonicLoad(0.3, -0.4, 1.3, 0.0)


def _state(rng):
    return rng.uniform(-7, 7), rng.uniform(-15, 15), rng.uniform(0, 3)


def test_reactions_do_no_virtual_work(rng):
    for _ in range(20):
        mech = random_mech(rng)
        phi = rng.uniform(-7, 7)
        gf = cj.model.newton_euler_form(mech, phi, 0.0)
        Q = cj.model.distribution_matrix(mech, phi)
        np.testing.assert_allclose(gf.J @ Q, 0.0, atol=1e-14)


def test_every_body_balances_when_phi_obeys_the_equation_of_motion(rng):
    for _ in range(20):
        mech = random_mech(rng)
        phi, dphi, t = _state(rng)
        ddphi = cj.model.acceleration(mech, phi, dphi, t, LOAD, TORQUE)
        rx = cj.model.reactions(mech, phi, dphi, ddphi, t, LOAD, TORQUE)
        g_r = jnp.concatenate([rx.O, rx.A, rx.B, rx.N[None]])
        gf = cj.model.newton_euler_form(mech, phi, dphi, t, LOAD, TORQUE)
        residual = (gf.Mbar @ gf.J * ddphi + gf.qbar_c - gf.qbar_e
                    - cj.model.distribution_matrix(mech, phi) @ g_r)
        scale = float(jnp.max(jnp.abs(gf.qbar_e))) + 1.0
        np.testing.assert_allclose(residual, 0.0, atol=1e-10 * scale)


def test_crank_moment_balance_fails_for_a_wrong_acceleration(rng):
    # The reactions are solved from seven of eight rows; the eighth (crank moments) holds
    # only for the true phi''. A perturbed phi'' must leave a residual there.
    mech = random_mech(rng)
    phi, dphi, t = _state(rng)
    ddphi = cj.model.acceleration(mech, phi, dphi, t, LOAD, TORQUE) + 1.0
    rx = cj.model.reactions(mech, phi, dphi, ddphi, t, LOAD, TORQUE)
    g_r = jnp.concatenate([rx.O, rx.A, rx.B, rx.N[None]])
    gf = cj.model.newton_euler_form(mech, phi, dphi, t, LOAD, TORQUE)
    res = (gf.Mbar @ gf.J * ddphi + gf.qbar_c - gf.qbar_e
           - cj.model.distribution_matrix(mech, phi) @ g_r)
    np.testing.assert_allclose(res[6], cj.model.mass(mech, phi) * 1.0, rtol=1e-9)


def test_whole_mechanism_newton_second_law(rng):
    # Internal pin forces cancel: sum of m a = frame force at O + guide normal + weights + P.
    for _ in range(20):
        mech = random_mech(rng)
        phi, dphi, t = _state(rng)
        ddphi = cj.model.acceleration(mech, phi, dphi, t, LOAD, TORQUE)
        kin = cj.model.kinematics(mech, phi, dphi, ddphi)
        rx = cj.model.reactions(mech, phi, dphi, ddphi, t, LOAD, TORQUE)
        ma = (mech.m_c * kin.a_c + mech.m_p * kin.a_p
              + mech.m_s * jnp.stack([kin.a_s, 0.0]))
        external = rx.O + jnp.stack([-(mech.m_c + mech.m_p + mech.m_s) * mech.g - LOAD(t), rx.N])
        np.testing.assert_allclose(ma, external, rtol=1e-9, atol=1e-9)


def test_wrist_pin_force_from_slider_equation(rng):
    mech = random_mech(rng)
    phi, dphi, t = _state(rng)
    ddphi = cj.model.acceleration(mech, phi, dphi, t, LOAD, TORQUE)
    kin = cj.model.kinematics(mech, phi, dphi, ddphi)
    rx = cj.model.reactions(mech, phi, dphi, ddphi, t, LOAD, TORQUE)
    # Slider along x: m_s a_s = -P - m_s g - B_x (it receives -B from the coupler).
    np.testing.assert_allclose(rx.B[0], -LOAD(t) - mech.m_s * mech.g - mech.m_s * kin.a_s,
                               rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(rx.N, rx.B[1], rtol=1e-12, atol=1e-12)


def test_static_equilibrium_reactions_carry_the_weight():
    mech = cj.load_scene("lab-rig").mech
    rx = cj.model.reactions(mech, 0.0, 0.0, 0.0)
    v = mech.as_dict()
    # At rest on the x axis the bearing holds the whole weight (along +x), nothing sideways.
    np.testing.assert_allclose(rx.O, [v["g"] * (v["m_c"] + v["m_p"] + v["m_s"]), 0.0],
                               atol=1e-12)
    np.testing.assert_allclose(rx.N, 0.0, atol=1e-12)
