"""Compiled programs kept between processes (`persistent.py`): a second process loads
what the first compiled, gets the same numbers, and survives a damaged store.

Each case runs fresh interpreters with their own cache directory, as CLI calls do (the
test process itself runs with `CRANK_JAX_NO_CACHE`, so no store).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

# A fresh interpreter with the store in the directory argv[1], counting in `compiled` the
# programs it compiles (rather than loads).
PRELUDE = r"""
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
import crank_jax as cj
from crank_jax import persistent
cj.enable_compilation_cache(sys.argv[1])
compiled = []
orig = persistent.PersistentProgram._compile
def counting(self, *a, **k):
    compiled.append(self.name)
    return orig(self, *a, **k)
persistent.PersistentProgram._compile = counting
"""

# A fit (its forward-mode residuals and Jacobian, a linearisation: every stored program of
# the CLI's fit) and a simulation. Prints the estimates and how many programs this
# process compiled.
SCRIPT = PRELUDE + r"""
scene = cj.load_scene("lab-rig")
data = cj.synthesize(scene, t1=2.0, rate=100.0, noise_std=1e-3, seed=int(sys.argv[2]))
res = cj.fit(scene, data, free=("k", "c", "phi0", "dphi0"), init={"k": 2.4},
             progress=False)
traj = scene.simulate(outputs=("energy", "reactions"))
print(json.dumps({"sim": [float(traj.phi[-1]), float(traj.extras["energy"][-1]),
                          float(traj.extras["N"][7]), int(traj.num_steps),
                          bool(traj.result == __import__("diffrax").RESULTS.successful)],
                  "values": {n: float(v) for n, v in res.values.items()},
                  "stderr": {n: float(v) for n, v in res.stderr.items()},
                  "converged": bool(res.converged), "compiled": sorted(compiled)}))
"""


def _run(cache: Path, seed: int = 1, devices: int = 1) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "CRANK_JAX_NO_CACHE"}
    env["JAX_NUM_CPU_DEVICES"] = str(devices)
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(cache), str(seed)], env=env,
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    cache = tmp_path_factory.mktemp("jax-cache")
    return cache, _run(cache)


def test_second_process_loads_instead_of_compiling(stored):
    cache, first = stored
    assert first["converged"]
    assert set(first["compiled"]) >= {"jacobian", "linearize", "simulate"}
    assert first["sim"][-1]
    files = sorted(p.name.split("-")[0] for p in (cache / "crank-jax-programs").glob("*.xla"))
    assert set(files) >= {"jacobian", "linearize", "simulate"}
    second = _run(cache)
    assert second["compiled"] == [], "a warm process compiled again"
    # Loaded executables compute the same numbers as freshly compiled ones.
    assert second["values"] == first["values"]
    assert second["stderr"] == first["stderr"]
    assert second["sim"] == first["sim"]
    # Another record (other noise) of the same shape reuses the same programs.
    assert _run(cache, seed=2)["compiled"] == []


def test_stored_programs_load_with_a_device_per_core(stored, tmp_path):
    """With several CPU devices (`configure_cpu`, as the CLI runs), one-device programs
    are stored and loaded too (JAX would load them onto every device, and they failed on
    their first call), and give the one-device numbers."""
    _, one = stored
    cache = tmp_path / "two-devices"
    first = _run(cache, devices=2)
    assert set(first["compiled"]) >= {"jacobian", "linearize", "simulate"}
    second = _run(cache, devices=2)
    assert second["compiled"] == [], "a warm two-device process compiled again"
    assert second["values"] == one["values"] and second["sim"] == one["sim"]


def test_stored_simulate_equals_the_ordinary_one(stored, tmp_path):
    """The stored program (host mode, no callbacks) gives the numbers the ordinary
    in-process `simulate` gives, extras and step count included."""
    import jax  # noqa: F401  (x64 is on in the tests' conftest)

    import crank_jax as cj

    _, first = stored
    traj = cj.load_scene("lab-rig").simulate(outputs=("energy", "reactions"))
    assert first["sim"][:4] == [float(traj.phi[-1]), float(traj.extras["energy"][-1]),
                                float(traj.extras["N"][7]), int(traj.num_steps)]


def test_damaged_store_is_recompiled(stored, tmp_path):
    cache, first = stored
    copy = tmp_path / "cache"
    (copy / "crank-jax-programs").mkdir(parents=True)
    damages = (lambda b: b[: len(b) // 2], lambda b: b"\0garbage" * 100, lambda b: b"",
               lambda b: b[:4])
    files = sorted((cache / "crank-jax-programs").glob("*.xla"))
    assert len(files) >= 4  # so that every kind of damage is tried
    for i, p in enumerate(files):
        # truncated, garbage, empty or a bare header: each must be a miss, never a crash
        (copy / "crank-jax-programs" / p.name).write_bytes(damages[i % 4](p.read_bytes()))
    again = _run(copy)
    assert again["values"] == first["values"]
    assert set(again["compiled"]) == {"jacobian", "linearize", "simulate"}
    assert all(p.stat().st_size > 1000 for p in (copy / "crank-jax-programs").glob("*.xla"))


# A stored program that calls LAPACK (a linear solve): a fresh process must register
# LAPACK's custom-call targets before it runs the loaded executable, or it would crash.
LAPACK = PRELUDE + r"""
import jax.numpy as jnp
prog = persistent.PersistentProgram(lambda A, b: (jnp.linalg.solve(A, b),), "lapack_test")
x, = prog(jnp.array([[4.0, 1.0], [1.0, 3.0]]), jnp.array([1.0, 2.0]))
print(json.dumps({"x": [float(v) for v in x], "compiled": compiled}))
"""


def test_stored_program_calling_lapack_loads_in_a_fresh_process(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "CRANK_JAX_NO_CACHE"}
    runs = []
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", LAPACK, str(tmp_path)], env=env,
                             capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    assert runs[0]["compiled"] == ["lapack_test"] and runs[1]["compiled"] == []
    assert runs[0]["x"] == runs[1]["x"]
    assert abs(runs[0]["x"][0] - 1 / 11) < 1e-15 and abs(runs[0]["x"][1] - 7 / 11) < 1e-15
