"""Nonlinear vibration analysis (crank_jax.vibration): each result against an independent
computation, by plain time stepping (`simulate`), finite differences, the linearisation or
the damped Mathieu equation's theory."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.vibration import VibrationError, mathieu_tongue
from crank_jax.vibration.chart import floquet_max
from crank_jax.vibration.orbit import periodic_orbit

#: The lab rig driven by a harmonic crank torque of 0.05 N*m: its response curve folds
#: (softening), with a hysteresis region between about 3.87 and 4.13 Hz.
TAU1 = 0.05


@pytest.fixture(scope="module")
def driven():
    sc = cj.load_scene("lab-rig")
    return eqx.tree_at(lambda s: s.torque, sc, cj.HarmonicLoad(0.0, TAU1, 4.0))


@pytest.fixture(scope="module")
def response(driven):
    return cj.forced_response(driven, (3.0, 5.5))


def _steady(scene, y0, f, periods):
    """State after `periods` forcing periods from `y0`, and phi over one more period."""
    T = 1.0 / f
    ts = jnp.concatenate([jnp.array([0.0]), periods * T + jnp.linspace(0.0, T, 2049)])
    tr = cj.simulate(scene.mech, y0[0], y0[1], ts, torque=scene.torque, rtol=1e-10,
                     atol=1e-12, solver="dopri8-adaptive", max_steps=10**6)
    return np.asarray(tr.phi[1:]), np.asarray(tr.dphi[1:])


# ---------------------------------------------------------------------------------------
# Backbone


def test_backbone_small_amplitude_limit_is_the_linearisation(lab_rig):
    bb = cj.backbone(lab_rig.mech, [1e-4, 2e-4])
    f_lin = float(cj.linearize(lab_rig.mech).omega_n) / (2 * np.pi)
    assert float(bb.linear_frequency_hz) == pytest.approx(f_lin, rel=1e-14)
    f = np.asarray(bb.frequency_hz)
    assert np.all(np.asarray(bb.ok))
    assert abs(f[0] - f_lin) / f_lin < 1e-8  # the O(A^2) shift is 3.2e-9 at 1e-4 rad
    # The shift is quadratic in the amplitude, and its extrapolation to zero is the
    # linear frequency to the solver's accuracy.
    f0 = (4 * f[0] - f[1]) / 3
    assert abs(f0 - f_lin) / f_lin < 1e-11
    np.testing.assert_allclose(np.asarray(bb.phi_max) - np.asarray(bb.phi_min),
                               2 * np.array([1e-4, 2e-4]), rtol=1e-9)


def test_backbone_against_a_released_swing(lab_rig):
    # Large swings: the period is 15-20% longer than the linear one (softening).
    amps = np.array([0.5, 1.0, 1.5])
    bb = cj.backbone(lab_rig.mech, amps)
    mech = lab_rig.mech.replace(c=0.0)
    f_lin = float(bb.linear_frequency_hz)
    assert np.all(np.asarray(bb.frequency_hz)[1:] < 0.9 * f_lin)
    for i, a in enumerate(amps):
        T, pmax, pmin = (float(np.asarray(x)[i]) for x in (bb.period, bb.phi_max, bb.phi_min))
        tr = cj.simulate(mech, pmax, 0.0, jnp.array([0.0, T / 2, T]), rtol=1e-11,
                         atol=1e-13, solver="dopri8-adaptive")
        phi, dphi = np.asarray(tr.phi), np.asarray(tr.dphi)
        w = 2 * np.pi / T
        # Released at rest at phi_max, it is at rest at phi_min half a period later and
        # back where it started after one period.
        assert abs(phi[1] - pmin) < 1e-8 * a and abs(dphi[1]) < 1e-8 * w * a
        assert abs(phi[2] - pmax) < 1e-8 * a and abs(dphi[2]) < 1e-8 * w * a
        assert pmax - pmin == pytest.approx(2 * a, rel=1e-10)


def test_backbone_is_about_the_stable_rest_and_refuses_where_there_is_none():
    # Below k_crit phi = 0 is unstable and the crank buckles: it swings about its buckled
    # rest phi_b, an equilibrium whose stiffness the linear frequency is.
    mech = cj.load_scene("near-buckling").mech.replace(k=0.5)
    from crank_jax.model import acceleration
    from crank_jax.vibration.rest import stable_rest

    bb = cj.backbone(mech, [1e-3])
    phi_b, _ = stable_rest(mech.replace(c=0.0))
    assert abs(phi_b) > 0.1 and bool(bb.ok[0])
    assert abs(float(bb.phi_max[0] + bb.phi_min[0]) / 2 - phi_b) < 1e-5  # O(A^2) offset
    rigid = mech.replace(c=0.0)
    assert abs(float(acceleration(rigid, phi_b, 0.0))) < 1e-9
    h = 1e-5
    rate = -(float(acceleration(rigid, phi_b + h, 0.0))
             - float(acceleration(rigid, phi_b - h, 0.0))) / (2 * h)
    f_lin = np.sqrt(rate) / (2 * np.pi)
    assert float(bb.linear_frequency_hz) == pytest.approx(f_lin, rel=1e-6)
    assert float(bb.frequency_hz[0]) == pytest.approx(f_lin, rel=1e-3)
    # No spring, no gravity, no load: neutral everywhere, no rest to swing about.
    with pytest.raises(VibrationError, match="k_crit"):
        cj.backbone(mech.replace(k=0.0, g=0.0), [0.1])
    with pytest.raises(VibrationError, match="increasing"):
        cj.backbone(cj.load_scene("lab-rig").mech, [0.2, 0.1])


# ---------------------------------------------------------------------------------------
# Forced response, Floquet multipliers


def test_forced_response_passes_both_folds(response):
    (b,) = response.branches
    n = len(b.freq_hz)
    for k in ("amplitude", "phi_max", "phi_min", "stable"):
        assert len(getattr(b, k)) == n
    assert b.floquet.shape == (n, 2)
    assert response.drive == "torque"
    # Softening: the peak leans left, so the curve turns back (fold 1) then forward again.
    assert len(response.folds) == 2
    hi, lo = sorted(response.folds, key=lambda x: -x["freq_hz"])
    assert 4.0 < hi["freq_hz"] < 4.3 and 3.7 < lo["freq_hz"] < 4.0
    assert lo["amplitude"] > hi["amplitude"]
    # Unstable exactly between the folds (a multiplier through +1 at each fold), stable
    # on the outer parts; the curve ends beyond f1.
    unstable = np.flatnonzero(~b.stable)
    assert unstable.size > 3 and np.all(np.diff(unstable) == 1)
    a_u = b.amplitude[unstable]
    assert hi["amplitude"] - 0.03 < a_u.min() and a_u.max() < lo["amplitude"] + 0.03
    assert np.all(b.floquet[unstable, 0] > 1) and np.all(b.floquet[b.stable, 0] < 1)
    assert b.freq_hz[-1] >= 5.5 and b.freq_hz[0] == pytest.approx(3.0)


def test_floquet_multipliers_against_perturbed_simulations(driven):
    f = 4.5
    orb = periodic_orbit(driven, f)
    assert bool(orb.ok) and bool(orb.stable)
    y0 = np.asarray(orb.y0)
    T = 1.0 / f
    # Monodromy by central differences of plain simulations, one perturbed start a column.
    cols = []
    for e, h in ((np.array([1.0, 0.0]), 1e-6), (np.array([0.0, 1.0]), 1e-5)):
        ends = [np.array([float(tr.phi[-1]), float(tr.dphi[-1])]) for tr in (
            cj.simulate(driven.mech, *(y0 + s * h * e), jnp.array([0.0, T]),
                        torque=driven.torque.__class__(0.0, TAU1, f), rtol=1e-12,
                        atol=1e-14, solver="dopri8-adaptive") for s in (1, -1))]
        cols.append((ends[0] - ends[1]) / (2 * h))
    lam = np.linalg.eigvals(np.stack(cols, axis=1))
    np.testing.assert_allclose(np.sort(np.abs(lam))[::-1], np.asarray(orb.floquet),
                               rtol=1e-6)


def test_parametric_instability_grows_at_the_floquet_rate(lab_rig):
    f, P1 = 9.0, 15.0  # inside the first tongue (f ~ 2 f_n)
    lam = float(jax.jit(lambda a, q: floquet_max(lab_rig, a, q))(P1, f))
    assert lam > 1.05
    T = 1 / f
    load = cj.HarmonicLoad(0.0, P1, f, jnp.pi / 2)
    tr = cj.simulate(lab_rig.mech, 1e-10, 0.0, jnp.array([0.0, 20 * T, 30 * T]), load=load,
                     rtol=1e-11, atol=1e-22, solver="dopri8-adaptive")
    # After 20 periods the start has turned onto the growing direction: ten more periods
    # multiply the state by lam^10.
    x20 = np.array([float(tr.phi[1]), float(tr.dphi[1])])
    x30 = np.array([float(tr.phi[2]), float(tr.dphi[2])])
    ratio = x30 / x20
    np.testing.assert_allclose(ratio, lam ** 10, rtol=1e-5)


@pytest.mark.slow
def test_forced_response_against_long_simulations(driven, response):
    """Steady states of long simulations at three frequencies; at 4.0 Hz, inside the
    hysteresis region, both stable branches: from rest (the lower one, which a sweep up
    stays on) and, as a sweep down arrives, from the steady state at 4.3 Hz (the upper
    one). Each sweep is a list of frequencies, each held for 150 periods."""
    (b,) = response.branches
    for f, sweeps in ((3.5, [[3.5]]), (4.0, [[4.0], [4.3, 4.0]]), (5.0, [[5.0]])):
        # The curve's stable orbits at f: on each stable segment that brackets f, the
        # orbit from the segment's interpolated start.
        curve = []
        for i in range(len(b.freq_hz) - 1):
            f_a, f_b = b.freq_hz[i], b.freq_hz[i + 1]
            if b.stable[i] and b.stable[i + 1] and (f_a - f) * (f_b - f) <= 0:
                w = (f - f_a) / (f_b - f_a)
                guess = jnp.asarray([b.phi0[i] + w * (b.phi0[i + 1] - b.phi0[i]),
                                     b.dphi0[i] + w * (b.dphi0[i + 1] - b.dphi0[i])])
                orb = periodic_orbit(driven, f, guess=guess)
                assert bool(orb.ok) and bool(orb.stable)
                amp_i = b.amplitude[i] + w * (b.amplitude[i + 1] - b.amplitude[i])
                assert float(orb.amplitude) == pytest.approx(amp_i, rel=1e-2)
                curve.append(float(orb.amplitude))
        assert len(curve) == len(sweeps), f
        brute = []
        for sweep in sweeps:
            y0 = np.zeros(2)
            for f_s in sweep:
                sc = eqx.tree_at(lambda s: s.torque.freq_hz, driven, jnp.asarray(f_s))
                phi, dphi = _steady(sc, y0, f_s, 150)
                y0 = np.array([phi[-1], dphi[-1]])
            brute.append((phi.max() - phi.min()) / 2)
        # 2049 samples per period: the sampled extreme is within 2e-6 of the true one.
        np.testing.assert_allclose(sorted(brute), sorted(curve), rtol=5e-6)


# ---------------------------------------------------------------------------------------
# Parametric resonance


def test_tongue_edges_against_mathieu_theory(lab_rig):
    lin = cj.linearize(lab_rig.mech)
    xi_P = float(cj.linearize(lab_rig.mech, cj.ConstantLoad(1.0)).xi) - float(lin.xi)
    f_n = float(lin.omega_n) / (2 * np.pi)
    freqs = jnp.linspace(1.8 * f_n, 2.2 * f_n, 401)
    fm = jax.jit(jax.vmap(lambda a, q: floquet_max(lab_rig, a, q), (None, 0)))
    errs = []
    for h in (0.2, 0.1):  # h = xi_P P1 / xi0, well above the damping's threshold 4 zeta
        P1 = h * float(lin.xi) / abs(xi_P)
        m = np.asarray(fm(P1, freqs)) - 1
        cross = np.flatnonzero(np.diff(np.sign(m)) != 0)
        assert cross.size == 2
        edges = [float(freqs[i] - m[i] * (freqs[i + 1] - freqs[i]) / (m[i + 1] - m[i]))
                 for i in cross]
        theory = mathieu_tongue(lab_rig, P1)
        errs.append(np.abs(np.array(edges) - theory) / (2 * f_n))
        # First-order harmonic balance leaves O(h^2) (the undamped edges' next term is
        # -h^2/64 in f / 2 f_n).
        assert np.all(errs[-1] < h * h / 16), (edges, theory)
    # ... and the error falls as h^2: halving h quarters it.
    assert np.all(errs[1] < errs[0] / 3)


def test_stability_chart_shape_and_refusals(lab_rig):
    f_n = float(cj.linearize(lab_rig.mech).omega_n) / (2 * np.pi)
    ch = cj.stability_chart(lab_rig, (0.0, 20.0), (1.5 * f_n, 2.5 * f_n), grid=4)
    assert ch.floquet_max.shape == (4, 4) and ch.stable.shape == (4, 4)
    assert np.all(ch.stable[0])  # no forcing: damped, stable
    assert not ch.stable[-1, 1]  # inside the first tongue at 20 N
    with pytest.raises(VibrationError, match="e = 0"):
        cj.stability_chart(eqx.tree_at(lambda s: s.mech, lab_rig, lab_rig.mech.replace(
            e=0.01)), (0, 1), (1, 2), grid=3)
    with pytest.raises(VibrationError, match="T_c"):
        cj.stability_chart(eqx.tree_at(lambda s: s.mech, lab_rig, lab_rig.mech.replace(
            T_c=0.01)), (0, 1), (1, 2), grid=3)
    with pytest.raises(VibrationError, match="harmonic drive"):
        cj.forced_response(lab_rig, (3.0, 5.0))
    both = eqx.tree_at(lambda s: (s.load, s.torque), lab_rig,
                       (cj.HarmonicLoad(0.0, 1.0, 3.0), cj.HarmonicLoad(0.0, 0.05, 4.0)))
    with pytest.raises(VibrationError, match=r"\[load\] must be absent or constant"):
        cj.forced_response(both, (3.0, 5.0))


# ---------------------------------------------------------------------------------------
# Derivatives


def test_grad_of_orbit_amplitude_wrt_stiffness_matches_finite_differences(driven):
    f = 4.0

    def amp(k):
        return periodic_orbit(eqx.tree_at(lambda s: s.mech.k, driven, k), f).amplitude

    k = jnp.asarray(2.0)
    g = float(jax.grad(amp)(k))
    h = 1e-5
    fd = float((amp(k + h) - amp(k - h)) / (2 * h))
    assert g == pytest.approx(fd, rel=1e-6)
    assert abs(g) > 0.1
