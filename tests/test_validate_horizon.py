"""k-step-ahead validation (`validate(..., horizon=T)`, `--horizon`) and parameters estimated
on the initial-state window (`init_free`, `--init-free`), on a rotating rig."""

import json

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli import main
from crank_jax.validation.horizon import cut

#: The held-out record's drive level, and the fitted scene's: 3% off.
TAU_TRUE, TAU_MODEL = 0.2575, 0.25
NOISE = 2e-3  # rad
REV = 0.25  # s, about one revolution at the record's 24 rad/s
RATE, N_SAMPLES = 50.0, 276  # Hz; the record's samples, 5.5 s from t = 0
OPEN_RMS, OPEN_MAX = 1.0, 2.5  # rad, the open-loop drift over the record


def _rig(tau0: float) -> cj.Scene:
    """A motor-driven offset slider-crank that turns (no spring), gravity on a tilted
    mount, crank friction; a constant drive torque `tau0`."""
    mech = cj.SliderCrank(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.1, m_p=0.05, m_s=0.1,
                          I_c=2e-3, I_p=2e-4, k=0.0, c=0.01, g=9.81, e=0.008, T_c=0.02,
                          w_c=0.05, gravity_angle=0.35)
    return cj.Scene(mech, torque=cj.ConstantLoad(tau0), phi0=0.0, dphi0=5.0, t1=6.0)


@pytest.fixture(scope="module")
def record():
    """The truth (drive 3% above the fitted scene's) and its held-out record: no torque
    column (its drive level is not measured), 5.5 s at 50 Hz from the start. Sampled
    from the truth's solve at the record's times, the program the open-loop validation
    of the same times runs too (one compile for both)."""
    truth = _rig(TAU_TRUE)
    ts = np.arange(N_SAMPLES) / RATE
    traj = truth.simulate(ts, outputs=())
    phi = np.asarray(traj.phi) + np.random.default_rng(3).normal(0.0, NOISE, N_SAMPLES)
    return truth, cj.Data(ts, phi, source="held-out")


@pytest.fixture(scope="module")
def rig(record):
    """The fitted scene (drive 3% low), the held-out record, and its open-loop and
    one-revolution validations. Compiled programs are most of this file's time: the
    record's solve (shared with the open-loop one), the initial-state fit, and one
    window prediction that every window's state fit and prediction share."""
    truth, data = record
    model = _rig(TAU_MODEL)
    kw = dict(scene_loads=True)
    return dict(truth=truth, model=model, data=data, span=float(data.ts[-1] - data.ts[0]),
                open=cj.validate(model, data, **kw),
                ahead=cj.validate(model, data, horizon=REV, **kw))


def test_one_revolution_ahead_is_small_where_open_loop_drifts_by_radians(rig):
    open_, ahead = rig["open"], rig["ahead"]
    # A drive 3% off: the open-loop prediction drifts by radians.
    assert open_.rms > OPEN_RMS and open_.max_abs > OPEN_MAX
    assert ahead.horizon == REV and len(ahead.windows) >= 8
    # One revolution ahead, each window (the first included) from its own first
    # samples, the model is good.
    assert ahead.rms < 0.06 and ahead.rms < open_.rms / 20
    assert max(w["rms"] for w in ahead.windows) < 0.06
    assert all(w["converged"] for w in ahead.windows)
    # The windows tile the record after the initial-state window; the scored samples
    # are the predicted ones, and the scores are recomputed from the returned arrays.
    ts = ahead.ts
    assert ahead.windows[0]["t_start"] == pytest.approx(ts[0] + ahead.init_window)
    for w in ahead.windows:  # a tenth of 0.25 s is ~1 sample at 50 Hz: the 5-sample minimum
        assert w["n_head"] == 5 and w["t_end"] <= w["t_start"] + REV
    assert ahead.n_samples == sum(w["n_predicted"] for w in ahead.windows)
    assert ahead.n_samples == int(ahead.scored.sum())
    e = (ahead.phi - ahead.predicted)[ahead.scored]
    assert ahead.rms == pytest.approx(float(np.sqrt(np.mean(e**2))), rel=1e-12)
    doc = ahead.to_json()
    assert doc["horizon"] == REV and len(doc["windows"]) == len(ahead.windows)
    assert "horizon" not in open_.to_json()  # without a horizon, val.json is as before


@pytest.mark.slow
def test_horizon_of_the_record_length_is_one_window_predicted_from_its_own_head(rig):
    model, data, open_ = rig["model"], rig["data"], rig["open"]
    whole = cj.validate(model, data, horizon=rig["span"], scene_loads=True)
    (w,) = whole.windows
    ts = whole.ts
    start = int(np.searchsorted(ts, w["t_start"], side="right"))
    # Its state comes from its own first samples: a tenth of the window (> 5 samples).
    head = int(np.searchsorted(ts, w["t_start"] + 0.1 * rig["span"], side="right")) - start
    assert head > 5 and w["n_head"] == head and w["converged"]
    assert np.array_equal(whole.scored, np.arange(ts.size) >= start + head)
    assert whole.n_samples == w["n_predicted"] == ts.size - start - head
    # Its prediction is the open-loop simulation from that state at its first sample (to
    # the solver's rounding: the window's solve saves at padded times too; another state
    # would be radians off).
    ref = model.simulate(ts[start:], phi0=w["phi0"], dphi0=w["dphi0"])
    np.testing.assert_allclose(whole.predicted[start:], np.asarray(ref.phi), rtol=1e-9)
    # That state is not the open-loop validation's (the initial-state window's, carried
    # over the window): its own head puts the first predicted samples closer to the data.
    k = slice(start + head, start + head + 5)
    own, carried = (np.mean(np.abs(v.predicted[k] - data.phi[k])) for v in (whole, open_))
    assert own < carried / 2


