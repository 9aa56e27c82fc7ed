"""Monte Carlo sweeps: distributions, agreement with single simulations, per-sample status,
static structure, chunking and order, the CLI."""

import json

import equinox as eqx
import numpy as np
import pytest

import crank_jax as cj
from crank_jax import cli
from crank_jax.sweep.distributions import (
    DRAW_BLOCK,
    Const,
    LogNormal,
    LogUniform,
    Normal,
    Uniform,
    draw,
    parse_distribution,
)

SHORT = dict(t1=0.5, num_saves=51)


# --- distributions ----------------------------------------------------------------------

@pytest.mark.parametrize("text, expected", [
    ("normal(2.0,0.1)", Normal(2.0, 0.1)),
    (" uniform( 0.005 , 0.02 )", Uniform(0.005, 0.02)),
    ("lognormal(2,0.5)", LogNormal(2.0, 0.5)),
    ("loguniform(1e-2,1e7)", LogUniform(1e-2, 1e7)),
    ("const(3)", Const(3.0)),
    ("4.5", Const(4.5)),
])
def test_parse_distribution(text, expected):
    assert parse_distribution(text) == expected


@pytest.mark.parametrize("text, words", [
    ("normal(2.0", "cannot read"), ("gauss(1,2)", "cannot read"),
    ("normal(1)", "takes 2"), ("normal(1,-1)", "sd >= 0"), ("uniform(2,1)", "lo <= hi"),
    ("lognormal(0,1)", "median > 0"), ("normal(a,b)", "must be numbers"),
    ("const(inf)", "finite"),
])
def test_parse_distribution_errors(text, words):
    with pytest.raises(ValueError, match=words):
        parse_distribution(text)


def test_draw_is_seeded_and_per_field():
    a = draw({"k": Normal(2, 0.1)}, n=1000, seed=7)
    b = draw({"c": Uniform(0, 1), "k": Normal(2, 0.1)}, n=1000, seed=7)
    c = draw({"k": Normal(2, 0.1)}, n=1000, seed=8)
    # Adding a field leaves the others' samples unchanged; another seed changes them.
    np.testing.assert_array_equal(a["k"], b["k"])
    assert not np.allclose(a["k"], c["k"])
    assert abs(a["k"].mean() - 2) < 4 * 0.1 / np.sqrt(1000)
    assert abs(a["k"].std() - 0.1) < 0.01
    lu = draw({"k": LogUniform(1e-2, 1e7)}, n=2000)["k"]
    assert lu.min() >= 1e-2 and lu.max() < 1e7 and np.median(np.log10(lu)) == pytest.approx(
        2.5, abs=0.3)
    assert np.all(draw({"m": LogNormal(2, 1)}, n=100)["m"] > 0)


def test_draw_explicit_arrays_and_errors():
    out = draw({"k": np.array([1.0, 2.0]), "c": 0.5})
    np.testing.assert_array_equal(out["c"], [0.5, 0.5])
    with pytest.raises(ValueError, match="different lengths"):
        draw({"k": np.ones(2), "c": np.ones(3)})
    with pytest.raises(ValueError, match="number of samples"):
        draw({"k": Normal(1, 1)})


def test_draw_any_range_alone_matches_the_whole():
    spec = {"k": Normal(2, 0.1), "c": "loguniform(1e-3,1)", "L": np.arange(DRAW_BLOCK + 90.0)}
    n = DRAW_BLOCK + 90
    whole = draw(spec, n=n, seed=4)
    for start, stop in ((0, 10), (DRAW_BLOCK - 50, DRAW_BLOCK + 70), (n - 1, n)):
        part = draw(spec, n=n, seed=4, start=start, stop=stop)
        for k in spec:
            np.testing.assert_array_equal(part[k], whole[k][start:stop])
    # The first samples do not depend on how many are drawn.
    np.testing.assert_array_equal(draw({"k": Normal(2, 0.1)}, n=10, seed=4)["k"],
                                  whole["k"][:10])
    with pytest.raises(ValueError, match="start < stop"):
        draw(spec, n=n, start=5, stop=5)


# --- agreement with simulate ------------------------------------------------------------

