"""Gravity in any in-plane direction (DESIGN.md §1 "Beyond the paper, second step"):
`gravity_angle` gamma, gravity along (-cos(gamma), -sin(gamma)), against references built
here from the bodies' positions alone: a potential, a Lagrangian, each body's Newton-Euler
equations, the energy along a simulation, autodiff of q for the linearisation."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_mech

import crank_jax as cj
from crank_jax import cli

LOAD = cj.HarmonicLoad(3.0, 2.0, 1.5, 0.3)
TORQUE = cj.HarmonicLoad(-0.2, 0.5, 2.5, 1.0)
SPECIAL = (0.0, np.pi / 2, np.pi, -np.pi / 2, 3 * np.pi / 4)


def _tilted(rng, gamma, rich=True):
    """A random mechanism with gravity at `gamma` (and an offset and friction if `rich`)."""
    m = random_mech(rng)
    v = dict(gravity_angle=gamma)
    if rich:
        v.update(e=rng.uniform(-0.9, 0.9) * float(m.L - m.r), T_c=rng.uniform(0.01, 0.2),
                 w_c=rng.uniform(0.005, 0.5), c_s=rng.uniform(0.1, 5.0),
                 F_s=rng.uniform(0.1, 3.0), w_s=rng.uniform(1e-4, 1e-2))
    return m.replace(**v)


def _cases(rng, n=16):
    gammas = list(SPECIAL) + list(rng.uniform(-2 * np.pi, 2 * np.pi, n - len(SPECIAL)))
    for i, gamma in enumerate(gammas):
        yield (_tilted(rng, gamma, rich=i % 2 == 0), rng.uniform(-2 * np.pi, 2 * np.pi),
               rng.uniform(-20, 20), rng.uniform(0, 5))


# --- the reference: positions from the loop closure, written here -----------------------

def _positions(m, phi):
    """Centres of mass of crank, coupler and slider, (3, 2), m, and the coupler angle."""
    delta = jnp.arcsin((m.r * jnp.sin(phi) - m.e) / m.L)
    crank = jnp.stack([m.s * jnp.cos(phi), m.s * jnp.sin(phi)])
    coupler = jnp.stack([m.r * jnp.cos(phi) + m.b * jnp.cos(delta),
                         m.r * jnp.sin(phi) - m.b * jnp.sin(delta)])
    slider = jnp.stack([m.r * jnp.cos(phi) + m.L * jnp.cos(delta), m.e + 0 * phi])
    return jnp.stack([crank, coupler, slider]), delta


def _gravity(m):
    """Gravity's vector, m/s^2."""
    return -m.g * jnp.stack([jnp.cos(m.gravity_angle), jnp.sin(m.gravity_angle)])


def _potential(m, phi):
    """V = -sum m_i g.r_i + k phi^2 / 2, J."""
    pos, _ = _positions(m, phi)
    masses = jnp.stack([m.m_c, m.m_p, m.m_s])
    return -jnp.sum(masses * (pos @ _gravity(m))) + 0.5 * m.k * phi**2


def _kinetic(m, phi, dphi):
    """T from each body's velocity (J dphi) and rotation rate, J."""
    jac, ddelta = jax.jacfwd(lambda p: _positions(m, p))(phi)
    masses = jnp.stack([m.m_c, m.m_p, m.m_s])
    trans = jnp.sum(masses * jnp.sum(jac**2, -1))
    return 0.5 * (trans + m.I_c + m.I_p * ddelta**2) * dphi**2


def _nonconservative(m, phi, dphi, t):
    """Generalised force of the loads, the damper and the friction terms, N*m."""
    dxs = jax.grad(lambda p: _positions(m, p)[0][2, 0])(phi)
    v_s = dxs * dphi
    slider = -LOAD(t) - m.c_s * v_s - m.F_s * jnp.tanh(v_s / m.w_s)
    crank = TORQUE(t) - m.c * dphi - m.T_c * jnp.tanh(dphi / m.w_c)
    return crank + slider * dxs


