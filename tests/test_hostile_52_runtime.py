"""Hostile inputs on the runtime's surfaces: the store's test of "our code" by file
location, a varied parameter with no effect, the trajectories' manifest checksummed, two
outputs that are one file, read-only outputs under root, and the API refusing what the
command line refuses (`run_sweep(n=)`, `demo_record(seed)`, `initialize_distributed`)."""

from __future__ import annotations

import importlib
import importlib.util
import os
import re
import sys
import time

import jax.numpy as jnp
import numpy as np
import pytest

from crank_jax.runtime import persistent
from crank_jax.runtime.foreign_code import foreign_classes

# --- the store's "our code" is decided by file location -----------------------------------

LOAD = """
import jax.numpy as jnp
import numpy as np
from crank_jax.model.loads import AbstractLoad

GAIN = 0.1

class Torque(AbstractLoad):
    a: float

    def __call__(self, t):
        return GAIN * self.a * jnp.sin(t)

    def mean(self):
        return jnp.asarray(0.0)
"""


def _write_module(tmp_path, name):
    path = tmp_path / f"{name}.py"
    path.write_text(LOAD)
    old = time.time() - 3600  # as a module written before this process started
    os.utime(path, (old, old))
    return path


@pytest.mark.parametrize("name", ["profile", "trace"])
def test_a_user_load_in_a_module_named_like_the_standard_library_is_foreign(
        tmp_path, monkeypatch, name):
    """A user's "torque profile" in `profile.py`, imported through `sys.path`, counted as
    the standard library's by its name: its program was stored, and a second process with
    another `GAIN` got the first one's trajectory."""
    _write_module(tmp_path, name)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    monkeypatch.delitem(sys.modules, name, raising=False)
    importlib.invalidate_caches()
    module = importlib.import_module(name)
    assert module.__file__.startswith(str(tmp_path))
    load = module.Torque(2.0)
    assert foreign_classes((), [load]) == {module.Torque}
    assert persistent._signature("user_load", (load, jnp.zeros(3)))[0] is None


def test_a_user_class_under_a_loaded_standard_module_name_is_foreign(tmp_path, monkeypatch):
    """The standard library's `profile` is the one in `sys.modules`, the user's module is
    loaded from its file under the same name: its methods' file gives it away."""
    import profile  # noqa: F401  the real one, loaded first

    path = _write_module(tmp_path, "profile")
    spec = importlib.util.spec_from_file_location("profile", path)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    spec.loader.exec_module(module)
    assert module.Torque.__module__ == "profile"
    assert foreign_classes((), [module.Torque(1.0)]) == {module.Torque}


def test_the_librarys_own_and_pinned_classes_stay_known():
    """Crank-jax's classes, the pinned libraries' and Python's own stay stored."""
    import jax

    import crank_jax as cj

    scene = cj.load_scene("lab-rig")
    leaves = [cj.NoLoad(), cj.HarmonicLoad(0.0, 1.0, 2.0), jnp.float64, (1, "a"),
              frozenset(), jax.numpy.zeros(2).dtype]
    assert foreign_classes((), leaves) == set()
    assert foreign_classes((jax.tree.structure(scene),), []) == set()


# --- a varied parameter with no effect is refused --------------------------------------------

@pytest.fixture(scope="module")
def lab_rig():
    import crank_jax as cj

    return cj.load_scene("lab-rig")  # no [load], no [torque], no friction


@pytest.mark.parametrize("samples, name", [
    # the made-up tone has frequency 0: tau1 sin(0) = 0 in every sample
    ({"tau1": "uniform(0,0.1)"}, "tau1"),
    ({"P1": "normal(1,0.1)"}, "P1"),
    ({"tau_freq_hz": "uniform(1,3)"}, "tau_freq_hz"),  # a tone of zero amplitude
    ({"P_phase": "uniform(0,3)", "P1": "const(0)"}, "P_phase"),
    ({"w_c": "uniform(0.01,0.1)"}, "w_c"),  # the width of a Coulomb friction T_c = 0
    ({"k": "normal(2,0.1)", "w_s": "uniform(0.01,0.1)"}, "w_s"),
])
def test_a_varied_parameter_with_no_effect_is_refused(lab_rig, samples, name):
    from crank_jax.sweep.plan import make_plan

    with pytest.raises(ValueError, match=rf"cannot vary '{name}': it has no effect on this "
                                         "scene"):
        make_plan(lab_rig, samples, ("peak_phi",), n=2)


