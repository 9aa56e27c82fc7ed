"""Loads: sampled-load interpolations (exactness, order, mean, gradients, the solver's
step boundaries, the bias on a sampled multisine) and the one table of load kinds."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.model.loads import (
    LOAD_KINDS,
    LOAD_PARAMS,
    get_param,
    load_from_table,
    load_to_table,
    promote,
    set_param,
)

# The multisine of DESIGN.md section 7: 4 tones, 1-7 Hz, logged at 250 Hz.
TONES = dict(amplitudes=[0.04, 0.03, 0.025, 0.02], freqs_hz=[1.3, 2.9, 4.7, 6.8],
             phases=[0.0, 1.0, 2.0, 3.0])


def _irregular(n, rng):
    return np.sort(np.concatenate([[0.0, 1.0], rng.uniform(0.0, 1.0, n - 2)]))


# --- interpolation ----------------------------------------------------------------------

def test_cubic_is_exact_for_cubics_and_holds_outside(rng):
    ts = _irregular(17, rng)
    p = lambda t: 1 + 2 * t - 3 * t**2 + 0.5 * t**3  # noqa: E731
    ld = cj.SampledLoad(ts, p(ts))
    t = np.linspace(0.0, 1.0, 301)
    np.testing.assert_allclose(np.asarray(ld(t)), p(t), atol=1e-12)
    np.testing.assert_allclose(np.asarray(ld(jnp.array([-1.0, 2.0]))), [p(0.0), p(1.0)])
    # The exact mean of the cubic on [0, 1]: 1 + 1 - 1 + 1/8.
    assert float(ld.mean()) == pytest.approx(1.125, abs=1e-12)


@jax.jit
def _cubic(ts, vs, t):
    return cj.SampledLoad(ts, vs)(t)


def test_cubic_is_c2_and_fourth_order(rng):
    ts = jnp.asarray(_irregular(12, rng))
    vs = jnp.sin(3 * ts)
    one = lambda t: _cubic(ts, vs, t)  # noqa: E731
    d1 = jax.jit(jax.vmap(jax.grad(one)))
    d2 = jax.jit(jax.vmap(jax.grad(jax.grad(one))))
    knots = ts[1:-1]
    eps = 1e-9
    for d, tol in ((d1, 1e-6), (d2, 1e-5)):  # continuous across every inner knot
        np.testing.assert_allclose(d(knots - eps), d(knots + eps), atol=tol)
    errs = []
    t = np.linspace(0.0, 1.0, 2001)
    for n in (41, 81, 161):
        grid = np.linspace(0.0, 1.0, n)
        errs.append(np.max(np.abs(np.asarray(_cubic(grid, np.sin(7 * grid), t))
                                  - np.sin(7 * t))))
    assert errs[0] / errs[1] > 12 and errs[1] / errs[2] > 12  # O(h^4): 16 per halving


def test_linear_and_zoh():
    ts, vs = np.array([0.0, 1.0, 3.0]), np.array([1.0, 3.0, -1.0])
    t = np.array([-1.0, 0.0, 0.5, 1.0, 2.0, 3.0, 4.0])
    lin = cj.SampledLoad(ts, vs, "linear")
    np.testing.assert_allclose(np.asarray(lin(t)), np.interp(t, ts, vs))
    assert float(lin.mean()) == pytest.approx((2.0 + 2.0) / 3)
    zoh = cj.SampledLoad(ts, vs, "zoh")
    np.testing.assert_allclose(np.asarray(zoh(t)), [1, 1, 1, 3, 3, -1, -1])
    assert float(zoh.mean()) == pytest.approx((1.0 + 6.0) / 3)
    assert lin.nonsmooth().step_ts is not None and zoh.nonsmooth().jump_ts is not None
    assert zoh.nonsmooth().step_ts is None and cj.SampledLoad(ts, vs).nonsmooth().step_ts \
        is not None
    with pytest.raises(ValueError, match="interp 'spline' is unknown"):
        cj.SampledLoad(ts, vs, "spline")


def test_spline_gradient_matches_finite_differences_and_never_retraces():
    ts = jnp.linspace(0.0, 1.0, 9)

    def f(v):
        return _cubic(ts, v, jnp.array([0.13, 0.61])).sum() ** 2

    grad = eqx.debug.assert_max_traces(jax.grad(f), max_traces=1)
    grad = jax.jit(grad)
    v = jnp.sin(3 * ts)
    g = grad(v)
    h = 1e-6
    fd = [(f(v.at[i].add(h)) - f(v.at[i].add(-h))) / (2 * h) for i in range(9)]
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-10)
    grad(v + 1.0)  # new values, same program


def test_zoh_solve_matches_piecewise_constant_solves(lab_rig):
    # Independent check of the jump handling: integrate interval by interval with the
    # held value as a constant torque, restarting at every sample.
    ts = np.linspace(0.0, 0.4, 9)
    vs = 0.05 * np.array([1, -1, 2, 0, -2, 1, 3, -1, 0.5])
    kw = dict(solver="dopri8", rtol=1e-11, atol=1e-13)
    whole = cj.simulate(lab_rig.mech, 0.5, 0.0, ts,
                        torque=cj.SampledLoad(ts, vs, "zoh"), **kw)
    y = (0.5, 0.0)
    for i in range(len(ts) - 1):
        tr = cj.simulate(lab_rig.mech, *y, ts[i:i + 2], torque=float(vs[i]), **kw)
        y = (tr.phi[-1], tr.dphi[-1])
    np.testing.assert_allclose([whole.phi[-1], whole.dphi[-1]], y, rtol=1e-8, atol=1e-9)


def test_sampled_multisine_bias_per_interpolation(lab_rig):
    """The model error of each interpolation of a multisine torque sampled at 250 Hz,
    against the continuous multisine: the cubic spline must be far below linear and zoh
    (DESIGN.md section 7: 0.6 mrad vs 0.2 urad on a fit-sized record)."""
    mech = lab_rig.mech
    true = cj.MultiSineLoad(**TONES)
    t_s = np.arange(0.0, 1.0 + 1e-9, 1 / 250)
    out = np.linspace(0.0, 1.0, 101)
    kw = dict(solver="dopri8", rtol=1e-10, atol=1e-12)
    ref = np.asarray(cj.simulate(mech, 1.5, 0.0, out, torque=true, **kw).phi)
    rms = {}
    for interp in cj.model.INTERPOLATIONS:
        ld = cj.SampledLoad(t_s, np.asarray(true(t_s)), interp)
        phi = np.asarray(cj.simulate(mech, 1.5, 0.0, out, torque=ld, **kw).phi)
        rms[interp] = float(np.sqrt(np.mean((phi - ref) ** 2)))
    assert rms["cubic"] < 1e-3 * rms["linear"], rms
    assert rms["linear"] < rms["zoh"], rms  # a hold lags by half a sample
    assert rms["cubic"] < 1e-6, rms


def test_load_data_takes_the_interpolation(tmp_path):
    path = tmp_path / "d.csv"
    path.write_text("t,phi,tau\n" + "".join(f"{i * 0.1},{0.01 * i},{i % 3}\n"
                                            for i in range(8)))
    for interp in cj.model.INTERPOLATIONS:
        d = cj.load_data(path, interp=interp)
        assert d.torque.interp == interp and d.load is None
    assert float(cj.load_data(path, interp="zoh").torque(0.19)) == 1.0
    assert float(cj.load_data(path, interp="linear").torque(0.15)) == pytest.approx(1.5)
    with pytest.raises(cj.DataError, match="interpolation 'spline' is unknown"):
        cj.load_data(path, interp="spline")


# --- the table --------------------------------------------------------------------------

def test_table_names_and_roles():
    assert set(LOAD_PARAMS) == {"P0", "P1", "P_freq_hz", "P_phase", "P_gain", "tau0", "tau1",
                                "tau_freq_hz", "tau_phase", "tau_gain"}
    h = cj.HarmonicLoad(1.0, 2.0, 3.0, 0.5)
    assert [float(get_param(h, r)) for r in ("mean", "amp", "freq_hz", "phase")] == \
        [1.0, 2.0, 3.0, 0.5]
    assert float(set_param(h, "amp", 4.0).X1) == 4.0
    ms = cj.MultiSineLoad(**TONES, X0=0.3)
    assert float(get_param(ms, "mean")) == 0.3 and get_param(ms, "amp") is None
    with pytest.raises(ValueError, match="MultiSineLoad .* no tau1; its parameters are"):
        set_param(ms, "amp", 1.0, "torque")
    assert isinstance(promote(cj.NoLoad(), {"mean"}), cj.ConstantLoad)
    p = promote(cj.ConstantLoad(2.0), {"amp"})
    assert isinstance(p, cj.HarmonicLoad) and float(p(0.3)) == 2.0
    with pytest.raises(ValueError, match="SampledLoad .* no P1"):
        promote(cj.SampledLoad([0.0, 1.0], [1.0, 2.0]), {"amp"}, "load")


@pytest.mark.parametrize("load", [
    cj.NoLoad(), cj.ConstantLoad(-2.0), cj.HarmonicLoad(0.5, 1.0, 2.0, 0.3),
    cj.MultiSineLoad(**TONES, X0=0.1)])
def test_every_toml_kind_round_trips(load, lab_rig, tmp_path):
    table = load_to_table(load, "torque")
    back = load_from_table(table or {}, "torque")
    assert type(back) is type(load)
    t = jnp.linspace(0.0, 1.0, 7)
    np.testing.assert_allclose(np.asarray(back(t)), np.asarray(load(t)))
    scene = eqx.tree_at(lambda s: s.torque, lab_rig, load)
    cj.save_scene(scene, tmp_path / "s.toml")
    again = cj.load_scene(tmp_path / "s.toml")
    assert type(again.torque) is type(load)
    np.testing.assert_allclose(np.asarray(again.torque(t)), np.asarray(load(t)))


def test_table_refusals():
    with pytest.raises(ValueError, match="kind 'sampled' cannot be used in a scene"):
        load_from_table({"kind": "sampled"}, "load")
    with pytest.raises(ValueError, match="key 'P1' does not apply to kind 'constant'"):
        load_from_table({"kind": "constant", "P1": 1.0}, "load")
    with pytest.raises(ValueError, match="needs amplitudes"):
        load_from_table({"kind": "multisine"}, "torque")
    with pytest.raises(ValueError, match="cannot be written to a scene file"):
        load_to_table(cj.SampledLoad([0.0, 1.0], [1.0, 2.0]), "load")
    with pytest.raises(ValueError, match=r"kind 'angle' cannot be used in a scene.*load_by"):
        load_from_table({"kind": "angle"}, "load")
    angle = cj.model.AngleLoad.from_samples([0.0, 1.0, 2.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="cannot be written to a scene file"):
        load_to_table(angle, "load")
    assert {k.name for k in LOAD_KINDS} == {"none", "constant", "harmonic", "multisine",
                                            "sampled", "input", "angle"}
