"""Start values from the motion (issue 25, item 2): the slider position's angle across the
dead centres, and the equation of motion solved for the parameters that enter it
linearly."""

from __future__ import annotations

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.identify import angle
from crank_jax.identify.angle import slide_angle
from crank_jax.identify.fit_plan import make_plan, recoordinate
from crank_jax.identify.motion_start import motion_start
from crank_jax.identify.request import normalize
from crank_jax.model.loads import InputLoad

TRUTH = dict(tau_gain=0.03, c=0.01, T_c=0.02)
FREE = ("tau_gain", "c", "T_c", "phi0", "dphi0")
ENCODER = cj.Sensor("phi", "wheel_deg", "deg", scale=-1.0, offset=-3.083)


def motor_rig(volts, gain=TRUTH["tau_gain"], c=TRUTH["c"], T_c=TRUTH["T_c"], sensors=()):
    """A DC-motor-driven offset crank on a tilted mount (the README's rotating rig)."""
    mech = cj.SliderCrank(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.1, m_p=0.05, m_s=0.1,
                          I_c=2e-3, I_p=2e-4, k=0.0, c=c, g=9.81, e=0.008, T_c=T_c,
                          w_c=0.05, gravity_angle=0.35)
    torque = InputLoad(gain=gain, column="volts")
    if volts is not None:
        torque = torque.bind([0.0, 4.0], [volts, volts], interp="linear")
    return cj.Scene(mech, torque=torque, phi0=0.0, dphi0=5.0, t1=2.0,
                    sensors=tuple(sensors))


def test_slide_angle_bridges_the_dead_centres(monkeypatch):
    # Near a dead centre dx_s/dphi -> 0, so a slider position's noise makes an unbounded
    # angle error (about sqrt(2 noise / r) at the centre itself); the estimate there is
    # the straight line in time across it.
    scene = motor_rig(6.0)
    ts = np.linspace(0.5, 2.0, 301)  # 200 Hz, about 3.5 turns
    traj = scene.simulate(np.concatenate([[0.0], ts]))
    phi = np.asarray(traj.phi)[1:]
    x = np.asarray(cj.model.geometry_at(scene.mech, phi).x_s)
    noisy = x + np.random.default_rng(0).normal(0.0, 5e-5, x.shape)

    def worst(error):
        monkeypatch.setattr(angle, "ANGLE_ERROR", error)
        est = slide_angle(scene.mech, ts, noisy, direction=1.0, phi_start=float(phi[0]))
        return np.max(np.abs(est - phi))

    default = angle.ANGLE_ERROR
    assert worst(np.inf) > 0.04  # every sample inverted, dead centres included
    assert worst(default) < 0.02
    # Exact positions are inverted everywhere, dead centres included.
    exact = slide_angle(scene.mech, ts, x, direction=1.0, phi_start=float(phi[0]))
    assert np.max(np.abs(exact - phi)) < 1e-3


def _plan(records, start):
    req = normalize(start, records, FREE, init="scene", method="lm", shooting="auto",
                    segments=None, multistart=1, seed=0, max_steps=None, tol=1e-8,
                    sigma=None, profile=None, window=None, progress=False, warn=False,
                    per_record=(), force=None)
    return req, make_plan(req)


def test_motion_start_solves_the_linear_parameters_from_the_motion():
    # Dense, clean records at two voltages: the equation of motion on the smoothed angle
    # gives the motor's gain, the damping and the Coulomb friction, from start values 2x
    # off with no friction (the smoothing's bias is what is left, about 0.3%).
    records = [cj.synthesize(motor_rig(v, sensors=(ENCODER,)), t_start=0.5, rate=1000,
                             noise_std={"phi": 1e-9}, seed=i, sensors=(ENCODER,))
               for i, v in enumerate((6.0, 9.0))]
    req, plan = _plan(records, motor_rig(None, gain=0.015, c=0.02, T_c=0.0,
                                         sensors=(ENCODER,)))
    ss = plan.single
    z = plan.z0[:ss.p] if plan.shoot is ss else recoordinate(plan.shoot, ss, plan.z0)
    zs = motion_start(ss, z, req.records, req.angles, plan.periods)
    got = dict(zip(ss.names, np.asarray(ss.values(zs))))
    for name, want in TRUTH.items():
        assert got[name] == pytest.approx(want, rel=1e-2), name
    # The records' states are not the equation's to set: they stay as planned.
    for name in ("phi0[0]", "dphi0[0]", "phi0[1]", "dphi0[1]"):
        assert got[name] == pytest.approx(dict(zip(ss.names, np.asarray(ss.values(z))))[name])


