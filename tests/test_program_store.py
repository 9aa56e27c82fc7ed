"""The program store's files (`program_store.py`, `foreign_code.py`, issue 24 defect 1 and
issue 26 item 6), in this process: a damaged entry, whatever byte is damaged, is detected
before it is deserialised, discarded and compiled anew, with the clean result; eviction
survives links and FIFOs; no temporary file outlives its writer; a program holding a
class from outside crank-jax is never stored (issue 37 item 1).

The store is switched on here by pointing `persistent.program_store_dir` at a temporary
directory (the test process otherwise runs without one). Fresh-process cases are in
test_persistent.py.
"""

from __future__ import annotations

import importlib
import os
import signal
import stat
import subprocess
import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import flip_byte as _flip

import crank_jax as cj
from crank_jax.model.loads import AbstractLoad
from crank_jax.runtime import persistent, program_store
from crank_jax.runtime.foreign_code import foreign_classes
from crank_jax.runtime.io import atomic_write
from crank_jax.runtime.program_store import MAGIC, Entry

_X = jnp.linspace(0.0, 1.0, 7)
_W = jnp.asarray(1.5)


def _fn(x, w):
    # Three outputs: a changed output count in the header must not go unnoticed.
    return jnp.sin(x) * w, jnp.cumsum(x) ** 2, jnp.sum(x * w)


class Counted(persistent.PersistentProgram):
    """A program that counts its compilations (a load is not one)."""

    def __init__(self, fn=_fn, name="store_test"):
        super().__init__(fn, name)
        self.compiled = 0

    def _compile(self, *args):
        self.compiled += 1
        return super()._compile(*args)


@pytest.fixture
def store(tmp_path, monkeypatch):
    d = tmp_path / "programs"
    monkeypatch.setattr(persistent, "program_store_dir", lambda: d)
    return d


def _only(store):
    (path,) = store.glob("*.xla")
    return path


def _key(blob: bytes) -> str:
    return blob[len(MAGIC):len(MAGIC) + 64].decode()


