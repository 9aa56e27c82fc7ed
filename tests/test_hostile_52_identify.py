"""Hostile inputs to the identification commands: a stuck posterior chain, verdicts that
contradict each other, unconverged fitted scenes, a horizon below the record's spacing,
the same record counted twice, `--per-record` on one record, the iteration count."""

import dataclasses
import json
import threading
import types

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli import main
from crank_jax.validation.horizon import cut


def _one_line(capsys, *needles) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for n in needles:
        assert n in err[0], err[0]
    return err[0]


def _csv(path, ts, phi):
    rows = "".join(f"{float(t)!r},{float(p)!r}\n" for t, p in zip(ts, phi))
    path.write_text("t,phi\n" + rows)
    return path


# --- a horizon below the record's spacing is refused at once, never a hang ------------------


def _cut_within(seconds, *args):
    """`cut(*args)` in a thread given `seconds`: the old window loop never returned."""
    out = {}

    def run():
        try:
            out["value"] = cut(*args)
        except Exception as e:  # noqa: BLE001 (handed to the test)
            out["error"] = e

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(seconds)
    assert not t.is_alive(), f"cut{args[1:]} did not return within {seconds} s"
    return out


@pytest.mark.parametrize("horizon", [1e-15, 1e-300, 0.019])
def test_a_horizon_under_two_sample_intervals_is_refused_at_once(horizon):
    ts = 1.0 + np.arange(0.0, 3.0, 0.01)  # times near 1 s: float spacing 2.2e-16 s
    out = _cut_within(5.0, ts, 1.5, horizon)
    e = out.get("error")
    assert isinstance(e, ValueError), out
    assert "`horizon=`" in str(e) and "--" not in str(e)
    assert "shorter than two sample intervals" in str(e)
    assert "at least 0.06 s" in str(e)


def test_a_long_gap_costs_a_few_empty_windows_not_one_per_horizon():
    # A record with a gap of 1e9 horizons (times exact in binary): the window loop jumps
    # over it to the window after the gap.
    dt = 1 / 128
    ts = np.concatenate([np.arange(0.0, 1.0, dt), 1.25e8 + dt + np.arange(0.0, 1.0, dt)])
    out = _cut_within(5.0, ts, 0.5, 0.125)
    ws = out["value"]
    assert ws[-1].stop == ts.size and ws[0].t_start == 0.5
    assert [w.t_start for w in ws if w.t_start > 1][:2] == [1.25e8, 1.25e8 + 0.125]
    assert all(a.start < b.start for a, b in zip(ws, ws[1:]))


def test_cli_validate_refuses_a_tiny_horizon_with_one_line(tmp_path, capsys):
    ts = np.arange(0.0, 2.0, 0.01)
    rec = _csv(tmp_path / "rec.csv", ts, 0.3 * np.cos(2 * np.pi * 1.3 * ts))
    out = tmp_path / "val.json"
    rc = main(["validate", "lab-rig", str(rec), "--horizon", "1e-15", "--out", str(out),
               "--quiet"])
    assert rc == 2
    _one_line(capsys, "--horizon", "shorter than two sample intervals")
    assert not out.exists()


# --- the same record twice counts twice: refused; --per-record on one record: refused ------


def _record(tmp_path, name="rec.csv"):
    ts = np.arange(0.0, 2.0, 0.02)
    return _csv(tmp_path / name, ts, 0.3 * np.cos(2 * np.pi * 1.3 * ts) * np.exp(-0.2 * ts))


def test_the_same_samples_twice_are_refused_by_the_api():
    ts = np.arange(0.0, 2.0, 0.02)
    d = cj.Data(ts, 0.3 * np.cos(8 * ts))
    copy = cj.Data(ts.copy(), 0.3 * np.cos(8 * ts), source="copy")
    for fn in (cj.fit, cj.posterior):
        with pytest.raises(ValueError, match=r"data: records 0 and 2 hold the same samples"):
            fn(cj.load_scene("lab-rig"), [d, cj.Data(ts, 0.2 * np.cos(8 * ts)), copy],
               free=("k",), progress=False)


