"""`crank-jax validate`: scores, outputs, and one-line errors that overwrite nothing."""

import json

import pytest

import crank_jax as cj
from crank_jax.cli import main


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A scene with a known crank torque (TOML), a record of it with a tau column, and the
    same record without the column."""
    d = tmp_path_factory.mktemp("val")
    base = cj.load_scene("lab-rig")
    scene = cj.Scene(base.mech, torque=cj.HarmonicLoad(0.0, 0.2, 3.0), phi0=0.5, t1=3.0)
    toml = d / "shaken.toml"
    cj.save_scene(scene, toml)
    data = cj.synthesize(scene, rate=200.0, t_start=0.4)
    csv = d / "rec.csv"
    cj.save_data(data, csv)
    bare = d / "bare.csv"
    cj.save_data(cj.Data(data.ts, data.phi), bare)
    return d, toml, csv, bare


def test_validate_writes_scores_and_plot(files, tmp_path, capsys):
    _, toml, csv, _ = files
    out, png = tmp_path / "val.json", tmp_path / "val.png"
    rc = main(["validate", str(toml), str(csv), "--init-window", "0.25", "--t-end", "2.5",
               "--out", str(out), "--plot", str(png), "--quiet"])
    assert rc == 0
    doc = json.loads(out.read_text())
    for key in ("rms", "max_abs", "fit_percent", "n_samples", "phi0", "dphi0"):
        assert key in doc
    # The record's tau column is linearly interpolated at 200 Hz: a small model error.
    assert doc["rms"] < 1e-3 and doc["fit_percent"] > 99.0
    assert doc["t_end"] <= 2.5 and doc["n_samples"] == sum(
        1 for t in cj.load_data(csv).ts if 0.4 + 0.25 < t <= 2.5)
    assert png.stat().st_size > 1000
    assert "fit" in capsys.readouterr().out


def run_error(argv, capsys):
    rc = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    return err[0]


@pytest.mark.parametrize("extra, needle", [
    (["--t-start", "2.99"], "window"),
    (["--t-start", "2.0", "--t-end", "1.0"], "--t-start"),
    (["--init-window", "2.59"], "--init-window"),
    (["--init-window", "0"], "--init-window"),
    (["--load-interp", "quadratic"], "--load-interp"),
])
def test_bad_values_exit_2_and_write_nothing(files, tmp_path, capsys, extra, needle):
    _, toml, csv, _ = files
    out = tmp_path / "val.json"
    out.write_text("keep")
    msg = run_error(["validate", str(toml), str(csv), "--out", str(out), "--quiet"] + extra,
                    capsys)
    assert needle in msg
    assert out.read_text() == "keep"


def test_missing_load_column_takes_the_scenes_as_fit_does(files, tmp_path):
    # As in `fit`, the scene's torque serves where the record has no tau column (it was
    # refused unless --scene-loads was given); --scene-loads is kept and changes nothing.
    _, toml, _, bare = files
    docs = []
    for extra in ([], ["--scene-loads"]):
        out = tmp_path / f"val{len(extra)}.json"
        assert main(["validate", str(toml), str(bare), "--init-window", "0.25", "--out",
                     str(out), "--quiet"] + extra) == 0
        docs.append(json.loads(out.read_text()))
    assert docs[0]["rms"] < 1e-6 and docs[0]["rms"] == docs[1]["rms"]


def test_out_onto_an_input_is_refused(files, capsys):
    _, toml, csv, _ = files
    before = csv.read_text()
    msg = run_error(["validate", str(toml), str(csv), "--out", str(csv), "--quiet"], capsys)
    assert "input file" in msg
    assert csv.read_text() == before
    msg = run_error(["validate", str(toml), str(csv), "--out", str(csv.parent / "v.json"),
                     "--plot", str(toml), "--quiet"], capsys)
    assert "input file" in msg
