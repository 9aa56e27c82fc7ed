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

    sc = cj.load_scene("lab-rig")

    def end(phi0):
        return cj.Scene(sc.mech, phi0=phi0).simulate(jnp.linspace(0.0, 0.2, 3)).phi[-1]

    assert np.all(np.isfinite(jax.vmap(end)(jnp.array([0.1, 0.2]))))
    assert np.isfinite(jax.grad(end)(0.1))


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

    mech = cj.load_scene("lab-rig").mech

    def end(amp):
        return cj.simulate(mech, 0.1, 0.0, jnp.linspace(0.0, 0.2, 3),
                           torque=cj.HarmonicLoad(0.0, amp, 2.0)).phi[-1]

    assert np.all(np.isfinite(jax.vmap(end)(jnp.array([0.1, 0.2]))))
    assert np.isfinite(jax.grad(end)(0.1))
