"""Hostile records and column names (issue 37, third pass): every column plays exactly one
role, sensors are read alike by every command, column names a CSV can hold, fitted scenes
that reload to themselves, outputs that never collide, and constructors that check their
fields."""

import dataclasses
import types

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli import main
from crank_jax.identify import fitted_scene
from crank_jax.model.loads import InputLoad, SampledLoad
from crank_jax.records.sensors import Sensor, SensorError, sensors_from_table

TS = np.linspace(0.0, 0.5, 26)
ANGLE = np.cos(9 * TS)


def _csv(path, **cols):
    names = list(cols)
    rows = np.column_stack([np.asarray(cols[n], float) for n in names])
    path.write_text(",".join(names) + "\n" + "\n".join(",".join(repr(float(x)) for x in r)
                                                       for r in rows) + "\n")
    return path


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    for n in needles:
        assert n in err[0], err[0]
    return err[0]


@pytest.fixture
def lab_scene_file(tmp_path):
    """A writer of lab-rig scene files with extra TOML appended."""
    def write(extra: str = "", name: str = "rig.toml"):
        path = tmp_path / name
        path.write_text(cj.scene_to_toml(cj.load_scene("lab-rig")) + "\n" + extra)
        return path
    return write


# --- 2. one role per column --------------------------------------------------------------


@pytest.mark.parametrize("header, kwargs, roles", [
    # The angle column named tau, read as the angle: it would drive the crank as well.
    (("t", "tau"), dict(sensors=(Sensor("phi", "tau"),)), ("channel phi", "crank torque")),
    (("t", "P"), dict(sensors=(Sensor("phi", "P"),)), ("channel phi", "slider force")),
    (("t", "tau"), dict(phi_col="tau"), ("the angle", "crank torque")),
    (("t", "P"), dict(phi_col="P"), ("the angle", "slider force")),
    (("t", "phi"), dict(sensors=(Sensor("phi", "t"),)), ("the time", "channel phi")),
    # An input column that is also the torque column: the torque twice over.
    (("t", "phi", "tau"), dict(inputs=("tau",)), ("input of a load", "crank torque")),
    (("t", "phi", "volts"), dict(sensors=(Sensor("phi"), Sensor("x_s", "volts")),
                                 inputs=("volts",)), ("channel x_s", "input of a load")),
])
def test_a_column_with_two_roles_is_refused(tmp_path, header, kwargs, roles):
    path = _csv(tmp_path / "rec.csv", **{h: (TS if h == "t" else ANGLE) for h in header})
    with pytest.raises(cj.DataError, match="claimed twice") as e:
        cj.load_data(path, **kwargs)
    for r in roles:
        assert r in str(e.value)


def test_fit_validate_posterior_refuse_a_column_with_two_roles(tmp_path, capsys):
    """`fit tau.csv lab-rig --channel phi=tau` read the angle as the torque too and gave
    k = 3.0 "converged" against a truth of 2; every command now refuses before any work."""
    rec = _csv(tmp_path / "tau.csv", t=TS, tau=ANGLE)
    out = str(tmp_path / "o.json")
    for argv in (["fit", str(rec), "lab-rig", "--channel", "phi=tau", "--quiet"],
                 ["validate", "lab-rig", str(rec), "--channel", "phi=tau", "--out", out],
                 ["posterior", str(rec), "lab-rig", "--channel", "phi=tau", "--out", out]):
        assert main(argv) == 2, argv
        _one_line_error(capsys, "claimed twice", "'tau'", "channel phi", "crank torque tau")


@pytest.mark.parametrize("extra, names", [
    ('[sensors]\nphi = { column = "P" }\n', ("[sensors] phi", "'P'")),
    ('[sensors]\nphi = { column = "t" }\n', ("[sensors] phi", "'t'")),
    ('[torque]\nkind = "input"\ninput = "tau"\ngain = 1.0\n', ("[torque] input", "'tau'")),
    ('[torque]\nkind = "input"\ninput = "wheel"\ngain = 1.0\n'
     '[sensors]\nphi = { column = "wheel" }\n', ("[sensors] phi", "load's input")),
    ('[sensors]\nphi = { column = "a" }\nx_s = { column = "a" }\n',
     ("channel phi", "channel x_s")),
])
def test_scene_columns_with_two_roles_are_refused(lab_scene_file, capsys, extra, names):
    scene = lab_scene_file(extra)
    with pytest.raises(cj.SceneError) as e:
        cj.load_scene(scene)
    for n in names:
        assert n in str(e.value)
    assert main(["synth", str(scene), "--t1", "0.2", "--out", str(scene.with_suffix(".csv"))]
                ) == 2
    _one_line_error(capsys, *names)


