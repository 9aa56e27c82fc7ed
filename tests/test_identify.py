"""Parameter identification: recovery, sensitivities, identifiability, robustness."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli.identify import DEMO, demo_data
from crank_jax.identify.problem import build_problem


@pytest.fixture(scope="module")
def demo_fit():
    """The README demo: 5 s of noisy lab-rig data under a known harmonic torque."""
    scene, data = demo_data(seed=1)
    res = cj.fit(scene, data, free=("k", "c", "phi0", "dphi0"), init=DEMO["start"],
                 progress=False)
    return scene, data, res


def test_recover_k_c_state_under_known_harmonic_torque(demo_fit):
    scene, data, res = demo_fit
    truth = {"k": float(scene.mech.k), "c": float(scene.mech.c), "phi0": DEMO["phi0"],
             "dphi0": 0.0}
    assert res.converged and res.identifiable, res.warnings
    assert res.start["k"] == DEMO["start"]["k"]  # the start really was off
    for name, true in truth.items():
        est, se = res.values[name], res.stderr[name]
        assert se is not None and se > 0
        assert abs(est - true) < 3 * se, (name, est, true, se)
        if true != 0.0:
            assert abs(est - true) < 0.01 * abs(true), (name, est, true)
        lo, hi = res.ci95[name]
        assert lo < est < hi
    # sigma from the residuals matches the synthetic noise
    assert res.rms_residual == pytest.approx(DEMO["noise_std"], rel=0.1)
    corr = res.correlation
    np.testing.assert_allclose(np.diag(corr), 1.0)
    np.testing.assert_allclose(corr, corr.T)
    assert math.isfinite(res.condition_number) and res.condition_number >= 1


def test_fit_json_has_exactly_the_documented_keys(demo_fit):
    _, _, res = demo_fit
    doc = json.loads(json.dumps(res.to_json()))
    assert list(doc) == ["estimates", "identifiable", "unidentifiable_directions",
                         "rms_residual", "n_samples", "converged", "iterations", "seconds",
                         "warnings"]
    assert set(doc["estimates"]) == {"k", "c", "phi0", "dphi0"}
    k = doc["estimates"]["k"]
    assert k["ci95"][0] < k["value"] < k["ci95"][1] and k["stderr"] > 0
    assert doc["n_samples"] == 1001 and doc["converged"] is True


def _tiny_problem(adjoint, scene, data):
    return build_problem(scene.mech, [(data, scene.load, scene.torque, 0.5, 0.1)],
                         ("k", "c", "m_s", "phi0", "dphi0"), {"k": 2.0, "c": 0.002,
                                                              "m_s": 0.4},
                         [1], solver="tsit5", rtol=1e-11, atol=1e-13, max_steps=100_000,
                         adjoint=adjoint)


def test_forward_reverse_and_finite_difference_sensitivities_agree(lab_rig):
    scene = cj.Scene(lab_rig.mech, torque=cj.HarmonicLoad(0.0, 0.2, 3.0))
    data = cj.synthesize(scene, t1=0.6, rate=50.0)
    fwd = _tiny_problem("forward", scene, data)
    rev = _tiny_problem("reverse", scene, data)
    z = jnp.asarray(fwd.to_z([2.1, 0.003, 0.35, 0.5, 0.1]))
    Jf = np.asarray(jax.jit(jax.jacfwd(lambda x: fwd.residuals(x)[0]))(z))
    Jr = np.asarray(jax.jit(jax.jacrev(lambda x: rev.residuals(x)[0]))(z))
    res = jax.jit(lambda x: fwd.residuals(x)[0])
    h = 1e-5
    Jd = np.stack([(np.asarray(res(z.at[j].add(h))) - np.asarray(res(z.at[j].add(-h))))
                   / (2 * h) for j in range(z.shape[0])], axis=1)
    scale = np.max(np.abs(Jf), axis=0)
    assert np.all(scale > 0)
    np.testing.assert_allclose(Jf / scale, Jr / scale, atol=1e-8)
    np.testing.assert_allclose(Jf / scale, Jd / scale, atol=2e-5)


def test_all_seven_free_on_free_decay_is_flagged_with_the_scale_message(lab_rig):
    data = cj.synthesize(lab_rig, t1=3.0, rate=100.0, noise_std=1e-3, seed=1)
    seven = ("m_c", "m_p", "m_s", "I_c", "I_p", "k", "c")
    with pytest.warns(cj.IdentifiabilityWarning, match="common scale"):
        res = cj.fit(lab_rig, data, free=seven + ("phi0", "dphi0"), progress=False)
    assert res.converged and not res.identifiable
    msg = ("m_c, m_p, m_s, I_c, I_p, k and c are determined only up to a common scale: fix "
           "one of them or supply a known load")
    assert msg in res.unidentifiable_directions
    doc = res.to_json()
    assert doc["identifiable"] is False
    for name in seven:
        assert doc["estimates"][name]["stderr"] is None
        assert doc["estimates"][name]["ci95"] is None
        assert math.isfinite(doc["estimates"][name]["value"])
    # The initial state is still determined, and says so.
    assert doc["estimates"]["phi0"]["stderr"] is not None
    # The second exact symmetry (the coupler's equivalent point masses) is named too.
    assert any("m_p trades against" in d for d in res.unidentifiable_directions)
    assert any("common scale" in w for w in doc["warnings"])


def test_fixing_one_mass_restores_identifiability_of_k_and_c(demo_fit):
    # With a known torque the scale is fixed: k and c are determined (the demo fit).
    _, _, res = demo_fit
    assert res.identifiable and res.unidentifiable_directions == []


def test_pendulum_irregular_samples_starting_late():
    scene = cj.load_scene("pendulum")
    data = cj.synthesize(scene, t1=4.0, rate=100.0, t_start=1.37, drop=0.25, jitter_std=2e-4,
                         noise_std=2e-3, seed=5)
    assert data.ts[0] == pytest.approx(1.37) and np.ptp(np.diff(data.ts)) > 0.005
    res = cj.fit(scene, data, free=("I_c", "c", "phi0", "dphi0"),
                 init={"I_c": 3e-4, "c": 1e-3}, progress=False)
    assert res.converged and res.identifiable, res.warnings
    truth = {"I_c": float(scene.mech.I_c), "c": float(scene.mech.c)}
    # The true state at the first sample, from an exact simulation.
    exact = scene.simulate(jnp.asarray([0.0, data.ts[0]]))
    truth["phi0"], truth["dphi0"] = float(exact.phi[1]), float(exact.dphi[1])
    for name, true in truth.items():
        assert abs(res.values[name] - true) < 3.5 * res.stderr[name], (name, res.values[name],
                                                                          true)


def test_never_crash_never_nan():
    scene = cj.load_scene("pendulum")
    data = cj.synthesize(scene, t1=4.0, rate=100.0, t_start=1.37, drop=0.25, jitter_std=2e-4,
                         noise_std=2e-3, seed=5)
    # A two-step budget cannot converge: a result, not an exception.
    with pytest.warns(cj.ConvergenceWarning, match="did not converge"):
        with pytest.warns(cj.IdentifiabilityWarning):  # judged at a point far off
            res = cj.fit(scene, data, free=("I_c", "c", "phi0", "dphi0"),
                         init={"I_c": 3e-3, "c": 1e-1}, max_steps=2, progress=False)
    assert not res.converged and "max_steps" in res.message
    assert res.warnings[0].startswith("fit did not converge")
    assert all(math.isfinite(v) for v in res.values.values())
    assert all(v is None for v in res.stderr.values())
    assert "converged" in res.to_json() and res.to_json()["converged"] is False


def test_request_errors(lab_rig):
    data = cj.synthesize(lab_rig, t1=0.2, rate=50.0)
    with pytest.raises(ValueError, match="unknown free parameter"):
        cj.fit(lab_rig, data, free=("k", "mass"))
    with pytest.raises(ValueError, match="cannot be free"):
        cj.fit(lab_rig, data, free=("tau1",))
    with pytest.raises(ValueError, match="log space"):
        cj.fit(lab_rig, data, free=("k",), init={"k": 0.0})
    with pytest.raises(ValueError, match="too few samples"):
        cj.fit(lab_rig, data, free=("m_c", "m_p", "m_s", "I_c", "I_p", "k", "c", "phi0",
                                    "dphi0", "r", "L"))