@pytest.mark.parametrize("how", ["same", "dot", "link", "copy"])
@pytest.mark.parametrize("command", ["fit", "posterior"])
def test_cli_refuses_a_record_given_twice(tmp_path, capsys, how, command):
    rec = _record(tmp_path)
    other = {"same": rec, "dot": tmp_path / "." / "rec.csv",
             "link": tmp_path / "link.csv", "copy": tmp_path / "copy.csv"}[how]
    if how == "link":
        other.symlink_to(rec)
    if how == "copy":
        other.write_bytes(rec.read_bytes())
    out = tmp_path / "out.json"
    rc = main([command, str(rec), "lab-rig", "--more-data", str(other), "--free", "k",
               "--out", str(out), "--quiet"])
    assert rc == 2
    _one_line(capsys, "--more-data", "DATA", "given twice",
              "a copy of" if how == "copy" else "the same file as")
    assert not out.exists()


def test_per_record_with_one_record_is_refused(tmp_path, capsys):
    rec = _record(tmp_path)
    rc = main(["fit", str(rec), "lab-rig", "--free", "k,c", "--per-record", "k", "--quiet"])
    assert rc == 2
    _one_line(capsys, "--per-record k needs several records (--more-data)")
    with pytest.raises(ValueError, match="`per_record=` names k, but there is one record"):
        cj.fit(cj.load_scene("lab-rig"), cj.Data(np.arange(0.0, 2.0, 0.02),
                                                 np.zeros(100)), free=("k", "c"),
               per_record=("k",), progress=False)


# --- a budget spent over several tries: the words and fit.json count alike ------------------


def test_the_words_of_a_budget_spent_over_several_tries_give_every_tries_count():
    from crank_jax.identify.fit import _all_tries
    from crank_jax.identify.outcome import budget_spent, termination

    words = budget_spent(1)
    assert "after 1 iteration without" in words
    msg, term = _all_tries(words, termination("budget", words), 1, 8, 1)
    assert "8 iterations in all over the fit's tries (`max_steps=` 1 per try)" in msg
    assert term["words"] == msg
    # One try: its count is every try's, nothing to add.
    assert _all_tries(words, termination("budget", words), 1, 1, 1)[0] == words


def test_cli_max_steps_1_words_and_fit_json_count_alike(tmp_path, capsys):
    out = tmp_path / "fit.json"
    assert main(["fit", "--max-steps", "1", "--shooting", "auto", "--out", str(out),
                 "--quiet"]) == 0
    doc = json.loads(out.read_text())
    text = capsys.readouterr().out
    n = doc["iterations"]
    assert n > 1 and not doc["converged"]
    assert f"{n} iterations in all" in doc["termination"]["words"]
    assert f"{n} iterations in all" in text and f"after {n} iterations in" in text
    # The library's words name the argument; the command prints its option.
    assert "(`max_steps=` 1 per try)" in doc["termination"]["words"]
    assert "(--max-steps 1 per try)" in text and "max_steps" not in text


# --- a fit that did not converge writes no fitted scene unless asked, and marks it ----------


def _unconverged(scene, **values):
    return types.SimpleNamespace(values=dict(values), mech=scene.mech.replace(k=13.3),
                                 data=[cj.Data(np.arange(0.0, 1.0, 0.02), np.zeros(50))],
                                 converged=False, message="stopped after 3 iterations\n(x)")


def test_the_api_refuses_an_unconverged_fitted_scene_unless_asked_and_marks_it(tmp_path):
    from crank_jax.identify import fitted as ft

    scene = cj.load_scene("lab-rig")
    res = _unconverged(scene, k=13.3, dphi0=33.0)
    path = tmp_path / "fitted.toml"
    for call in (lambda: ft.fitted_scene(scene, res),
                 lambda: ft.save_fitted_scene(scene, res, path)):
        with pytest.raises(ValueError, match=r"did not converge \(stopped after 3 "
                                             r"iterations \(x\)\).*pass anyway=True"):
            call()
    assert not path.exists()
    ft.save_fitted_scene(scene, res, path, anyway=True)
    text = path.read_text()
    assert text.startswith("# NOT CONVERGED")
    assert ft.fit_mark(path) == {"converged": False, "message": "stopped after 3 "
                                                               "iterations (x)"}
    back = cj.load_scene(path)  # still a scene: the mark is a table load_scene allows
    assert float(back.mech.k) == 13.3 and float(back.dphi0) == 33.0
    assert ft.fit_mark("lab-rig") is None
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("converged = false", 'converged = "no"'))
    with pytest.raises(cj.SceneError, match=r"\[fit\] must hold converged = true or false"):
        ft.fit_mark(bad)