def test_data_refuses_a_column_with_two_roles():
    with pytest.raises(cj.DataError, match="claimed twice, as the time and as channel phi"):
        cj.Data(TS, None, channels={"phi": ANGLE}, sensors=(Sensor("phi", "t"),))
    with pytest.raises(cj.DataError, match="channel phi and as channel x_s"):
        cj.Data(TS, None, channels={"phi": ANGLE, "x_s": ANGLE},
                sensors=(Sensor("phi", "a"), Sensor("x_s", "a", "mm")))
    with pytest.raises(cj.DataError, match="slider force P and as the input 'P'"):
        cj.Data(TS, ANGLE, load=SampledLoad(TS, ANGLE), inputs={"P": SampledLoad(TS, ANGLE)})


# --- 3. posterior reads records through the sensors, as fit does --------------------------


def test_cli_posterior_reads_the_scenes_sensors(lab_scene_file, tmp_path, monkeypatch):
    """`posterior` read the raw column as the angle (phi0 = -1.03 where fit gave 1.0); it
    now reads every record through the function `fit` reads them with."""
    import crank_jax.bayes.posterior as post

    scene = lab_scene_file('[sensors]\nphi = { column = "phi", scale = -1.0, offset = 0.3 }\n')
    rec = _csv(tmp_path / "rec.csv", t=TS, phi=0.3 - ANGLE)
    seen = {}

    def spy(scene, data, *args, **kwargs):
        seen["data"] = data
        raise ValueError("stop here")

    monkeypatch.setattr(post, "posterior", spy)
    main(["posterior", str(rec), str(scene), "--out", str(tmp_path / "p.json"), "--quiet"])
    (s, y), = seen["data"].outputs()
    assert s == Sensor("phi", "phi", "rad", -1.0, 0.3)
    np.testing.assert_allclose(s.model(y), ANGLE, atol=1e-12)


@pytest.mark.slow  # two compiled solves: ~25 s of CPU (70 s wall under load)
def test_posterior_problem_reads_channels_as_the_fit():
    """`cj.posterior` on a channel record raised a TypeError (its problem read `data.phi`);
    its residual problem is now the fit's, reading each channel through its sensor: at
    the true values the residuals are the noise (2 mrad), not the raw column's misfit."""
    import jax.numpy as jnp

    from crank_jax.bayes.posterior import _problem_at
    from crank_jax.identify.programs import jacobian_at
    from crank_jax.identify.request import normalize

    scene = dataclasses.replace(cj.load_scene("lab-rig"),
                                sensors=(Sensor("phi", scale=-1.0, offset=0.3),))
    data = cj.synthesize(scene, t1=0.5, rate=60, noise_std=2e-3, seed=3)
    assert data.phi is None
    req = normalize(scene, data, ("k", "c"), init="scene", method="lm", shooting="auto",
                    segments=None, multistart=1, seed=0, max_steps=None, tol=1e-8,
                    sigma=None, profile=None, window=None, progress=False, warn=False)
    truth = types.SimpleNamespace(values={"k": 2.0, "c": 0.002}, mech=scene.mech,
                                  channels={"phi": {"sigma": 2e-3}})
    problem, z = _problem_at(req, truth)
    r, failed, _, _ = jacobian_at(problem, jnp.asarray(z))
    assert int(failed) == 0
    assert float(np.sqrt(np.sum(np.asarray(r) ** 2) / data.n)) == pytest.approx(2e-3, rel=0.3)


# --- 12. column names a CSV can hold -----------------------------------------------------


@pytest.mark.parametrize("column, match", [
    ("t", "time column"), ("P", "slider force column"), ("tau", "crank torque column"),
    ("a,b", "comma"), ('a"b', "double quote"), ("a\nb", "control character"),
    (" a", "spaces at an end"), ("a ", "spaces at an end"),
])
def test_sensor_columns_that_would_corrupt_a_record_are_refused(column, match):
    with pytest.raises(SensorError, match=match) as e:
        sensors_from_table({"phi": {"column": "phi"}, "x_s": {"column": column}})
    assert "x_s" in str(e.value)


