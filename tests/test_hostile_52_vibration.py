"""Hostile inputs to the vibration analyses, scenes and loads built in Python: every check
a scene file or the command line makes, the library makes at construction, and a partial
vibration result says so."""

import importlib.resources
import json

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli import main


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


# --- scenes: the tolerances and initial state a scene file is checked for ---------------

@pytest.mark.parametrize("kw,match", [
    ({"rtol": -1.0}, "rtol must be"), ({"rtol": 0.5}, "rtol must be"),
    ({"rtol": float("nan")}, "rtol must be"), ({"rtol": float("inf")}, "rtol must be"),
    ({"atol": -1.0}, "atol must be"), ({"atol": 0.0}, "atol must be"),
    ({"atol": 1.0}, "atol must be"), ({"atol": 1e3}, "atol must be"),
    ({"phi0": float("nan")}, "phi0 must be finite"),
    ({"dphi0": float("inf")}, "dphi0 must be finite"),
])
def test_scene_refuses_what_its_file_refuses(kw, match):
    mech = cj.load_scene("lab-rig").mech
    with pytest.raises(cj.SceneError, match=match):
        cj.Scene(mech, **kw)


def test_scene_checks_skip_traced_values():
    import jax
    import jax.numpy as jnp

    mech = cj.load_scene("lab-rig").mech

    def twice(phi0):
        return 2 * cj.Scene(mech, phi0=phi0).phi0

    assert jax.vmap(twice)(jnp.array([0.1, 0.2])).tolist() == [0.2, 0.4]
    assert jax.grad(twice)(0.1) == 2.0
    assert jax.jit(lambda r, a: cj.Scene(mech, rtol=r, atol=a).rtol)(1e-8, 1e-10) == 1e-8


def test_atol_has_an_upper_bound_in_file_cli_and_api(tmp_path, capsys):
    text = (importlib.resources.files("crank_jax") / "scenes/lab-rig.toml").read_text()
    path = tmp_path / "loose.toml"
    path.write_text(text.replace("atol = 1e-10", "atol = 1e3"))
    with pytest.raises(cj.SceneError, match=r"\[solver\] atol must be .* <= 0.001"):
        cj.load_scene(path)
    code, _, err = _run(capsys, "simulate", "lab-rig", "--atol", "1", "--out",
                        str(tmp_path / "x.csv"))
    assert code == 2 and "--atol must be at most 0.001" in err, err
    mech = cj.load_scene("lab-rig").mech
    with pytest.raises(ValueError, match="atol must be a finite number > 0 and <= 0.001"):
        cj.simulate(mech, 1.0, 0.0, [0.0, 0.1], atol=1.0)


# --- loads: refused at construction as their `[load]` table is ---------------------------

def _input_load(**kw):
    from crank_jax.model.loads import InputLoad

    return InputLoad(column="volts", **kw)


