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
from conftest import flip_byte as _flip

# A fresh interpreter with the store in the directory argv[1], counting in `compiled` the
# programs it compiles (rather than loads).
PRELUDE = r"""
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
import crank_jax as cj
from crank_jax.runtime import persistent
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
    """Issue 24 defect 1: a damaged stored program, whatever byte is damaged, is a miss:
    the next process recompiles it, gets the clean numbers, and replaces the file. A
    dangling `*.xla` link and a temporary file left by a killed writer do no harm."""
    from crank_jax.runtime.program_store import MAGIC, STALE_TEMP_S, unpack

    cache, first = stored
    copy = tmp_path / "cache"
    store = copy / "crank-jax-programs"
    store.mkdir(parents=True)
    count = len(MAGIC) + 64  # the output count's first byte
    damages = {  # by program: the cases on the programs they were seen on
        "simulate": _flip(-40),  # a flip near the end: wrong phi with exit 0, or SIGSEGV
        "jacobian": _flip(count),  # "Too few leaves for PyTreeDef" on every run
        "linearize": lambda b: b + b"\0",
    }
    others = [lambda b: b[: len(b) // 2], lambda b: b"\0garbage" * 100, lambda b: b"",
              lambda b: b[:4], _flip(len(MAGIC) + 80)]
    files = sorted((cache / "crank-jax-programs").glob("*.xla"))
    assert len(files) >= 4
    for i, p in enumerate(files):
        damage = damages.get(p.name.split("-")[0], others[i % len(others)])
        (store / p.name).write_bytes(damage(p.read_bytes()))
    (store / "dangling.xla").symlink_to(tmp_path / "gone.xla")
    stale = store / f".{files[0].name}.x1y2z3.tmp"
    stale.write_bytes(b"partial")
    old = os.stat(stale).st_mtime - STALE_TEMP_S - 60
    os.utime(stale, (old, old))
    again = _run(copy)
    assert again["values"] == first["values"] and again["stderr"] == first["stderr"]
    assert again["sim"] == first["sim"]
    assert set(again["compiled"]) == {p.name.split("-")[0] for p in files}
    for p in files:  # every damaged file replaced by an intact one
        blob = (store / p.name).read_bytes()
        unpack(blob, blob[len(MAGIC):len(MAGIC) + 64].decode())
    assert not stale.exists()


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


# Issue 26 item 6 and issue 37 item 1: a user's load and force classes (a module file of
# their own) whose code reads a module global set from outside (here an environment
# variable). The program holds the code as traced, so a store keyed on the source gave the
# second run the first run's executable: the first run's trajectory. Nothing holding a
# user's class is stored; its compilation is JAX's persistent cache's.
USER_LOAD = """
import os
import jax.numpy as jnp
import equinox as eqx
from crank_jax.model.loads import AbstractLoad

GAIN = float(os.environ["USER_GAIN"])

class Push(AbstractLoad):
    a: float

    def __call__(self, t):
        return GAIN * self.a * jnp.sin(t)

    def mean(self):
        return jnp.asarray(0.0)

class Drag(eqx.Module):
    c: float

    def __call__(self, t, phi, dphi):
        return -GAIN * self.c * dphi
"""

USER_SCRIPT = PRELUDE + r"""
sys.path.insert(0, sys.argv[2])
import numpy as np
import userload
mech = cj.load_scene("lab-rig").mech
ts = np.linspace(0.0, 0.5, 11)
load = cj.simulate(mech, 0.3, 0.0, ts, load=userload.Push(a=40.0))
force = cj.simulate(mech, 0.3, 0.0, ts, force=userload.Drag(c=0.5))
print(json.dumps({"phi": [float(load.phi[-1]), float(force.phi[-1])],
                  "compiled": sorted(compiled)}))
