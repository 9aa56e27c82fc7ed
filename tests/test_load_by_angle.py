"""A measured load that follows the crank angle (`load_by="angle"`, `--load-by angle`): the
record's P/tau column tabled by the record's own angle and evaluated at the model's."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import experiment

import crank_jax as cj
from crank_jax.cli import main
from crank_jax.model import AngleLoad
from crank_jax.model.dynamics import CrankField
from crank_jax.records.load_by import loads_by

# Measured (rtol 1e-10, a 2 kHz record of 0.2 s at 1,400 rpm): the model's motion off the
# truth's, 5.7e-5 rad with the column interpolated in time, 5.2e-6 rad tabled by angle.
TOL_TIME, TOL_ANGLE = 2e-4, 2e-5
MECH = cj.SliderCrank(r=0.025, L=0.09, b=0.03, s=0.0, m_c=0.3, m_p=0.15, m_s=0.12,
                      I_c=0.01, I_p=1e-4, k=0.0, c=5e-4)


def _gas(phi):
    """A compression pulse each turn, N: peaks 1.5 kN just before dead centre."""
    w = (np.asarray(phi) + np.pi) % (2 * np.pi) - np.pi
    return 1500.0 * np.exp(-((w + 0.05) / 0.5) ** 2)


def _record(ts, phi, source="rec"):
    return cj.Data(ts, phi, load=cj.SampledLoad(ts, _gas(phi)), source=source)


def test_angle_table_evaluates_at_the_angle_and_holds_beyond_it():
    phi = np.linspace(0.0, 4 * np.pi, 400)
    load = AngleLoad.from_samples(phi, _gas(phi), ts=np.linspace(0, 1, 400))
    x = jnp.asarray([0.3, 2.0, 7.0])
    np.testing.assert_allclose(np.asarray(load.at(0.0, x)), _gas(np.asarray(x)), rtol=2e-4)
    # Past the record's last angle: the last measured value, not an extrapolation.
    assert float(load.at(0.0, 4 * np.pi + 3.0)) == pytest.approx(float(_gas(4 * np.pi)))
    # A periodic load wraps instead.
    wrapped = AngleLoad.from_samples(phi, _gas(phi), period=2 * np.pi)
    assert float(wrapped.at(0.0, 4 * np.pi + 0.3)) == pytest.approx(float(_gas(0.3)),
                                                                    rel=2e-4)
    # A record turning backwards is tabled the same way.
    back = AngleLoad.from_samples(-phi, _gas(phi))
    assert float(back.at(0.0, -2.0)) == pytest.approx(float(_gas(2.0)), rel=2e-4)


def test_the_field_takes_the_force_at_the_models_angle():
    phi = np.linspace(-1.0, 8.0, 300)
    load = AngleLoad.from_samples(phi, _gas(phi))
    for angle in (0.2, 3.0):  # the same time, two crank angles: two forces
        table = CrankField(MECH, load, cj.NoLoad()).acceleration(0.5, angle, 100.0)
        const = CrankField(MECH, cj.ConstantLoad(float(load.at(0.5, angle))),
                           cj.NoLoad()).acceleration(0.5, angle, 100.0)
        assert float(table) == pytest.approx(float(const), rel=1e-12)


def test_angle_table_equals_time_interpolation_when_the_model_follows_the_record():
    # The truth: a force that follows the angle, and its record at 2 kHz with the column.
    grid = np.linspace(-np.pi, np.pi, 721)
    truth_load = AngleLoad.from_samples(grid, _gas(grid), period=2 * np.pi)
    scene = cj.Scene(MECH, load=truth_load, phi0=0.3, dphi0=150.0)
    ts = np.linspace(0.0, 0.2, 401)
    truth = np.asarray(scene.simulate(jnp.asarray(ts), rtol=1e-10, atol=1e-10).phi)
    data = _record(ts, truth)
    # From the truth's state, the model follows the record: the column interpolated in
    # time and tabled by angle give the same motion, to interpolation error.
    by = {}
    for how in ("time", "angle"):
        load = loads_by(data, how).load
        by[how] = np.asarray(dataclasses.replace(scene, load=load).simulate(
            jnp.asarray(ts), rtol=1e-10, atol=1e-10).phi)
    assert isinstance(loads_by(data, "angle").load, AngleLoad)
    assert np.max(np.abs(by["time"] - truth)) < TOL_TIME
    assert np.max(np.abs(by["angle"] - truth)) < TOL_ANGLE
    assert np.max(np.abs(by["angle"] - by["time"])) < TOL_TIME
    # The table gives back the column at the record's own angles.
    tabled = loads_by(data, "angle").load
    np.testing.assert_allclose(np.asarray(tabled.at(ts, data.phi)),
                               np.asarray(data.load(ts)), rtol=1e-12, atol=1e-9)


def test_gradient_through_the_angle_table_matches_finite_differences():
    phi = np.linspace(0.0, 6.0, 120)
    load = AngleLoad.from_samples(phi, _gas(phi))
    f = jax.jit(lambda x: load.at(0.0, x))
    for x in (0.7, 2.9, 5.5):
        g = float(jax.grad(f)(x))
        h = 1e-6
        fd = (float(f(x + h)) - float(f(x - h))) / (2 * h)
        assert np.isfinite(g) and g == pytest.approx(fd, rel=1e-5, abs=1e-6)


def test_gradient_through_a_solve_with_the_angle_table_matches_finite_differences():
    # d(final angle)/d(I_c), forward mode through the solve, against finite differences.
    phi = np.linspace(0.0, 20.0, 400)
    load = AngleLoad.from_samples(phi, _gas(phi))
    ts = jnp.linspace(0.0, 0.1, 11)

    def end(I_c):
        sc = cj.Scene(MECH.replace(I_c=I_c), load=load, phi0=0.3, dphi0=150.0)
        return sc.simulate(ts, rtol=1e-11, atol=1e-11).phi[-1]

    g = float(jax.jacfwd(end)(0.01))
    # Measured: central differences with h = 1e-5 give 1.643721 (3.8e-5 off the Jacobian's
    # 1.643659); h = 1e-7 gave 1.6324, the solve's rtol over h (rounding, not the table).
    h = 1e-5
    fd = (float(end(0.01 + h)) - float(end(0.01 - h))) / (2 * h)
    assert np.isfinite(g) and g == pytest.approx(fd, rel=1e-4)


def test_refusals_name_load_by_and_the_fix():
    ts = np.linspace(0.0, 0.2, 60)
    phi = 0.3 + 150.0 * ts
    good = _record(ts, phi)
    back = _record(ts, np.where(ts < 0.1, phi, phi[30] - 10 * (ts - ts[30])))
    scene = cj.Scene(MECH, phi0=0.3, dphi0=150.0)
    kw = dict(free=("c", "phi0", "dphi0"), progress=False, warn=False)
    with pytest.raises(ValueError, match=r"`load_by='angle'`.*not strictly monotone.*"
                                         r"t = 0\.10\d* s.*`t_start=`, `t_end=`"):
        cj.fit(scene, back, load_by="angle", **kw)
    with pytest.raises(ValueError, match="load_by must be 'time' or 'angle', got 'crank'"):
        cj.fit(scene, good, load_by="crank", **kw)
    with pytest.raises(ValueError, match="`load_by='angle'`.*neither"):
        cj.fit(scene, cj.Data(ts, phi), load_by="angle", **kw)
    slide = cj.Data(ts, None, load=cj.SampledLoad(ts, _gas(phi)),
                    channels={"x_s": 0.1 + 0.02 * np.cos(phi)})
    with pytest.raises(ValueError, match="angle channel phi, which it lacks"):
        cj.fit(scene, slide, load_by="angle", **kw)
    with pytest.raises(ValueError, match="phi_offset cannot be free with `load_by='angle'`"):
        cj.fit(scene, good, load_by="angle", **{**kw, "free": ("c", "phi_offset")})
    with pytest.raises(ValueError, match="not strictly monotone"):
        cj.validate(scene, back, load_by="angle", init_window=0.05)
    with pytest.raises(ValueError, match="AngleLoad angle: .*sample 1"):
        AngleLoad.from_samples([0.0, 0.0, 1.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="interp='zoh'"):
        AngleLoad.from_samples([0.0, 0.5, 1.0], [1.0, 2.0, 3.0], interp="zoh")


def test_sensor_calibration_is_undone_before_tabling():
    # An encoder counting backwards with an offset: the table is by the model's phi.
    ts = np.linspace(0.0, 0.2, 60)
    phi = 0.3 + 150.0 * ts
    sensor = cj.Sensor("phi", scale=-1.0, offset=0.5)
    data = cj.Data(ts, None, load=cj.SampledLoad(ts, _gas(phi)),
                   channels={"phi": np.asarray(sensor.measure(phi))}, sensors=(sensor,))
    tabled = loads_by(data, "angle").load
    np.testing.assert_allclose(np.asarray(tabled.at(0.0, phi)), _gas(phi), rtol=1e-12,
                               atol=1e-9)


def test_cli_load_by_flag(tmp_path, capsys):
    ts = np.linspace(0.0, 0.2, 60)
    phi = 0.3 + 150.0 * ts
    phi = np.where(ts < 0.1, phi, phi[30] - 10 * (ts - ts[30]))
    cj.save_data(_record(ts, phi), tmp_path / "back.csv")
    cj.save_scene(cj.Scene(MECH, phi0=0.3, dphi0=150.0), tmp_path / "s.toml")
    rec, scene = str(tmp_path / "back.csv"), str(tmp_path / "s.toml")
    for argv in (["fit", rec, scene, "--load-by", "crank"],
                 ["posterior", rec, scene, "--load-by", "crank", "--out", "p.json"],
                 ["validate", scene, rec, "--load-by", "crank", "--out", "v.json"]):
        assert main(argv) == 2
        assert "--load-by" in capsys.readouterr().err
    # Accepted, and the library's refusal in the command's words: exit 2, no traceback.
    assert main(["fit", rec, scene, "--free", "c,phi0,dphi0", "--load-by", "angle",
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--load-by angle needs a crank turning one way" in err
    assert "(--t-start, --t-end)" in err and "Traceback" not in err and "`" not in err
    assert main(["validate", scene, rec, "--load-by", "angle", "--init-window", "0.05",
                 "--out", str(tmp_path / "v.json"), "--quiet"]) == 2
    assert "--load-by angle" in capsys.readouterr().err


def _tooth_record(scene, t1, seed, teeth=36):
    """A coast-down of `scene` sampled at the edges of a 36-1 toothed wheel: irregular
    times (20 us of jitter), no sample at the missing tooth, the force column with 5 N of
    noise."""
    tf = np.linspace(0.0, t1, int(t1 * 4000) + 1)
    tr = scene.simulate(jnp.asarray(tf), rtol=1e-10, atol=1e-10)
    rng = np.random.default_rng(seed)
    ts, angle = experiment("_bench").tooth_edges(tf, np.asarray(tr.phi), np.asarray(tr.dphi),
                                                 teeth, rng)
    force = _gas(angle) + rng.normal(0.0, 5.0, angle.shape)
    return cj.Data(ts, angle, load=cj.SampledLoad(ts, force), source=f"coast-{seed}")


def test_force_by_angle_stand_in_tooth_wheel_coast_down():
    # The misfit bench's "force by angle": a coast-down at high speed whose gas force
    # follows the crank, recorded by a 36-1 toothed wheel, with crank-bearing Coulomb
    # friction the fitted model lacks. Fitted by angle on one record (irregular samples
    # with a gap each turn, taken as they are), it predicts a held-out record open loop;
    # the held-out force interpolated in time meets the model's slipping crank at the
    # wrong angle and the prediction runs off (experiments/force_by_angle.py: 4.9 rad
    # against 0.13 rad on 0.4 s records; it passes within 0.5 rad, the pulse's width).
    grid = np.linspace(-np.pi, np.pi, 721)
    truth = MECH.replace(T_c=0.05, w_c=0.5)
    load = AngleLoad.from_samples(grid, _gas(grid), period=2 * np.pi)
    fit_rec = _tooth_record(cj.Scene(truth, load=load, phi0=0.3, dphi0=160.0), 0.4, 1)
    held = _tooth_record(cj.Scene(truth, load=load, phi0=0.3, dphi0=120.0), 0.4, 2)
    gaps = np.diff(fit_rec.ts)
    assert gaps.max() > 1.8 * np.median(gaps)  # the missing tooth: irregular samples
    model = cj.Scene(MECH.replace(I_c=0.012, c=1e-3), phi0=0.3, dphi0=150.0)
    res = cj.fit(model, fit_rec, free=("I_c", "c", "phi0", "dphi0"), progress=False,
                 warn=False, load_by="angle")
    assert res.converged and res.rms_residual < 0.02
    fitted = cj.Scene(res.mech, phi0=0.3, dphi0=150.0)
    by_angle = cj.validate(fitted, held, init_window=0.05, load_by="angle")
    by_time = cj.validate(fitted, held, init_window=0.05, load_by="time")
    assert by_angle.rms < 0.5 < by_time.rms


def test_a_new_table_of_the_same_length_does_not_recompile():
    import equinox as eqx

    traces = []

    @eqx.filter_jit
    def force(load, x):
        traces.append(1)  # runs once per trace
        return jax.vmap(lambda p: load.at(0.0, p))(x)

    phi = np.linspace(-3.0, 3.0, 200)
    x = jnp.asarray([-0.3, 0.1, 0.4])
    a = force(AngleLoad.from_samples(phi, _gas(phi)), x)
    b = force(AngleLoad.from_samples(phi + 0.1, 2.0 * _gas(phi)), x)
    assert len(traces) == 1
    np.testing.assert_allclose(np.asarray(a), _gas(np.asarray(x)), rtol=1e-3)
    assert not np.allclose(np.asarray(a), np.asarray(b))
