"""Scenes: presets, TOML round trip, strict parsing, static structure."""

import dataclasses

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.scene import SceneError

TOML = """
[mechanism]
r = 0.05
L = 0.20
b = 0.06
s = 0.025
m_c = 1.0
m_p = 0.5
m_s = 0.4
I_c = 2e-4
I_p = 1.7e-3
k = 2.0
c = 0.01
g = 9.81
[load]
P0 = 1.0
P1 = 2.0
freq_hz = 3.0
phase = 0.5
[torque]
tau0 = 0.1
[initial]
phi0 = 0.5
dphi0 = 0.2
[solver]
name = "dopri8"
rtol = 1e-9
atol = 1e-11
"""


def _write(tmp_path, text, name="scene.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_presets_load_and_have_the_promised_character():
    assert set(cj.presets()) == {"lab-rig", "torsional", "near-buckling", "pendulum"}
    f = {n: float(cj.linearize(cj.load_scene(n).mech).omega_n) / (2 * np.pi)
         for n in ("lab-rig", "torsional")}
    assert 4.0 < f["lab-rig"] < 5.0
    assert 95 < f["torsional"] < 105
    nb = cj.linearize(cj.load_scene("near-buckling").mech)
    assert 0 < float(nb.xi) < 0.02 * float(cj.load_scene("near-buckling").mech.k)
    pend = cj.load_scene("pendulum")
    assert pend.structure == cj.model.ModelTerms(
        coupler=False, slider=False, spring=False, offset=False, crank_coulomb=False,
        slider_damper=False, slider_coulomb=False, tilt=False)


def test_full_scene_file(tmp_path):
    sc = cj.load_scene(_write(tmp_path, TOML))
    assert isinstance(sc.load, cj.HarmonicLoad) and isinstance(sc.torque, cj.ConstantLoad)
    assert sc.solver == "dopri8" and float(sc.rtol) == 1e-9
    assert float(sc.phi0) == 0.5 and float(sc.dphi0) == 0.2
    np.testing.assert_allclose(sc.load(0.25), 1.0 + 2.0 * np.sin(2 * np.pi * 0.75 + 0.5))


def test_round_trip(tmp_path):
    sc = cj.load_scene(_write(tmp_path, TOML))
    out = tmp_path / "again.toml"
    cj.save_scene(sc, out)
    again = cj.load_scene(out)
    assert cj.scene_to_toml(again) == cj.scene_to_toml(sc)


FRICTION = TOML.replace("g = 9.81", "g = 9.81\ne = -0.01\nT_c = 0.02\nc_s = 0.5\nF_s = 0.3") + """
[friction]
crank_width = 0.02
slider_width = 0.005
"""


def test_offset_and_friction_keys_round_trip(tmp_path):
    sc = cj.load_scene(_write(tmp_path, FRICTION))
    v = sc.mech.as_dict()
    assert (v["e"], v["T_c"], v["c_s"], v["F_s"]) == (-0.01, 0.02, 0.5, 0.3)
    assert (v["w_c"], v["w_s"]) == (0.02, 0.005)
    text = cj.scene_to_toml(sc)
    assert "[friction]" in text and "e = -0.01" in text
    again = cj.load_scene(_write(tmp_path, text, "again.toml"))
    assert again.mech.as_dict() == v
    assert cj.scene_to_toml(again) == text
    st = again.structure
    assert st.offset and st.crank_coulomb and st.slider_damper and st.slider_coulomb


def test_defaults_of_offset_and_friction(tmp_path):
    sc = cj.load_scene(_write(tmp_path, TOML))
    v = sc.mech.as_dict()
    assert (v["e"], v["T_c"], v["c_s"], v["F_s"], v["w_c"], v["w_s"]) == (0, 0, 0, 0, 0.01, 1e-3)
    text = cj.scene_to_toml(sc)
    assert "[friction]" not in text and "T_c" not in text


@pytest.mark.parametrize("text,match", [
    (FRICTION.replace("slider_width = 0.005", "slider_width = 0.0"), "w_s must be > 0"),
    (FRICTION.replace("slider_width", "slider_wdth"),
     "unknown key 'slider_wdth' in \\[friction\\]"),
    (FRICTION.replace("F_s = 0.3", "F_s = -0.3"), "F_s must be >= 0"),
    (FRICTION.replace("e = -0.01", "e = 0.2"), "L must be > r \\+ \\|e\\|"),
    (FRICTION.replace("e = -0.01", "offset = 0.01"), "unknown key 'offset' in \\[mechanism\\]"),
])
def test_bad_offset_and_friction_rejected(tmp_path, text, match):
    with pytest.raises(SceneError, match=match):
        cj.load_scene(_write(tmp_path, text))


def test_only_mechanism_is_required(tmp_path):
    body = TOML.split("[load]")[0]
    sc = cj.load_scene(_write(tmp_path, body))
    assert isinstance(sc.load, cj.NoLoad) and isinstance(sc.torque, cj.NoLoad)


@pytest.mark.parametrize("text,match", [
    (TOML + "\n[damping]\nc = 1\n", "unknown table or key 'damping'"),
    (TOML.replace("k = 2.0", "stiffness = 2.0"), "unknown key 'stiffness' in \\[mechanism\\]"),
    (TOML.replace("phase = 0.5", "phase = 0.5\nphse = 1"), "unknown key 'phse' in \\[load\\]"),
    (TOML.replace("k = 2.0", 'k = "two"'), "\\[mechanism\\] k must be a number"),
    (TOML.replace("k = 2.0\n", ""), "missing \\['k'\\]"),
    (TOML.replace("L = 0.20", "L = 0.04"), "L must be > r"),
    (TOML.replace("m_s = 0.4", "m_s = -0.4"), "m_s must be >= 0"),
    (TOML.replace('name = "dopri8"', 'name = "rk4"'), "name 'rk4' is unknown"),
    (TOML.replace("k = 2.0", "k = nan"), "k must be finite"),
    (TOML.replace("[initial]", "[initial"), "malformed TOML"),
    ("", "\\[mechanism\\] table is required"),
])
def test_malformed_files_rejected_with_the_place_named(tmp_path, text, match):
    with pytest.raises(SceneError, match=match):
        cj.load_scene(_write(tmp_path, text))


def test_missing_file_or_preset(tmp_path):
    with pytest.raises(SceneError, match="neither a preset"):
        cj.load_scene(tmp_path / "nope.toml")


def test_binary_file_rejected(tmp_path):
    p = tmp_path / "bin.toml"
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(SceneError):
        cj.load_scene(p)


def test_scene_simulate_uses_its_settings():
    sc = cj.load_scene("pendulum")
    tr = sc.simulate(sc.ts(1.0, 11))
    assert tr.phi.shape == (11,) and float(tr.phi[0]) == float(sc.phi0)


@pytest.mark.parametrize("description", [
    "line one\nline two", "tab\there", "bell\x07 and nul\x00 and del\x7f", 'quote " and \\',
    "\\n is not a newline", "CR\r\nLF", "ünïcødé ✓ 🦀", "'''", '"""', "\ufeffbom"])
def test_description_round_trips(tmp_path, description):
    # Issue 24 (13): --scene-out wrote raw newlines and control characters into a TOML
    # basic string, and the file could not be read back.
    sc = dataclasses.replace(cj.load_scene("lab-rig"), description=description)
    out = tmp_path / "s.toml"
    cj.save_scene(sc, out)
    again = cj.load_scene(out)
    assert again.description == description
    assert cj.scene_to_toml(again) == cj.scene_to_toml(sc)


def test_lone_surrogate_is_refused_before_writing(tmp_path):
    sc = dataclasses.replace(cj.load_scene("lab-rig"), description="bad \ud800")
    with pytest.raises(cj.SceneError, match="surrogate"):
        cj.save_scene(sc, tmp_path / "s.toml")
    assert not list(tmp_path.iterdir())


def test_byte_order_mark_is_accepted(tmp_path):
    # Issue 24 (10): a UTF-8 byte-order mark (as Windows editors write) gave "Invalid
    # statement (line 1, column 1)", though CSV records accept one.
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + TOML.encode())
    assert cj.scene_to_toml(cj.load_scene(path)) == cj.scene_to_toml(
        cj.load_scene(_write(tmp_path, TOML)))