@eqx.filter_jit
def _lagrange_acceleration(m, phi, dphi, t):
    """phi'' from d/dt dL/dphi' - dL/dphi = Q with L = T - V."""
    def lag(p, v):
        return _kinetic(m, p, v) - _potential(m, p)
    dL_dq = jax.grad(lag, 0)(phi, dphi)
    hess = jax.hessian(lag, (0, 1))(phi, dphi)
    d2_vq, d2_vv = hess[1][0], hess[1][1]
    return (_nonconservative(m, phi, dphi, t) + dL_dq - d2_vq * dphi) / d2_vv


# --- the equation of motion ---------------------------------------------------------------

def test_potential_and_conservative_q_match_the_reference(rng):
    for mech, phi, _, _ in _cases(rng):
        np.testing.assert_allclose(cj.model.potential_energy(mech, phi), _potential(mech, phi),
                                   rtol=1e-12, atol=1e-13)
        # At rest every friction term vanishes (tanh(0) = 0): q(phi, 0) is conservative.
        q = cj.model.generalized_force(mech.replace(c=0.0), phi, 0.0,
                                 structure=cj.model.ModelTerms.of(mech))
        dV = jax.grad(lambda p, m=mech: _potential(m, p))(phi)
        np.testing.assert_allclose(q, -dV, rtol=1e-11, atol=1e-12)


@eqx.filter_jit
def _model_accelerations(mech, phi, dphi, t, structure):
    """The acceleration from the fused formula and from the packed field."""
    acc = cj.model.acceleration(mech, phi, dphi, t, LOAD, TORQUE, structure)
    packed = cj.model.CrankField(mech, LOAD, TORQUE, structure).packed()
    return acc, packed(t, (phi, dphi))[1]


def test_acceleration_equals_an_independent_lagrangian(rng):
    for mech, *state in _cases(rng):
        phi, dphi, t = (jnp.asarray(x) for x in state)  # traced: one compilation
        ref = _lagrange_acceleration(mech, phi, dphi, t)
        for st in (cj.model.ModelTerms(), cj.model.ModelTerms.of(mech)):
            for acc in _model_accelerations(mech, phi, dphi, t, st):
                np.testing.assert_allclose(acc, ref, rtol=1e-9, atol=1e-9)


def test_direction_is_the_documented_one():
    # A crank-only pendulum without spring: the weight torque is m s g x (-cos, -sin)
    # about O, i.e. q = m s g sin(phi - gamma); gamma = pi/2 pulls along -y.
    mech = cj.load_scene("pendulum").mech
    msg = float(mech.m_c * mech.s * mech.g)
    for gamma in SPECIAL + (1.1,):
        m = mech.replace(gravity_angle=gamma, c=0.0)
        for phi in (0.0, 0.4, -2.0):
            np.testing.assert_allclose(cj.model.generalized_force(m, phi, 0.0),
                                       msg * np.sin(phi - gamma), rtol=1e-13, atol=1e-15)


def test_energy_rate_equals_power_in(rng):
    for mech, phi, dphi, t in _cases(rng):
        ddphi = cj.model.acceleration(mech, phi, dphi, t, LOAD, TORQUE)
        dE_dphi, dE_ddphi = jax.grad(lambda p, d, m=mech: cj.model.energy(m, p, d),
                                     argnums=(0, 1))(phi, dphi)
        rate = dE_dphi * dphi + dE_ddphi * ddphi
        power = cj.model.nonconservative_power(mech, phi, dphi, t, LOAD, TORQUE)
        scale = abs(float(power)) + abs(float(dE_dphi * dphi)) + 1e-12
        np.testing.assert_allclose(rate, power, rtol=0, atol=1e-10 * scale)


@pytest.mark.parametrize("gamma", [0.0, 0.7, np.pi / 2, np.pi, -2.3])
def test_energy_is_constant_along_a_simulation_without_dissipation(gamma):
    mech = cj.load_scene("lab-rig").mech.replace(c=0.0, e=0.01, gravity_angle=gamma)
    ts = np.linspace(0.0, 1.0, 201)
    tr = cj.simulate(mech, 1.0, 0.0, ts, solver="dopri8", rtol=1e-12, atol=1e-14,
                     outputs=("energy",))
    e = np.asarray(tr.extras["energy"])
    kinetic = np.asarray(cj.model.kinetic_energy(mech, tr.phi, tr.dphi))
    np.testing.assert_allclose(e, e[0], rtol=0, atol=1e-10 * kinetic.max())
    assert kinetic.max() > 1e-3  # it moves


