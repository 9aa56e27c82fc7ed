"""`crank-jax backbone`, `response` and `stability`: their JSON, figures and one-line
refusals (exit 2)."""

import json

import equinox as eqx
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli import main


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("argv,match", [
    (["backbone", "lab-rig", "--amplitudes", "1:0.1", "--out", "b.json"], "--amplitudes"),
    (["backbone", "lab-rig", "--amplitudes", "0.1", "--out", "b.json"], "A0:A1[:N]"),
    (["backbone", "lab-rig", "--amplitudes", "0:1", "--out", "b.json"], "> 0"),
    (["response", "lab-rig", "--freq", "3:5", "--out", "r.json"], "tau1"),
    (["response", "lab-rig", "--freq", "5:3", "--out", "r.json"], "--freq"),
    (["response", "lab-rig", "--freq", "3:5", "--out", "r.json", "--plot", "r.xyz"],
     "not supported"),
    (["stability", "lab-rig", "--load-amplitude", "0:10", "--freq", "1:2", "--grid", "1",
      "--out", "c.json"], "--grid"),
    (["stability", "lab-rig", "--load-amplitude", "-1:10", "--freq", "1:2", "--out",
      "c.json"], "--load-amplitude"),
    (["backbone", "lab-rig", "--amplitudes", "0.1:1", "--out", "/no/such/dir/b.json"],
     "does not exist"),
])
def test_vibration_mistakes_exit_2_with_one_line(tmp_path, capsys, monkeypatch, argv, match):
    monkeypatch.chdir(tmp_path)
    code, out, err = _run(capsys, *argv)
    assert code == 2
    assert len(err.strip().splitlines()) == 1, err
    assert match in err and "Traceback" not in err
    assert not list(tmp_path.iterdir())  # nothing written


def test_backbone_command_writes_json(tmp_path, capsys):
    out = tmp_path / "bb.json"
    code, text, err = _run(capsys, "backbone", "lab-rig", "--amplitudes", "0.1:1.0:3",
                           "--out", str(out))
    assert code == 0, err
    doc = json.loads(out.read_text())
    f_lin = float(cj.linearize(cj.load_scene("lab-rig").mech).omega_n) / (2 * np.pi)
    assert doc["linear_frequency_hz"] == pytest.approx(f_lin, rel=1e-12)
    pts = doc["points"]
    assert [p["amplitude"] for p in pts] == pytest.approx([0.1, 0.55, 1.0])
    for p in pts:
        assert set(p) == {"amplitude", "phi_max", "phi_min", "frequency_hz", "period"}
        assert p["period"] * p["frequency_hz"] == pytest.approx(1.0)
        assert (p["phi_max"] - p["phi_min"]) / 2 == pytest.approx(p["amplitude"])


@pytest.mark.slow
def test_response_and_stability_commands(tmp_path, capsys):
    scene = tmp_path / "driven.toml"
    sc = cj.load_scene("lab-rig")
    cj.save_scene(eqx.tree_at(lambda s: s.torque, sc, cj.HarmonicLoad(0.0, 0.05, 4.0)),
                  scene)
    out, png = tmp_path / "frc.json", tmp_path / "frc.png"
    code, _, err = _run(capsys, "response", str(scene), "--freq", "3:5.5", "--out", str(out),
                        "--plot", str(png))
    assert code == 0, err
    doc = json.loads(out.read_text())
    (b,) = doc["branches"]
    n = len(b["freq_hz"])
    assert all(len(b[k]) == n for k in ("amplitude", "phi_max", "phi_min", "stable",
                                        "floquet"))
    assert len(doc["folds"]) == 2 and set(doc["folds"][0]) == {"freq_hz", "amplitude"}
    assert png.read_bytes()[:4] == b"\x89PNG"
    out, png = tmp_path / "chart.json", tmp_path / "chart.png"
    code, _, err = _run(capsys, "stability", "lab-rig", "--load-amplitude", "0:20", "--freq",
                        "7:11", "--grid", "3", "--out", str(out), "--plot", str(png))
    assert code == 0, err
    doc = json.loads(out.read_text())
    assert np.shape(doc["floquet_max"]) == (3, 3) and np.shape(doc["stable"]) == (3, 3)
    assert len(doc["freq_hz"]) == 3 and len(doc["amplitude"]) == 3
    assert png.read_bytes()[:4] == b"\x89PNG"
