"""The linearisation about the static equilibrium phi_eq (offset, constant loads)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_mech

import crank_jax as cj
from crank_jax.cli import main


def _offset_mech(rng, **kw):
    m = random_mech(rng, **kw)
    return m.replace(e=rng.uniform(-0.5, 0.5) * float(m.L - m.r), c_s=rng.uniform(0, 3))


def test_paper_case_comes_back_exactly(rng):
    # e = 0 and no constant torque: phi_eq = 0 and the closed form of eq. 33 (corrected).
    for _ in range(10):
        mech = random_mech(rng, k=rng.uniform(20, 40))
        P = rng.uniform(-5, 5)
        lin = cj.linearize(mech, cj.ConstantLoad(P))
        v = mech.as_dict()
        r, L, b, s, g = v["r"], v["L"], v["b"], v["s"], v["g"]
        mu = (v["m_c"] * s**2 + v["I_c"] + v["m_p"] * r**2 * (1 - b / L) ** 2
              + v["I_p"] * r**2 / L**2)
        soft = (g * (v["m_c"] * s + v["m_p"] * r * (1 + r * b / L**2) + v["m_s"] * r * (1 + r / L))
                + P * r * (1 + r / L))
        assert float(lin.phi_eq) == 0.0
        np.testing.assert_allclose(lin.mu, mu, rtol=1e-13)
        np.testing.assert_allclose(lin.chi, v["c"], rtol=1e-15)
        np.testing.assert_allclose(lin.xi, v["k"] - soft, rtol=1e-12)
        np.testing.assert_allclose(lin.k_crit, soft, rtol=1e-13)


def _rhs(mech, P, tau):
    def f(phi, dphi):
        return (cj.model.generalized_force(mech, phi, dphi, 0.0, load=P, torque=tau)
                - cj.model.coriolis(mech, phi) * dphi**2)
    return f


def test_offset_and_constant_loads_equal_jacobian_at_phi_eq(rng):
    for _ in range(15):
        mech = _offset_mech(rng, k=rng.uniform(10, 40))
        P, tau = rng.uniform(-5, 5), rng.uniform(-0.3, 0.3)
        lin = cj.linearize(mech, cj.ConstantLoad(P), cj.ConstantLoad(tau))
        phi_eq = float(lin.phi_eq)
        f = _rhs(mech, P, tau)
        assert abs(phi_eq) < 1.0
        np.testing.assert_allclose(f(phi_eq, 0.0), 0.0, atol=1e-12)
        dq_dphi, dq_ddphi = jax.jacfwd(f, argnums=(0, 1))(phi_eq, 0.0)
        np.testing.assert_allclose(lin.mu, cj.model.mass(mech, phi_eq), rtol=1e-13)
        np.testing.assert_allclose(lin.xi, -dq_dphi, rtol=1e-10, atol=1e-11)
        np.testing.assert_allclose(lin.chi, -dq_ddphi, rtol=1e-12)
        np.testing.assert_allclose(lin.k_crit, mech.k - lin.xi, rtol=1e-12)


def test_crank_at_rest_at_phi_eq_stays_there():
    mech = cj.load_scene("lab-rig").mech.replace(e=0.01)
    lin = cj.linearize(mech, cj.ConstantLoad(2.0), cj.ConstantLoad(0.05))
    assert bool(lin.stable) and float(lin.phi_eq) != 0.0
    ts = np.linspace(0, 1, 11)
    tr = cj.simulate(mech, lin.phi_eq, 0.0, ts, load=2.0, torque=0.05, solver="dopri8",
                     rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(tr.phi, float(lin.phi_eq), atol=1e-11)


def test_small_oscillations_about_phi_eq_have_omega_n():
    mech = cj.load_scene("lab-rig").mech.replace(e=0.01, c=0.0)
    lin = cj.linearize(mech, None, cj.ConstantLoad(0.05))
    period = 2 * np.pi / float(lin.omega_n)
    ts = np.linspace(0, period, 2001)
    tr = cj.simulate(mech, lin.phi_eq + 1e-4, 0.0, ts, torque=0.05, solver="dopri8",
                     rtol=1e-12, atol=1e-16)
    x = np.asarray(tr.phi) - float(lin.phi_eq)
    np.testing.assert_allclose(x[-1], 1e-4, rtol=1e-3)  # back after one linear period
    assert x[1000] < -0.99e-4  # and opposite at half of it


def test_jit_vmap_and_implicit_gradient(rng):
    mechs = [_offset_mech(rng, k=rng.uniform(10, 40)) for _ in range(4)]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *mechs)
    lin_b = jax.jit(jax.vmap(lambda m: cj.linearize(m, cj.ConstantLoad(1.0))))(batch)
    direct = cj.linearize(batch, cj.ConstantLoad(1.0))
    for i, m in enumerate(mechs):
        one = cj.linearize(m, cj.ConstantLoad(1.0))
        np.testing.assert_allclose(lin_b.phi_eq[i], one.phi_eq, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(direct.xi[i], one.xi, rtol=1e-12)
    m = mechs[0]
    grad = jax.grad(lambda e: cj.model.equilibrium(m.replace(e=e), 1.0))(m.e)
    h = 1e-6
    fd = (cj.model.equilibrium(m.replace(e=m.e + h), 1.0)
          - cj.model.equilibrium(m.replace(e=m.e - h), 1.0)) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


def test_no_equilibrium_is_nan_and_unstable():
    # A constant torque beyond what any angle can hold: no root of q(phi, 0) near 0.
    mech = cj.load_scene("pendulum").mech
    lin = cj.linearize(mech, None, cj.ConstantLoad(100.0))
    assert np.isnan(lin.phi_eq) and not bool(lin.stable)
    assert np.isfinite(lin.mu) and np.isfinite(lin.xi)


def test_coulomb_note():
    mech = cj.load_scene("lab-rig").mech
    assert cj.model.coulomb_friction_note(mech) is None
    assert "T_c" in cj.model.coulomb_friction_note(mech.replace(T_c=0.1))
    assert "F_s" in cj.model.coulomb_friction_note(mech.replace(F_s=0.1))


def test_cli_linearize_reports_phi_eq_and_coulomb_note(tmp_path, capsys):
    text = cj.scene_to_toml(cj.load_scene("lab-rig")).replace("[mechanism]",
                                                              "[mechanism]\ne = 0.01\nT_c = 0.02")
    path = tmp_path / "rig.toml"
    path.write_text(text)
    assert main(["linearize", str(path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    lin = cj.linearize(cj.load_scene(path).mech)
    assert d["phi_eq"] == pytest.approx(float(lin.phi_eq), rel=1e-15) and d["phi_eq"] != 0
    assert main(["linearize", str(path)]) == 0
    out = capsys.readouterr().out
    assert "phi_eq" in out and "Coulomb friction (T_c)" in out
