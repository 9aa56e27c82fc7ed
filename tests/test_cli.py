"""The crank-jax command line: outputs, atomic writes, one-line errors with exit 2."""

import json
import subprocess
import sys

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli import main


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_simulate_writes_csv_and_plot(tmp_path, capsys):
    out, png = tmp_path / "x.csv", tmp_path / "x.png"
    code, _, err = _run(capsys, "simulate", "lab-rig", "--t1", "2", "--samples", "201",
                        "--extras", "energy,reactions", "--out", str(out), "--plot", str(png))
    assert code == 0, err
    header = out.read_text().splitlines()[0].split(",")
    assert header == ["t", "phi", "dphi", "energy", "O_x", "O_y", "A_x", "A_y", "B_x", "B_y", "N",
                      "F"]
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    assert data.shape == (201, 12)
    np.testing.assert_allclose(data[:, 0], np.linspace(0, 2, 201))
    ref = cj.load_scene("lab-rig").simulate(np.linspace(0, 2, 201))
    np.testing.assert_allclose(data[:, 1], ref.phi, rtol=0, atol=1e-12)
    assert png.stat().st_size > 1000
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary files left behind


def test_simulate_overrides(tmp_path, capsys):
    out = tmp_path / "x.csv"
    code, _, err = _run(capsys, "simulate", "pendulum", "--t1", "1", "--samples", "11",
                        "--phi0", "0.3", "--dphi0", "-1", "--solver", "tsit5", "--rtol", "1e-6",
                        "--atol", "1e-9", "--out", str(out))
    assert code == 0, err
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    assert data[0, 1] == 0.3 and data[0, 2] == -1.0


def test_linearize_json_keys(capsys):
    code, out, _ = _run(capsys, "linearize", "lab-rig", "--json")
    assert code == 0
    d = json.loads(out)
    assert list(d) == ["mu", "chi", "xi", "omega_n", "zeta", "stable", "k_crit", "phi_eq"]
    lin = cj.linearize(cj.load_scene("lab-rig").mech)
    assert d["xi"] == pytest.approx(float(lin.xi), rel=1e-15) and d["stable"] is True


def test_scenes_lists_presets(capsys):
    code, out, _ = _run(capsys, "scenes")
    assert code == 0
    assert [ln.split()[0] for ln in out.splitlines()] == list(cj.presets())


def test_never_overwrites_the_input(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    cj.save_scene(cj.load_scene("lab-rig"), scene)
    before = scene.read_bytes()
    code, _, err = _run(capsys, "simulate", str(scene), "--out", str(scene))
    assert code == 2 and "refusing to overwrite" in err
    assert scene.read_bytes() == before


@pytest.mark.parametrize("argv,match", [
    (["simulate", "nope", "--out", "x.csv"], "neither a preset"),
    (["simulate", "lab-rig"], "required: --out"),
    (["simulate", "lab-rig", "--out", "x.csv", "--bogus"], "unrecognized arguments"),
    (["simulate", "lab-rig", "--out", "x.csv", "--solver", "rk4"], "--solver 'rk4'"),
    (["simulate", "lab-rig", "--out", "x.csv", "--t1", "-1"], "--t1 must be"),
    (["simulate", "lab-rig", "--out", "x.csv", "--samples", "1"], "--samples must be"),
    (["simulate", "lab-rig", "--out", "x.csv", "--rtol", "nan"], "--rtol must be"),
    (["simulate", "lab-rig", "--out", "x.csv", "--extras", "junk"], "unknown output"),
    (["simulate", "lab-rig", "--out", "/no/such/dir/x.csv", "--t1", "0.1", "--samples", "3"],
     "does not exist"),
    (["frobnicate"], "invalid choice"),
    ([], "required"),
])
def test_user_mistakes_exit_2_with_one_line(tmp_path, capsys, monkeypatch, argv, match):
    monkeypatch.chdir(tmp_path)
    code, out, err = _run(capsys, *argv)
    assert code == 2
    assert len(err.strip().splitlines()) == 1, err
    assert match in err
    assert "Traceback" not in err


def test_malformed_scene_file_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[mechanism]\nr = 0.05\nL = 0.02\n")
    code, _, err = _run(capsys, "linearize", str(bad))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "missing" in err


def test_console_script_entry_point(tmp_path):
    out = tmp_path / "x.csv"
    p = subprocess.run([sys.executable, "-m", "crank_jax", "simulate", "lab-rig", "--t1",
                        "0.5", "--samples", "6", "--out", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert out.read_text().startswith("t,phi,dphi\n")


def _commands():
    from crank_jax.cli import identify, sweep
    from crank_jax.cli import simulate_command as simulate
    from crank_jax.cli import synth_command as synth

    return [c[0] for c in simulate.COMMANDS + synth.COMMANDS + identify.COMMANDS
            + sweep.COMMANDS]


@pytest.mark.parametrize("argv", [["--help"]] + [[c, "--help"] for c in _commands()])
def test_help_of_every_command(capsys, argv):
    # Issue 10, row 1: an unescaped % in a help text made --help a traceback.
    code, out, err = _run(capsys, *argv)
    assert code == 0 and err == ""
    assert out.startswith("usage: crank-jax")
