"""Issue 37 (11): the HTML reports of fits and validations on sensor channels (a slide-only
record, a calibrated one, two channels) draw every channel in its own SI unit; they
crashed ("x, y, and format string must not be None") or labelled metres "rad"."""

import json
import re

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli import main
from crank_jax.records.sensors import Sensor

SLIDE = Sensor("x_s", "slide_mm", "mm", scale=-1.0, offset=0.2948)
WHEEL = Sensor("phi", "wheel_deg", "deg", scale=-1.0, offset=-3.083)


def _scene(sensors, c=1e-3):
    """A motor-driven crank with no spring, turning (as in test_sensors.py)."""
    mech = cj.SliderCrank(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.5, m_p=0.3, m_s=0.4, I_c=1e-3,
                          I_p=2e-3, k=0.0, c=c, g=9.81)
    return cj.Scene(mech, torque=cj.ConstantLoad(0.05), phi0=0.0, dphi0=10.0, t1=0.3,
                    sensors=tuple(sensors))


def _labels(html: str) -> list[str]:
    """The axis labels of the page's SVG figures (matplotlib writes each text as a
    comment beside its glyphs)."""
    return re.findall(r"<!-- ([^<>]*?\[[^\]]*\]) -->", html)


def _score_units(html: str) -> dict[str, str]:
    rows = re.findall(r'<tr data-name="([^"]+)"><th>[^<]*</th><td[^>]*>[^<]*</td><td>([^<]*)'
                      r"</td></tr>", html)
    return dict(rows)


@pytest.mark.parametrize("sensors", [
    (SLIDE,), pytest.param((WHEEL, SLIDE), marks=pytest.mark.slow)], ids=["slide", "two"])
def test_reports_draw_each_channel_in_its_unit(tmp_path, capsys, sensors):
    truth = _scene(sensors)
    noise = {"x_s": 2e-5, "phi": 1e-3}
    data = cj.synthesize(truth, rate=100, noise_std={s.name: noise[s.name] for s in sensors},
                         seed=1)
    rec, scene_path = tmp_path / "rec.csv", tmp_path / "start.toml"
    cj.save_data(data, rec)
    cj.save_scene(_scene(sensors, c=1.3e-3), scene_path)
    html, fitted = tmp_path / "fit.html", tmp_path / "fitted.toml"
    code = main(["fit", str(rec), str(scene_path), "--free", "c,phi0,dphi0", "--quiet",
                 "--shooting", "single", "--report", str(html), "--scene-out", str(fitted),
                 "--out", str(tmp_path / "f.json")])
    assert code == 0, capsys.readouterr().err
    assert json.loads((tmp_path / "f.json").read_text())["converged"]
    page = html.read_text()
    want = {"x_s [m]", "data - fit [m]"} | ({"phi [rad]", "data - fit [rad]"}
                                            if len(sensors) == 2 else set())
    assert set(_labels(page)) >= want and ("phi [rad]" in page) == (len(sensors) == 2)
    first_unit = "rad" if len(sensors) == 2 else "m"
    assert re.search(rf"rms residual</th>\s*<td[^>]*>[^<]* {first_unit}<", page), page[:3000]

    vhtml = tmp_path / "val.html"
    assert main(["validate", str(fitted), str(rec), "--init-window", "0.12", "--quiet",
                 "--out", str(tmp_path / "val.json"), "--report", str(vhtml)]) == 0
    page = vhtml.read_text()
    labels = set(_labels(page))
    assert {"x_s [m]", "data - prediction [m]"} <= labels
    assert ("phi [rad]" in labels) == (len(sensors) == 2)
    units = _score_units(page)
    assert units["rms error"] == first_unit and units["max |error|"] == first_unit
    if len(sensors) == 2:
        assert units["x_s: rms error"] == "m" and units["phi: rms error"] == "rad"
    assert np.isfinite(float(re.search(r"scores ([-\d.e+]+)%", page).group(1)))
