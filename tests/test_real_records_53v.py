"""Real records III, verdicts and validation: profiles that keep the estimate's sign and
find the 95% crossing, an identifiability verdict on the parameters' own scale, `validate`
taking loads as `fit` does with a state window from the record, and the per-sample
predictions in fit.json / val.json / `--predictions CSV`."""

import csv
import json
import math

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli import main
from crank_jax.identify.uncertainty import analyze

TAU, I_C = -0.25, 2e-3  # N m (driving the crank backwards), kg m^2
NOISE = 2e-3  # rad
RATE, N = 50.0, 150  # Hz, samples: 3 s, about 10 turns


def _rig(tau0: float = TAU, I_c: float = I_C, dphi0: float = -20.0) -> cj.Scene:
    """A motor-driven offset slider-crank that turns (no spring) under a constant torque
    `tau0`, gravity on a tilted mount, crank friction."""
    mech = cj.SliderCrank(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.1, m_p=0.05, m_s=0.1,
                          I_c=I_c, I_p=2e-4, k=0.0, c=0.01, g=9.81, e=0.008, T_c=0.02,
                          w_c=0.05, gravity_angle=0.35)
    return cj.Scene(mech, torque=cj.ConstantLoad(tau0), phi0=0.0, dphi0=dphi0, t1=6.0)


def _phi(scene: cj.Scene, ts) -> np.ndarray:
    return np.asarray(scene.simulate(ts, outputs=()).phi)


@pytest.fixture(scope="module")
def record():
    """The truth's record: angle only (no torque column), 2 mrad noise."""
    ts = np.arange(N) / RATE
    phi = _phi(_rig(), ts) + np.random.default_rng(3).normal(0.0, NOISE, N)
    return cj.Data(ts, phi, source="driven.csv")


@pytest.mark.full
def test_verdict_is_judged_on_the_parameters_own_scale():
    # The sensitivities of a driven rotating rig's angle to tau0 (linear, z = tau0 / ref)
    # and ln I_c: both determined to well under 1%. With tau0 started near 0 its ref is
    # tiny (1e-6 N m), and in units of it the old verdict found the combination
    # "tau0 - ln I_c" with a standard error of thousands: "identifiable: NO".
    ts = np.arange(N) / RATE
    base = _phi(_rig(), ts)
    cols = []
    for tau0, I_c in ((TAU * (1 + 1e-6), I_C), (TAU, I_C * (1 + 1e-6))):
        cols.append((_phi(_rig(tau0, I_c), ts) - base) / 1e-6)  # per relative change
    # dphi/dz: z = tau0 / ref (linear) and z = ln I_c.
    d_tau, d_lnI = cols[0] / TAU, cols[1]
    r = np.random.default_rng(0).normal(0.0, NOISE, N)
    values = np.array([TAU, I_C])
    verdicts = []
    for ref in (1e-6, 1e-3, 0.25):
        J = np.column_stack([d_tau * ref, d_lnI])
        unc = analyze(J, r, N, ("tau0", "I_c"), values, [False, True], np.array([ref, 1.0]))
        verdicts.append(unc)
        assert unc.identifiable and not unc.directions and unc.candidates == ()
        rel = unc.stderr / np.abs(values)
        assert np.all(rel < 0.01), rel
    # The same data, the same errors, whatever the coordinate's made-up scale.
    for unc in verdicts[1:]:
        np.testing.assert_allclose(unc.stderr, verdicts[0].stderr, rtol=1e-6)
        np.testing.assert_allclose(unc.ci95, verdicts[0].ci95, rtol=1e-6)


