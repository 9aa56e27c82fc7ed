"""Following a running machine: the extended Kalman filter on state and parameters, its
bands, its change alarms, its chunks and batches, and the `track` command."""

import dataclasses
import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.model.sampled import SampledLoad
from crank_jax.online import prepare, run_filter, track
from crank_jax.online import runner as runner_module

jax.config.update("jax_enable_x64", True)

LAB = cj.load_scene("lab-rig")
RATE = 200.0


def driven_record(T: float, t_change: float | None = None, drop: float = 0.05, seed: int = 0,
                  noise: float = 1e-3, name: str = "k", phi0: float = 0.3) -> cj.Data:
    """The lab rig driven by a measured two-tone torque, `name` dropping by `drop` at
    `t_change` s (None: no change), logged at 200 Hz with `noise` rad of noise."""
    tt = np.arange(0.0, T + 1.0, 1 / RATE)
    tau = 0.15 * np.sin(2 * np.pi * 3.1 * tt) + 0.1 * np.sin(2 * np.pi * 5.3 * tt + 1.0)
    torque = SampledLoad(tt, tau)
    ts = np.arange(0.0, T, 1 / RATE)
    kw = dict(torque=torque, rtol=1e-11, atol=1e-12)
    if t_change is None:
        phi = np.asarray(cj.simulate(LAB.mech, phi0, 0.0, ts, **kw).phi)
    else:
        a, later = ts[ts < t_change], ts[ts >= t_change]
        tr = cj.simulate(LAB.mech, phi0, 0.0, np.append(a, t_change), **kw)
        after = LAB.mech.replace(**{name: getattr(LAB.mech, name) * (1 - drop)})
        b = np.concatenate([[t_change], later[later > t_change]])
        tr2 = cj.simulate(after, float(tr.phi[-1]), float(tr.dphi[-1]), b, **kw)
        # (The solve from the change starts at t_change, a sample or not.)
        phi = np.concatenate([np.asarray(tr.phi)[:-1],
                              np.asarray(tr2.phi)[b.size - later.size:]])
    phi = phi + np.random.default_rng(seed).normal(0.0, noise, phi.shape)
    return cj.Data(ts, phi, torque=SampledLoad(ts, tau[:ts.size]), source=f"seed {seed}")


def _truth(res, t_change, drop=0.05):
    t = res.t
    return np.where(t < t_change, 2.0, 2.0 * (1 - drop)) if t_change else np.full(t.size, 2.0)


def test_a_stiffness_drop_is_alarmed_and_followed_and_no_change_is_quiet():
    # 20 s records, k 5% down at 10 s; the filter started 10% off (the scene's values).
    start = dataclasses.replace(LAB, mech=LAB.mech.replace(k=2.2, c=0.003))
    quiet = track(start, driven_record(20.0), free=("k", "c"), start="scene", progress=False)
    assert quiet.alarms == [], quiet.summary()
    truth = _truth(quiet, None)
    lo, hi = quiet.band("k")
    settled = quiet.t > 5.0
    cover = np.mean((lo <= truth) & (truth <= hi) & settled) / np.mean(settled)
    assert cover >= 0.85, cover
    assert abs(quiet.values["k"][-1] / 2.0 - 1) < 5e-3

    res = track(start, driven_record(20.0, 10.0), free=("k", "c"), start="scene",
                progress=False)
    assert len(res.alarms) == 1, res.summary()
    a = res.alarms[0]
    assert 10.0 <= a["t"] <= 13.0 and a["parameters"] == ["k"], a
    assert a["before"]["k"] == pytest.approx(2.0, rel=5e-3)
    assert a["after"]["k"] == pytest.approx(1.9, rel=5e-3)
    i = np.searchsorted(res.t, 19.0)
    assert abs(res.values["k"][i] / 1.9 - 1) < 5e-3
    lo, hi = res.band("k")
    assert lo[i] <= 1.9 <= hi[i]
    doc = res.to_json()
    assert set(doc) >= {"t", "values", "stderr", "alarms", "settings"}
    assert doc["alarms"][0]["parameters"] == ["k"] and len(doc["t"]) == res.t.size