_OUT = len(MAGIC) + 64  # the output count's first byte
DAMAGES = {
    "magic": _flip(0),
    "key": _flip(len(MAGIC) + 5),
    "output count": _flip(_OUT),  # 3 outputs read as 2 ("Too few leaves for PyTreeDef")
    "lapack flag": _flip(_OUT + 4),
    "device count": _flip(_OUT + 5),
    "first payload byte": _flip(_OUT + 6),
    "middle": lambda b: _flip(len(b) // 2)(b),
    "last payload byte": _flip(-33),
    "near the end": _flip(-40),  # the flips: wrong numbers or SIGSEGV before
    "digest": _flip(-1),
    "truncated by one": lambda b: b[:-1],
    "truncated to half": lambda b: b[:len(b) // 2],
    "header only": lambda b: b[:_OUT + 6],
    "empty": lambda b: b"",
    "appended byte": lambda b: b + b"\0",
    "appended copy": lambda b: b + b,
}


def _clean(store):
    """(the clean outputs, the stored file's bytes) from a first, compiling call."""
    prog = Counted()
    out = prog(_X, _W)
    assert prog.compiled == 1
    return out, _only(store).read_bytes()


def _check_recompiled(store, clean, damaged: bytes):
    """A fresh program (as in a fresh process) over the damaged store: the clean result,
    one compilation, and an intact file in place of the damaged one."""
    prog = Counted()
    out = prog(_X, _W)
    assert prog.compiled == 1, "a damaged program was loaded"
    assert len(out) == len(clean)
    for a, b in zip(out, clean):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    blob = _only(store).read_bytes()
    assert blob != damaged
    program_store.unpack(blob, _key(blob))  # intact again
    again = Counted()
    again(_X, _W)
    assert again.compiled == 0, "the replaced program was not loaded"


@pytest.mark.parametrize("damage", list(DAMAGES), ids=list(DAMAGES))
def test_damaged_program_is_discarded_and_recompiled(store, damage):
    clean, blob = _clean(store)
    damaged = DAMAGES[damage](blob)
    assert damaged != blob
    _only(store).write_bytes(damaged)
    _check_recompiled(store, clean, damaged)


def test_an_intact_file_of_another_key_is_a_miss(store):
    clean, blob = _clean(store)
    entry = program_store.unpack(blob, _key(blob))
    other = program_store.pack("0" * 64, entry)
    _only(store).write_bytes(other)
    _check_recompiled(store, clean, other)


@pytest.mark.parametrize("bad", ["garbage executable", "wrong output count", "no outputs",
                                 "more devices"])
def test_intact_program_that_cannot_load_or_run_is_recompiled(store, bad):
    """A stored program with a valid digest that still cannot be loaded or run (another
    build, a stale layout) is recompiled, never a crash."""
    clean, blob = _clean(store)
    key = _key(blob)
    e = program_store.unpack(blob, key)
    entry = {"garbage executable": e._replace(payload=b"\x00not an executable" * 50),
             "wrong output count": e._replace(n_out=2),
             "no outputs": e._replace(n_out=0),
             "more devices": e._replace(n_dev=200)}[bad]
    _only(store).write_bytes(program_store.pack(key, entry))
    _check_recompiled(store, clean, program_store.pack(key, entry))


def test_every_header_and_length_damage_fails_the_digest():
    """Every single-bit flip of a small entry, and every truncation and extension, is
    refused by `unpack` (the check that runs before any deserialisation)."""
    key = "ab" * 32
    blob = program_store.pack(key, Entry(3, True, 1, bytes(range(40))))
    assert program_store.unpack(blob, key) == Entry(3, True, 1, bytes(range(40)))
    variants = [blob[:n] for n in range(len(blob))] + [blob + b"\0", blob + blob]
    for i in range(len(blob)):
        for bit in range(8):
            b = bytearray(blob)
            b[i] ^= 1 << bit
            variants.append(bytes(b))
    for v in variants:
        with pytest.raises(ValueError):
            program_store.unpack(v, key)


def _program_files(n, store):
    for i in range(n):
        key = f"{i:064x}"
        program_store.write(store / f"p-{key[-32:]}.xla",
                            program_store.pack(key, Entry(1, False, 1, b"x" * 10)))
        t = 1e9 + i  # distinct, increasing use times
        os.utime(store / f"p-{key[-32:]}.xla", (t, t))


def test_eviction_keeps_the_cap_despite_links_fifos_and_directories(tmp_path):
    store = tmp_path / "programs"
    store.mkdir()
    (store / "dangling.xla").symlink_to(tmp_path / "gone.xla")
    (store / "dir.xla").mkdir()
    os.mkfifo(store / "fifo.xla")
    cap = program_store.MAX_PROGRAMS
    _program_files(cap + 5, store)
    regular = [p for p in store.glob("*.xla") if p.is_file() and not p.is_symlink()]
    assert len(regular) == cap
    # The most recently used are kept.
    assert min(int(p.stem[2:], 16) for p in regular) == 5


def test_links_and_fifos_at_a_programs_path_are_replaced_never_followed(tmp_path):
    store = tmp_path / "programs"
    store.mkdir()
    key = "cd" * 32
    blob = program_store.pack(key, Entry(1, False, 1, b"y" * 10))
    link, fifo = store / "link.xla", store / "fifo.xla"
    link.symlink_to(tmp_path / "target.xla")
    os.mkfifo(fifo)
    t = time.perf_counter()
    assert program_store.read(fifo, key) is None  # never waits for a writer
    assert program_store.read(link, key) is None
    assert time.perf_counter() - t < 5
    program_store.write(link, blob)
    program_store.write(fifo, blob)
    assert not (tmp_path / "target.xla").exists()
    for p in (link, fifo):
        assert stat.S_ISREG(os.lstat(p).st_mode)
        assert program_store.read(p, key) == program_store.unpack(blob, key)


def test_stale_temporary_files_are_removed_and_fresh_ones_kept(tmp_path):
    store = tmp_path / "programs"
    store.mkdir()
    stale, fresh = store / ".p-1.xla.k3j2.tmp", store / ".p-2.xla.a8d0.tmp"
    for p in (stale, fresh):
        p.write_bytes(b"partial")
    old = time.time() - program_store.STALE_TEMP_S - 60
    os.utime(stale, (old, old))
    _program_files(1, store)
    assert not stale.exists() and fresh.exists()


def test_a_failed_write_leaves_no_temporary_file(tmp_path, monkeypatch):
    store = tmp_path / "programs"

    def fail(*a):
        raise OSError("disk full")

    monkeypatch.setattr(program_store.os, "replace", fail)
    program_store.write(store / "p.xla", b"data")  # not an error
    assert list(store.iterdir()) == []


# --- classes from outside crank-jax (issue 37 item 1) ----------------------------------

LOAD = """
import equinox as eqx
import jax
import jax.numpy as jnp
from crank_jax.model.loads import AbstractLoad

GAIN = 0.1

class Pulse(AbstractLoad):
    a: float

    def __call__(self, t):
        return GAIN * self.a * jnp.sin(t)

    def mean(self):
        return jnp.asarray(0.0)
"""


def _user_module(tmp_path, monkeypatch, name):
    """Module `name` in `tmp_path`, with class `Pulse` whose load reads the module global
    `GAIN`, imported afresh (and removed from `sys.modules` after the test)."""
    (tmp_path / f"{name}.py").write_text(LOAD)
    old = time.time() - 3600  # as a module written before this process started
    os.utime(tmp_path / f"{name}.py", (old, old))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    monkeypatch.delitem(sys.modules, name, raising=False)
    importlib.invalidate_caches()
    return importlib.import_module(name)


def _load_program():
    """A fresh program, as in a fresh process (nothing in memory, the same store)."""
    return Counted(lambda load, t: (load(t),), "user_load")


def test_a_user_class_reading_a_global_is_never_stored(store, tmp_path, monkeypatch):
    """The issue's case: a load whose `__call__` reads a module global gave the first
    run's result after the global changed (its source, the old key, did not change)."""
    t = jnp.linspace(0.0, 1.0, 5)
    module = _user_module(tmp_path, monkeypatch, "user_load_gain")
    (first,) = _load_program()(module.Pulse(2.0), t)
    np.testing.assert_allclose(first, 0.2 * np.sin(np.asarray(t)), rtol=1e-15)
    monkeypatch.setattr(module, "GAIN", 0.5)  # e.g. read from a configuration file
    (second,) = _load_program()(module.Pulse(2.0), t)
    np.testing.assert_allclose(second, 1.0 * np.sin(np.asarray(t)), rtol=1e-15)
    assert not list(store.glob("*.xla"))
    assert persistent._signature("user_load", (module.Pulse(2.0), t))[0] is None


def _factory(gain: float):
    class Scaled(AbstractLoad):  # one source, a closure value of its own
        def __call__(self, t):
            return gain * t

        def mean(self):
            return jnp.asarray(0.0)

    return Scaled


def test_two_classes_from_one_factory_get_their_own_programs(store):
    """Same source, same name, another closure value: one process, one program object."""
    t = jnp.linspace(0.0, 1.0, 5)
    prog = _load_program()
    (one,) = prog(_factory(1.0)(), t)
    (three,) = prog(_factory(3.0)(), t)
    np.testing.assert_allclose(one, np.asarray(t), rtol=1e-15)
    np.testing.assert_allclose(three, 3.0 * np.asarray(t), rtol=1e-15)
    assert not list(store.glob("*.xla")) and prog.compiled == 0


class _Holder(eqx.Module):
    """Stands for a module of crank-jax's whose static field holds a user's object."""

    __module__ = "crank_jax.model.loads"
    inner: object = eqx.field(static=True)


def test_a_user_object_anywhere_in_static_data_is_found():
    """Not only the pytree's own nodes: inside containers and other modules' static
    fields (an object with no address in its repr would otherwise be keyed by it)."""
    user = _factory(2.0)()
    assert foreign_classes((), [{"a": (1, [user])}]) == {type(user)}
    assert foreign_classes((jax.tree.structure(_Holder(user)),), []) == {type(user)}
    assert foreign_classes((jax.tree.structure(_Holder({"x": (1.0, "a")})),),
                           [frozenset({("x", 1)}), cj.NoLoad()]) == set()


# --- temporary files of a killed writer ----------------------------------------------------

KILLED = r"""
import os, signal, sys
from pathlib import Path
from crank_jax.runtime import io, program_store

def die(*a):
    os.kill(os.getpid(), signal.SIGKILL)

if sys.argv[1] == "output":
    with io.atomic_write(sys.argv[2]) as f:
        f.write("partial")
        f.flush()
        die()
else:
    program_store.os.replace = die  # killed between writing and renaming
    program_store.write(Path(sys.argv[2]), b"partial program")
"""


def _killed_writer(kind: str, path) -> list:
    out = subprocess.run([sys.executable, "-c", KILLED, kind, str(path)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == -signal.SIGKILL, out.stderr[-2000:]
    left = list(path.parent.glob(".*.tmp"))
    assert len(left) == 1  # what a killed process leaves (no code of its own runs)
    return left


def test_a_killed_writers_temporary_output_is_removed_by_the_next_write(tmp_path):
    out = tmp_path / "traj.csv"
    _killed_writer("output", out)
    other = tmp_path / ".traj.csv.1.0123abcd-zzzz.tmp"  # another host's live writer
    other.write_text("x")
    with atomic_write(out) as f:
        f.write("done")
    assert out.read_text() == "done"
    assert [p.name for p in tmp_path.glob(".*.tmp")] == [other.name]


def test_a_killed_writers_temporary_program_is_removed_by_the_next_store(tmp_path):
    store = tmp_path / "programs"
    _killed_writer("store", store / "p-a.xla")
    key = "ef" * 32
    program_store.write(store / "p-b.xla",
                        program_store.pack(key, Entry(1, False, 1, b"z" * 10)))
    assert not list(store.glob(".*.tmp"))
    assert not (store / "p-a.xla").exists()


def _with_callback(x, w):
    # A host callback: the store cannot hold this program (`_custom_calls`).
    y = jax.pure_callback(lambda a: np.asarray(a) * 2.0, jax.ShapeDtypeStruct(x.shape, x.dtype),
                          x)
    return y * w, jnp.sum(x)


def test_loaded_programs_are_evicted_but_an_unstorable_one_is_kept(store, monkeypatch):
    # The bounded set of loaded executables drops the least recently called, which the
    # store gives back; one the store cannot hold would only compile again, so it stays.
    monkeypatch.setattr(program_store, "LOADED", program_store.LoadedPrograms(0))
    monkeypatch.setattr(persistent, "LOADED", program_store.LOADED)
    stored, unstorable = Counted(), Counted(_with_callback, "store_test_callback")
    first = [stored(_X, _W), unstorable(_X, _W)]
    again = [stored(_X, _W), unstorable(_X, _W)]
    assert stored.compiled == 1 and unstorable.compiled == 1
    assert len(program_store.LOADED) == 0 and len(list(store.glob("*.xla"))) == 1
    for a, b in zip(first, again):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