@pytest.mark.slow
def test_window_states_match_the_truth_and_a_perfect_model_predicts_to_the_noise(rig):
    # The windows from 1 s on, after the start-up (the default state window is now one
    # revolution, at least 30 samples: 0.58 s, inside the start-up, where 5-sample heads
    # give 2.2x the noise).
    val = cj.validate(rig["truth"], rig["data"], horizon=REV, init_window=1.0)
    assert val.rms < 2 * NOISE
    # Each window's state against the truth's own state at the window's first sample.
    starts = val.windows
    idx = [int(np.searchsorted(val.ts, w["t_start"], side="right")) for w in starts]
    ref = rig["truth"].simulate(np.concatenate([[0.0], val.ts[idx]]))
    got_phi = np.array([w["phi0"] for w in starts])
    got_dphi = np.array([w["dphi0"] for w in starts])
    assert np.max(np.abs(got_phi - np.asarray(ref.phi[1:]))) < 3 * NOISE
    assert np.max(np.abs(got_dphi - np.asarray(ref.dphi[1:]))) < 0.3


@pytest.mark.slow
def test_init_free_recovers_the_held_out_drive_level(rig, tmp_path, capsys):
    val = cj.validate(rig["model"], rig["data"], scene_loads=True, init_free=("tau0",))
    assert val.init_values["tau0"] == pytest.approx(TAU_TRUE, rel=5e-3)
    assert val.rms < 0.02  # open loop, now that the operating point is the record's
    # The command line: --horizon and --init-free, and val.json's horizon and windows.
    scene, csv, out = tmp_path / "rig.toml", tmp_path / "rec.csv", tmp_path / "val.json"
    cj.save_scene(rig["model"], scene)
    cj.save_data(rig["data"], csv)
    assert main(["validate", str(scene), str(csv), "--scene-loads", "--horizon", str(REV),
                 "--init-free", "tau0", "--out", str(out), "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert doc["init_free"]["tau0"] == pytest.approx(TAU_TRUE, rel=5e-3)
    assert doc["horizon"] == REV and doc["windows"][1]["n_head"] == 5
    assert doc["rms"] < 0.01
    assert "ahead" in capsys.readouterr().out


def test_cut_tiles_the_record_and_refuses_a_horizon_with_nothing_to_predict():
    ts = np.arange(0.0, 3.0, 0.02)
    ws = cut(ts, 1.0, 0.5)
    assert ws[0].start == int(np.searchsorted(ts, 1.0, side="right"))
    assert all(a.stop == b.start for a, b in zip(ws, ws[1:]))
    # Every window, the first included, estimates its state from its own first samples:
    # max(5 samples, a tenth of the window).
    assert ws[-1].stop == ts.size and all(w.head == 5 for w in ws)
    (w,) = cut(ts, 1.0, 2.0)  # the rest of the record: one window, a tenth is 10 samples
    assert (w.start, w.stop, w.head) == (51, ts.size, 10)
    with pytest.raises(ValueError, match=r"`horizon=` 0.09 s holds"):
        cut(ts, 1.0, 0.09)
    # A gap longer than the horizon right after the initial-state window: the first
    # window with samples starts after it, with its own head.
    gap = np.concatenate([np.arange(0.0, 1.0, 0.02), np.arange(1.6, 3.0, 0.02)])
    ws = cut(gap, 1.0, 0.5)
    assert ws[0].t_start == 1.5 and ws[0].head == 5 and ws[1].head == 5


@pytest.mark.parametrize("kw, needle", [
    (dict(horizon=0.0), r"`horizon=` must be a time > 0"),
    (dict(horizon=float("nan")), r"`horizon=` must be a time > 0"),
    (dict(init_free=("bogus",)), r"`init_free=` names 'bogus'"),
    (dict(init_free=("phi0",)), "always estimated"),
    (dict(init_free=("tau0",)), "supplies its torque as its 'tau' column"),
])
def test_bad_requests_name_the_argument(record, kw, needle):
    _, data = record
    # A record that carries its torque (the refusal of init_free tau0 needs one).
    rec = cj.Data(data.ts, data.phi, torque=cj.ConstantLoad(TAU_MODEL), source="with tau")
    with pytest.raises(ValueError, match=needle):
        cj.validate(_rig(TAU_MODEL), rec, **kw)


@pytest.mark.parametrize("extra, needle", [
    (["--horizon", "0"], "--horizon must be a time > 0"),
    (["--horizon", "inf"], "--horizon must be a time > 0"),
    (["--init-free", "tau0,bogus"], "--init-free names 'bogus'"),
    (["--init-free", "dphi0"], "--init-free names dphi0"),
])
def test_cli_bad_values_exit_2_and_write_nothing(record, tmp_path, capsys, extra, needle):
    out = tmp_path / "val.json"
    out.write_text("keep")
    csv = tmp_path / "rec.csv"
    cj.save_data(record[1], csv)
    rc = main(["validate", "pendulum", str(csv), "--out", str(out), "--quiet"] + extra)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and needle in err[0], err
    assert out.read_text() == "keep"