def test_sweep_matches_individual_simulations(lab_rig):
    ks = np.array([2.5, 1.5, 40.0, 2.0, 0.3])
    c = np.array([0.01, 0.02, 0.005, 0.0, 0.01])
    outs = ("peak_phi", "peak_dphi", "final_phi", "final_energy", "peak_O", "phi")
    r = cj.run_sweep(lab_rig, {"k": ks, "c": c, "phi0": 0.5}, outs, chunk_size=2, **SHORT)
    assert r.n == 5 and np.all(r.ok) and r.seed == -1
    # "auto" goes through the solver policy: the fused solver on a sweep's uniform saves.
    assert {cj.solve.SOLVERS[i] for i in r.solver} == {"dopri8-uniform"}
    for i in range(5):
        mech = lab_rig.mech.replace(k=ks[i], c=c[i])
        tr = cj.simulate(mech, 0.5, 0.0, r.ts, solver=cj.solve.SOLVERS[r.solver[i]],
                         outputs=("reactions",))
        np.testing.assert_allclose(r.outputs["phi"][i], tr.phi, rtol=1e-10, atol=1e-12)
        assert r.outputs["peak_phi"][i] == pytest.approx(np.abs(tr.phi).max(), rel=1e-12)
        assert r.outputs["final_phi"][i] == pytest.approx(float(tr.phi[-1]), rel=1e-10)
        e = cj.model.energy(mech, tr.phi[-1], tr.dphi[-1])
        assert r.outputs["final_energy"][i] == pytest.approx(float(e), rel=1e-10)
        peak_O = np.hypot(tr.extras["O_x"], tr.extras["O_y"]).max()
        assert r.outputs["peak_O"][i] == pytest.approx(float(peak_O), rel=1e-9)
        assert r.num_steps[i] == int(tr.num_steps)


def test_order_chunking_and_sorting_do_not_change_results(lab_rig):
    spec = {"k": "loguniform(0.5,500)", "c": "uniform(0.0,0.05)", "dphi0": "normal(0,1)"}
    a = cj.run_sweep(lab_rig, spec, ("peak_phi", "settling_time"), n=7, seed=3, chunk_size=3,
                 **SHORT)
    b = cj.run_sweep(lab_rig, spec, ("peak_phi", "settling_time"), n=7, seed=3, chunk_size=8,
                 sort=False, **SHORT)
    np.testing.assert_array_equal(a.samples["k"], b.samples["k"])
    np.testing.assert_allclose(a.outputs["peak_phi"], b.outputs["peak_phi"], rtol=1e-9)
    np.testing.assert_allclose(a.outputs["settling_time"], b.outputs["settling_time"])


def test_dominant_frequency_matches_linearisation(lab_rig):
    # Small amplitude, light damping: the spectrum peaks at the linear natural frequency.
    ks = np.array([5.0, 20.0])
    r = cj.run_sweep(lab_rig, {"k": ks, "phi0": 1e-3}, ("dominant_freq",), t1=4.0, num_saves=801)
    fn = [float(cj.linearize(lab_rig.mech.replace(k=k)).omega_n) / (2 * np.pi) for k in ks]
    np.testing.assert_allclose(r.outputs["dominant_freq"], fn, rtol=0.02)


# --- per-sample status, no NaN ----------------------------------------------------------

def test_invalid_and_failed_samples_are_marked_and_the_rest_kept(lab_rig):
    L = np.array([0.2, 0.04, 0.2, np.nan, 0.2])      # 0.04 < r = 0.05: invalid
    k = np.array([2.0, 2.0, 2e6, 2.0, 3.0])          # 2e6: needs far more than 3000 steps
    r = cj.run_sweep(lab_rig, {"L": L, "k": k}, ("peak_phi", "phi"), solver="tsit5",
                 max_steps=3000, **SHORT)
    names = [cj.sweep.STATUS[s] for s in r.status]
    assert names == ["ok", "invalid", "max_steps", "invalid", "ok"]
    for v in r.outputs.values():
        assert np.all(np.isfinite(v))
    assert np.all(r.outputs["peak_phi"][~r.ok] == 0)
    assert r.counts() == {"ok": 2, "invalid": 2, "max_steps": 1, "failed": 0, "nonfinite": 0}
    ok = cj.run_sweep(lab_rig, {"k": k[[0, 4]]}, ("peak_phi",), solver="tsit5", **SHORT)
    np.testing.assert_allclose(r.outputs["peak_phi"][[0, 4]], ok.outputs["peak_phi"])
    s = r.summary()
    assert s["peak_phi"]["max"] == pytest.approx(r.outputs["peak_phi"][r.ok].max())


