"""The Bayesian posterior (NUTS): priors, a smoke run against the Laplace intervals, and
the CLI's bad input."""

import json

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.bayes.priors import load_priors, parse_priors
from crank_jax.cli.main import main


@pytest.mark.parametrize("spec, match", [
    ({"k": "gamma(1, 2)"}, "cannot read distribution"),
    ({"k": "normal(2, 0.5)"}, "puts mass below 0"),
    ({"m_s": "uniform(-1, 1)"}, "puts mass below 0"),
    ({"k": "const(2)"}, "is not a prior"),
    ({"k": "lognormal(2, 0)"}, "zero width"),
    ({"I_p": "lognormal(1e-3, 0.5)"}, "not a free parameter"),
])
def test_bad_priors_name_the_parameter(spec, match):
    with pytest.raises(ValueError, match=match):
        parse_priors(spec, ("k", "c", "m_s", "phi0"))


def test_priors_parse_and_signed_parameters_take_normal(tmp_path):
    d = parse_priors({"k": "lognormal(2, 0.5)", "phi0": "normal(1, 0.1)",
                      "c": "loguniform(1e-4, 1)"}, ("k", "c", "phi0[0]", "phi0[1]"))
    assert str(d["k"]) == "lognormal(2,0.5)" and set(d) == {"k", "phi0", "c"}
    scene = tmp_path / "s.toml"
    text = cj.scene_to_toml(cj.load_scene("lab-rig")) + '\n[priors]\nk = "lognormal(2, 0.5)"\n'
    scene.write_text(text)
    assert load_priors(scene) == {"k": "lognormal(2, 0.5)"}
    cj.load_scene(scene)  # the scene itself loads with a [priors] table


@pytest.fixture(scope="module")
def short_record():
    scene = cj.load_scene("lab-rig")
    return scene, cj.synthesize(scene, t1=1.5, rate=100, noise_std=2e-3, seed=3)


def test_posterior_matches_laplace_where_well_conditioned(short_record):
    """k and c from a clean free decay: the posterior is nearly Gaussian, so its mean and
    sd agree with the fit and its Laplace standard errors (a likelihood off by a factor,
    e.g. sigma counted twice, would make the sd wrong by >= 40%)."""
    scene, data = short_record
    post = cj.posterior(scene, data, ("k", "c"), draws=200, chains=2, warmup=150, seed=1,
                        progress=False)
    assert post.draws["k"].shape == (2, 200)
    s = post.summary()
    for n in ("k", "c"):
        se = post.fit.stderr[n]
        assert abs(s[n]["mean"] - post.fit.values[n]) < 0.3 * se
        assert s[n]["sd"] == pytest.approx(se, rel=0.25)
        assert s[n]["q2.5"] < post.fit.values[n] < s[n]["q97.5"]
        assert s[n]["rhat"] < 1.05 and s[n]["ess_bulk"] > 50
    assert post.divergences == 0


def test_chains_one_after_another_match_the_vmapped_chains(short_record):
    """On the CPU the chains run one after another in the program (`lax.map`, nuts.py's
    `_batched`); the same keys give the same transitions as vmapped chains, to rounding."""
    import jax
    import jax.numpy as jnp

    from crank_jax.bayes import nuts
    from crank_jax.bayes.posterior import _laplace_z, _problem_at
    from crank_jax.bayes.priors import prior_arrays
    from crank_jax.identify.request import normalize

    scene, data = short_record
    free = ("k", "c")
    req = normalize(scene, data, free, init="scene", method="lm", shooting="auto",
                    segments=None, multistart=1, seed=0, max_steps=None, tol=1e-8,
                    sigma=None, profile=None, window=None, progress=False, warn=False)
    res = cj.fit(scene, data, free, progress=False, warn=False)
    problem, z = _problem_at(req, res)
    codes, params = prior_arrays(problem.names, {}, problem.log)
    L = np.linalg.cholesky(_laplace_z(problem, z, codes, params))
    carry = nuts.initial_carry(problem, codes, params, z, L, 2, jax.random.PRNGKey(0))
    stages = jnp.asarray(nuts.schedule(60)[:nuts.CHUNK])  # warm-up: adapting, too
    keys = jax.random.split(jax.random.PRNGKey(1), 2 * nuts.CHUNK).reshape(2, nuts.CHUNK, -1)
    args = (problem, codes, params, jnp.asarray(z), jnp.asarray(L), carry, keys, stages)
    _, x_map, _, s_map = nuts._chunk_program(*args, False)
    _, x_vmap, _, s_vmap = nuts._chunk_program(*args, True)
    # Every transition's tree is the same; the draws agree to rounding at first, and
    # that rounding then grows from transition to transition (the leapfrog integrator
    # amplifies it: 2e-6 at the third draw, 5e-3 at the twentieth in one install), so
    # only the first two draws are compared to rounding.
    np.testing.assert_array_equal(np.asarray(s_map), np.asarray(s_vmap))
    np.testing.assert_allclose(np.asarray(x_map)[:, :2], np.asarray(x_vmap)[:, :2], rtol=0,
                               atol=1e-6)