@pytest.mark.parametrize("samples", [
    {"tau1": "uniform(0,0.1)", "tau_freq_hz": 2.0},
    {"tau1": "uniform(0,0.1)", "tau_phase": "uniform(0.1,1)"},  # a constant X1 sin(phase)
    {"P1": "normal(1,0.1)", "P_freq_hz": "uniform(1,2)", "P_phase": 0.0},
    {"w_c": "uniform(0.01,0.1)", "T_c": "uniform(0,0.01)"},
    {"P0": "const(0)", "tau0": 0.1},  # a mean always acts (a zero mean is the user's value)
])
def test_a_varied_parameter_that_acts_is_planned(lab_rig, samples):
    from crank_jax.sweep.plan import make_plan

    assert make_plan(lab_rig, samples, ("peak_phi",), n=2).n == 2


def test_cli_sweep_refuses_a_varied_parameter_with_no_effect(tmp_path, capsys):
    from crank_jax import cli

    out = tmp_path / "x.npz"
    argv = ["sweep", "lab-rig", "--vary", "tau1=uniform(0,0.1)", "--n", "2", "--out",
            str(out), "--quiet"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot vary 'tau1'" in err
    assert "tau_freq_hz or tau_phase too" in err and not out.exists()


# --- saved trajectories: the manifest is checksummed -----------------------------------------

@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A finished store of two chunks, written by the sweep's own writer (no solve)."""
    from crank_jax.sweep.trajectories import TrajectoryStore

    path = tmp_path_factory.mktemp("traj") / "tr"
    store = TrajectoryStore(path, {"plan": "stand-in"}, np.linspace(0.0, 0.2, 5), 1, 3)
    rows = np.arange(15.0).reshape(3, 5)
    for start, idx in ((0, np.array([0, 1])), (2, np.array([2]))):
        store.save(0, start, idx, {"phi": rows[idx], "dphi": -rows[idx]})
        store.chunks.append((0, start))
    store.finish()
    return path


def _edit(doc, key):
    if key == "ts":
        doc["ts"] = [2.0 * t for t in doc["ts"]]  # the same length, other times
    elif key == "n":
        doc["n"] += 1
    elif key == "chunks":
        doc["chunks"] = doc["chunks"][::-1]
    elif key == "units":
        doc["units"]["ts"] = "ms"
    elif key == "sha256":
        del doc["sha256"]


@pytest.mark.parametrize("key", ["ts", "n", "chunks", "units", "sha256"])
def test_an_edited_trajectory_manifest_is_refused(saved, tmp_path, key):
    """The chunk files were checksummed, the manifest was not: its edited `ts` were
    served as the sweep's save times."""
    import json
    import shutil

    import crank_jax as cj

    good = cj.load_trajectories(saved)
    assert good.ts.shape == (5,) and good.ts[-1] == pytest.approx(0.2)
    np.testing.assert_array_equal(good[[2, 0]]["phi"], [np.arange(10.0, 15.0), np.arange(5.0)])
    copy = tmp_path / "tr"
    shutil.copytree(saved, copy)
    doc = json.loads((copy / "manifest.json").read_text())
    _edit(doc, key)
    (copy / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"manifest.json' are damaged or were edited"):
        cj.load_trajectories(copy)


# --- a read-only output is kept, also for root -----------------------------------------------

@pytest.mark.parametrize("mode", [0o444, 0o400, 0o000])
def test_a_read_only_output_is_never_replaced_even_by_root(tmp_path, mode):
    """The check relied on `os.access`, which root passes for any file: run as root (as
    here), a file made read-only was replaced."""
    from crank_jax.runtime.io import atomic_write, check_output

    ro = tmp_path / "ro.csv"
    ro.write_text("keep\n")
    ro.chmod(mode)
    with pytest.raises(ValueError, match=r"^output path .* exists and is read-only"):
        check_output(ro)
    with pytest.raises(ValueError, match=r"^--out .* exists and is read-only"):
        check_output(ro, option="--out")
    with pytest.raises(PermissionError, match="exists and is read-only"):
        with atomic_write(ro) as f:
            f.write("lost")
    link = tmp_path / "link.csv"
    link.symlink_to(ro)  # written through to its target: the same refusal
    with pytest.raises(PermissionError, match="read-only"):
        with atomic_write(link) as f:
            f.write("lost")
    ro.chmod(0o600)
    assert ro.read_text() == "keep\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.csv", "ro.csv"]


