"""Per-program XLA compile options (issue 40): the fit's programs and the linearisation
compile with XLA's older fusion emitters (`runtime/persistent.py`, `FAST_COMPILE`, 0.4-0.7x
the compile time)
only where that leaves every bit of their results the same, and an option this XLA does
not know never fails a program (`persistent.py`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.identify import channel_noise as ch
from crank_jax.identify.fit_plan import recoordinate
from crank_jax.identify.programs import FAST_COMPILE, compile_options, jacobian_at
from crank_jax.identify.request import normalize
from crank_jax.runtime import persistent
from crank_jax.runtime.xla_flags import small_loop_bytes

_X = jnp.linspace(0.0, 1.0, 5)


def _fn(x):
    return (jnp.sin(x) * 2.0, jnp.sum(x))


@pytest.fixture(scope="module")
def problems(lab_rig):
    """(single, its z, multiple (3 segments), its z) of a short lab-rig record, built
    without a solve."""
    from crank_jax.identify.fit_plan import _problem, _starts, pick_solver
    from crank_jax.identify.strategy import MAX_ODE_STEPS

    start = cj.Scene(lab_rig.mech.replace(k=2.4, c=0.004), phi0=1.0, name="start")
    ts = np.linspace(0.0, 1.5, 151)  # a decaying swing: a record's shapes, no solve
    data = cj.Data(ts, np.exp(-0.2 * ts) * np.cos(8.0 * ts))
    req = normalize(
        start, data, ("k", "c", "phi0", "dphi0"), init="scene", method="lm",
        shooting="single", segments=None, multistart=1, seed=0, max_steps=None,
        tol=1e-8, sigma=None, profile=None, window=None, progress=False, warn=False)
    start_g, states, _ = _starts(req, [None])
    solver = pick_solver(start.mech, req.loads[0][0], float(start.rtol), start.solver)
    ss = _problem(req, start_g, states, [1], MAX_ODE_STEPS, solver)
    ms = _problem(req, start_g, states, [3], MAX_ODE_STEPS, solver, linear=True)
    z = ss.to_z([start_g["k"], start_g["c"], *states[0]])
    z_ms = np.concatenate([recoordinate(ss, ms, z), ch.segment_states(ms, req)])
    return ss, z, ms, z_ms


def test_fit_programs_choose_the_fast_compile(problems):
    ss, z, ms, z_ms = problems
    assert ms.n_extra > 0 and ss.n_extra == 0
    assert jacobian_at.options(ms, z_ms) == tuple(FAST_COMPILE.items())
    # A single-shooting solve keeps XLA's defaults unless crank-jax's CPU flags are set
    # (there the emitters give the same bits as well).
    want = tuple(FAST_COMPILE.items()) if small_loop_bytes() is not None else ()
    assert jacobian_at.options(ss, z) == want
    assert compile_options(ss) == dict(want)


@pytest.mark.slow  # two compiles of a Jacobian program: ~10 s on 2 idle cores
def test_fast_compile_same_bits(problems):
    """The multiple-shooting Jacobian program compiled with and without the options: the
    same bits in every output (residuals, failures, steps, Jacobian)."""
    _, _, ms, z_ms = problems
    lowered = jacobian_at.lower(ms, jnp.asarray(z_ms))
    fast = lowered.compile(dict(FAST_COMPILE))(ms, jnp.asarray(z_ms))
    plain = lowered.compile({"xla_cpu_use_fusion_emitters": True})(ms, jnp.asarray(z_ms))
    for a, b in zip(fast, plain, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.all(np.isfinite(np.asarray(fast[3])))


def test_linearization_compiles_fast_with_the_same_bits():
    """The linearisation's program (`simulation._linearize_program`) asks for the fast
    compile, and gives the same bits with and without it: a sample of mechanisms of the
    four preset scenes, with a constant and a harmonic slider force and a crank torque
    (experiments: 960 of them, under the defaults and the CPU flags)."""
    from crank_jax.model import ConstantLoad, HarmonicLoad, NoLoad
    from crank_jax.model.linear import linearize_tuple, mean_loads
    from crank_jax.simulation import _linearize_program

    lab = cj.load_scene("lab-rig")
    assert _linearize_program.options(lab.mech, mean_loads(None, None)) == tuple(
        FAST_COMPILE.items())
    rng = np.random.default_rng(3)
    for name in ("lab-rig", "near-buckling", "pendulum", "torsional"):
        mech0 = cj.load_scene(name).mech
        for load, torque in ((NoLoad(), NoLoad()), (ConstantLoad(3.0), ConstantLoad(0.01)),
                             (HarmonicLoad(-2.0, 1.0, 2.0), NoLoad())):
            loads = mean_loads(load, torque)
            low = jax.jit(linearize_tuple).lower(mech0, loads)
            fast = low.compile(dict(FAST_COMPILE))
            plain = low.compile({"xla_cpu_use_fusion_emitters": True})
            for _ in range(4):
                mech = mech0.replace(k=float(mech0.k) * rng.uniform(0.2, 3.0),
                                     c=rng.uniform(0.0, 0.02), e=rng.uniform(-0.01, 0.01),
                                     gravity_angle=rng.uniform(-1.0, 1.0))
                for a, b in zip(fast(mech, loads), plain(mech, loads), strict=True):
                    assert np.asarray(a).tobytes() == np.asarray(b).tobytes()


@pytest.mark.parametrize("stored", [False, True])
def test_unknown_option_is_dropped(stored, tmp_path, monkeypatch):
    """An option this XLA refuses: the program runs as without it (stored or not), and
    later compiles leave it out."""
    if stored:
        monkeypatch.setattr(persistent, "program_store_dir", lambda: tmp_path / "programs")
    monkeypatch.setattr(persistent, "_UNKNOWN_OPTIONS", set())
    prog = persistent.PersistentProgram(
        _fn, f"options_test_{stored}",
        lambda x: {"xla_no_such_option_here": True, **FAST_COMPILE})
    out = prog(_X)
    np.testing.assert_array_equal(np.asarray(out[0]), np.asarray(jnp.sin(_X) * 2.0))
    assert persistent._UNKNOWN_OPTIONS == {"xla_no_such_option_here"}
    assert prog.options(_X) == tuple(FAST_COMPILE.items())
    np.testing.assert_array_equal(np.asarray(prog(_X)[1]), np.asarray(jnp.sum(_X)))


def test_a_program_error_is_not_swallowed(monkeypatch):
    """Only XLA's refusal of an option falls back; any other failure is raised."""
    monkeypatch.setattr(persistent, "_UNKNOWN_OPTIONS", set())

    def bad(x):
        raise ValueError("the program's own error")

    prog = persistent.PersistentProgram(bad, "options_error", lambda x: dict(FAST_COMPILE))
    with pytest.raises(ValueError, match="own error"):
        prog(_X)
    assert not persistent._UNKNOWN_OPTIONS


