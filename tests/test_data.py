"""Data files, validation, and the synthetic-data noise model."""

import math

import numpy as np
import pytest

import crank_jax as cj


def _write(tmp_path, text, name="d.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _rows(n=8, dt=0.1, t0=0.0):
    return "".join(f"{t0 + i * dt:.3f},{math.sin(i):.6f}\n" for i in range(n))


def test_load_csv_with_comments_and_offset_start(tmp_path):
    p = _write(tmp_path, "# logged by rig 3\n% matlab style\n\nt,phi\n" + _rows(t0=12.5))
    d = cj.load_data(p)
    assert d.n == 8 and d.ts[0] == pytest.approx(12.5)
    assert d.load is None and d.torque is None
    np.testing.assert_allclose(d.phi, np.sin(np.arange(8)), atol=1e-6)


def test_load_whitespace_degrees_and_renamed_columns(tmp_path):
    body = "".join(f"{i * 0.01}  {10.0 * i}  7\n" for i in range(6))
    p = _write(tmp_path, "# comment\ntime  angle  other\n" + body, "d.txt")
    d = cj.load_data(p, t_col="time", phi_col="angle", angle_unit="deg")
    np.testing.assert_allclose(d.phi, np.deg2rad(10.0 * np.arange(6)))


def test_load_columns_become_sampled_loads(tmp_path):
    body = "".join(f"{i * 0.1},{0.01 * i},{i},{-i}\n" for i in range(6))
    d = cj.load_data(_write(tmp_path, "t,phi,P,tau\n" + body))
    assert isinstance(d.load, cj.SampledLoad) and isinstance(d.torque, cj.SampledLoad)
    assert float(d.load(0.25)) == pytest.approx(2.5)
    assert float(d.torque(0.25)) == pytest.approx(-2.5)


@pytest.mark.parametrize(
    "text, kwargs, match",
    [
        ("t,phi\n0,1\n0.1,nan\n0.2,1\n0.3,1\n0.4,1\n", {}, r"line 3: column 'phi' is nan"),
        ("t,phi\n0,1\n0.1,1\n0.1,1\n0.3,1\n0.4,1\n", {}, r"line 4: time t = 0\.1 does not"),
        ("t,phi\n0,1\n0.2,1\n0.1,1\n0.3,1\n0.4,1\n", {}, r"line 4: time t = 0\.1 does not"),
        ("t,phi\n0,1\n0.1,1\n0.2,1\n", {}, r"too few samples \(3\)"),
        ("time,phi\n0,1\n0.1,1\n", {}, r"missing column 't'.*`t_col=`"),
        ("t,angle\n0,1\n0.1,1\n", {}, r"missing column 'phi'.*`phi_col=`"),
        ("t,phi\n0,1\n0.1,x\n", {}, r"line 3: column 'phi': 'x' is not a number"),
        ("t,phi\n0,1\n0.1\n", {}, r"line 3: 1 values but the header has 2"),
        ("t,phi,tau\n0,1,2\n0.1,1,inf\n", {}, r"line 3: column 'tau' is inf"),
        ("# only a comment\n", {}, r"no header"),
        ("t,phi\n" + _rows(), {"angle_unit": "grad"}, r"angle unit"),
    ],
)
def test_each_validation_error(tmp_path, text, kwargs, match):
    with pytest.raises(cj.DataError, match=match):
        cj.load_data(_write(tmp_path, text), **kwargs)


def test_data_arrays_are_validated():
    t = np.linspace(0, 1, 10)
    with pytest.raises(cj.DataError, match="sample 3"):
        cj.Data(t, np.where(np.arange(10) == 3, np.nan, 0.0))
    with pytest.raises(cj.DataError, match="sample 5"):
        cj.Data(np.where(np.arange(10) == 5, 0.0, t), np.zeros(10))
    with pytest.raises(cj.DataError, match="equal length"):
        cj.Data(t, np.zeros(9))


def test_missing_file_is_oserror(tmp_path):
    with pytest.raises(OSError):
        cj.load_data(tmp_path / "nope.csv")


def test_synthesize_noise_model(lab_rig, tmp_path):
    exact = cj.synthesize(lab_rig, t1=1.0, rate=100.0)
    assert exact.n == 101 and exact.ts[0] == 0.0
    np.testing.assert_allclose(exact.phi, np.asarray(lab_rig.simulate(exact.ts).phi), atol=1e-9)
    # Quantisation: every angle a multiple of 2 pi / N.
    q = cj.synthesize(lab_rig, t1=1.0, rate=100.0, quantization=1000)
    steps = q.phi / (2 * np.pi / 1000)
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)
    assert np.max(np.abs(q.phi - exact.phi)) <= np.pi / 1000 + 1e-12
    # Gaussian noise: the right size, reproducible by seed.
    a = cj.synthesize(lab_rig, t1=1.0, rate=100.0, noise_std=0.01, seed=3)
    b = cj.synthesize(lab_rig, t1=1.0, rate=100.0, noise_std=0.01, seed=3)
    np.testing.assert_array_equal(a.phi, b.phi)
    assert 0.007 < np.std(a.phi - exact.phi) < 0.013
    # Late start, dropped samples: irregular nominal times on the 100 Hz grid.
    late = cj.synthesize(lab_rig, t1=1.0, rate=100.0, t_start=0.3, drop=0.3, seed=1)
    assert late.ts[0] == pytest.approx(0.3) and late.n < 71
    np.testing.assert_allclose(late.ts * 100, np.round(late.ts * 100), atol=1e-6)
    np.testing.assert_allclose(late.phi, np.asarray(lab_rig.simulate(
        np.concatenate([[0.0], late.ts])).phi)[1:], atol=1e-9)
    # Jitter: logged at nominal times, sampled elsewhere.
    jit = cj.synthesize(lab_rig, t1=1.0, rate=100.0, jitter_std=1e-3, seed=2)
    np.testing.assert_array_equal(jit.ts, exact.ts)
    assert 0 < np.max(np.abs(jit.phi - exact.phi)) < 0.2
    with pytest.raises(ValueError, match="rate"):
        cj.synthesize(lab_rig, rate=-1.0)


def test_save_load_roundtrip_with_torque(lab_rig, tmp_path):
    scene = cj.Scene(lab_rig.mech, torque=cj.HarmonicLoad(0.0, 0.2, 3.0))
    d = cj.synthesize(scene, t1=0.5, rate=50.0, noise_std=1e-3)
    p = tmp_path / "x.csv"
    cj.save_data(d, p, comment="test")
    back = cj.load_data(p)
    np.testing.assert_array_equal(back.ts, d.ts)
    np.testing.assert_array_equal(back.phi, d.phi)
    np.testing.assert_allclose(np.asarray(back.torque(d.ts)), np.asarray(d.torque(d.ts)),
                               atol=1e-12)
    assert back.load is None


def test_multisine_load():
    ld = cj.MultiSineLoad([1.0, 0.5], [1.0, 3.0], [0.0, 0.5], X0=0.2)
    t = np.array([0.1, 0.2])
    want = 0.2 + np.sin(2 * np.pi * t) + 0.5 * np.sin(2 * np.pi * 3 * t + 0.5)
    np.testing.assert_allclose(np.asarray(ld(t)), want)
    assert float(ld.mean()) == pytest.approx(0.2)
