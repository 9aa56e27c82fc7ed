"""`fit --per-record` with any free name, channel offsets included."""

import dataclasses
import json

import pytest

import crank_jax as cj
from crank_jax.cli import main
from crank_jax.cli.errors import UserError
from crank_jax.cli.identify import _fit_kwargs
from crank_jax.cli.main import build_parser
from crank_jax.records.sensors import Sensor

SLIDE = Sensor("x_s", "slide_mm", "mm", scale=-1.0, offset=0.2948)
WHEEL = Sensor("phi", "wheel_deg", "deg", scale=-1.0, offset=-3.083)


def _scene(sensors=(WHEEL, SLIDE)) -> cj.Scene:
    """A motor-driven crank with no spring: it turns about 4 times in 1 s."""
    mech = cj.SliderCrank(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.5, m_p=0.3, m_s=0.4, I_c=1e-3,
                          I_p=2e-3, k=0.0, c=1e-3, g=9.81)
    return cj.Scene(mech, torque=cj.ConstantLoad(0.05), phi0=0.0, dphi0=10.0, t1=1.0,
                    sensors=tuple(sensors))


def _args(*extra):
    return build_parser().parse_args(["fit", "a.csv", "s.toml", "--more-data", "b.csv",
                                      "--free", "c,x_s_offset,phi0,dphi0", "--per-record",
                                      "x_s_offset", *extra])


def test_profile_names_a_per_record_value():
    # --profile was checked against the names of a fit without --per-record: a record's
    # own value (x_s_offset[1]) was refused, the shared name (no longer reported) let
    # through to fail later.
    kw = _fit_kwargs(_args("--profile", "x_s_offset[1]"), _scene(), 2)
    assert kw["profile"] == "x_s_offset[1]" and kw["per_record"] == ("x_s_offset",)
    with pytest.raises(UserError, match=r"--profile 'x_s_offset' is not a free parameter; "
                                        r"choose from c, x_s_offset\[0\], phi0\[0\]"):
        _fit_kwargs(_args("--profile", "x_s_offset"), _scene(), 2)


@pytest.mark.slow
def test_a_channel_offset_fitted_per_record_goes_into_each_records_scene(tmp_path):
    # The slide sensor re-zeroed between the records: 2 mm apart.
    paths = []
    for i, shift in enumerate((0.0, 0.002)):
        sensors = (WHEEL, dataclasses.replace(SLIDE, offset=SLIDE.offset + shift))
        data = cj.synthesize(_scene(sensors), rate=50, noise_std={"phi": 1e-3, "x_s": 2e-5},
                             seed=i, sensors=sensors)
        paths.append(tmp_path / f"r{i}.csv")
        cj.save_data(data, paths[-1])
    start, out = tmp_path / "s.toml", tmp_path / "fitted.toml"
    cj.save_scene(_scene(), start)
    assert main(["fit", str(paths[0]), str(start), "--more-data", str(paths[1]), "--free",
                 "c,x_s_offset,phi0,dphi0", "--per-record", "x_s_offset", "--scene-out",
                 str(out), "--out", str(tmp_path / "fit.json"), "--quiet"]) == 0
    doc = json.loads((tmp_path / "fit.json").read_text())
    assert doc["converged"]
    for i, path in enumerate((out, tmp_path / "fitted.record1.toml")):
        got = {s.name: s for s in cj.load_scene(str(path)).sensors}["x_s"].offset
        assert got == pytest.approx(doc["estimates"][f"x_s_offset[{i}]"]["value"], rel=1e-12)
        assert got == pytest.approx(SLIDE.offset + 0.002 * i, abs=2e-5)
