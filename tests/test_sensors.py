"""Sensors: the measurement model's outputs, units and calibration, records read through
sensors, and fits and validations per channel (DESIGN.md section 1, second step)."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_mech

import crank_jax as cj
from crank_jax.cli import main
from crank_jax.identify import fitted_scene
from crank_jax.identify.angle import slide_angle
from crank_jax.model.outputs import OUTPUT_NAMES, output
from crank_jax.records.sensors import (
    CHANNELS,
    Sensor,
    SensorError,
    parse_channel,
    select_sensors,
    sensors_from_table,
)

# --- outputs: the hand-written slider kinematics against autodiff of x_s(phi(t)) ----------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_slider_outputs_match_autodiff_along_the_motion(seed):
    rng = np.random.default_rng(seed)
    mech = random_mech(rng, e=0.3 * float(rng.uniform(-1, 1)) * 0.05)
    torque = cj.HarmonicLoad(0.1, 0.3, 2.0)
    phi, dphi, t = rng.uniform(-3, 3), rng.uniform(-5, 5), rng.uniform(0, 1)
    ddphi = cj.model.acceleration(mech, phi, dphi, t, torque=torque)

    # The motion through (phi, dphi) at t with the equation of motion's phi'' there: its
    # second-order Taylor path has the trajectory's first two time derivatives at s = 0.
    def x_of_time(s):
        path = phi + dphi * s + 0.5 * ddphi * s**2
        return cj.model.geometry_at(mech, path).x_s

    v_ad = jax.jacfwd(x_of_time)(0.0)
    a_ad = jax.jacfwd(jax.jacfwd(x_of_time))(0.0)
    kw = dict(torque=torque)
    np.testing.assert_allclose(output("x_s", mech, t, phi, dphi, **kw), x_of_time(0.0),
                               rtol=1e-14)
    np.testing.assert_allclose(output("v_s", mech, t, phi, dphi, **kw), v_ad, rtol=1e-11,
                               atol=1e-14)
    np.testing.assert_allclose(output("a_s", mech, t, phi, dphi, **kw), a_ad, rtol=1e-10,
                               atol=1e-12)
    assert output("phi", mech, t, phi, dphi) == phi
    assert output("dphi", mech, t, phi, dphi) == dphi


def test_slider_velocity_matches_a_simulated_trajectory():
    # Independent of the formulas: finite differences of the simulated slider position.
    scene = cj.load_scene("lab-rig")
    ts = jnp.linspace(0.0, 1.0, 4001)
    traj = scene.simulate(ts)
    x = np.asarray(output("x_s", scene.mech, ts, traj.phi, traj.dphi))
    v = np.asarray(output("v_s", scene.mech, ts, traj.phi, traj.dphi))
    h = float(ts[1] - ts[0])
    d1 = (x[3:-1] - x[1:-3]) / (2 * h)
    d2 = (x[4:] - x[:-4]) / (4 * h)
    # Richardson: error O(h^4), ~1e-9 here against speeds of ~1 m/s.
    np.testing.assert_allclose((4 * d1 - d2) / 3, v[2:-2], atol=1e-7)


def test_unknown_output_is_refused():
    with pytest.raises(ValueError, match="choose from"):
        output("y_s", cj.load_scene("lab-rig").mech, 0.0, 0.0, 0.0)
    assert OUTPUT_NAMES == CHANNELS


# --- sensors: units, calibration, bad input ----------------------------------------------


@pytest.mark.parametrize("name,unit,factor", [
    ("phi", "deg", math.pi / 180), ("phi", "rev", 2 * math.pi), ("dphi", "rpm", math.pi / 30),
    ("dphi", "deg/s", math.pi / 180), ("x_s", "mm", 1e-3), ("v_s", "mm/s", 1e-3),
    ("a_s", "g", 9.80665), ("a_s", "m/s^2", 1.0)])
def test_units_convert_to_si(name, unit, factor):
    s = Sensor(name, unit=unit)
    assert s.to_si(np.array([2.0]))[0] == pytest.approx(2.0 * factor, rel=1e-15)
    assert s.from_si(s.to_si(np.array([3.0])))[0] == pytest.approx(3.0, rel=1e-15)


def test_calibration_is_affine_and_inverts():
    s = Sensor("x_s", scale=-1.0, offset=0.3)
    assert s.measure(0.1) == pytest.approx(0.2)
    assert s.model(s.measure(0.123)) == pytest.approx(0.123)


@pytest.mark.parametrize("kwargs,match", [
    (dict(name="y_s"), "channel 'y_s' is unknown"),
    (dict(name="x_s", unit="deg"), "unit 'deg' is unknown for x_s"),
    (dict(name="phi", scale=0.0), "scale = 0"),
    (dict(name="phi", offset=math.nan), "offset must be a finite number"),
])
def test_bad_sensors_are_refused(kwargs, match):
    with pytest.raises(SensorError, match=match):
        Sensor(**kwargs)


def test_channel_option_rules():
    scene = sensors_from_table({"x_s": {"column": "slide", "unit": "mm", "scale": -1.0,
                                        "offset": 0.3}})
    assert parse_channel("phi=wheel:deg") == ("phi", "wheel", "deg")
    assert parse_channel("x_s") == ("x_s", None, None)
    # --channel given: exactly those, each with the scene's calibration of that name.
    got = select_sensors(["x_s=other"], scene)
    assert got == (Sensor("x_s", "other", "mm", -1.0, 0.3),)
    assert select_sensors(["phi"], scene) == (Sensor("phi"),)
    # Without it: the scene's sensors found in the record; with neither, phi in rad.
    assert select_sensors([], scene, ["t", "slide"]) == scene
    assert select_sensors([], scene, ["t", "phi"]) == (Sensor("phi"),)
    with pytest.raises(SensorError, match="given twice"):
        select_sensors(["phi", "phi=a"], scene)
    with pytest.raises(SensorError, match="unit 'furlong'"):
        parse_channel("x_s=a:furlong")


# --- records through sensors ---------------------------------------------------------------


def rotating_scene(sensors=(), **mech):
    """A motor-driven crank with no spring: it turns, speeding up under a constant torque."""
    m = dict(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.5, m_p=0.3, m_s=0.4, I_c=1e-3, I_p=2e-3,
             k=0.0, c=1e-3, g=9.81)
    m.update(mech)
    return cj.Scene(cj.SliderCrank(**m), torque=cj.ConstantLoad(0.05), phi0=0.0, dphi0=10.0,
                    t1=1.0, sensors=tuple(sensors))


SLIDE = Sensor("x_s", "slide_mm", "mm", scale=-1.0, offset=0.2948)
WHEEL = Sensor("phi", "wheel_deg", "deg", scale=-1.0, offset=-3.083)


def test_synthesised_channels_follow_the_calibration(tmp_path):
    scene = rotating_scene((WHEEL, SLIDE))
    data = cj.synthesize(scene, rate=100)
    traj = scene.simulate(data.ts)
    x = np.asarray(output("x_s", scene.mech, data.ts, traj.phi, traj.dphi))
    np.testing.assert_allclose(data.channels["x_s"], 0.2948 - x, atol=1e-12)
    np.testing.assert_allclose(data.channels["phi"], -3.083 - np.asarray(traj.phi), atol=1e-12)
    path = tmp_path / "rec.csv"
    cj.save_data(data, path)
    assert path.read_text().splitlines()[0] == "t,wheel_deg,slide_mm,tau"
    back = cj.load_data(path, sensors=(WHEEL, SLIDE))
    np.testing.assert_allclose(back.channels["x_s"], data.channels["x_s"], rtol=1e-15)
    np.testing.assert_allclose(back.channels["phi"], data.channels["phi"], rtol=1e-14)
    # The column is in mm: 1000x the SI value.
    raw = np.loadtxt(path, delimiter=",", skiprows=1)
    np.testing.assert_allclose(raw[:, 2], 1e3 * data.channels["x_s"], rtol=1e-15)
    assert back.window(0.2, 0.5).channels["x_s"].shape == (31,)


def test_missing_sensor_column_and_nan_are_named(tmp_path):
    path = tmp_path / "rec.csv"
    path.write_text("t,slide_mm\n0,1\n0.1,2\n0.2,nan\n0.3,4\n0.4,5\n0.5,6\n")
    with pytest.raises(cj.DataError,
                       match=r"missing column 'wheel_deg'.*`sensors=` \(sensor phi's"):
        cj.load_data(path, sensors=(WHEEL,))
    with pytest.raises(cj.DataError, match=r"line 4: column 'slide_mm' is nan"):
        cj.load_data(path, sensors=(SLIDE,))


def test_scene_sensors_table_round_trips(tmp_path):
    scene = rotating_scene((WHEEL, SLIDE))
    path = tmp_path / "s.toml"
    cj.save_scene(scene, path)
    assert "[sensors]" in path.read_text()
    assert cj.load_scene(path).sensors == (WHEEL, SLIDE)
    bad = path.read_text().replace('unit = "mm"', 'unit = "inch"')
    path.write_text(bad)
    with pytest.raises(cj.SceneError, match=r"\[sensors\] x_s: .*unit 'inch'"):
        cj.load_scene(path)


def test_slide_position_gives_back_the_turning_angle():
    scene = rotating_scene()
    ts = np.linspace(0, 1.0, 201)
    traj = scene.simulate(ts)
    x = np.asarray(cj.model.geometry_at(scene.mech, traj.phi).x_s)
    est = slide_angle(scene.mech, ts, x, direction=1.0, phi_start=0.0)
    np.testing.assert_allclose(est, np.asarray(traj.phi), atol=2e-2)


# --- fits and validation per channel -------------------------------------------------------


@pytest.fixture(scope="module")
def slide_fit():
    truth = rotating_scene((SLIDE,))
    data = cj.synthesize(truth, rate=100, noise_std={"x_s": 2e-5}, seed=1)
    start = rotating_scene((SLIDE,), c=1.4e-3)
    res = cj.fit(start, data, free=("c", "x_s_offset", "phi0", "dphi0"), progress=False,
                 warn=False)
    return truth, data, res


def test_slide_only_fit_recovers_the_parameters_and_offset(slide_fit):
    truth, _, res = slide_fit
    assert res.converged
    for name, want in (("c", 1e-3), ("x_s_offset", 0.2948), ("phi0", 0.0), ("dphi0", 10.0)):
        lo, hi = res.ci95[name]
        assert lo <= want <= hi, (name, res.values[name], res.ci95[name])
    ch = res.channels["x_s"]
    assert ch["n_samples"] == 101 and ch["rms"] == pytest.approx(2e-5, rel=0.3)
    doc = json.loads(json.dumps(res.to_json()))
    assert fitted_scene(truth, res).sensors[0].offset == res.values["x_s_offset"]
    assert set(doc["channels"]) == {"x_s"}
    assert set(doc["channels"]["x_s"]) == {"rms", "sigma", "n_samples", "ljung_box_p"}


def test_two_channels_with_given_noise_levels():
    truth = rotating_scene((WHEEL, SLIDE))
    data = cj.synthesize(truth, rate=100, noise_std={"phi": 1e-3, "x_s": 2e-5}, seed=2)
    res = cj.fit(rotating_scene((WHEEL, SLIDE), c=1.2e-3), data, free=("c", "phi0", "dphi0"),
                 sigma={"phi": 1e-3, "x_s": 2e-5}, progress=False, warn=False)
    assert res.converged
    assert list(res.channels) == ["phi", "x_s"]
    assert res.channels["x_s"]["sigma"] == 2e-5 and res.channels["phi"]["sigma"] == 1e-3
    # Each channel's rms is its own noise level: weighting did not trade one for the other.
    assert res.channels["phi"]["rms"] == pytest.approx(1e-3, rel=0.3)
    assert res.channels["x_s"]["rms"] == pytest.approx(2e-5, rel=0.3)
    assert res.rms_residual == pytest.approx(1e-3, rel=0.3)  # the first channel's unit
    lo, hi = res.ci95["c"]
    assert lo <= 1e-3 <= hi
    # Validation on another record, per channel; top-level scores are the first channel's.
    other = cj.synthesize(truth, rate=100, noise_std={"phi": 1e-3, "x_s": 2e-5}, seed=5)
    val = cj.validate(fitted_scene(truth, res), other, init_window=0.3)
    assert set(val.channels) == {"phi", "x_s"}
    assert val.rms == val.channels["phi"]["rms"]
    assert val.channels["x_s"]["rms"] < 5e-5 and val.channels["phi"]["rms"] < 3e-3
    assert set(val.to_json()["channels"]["x_s"]) == {"rms", "max_abs", "fit_percent",
                                                     "n_samples"}


def test_offset_of_a_channel_the_record_lacks_is_refused():
    data = cj.synthesize(rotating_scene((SLIDE,)), rate=50)
    with pytest.raises(ValueError, match="phi_offset cannot be free: no record has a phi"):
        cj.fit(rotating_scene(), data, free=("phi_offset", "c"), progress=False)


# --- CLI -------------------------------------------------------------------------------


def test_cli_synth_fit_and_bad_channels(tmp_path, capsys):
    scene_path = tmp_path / "rig.toml"
    cj.save_scene(rotating_scene((WHEEL, SLIDE)), scene_path)
    rec = tmp_path / "rec.csv"
    assert main(["synth", str(scene_path), "--rate", "50", "--noise-std", "phi=1e-3",
                 "--noise-std", "x_s=2e-5", "--out", str(rec)]) == 0
    assert rec.read_text().splitlines()[1] == "t,wheel_deg,slide_mm,tau"
    for args, match in ((["--channel", "y_s"], "channel 'y_s' is unknown"),
                        (["--channel", "x_s=slide_mm:inch"], "unit 'inch' is unknown"),
                        (["--channel", "x_s=nope"], "missing column 'nope'"),
                        (["--sigma", "q=1"], "channel 'q' is unknown")):
        capsys.readouterr()
        assert main(["fit", str(rec), str(scene_path), "--quiet", *args]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and match in err[0], err


# --- measured inputs through gains, per-record names, a user's force term ----------------


def test_input_load_table_round_trips_and_needs_its_column(tmp_path):
    from crank_jax.model.loads import InputLoad, load_from_table, load_to_table

    load = load_from_table({"input": "volts", "gain": 0.02, "tau0": 0.1}, "torque")
    assert isinstance(load, InputLoad) and load.column == "volts"
    assert load_to_table(load, "torque") == {"kind": "input", "tau0": 0.1, "tau1": 0.0,
                                             "freq_hz": 0.0, "phase": 0.0, "gain": 0.02,
                                             "input": "volts"}
    ts = np.linspace(0, 1, 11)
    bound = load.bind(ts, 2 * ts)
    np.testing.assert_allclose(bound(ts), 0.1 + 0.02 * 2 * ts, atol=1e-12)
    with pytest.raises(ValueError, match="input 'volts' has no samples"):
        load(0.5)
    path = tmp_path / "rec.csv"
    path.write_text("t,phi,volts\n0,0,1\n0.1,0.1,nan\n0.2,0.2,1\n0.3,0.3,1\n0.4,0.4,1\n")
    with pytest.raises(cj.DataError, match="line 3: column 'volts' is nan"):
        cj.load_data(path, inputs=("volts",))


def _motor_rig(gain, volts, ts, **mech):
    from crank_jax.model.loads import InputLoad

    torque = InputLoad(gain=gain, column="volts")
    if volts is not None:
        torque = torque.bind(ts, volts)
    return rotating_scene((SLIDE,), **mech).__class__(
        rotating_scene(**mech).mech, torque=torque, phi0=0.0, dphi0=10.0, t1=1.0,
        sensors=(SLIDE,))


def test_motor_gain_fitted_from_the_voltage_column(tmp_path):
    ts = np.linspace(0, 1.0, 51)
    volts = 5.0 + 0.5 * np.sin(2 * np.pi * 1.3 * ts)
    data = cj.synthesize(_motor_rig(0.01, volts, ts), rate=50, noise_std={"x_s": 2e-5}, seed=3)
    path = tmp_path / "motor.csv"
    cj.save_data(data, path)
    assert path.read_text().splitlines()[0] == "t,slide_mm,volts"
    back = cj.load_data(path, sensors=(SLIDE,), inputs=("volts",))
    res = cj.fit(_motor_rig(0.015, None, ts), back, free=("tau_gain", "phi0", "dphi0"),
                 progress=False, warn=False)
    assert res.converged
    lo, hi = res.ci95["tau_gain"]
    assert lo <= 0.01 <= hi and hi - lo < 1e-3
    with pytest.raises(ValueError, match="`per_record=` names 'c', which is not free"):
        cj.fit(_motor_rig(0.015, None, ts), [back, back], free=("tau_gain", "phi0"),
               per_record=("c",), progress=False)


def test_cli_per_record_must_name_a_free_parameter(tmp_path, capsys):
    rec = tmp_path / "rec.csv"
    cj.save_data(cj.synthesize(rotating_scene(), rate=50), rec)
    scene_path = tmp_path / "rig.toml"
    cj.save_scene(rotating_scene(), scene_path)
    code = main(["fit", str(rec), str(scene_path), "--more-data", str(rec), "--free", "c",
                 "--per-record", "tau0", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--per-record names tau0" in err[0]


def test_a_users_force_term_is_fitted():
    from conftest import experiment

    unbalance_force = experiment("unbalance_force")
    truth, res = unbalance_force.run(seed=1)
    assert res.converged
    for name, want in (("force.a", float(truth.a)), ("force.b", float(truth.b))):
        lo, hi = res.ci95[name]
        assert lo <= want <= hi, (name, res.values[name], res.ci95[name])
    with pytest.raises(ValueError, match=r"`free=` names unknown parameter\(s\) \['force.q'\]"):
        cj.fit(unbalance_force.rig(), cj.synthesize(unbalance_force.rig(), rate=50),
               free=("force.q",), force=truth, progress=False)


def test_per_record_values_go_into_one_fitted_scene_per_record(tmp_path, capsys):
    # Issue 25: --scene-out wrote the start value of a parameter fitted per record.
    ts = np.linspace(0, 1.0, 51)
    volts = 5.0 + 0.5 * np.sin(2 * np.pi * 1.3 * ts)
    paths = []
    for i, gain in enumerate((0.01, 0.02)):
        data = cj.synthesize(_motor_rig(gain, volts, ts), rate=50, noise_std={"x_s": 2e-5},
                             seed=3 + i)
        paths.append(tmp_path / f"motor{i}.csv")
        cj.save_data(data, paths[-1])
    start = tmp_path / "start.toml"
    cj.save_scene(_motor_rig(0.015, None, ts), start)
    out = tmp_path / "fitted.toml"
    assert main(["fit", str(paths[0]), str(start), "--more-data", str(paths[1]), "--free",
                 "tau_gain,phi0,dphi0", "--per-record", "tau_gain", "--scene-out", str(out),
                 "--out", str(tmp_path / "fit.json"), "--quiet"]) == 0
    doc = json.loads((tmp_path / "fit.json").read_text())
    assert doc["converged"]
    err = capsys.readouterr().err
    assert "fitted.record1.toml" in err
    for i, (path, gain) in enumerate(((out, 0.01), (tmp_path / "fitted.record1.toml", 0.02))):
        scene = cj.load_scene(str(path))
        est = doc["estimates"]
        assert float(scene.torque.gain) == pytest.approx(est[f"tau_gain[{i}]"]["value"],
                                                         rel=1e-12)
        assert float(scene.torque.gain) == pytest.approx(gain, rel=0.05)
        assert float(scene.phi0) == pytest.approx(est[f"phi0[{i}]"]["value"], rel=1e-12)


def test_fitted_scene_takes_a_records_own_mechanism_field():
    from types import SimpleNamespace

    scene = rotating_scene((SLIDE,))
    # The shared fields are the fitted mechanism's (T_c); c was fitted per record.
    res = SimpleNamespace(mech=scene.mech.replace(T_c=0.03), converged=True,
                          values={"c[0]": 0.1, "c[1]": 0.2, "T_c": 0.03, "phi0[1]": 0.5})
    for i, c in enumerate((0.1, 0.2)):
        got = fitted_scene(scene, res, record=i)
        assert float(got.mech.c) == c and float(got.mech.T_c) == 0.03
    assert float(fitted_scene(scene, res, record=1).phi0) == 0.5


def test_noise_level_of_a_coarse_fast_record_is_the_noise():
    # Issue 25: a slider read at 50 Hz while the crank turns 4 times a second (12.5
    # samples a turn, 3 ms jitter, actual times): local quartics over a fraction of a
    # turn put the motion into the noise estimate (5x the noise); divided differences
    # at the recorded times do not.
    from crank_jax.identify.start import noise_level

    rng = np.random.default_rng(1)
    ts = np.arange(200) / 50.0 + 3e-3 * rng.standard_normal(200)
    w = 2 * np.pi * 4.0
    x = 0.05 * np.cos(w * ts) + 0.00625 * np.cos(2 * w * ts)
    sigma = 5e-5
    got = noise_level(ts, x + sigma * rng.standard_normal(200))
    assert 0.8 * sigma < got < 1.25 * sigma
    # White noise alone, many samples: an unbiased estimate.
    ts = np.cumsum(0.02 + 3e-3 * rng.standard_normal(4000))
    assert noise_level(ts, rng.standard_normal(4000)) == pytest.approx(1.0, rel=0.05)
