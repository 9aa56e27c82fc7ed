"""The small-loop XLA flag: the CLI program sets it, the library never does, and it changes
how fast a solve runs, not what it returns."""

import json
import os
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.xla_flags import SMALL_LOOP_FLAG, small_loops_set, with_small_loops

KEY = "xla_cpu_small_while_loop_byte_threshold"


@pytest.mark.parametrize("flags, expected", [
    (None, SMALL_LOOP_FLAG),
    ("", SMALL_LOOP_FLAG),
    ("--xla_dump_to=/tmp/x", f"--xla_dump_to=/tmp/x {SMALL_LOOP_FLAG}"),
    # The user's own backend options are kept: the threshold joins their list.
    ("--xla_backend_extra_options=a=1 --b",
     f"--xla_backend_extra_options=a=1,{KEY}=1048576 --b"),
    # The user's threshold wins.
    (f"--xla_backend_extra_options={KEY}=0", f"--xla_backend_extra_options={KEY}=0"),
])
def test_with_small_loops_merges_and_respects_the_user(flags, expected):
    assert with_small_loops(flags) == expected
    assert small_loops_set(with_small_loops(flags))


def _env(**extra):
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env.update(extra)
    return env


def _flags_seen_by_the_program(env) -> str:
    code = ("import os, sys, crank_jax.cli\n"
            "m = sys.modules['crank_jax.cli.main']\n"
            "m.main = lambda: print(os.environ.get('XLA_FLAGS')) or 0\n"
            "m.entry()\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=env, timeout=120)
    assert p.returncode == 0, p.stderr
    return p.stdout.strip()


def test_the_program_sets_the_flag_and_the_library_does_not():
    assert _flags_seen_by_the_program(_env()) == SMALL_LOOP_FLAG
    mine = f"--xla_backend_extra_options={KEY}=2048"
    assert _flags_seen_by_the_program(_env(XLA_FLAGS=mine)) == mine
    # Importing the library and running a solve leave XLA_FLAGS alone.
    code = ("import os, crank_jax as cj\n"
            "cj.simulate(cj.load_scene('lab-rig').mech, 1.0, 0.0, [0.0, 0.1])\n"
            "print(os.environ.get('XLA_FLAGS'))\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=_env(), timeout=300)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "None"


def test_the_flag_changes_speed_not_results():
    """A solve and a forward Jacobian in a process with the flag equal this process's (run
    under the environment's flags) to rounding: the flag changes how XLA schedules the
    loops, not the arithmetic."""
    code = (
        "import json, jax; jax.config.update('jax_enable_x64', True)\n"
        "import jax.numpy as jnp, crank_jax as cj\n"
        "m = cj.load_scene('lab-rig').mech.replace(c=1e-3)\n"
        "ts = jnp.linspace(0.0, 2.0, 201)\n"
        "f = lambda k: cj.simulate(m.replace(k=k), 1.0, 0.0, ts, adjoint='forward').phi\n"
        "print(json.dumps([f(2.0).tolist(), jax.jacfwd(f)(2.0).tolist()]))\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=_env(XLA_FLAGS=SMALL_LOOP_FLAG), timeout=300)
    assert p.returncode == 0, p.stderr
    phi, dphi_dk = (np.asarray(x) for x in json.loads(p.stdout.strip().splitlines()[-1]))
    mech = cj.load_scene("lab-rig").mech.replace(c=1e-3)
    ts = jnp.linspace(0.0, 2.0, 201)

    def f(k):
        return cj.simulate(mech.replace(k=k), 1.0, 0.0, ts, adjoint="forward").phi

    import jax

    np.testing.assert_allclose(phi, f(2.0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(dphi_dk, jax.jacfwd(f)(2.0), rtol=0, atol=1e-10)
