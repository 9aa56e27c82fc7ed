"""crank-jax's CPU flags for XLA: the CLI program sets them, the library never does, and
they change how fast a solve runs, not what it returns."""

import json
import os
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest

import crank_jax as cj
from crank_jax.runtime.xla_flags import configure_cpu, cpu_flags, with_cpu_flags

KEY = "xla_cpu_small_while_loop_byte_threshold"
LOOP = f"--xla_backend_extra_options={KEY}=1048576"
WIDTH = "--xla_cpu_prefer_vector_width=512"


@pytest.mark.parametrize("flags, expected", [
    (None, "{ours}"),
    ("", "{ours}"),
    ("--xla_dump_to=/tmp/x", "--xla_dump_to=/tmp/x {ours}"),
    # The user's own backend options are kept: the threshold joins their list.
    ("--xla_backend_extra_options=a=1 --b",
     f"--xla_backend_extra_options=a=1,{KEY}=1048576 --b {{width}}"),
    # The user's threshold and vector width win.
    (f"--xla_backend_extra_options={KEY}=0", f"--xla_backend_extra_options={KEY}=0 {{width}}"),
    (f"--xla_cpu_prefer_vector_width=256 {LOOP}", f"--xla_cpu_prefer_vector_width=256 {LOOP}"),
])
def test_with_cpu_flags_merges_and_respects_the_user(flags, expected):
    ours = " ".join(cpu_flags())
    width = WIDTH if WIDTH in ours else ""
    assert cpu_flags()[0] == LOOP
    assert with_cpu_flags(flags) == expected.format(ours=ours, width=width).strip()
    assert with_cpu_flags(with_cpu_flags(flags)) == with_cpu_flags(flags)  # idempotent


def _env(**extra):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_NUM_CPU_DEVICES")}
    env.update(extra)
    return env


def _seen_by_the_program(env) -> tuple[str, int]:
    """`XLA_FLAGS` and the CPU device count inside the `crank-jax` program."""
    code = ("import os, sys, jax, crank_jax.cli\n"
            "m = sys.modules['crank_jax.cli.main']\n"
            "m.main = lambda: print(os.environ.get('XLA_FLAGS')) or "
            "print(jax.device_count()) or 0\n"
            "m.entry()\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=env, timeout=120)
    assert p.returncode == 0, p.stderr
    flags, devices = p.stdout.strip().splitlines()[-2:]
    return flags, int(devices)


def test_the_program_sets_the_flag_and_the_library_does_not():
    cores = len(os.sched_getaffinity(0))
    assert _seen_by_the_program(_env()) == (" ".join(cpu_flags()), cores)
    # What the user set wins: their threshold, their device count.
    mine = f"--xla_backend_extra_options={KEY}=2048"
    seen, devices = _seen_by_the_program(_env(XLA_FLAGS=mine, JAX_NUM_CPU_DEVICES="3"))
    assert seen.startswith(mine) and seen == with_cpu_flags(mine) and "1048576" not in seen
    assert devices == 3
    # Importing the library and running a solve leave XLA_FLAGS alone.
    code = ("import os, jax, crank_jax as cj\n"
            "cj.simulate(cj.load_scene('lab-rig').mech, 1.0, 0.0, [0.0, 0.1])\n"
            "print(os.environ.get('XLA_FLAGS'), jax.device_count())\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=_env(), timeout=300)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "None 1"


def test_configure_cpu_refuses_once_jax_has_started():
    # This process has run JAX already: the settings could no longer take effect.
    jnp.zeros(1).block_until_ready()
    with pytest.raises(RuntimeError, match="before the first JAX computation"):
        configure_cpu()


def test_the_flag_changes_speed_not_results():
    """A solve and a forward Jacobian in a process with the flags equal this process's (run
    under the environment's flags) to rounding: the flags change how XLA schedules the
    loops and how wide its vectors are, not the arithmetic."""
    code = (
        "import json, jax; jax.config.update('jax_enable_x64', True)\n"
        "import jax.numpy as jnp, crank_jax as cj\n"
        "m = cj.load_scene('lab-rig').mech.replace(c=1e-3)\n"
        "ts = jnp.linspace(0.0, 2.0, 201)\n"
        "f = lambda k: cj.simulate(m.replace(k=k), 1.0, 0.0, ts, adjoint='forward').phi\n"
        "print(json.dumps([f(2.0).tolist(), jax.jacfwd(f)(2.0).tolist()]))\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=_env(XLA_FLAGS=with_cpu_flags(None)), timeout=300)
    assert p.returncode == 0, p.stderr
    phi, dphi_dk = (np.asarray(x) for x in json.loads(p.stdout.strip().splitlines()[-1]))
    mech = cj.load_scene("lab-rig").mech.replace(c=1e-3)
    ts = jnp.linspace(0.0, 2.0, 201)

    def f(k):
        return cj.simulate(mech.replace(k=k), 1.0, 0.0, ts, adjoint="forward").phi

    import jax

    np.testing.assert_allclose(phi, f(2.0), rtol=0, atol=1e-12)
    # The Jacobian steps the variational equation beside the solution (variational.py),
    # whose step control takes discrete decisions (a step shortened to a save window keeps
    # the controller's proposal) that a last-bit difference can flip: measured 1.2e-10 of
    # the largest sensitivity, 100x below the solve's own error at rtol 1e-8.
    jac = jax.jacfwd(f)(2.0)
    np.testing.assert_allclose(dphi_dk, jac, rtol=0, atol=1e-9 * np.max(np.abs(jac)))