def test_motion_start_leaves_a_nonlinear_parameter_at_its_start():
    # r enters the geometry, not linearly: it keeps its start value, while c is solved.
    records = [cj.synthesize(motor_rig(6.0, sensors=(ENCODER,)), t_start=0.5, rate=500,
                             noise_std={"phi": 1e-9}, seed=0, sensors=(ENCODER,))]
    start = motor_rig(6.0, c=0.02, sensors=(ENCODER,))
    req = normalize(start, records, ("c", "r", "phi0", "dphi0"), init="scene", method="lm",
                    shooting="single", segments=None, multistart=1, seed=0, max_steps=None,
                    tol=1e-8, sigma=None, profile=None, window=None, progress=False,
                    warn=False, per_record=(), force=None)
    plan = make_plan(req)
    ss = plan.single
    zs = motion_start(ss, plan.z0[:ss.p], req.records, req.angles, plan.periods)
    got = dict(zip(ss.names, np.asarray(ss.values(zs))))
    assert got["r"] == 0.05
    assert got["c"] == pytest.approx(TRUTH["c"], rel=2e-2)


@pytest.mark.slow
def test_slide_only_record_that_stalls_is_mended_by_the_motion_start():
    # Issue 25: seed 22 of experiments/rotating_rig.py's coverage run (`--coverage`),
    # slide sensor only. From the generic start the fit does not converge; the start from
    # the motion does, to the truth.
    import importlib.util
    import pathlib

    path = pathlib.Path(__file__).parents[1] / "experiments" / "rotating_rig.py"
    spec = importlib.util.spec_from_file_location("rotating_rig", path)
    rr = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rr)
    res = rr.fit_config(rr.CONFIGS["slide"], seed=1022)
    assert res.converged, res.message
    assert any("a start from the motion" in w for w in res.warnings), res.warnings
    for name, want in TRUTH.items():
        lo, hi = res.ci95[name]
        assert lo <= want <= hi, (name, res.values[name], res.ci95[name])


def test_motion_start_keeps_its_values_in_range_instead_of_discarding_them():
    # The truth adds a constant assisting torque (0.01 N*m) that the fitted model lacks:
    # the free least squares puts the Coulomb friction at -0.01 N*m, outside its domain.
    # The start from the motion was then discarded whole (None); bounded, T_c sits at 0
    # and the gain and damping are still solved from the motion.
    def truth(volts):
        scene = motor_rig(volts, T_c=0.0, sensors=(ENCODER,))
        torque = InputLoad(gain=TRUTH["tau_gain"], column="volts", X0=0.01).bind(
            [0.0, 4.0], [volts, volts], interp="linear")
        return cj.Scene(scene.mech, torque=torque, phi0=0.0, dphi0=5.0, t1=2.0,
                        sensors=(ENCODER,))

    records = [cj.synthesize(truth(v), t_start=0.5, rate=1000, noise_std={"phi": 1e-9},
                             seed=i, sensors=(ENCODER,)) for i, v in enumerate((6.0, 9.0))]
    req, plan = _plan(records, motor_rig(None, gain=0.015, c=0.02, T_c=0.005,
                                         sensors=(ENCODER,)))
    ss = plan.single
    z = plan.z0[:ss.p] if plan.shoot is ss else recoordinate(plan.shoot, ss, plan.z0)
    zs = motion_start(ss, z, req.records, req.angles, plan.periods)
    assert zs is not None
    got = dict(zip(ss.names, np.asarray(ss.values(zs))))
    assert got["T_c"] == 0.0
    assert 0.0 < got["c"] and got["c"] == pytest.approx(TRUTH["c"], rel=0.3)
    assert got["tau_gain"] == pytest.approx(TRUTH["tau_gain"], rel=0.3)