def test_options_are_part_of_the_key():
    args = (_X,)
    assert (persistent._signature("p", args, ())[0]
            != persistent._signature("p", args, tuple(FAST_COMPILE.items()))[0])
    assert jax.default_backend() == "cpu"


_UNDER_FLAGS = """
import os, sys
import numpy as np
sys.path.insert(0, {tests!r})
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import crank_jax as cj
import test_compile_options as t
from crank_jax.identify.programs import FAST_COMPILE, jacobian_at
ss, z, ms, z_ms = t.problems.__wrapped__(cj.load_scene("lab-rig"))
assert jacobian_at.options(ss, z) == tuple(FAST_COMPILE.items())
low = jacobian_at.lower(ss, jnp.asarray(z))
fast = low.compile(dict(FAST_COMPILE))(ss, jnp.asarray(z))
plain = low.compile({{"xla_cpu_use_fusion_emitters": True}})(ss, jnp.asarray(z))
for a, b in zip(fast, plain, strict=True):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
print("same bits")
"""


@pytest.mark.slow  # a fresh process and two compiles: ~15 s on 2 idle cores
def test_single_shooting_same_bits_under_the_cpu_flags():
    """Under crank-jax's CPU flags (the `crank-jax` program's) the single-shooting
    Jacobian also takes the options: the same bits as without them."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from crank_jax.runtime.xla_flags import with_cpu_flags

    env = dict(os.environ, XLA_FLAGS=with_cpu_flags(os.environ.get("XLA_FLAGS")),
               CRANK_JAX_NO_CACHE="1")
    code = _UNDER_FLAGS.format(tests=str(Path(__file__).parent))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, timeout=900)
    assert out.returncode == 0 and "same bits" in out.stdout, out.stderr[-2000:]