def test_synth_refuses_a_sensor_column_equal_to_anothers(lab_scene_file, capsys, tmp_path):
    scene = lab_scene_file('[sensors]\nphi = { column = "a" }\nx_s = { column = "a" }\n')
    out = tmp_path / "rec.csv"
    assert main(["synth", str(scene), "--t1", "0.2", "--out", str(out)]) == 2
    _one_line_error(capsys, "[sensors]", "'a'")
    assert not out.exists()


@pytest.mark.parametrize("kwargs, match", [
    (dict(sensors=(Sensor("phi"), Sensor("x_s", "phi", "mm"))), "claimed twice"),
    (dict(inputs={"a,b": SampledLoad(TS, TS)}), "comma"),
    (dict(inputs={"t": SampledLoad(TS, TS)}), "claimed twice"),
])
def test_save_data_never_writes_a_corrupt_header(tmp_path, kwargs, match):
    channels = {"phi": ANGLE, "x_s": ANGLE} if "sensors" in kwargs else {"phi": ANGLE}
    with pytest.raises(cj.DataError, match=match):
        cj.save_data(cj.Data(TS, None, channels=channels, **kwargs), tmp_path / "r.csv")
    assert not (tmp_path / "r.csv").exists()


# --- 13. fitted scenes keep the calibration and reload to themselves -----------------------


def _fake_result(scene, data, **values):
    return types.SimpleNamespace(values=dict(values), mech=scene.mech, data=[data],
                                 converged=True)


def _same_scene(a, b):
    assert a.sensors == b.sensors
    assert cj.scene_to_toml(a) == cj.scene_to_toml(b)


def test_scene_out_keeps_the_channels_and_fitted_offsets(tmp_path):
    """A fitted x_s_offset of a record read through --channel (the scene has no [sensors])
    was dropped from --scene-out; the written scene now reloads to the fitted one."""
    from crank_jax.cli.identify import _write_scene

    scene = cj.load_scene("lab-rig")
    slide = Sensor("x_s", "slide_mm", "mm", -1.0, 0.0)
    data = cj.Data(TS, None, channels={"x_s": ANGLE * 1e-3}, sensors=(slide,))
    res = _fake_result(scene, data, k=2.5, x_s_offset=0.0123, phi0=0.9)
    fitted = fitted_scene(scene, res)
    assert fitted.sensors == (dataclasses.replace(slide, offset=0.0123),)
    path = tmp_path / "fitted.toml"
    a = types.SimpleNamespace(scene_out=str(path), fitted_scene=scene, more_data=[],
                              per_record="", record_sensors=[(slide,)])
    _write_scene(res, a)
    _same_scene(cj.load_scene(path), fitted)


def test_scene_out_keeps_the_scenes_sensors_and_a_plain_angle_column(tmp_path):
    wheel = Sensor("phi", "wheel", "deg", -1.0, 0.1)
    scene = dataclasses.replace(cj.load_scene("lab-rig"), sensors=(wheel,))
    data = cj.Data(TS, ANGLE)
    # A plain record read through --phi-col angle --angle-unit deg, with its offset fitted.
    angle = Sensor("phi", "angle", "deg")
    fitted = fitted_scene(scene, _fake_result(scene, data, phi_offset=0.02),
                             sensors=(angle,))
    assert fitted.sensors == (dataclasses.replace(angle, offset=0.02),)
    # Without a fitted offset, the scene's own sensors stay, and a plain record adds none.
    assert fitted_scene(scene, _fake_result(scene, data, k=2.0)).sensors == (wheel,)
    plain = cj.load_scene("lab-rig")
    assert fitted_scene(plain, _fake_result(plain, data, k=2.0)).sensors == ()
    # --channel phi --channel x_s: the written scene must read the angle too.
    both = (Sensor("phi"), Sensor("x_s", "slide_mm", "mm"))
    got = fitted_scene(plain, _fake_result(plain, data, x_s_offset=1e-3), sensors=both)
    assert got.sensors == (both[0], dataclasses.replace(both[1], offset=1e-3))
    cj.save_scene(fitted, tmp_path / "f.toml")
    _same_scene(cj.load_scene(tmp_path / "f.toml"), fitted)


