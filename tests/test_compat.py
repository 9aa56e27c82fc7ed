"""Each private or undocumented API of another library that crank-jax still uses
(`crank_jax.runtime.compat`, `crank_jax.solve.library_api`): a test that fails, naming the
entry, when the API moves."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from crank_jax.runtime import compat
from crank_jax.solve import library_api
from crank_jax.solve.erk import dopri8


def test_results_round_trip_through_their_code():
    for item in (diffrax.RESULTS.successful, diffrax.RESULTS.max_steps_reached):
        back = library_api.result_from_code(library_api.result_code(item))
        assert bool(back == item)
    # A batch of codes (a vmap-ed solve's) stays one item of shape (B,).
    ok = jnp.array([True, False, True])
    batch = jax.vmap(lambda d: diffrax.RESULTS.where(
        d, diffrax.RESULTS.successful, diffrax.RESULTS.max_steps_reached))(ok)
    code = library_api.result_code(batch)
    assert code.shape == (3,)
    np.testing.assert_array_equal(
        library_api.result_from_code(code) == diffrax.RESULTS.successful, ok)


def test_dopri8_dense_output_is_diffrax_own():
    # "diffrax.Dopri8.interpolation_cls.eval_coeffs moved" if this fails to run. One step
    # of dy/dt = -y + sin t: the dense output from these coefficients and the fused stages
    # equals diffrax's own (`sol.evaluate`) inside the step, and y1 at its end.
    P = library_api.dopri8_dense_coefficients()
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
        return library_api.while_loop(lambda c: c[0] < 5, lambda c: (c[0] + 1, c[1] * 1.1),
                                 (0, x), max_steps=8, kind=kind)[1]

    for kind in ("lax", "bounded", "checkpointed"):
        assert float(run(2.0, kind)) == pytest.approx(2.0 * 1.1 ** 5)
    assert float(jax.grad(lambda x: run(x, "checkpointed"))(2.0)) == pytest.approx(1.1 ** 5)


def test_no_module_writes_another_librarys_globals():
    # Issue 26: equinox's check mode was switched process-wide (not thread-safe, and it
    # leaked through equinox's check cache). No source file may reach for it again.
    import re
    from pathlib import Path

    import crank_jax

    banned = re.compile(r"(import|from)\s+equinox\._errors|equinox\s+import\s+_errors"
                        r"|EQX_ON_ERROR\s*=[^=]|setattr\([^)]*EQX_ON_ERROR")
    root = Path(crank_jax.__file__).parent
    for path in root.rglob("*.py"):
        hit = banned.search(path.read_text())
        assert hit is None, f"{path.relative_to(root)}: {hit.group(0)}"
    assert banned.search("import equinox._errors as e\ne.EQX_ON_ERROR = 'nan'")


def test_jax_internals():
    # "jax._src.xla_bridge.backends_are_initialized moved" / "jax._src.lax.linalg.
    # initialize_lapack moved" if this fails (the latter has a public fallback, but the
    # program store loads 0.1 s slower without it).
    jnp.zeros(1).block_until_ready()
    assert compat.backends_are_initialized() is True
    from jax._src.lax.linalg import initialize_lapack  # noqa: F401

    compat.initialize_lapack()


def test_jax_distributed_client():
    # "jax._src.distributed.global_state.client moved" if this fails: None before
    # jax.distributed.initialize (as in this process), and the client's type still has
    # the barrier that every multi-process sweep's collective waits at first.
    from jax._src import lib

    assert compat.distributed_client() is None
    native = getattr(lib, "_jax", None) or lib.xla_extension  # its name before jax 0.7
    assert callable(getattr(native.DistributedRuntimeClient, "wait_at_barrier", None))


def test_private_apis_are_used_only_in_the_compat_modules():
    # Every private use sits behind one of the two compat modules, with a test above that
    # names it when it moves (sweep/collective.py imported jax._src.distributed itself).
    import re
    from pathlib import Path

    import crank_jax

    private = re.compile(r"(from|import)\s+(jax|jaxlib|equinox|diffrax|optimistix|lineax|"
                         r"optax)(\.\w+)*\._\w+|\bjax\._src\b|\bequinox\.internal\b")
    root = Path(crank_jax.__file__).parent
    allowed = {root / "runtime" / "compat.py", root / "solve" / "library_api.py"}
    for path in root.rglob("*.py"):
        if path not in allowed:
            hit = private.search(path.read_text())
            assert hit is None, f"{path.relative_to(root)}: {hit.group(0)}"
    assert private.search("    from jax._src import distributed")
    assert private.search("import equinox.internal as eqxi")