"""


@pytest.mark.slow  # three fresh processes, each tracing and compiling: ~2 min when loaded
def test_user_classes_are_traced_in_every_process(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "CRANK_JAX_NO_CACHE"}
    code = tmp_path / "code"
    code.mkdir()
    (code / "userload.py").write_text(USER_LOAD)

    def run(gain: str, cache: str = "cache") -> dict:
        out = subprocess.run([sys.executable, "-c", USER_SCRIPT, str(tmp_path / cache),
                              str(code)], env=env | {"USER_GAIN": gain},
                             capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        return json.loads(out.stdout.strip().splitlines()[-1])

    first = run("0.1")
    gain = run("0.5")  # the same source, another global
    fresh = run("0.5", "fresh-cache")
    assert gain["phi"] == fresh["phi"], "the store gave the first run's program"
    assert gain["phi"][0] != first["phi"][0] and gain["phi"][1] != first["phi"][1]
    # Only crank-jax's own programs (e.g. the solver policy's) are stored.
    assert not list((tmp_path / "cache" / "crank-jax-programs").glob("simulate-*.xla"))


# Issue 26: a fit on one of diffrax's explicit solvers. Its programs saved through
# `SaveAt(ts)`, whose check of the save times is a host callback, so they were compiled in
# every process; they now save inside the steps (solve/saves.py) and are stored, as is
# `synthesize`'s simulation (host mode, forward mode's program). argv[1]:
# the cache directory, or "-" for none (a plain compile, no store).
DIFFRAX_FIT = PRELUDE.replace("cj.enable_compilation_cache(sys.argv[1])", """
if sys.argv[1] != "-":
    cj.enable_compilation_cache(sys.argv[1])""") + r"""
import dataclasses
scene = dataclasses.replace(cj.load_scene("lab-rig"), solver="dopri5")
data = cj.synthesize(scene, t1=2.0, rate=100.0, noise_std=1e-3, seed=1)
res = cj.fit(scene, data, free=("k", "c", "phi0", "dphi0"), init={"k": 2.4},
             progress=False)
print(json.dumps({"values": {n: float(v) for n, v in res.values.items()},
                  "stderr": {n: float(v) for n, v in res.stderr.items()},
                  "converged": bool(res.converged), "compiled": sorted(compiled)}))
"""


def test_fit_on_a_diffrax_solver_is_stored_and_loaded(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "CRANK_JAX_NO_CACHE"}

    def run(cache: str) -> dict:
        out = subprocess.run([sys.executable, "-c", DIFFRAX_FIT, cache], env=env,
                             capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr[-2000:]
        return json.loads(out.stdout.strip().splitlines()[-1])

    cache = tmp_path / "cache"
    first = run(str(cache))
    assert first["converged"] and "jacobian" in first["compiled"]
    assert list((cache / "crank-jax-programs").glob("jacobian-*.xla"))
    second = run(str(cache))
    # The fit's programs, and the simulation that made its data (host mode) are loaded.
    assert "simulate" in first["compiled"]
    assert not {"jacobian", "simulate"} & set(second["compiled"]), second["compiled"]
    plain = run("-")
    assert plain["compiled"] == []  # no store: nothing goes through `_compile`
    # Loaded, stored-on-compile and plainly compiled programs: the same numbers.
    assert second["values"] == first["values"] == plain["values"]
    assert second["stderr"] == first["stderr"] == plain["stderr"]


def test_the_key_holds_all_of_crank_jax_source():
    # The traced code is anywhere in the package (the fleet's LM in fleet/, the fit's in
    # identify/): a key over runtime/ alone loaded a changed program as stored before.
    import crank_jax
    from crank_jax.runtime import persistent

    root = Path(crank_jax.__file__).resolve().parent
    assert persistent.SOURCE == root
    assert root / "fleet" / "batch_lm.py" in set(persistent.SOURCE.rglob("*.py"))


def test_loaded_programs_are_bounded_and_an_evicted_one_loads_again(tmp_path):
    # Each loaded executable holds ~210 memory mappings, and a process may hold 65530:
    # the loaded set is bounded. With room for one, two shapes called in turn evict each
    # other; each comes back from the store (no compile), with the same numbers.
    script = PRELUDE + r"""
import numpy as np
from crank_jax.runtime import program_store
program_store.LOADED.limit = 1
mech = cj.load_scene("lab-rig").mech
out = [float(np.sum(cj.simulate(mech, 1.0, 0.0, np.linspace(0, 1, n)).phi))
       for n in (50, 60, 50, 60)]
print(json.dumps({"phi": out, "compiled": compiled, "loaded": len(program_store.LOADED)}))
"""
    env = {k: v for k, v in os.environ.items() if k != "CRANK_JAX_NO_CACHE"}
    out = subprocess.run([sys.executable, "-c", script, str(tmp_path)], env=env,
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["loaded"] == 1 and got["compiled"].count("simulate") == 2, got
    assert got["phi"][0] == got["phi"][2] != got["phi"][1] == got["phi"][3]