def test_the_direction_changes_the_motion():
    mech = cj.load_scene("lab-rig").mech
    ts = np.linspace(0.0, 1.0, 51)
    runs = [np.asarray(cj.simulate(mech.replace(gravity_angle=g), 1.0, 0.0, ts).phi)
            for g in (0.0, np.pi / 2, np.pi, 2 * np.pi)]
    assert np.abs(runs[0] - runs[1]).max() > 0.05 and np.abs(runs[0] - runs[2]).max() > 0.05
    np.testing.assert_allclose(runs[3], runs[0], rtol=1e-7, atol=1e-8)  # 2 pi is 0


def test_horizontal_table_has_no_gravity(rng):
    for mech, phi, dphi, t in list(_cases(rng))[:6]:
        flat = mech.replace(g=0.0)
        ref = flat.replace(gravity_angle=0.0)
        np.testing.assert_array_equal(cj.model.acceleration(flat, phi, dphi, t, LOAD, TORQUE),
                                      cj.model.acceleration(ref, phi, dphi, t, LOAD, TORQUE))


# --- gamma = 0 is the paper's, with its arithmetic ---------------------------------------

def test_gamma_zero_compiles_the_direction_out_and_changes_no_bit(rng):
    mech = cj.load_scene("lab-rig").mech.replace(e=0.01, T_c=0.05, c_s=1.0, F_s=0.5)
    st = cj.model.ModelTerms.of(mech)
    assert not st.tilt and cj.model.ModelTerms.of(mech.replace(gravity_angle=0.3)).tilt

    def acc(gamma, structure):
        return cj.model.acceleration(mech.replace(gravity_angle=gamma), 0.3, 1.0, 0.2, LOAD,
                               TORQUE, structure)

    jaxpr = jax.make_jaxpr(lambda gamma: acc(gamma, st))(0.0).jaxpr
    gamma = jaxpr.invars[0]
    reads = [v for eqn in jaxpr.eqns for v in eqn.invars] + list(jaxpr.outvars)
    assert not any(v is gamma for v in reads)  # without tilt, gamma is not read at all
    tilted = jax.make_jaxpr(lambda gamma: acc(gamma, cj.model.ModelTerms()))(0.0).jaxpr
    assert len(tilted.eqns) > len(jaxpr.eqns)
    phis = jnp.linspace(-4, 4, 33)
    for f in (lambda s: cj.model.acceleration(mech, phis, 0.3, 0.2, LOAD, TORQUE, s),
              lambda s: cj.model.generalized_force(mech, phis, 0.0, structure=s)):
        np.testing.assert_array_equal(f(st), f(cj.model.ModelTerms()))
    # The potential is the paper's g (m_c x_c + m_p x_p + m_s x_s) + k phi^2 / 2, bit for bit.
    g = cj.model.geometry_at(mech, phis)
    paper = mech.g * (mech.m_c * g.x_c + mech.m_p * g.x_p + mech.m_s * g.x_s) \
        + 0.5 * mech.k * phis**2
    np.testing.assert_array_equal(cj.model.potential_energy(mech, phis), paper)


def test_new_values_never_retrace():
    mech = cj.load_scene("lab-rig").mech

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def acc(m):
        return cj.model.acceleration(m, 0.3, 1.0), cj.linearize(m).xi

    for gamma, g in [(0.0, 9.81), (0.4, 9.81), (-2.0, 3.0), (np.pi / 2, 0.0)]:
        acc(mech.replace(gravity_angle=gamma, g=g))

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(gamma):
        return cj.simulate(mech.replace(gravity_angle=gamma), 1.0, 0.0,
                           jnp.linspace(0.0, 0.2, 5)).phi

    for gamma in (0.3, -1.0, 2.5):
        run(jnp.asarray(gamma))


# --- Newton-Euler and the reactions ------------------------------------------------------

