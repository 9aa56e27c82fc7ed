"""`crank-jax synth`, `crank-jax fit` and `crank-jax demo`."""

import json

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli import main

KEYS = ["estimates", "identifiable", "unidentifiable_directions", "rms_residual", "n_samples",
        "converged", "iterations", "seconds", "warnings", "diagnostics", "channels",
        "termination", "predictions"]


@pytest.fixture(scope="module")
def pendulum_csv(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    out = d / "data.csv"
    assert main(["synth", "pendulum", "--t1", "2", "--rate", "50", "--noise-std", "0.002",
                 "--quantization", "4096", "--jitter-std", "1e-4", "--seed", "4",
                 "--out", str(out)]) == 0
    return out


def test_synth_writes_documented_csv(pendulum_csv):
    text = pendulum_csv.read_text().splitlines()
    assert text[0].startswith("# crank-jax synth pendulum")
    assert text[1] == "t,phi"
    data = cj.load_data(pendulum_csv)
    assert data.n == 101


def test_synth_writes_load_columns(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text(cj.scene_to_toml(cj.Scene(cj.load_scene("lab-rig").mech,
                                               torque=cj.HarmonicLoad(0.0, 0.2, 3.0))))
    out = tmp_path / "d.csv"
    assert main(["synth", str(scene), "--t1", "0.2", "--rate", "50", "--out", str(out)]) == 0
    assert out.read_text().splitlines()[1] == "t,phi,tau"


def test_fit_writes_report_and_plot(pendulum_csv, tmp_path, capsys):
    out, png = tmp_path / "fit.json", tmp_path / "fit.png"
    rc = main(["fit", str(pendulum_csv), "pendulum", "--free", "c,phi0,dphi0", "--out",
               str(out), "--plot", str(png), "--quiet"])
    assert rc == 0
    doc = json.loads(out.read_text())
    assert list(doc) == KEYS
    c = doc["estimates"]["c"]
    assert doc["converged"] and doc["identifiable"] and c["stderr"] > 0
    assert c["ci95"][0] < c["value"] < c["ci95"][1]
    assert abs(c["value"] - 0.0005) < 4 * c["stderr"]
    assert png.stat().st_size > 1000
    assert "95% CI" in capsys.readouterr().out


def test_fit_degrees_and_renamed_columns(pendulum_csv, tmp_path):
    data = cj.load_data(pendulum_csv)
    other = tmp_path / "deg.txt"
    rows = "\n".join(f"{float(t)!r} {float(np.rad2deg(p))!r}"
                     for t, p in zip(data.ts, data.phi))
    other.write_text("% exported\ntime angle_deg\n" + rows + "\n")
    out = tmp_path / "fit.json"
    assert main(["fit", str(other), "pendulum", "--free", "c,phi0,dphi0", "--t-col", "time",
                 "--phi-col", "angle_deg", "--angle-unit", "deg", "--out", str(out),
                 "--quiet"]) == 0
    direct = tmp_path / "direct.json"
    assert main(["fit", str(pendulum_csv), "pendulum", "--free", "c,phi0,dphi0", "--out",
                 str(direct), "--quiet"]) == 0
    a = json.loads(out.read_text())["estimates"]["c"]
    b = json.loads(direct.read_text())["estimates"]["c"]
    # The same estimate to 1% of its standard error. The conversion is exact to rounding;
    # what is left is where Levenberg-Marquardt stops on an objective that carries the
    # solver's own error (rtol 1e-8): 6e-4 standard errors seen (1.1e-6 relative, so a
    # relative 1e-6 tested the stopping point, not the units). Angles read as radians
    # instead of degrees would move c by far more than its standard error.
    assert abs(a["value"] - b["value"]) <= 0.01 * b["stderr"]


def test_unidentifiable_request_exits_zero_with_warning(pendulum_csv, tmp_path, capsys):
    out = tmp_path / "fit.json"
    rc = main(["fit", str(pendulum_csv), "pendulum", "--free", "m_c,I_c,c,phi0,dphi0",
               "--out", str(out), "--quiet"])
    assert rc == 0
    doc = json.loads(out.read_text())
    assert doc["identifiable"] is False
    msg = "m_c, I_c and c are determined only up to a common scale"
    assert any(msg in d for d in doc["unidentifiable_directions"])
    assert doc["estimates"]["c"]["stderr"] is None and doc["estimates"]["c"]["ci95"] is None
    assert "warning: not identifiable: " + msg in capsys.readouterr().err


@pytest.mark.parametrize(
    "args, match",
    [
        (["fit", "{data}", "pendulum", "--free", "k,wat"], "unknown free parameter"),
        (["fit", "{data}", "pendulum", "--phi-col", "angle"], "missing column 'angle'"),
        (["fit", "{data}", "pendulum", "--out", "{data}"], "is an input file"),
        (["fit", "{data}"], "give both DATA and SCENE"),
        (["fit", "{data}", "pendulum", "--multistart", "0"], "--multistart must be >= 1"),
        (["synth", "pendulum", "--rate", "-5", "--out", "{tmp}/x.csv"], "rate"),
        (["fit", "{tmp}/missing.csv", "pendulum"], "missing.csv' does not exist"),
    ],
)
def test_user_errors_exit_2(pendulum_csv, tmp_path, capsys, args, match):
    args = [a.format(data=pendulum_csv, tmp=tmp_path) for a in args]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert match in err and err.count("\n") == 1


def test_demo_prints_estimates_with_intervals(tmp_path, capsys):
    out = tmp_path / "demo.json"
    assert main(["demo", "--quiet", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert "95% CI" in printed and "truth: k = 2" in printed
    # The demo does not warn about its own setup (it printed the reason for its shooting
    # choice as a warning on every run).
    assert "warning" not in captured.err, captured.err
    doc = json.loads(out.read_text())
    assert doc["converged"] and doc["identifiable"] and doc["warnings"] == []
    assert set(doc["estimates"]) == {"k", "c", "phi0", "dphi0"}


def test_demo_fits_the_public_demo_record(monkeypatch, capsys):
    # `crank-jax demo` fits `crank_jax.identify.demo_record(--noise-seed)`, the record a
    # script or test gets from the library, not a copy of its own.
    import crank_jax.identify.demo as demo
    from crank_jax.cli.errors import UserError

    def spy(seed=1):
        raise UserError(f"demo_record({seed}) called")

    monkeypatch.setattr(demo, "demo_record", spy)
    assert main(["demo", "--quiet", "--noise-seed", "7"]) == 2
    assert "demo_record(7) called" in capsys.readouterr().err
    assert cj.identify.DEMO is demo.DEMO and cj.identify.demo_record is not spy


def test_fit_window_options(pendulum_csv, tmp_path):
    out = tmp_path / "fit.json"
    assert main(["fit", str(pendulum_csv), "pendulum", "--free", "c,phi0,dphi0",
                 "--t-start", "0.5", "--t-end", "1.8", "--out", str(out), "--quiet"]) == 0
    data = cj.load_data(pendulum_csv)
    doc = json.loads(out.read_text())
    assert doc["n_samples"] == int(np.sum((data.ts >= 0.5) & (data.ts <= 1.8)))


def test_fit_window_errors_exit_2(pendulum_csv, capsys):
    assert main(["fit", str(pendulum_csv), "pendulum", "--t-start", "1.5", "--t-end",
                 "1.0"]) == 2
    assert "--t-start (1.5) must be before --t-end (1)" in capsys.readouterr().err
    assert main(["fit", str(pendulum_csv), "pendulum", "--t-start", "50"]) == 2
    assert "widen --t-start/--t-end" in capsys.readouterr().err


def test_every_command_that_reads_records_takes_the_same_record_options():
    # `posterior` lacked `--t-col` and `--load-interp`: a record with a "time" column
    # could be fitted and validated but not sampled.
    from crank_jax.cli.main import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command").choices

    def options(name):
        return {o for a in sub[name]._actions for o in a.option_strings}

    record = {"--t-col", "--load-interp", "--phi-col", "--angle-unit"}
    for name in ("fit", "validate", "posterior"):
        assert record <= options(name), (name, sorted(record - options(name)))
