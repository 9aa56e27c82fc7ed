"""Validation on a second record (crank_jax.validation.kstep), Data.window and synthetic
transients."""

import math

import numpy as np
import pytest

import crank_jax as cj


@pytest.fixture(scope="module")
def shaken():
    """The lab rig under a known harmonic crank torque, 3 s at 200 Hz."""
    base = cj.load_scene("lab-rig")
    return cj.Scene(base.mech, torque=cj.HarmonicLoad(0.0, 0.2, 3.0), phi0=0.5, dphi0=0.0,
                    rtol=base.rtol, atol=base.atol, t1=3.0)


def test_perfect_model_predicts_the_record(shaken):
    data = cj.synthesize(shaken, rate=200.0, t_start=0.4)
    val = cj.validate(shaken, data, init_window=0.25)
    # Independent truth: the scene's own state at the record's first sample.
    truth = shaken.simulate(np.array([0.0, 0.4]))
    assert val.phi0 == pytest.approx(float(truth.phi[-1]), abs=1e-7)
    assert val.dphi0 == pytest.approx(float(truth.dphi[-1]), abs=1e-5)
    assert val.n_samples == int(np.sum(data.ts > 0.4 + 0.25))
    assert val.rms < 1e-6 and val.max_abs < 5e-6
    assert val.fit_percent > 99.99
    # The scores are what their definitions say, recomputed from the returned arrays.
    e = (val.phi - val.predicted)[val.scored]
    y = val.phi[val.scored]
    assert val.rms == pytest.approx(math.sqrt(np.mean(e**2)), rel=1e-12)
    assert val.fit_percent == pytest.approx(
        100 * (1 - np.linalg.norm(e) / np.linalg.norm(y - y.mean())), rel=1e-12)
    doc = val.to_json()
    for key in ("rms", "max_abs", "fit_percent", "n_samples", "phi0", "dphi0"):
        assert key in doc


@pytest.mark.slow
def test_wrong_model_scores_worse_and_window_is_used(shaken):
    data = cj.synthesize(shaken, rate=200.0, noise_std=1e-3, seed=3)
    wrong = cj.Scene(shaken.mech.replace(k=2.1), torque=shaken.torque, t1=3.0)
    good = cj.validate(shaken, data, t_start=0.5, t_end=2.5, init_window=0.25)
    bad = cj.validate(wrong, data, t_start=0.5, t_end=2.5, init_window=0.25)
    assert good.ts[0] >= 0.5 and good.ts[-1] <= 2.5
    assert good.rms == pytest.approx(1e-3, rel=0.15)  # the noise, nothing else
    assert bad.rms > 5 * good.rms
    assert bad.fit_percent < good.fit_percent - 5


@pytest.mark.slow
def test_transient_hurts_until_trimmed(shaken):
    data = cj.synthesize(shaken, rate=200.0, noise_std=1e-4, transient=0.05, seed=1)
    raw = cj.validate(shaken, data, t_start=0.0, init_window=0.25)
    trimmed = cj.validate(shaken, data, t_start=0.6, init_window=0.25)
    assert raw.rms > 5 * trimmed.rms
    assert trimmed.rms < 3e-4


def test_bad_requests_name_the_argument(shaken):
    data = cj.synthesize(shaken, rate=200.0)
    with pytest.raises(ValueError, match="window"):
        cj.validate(shaken, data, t_start=2.99)
    with pytest.raises(ValueError, match="init_window"):
        cj.validate(shaken, data, t_start=2.8, init_window=0.18)
    with pytest.raises(ValueError, match="init_window"):
        cj.validate(shaken, data, init_window=-1.0)
    bare = cj.Data(data.ts, data.phi, source="bare.csv")
    with pytest.raises(ValueError, match="bare.csv: the record has no 'tau' column"):
        cj.validate(shaken, bare, scene_loads=False)


def test_scene_loads_fill_a_missing_column(shaken):
    data = cj.synthesize(shaken, rate=200.0, t_start=0.4)
    bare = cj.Data(data.ts, data.phi, source="bare.csv")
    val = cj.validate(shaken, bare, init_window=0.25, scene_loads=True)
    assert val.rms < 1e-6


def test_default_init_window_is_a_period(shaken):
    lin = cj.linearize(shaken.mech)
    assert cj.validate.__module__ == "crank_jax.validation.kstep"
    from crank_jax.validation.kstep import default_init_window

    assert default_init_window(shaken) == pytest.approx(2 * math.pi / float(lin.omega_n))


def test_data_window():
    ts = np.linspace(0.0, 1.0, 11)
    d = cj.Data(ts, np.sin(ts), torque=cj.ConstantLoad(2.0), source="rec")
    w = d.window(0.25, 0.75)
    assert np.array_equal(w.ts, ts[3:8]) and np.array_equal(w.phi, np.sin(ts[3:8]))
    assert w.torque is d.torque and w.source == "rec"
    assert d.window().n == 11 and d.window(t_end=0.4).n == 5
    with pytest.raises(cj.DataError, match="rec: the window .* holds 4 samples"):
        d.window(0.65)
    with pytest.raises(cj.DataError, match="t_start must be below t_end"):
        d.window(0.5, 0.5)


def test_synthesize_transient_is_the_documented_term(shaken):
    kw = dict(rate=100.0, t1=1.0, t_start=0.05, noise_std=1e-3, seed=4)
    plain = cj.synthesize(shaken, **kw)
    messy = cj.synthesize(shaken, transient=0.03, transient_time=0.2, transient_hz=12.0, **kw)
    t = plain.ts
    want = 0.03 * np.exp(-t / 0.2) * np.cos(2 * np.pi * 12.0 * t)
    assert np.allclose(messy.phi - plain.phi, want, atol=1e-14)
    for name, bad in (("transient_time", 0.0), ("transient_hz", -1.0), ("transient", np.nan)):
        with pytest.raises(ValueError, match=name):
            cj.synthesize(shaken, **{name: bad})