def test_bad_arguments(lab_rig):
    with pytest.raises(ValueError, match="cannot vary 'q'"):
        cj.run_sweep(lab_rig, {"q": 1.0}, n=2)
    with pytest.raises(ValueError, match="unknown sweep output"):
        cj.run_sweep(lab_rig, {"k": 1.0}, ("peak_q",), n=2)
    with pytest.raises(ValueError, match="unknown solver"):
        cj.run_sweep(lab_rig, {"k": 1.0}, n=2, solver="euler")


def test_a_result_too_large_is_refused_before_any_work(lab_rig, tmp_path, capsys):
    with pytest.raises(ValueError, match=r"n = 100000000000 samples need .* GiB .* give `n=` <="):
        cj.run_sweep(lab_rig, {"k": "normal(2,0.1)"}, n=10**11, chunk_size=8)
    with pytest.raises(ValueError, match="limit is 0.0 GiB"):
        cj.run_sweep(lab_rig, {"k": "normal(2,0.1)"}, ("phi",), n=1000, max_memory=10_000)
    argv = ["sweep", "lab-rig", "--vary", "k=normal(2,0.1)", "--n", "100000000000",
            "--chunk-size", "8", "--out", str(tmp_path / "x.npz"), "--quiet"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "GiB" in err and err.count("\n") == 1


# --- every load kind --------------------------------------------------------------------

def test_every_load_kind_sweeps_or_is_refused_by_name(lab_rig):
    ms = cj.MultiSineLoad([0.04, 0.03], [1.3, 2.9], [0.0, 1.0], X0=0.01)
    scene = cj.Scene(lab_rig.mech, torque=ms, phi0=0.5, t1=0.5, samples=51, solver="tsit5")
    r = cj.run_sweep(scene, {"k": np.array([2.0, 3.0]), "tau0": np.array([0.0, 0.02])},
                 ("final_phi",))
    assert np.all(r.ok)
    tr = cj.simulate(scene.mech.replace(k=3.0), 0.5, 0.0, r.ts, solver="tsit5",
                     torque=cj.MultiSineLoad(ms.amplitudes, ms.freqs_hz, ms.phases, 0.02))
    assert r.outputs["final_phi"][1] == pytest.approx(float(tr.phi[-1]), rel=1e-9)
    with pytest.raises(ValueError, match=r"MultiSineLoad .* no tau1; its parameters are"):
        cj.run_sweep(scene, {"tau1": "normal(0.1,0.01)"}, n=2)
    sampled = cj.SampledLoad(np.linspace(0, 0.5, 26), 0.03 * np.sin(np.arange(26.0)))
    scene = eqx.tree_at(lambda s: s.torque, scene, sampled)
    r = cj.run_sweep(scene, {"k": np.array([2.0])}, ("final_phi",))
    tr = cj.simulate(scene.mech, 0.5, 0.0, r.ts, torque=sampled, solver="tsit5")
    assert r.ok[0] and r.outputs["final_phi"][0] == pytest.approx(float(tr.phi[-1]), rel=1e-9)
    with pytest.raises(ValueError, match="SampledLoad .* no tau0"):
        cj.run_sweep(scene, {"tau0": 1.0}, n=2)
    # A harmonic load has no gain (only an input load has): refused, not promoted to a
    # tone of zero amplitude (issue 37 item 4).
    tone = cj.HarmonicLoad(0.01, 0.03, 1.3, 0.0)
    scene = eqx.tree_at(lambda s: s.torque, scene, tone)
    with pytest.raises(ValueError, match=r"cannot vary 'tau_gain': .* HarmonicLoad .* "
                                         r"its parameters are \['tau0', 'tau1'"):
        cj.run_sweep(scene, {"tau_gain": 1.0, "tau1": 0.02}, n=2)


# --- static structure -------------------------------------------------------------------

def test_structure_is_the_union_of_scene_and_samples(lab_rig):
    scene = cj.Scene(lab_rig.mech.replace(c=0.0, m_s=0.0), phi0=0.3, t1=0.5, samples=11)
    assert not scene.structure.damper and not scene.structure.slider
    r0 = cj.run_sweep(scene, {"k": "normal(2,0.1)", "c": "const(0)"}, n=2)
    assert not r0.structure.damper and not r0.structure.slider
    r1 = cj.run_sweep(scene, {"c": "uniform(0,0.01)", "m_s": np.array([0.0, 0.2])}, n=2)
    assert r1.structure.damper and r1.structure.slider


def test_unused_outputs_bodies_and_loads_cost_nothing(lab_rig):
    spec = {"k": "normal(2,0.1)"}
    base = cj.sweep_cost(lab_rig, spec, ("peak_phi",), num_saves=11)
    # A load varied at constant zero compiles exactly the program without it. (A mean:
    # an amplitude without a frequency has no effect, and is refused.)
    assert cj.sweep_cost(lab_rig, {**spec, "P0": "const(0)"}, ("peak_phi",),
                         num_saves=11) == base
    with_load = cj.sweep_cost(lab_rig, {**spec, "P0": "normal(1,0.1)"}, ("peak_phi",),
                              num_saves=11)
    assert with_load["flops"] > base["flops"]
    with_O = cj.sweep_cost(lab_rig, spec, ("peak_phi", "peak_O"), num_saves=11)
    assert with_O["flops"] > 2 * base["flops"]
    pend = cj.load_scene("pendulum")
    lean = cj.sweep_cost(pend, {"c": "uniform(0,1e-3)"}, ("peak_phi",), num_saves=11)
    full = cj.sweep_cost(pend, {"c": "uniform(0,1e-3)"}, ("peak_phi",), num_saves=11,
                         structure=cj.model.ModelTerms())
    assert lean["transcendentals"] < full["transcendentals"]
    assert lean["hlo_lines"] < full["hlo_lines"]


def test_varied_load_amplitude_switches_the_load_on(lab_rig):
    scene = cj.Scene(lab_rig.mech, phi0=0.0, t1=0.5, samples=51)
    r = cj.run_sweep(scene, {"tau1": np.array([0.0, 0.05]), "tau_freq_hz": 4.0}, ("peak_phi",))
    assert r.outputs["peak_phi"][0] == 0.0 and r.outputs["peak_phi"][1] > 1e-3
    tr = cj.simulate(scene.mech, 0.0, 0.0, r.ts, torque=cj.HarmonicLoad(0.0, 0.05, 4.0))
    assert r.outputs["peak_phi"][1] == pytest.approx(float(np.abs(tr.phi).max()), rel=1e-8)


# --- CLI --------------------------------------------------------------------------------

def test_cli_sweep_writes_npz_and_summary(tmp_path, capsys):
    out = tmp_path / "s.npz"
    rc = cli.main(["sweep", "lab-rig", "--vary", "k=normal(2.0,0.1)", "--vary",
                   "c=uniform(0.005,0.02)", "--n", "6", "--t1", "0.5", "--samples", "21",
                   "--out", str(out), "--summary", "--quiet", "--outputs",
                   "peak_phi,final_energy"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["status"]["ok"] == 6
    with np.load(out) as z:
        assert z["sample.k"].shape == (6,) and z["output.final_energy"].shape == (6,)
        np.testing.assert_array_equal(z["sample.k"], draw({"k": Normal(2.0, 0.1)}, 6)["k"])
        assert summary["outputs"]["peak_phi"]["max"] == pytest.approx(
            z["output.peak_phi"].max())


@pytest.mark.parametrize("args, words", [
    (["--vary", "k"], "expected NAME=DIST"),
    (["--vary", "q=normal(1,1)"], "cannot vary 'q'"),
    # issue 37 item 4: a parameter no load of the scene has nor can be given was dropped,
    # giving the nominal scene's outputs with exit 0
    (["--vary", "tau_gain=const(1)"], "cannot vary 'tau_gain': the scene's torque is a "
                                      "NoLoad"),
    (["--vary", "P_gain=const(0)"], "cannot vary 'P_gain'"),
    (["--vary", "k=normal(1"], "cannot read"),
    (["--vary", "k=1", "--vary", "k=2"], "given twice"),
    (["--outputs", "peak_q"], "unknown output"),
    (["--n", "0"], "--n must be"),
])
def test_cli_sweep_user_errors(tmp_path, capsys, args, words):
    argv = ["sweep", "lab-rig", "--n", "2", "--out", str(tmp_path / "x.npz"), "--quiet"]
    assert cli.main(argv + args) == 2
    err = capsys.readouterr().err
    assert words in err and err.count("\n") == 1


def test_cli_sweep_never_overwrites_its_input(tmp_path, capsys, lab_rig):
    scene = tmp_path / "scene.npz"
    cj.save_scene(lab_rig, scene)
    before = scene.read_bytes()
    assert cli.main(["sweep", str(scene), "--n", "2", "--out", str(scene), "--quiet"]) == 2
    assert "input file" in capsys.readouterr().err
    assert scene.read_bytes() == before


# --- memory bounded by the save times, errors inside JAX -------------------------------

@pytest.mark.parametrize("samples", ["100000000", "1000000000", "1000000000000"])
def test_cli_sweep_refuses_save_times_beyond_memory_at_once(tmp_path, capsys, samples):
    # issue 24, 6: n = 2 with --samples 10^8 used 5.8 GB before RESOURCE_EXHAUSTED, 10^9
    # ran into the memory limit. The working memory of a chunk is refused up front, before
    # even the save times are made, naming the option and the largest that fits.
    argv = ["sweep", "lab-rig", "--vary", "k=normal(2,0.1)", "--n", "2", "--samples",
            samples, "--outputs", "peak_phi,peak_O", "--out", str(tmp_path / "x.npz"),
            "--quiet"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "GiB of working memory" in err and "give --samples <=" in err
    assert not (tmp_path / "x.npz").exists()


def test_the_working_memory_bound_is_the_chunk_not_n(lab_rig):
    from crank_jax.sweep.plan import chunk_bytes

    per_save = chunk_bytes(1, ("peak_phi",), 1)
    assert per_save > 0
    # the bound grows with the save times and the chunk, and peak_O's extra outputs
    assert chunk_bytes(4, ("peak_phi",), 10) == 40 * per_save
    assert chunk_bytes(1, ("peak_O",), 1) > per_save
    with pytest.raises(ValueError,
                       match=r"limit is .* \(max_memory\); give `num_saves=` <= 1000,"):
        cj.run_sweep(lab_rig, {"k": "normal(2,0.1)"}, ("peak_phi",), n=100, chunk_size=10,
                 num_saves=1001, max_memory=per_save * 10 * 1000 + per_save)
    # a smaller chunk fits the same save times
    cj.run_sweep(lab_rig, {"k": "normal(2,0.1)"}, ("peak_phi",), n=2, chunk_size=2, t1=0.2,
             num_saves=1001, max_memory=per_save * 10 * 1000 + per_save)


def test_a_value_error_inside_jax_is_an_internal_error_not_a_user_mistake(monkeypatch,
                                                                           capsys):
    # issue 24, 2: a sharding failure inside JAX was reported as the user's mistake (exit 2)
    import importlib

    import jax.numpy as jnp

    cli_main = importlib.import_module("crank_jax.cli.main")

    def run(args):
        jnp.linspace(0.0, 1.0, -1)  # raises ValueError inside jax

    name, help_, add, _ = cli_main.sweep.COMMANDS[0]
    monkeypatch.setattr(cli_main.sweep, "COMMANDS", [(name, help_, add, run)])
    assert cli.main(["sweep", "lab-rig", "--n", "2", "--out", "x.npz"]) == 1
    err = capsys.readouterr().err
    assert "internal error: ValueError" in err and "please report" in err
    assert err.count("\n") == 1