def test_designed_scene_keeps_the_sensors():
    from crank_jax.bayes.design import _with_torque

    scene = dataclasses.replace(cj.load_scene("lab-rig"),
                                sensors=(Sensor("x_s", "slide", "mm", -1.0, 0.2),))
    out = _with_torque(scene, cj.HarmonicLoad(0.0, 0.1, 2.0), 1.0, 101, cj.NoLoad(),
                       (0.5, 0.0))
    assert out.sensors == scene.sensors


# --- 14. outputs never collide -----------------------------------------------------------


def test_a_record_scene_may_not_overwrite_another_output(tmp_path, capsys):
    recs = [_csv(tmp_path / f"r{i}.csv", t=TS, phi=ANGLE) for i in range(2)]
    out = tmp_path / "fit.record1.toml"
    for report in (str(out), str(tmp_path / "." / "fit.record1.toml")):
        assert main(["fit", str(recs[0]), "lab-rig", "--more-data", str(recs[1]),
                     "--free", "k,c", "--per-record", "k", "--scene-out",
                     str(tmp_path / "fit.toml"), "--out", report, "--quiet"]) == 2
        _one_line_error(capsys, "--out", "the same file", "record 1")
    assert main(["fit", str(recs[0]), "lab-rig", "--scene-out", str(tmp_path / "f.json"),
                 "--out", str(tmp_path / "." / "f.json"), "--quiet"]) == 2
    _one_line_error(capsys, "the same file")
    assert not out.exists()


# --- 17. --phi-col and --angle-unit are never silently ignored ------------------------------


@pytest.mark.parametrize("command", ["fit", "validate", "posterior"])
def test_angle_options_beside_sensors_are_refused(lab_scene_file, tmp_path, capsys, command):
    rec = _csv(tmp_path / "rec.csv", t=TS, wheel=np.rad2deg(ANGLE), phi=ANGLE)
    calibrated = lab_scene_file('[sensors]\nphi = { column = "wheel", unit = "deg" }\n')
    out = ["--out", str(tmp_path / "o.json")]
    cases = ((["lab-rig", "--channel", "phi=wheel:deg", "--angle-unit", "deg"],
              ("--angle-unit deg", "--channel phi=wheel:deg")),
             (["lab-rig", "--channel", "phi", "--phi-col", "wheel"],
              ("--phi-col wheel", "--channel phi")),
             ([str(calibrated), "--angle-unit", "rad"], ("--angle-unit rad", "[sensors]")))
    for (scene, *opts), names in cases:
        pos = [scene, str(rec)] if command == "validate" else [str(rec), scene]
        assert main([command, *pos, *opts, *out, "--quiet"]) == 2
        _one_line_error(capsys, "would be ignored", *names)


# --- 19. constructors check their fields ---------------------------------------------------


@pytest.mark.parametrize("make, error, match", [
    (lambda: Sensor("phi", column=5), SensorError, "column must be a string"),
    (lambda: cj.Data(TS, None, channels={"theta": ANGLE}), cj.DataError,
     "Data.channels: channel 'theta' is unknown"),
    (lambda: cj.Data(TS, ANGLE, channels={"phi": ANGLE + 1}), cj.DataError,
     "given twice, as Data.phi and as Data.channels"),
    (lambda: cj.Data(TS, ANGLE, sensors=("phi",)), cj.DataError,
     "Data.sensors must be a tuple of Sensor"),
    (lambda: cj.Data(TS, ANGLE, inputs={"volts": 5.0}), cj.DataError,
     r"Data.inputs\['volts'\] must be the input's samples as a SampledLoad"),
    (lambda: cj.Scene(cj.load_scene("lab-rig").mech, torque=None), cj.SceneError,
     "Scene.torque must be a load"),
    (lambda: cj.Scene(cj.load_scene("lab-rig").mech, sensors=("phi",)), cj.SceneError,
     "Scene.sensors must be a tuple of Sensor"),
    (lambda: cj.Scene(cj.load_scene("lab-rig").mech,
                      torque=InputLoad(gain=1.0, column="tau")), cj.SceneError,
     r"\[torque\] input"),
    (lambda: cj.Data(TS, ANGLE + 0.5j), cj.DataError, "Data.phi is complex"),
    (lambda: cj.Data(TS + 0j, ANGLE), cj.DataError, "Data.ts is complex"),
    (lambda: cj.Data(TS, None, channels={"x_s": ANGLE * 1j}), cj.DataError,
     r"Data.channels\['x_s'\] is complex"),
])
def test_constructors_refuse_what_would_fail_later(make, error, match):
    with pytest.raises(error, match=match):
        make()