@pytest.mark.full
def test_profile_keeps_the_sign_and_finds_the_crossing(record, monkeypatch, tmp_path,
                                                        capsys):
    # `crank-jax fit --profile tau0` of a drive torque of -0.25 N m started at -1e-6 N m
    # (its coordinate's scale, 1e-6, is far below the interval's half-width, 1e-5). The
    # profile printed +0.25: its values dropped the sign of a signed coordinate. Without
    # a standard error (a fit that did not converge, or a parameter in a weak direction),
    # its grid was +-0.5 in the coordinate, +-5e-7 N m here: no crossing, no interval.
    from crank_jax.identify import fit as fit_module
    from crank_jax.identify.profile import CHI2_95, profile_likelihood

    seen = {}

    def keep(problem, z_hat, j, se_z, *rest):
        seen.update(problem=problem, z_hat=z_hat, j=j, rest=rest)
        return profile_likelihood(problem, z_hat, j, se_z, *rest)

    monkeypatch.setattr(fit_module, "profile_likelihood", keep)
    scene, data = tmp_path / "start.toml", tmp_path / "rec.csv"
    cj.save_scene(_rig(tau0=-1e-6, I_c=1.5e-3), scene)
    cj.save_data(record, data)
    out, pred = tmp_path / "fit.json", tmp_path / "fit.csv"
    assert main(["fit", str(data), str(scene), "--free", "tau0,I_c,phi0,dphi0", "--profile",
                 "tau0", "--out", str(out), "--predictions", str(pred), "--quiet"]) == 0
    printed = capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert doc["converged"] and doc["identifiable"]
    tau = doc["estimates"]["tau0"]
    est, (h_lo, h_hi) = tau["value"], tau["ci95"]
    assert est == pytest.approx(TAU, rel=1e-3)
    values, dev = np.array(tau["profile"]["values"]), np.array(tau["profile"]["deviance"])
    assert np.all(values < 0) and np.all(np.diff(values) > 0)
    lo, hi = tau["profile"]["ci95"]
    assert lo is not None and hi is not None and lo < est < hi
    assert f"profile-likelihood 95% interval of tau0: [{lo:.6g}, {hi:.6g}]" in printed
    # A quadratic cost: the profile's interval is the Hessian's.
    assert lo == pytest.approx(h_lo, abs=0.05 * (h_hi - h_lo))
    assert hi == pytest.approx(h_hi, abs=0.05 * (h_hi - h_lo))
    assert not any("disagree" in w for w in doc["warnings"])
    assert dev[0] > CHI2_95 and dev[-1] > CHI2_95  # it passes the threshold both sides
    # No standard error: the walk from 1% of |tau0| still brackets and refines it.
    blind = profile_likelihood(seen["problem"], seen["z_hat"], seen["j"], math.nan,
                               *seen["rest"])
    assert np.all(blind.values < 0)
    assert blind.ci95[0] == pytest.approx(lo, abs=0.05 * (hi - lo))
    assert blind.ci95[1] == pytest.approx(hi, abs=0.05 * (hi - lo))
    # fit.json and --predictions carry each sample's prediction beside its measurement.
    (p,) = doc["predictions"]
    assert p["source"].endswith("rec.csv") and p["t"] == pytest.approx(list(record.ts), abs=1e-12)
    e = np.array(p["phi"]["predicted"]) - np.array(p["phi"]["measured"])
    assert np.array(p["phi"]["measured"]) == pytest.approx(record.phi, abs=1e-12)
    assert float(np.sqrt(np.mean(e**2))) == pytest.approx(doc["rms_residual"], rel=1e-9)
    with open(pred, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["phi_predicted"]) for r in rows] == pytest.approx(p["phi"]["predicted"],
                                                                       rel=1e-15)
    assert {r["record"] for r in rows} == {"0"}


def _revolution(data: cj.Data) -> float:
    """The record's mean time per revolution, s."""
    return 2 * math.pi * float(data.ts[-1] - data.ts[0]) / abs(float(data.phi[-1] - data.phi[0]))