@pytest.mark.slow  # a second sampling run: ~1 min on a quiet 2-core machine
def test_prior_pulls_the_posterior(short_record):
    """A tight prior on k away from the data's value moves k's posterior towards it."""
    scene, data = short_record
    res = cj.fit(scene, data, ("k", "c"), progress=False, warn=False)
    se = res.stderr["k"]
    prior = {"k": f"lognormal({res.values['k'] + 4 * se}, {se / res.values['k']})"}
    post = cj.posterior(scene, data, ("k", "c"), prior, draws=100, chains=2, warmup=100,
                        seed=2, progress=False)
    # Data and prior equally precise: the posterior mean sits half way, sd / sqrt(2).
    k = post.summary()["k"]
    assert k["mean"] == pytest.approx(res.values["k"] + 2 * se, abs=0.6 * se)


@pytest.mark.parametrize("extra, prior, match", [
    (["--draws", "0"], None, "--draws must be >= 1"),
    (["--chains", "0"], None, "--chains must be >= 1"),
    ([], 'k = "gamma(1, 2)"', "cannot read distribution"),
    ([], 'm_s = "lognormal(0.4, 0.2)"', "not a free parameter"),
    ([], 'c = "normal(0.002, 0.001)"', "puts mass below 0"),
])
def test_cli_bad_input_exit_2_one_line(tmp_path, capsys, extra, prior, match):
    rec = tmp_path / "rec.csv"
    rec.write_text("t,phi\n" + "".join(f"{0.01 * i},{np.cos(0.1 * i)}\n" for i in range(50)))
    scene = tmp_path / "s.toml"
    scene.write_text(cj.scene_to_toml(cj.load_scene("lab-rig"))
                     + (f"\n[priors]\n{prior}\n" if prior else ""))
    rc = main(["posterior", str(rec), str(scene), "--out", str(tmp_path / "p.json"), *extra])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and match in err
    assert not (tmp_path / "p.json").exists()


def test_cli_posterior_writes_summary(tmp_path, capsys, short_record):
    scene, data = short_record
    rec = tmp_path / "rec.csv"
    cj.save_data(data, rec)
    out = tmp_path / "post.json"
    rc = main(["posterior", str(rec), "lab-rig", "--free", "k,c", "--draws", "30", "--warmup",
               "30", "--chains", "2", "--out", str(out), "--quiet"])
    assert rc == 0
    doc = json.loads(out.read_text())
    assert doc["draws"] == 30 and doc["chains"] == 2 and isinstance(doc["divergences"], int)
    assert set(doc["parameters"]["k"]) == {"mean", "sd", "q2.5", "q97.5", "rhat", "ess_bulk"}
    assert len(doc["samples"]["k"]) == 2 and len(doc["samples"]["k"][0]) == 30


class _Coords:
    """A stand-in for the fit's problem: one log coordinate and one linear (ref 2)."""

    log = (True, False)
    ref = (1.0, 2.0)

    def values(self, z):
        import jax.numpy as jnp

        return jnp.stack([jnp.exp(z[0]), 2.0 * z[1]])


@pytest.mark.parametrize("spec, expect", [
    # density of z = ln x under lognormal(m, s) is N(z; ln m, s): no Jacobian term left
    ("lognormal(2, 0.5)", lambda z: -0.5 * ((z - np.log(2)) / 0.5) ** 2),
    # loguniform is flat in ln x inside its bounds
    ("loguniform(0.5, 8)", lambda z: 0.0 * z),
    # uniform in x is e^z in z
    ("uniform(0.5, 8)", lambda z: z),
])
def test_log_prior_is_the_density_of_the_coordinate(spec, expect):
    from crank_jax.bayes.priors import log_prior, prior_arrays

    priors = parse_priors({"k": spec, "phi0": "normal(1, 0.1)"}, ("k", "phi0"))
    codes, params = prior_arrays(("k", "phi0"), priors, _Coords.log)
    z1, z2 = np.log(1.3), np.log(3.1)
    lp = [float(log_prior(np.array([z, 0.45]), _Coords(), codes, params)) for z in (z1, z2)]
    assert lp[1] - lp[0] == pytest.approx(expect(z2) - expect(z1), abs=1e-12)
    # phi0 = 2 * 0.45 = 0.9 under normal(1, 0.1): one sd below the mean
    base = float(log_prior(np.array([z1, 0.5]), _Coords(), codes, params))
    assert lp[0] - base == pytest.approx(-0.5, abs=1e-12)
    out = float(log_prior(np.array([np.log(20.0), 0.5]), _Coords(), codes, params))
    assert out == (-np.inf if "uniform" in spec else out)


def test_flat_prior_keeps_a_nonnegative_linear_field_nonnegative():
    from crank_jax.bayes.priors import log_prior, prior_arrays

    codes, params = prior_arrays(("k", "c_s"), {}, (True, False))
    assert float(log_prior(np.array([0.0, 0.1]), _Coords(), codes, params)) == 0.0
    assert float(log_prior(np.array([0.0, -0.1]), _Coords(), codes, params)) == -np.inf


def test_prior_precision_in_the_coordinates():
    """lognormal(m, s) on a log coordinate has sd s in z; normal(mu, sd) on a linear one
    with ref 2 has sd sd / 2 in z."""
    from crank_jax.bayes.priors import prior_arrays, prior_precision

    priors = parse_priors({"k": "lognormal(2, 0.5)", "phi0": "normal(1, 0.1)"}, ("k", "phi0"))
    codes, params = prior_arrays(("k", "phi0"), priors, _Coords.log)
    prec = prior_precision(codes, params, _Coords(), np.array([0.3, 0.5]))
    assert prec == pytest.approx([1 / 0.5**2, 1 / 0.05**2], rel=1e-12)
