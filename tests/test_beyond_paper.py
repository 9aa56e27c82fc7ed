"""Offset slider line and joint friction (DESIGN.md §1 "Beyond the paper") against
independent derivations: autodiff identities, the global Newton-Euler form, each body's
own Newton-Euler equations, a potential, and the power balance."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from conftest import random_mech

import crank_jax as cj

N_CASES = 20
LOAD = cj.HarmonicLoad(3.0, 2.0, 1.5, 0.3)
TORQUE = cj.HarmonicLoad(-0.2, 0.5, 2.5, 1.0)


def _rich(rng, **overrides):
    """A random mechanism with an offset and every friction term on."""
    m = random_mech(rng)
    slack = float(m.L - m.r)
    v = dict(e=rng.uniform(-0.9, 0.9) * slack, T_c=rng.uniform(0.01, 0.2),
             w_c=rng.uniform(0.005, 0.5), c_s=rng.uniform(0.1, 5.0), F_s=rng.uniform(0.1, 3.0),
             w_s=rng.uniform(1e-4, 1e-2))
    v.update(overrides)
    return m.replace(**v)


def _cases(rng):
    for _ in range(N_CASES):
        yield (_rich(rng), rng.uniform(-2 * np.pi, 2 * np.pi), rng.uniform(-20, 20),
               rng.uniform(0, 5))


def test_offset_closure_puts_the_wrist_pin_on_y_equals_e(rng):
    for mech, phi, _, _ in _cases(rng):
        g = cj.model.geometry_at(mech, phi)
        np.testing.assert_allclose(mech.r * jnp.sin(phi) - mech.L * g.sin, mech.e, atol=1e-15)
        np.testing.assert_allclose(g.sin**2 + g.cos**2, 1.0, rtol=1e-15)
        delta = lambda p: cj.model.geometry_at(mech, p).delta  # noqa: E731
        np.testing.assert_allclose(g.d1, jax.grad(delta)(phi), rtol=1e-11, atol=1e-14)
        np.testing.assert_allclose(g.d2, jax.grad(lambda p: cj.model.geometry_at(mech, p).d1)(phi),
                                   rtol=1e-10, atol=1e-13)
        x_s = lambda p: cj.model.geometry_at(mech, p).x_s  # noqa: E731
        np.testing.assert_allclose(g.lever, -jax.grad(x_s)(phi), rtol=1e-11, atol=1e-14)
        np.testing.assert_allclose(g.dlever, -jax.grad(jax.grad(x_s))(phi),
                                   rtol=1e-10, atol=1e-13)


def test_K_is_half_dM_dphi_with_offset(rng):
    for mech, phi, _, _ in _cases(rng):
        dM = jax.grad(lambda p: cj.model.mass(mech, p))(phi)
        np.testing.assert_allclose(cj.model.coriolis(mech, phi), 0.5 * dM, rtol=1e-11, atol=1e-14)


def test_global_newton_euler_projection_with_offset_and_friction(rng):
    for mech, phi, dphi, t in _cases(rng):
        gf = cj.model.newton_euler_form(mech, phi, dphi, t, LOAD, TORQUE)
        np.testing.assert_allclose(gf.J @ gf.Mbar @ gf.J, cj.model.mass(mech, phi), rtol=1e-12)
        np.testing.assert_allclose(gf.J @ gf.qbar_c, cj.model.coriolis(mech, phi) * dphi**2,
                                   rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(
            gf.J @ gf.qbar_e, cj.model.generalized_force(mech, phi, dphi, t, LOAD, TORQUE),
            rtol=1e-10, atol=1e-11)


def test_acceleration_equals_global_newton_euler_solution(rng):
    # The fused acceleration (one rsqrt, one division) against the projected global form,
    # which shares none of its M, K, q code; with and without offset and friction.
    for mech, phi, dphi, t in _cases(rng):
        for m in (mech, mech.replace(e=0.0, T_c=0.0, c_s=0.0, F_s=0.0)):
            gf = cj.model.newton_euler_form(m, phi, dphi, t, LOAD, TORQUE)
            ne = (gf.J @ gf.qbar_e - gf.J @ gf.qbar_c) / (gf.J @ gf.Mbar @ gf.J)
            acc = cj.model.acceleration(m, phi, dphi, t, LOAD, TORQUE, cj.model.ModelTerms.of(m))
            np.testing.assert_allclose(acc, ne, rtol=1e-10, atol=1e-10)


def test_conservative_q_is_minus_grad_potential_with_offset(rng):
    # At rest every friction term vanishes (tanh(0) = 0), so q(phi, 0) is conservative.
    for mech, phi, _, _ in _cases(rng):
        q_cons = cj.model.generalized_force(mech, phi, 0.0)
        dV = jax.grad(lambda p: cj.model.potential_energy(mech, p))(phi)
        np.testing.assert_allclose(q_cons, -dV, rtol=1e-11, atol=1e-12)


def test_energy_rate_equals_power_in_with_all_friction(rng):
    for mech, phi, dphi, t in _cases(rng):
        ddphi = cj.model.acceleration(mech, phi, dphi, t, LOAD, TORQUE)
        dE_dphi, dE_ddphi = jax.grad(lambda p, d: cj.model.energy(mech, p, d), argnums=(0, 1))(
            phi, dphi)
        rate = dE_dphi * dphi + dE_ddphi * ddphi
        power = cj.model.nonconservative_power(mech, phi, dphi, t, LOAD, TORQUE)
        scale = abs(float(power)) + abs(float(dE_dphi * dphi)) + 1e-12
        np.testing.assert_allclose(rate, power, rtol=0, atol=1e-10 * scale)


def test_friction_only_takes_energy_out(rng):
    for mech, phi, dphi, _ in _cases(rng):
        free = mech.replace(c=0.0)  # no loads, no viscous shaft: only friction does work
        assert float(cj.model.nonconservative_power(free, phi, dphi)) < 0.0
        lossless = free.replace(T_c=0.0, c_s=0.0, F_s=0.0)
        assert float(cj.model.nonconservative_power(lossless, phi, dphi)) == 0.0


def _cross(u, f):
    return u[0] * f[1] - u[1] * f[0]


def test_reactions_satisfy_each_body_newton_euler_with_friction(rng):
    for mech, phi, dphi, t in _cases(rng):
        ddphi = cj.model.acceleration(mech, phi, dphi, t, LOAD, TORQUE)
        kin = cj.model.kinematics(mech, phi, dphi, ddphi)
        rx = cj.model.reactions(mech, phi, dphi, ddphi, t, LOAD, TORQUE)
        grav = lambda m: jnp.array([-m * mech.g, 0.0])  # noqa: E731
        pA = jnp.array([mech.r * jnp.cos(phi), mech.r * jnp.sin(phi)])
        pB = jnp.array([kin.x_s, mech.e])
        tol = dict(rtol=1e-9, atol=1e-9)
        # Crank: bearing O, pin A, weight, shaft spring/damper, bearing friction, tau.
        shaft = (-mech.k * phi - mech.c * dphi + TORQUE(t)
                 - mech.T_c * jnp.tanh(dphi / mech.w_c))
        np.testing.assert_allclose(mech.m_c * kin.a_c, rx.O + rx.A + grav(mech.m_c), **tol)
        np.testing.assert_allclose(
            mech.I_c * ddphi,
            _cross(-kin.r_c, rx.O) + _cross(pA - kin.r_c, rx.A) + shaft, **tol)
        # Coupler: -A at A, B at B, weight; its rotation angle is -delta.
        np.testing.assert_allclose(mech.m_p * kin.a_p, -rx.A + rx.B + grav(mech.m_p), **tol)
        np.testing.assert_allclose(
            -mech.I_p * kin.dddelta,
            _cross(pA - kin.r_p, -rx.A) + _cross(pB - kin.r_p, rx.B), **tol)
        # Slider: -B from the coupler, P along -x, weight, guide normal N and friction F.
        F = -mech.c_s * kin.v_s - mech.F_s * jnp.tanh(kin.v_s / mech.w_s)
        np.testing.assert_allclose(rx.F, F, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(mech.m_s * kin.a_s,
                                   -rx.B[0] - LOAD(t) - mech.m_s * mech.g + rx.F, **tol)
        np.testing.assert_allclose(0.0, -rx.B[1] + rx.N, **tol)


def test_zero_terms_are_compiled_out():
    mech = cj.load_scene("lab-rig").mech
    st = cj.model.ModelTerms.of(mech)
    assert not (st.offset or st.crank_coulomb or st.slider_damper or st.slider_coulomb)
    jaxpr = str(jax.make_jaxpr(
        lambda p, d: cj.model.acceleration(mech, p, d, structure=st))(0.3, 1.0))
    assert "tanh" not in jaxpr
    rich = mech.replace(e=0.01, T_c=0.05, c_s=1.0, F_s=0.5)
    st2 = cj.model.ModelTerms.of(rich)
    assert st2.offset and st2.crank_coulomb and st2.slider_damper and st2.slider_coulomb
    jaxpr2 = str(jax.make_jaxpr(
        lambda p, d: cj.model.acceleration(rich, p, d, structure=st2))(0.3, 1.0))
    assert jaxpr2.count("tanh") == 2
    phis = jnp.linspace(-4, 4, 17)
    np.testing.assert_allclose(cj.model.acceleration(mech, phis, 0.3, structure=st),
                               cj.model.acceleration(mech, phis, 0.3), rtol=1e-14)
    np.testing.assert_allclose(cj.model.acceleration(rich, phis, 0.3, structure=st2),
                               cj.model.acceleration(rich, phis, 0.3), rtol=1e-14)


def test_traced_fields_keep_their_terms_and_zero_constants_beside_them_compile_out():
    # Inside jit/vmap a traced field may take any value (its terms stay); a concrete zero
    # beside it is a constant of that program, so its terms are dropped there too.
    mech = cj.load_scene("lab-rig").mech
    ts = jnp.linspace(0.0, 1.0, 11)
    seen = []

    def run(k, T_c):
        m = mech.replace(k=k, T_c=T_c)
        seen.append(cj.model.ModelTerms.of(m))
        return cj.simulate(m, 1.0, 0.0, ts).phi

    batch = jax.jit(jax.vmap(run, in_axes=(0, None)))(jnp.array([1.5, 2.0]), 0.0)
    st = seen[-1]
    assert st.spring and st.crank_coulomb  # traced, zero or not
    assert not (st.offset or st.slider_damper or st.slider_coulomb)  # concrete zeros
    jaxpr = str(jax.make_jaxpr(lambda k: run(k, mech.T_c))(2.0))
    assert "tanh" not in jaxpr  # T_c a concrete zero: no Coulomb term in the program
    # The batch steps in lockstep (steps its two members allow): equal to the tolerance.
    np.testing.assert_allclose(batch[1], cj.simulate(mech, 1.0, 0.0, ts).phi, atol=1e-7)


def test_new_values_never_retrace():
    mech = cj.load_scene("lab-rig").mech

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def acc(m):
        return cj.model.acceleration(m, 0.3, 1.0)

    for e, T_c, F_s in [(0.0, 0.0, 0.0), (0.01, 0.1, 0.5), (-0.02, 0.3, 2.0)]:
        acc(mech.replace(e=e, T_c=T_c, c_s=2 * T_c, F_s=F_s, w_c=0.02, w_s=0.002))


def test_crank_field_is_the_acceleration(rng):
    mech = _rich(rng)
    field = cj.model.CrankField(mech, LOAD, TORQUE, cj.model.ModelTerms.of(mech))
    dphi, ddphi = field(0.7, (jnp.asarray(0.4), jnp.asarray(-3.0)))
    assert float(dphi) == -3.0
    np.testing.assert_allclose(ddphi, cj.model.acceleration(mech, 0.4, -3.0, 0.7, LOAD, TORQUE),
                               rtol=1e-14)


def test_coulomb_friction_decays_linearly():
    # A crank held only by its spring with bearing Coulomb friction: each half swing loses
    # 2 T_c / k of amplitude (to within the smoothing), the classical result.
    mech = cj.SliderCrank(r=0.05, L=0.2, b=0.0, s=0.0, m_c=0.0, m_p=0.0, m_s=0.0, I_c=1e-3,
                          I_p=0.0, k=1.0, c=0.0, g=0.0, T_c=0.01, w_c=1e-4)
    period = 2 * np.pi * np.sqrt(1e-3 / 1.0)
    ts = np.linspace(0, 2 * period, 4001)
    tr = cj.simulate(mech, 0.5, 0.0, ts, solver="dopri8", rtol=1e-10, atol=1e-12,
                     max_steps=1_000_000)
    phi = np.asarray(tr.phi)
    half = np.argmin(phi[: 2100])  # first turning point, near half a period
    np.testing.assert_allclose(-phi[half], 0.5 - 2 * 0.01 / 1.0, rtol=2e-3)
