"""Estimates that stay physical: damping and friction as bounded coordinates, a load
that starts at 0 scaled by the record, a runaway never called converged, segments sized
for a channel that does not measure the angle, an escalation that stops when it makes no
progress."""

import dataclasses
import math
import types

import jax
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.identify.attempt import in_range
from crank_jax.identify.coordinates import coordinate, coordinates
from crank_jax.identify.escalation import PROGRESS, _no_progress
from crank_jax.identify.outcome import Run
from crank_jax.identify.physical import RUNAWAY, Ranges, load_scale
from crank_jax.identify.strategy import BLIND_DRIFT, n_segments
from crank_jax.model.loads import ConstantLoad

jax.config.update("jax_enable_x64", True)

LAB = cj.load_scene("lab-rig")


# ------------------------------------------------------------------ coordinates -------

def test_damping_is_a_bounded_coordinate_in_both_shootings():
    # Single shooting: folded, `value = ref |z|`, whatever the start (a true 0 is
    # reachable); multiple shooting: folded too, never a wall at 0 for any field that
    # cannot be negative (an inertia, a mass, a stiffness).
    assert coordinates("c", 0.004, LAB.mech, None, linear=False) == (False, 0.004, True)
    for name, v in (("c", 0.004), ("I_c", 0.01), ("k", 2.0), ("m_s", 0.3)):
        log, ref, folded = coordinates(name, v, LAB.mech, None, linear=True)
        assert (log, ref, folded) == (False, v, True), name
    # The signed offset stays linear, not folded.
    assert coordinates("e", 0.01, LAB.mech, None, linear=True)[2] is False


def test_a_load_that_starts_at_zero_takes_the_records_torque_scale():
    assert coordinate("tau0", 0.0, LAB.mech, torque=0.6) == (False, 0.6)
    assert coordinate("tau1", 0.0, LAB.mech, torque=0.6) == (False, 0.6)
    log, ref = coordinate("P0", 0.0, LAB.mech, torque=0.6)
    assert not log and ref == pytest.approx(0.6 / float(LAB.mech.r))
    # A start that is not 0 keeps its own scale; no torque scale keeps the old unit.
    assert coordinate("tau0", -0.3, LAB.mech, torque=0.6) == (False, 0.3)
    assert coordinate("tau0", 0.0, LAB.mech) == (False, 1e-3)


def test_load_scale_is_inertia_times_the_records_acceleration():
    # A coast-down at a constant deceleration a: the scale is mu a, the drag torque.
    mech = LAB.mech.replace(k=0.0, g=0.0)
    mu = float(cj.linearize(mech).mu)
    ts = np.linspace(0.0, 1.0, 501)
    a = -30.0
    angle = 100.0 * ts + 0.5 * a * ts**2
    rec = types.SimpleNamespace(ts=ts)
    assert load_scale(mech, [rec], [angle], [None]) == pytest.approx(mu * 30.0, rel=1e-6)


# ------------------------------------------------------------------ runaway -----------

def _ranges(**over):
    kw = dict(start={"I_c": 0.002, "c": 0.01, "tau0": 0.1, "P0": 0.0}, speeds=(8.0,),
              torque=0.5, lever=0.05)
    kw.update(over)
    return Ranges(**kw)


def test_ranges_name_what_ran_off_and_pass_what_did_not():
    r = _ranges()
    names = ("I_c", "c", "tau0", "P0", "phi0", "dphi0")
    assert r.ran_off(names, (0.0021, 0.0, 0.2, 3.0, 1.0, 19.0)) is None
    why = r.ran_off(names, (240.0, 3205.0, -23558.0, -142e3, 1.0, -109.0))
    for n in ("I_c = 240", "c = 3205", "tau0 = -2.356e+04", "P0 = -1.42e+05",
              "dphi0 = -109"):
        assert n in why, (n, why)
    assert "ran off" in why and "channel" in why
    # An inertia collapsing (the common scale running off towards 0) is a runaway too; a
    # damping or a stiffness at 0 is not.
    assert "I_c" in r.ran_off(("I_c",), (0.002 / (2 * RUNAWAY),))
    assert r.ran_off(("c",), (0.0,)) is None
    # Per-record names are judged against their own record.
    assert "dphi0[1]" in _ranges(speeds=(20.0, 5.0)).ran_off(("dphi0[1]",), (60.0,))
    assert _ranges(speeds=(20.0, 5.0)).ran_off(("dphi0[0]",), (60.0,)) is None


def test_a_runaway_run_is_never_converged():
    ss = types.SimpleNamespace(names=("I_c", "tau0"), p=2,
                               host_values=lambda z: np.asarray(z, dtype=float))
    plan = types.SimpleNamespace(single=ss, ranges=_ranges())
    good = Run(np.array([0.0021, 0.2]), 1.0, 5, True, "converged")
    assert in_range(plan, good) is good
    far = in_range(plan, good._replace(z=np.array([0.0021 * 1e5, 0.2])))
    assert not far.converged and far.termination["verdict"] == "ran off"
    assert "I_c" in far.message and far.message == far.termination["words"]
    # No ranges (a plan that did not judge them): the run as it was.
    plan_none = types.SimpleNamespace(single=ss, ranges=None)
    assert in_range(plan_none, far._replace(converged=True)).converged