@pytest.mark.parametrize("make,match", [
    (lambda: cj.HarmonicLoad(0.0, float("nan"), 2.0), "HarmonicLoad.X1 must be finite"),
    (lambda: cj.HarmonicLoad(0.0, 1.0, -2.0), "HarmonicLoad.freq_hz must be >= 0 Hz"),
    (lambda: cj.HarmonicLoad(0.0, 1.0, 2.0, float("inf")), "HarmonicLoad.phase"),
    (lambda: cj.HarmonicLoad(0.0, np.array([1.0, np.nan]), 2.0), "HarmonicLoad.X1"),
    (lambda: cj.ConstantLoad(float("nan")), "ConstantLoad.value must be finite"),
    (lambda: cj.SampledLoad([0.0, 1.0, 2.0], [0.0, np.nan, 1.0]),
     "SampledLoad.values must be finite; sample 1"),
    (lambda: cj.SampledLoad([0.0, np.nan, 2.0], [0.0, 1.0, 1.0]), "SampledLoad.ts must be"),
    (lambda: cj.MultiSineLoad([1.0, 2.0], [1.0], [0.0, 0.0]), "of one length"),
    (lambda: cj.MultiSineLoad([], [], []), "of one length >= 1"),
    (lambda: cj.MultiSineLoad([1.0], [-1.0], [0.0]), "MultiSineLoad.freqs_hz must be >= 0"),
    (lambda: _input_load(gain=float("nan")), "InputLoad.gain must be finite"),
    (lambda: _input_load(gain=1.0, freq_hz=-1.0), "InputLoad.freq_hz must be >= 0"),
])
def test_loads_refuse_bad_values_naming_the_field(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_load_checks_skip_traced_amplitudes():
    import jax
    import jax.numpy as jnp

    def at_quarter(amp):  # X(t) at a quarter period of 1 Hz: X1
        return cj.HarmonicLoad(0.0, amp, 1.0)(0.25)

    np.testing.assert_allclose(jax.vmap(at_quarter)(jnp.array([0.1, 0.2])), [0.1, 0.2])
    assert jax.grad(at_quarter)(0.1) == pytest.approx(1.0)
    assert jax.jit(lambda f: cj.HarmonicLoad(0.0, 1.0, f).freq_hz)(2.0) == 2.0


# --- the vibration API refuses what the command line refuses ----------------------------

def _driven():
    import equinox as eqx

    sc = cj.load_scene("lab-rig")
    return eqx.tree_at(lambda s: s.torque, sc, cj.HarmonicLoad(0.0, 0.05, 4.0))


def _loose(scene):
    import equinox as eqx

    return eqx.tree_at(lambda s: s.rtol, scene, np.asarray(0.5))  # skips construction


@pytest.mark.parametrize("call,match", [
    (lambda: cj.periodic_orbit(_driven(), -4.0), "freq_hz must be one finite frequency > 0"),
    (lambda: cj.periodic_orbit(_driven(), 0.0), "freq_hz must be one finite"),
    (lambda: cj.periodic_orbit(_driven(), float("nan")), "freq_hz must be one finite"),
    (lambda: cj.periodic_orbit(_driven(), 4.0, guess=np.zeros(3)), r"guess must be .* \(2,\)"),
    (lambda: cj.periodic_orbit(_loose(_driven()), 4.0), "the scene's rtol must be"),
    (lambda: cj.forced_response(_driven(), (3.0, 5.0), step=0.0), "step must be a number > 0"),
    (lambda: cj.forced_response(_driven(), (3.0, 5.0), step=-1.0), "step must be"),
    (lambda: cj.forced_response(_driven(), (3.0, 5.0), step=1e9), "at most 0.5"),
    (lambda: cj.forced_response(_driven(), (3.0, 5.0), max_points=1), "max_points must be"),
    (lambda: cj.forced_response(_driven(), (3.0, 4.0, 5.0)), "freq_hz must be a pair"),
    (lambda: cj.forced_response(_driven(), 3.0), "freq_hz must be a pair"),
    (lambda: cj.forced_response(_loose(_driven()), (3.0, 5.0)), "the scene's rtol"),
    (lambda: cj.backbone(cj.load_scene("lab-rig").mech, []), "amplitudes must be one or more"),
    (lambda: cj.backbone(cj.load_scene("lab-rig").mech, [[0.1, 0.2]]), "shape"),
    (lambda: cj.backbone(cj.load_scene("lab-rig").mech.replace(k=np.array([2.0, 3.0])), [0.1]),
     "mech.k has shape"),
    (lambda: cj.backbone(cj.load_scene("lab-rig").mech, [0.1], rtol=0.5), "rtol must be"),
    (lambda: cj.stability_chart(cj.load_scene("lab-rig"), (0.0, 1.0, 2.0), (1.0, 2.0)),
     "load_amplitude must be a pair"),
    (lambda: cj.stability_chart(cj.load_scene("lab-rig"), (0.0, 1.0), (2.0, 1.0)),
     "freq_hz must be"),
    (lambda: cj.stability_chart(_loose(cj.load_scene("lab-rig")), (0.0, 1.0), (1.0, 2.0)),
     "the scene's rtol"),
])
def test_vibration_api_refuses_bad_arguments_naming_them(call, match):
    with pytest.raises(cj.vibration.VibrationError, match=match):
        call()


# --- partial results say so, in the user's units, and do not exit 0 ---------------------

def _half_failed(monkeypatch):
    """Make every other chart point's monodromy solve fail (NaN), as a solve that ran out of
    steps does, without the minutes such a solve takes."""
    import jax.numpy as jnp

    from crank_jax.vibration import chart

    real = chart._chart

    def failing(scene, amps, freqs, structure, rest):
        fm = real(scene, amps, freqs, structure, rest)
        return jnp.where(jnp.arange(fm.shape[0]) % 2 == 0, jnp.nan, fm)

    monkeypatch.setattr(chart, "_chart", failing)


def test_chart_failed_points_are_neither_stable_nor_unstable(monkeypatch, tmp_path, capsys):
    _half_failed(monkeypatch)
    lab = cj.load_scene("lab-rig")
    ch = cj.stability_chart(lab, (0.0, 1e-3), (2.0, 3.0), grid=2)  # no forcing: damped rest
    assert ch.ok.tolist() == [[False, True], [False, True]]
    assert not ch.stable[:, 0].any() and not ch.unstable.any() and ch.stable[:, 1].all()
    out = tmp_path / "c.json"
    code, text, err = _run(capsys, "stability", "lab-rig", "--load-amplitude", "0:0.001",
                           "--freq", "2:3", "--grid", "2", "--out", str(out))
    assert code == 1, err
    assert "0% unstable, 50% stable" in text, text
    assert "partial: 2 of 4 points failed" in err and "Hz" in err, err
    doc = json.loads(out.read_text())
    assert doc["ok"] == [[False, True], [False, True]]
    assert doc["floquet_max"][0][0] is None


def test_backbone_below_the_resolvable_amplitude_is_refused(tmp_path, capsys):
    code, _, err = _run(capsys, "backbone", "lab-rig", "--amplitudes", "1e-300:1e-299:2",
                        "--out", str(tmp_path / "b.json"))
    assert code == 2 and "amplitudes must be >= 1e-200 rad" in err, err
    assert "rotation" not in err and not (tmp_path / "b.json").exists()
    with pytest.raises(cj.vibration.VibrationError, match=r"amplitudes must be >= 0.00011 rad "
                       r"about the rest at 3.14159 rad"):
        cj.backbone(cj.load_scene("pendulum").mech, [3e-5, 0.1])


def test_response_stopped_early_is_partial_in_hz(tmp_path, capsys):
    import equinox as eqx

    sc = cj.load_scene("lab-rig")
    driven = eqx.tree_at(lambda s: s.torque, sc, cj.HarmonicLoad(0.0, 0.05, 4.0))
    resp = cj.forced_response(driven, (3.0, 5.5), max_points=3)
    assert resp.complete is False and resp.to_dict()["complete"] is False
    assert resp.stopped.startswith("partial: the curve covers 3 to ")
    assert "Hz of the 3 to 5.5 Hz asked" in resp.stopped and "max_points = 3" in resp.stopped
    path = tmp_path / "d.toml"
    cj.save_scene(driven, path)
    out = tmp_path / "r.json"
    code, _, err = _run(capsys, "response", str(path), "--freq", "3:5.5", "--max-points", "3",
                        "--out", str(out))
    assert code == 1 and "partial: the curve covers 3 to" in err, err
    assert json.loads(out.read_text())["complete"] is False


# --- a crank that hangs is analysed about its stable rest at pi --------------------------

def test_pendulum_backbone_is_the_exact_pendulum_law():
    from scipy.special import ellipk

    mech = cj.load_scene("pendulum").mech
    amps = np.array([0.1, 1.0, 2.0])
    bb = cj.backbone(mech, amps)
    assert np.all(bb.ok)
    # A compound pendulum: omega0^2 = m g s / (I_c + m s^2), and the exact period of a swing
    # of amplitude A is 2 K(sin^2(A/2)) / pi times the linear one.
    f0 = np.sqrt(9.81 * 0.025 / (2e-4 + 0.025**2)) / (2 * np.pi)
    assert float(bb.linear_frequency_hz) == pytest.approx(f0, rel=1e-12)
    exact = f0 * np.pi / (2 * ellipk(np.sin(amps / 2) ** 2))
    np.testing.assert_allclose(bb.frequency_hz, exact, rtol=1e-8)
    np.testing.assert_allclose(np.asarray(bb.phi_max) - amps, np.pi, atol=1e-9)


def test_pendulum_chart_is_about_its_rest_at_pi():
    ch = cj.stability_chart(cj.load_scene("pendulum"), (0.0, 1e-3), (1.0, 3.0), grid=2)
    assert ch.rest == pytest.approx(np.pi)
    assert ch.ok.all() and ch.stable.all()  # lightly damped, hardly forced: stable


def test_backbone_cli_tells_a_rotation_from_a_failed_solve(tmp_path, capsys):
    # The pendulum goes over the top beyond pi: no swing of 3.3 rad exists (a complete
    # answer, exit 0). A jump from 2 to 3 rad fails although that swing exists: partial.
    out = tmp_path / "b.json"
    code, text, err = _run(capsys, "backbone", "pendulum", "--amplitudes", "0.5:3.3:4",
                           "--out", str(out))
    assert code == 0 and "beyond 3.14159 rad the crank goes over the top" in text, err
    doc = json.loads(out.read_text())
    assert len(doc["points"]) == 3 and doc["largest_swing"] == pytest.approx(np.pi)
    code, _, err = _run(capsys, "backbone", "pendulum", "--amplitudes", "2:3:2", "--out",
                        str(out))
    assert code == 1 and "partial: no swing of amplitude 3 rad or more was found" in err
    assert "swings up to 3.14159 rad exist" in err, err
    assert len(json.loads(out.read_text())["points"]) == 1