def _cross(u, f):
    return u[0] * f[1] - u[1] * f[0]


def test_global_newton_euler_projection(rng):
    for mech, phi, dphi, t in _cases(rng):
        gf = cj.model.newton_euler_form(mech, phi, dphi, t, LOAD, TORQUE)
        np.testing.assert_allclose(
            gf.J @ gf.qbar_e, cj.model.generalized_force(mech, phi, dphi, t, LOAD, TORQUE),
            rtol=1e-10, atol=1e-11)


def test_reactions_satisfy_each_body_newton_euler(rng):
    for mech, phi, dphi, t in _cases(rng):
        ddphi = cj.model.acceleration(mech, phi, dphi, t, LOAD, TORQUE)
        kin = cj.model.kinematics(mech, phi, dphi, ddphi)
        rx = cj.model.reactions(mech, phi, dphi, ddphi, t, LOAD, TORQUE)
        gvec = _gravity(mech)
        pA = jnp.array([mech.r * jnp.cos(phi), mech.r * jnp.sin(phi)])
        pB = jnp.array([kin.x_s, mech.e])
        tol = dict(rtol=1e-9, atol=1e-9)
        shaft = (-mech.k * phi - mech.c * dphi + TORQUE(t)
                 - mech.T_c * jnp.tanh(dphi / mech.w_c))
        np.testing.assert_allclose(mech.m_c * kin.a_c, rx.O + rx.A + mech.m_c * gvec, **tol)
        np.testing.assert_allclose(
            mech.I_c * ddphi,
            _cross(-kin.r_c, rx.O) + _cross(pA - kin.r_c, rx.A) + shaft, **tol)
        np.testing.assert_allclose(mech.m_p * kin.a_p, -rx.A + rx.B + mech.m_p * gvec, **tol)
        np.testing.assert_allclose(
            -mech.I_p * kin.dddelta,
            _cross(pA - kin.r_p, -rx.A) + _cross(pB - kin.r_p, rx.B), **tol)
        # Slider: along the guide it accelerates; across it the normal force N carries
        # the coupler's push and the weight's y-part.
        np.testing.assert_allclose(mech.m_s * kin.a_s,
                                   -rx.B[0] - LOAD(t) + mech.m_s * gvec[0] + rx.F, **tol)
        np.testing.assert_allclose(0.0, -rx.B[1] + rx.N + mech.m_s * gvec[1], **tol)


# --- linearisation and equilibrium -------------------------------------------------------

def test_linearisation_equals_autodiff_of_q_at_phi_eq(rng):
    for i in range(12):
        gamma = SPECIAL[i] if i < len(SPECIAL) else rng.uniform(-np.pi, np.pi)
        mech = random_mech(rng, k=rng.uniform(20, 40))
        mech = mech.replace(e=rng.uniform(-0.5, 0.5) * float(mech.L - mech.r),
                            c_s=rng.uniform(0, 3), gravity_angle=gamma)
        P, tau = rng.uniform(-5, 5), rng.uniform(-0.3, 0.3)
        lin = cj.linearize(mech, cj.ConstantLoad(P), cj.ConstantLoad(tau))
        phi_eq = float(lin.phi_eq)
        assert np.isfinite(phi_eq)

        def f(phi, dphi, m=mech, P=P, tau=tau):
            return (cj.model.generalized_force(m, phi, dphi, 0.0, load=P, torque=tau)
                    - cj.model.coriolis(m, phi) * dphi**2)

        np.testing.assert_allclose(f(phi_eq, 0.0), 0.0, atol=1e-12)
        dq_dphi, dq_ddphi = jax.jacfwd(f, argnums=(0, 1))(phi_eq, 0.0)
        np.testing.assert_allclose(lin.mu, cj.model.mass(mech, phi_eq), rtol=1e-13)
        np.testing.assert_allclose(lin.xi, -dq_dphi, rtol=1e-10, atol=1e-11)
        np.testing.assert_allclose(lin.chi, -dq_ddphi, rtol=1e-12)