def test_validate_refuses_a_scene_marked_unconverged_unless_asked(tmp_path, capsys):
    from crank_jax.identify.fitted import save_fitted_scene

    scene = cj.load_scene("lab-rig")
    marked = tmp_path / "fitted.toml"
    save_fitted_scene(scene, _unconverged(scene, k=13.3), marked, anyway=True)
    rec = _record(tmp_path)
    out = tmp_path / "val.json"
    rc = main(["validate", str(marked), str(rec), "--out", str(out), "--quiet"])
    assert rc == 2
    _one_line(capsys, "did not converge", "--allow-unconverged")
    assert not out.exists()


def test_cli_fit_that_did_not_converge_writes_no_scene_unless_asked(tmp_path, capsys):
    scene = cj.load_scene("lab-rig")
    rec = tmp_path / "rec.csv"
    cj.save_data(cj.synthesize(scene, t1=1.0, rate=50.0, noise_std=1e-3, seed=1), rec)
    start = tmp_path / "start.toml"
    cj.save_scene(dataclasses.replace(scene, mech=scene.mech.replace(k=4.0)), start)
    fitted, out = tmp_path / "fitted.toml", tmp_path / "fit.json"
    argv = ["fit", str(rec), str(start), "--free", "k", "--shooting", "single",
            "--max-steps", "1", "--scene-out", str(fitted), "--out", str(out), "--quiet"]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert "not written: the fit did not converge" in err[-1]
    assert "--scene-out-anyway" in err[-1] and not fitted.exists()
    assert json.loads(out.read_text())["converged"] is False  # the report is written
    assert main(argv + ["--scene-out-anyway"]) == 0
    assert "marked NOT converged" in capsys.readouterr().err
    assert fitted.read_text().startswith("# NOT CONVERGED")
    val = tmp_path / "val.json"
    assert main(["validate", str(fitted), str(rec), "--out", str(val), "--quiet",
                 "--allow-unconverged"]) == 0
    doc = json.loads(val.read_text())
    assert "did not converge" in doc["warnings"][0]


def test_scene_out_anyway_needs_scene_out(tmp_path, capsys):
    rc = main(["fit", str(_record(tmp_path)), "lab-rig", "--scene-out-anyway", "--quiet"])
    assert rc == 2
    _one_line(capsys, "--scene-out-anyway needs --scene-out")


# --- a stuck posterior chain is never reported as certainty ---------------------------------


def test_a_chain_that_never_moves_is_found():
    from crank_jax.bayes.posterior import MIN_MOVED, moved_fraction

    rng = np.random.default_rng(0)
    w = rng.normal(size=(3, 40, 2))
    w[1] = w[1, :1]  # chain 1 repeats its start
    w[2, 1::2] = w[2, ::2][:20]  # chain 2 repeats every other draw
    moved = moved_fraction(w)
    assert moved[0] == 1.0 and moved[1] == 0.0 and moved[1] < MIN_MOVED
    assert moved[2] == pytest.approx(19 / 39)
    assert moved_fraction(w[:, :1]).tolist() == [1.0, 1.0, 1.0]  # one draw: nothing to judge


def _post(stuck=(0,), chains=1):
    from crank_jax.bayes.posterior import Posterior, sampler_warnings

    moved = np.array([0.0 if i in stuck else 1.0 for i in range(chains)])
    draws = {"k": np.full((chains, 30), 2.0)}
    fit = types.SimpleNamespace(values={"k": 2.0}, stderr={"k": 0.1}, ci95={"k": (1.8, 2.2)})
    return Posterior(names=("k",), draws=draws, rhat={"k": float("nan")},
                     ess={"k": float("nan")}, divergences=0, chains=chains, n_draws=30,
                     warmup=20, step_size=np.full(chains, 0.2), mean_tree_steps=1.0,
                     gradient_evaluations=100, seconds=1.0, fit=fit, priors={},
                     moved=moved, stuck=tuple(stuck),
                     warnings=sampler_warnings(moved, np.full(chains, 0.2), chains, 30))


def test_a_stuck_posterior_is_marked_and_one_chain_says_no_rhat():
    post = _post()
    doc = post.to_json()
    assert doc["reliable"] is False and doc["stuck_chains"] == [0]
    assert doc["moved_fraction"] == [0.0]
    assert doc["warnings"][0].startswith("UNRELIABLE: chain(s) 0 moved in only 0% of their "
                                         "30 draws")
    assert "one chain: R-hat cannot be computed" in doc["warnings"][1]
    ok = _post(stuck=(), chains=2).to_json()
    assert ok["reliable"] is True and ok["warnings"] == []