def test_cli_refuses_a_read_only_output_even_as_root(tmp_path, capsys):
    from crank_jax import cli

    ro = tmp_path / "ro.csv"
    ro.write_text("keep\n")
    ro.chmod(0o444)
    assert cli.main(["simulate", "lab-rig", "--out", str(ro)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "read-only" in err and "--out" in err
    ro.chmod(0o600)
    assert ro.read_text() == "keep\n"


# --- two outputs that are one file are refused before any work --------------------------------

# command line (with a "{data}" record file), the two options made to collide, and further
# options each command needs
_TWO_OUTPUTS = {
    "validate": (["validate", "lab-rig", "{data}", "--quiet"], "--out", "--plot", []),
    "validate-report": (["validate", "lab-rig", "{data}", "--quiet"], "--out", "--report",
                        []),
    "posterior": (["posterior", "{data}", "lab-rig"], "--out", "--plot", []),
    "design": (["design", "lab-rig", "--free", "k,c", "--t1", "1", "--rate", "100",
                "--torque-amplitude", "0.1"], "--scene-out", "--out", ["--plot", "d.png"]),
    "design-plot": (["design", "lab-rig", "--free", "k,c", "--t1", "1", "--rate", "100",
                     "--torque-amplitude", "0.1"], "--out", "--plot",
                    ["--scene-out", "d.toml"]),
    "response": (["response", "lab-rig", "--freq", "3:5"], "--out", "--plot", []),
    "stability": (["stability", "lab-rig", "--load-amplitude", "0:10", "--freq", "1:2"],
                  "--out", "--plot", []),
    "fit": (["fit", "{data}", "pendulum", "--free", "c", "--quiet"], "--out", "--plot", []),
    "fit-report": (["fit", "{data}", "pendulum", "--free", "c", "--quiet"], "--report",
                   "--scene-out", []),
    "simulate": (["simulate", "lab-rig"], "--out", "--plot", []),
    "sweep": (["sweep", "lab-rig", "--n", "2", "--quiet"], "--out", "--checkpoint", []),
}


@pytest.mark.parametrize("how", ["dot", "symlink", "hardlink"])
@pytest.mark.parametrize("command", list(_TWO_OUTPUTS))
def test_two_outputs_that_are_one_file_are_refused(tmp_path, capsys, monkeypatch, command,
                                                   how):
    """`./x` and `x`, a symbolic link and its target, two hard links: one file, which the
    output written last replaced (a JSON result by the figure, a TOML by the JSON)."""
    from crank_jax import cli

    monkeypatch.chdir(tmp_path)
    (tmp_path / "data.csv").write_text("t,phi\n0,0\n0.1,0\n")
    argv, first, second, more = _TWO_OUTPUTS[command]
    argv = [a.replace("{data}", "data.csv") for a in argv] + more
    name = "o.png"  # every output here may have a figure's suffix
    (tmp_path / name).write_text("keep\n")
    other = {"dot": f"./{name}", "symlink": "link.png", "hardlink": "hard.png"}[how]
    if how == "symlink":
        (tmp_path / other).symlink_to(tmp_path / name)
    elif how == "hardlink":
        os.link(tmp_path / name, tmp_path / other)
    before = sorted(p.name for p in tmp_path.iterdir())
    t = time.perf_counter()
    assert cli.main(argv + [first, name, second, other]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and ("same file" in err or "same path" in err), err
    assert first in err and second in err, err
    assert time.perf_counter() - t < 30  # refused before the work
    assert (tmp_path / name).read_text() == "keep\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_same_file_cases(tmp_path, monkeypatch):
    from crank_jax.runtime.io import same_file

    monkeypatch.chdir(tmp_path)
    assert same_file("x", "./x") and same_file("x", str(tmp_path / "sub" / ".." / "x"))
    (tmp_path / "x").write_text("a")
    (tmp_path / "l").symlink_to("x")
    os.link("x", "h")
    assert same_file("l", "x") and same_file("h", "x") and same_file("h", "l")
    (tmp_path / "dangling").symlink_to("y")  # a link to an output not yet written
    assert same_file("dangling", "y")
    (tmp_path / "y2").write_text("a")
    assert not same_file("x", "y2") and not same_file("x", "y")


# --- the API refuses what the command line refuses --------------------------------------------

@pytest.mark.parametrize("kw, words", [
    ({"n": 2.5}, "n must be an integer >= 1, got 2.5"),  # ran 2 samples
    ({"n": 2.0}, "n must be an integer"),
    ({"n": True}, "n must be an integer"),
    ({"n": 0}, "n must be an integer >= 1"),
    ({"seed": 1.5}, "seed must be an integer from 0 to"),
    ({"seed": 2**63}, "seed must be an integer from 0 to"),
    ({"seed": -1}, "seed must be an integer from 0 to"),
    ({"num_saves": 10.5}, "num_saves must be an integer >= 2"),
    ({"chunk_size": 1.5}, "chunk_size must be an integer >= 1"),
    ({"max_steps": 1.5}, "max_steps must be an integer >= 1"),
    ({"max_steps": 0}, "max_steps must be an integer >= 1"),
    ({"trajectory_every": 1.5, "save_trajectories": "unused"}, "trajectory_every must be"),
    ({"max_memory": 1e9}, "max_memory must be an integer"),
    ({"t1": float("inf")}, "finite t1 > 0"),
])
def test_run_sweep_refuses_what_the_cli_refuses(lab_rig, tmp_path, kw, words):
    import crank_jax as cj

    kw = {"n": 2, **kw}
    if "save_trajectories" in kw:
        kw["save_trajectories"] = tmp_path / "tr"
    with pytest.raises(ValueError, match=re.escape(words)):
        cj.run_sweep(lab_rig, {"k": "normal(2,0.1)"}, ("peak_phi",), **kw)
    assert not (tmp_path / "tr").exists()


def test_integer_arguments_of_numpy_types_are_taken(lab_rig):
    from crank_jax.sweep.plan import make_plan

    plan = make_plan(lab_rig, {"k": "normal(2,0.1)"}, ("peak_phi",), n=np.int64(3),
                     seed=np.uint64(2**63 - 1), num_saves=np.int32(5))
    assert plan.n == 3 and plan.seed == 2**63 - 1 and plan.ts.shape == (5,)


@pytest.mark.parametrize("seed", [2**63, -1, 1.5, True, "1"])
def test_demo_record_refuses_a_seed_the_cli_refuses(seed):
    from crank_jax.identify.demo import demo_record

    with pytest.raises(ValueError, match=r"demo_record: seed must be an integer from 0 to "
                                         r"9223372036854775807"):
        demo_record(seed)


_JOIN = """
import json, os, sys, time
import crank_jax as cj
for kw, env in json.loads(sys.argv[1]):
    for k in [k for k in os.environ if k.startswith("JAX_")]:
        del os.environ[k]
    os.environ.update(env)
    t = time.perf_counter()
    try:
        cj.sweep.initialize_distributed(**kw, initialization_timeout=5)
        what = "JOINED"
    except Exception as e:
        what = type(e).__name__ + " " + (str(e).splitlines() or [""])[0]
    print(json.dumps([what, time.perf_counter() - t]), flush=True)
"""

_BAD_CLUSTERS = [
    ({"coordinator_address": "nohost", "num_processes": 1, "process_id": 0}, {},
     "coordinator_address='nohost': expected 'HOST:PORT'"),  # IndexError
    ({"coordinator_address": "localhost:99999", "num_processes": 1, "process_id": 0}, {},
     "coordinator_address='localhost:99999'"),  # joined
    ({"coordinator_address": "localhost:0", "num_processes": 1, "process_id": 0}, {},
     "coordinator_address='localhost:0'"),
    ({"num_processes": 0, "process_id": 0, "coordinator_address": "localhost:1234"}, {},
     "num_processes=0: expected an integer >= 1"),
    ({}, {"JAX_COORDINATOR_ADDRESS": "localhost:1234", "JAX_NUM_PROCESSES": "2",
          "JAX_PROCESS_ID": "2"},
     "environment variable JAX_PROCESS_ID=2 must be below environment variable "
     "JAX_NUM_PROCESSES=2"),
    ({"coordinator_address": ":1234", "num_processes": 1, "process_id": 0}, {},
     "coordinator_address=':1234'"),  # aborted the process: last
]


def test_initialize_distributed_refuses_a_bad_cluster_at_once():
    """Refused in the library as the CLI refuses it (in 2 s): JAX raised IndexError,
    joined a port that cannot exist, aborted the process, or waited minutes."""
    import json
    import subprocess

    cases = json.dumps([[kw, env] for kw, env, _ in _BAD_CLUSTERS])
    out = subprocess.run([sys.executable, "-c", _JOIN, cases], capture_output=True,
                         text=True, timeout=120)
    lines = [json.loads(x) for x in out.stdout.splitlines() if x.startswith("[")]
    assert len(lines) == len(_BAD_CLUSTERS), out.stdout + out.stderr[-2000:]
    for (what, seconds), (_, _, words) in zip(lines, _BAD_CLUSTERS):
        assert what.startswith(f"ValueError {words}"), what
        assert seconds < 2.0


def test_initialize_distributed_without_its_coordinator_raises_instead_of_aborting():
    """Process 1 whose coordinator never answers: JAX aborted the Python process (a C++
    stack dump, no exception) after `initialization_timeout`; now a `RuntimeError` that
    names the address."""
    import json
    import socket
    import subprocess

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    kw = {"coordinator_address": f"127.0.0.1:{port}", "num_processes": 2, "process_id": 1}
    cases = json.dumps([[kw, {}]])
    out = subprocess.run([sys.executable, "-c", _JOIN, cases], capture_output=True,
                         text=True, timeout=120)
    lines = [json.loads(x) for x in out.stdout.splitlines() if x.startswith("[")]
    assert out.returncode == 0 and len(lines) == 1, out.stdout + out.stderr[-2000:]
    what, seconds = lines[0]
    assert what.startswith(f"RuntimeError coordinator_address='127.0.0.1:{port}': process 0 "
                           "(the coordinator) did not answer within 5 s"), what
    assert seconds < 30