def test_equilibrium_gradient_in_gamma_is_the_implicit_one(rng):
    mech = random_mech(rng, k=30.0).replace(gravity_angle=0.8)
    grad = jax.grad(lambda a: cj.model.equilibrium(mech.replace(gravity_angle=a), 1.0))(0.8)
    h = 1e-6
    fd = (cj.model.equilibrium(mech.replace(gravity_angle=0.8 + h), 1.0)
          - cj.model.equilibrium(mech.replace(gravity_angle=0.8 - h), 1.0)) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


@pytest.mark.parametrize("gamma, hangs", [(np.pi / 2, -np.pi / 2), (-np.pi / 2, np.pi / 2),
                                          (2.5, 2.5 - np.pi)])
def test_pendulum_hangs_along_gravity(gamma, hangs):
    # Without a spring the crank hangs where gravity points, (-cos, -sin)(gamma); at
    # gamma = +-pi/2 the search starts on a flat point (dq/dphi = 0 at phi = 0).
    mech = cj.load_scene("pendulum").mech.replace(gravity_angle=gamma)
    lin = cj.linearize(mech)
    np.testing.assert_allclose(lin.phi_eq, hangs, atol=1e-12)
    assert bool(lin.stable)
    v = mech.as_dict()
    np.testing.assert_allclose(lin.omega_n, np.sqrt(v["g"] * v["m_c"] * v["s"]
                                                    / (v["m_c"] * v["s"] ** 2 + v["I_c"])),
                               rtol=1e-12)
    tr = cj.simulate(mech, lin.phi_eq, 0.0, np.linspace(0, 1, 5), solver="dopri8",
                     rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(tr.phi, hangs, atol=1e-11)


# --- validation, scenes, fit, sweep ------------------------------------------------------

@pytest.mark.parametrize("change, rule", [
    ({"gravity_angle": float("nan")}, "gravity_angle must be finite"),
    ({"gravity_angle": float("inf")}, "gravity_angle must be finite"),
    ({"g": -9.81}, "g must be >= 0"),
])
def test_invalid_values_are_named(change, rule):
    good = cj.load_scene("lab-rig").mech.as_dict()
    (field, value), = change.items()
    with pytest.raises(ValueError, match=rf"SliderCrank\.{field} .*{rule}"):
        cj.SliderCrank(**{**good, **change})
    _checked_run(field, jnp.asarray(0.5))  # valid: fine
    with pytest.raises(Exception, match=rf"SliderCrank\.{field} is invalid: {rule}"):
        _checked_run(field, jnp.asarray(value))


@functools.partial(jax.jit, static_argnums=0)
def _checked_run(field, x):
    """A simulation with `field` traced: its value is checked inside the program."""
    m = cj.load_scene("lab-rig").mech.replace(**{field: x})
    return cj.simulate(m, 0.1, 0.0, jnp.linspace(0, 0.1, 3)).phi


_SCENE = """
[mechanism]
r = 0.05
L = 0.20
b = 0.06
s = 0.025
m_c = 1.0
m_p = 0.5
m_s = 0.4
I_c = 2e-4
I_p = 1.7e-3
k = 2.0
c = 0.01
gravity_angle = 0.5
"""


def test_scene_key_round_trips(tmp_path):
    path = tmp_path / "tilted.toml"
    path.write_text(_SCENE)
    sc = cj.load_scene(path)
    assert float(sc.mech.gravity_angle) == 0.5 and float(sc.mech.g) == 9.81
    assert sc.structure.tilt
    text = cj.scene_to_toml(sc)
    assert "gravity_angle = 0.5" in text
    again = tmp_path / "again.toml"
    again.write_text(text)
    assert cj.load_scene(again).mech.as_dict() == sc.mech.as_dict()
    # The default is not written: a scene without a direction reads exactly as before.
    assert "gravity_angle" not in cj.scene_to_toml(cj.load_scene("lab-rig"))


@pytest.mark.parametrize("line, words", [("gravity_angle = nan", "gravity_angle must be finite"),
                                         ("gravity_angle = inf", "gravity_angle must be finite"),
                                         ("g = -9.81", "g must be >= 0")])
def test_cli_refuses_bad_values_in_one_line(tmp_path, capsys, line, words):
    path = tmp_path / "bad.toml"
    path.write_text(_SCENE.replace("gravity_angle = 0.5", line))
    out = tmp_path / "out.csv"
    assert cli.main(["simulate", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert words in err and err.count("\n") == 1 and not out.exists()


def test_cli_sweep_varies_gravity_angle_like_single_simulations(tmp_path, capsys, lab_rig):
    out = tmp_path / "s.npz"
    rc = cli.main(["sweep", "lab-rig", "--vary", "gravity_angle=uniform(0,1)", "--n", "3",
                   "--t1", "0.2", "--samples", "11", "--out", str(out), "--quiet",
                   "--outputs", "final_phi,final_energy"])
    assert rc == 0, capsys.readouterr().err
    with np.load(out) as z:
        gammas, ts = z["sample.gravity_angle"], z["ts"]
        phi, energy = z["output.final_phi"], z["output.final_energy"]
        solvers = [str(z["solver_names"][i]) for i in z["solver"]]
    assert gammas.shape == (3,) and np.all((gammas > 0) & (gammas < 1))
    assert len(set(gammas)) == 3
    for i in range(2):
        mech = lab_rig.mech.replace(gravity_angle=gammas[i])
        tr = cj.simulate(mech, lab_rig.phi0, lab_rig.dphi0, ts, solver=solvers[i])
        assert phi[i] == pytest.approx(float(tr.phi[-1]), rel=1e-10)
        assert energy[i] == pytest.approx(float(cj.model.energy(mech, tr.phi[-1], tr.dphi[-1])),
                                          rel=1e-10)


def test_fit_recovers_a_free_gravity_angle(lab_rig):
    truth = cj.Scene(lab_rig.mech.replace(gravity_angle=0.4), phi0=0.8)
    data = cj.synthesize(truth, t1=1.5, rate=100.0, noise_std=1e-3, seed=3)
    start = cj.Scene(lab_rig.mech, phi0=0.8)  # gravity_angle starts at 0 (compiled out)
    res = cj.fit(start, data, free=("gravity_angle", "c"), progress=False, warn=False)
    assert res.start["gravity_angle"] == 0.0 and res.converged, res.warnings
    assert abs(res.values["gravity_angle"] - 0.4) < 4 * res.stderr["gravity_angle"]
    assert res.stderr["gravity_angle"] < 0.01


def test_wrap_angle_lands_in_minus_pi_to_pi():
    from crank_jax.identify.fit_result import wrap_angle

    for x, want in ((0.0, 0.0), (np.pi, np.pi), (-np.pi, np.pi), (3 * np.pi, np.pi),
                    (0.4 + 2 * np.pi, 0.4), (-0.4 - 4 * np.pi, -0.4), (-3.0, -3.0)):
        assert wrap_angle(x) == pytest.approx(want, abs=1e-12)


def test_a_fitted_gravity_angle_is_reported_within_minus_pi_to_pi(lab_rig, tmp_path):
    # Issue 25: a fit started a turn away ended a turn away (gamma + 2 pi: the same
    # gravity), and reported and wrote it so.
    truth = cj.Scene(lab_rig.mech.replace(gravity_angle=0.4), phi0=0.8)
    data = cj.synthesize(truth, t1=1.5, rate=100.0, noise_std=1e-3, seed=3)
    start = cj.Scene(lab_rig.mech.replace(gravity_angle=0.3 + 2 * np.pi), phi0=0.8)
    res = cj.fit(start, data, free=("gravity_angle", "c"), progress=False, warn=False)
    assert res.converged, res.warnings
    g, (lo, hi) = res.values["gravity_angle"], res.ci95["gravity_angle"]
    assert -np.pi < g <= np.pi and abs(g - 0.4) < 4 * res.stderr["gravity_angle"]
    assert lo < g < hi and hi - lo < 0.1
    assert float(res.mech.gravity_angle) == pytest.approx(g, abs=1e-12)
    out = tmp_path / "fitted.toml"
    cj.save_scene(cj.identify.fitted_scene(start, res), out)
    assert float(cj.load_scene(str(out)).mech.gravity_angle) == pytest.approx(g, abs=1e-9)