def test_cli_posterior_with_a_stuck_chain_exits_1_and_marks_the_json(tmp_path, capsys,
                                                                     monkeypatch):
    import crank_jax.bayes.posterior as ps

    monkeypatch.setattr(ps, "posterior", lambda *a, **k: _post())
    out, plot = tmp_path / "post.json", tmp_path / "corner.png"
    rc = main(["posterior", str(_record(tmp_path)), "lab-rig", "--free", "k", "--chains",
               "1", "--out", str(out), "--plot", str(plot), "--quiet"])
    assert rc == 1
    err = capsys.readouterr().err
    assert "crank-jax: warning: UNRELIABLE: chain(s) 0" in err
    assert "R-hat cannot be computed" in err
    assert "error: the posterior is unreliable: chain(s) 0 never moved" in err
    assert json.loads(out.read_text())["reliable"] is False and not plot.exists()


def test_a_chain_stuck_after_a_short_warmup_is_sampled_again_with_a_smaller_step():
    # One chain, 20 warm-up steps: the adapted step (3.3 in whitened coordinates) was
    # rejected at every draw, and the posterior reported sd = 0 with no warning.
    from crank_jax.bayes.posterior import MIN_MOVED

    scene = cj.load_scene("lab-rig")
    data = cj.synthesize(scene, t1=1.5, rate=100, noise_std=2e-3, seed=3)
    post = cj.posterior(scene, data, ("k", "c"), draws=30, chains=1, warmup=20, seed=1,
                        progress=False)
    assert "sampled again with it cut by 4" in post.warnings[0]
    assert post.reliable and post.moved[0] >= MIN_MOVED
    for n, s in post.summary().items():
        assert 0.3 * post.fit.stderr[n] < s["sd"] < 3 * post.fit.stderr[n]


# --- a refusal's words agree with its numbers ------------------------------------------------


def test_no_motion_words_agree_with_the_numbers_on_a_short_record():
    # "no motion above its noise (spread 0.319 rad, noise 0.000576 rad)" read as a
    # contradiction: on a few samples pure noise can reach 7760 times its level.
    from crank_jax.identify.strategy import no_motion

    ts = np.arange(10) / 50
    msg = no_motion(0.3 * np.sin(3 * ts) + 0.1, 0.000576)
    assert "that 10 samples can tell" in msg and "is 85.8 times its noise level" in msg
    assert "pure noise of 10 samples reaches 7.76e+03 times one time in 10000" in msg
    assert "constant" in no_motion(np.full(10, 0.3), 0.0)


# --- verdicts agree: a channel's reported noise level is its residuals' when converged -------


def test_superseded_notes_no_longer_say_none_converged_alone():
    from crank_jax.identify.reweight import superseded

    notes = ["the single shooting fit did not converge; tried x; the result is y (rms 1 rad, "
             "the lowest-cost try: none converged)", "none of the 3 starts converged; z",
             "other"]
    notes = list(superseded(tuple(notes)))
    assert all("the refit from that try converged" in n for n in notes[:2])
    assert notes[2] == "other"


def test_a_converged_fit_reports_each_channels_residual_level(monkeypatch):
    # A slide channel with a slow misfit (1e-3 m, 50x its noise): its level from the
    # record is the noise's, its residuals' is the misfit's. With the refits stopped
    # before the levels settled (none here), the report gave the stale level and the
    # uncertainty weighted by it.
    import crank_jax.identify.reweight as rw
    from crank_jax.records.sensors import Sensor

    monkeypatch.setattr(rw, "REWEIGHT_ROUNDS", 0)
    scene = dataclasses.replace(cj.load_scene("lab-rig"),
                                sensors=(Sensor("phi"), Sensor("x_s")), t1=1.5)
    rec = cj.synthesize(scene, rate=100, noise_std={"phi": 1e-3, "x_s": 2e-5}, seed=2)
    ts, ys = np.asarray(rec.ts), {n: np.asarray(y) for n, y in rec.outputs_items()}
    ys["x_s"] = ys["x_s"] + 1e-3 * np.sin(2 * np.pi * 0.4 * ts)
    data = cj.Data(ts, None, channels=ys, sensors=scene.sensors)
    res = cj.fit(scene, data, free=("k", "phi0", "dphi0"), progress=False, warn=False)
    assert res.converged
    for name, c in res.channels.items():
        assert 1 / 1.25 < c["sigma"] / c["rms"] < 1.25, (name, c)
    assert any("had not settled" in w for w in res.warnings)