def test_chunks_and_thinning_give_the_plain_path(monkeypatch):
    data = driven_record(6.0, seed=3)
    whole = track(LAB, data, free=("k",), start="scene", progress=False)
    monkeypatch.setattr(runner_module, "CHUNK", 500)
    chunked = track(LAB, data, free=("k",), start="scene", progress=False, every=3)
    np.testing.assert_allclose(chunked.values["k"], whole.values["k"][::3], rtol=1e-12)
    np.testing.assert_allclose(chunked.stderr["k"], whole.stderr["k"][::3], rtol=1e-9)
    np.testing.assert_array_equal(chunked.t, whole.t[::3])


def test_a_fleet_is_one_vmap_and_equals_its_members():
    # The filter's program is a pure function of its records: `jax.vmap` runs a fleet,
    # each machine from its own first state.
    probs = [prepare(LAB, driven_record(4.0, seed=s, phi0=0.2 + 0.1 * s), free=("k",),
                     start="scene", progress=False) for s in range(3)]
    p0 = probs[0]
    ts = jnp.asarray(p0.ts)
    ok = jnp.ones(ts.shape, bool)
    states = jax.tree.map(lambda *a: jnp.stack(a), *[p.state for p in probs])
    ys = jnp.stack([jnp.asarray(p.ys) for p in probs])
    _, batch = jax.jit(jax.vmap(lambda st, y: run_filter(p0.model, p0.settings, st, ts, y,
                                                         ok)))(states, ys)
    for i, p in enumerate(probs):
        _, one = run_filter(p0.model, p0.settings, p.state, ts, jnp.asarray(p.ys), ok)
        np.testing.assert_allclose(batch.x[i], one.x, rtol=1e-10, atol=1e-12)
    assert len({float(p.state.x[0]) for p in probs}) == 3


def test_requests_it_cannot_serve_name_the_argument():
    data = driven_record(2.0)
    for kw, word in ((dict(free=("tau0",)), "`free=`"), (dict(free=()), "`free=`"),
                     (dict(start="middle"), "`start=`"), (dict(settle=0.0), "`settle=`"),
                     (dict(change_ratio=1.0), "`change_ratio=`"), (dict(every=0), "`every=`"),
                     (dict(false_alarm_rate=float("nan")), "`false_alarm_rate=`"),
                     (dict(load_by="angle"), "`load_by='angle'` needs a crank turning one way"),
                     (dict(load_by="sideways"), "load_by")):
        with pytest.raises(ValueError, match=word):
            track(LAB, data, progress=False, **{"free": ("k",), **kw})


def _csv(path, data):
    tau = np.asarray(data.torque(jnp.asarray(data.ts)))
    np.savetxt(path, np.column_stack([data.ts, data.phi, tau]), delimiter=",",
               header="t,phi,tau", comments="")


def _command(tmp_path, seconds: float):
    """A record of `seconds` s as CSV, and the `track` command line on it."""
    rec = tmp_path / "rec.csv"
    _csv(rec, driven_record(seconds))
    out = tmp_path / "track.json"
    return out, [sys.executable, "-m", "crank_jax", "track", str(rec), "lab-rig", "--free",
                 "k,c", "--start", "scene", "--out", str(out), "--quiet"]


def test_the_track_command_writes_its_json_and_report(tmp_path):
    out, cmd = _command(tmp_path, 3.0)
    p = subprocess.run(cmd, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    doc = json.loads(out.read_text())
    assert set(doc["values"]) == {"k", "c"} and doc["alarms"] == []
    assert doc["settings"]["false_alarm_rate_per_hour"] == 1.0
    report = tmp_path / "track.html"
    p = subprocess.run(cmd + ["--report", str(report)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert "Changes" in report.read_text() and "<svg" in report.read_text()


def test_the_track_command_refuses_bad_options_in_its_own_words(tmp_path):
    out, cmd = _command(tmp_path, 1.0)
    for bad, word in ((["--change-ratio", "1"], "--change-ratio"),
                      (["--free", "tau0"], "--free")):
        p = subprocess.run(cmd + bad, capture_output=True, text=True)
        assert p.returncode == 2 and word in p.stderr and "Traceback" not in p.stderr, p.stderr
        assert "free=" not in p.stderr
    assert not out.exists()