@pytest.mark.full
def test_validate_takes_the_scenes_torque_as_fit_does_and_one_revolution(tmp_path):
    # The record has no tau column; `fit` takes the scene's constant torque, and
    # `validate` refused it ("the record has no 'tau' column ... --scene-loads"). Its
    # default state window was the scene's "period", 1 s with no spring (over 3
    # revolutions here, and longer than a short record); it is now one revolution at
    # the record's own mean speed (55 samples at 200 Hz).
    ts = np.arange(300) / 200.0
    phi = _phi(_rig(), ts) + np.random.default_rng(4).normal(0.0, NOISE, ts.size)
    record = cj.Data(ts, phi, source="dense.csv")
    val = cj.validate(_rig(), record)
    assert val.init_window == pytest.approx(_revolution(record), rel=1e-9)
    assert val.rms < 3 * NOISE and val.fit_percent > 99.0 and val.warnings == []
    # The CLI, without --scene-loads: the same numbers, and the per-sample predictions.
    scene, csv_in = tmp_path / "rig.toml", tmp_path / "rec.csv"
    cj.save_scene(_rig(), scene)
    cj.save_data(record, csv_in)
    out, pred = tmp_path / "val.json", tmp_path / "val.csv"
    assert main(["validate", str(scene), str(csv_in), "--out", str(out), "--predictions",
                 str(pred), "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert doc["init_window"] == pytest.approx(val.init_window, rel=1e-9)
    assert doc["rms"] == pytest.approx(val.rms, rel=1e-6)
    p = doc["predictions"]
    assert p["t"] == pytest.approx(list(record.ts), abs=1e-12)
    assert p["phi"]["measured"] == pytest.approx(list(record.phi), abs=1e-12)
    e = (np.array(p["phi"]["measured"]) - np.array(p["phi"]["predicted"]))[p["scored"]]
    assert float(np.sqrt(np.mean(e**2))) == pytest.approx(doc["rms"], rel=1e-9)
    with open(pred, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == record.n and list(rows[0]) == ["record", "t", "phi_measured",
                                                       "phi_predicted"]
    assert [float(r["phi_predicted"]) for r in rows] == pytest.approx(p["phi"]["predicted"],
                                                                       rel=1e-15)


def test_default_state_window_is_never_longer_than_the_record():
    # A crank that turns slowly and less than a revolution, no spring and no gravity: no
    # period and no revolution, so the old rule's 1 s, past the end of this 0.6 s record
    # ("init_window takes 31 of the window's 31 samples"). At most half the record now.
    from crank_jax.validation.state_window import record_init_window

    mech = cj.SliderCrank(r=0.05, L=0.2, b=0.1, s=0.0, m_c=0.1, m_p=0.05, m_s=0.1,
                          I_c=2e-3, I_p=2e-4, k=0.0, c=0.0, g=0.0)
    scene = cj.Scene(mech, phi0=0.0, dphi0=1.0, t1=1.0)
    ts = np.arange(31) / 50.0
    data = cj.Data(ts, ts * 1.0, source="slow.csv")  # 0.6 rad in 0.6 s
    assert record_init_window(scene, data) == pytest.approx(0.3)
    # One revolution of the driven rig at 50 Hz is 14 samples, too few for a state fit
    # to tell the motion from its noise: the window takes 30 samples.
    fast = cj.Data(np.arange(N) / RATE, -22.8 * np.arange(N) / RATE, source="fast")
    assert _revolution(fast) < 14 / RATE
    assert record_init_window(_rig(), fast) == pytest.approx(29 / RATE)
    # A spring rig keeps its linearised period while the record is long enough.
    lab = cj.load_scene("lab-rig")
    period = 2 * math.pi / float(cj.linearize(lab.mech).omega_n)
    long = cj.Data(np.arange(2000) / 500.0, 0.1 * np.sin(np.arange(2000) / 500.0 * 28.0),
                   source="swing.csv")
    assert record_init_window(lab, long) == pytest.approx(period)


@pytest.mark.parametrize("command", ["fit", "validate"])
def test_predictions_csv_must_be_its_own_file(tmp_path, capsys, command):
    scene, data = tmp_path / "rig.toml", tmp_path / "rec.csv"
    cj.save_scene(_rig(), scene)
    ts = np.arange(20) / RATE
    cj.save_data(cj.Data(ts, -20.0 * ts), data)
    out = tmp_path / "out.json"
    args = [str(data), str(scene)] if command == "fit" else [str(scene), str(data)]
    for pred in (out, tmp_path / "." / "out.json", data):
        rc = main([command, *args, "--out", str(out), "--predictions", str(pred), "--quiet"])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and "--predictions" in err[0], err
    assert not out.exists()
