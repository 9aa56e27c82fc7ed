"""Experiment design: the Fisher information of a multisine torque, its bound, and the
CLI's bad input."""

import json

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.bayes.design import max_tones
from crank_jax.cli.main import main


@pytest.fixture(scope="module")
def short_design():
    scene = cj.load_scene("lab-rig")
    return scene, cj.design(scene, ("m_s", "I_p", "k"), 1.0, 100.0, amplitude=0.2, tones=2,
                            iterations=2, progress=False)


def test_design_respects_the_bound_and_predicts_from_the_fit(short_design):
    """The torque's peak is the bound; the predicted standard errors are those the fit's own
    Jacobian gives on a record synthesised with the designed scene (an independent path:
    the fit's residual program, not the design's solve)."""
    scene, d = short_design
    ts = np.linspace(0, 1.0, 20001)
    assert np.max(np.abs(np.asarray(d.torque(ts)))) <= 0.2 * (1 + 1e-9)
    assert d.peak == pytest.approx(0.2, rel=2e-3)
    assert d.scene.t1 == 1.0 and d.scene.samples == 101
    data = cj.synthesize(d.scene, rate=100.0, noise_std=0.0)
    noise = 1e-3
    data = cj.Data(data.ts, data.phi + np.random.default_rng(0).normal(0, noise, data.n),
                   torque=data.torque)
    res = cj.fit(d.scene, data, ("m_s", "I_p", "k"), sigma=noise, progress=False, warn=False)
    for n in ("m_s", "I_p", "k"):
        assert res.stderr[n] == pytest.approx(d.predicted_stderr[n]["designed"], rel=0.05)
    assert np.isfinite(d.log_det_fisher) and np.isfinite(d.baseline_log_det_fisher)


def test_slider_force_and_release_as_design_variables():
    """A designed slider force keeps its bound, a designed release speed its bound, and the
    designed scene carries both; the predicted standard errors (phi0 and dphi0 free, so
    the release enters the sensitivities too) are the fit's on a record of that scene."""
    scene = cj.load_scene("lab-rig")
    free = ("k", "m_s", "phi0", "dphi0")
    d = cj.design(scene, free, 1.0, 100.0, amplitude=0.2, tones=2, iterations=3,
                  force_amplitude=5.0, release=True, release_speed=2.0, progress=False)
    ts = np.linspace(0, 1.0, 20001)
    assert np.max(np.abs(np.asarray(d.force(ts)))) <= 5.0 * (1 + 1e-9)
    assert d.scene.load is d.force and d.scene.torque is d.torque
    assert (d.scene.phi0, d.scene.dphi0) == d.release and abs(d.release[1]) < 2.0
    assert d.release != (scene.phi0, scene.dphi0)  # the optimiser moved them
    doc = d.to_json()
    assert doc["release"] == {"phi0": d.release[0], "dphi0": d.release[1]}
    assert len(doc["force"]["amplitudes"]) == 2
    data = cj.synthesize(d.scene, rate=100.0, noise_std=0.0)
    noise = 1e-3
    data = cj.Data(data.ts, data.phi + np.random.default_rng(1).normal(0, noise, data.n))
    res = cj.fit(d.scene, data, free, sigma=noise, progress=False, warn=False)
    for n in free:
        assert res.stderr[n] == pytest.approx(d.predicted_stderr[n]["designed"], rel=0.05)


def test_force_design_refuses_a_scene_with_its_own_slider_load():
    import dataclasses

    from crank_jax.model.loads import ConstantLoad

    scene = dataclasses.replace(cj.load_scene("lab-rig"), load=ConstantLoad(1.0))
    with pytest.raises(ValueError, match="`force_amplitude=`: the scene has its own slider"):
        cj.design(scene, ("k",), 1.0, 100.0, force_amplitude=1.0, progress=False)


def test_max_tones():
    assert max_tones(5.0, 200.0) == 250  # 0.2 Hz apart, from 0.2 Hz up to 50 Hz
    assert max_tones(1.0, 4.0) == 1


@pytest.mark.parametrize("extra, match", [
    (["--torque-amplitude", "0"], "--torque-amplitude must be > 0"),
    (["--torque-amplitude", "-1"], "--torque-amplitude must be > 0"),
    (["--torque-amplitude", "0.2", "--tones", "500"], "--tones: 500 tones do not fit"),
    (["--torque-amplitude", "0.2", "--criterion", "c", "--target", "m_c"],
     "--target m_c is not free"),
    (["--torque-amplitude", "0.2", "--criterion", "c"], "needs --target"),
    (["--torque-amplitude", "0.2", "--force-amplitude", "0"], "--force-amplitude must be > 0"),
    (["--torque-amplitude", "0.2", "--force-amplitude", "nan"],
     "--force-amplitude must be > 0"),
    (["--torque-amplitude", "0.2", "--release-speed", "-1"], "--release-speed must be > 0"),
])
def test_cli_bad_input_exit_2_one_line(tmp_path, capsys, extra, match):
    rc = main(["design", "lab-rig", "--free", "m_s,I_p,k,c", "--t1", "5", "--rate", "200",
               *extra, "--scene-out", str(tmp_path / "d.toml"), "--out",
               str(tmp_path / "d.json")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and match in err
    assert not (tmp_path / "d.json").exists()


def test_cli_design_writes_a_scene_and_report(tmp_path, capsys):
    out, sc = tmp_path / "d.json", tmp_path / "d.toml"
    rc = main(["design", "lab-rig", "--free", "m_s,I_p,k", "--t1", "1", "--rate", "100",
               "--torque-amplitude", "0.2", "--tones", "2", "--iterations", "1",
               "--scene-out", str(sc), "--out", str(out), "--quiet"])
    assert rc == 0
    doc = json.loads(out.read_text())
    assert {"log_det_fisher", "baseline_log_det_fisher", "predicted_stderr"} <= set(doc)
    assert set(doc["predicted_stderr"]["m_s"]) == {"designed", "baseline"}
    scene = cj.load_scene(sc)
    assert isinstance(scene.torque, cj.MultiSineLoad)
    assert np.asarray(scene.torque.amplitudes).shape == (2,)


@pytest.mark.parametrize("command", ["posterior", "design"])
def test_help(capsys, command):
    with pytest.raises(SystemExit) as e:
        from crank_jax.cli.main import build_parser

        build_parser().parse_args([command, "--help"])
    assert e.value.code == 0
    assert capsys.readouterr().out.startswith("usage: crank-jax")