# ------------------------------------------------------------------ segments ----------

def test_a_channel_blind_to_the_angle_gets_short_segments():
    # 10 turns in 5 s, the start model 5 turns short: 31 rad of predicted drift.
    n_seen, _ = n_segments(5.0, None, None, "auto", None, 10.0, 5.0)
    n_blind, _ = n_segments(5.0, None, None, "auto", None, 10.0, 5.0, blind=True)
    assert n_seen == 6
    assert n_blind >= math.ceil(2 * math.pi * 5 / BLIND_DRIFT) and n_blind == 24
    # Oscillations too: the start period 1/6 off over 20 periods, 20.9 rad of drift.
    assert n_segments(10.0, 0.5, 0.6, "auto", None)[0] == 12
    n_osc, _ = n_segments(10.0, 0.5, 0.6, "auto", None, blind=True)
    assert n_osc == 16 >= math.ceil(2 * math.pi * 20 / 6 / BLIND_DRIFT)
    # A requested count or single shooting stays as asked.
    assert n_segments(5.0, None, None, "auto", 4, 10.0, 5.0, blind=True)[0] == 4
    assert n_segments(5.0, None, None, "single", None, 10.0, 5.0, blind=True)[0] == 1


# ------------------------------------------------------------------ escalation --------

def test_escalation_stops_at_a_try_that_makes_no_progress():
    def run(cost, converged=True):
        return (Run(np.zeros(1), cost, 10, converged, ""), "")

    unit2 = 1e-4
    big = 1e3  # far above the noise: 1e7 noise units of cost
    assert not _no_progress([run(big)], unit2)
    # A second converged try that lowers the cost by much more than PROGRESS: go on.
    assert not _no_progress([run(big), run(big - 10 * PROGRESS * unit2)], unit2)
    # One that lands higher, or lower by less than PROGRESS units: stop.
    assert _no_progress([run(big), run(big + 5.0)], unit2)
    assert _no_progress([run(big), run(big - 0.5 * PROGRESS * unit2)], unit2)
    # A failed try says nothing: judged among the converged ones.
    assert not _no_progress([run(big), run(big + 5.0, converged=False)], unit2)


# ------------------------------------------------------------------ fits --------------

def test_damping_whose_optimum_is_zero_converges_in_multiple_shooting():
    # Undamped truth, fitted from c = 0.004 by multiple shooting. With c linear there
    # (a step below 0 fails every solve), LM stalled on that wall or ended with c "not
    # determined" and the fit "identifiable: NO"; folded, c reaches its bound with an
    # interval [0, v + 1.96 se].
    truth = dataclasses.replace(LAB, mech=LAB.mech.replace(c=0.0))
    data = cj.synthesize(truth, t1=2.5, rate=80.0, noise_std=1e-3, seed=2)
    start = dataclasses.replace(LAB, mech=LAB.mech.replace(c=0.004, k=2.2))
    res = cj.fit(start, data, free=("k", "c", "phi0", "dphi0"), shooting="multiple",
                 progress=False, warn=False)
    assert res.converged and res.identifiable, res.summary()
    lo, hi = res.ci95["c"]
    assert lo == 0.0 and 0.0 < hi < 1e-4
    assert res.values["k"] == pytest.approx(2.0, rel=1e-3)
    assert res.iterations < 20


def test_a_drag_torque_started_at_zero_is_determined():
    # A flywheel coasting down from 110 rad/s against a constant drag of 0.6 N*m, the
    # drag started at exactly 0. At the old unit (1e-3 N*m) its column was so small that
    # the fit held it fixed as a flat direction: "not determined", "identifiable: NO".
    mech = cj.SliderCrank(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.5, m_p=0.3, m_s=0.4,
                          I_c=0.02, I_p=2e-3, k=0.0, c=0.0, g=9.81, e=0.0)

    def scene(tau0, **over):
        return cj.Scene(mech.replace(**over), torque=ConstantLoad(tau0), phi0=0.0,
                        dphi0=110.0, t1=1.0, name="coast")

    data = cj.synthesize(scene(-0.6), t1=1.0, rate=1000.0, noise_std=1e-4, seed=4)
    data = dataclasses.replace(data, load=None, torque=None)
    res = cj.fit(scene(0.0, I_c=0.03), data, free=("I_c", "tau0", "phi0", "dphi0"),
                 shooting="single", progress=False, warn=False)
    assert res.converged and res.identifiable, res.summary()
    lo, hi = res.ci95["tau0"]
    assert lo < -0.6 < hi and hi - lo < 0.01
    assert res.values["I_c"] == pytest.approx(0.02, rel=1e-3)
