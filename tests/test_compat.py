"""Each private or undocumented API of another library that crank-jax still uses
(`crank_jax.compat`): a test that fails, naming the entry, when the API moves."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from crank_jax import compat
from crank_jax.solve.erk import dopri8


def test_results_round_trip_through_their_code():
    for item in (diffrax.RESULTS.successful, diffrax.RESULTS.max_steps_reached):
        back = compat.result_from_code(compat.result_code(item))
        assert bool(back == item)
    # A batch of codes (a vmap-ed solve's) stays one item of shape (B,).
    ok = jnp.array([True, False, True])
    batch = jax.vmap(lambda d: diffrax.RESULTS.where(
        d, diffrax.RESULTS.successful, diffrax.RESULTS.max_steps_reached))(ok)
    code = compat.result_code(batch)
    assert code.shape == (3,)
    np.testing.assert_array_equal(
        compat.result_from_code(code) == diffrax.RESULTS.successful, ok)


def test_dopri8_dense_output_is_diffrax_own():
    # "diffrax.Dopri8.interpolation_cls.eval_coeffs moved" if this fails to run. One step
    # of dy/dt = -y + sin t: the dense output from these coefficients and the fused stages
    # equals diffrax's own (`sol.evaluate`) inside the step, and y1 at its end.
    P = compat.dopri8_dense_coefficients()
    assert P.shape[0] == 14
    f = lambda t, y, args: -y + jnp.sin(t)  # noqa: E731
    h, y0 = 0.5, jnp.array([1.0])
    sol = diffrax.diffeqsolve(diffrax.ODETerm(f), diffrax.Dopri8(), 0.0, h, h, y0,
                              saveat=diffrax.SaveAt(dense=True),
                              stepsize_controller=diffrax.ConstantStepSize())
    erk = dopri8()
    ks = erk.stages(f, 0.0, y0, None, h)
    y1 = erk.solution(y0, h, ks)
    ks = ks + [f(h, y1, None)]
    for theta in (0.3, 0.77, 1.0):
        weights = [np.polyval(P[i], theta) for i in range(14)]
        ours = y0 + theta * h * sum(w * k for w, k in zip(weights, ks))
        np.testing.assert_allclose(ours, sol.evaluate(theta * h), rtol=0, atol=1e-14)
    np.testing.assert_allclose(ours, y1, rtol=0, atol=1e-14)


def test_equinox_internal_while_loop_kinds():
    # "equinox.internal.while_loop moved" if this fails: each kind runs; the
    # checkpointed one is reverse-differentiable.
    def run(x, kind):
        return compat.while_loop(lambda c: c[0] < 5, lambda c: (c[0] + 1, c[1] * 1.1),
                                 (0, x), max_steps=8, kind=kind)[1]

    for kind in ("lax", "bounded", "checkpointed"):
        assert float(run(2.0, kind)) == pytest.approx(2.0 * 1.1 ** 5)
    assert float(jax.grad(lambda x: run(x, "checkpointed"))(2.0)) == pytest.approx(1.1 ** 5)


def test_equinox_checks_as_nan_and_restored():
    # "equinox._errors.EQX_ON_ERROR moved" if this fails: inside, a check traced then is
    # NaN (no host callback); outside, the mode is what it was.
    before = compat.checks_are_nan()

    def checked(x):
        return eqx.error_if(x, x > 0, "positive")

    with compat.checks_as_nan():
        assert compat.checks_are_nan()
        out = jax.jit(checked)(jnp.array(1.0))
        text = jax.jit(checked).lower(jnp.array(1.0)).as_text()
    assert np.isnan(float(out))
    assert "callback" not in text
    assert compat.checks_are_nan() == before
    if not before:
        # Another message: equinox caches a check's trace by its message and shapes, not
        # by the mode (see compat.checks_as_nan), so "positive" would stay NaN.
        with pytest.raises(Exception, match="still positive"):
            eqx.filter_jit(lambda x: eqx.error_if(x, x > 0, "still positive"))(jnp.array(2.0))


def test_jax_internals():
    # "jax._src.xla_bridge.backends_are_initialized moved" / "jax._src.lax.linalg.
    # initialize_lapack moved" if this fails (the latter has a public fallback, but the
    # program store loads 0.1 s slower without it).
    jnp.zeros(1).block_until_ready()
    assert compat.backends_are_initialized() is True
    from jax._src.lax.linalg import initialize_lapack  # noqa: F401

    compat.initialize_lapack()
