"""Compiled programs kept between processes, so that a fresh process neither traces nor
compiles them.

JAX's persistent compilation cache keeps compiled executables, but a fresh process must
still trace and lower a program to find its cache key, and tracing diffrax and optimistix
was most of a warm `crank-jax fit` (docs/benchmarks/design-figures.md, Start-up). A
[`PersistentProgram`][] skips that: the first call compiles the program and stores the executable
(`jax.experimental.serialize_executable`) under a key made of everything that decides it:
the static part of the arguments, their shapes and dtypes, this package's source, the
versions of JAX and of the libraries that trace into it, x64, the backend and the CPU's
instruction-set flags (an executable is machine code). A program whose arguments hold
a class from outside crank-jax (a user's load, a force of their own) is never stored: its
code may read anything (a module global, a closure), so no key short of the traced
program covers it (`foreign_code.py`); it is traced in every process, as `jax.jit` does,
and JAX's persistent cache spares its compilation. Later processes load a stored program
(tens of milliseconds to a few tenths of a second, by size).
Each file carries a SHA-256 of all of it, checked before anything is deserialised
(`program_store.py`); a damaged file, or one that does not load or run here, is
discarded and compiled again, never loaded and never fatal.

The store is used only where JAX's persistent compilation cache is configured (the CLI
does it; a library user calls `enable_compilation_cache()`): a library has no disk side
effects unless asked. A program takes pytrees and returns a tuple of arrays.
"""

from __future__ import annotations

import hashlib
import os
import platform
import re
import sys
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import program_store
from .foreign_code import foreign_classes
from .program_store import LOADED
from .xla_flags import instruction_sets

__all__ = ["PersistentProgram", "program_store_dir", "enum_code", "enum_name", "FAST_COMPILE",
           "fast_compile_on_cpu"]

#: XLA's CPU compile options for a program where they leave every result bit for bit the
#: same: XLA's older elemental emitters for the fusions instead of its MLIR fusion
#: emitters. LLVM's part of the compile is ~80% of a fit program's, and with these it
#: took 0.6-0.7x as long (the multiple-shooting Jacobian 21.6 -> 15.0 s, the
#: single-shooting one 16.2 -> 10.4 s on a 2-core VM at load 12;
#: experiments/results/fit_programs_options*.json), their calls as fast. Used by the
#: fit's programs (`identify/programs.py`) and the linearisation (`simulation.py`).
FAST_COMPILE = {"xla_cpu_use_fusion_emitters": False}


def fast_compile_on_cpu(*_) -> dict:
    """[`FAST_COMPILE`][] on the CPU, XLA's defaults elsewhere: the `compiler_options` of a
    program that gives the same bits either way on the CPU."""
    return dict(FAST_COMPILE) if jax.default_backend() == "cpu" else {}

# Libraries whose code is traced into the programs: a new version changes the program.
_TRACED = ("jax", "jaxlib", "equinox", "diffrax", "optimistix", "lineax", "optax")


_ARRAYS = (jax.Array, np.ndarray, np.generic)


def program_store_dir() -> Path | None:
    """Where compiled programs are kept: `<JAX's compilation cache>/crank-jax-programs`,
    or None (no store) when JAX has no persistent cache, `CRANK_JAX_NO_CACHE` is set, or
    the backend is not the CPU (there JAX's own persistent cache serves alone)."""
    base = jax.config.jax_compilation_cache_dir
    # CPU only: other backends' foreign functions are not checked by `_custom_calls`.
    if not base or os.environ.get("CRANK_JAX_NO_CACHE") or jax.default_backend() != "cpu":
        return None
    return Path(base) / "crank-jax-programs"


_ENV: str | None = None
#: The source the key holds: all of crank-jax (the traced code is anywhere in it; only
#: `runtime/` was, and a changed fit program was loaded as stored under its old code).
SOURCE = Path(__file__).resolve().parents[1]


def _environment() -> str:
    """Versions, this package's source, the machine (the costly part once per process)."""
    global _ENV  # reading the source and cpuinfo costs a few milliseconds: once
    if _ENV is None:
        h = hashlib.sha256()
        for p in sorted(SOURCE.rglob("*.py")):
            h.update(p.read_bytes())
        h.update(instruction_sets().encode())
        versions = []
        for name in _TRACED:
            try:
                versions.append(f"{name}={metadata.version(name)}")
            except metadata.PackageNotFoundError:
                versions.append(f"{name}=-")
        _ENV = (f"{h.hexdigest()}|{','.join(versions)}|{sys.version_info[:2]}"
                f"|{platform.machine()}")
    # XLA_FLAGS change the compiled code (e.g. the CLI's small-loop threshold, see
    # xla_flags.py), so programs compiled under other flags are other programs.
    # So does the device count (a batch may be spread over several CPU devices): this
    # process's own, and the processes of a distributed run.
    return (f"{_ENV}|x64={jax.config.jax_enable_x64}|{jax.default_backend()}"
            f"|{jax.local_device_count()}|{jax.process_count()}"
            f"|{os.environ.get('XLA_FLAGS', '')}")


def _signature(name: str, args, options: tuple = ()) -> tuple[str | None, list, object,
                                                                 object]:
    """(key, array leaves, their treedef, the static part) of a call; the key is None (not
    stored) when the static part names an object by its address (a user's function), or
    holds a class from outside crank-jax anywhere (see `foreign_code.py`): only code
    whose every input is in the key may skip tracing."""
    dyn, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree.flatten(dyn)
    static_leaves, static_def = jax.tree.flatten(static)
    text = "\n".join([
        name, _environment(), repr(options), str(treedef), str(static_def),
        repr([(type(x).__name__, x) for x in static_leaves]),
        repr([(x.shape, str(x.dtype), bool(getattr(x, "weak_type", False)))
              for x in leaves])])
    if " at 0x" in text:
        return None, leaves, treedef, static
    if foreign_classes((treedef, static_def), static_leaves):
        return None, leaves, treedef, static
    return hashlib.sha256(text.encode()).hexdigest(), leaves, treedef, static


def enum_code(item, enumeration, names: tuple[str, ...]):
    """Inside a program: the index in `names` of an equinox enumeration `item` (e.g. a
    `diffrax.RESULTS` or `optimistix.RESULTS` value), `len(names)` for any other. A stored
    program returns arrays only, and an enumeration item is a custom pytree."""
    hits = [item == getattr(enumeration, n) for n in names]
    return jnp.argmax(jnp.stack(hits + [True]))


def enum_name(code, names: tuple[str, ...]) -> str | None:
    """On the host: the name [`enum_code`][] encoded, or None for any other outcome."""
    code = int(code)
    return names[code] if code < len(names) else None


class PersistentProgram:
    """`fn(*args)` compiled once per static structure and kept on disk between processes.

    `fn` takes pytrees (equinox modules, arrays, Python scalars: the non-array leaves are
    static, as in `eqx.filter_jit`) and returns a tuple of arrays. A program holding a
    host callback (an `eqx.error_if`, e.g. diffrax's check of `SaveAt(ts)`) runs but is
    not stored (see `_compile`). Without a store (see [`program_store_dir`][]) it is
    `eqx.filter_jit(fn)`'s semantics with a lighter dispatch (see `_jit`).

    `compiler_options(*args) -> dict`, if given: XLA options for this program's compile
    (`jax.jit(..., compiler_options=...)`), a choice of the program's own that leaves the
    process's configuration alone; part of the stored program's key. Options this XLA
    does not know are dropped (the program compiles as without them), never an error.
    """

    def __init__(self, fn: Callable, name: str,
                 compiler_options: Callable[..., dict] | None = None):
        self.fn = fn
        self.name = name
        self.jitted = eqx.filter_jit(fn)
        self.compiler_options = compiler_options
        self._flat: dict = {}  # (treedef, array mask, static leaves, options) -> jax.jit
        self._unstored: set[str] = set()  # keys whose program runs unstored here
        # Executables the store cannot hold (a host callback): kept here, out of LOADED's
        # eviction, which would only compile them again.
        self._unstorable: dict[str, Callable] = {}

    def options(self, *args) -> tuple:
        """The XLA compile options of a call with `args`, as sorted `(name, value)` pairs
        (empty: XLA's defaults)."""
        if self.compiler_options is None:
            return ()
        return tuple(sorted(o for o in self.compiler_options(*args).items()
                            if o[0] not in _UNKNOWN_OPTIONS))

    def __call__(self, *args):
        store = program_store_dir()
        if store is None:
            return self._jit(args)
        options = self.options(*args)
        key, leaves, treedef, static = _signature(self.name, args, options)
        if key is None:
            return self._jit(args)
        if key in self._unstored:
            return self._jit(args)
        call = self._unstorable.get(key)
        if call is None:
            call = LOADED.get((self, key))
        if call is not None:
            return tuple(call(*leaves))
        path = store / f"{self.name}-{key[:32]}.xla"
        call = _load(path, key, len(leaves))
        if call is not None:
            out = self._try(call, leaves)
            if out is not None:
                LOADED.put((self, key), call)
                return out
            program_store.discard(path)  # it does not run here: compiled and stored anew
        # The program's name carries the key, and a retry a random tag: JAX's own cache
        # then never supplies the executable (one it supplies cannot be serialised again:
        # loaded in another process it fails with "Function ... not found").
        for tag in (key[:16], f"{key[:16]}_{os.urandom(4).hex()}"):
            call, blob = self._compile(leaves, treedef, static, key, tag, options)
            out = self._try(call, leaves)
            if out is not None:
                if blob is None:
                    self._unstorable[key] = call
                else:  # stored only once it has run
                    program_store.write(path, blob)
                    LOADED.put((self, key), call)
                return out
        self._unstored.add(key)
        return self._jit(args)

    @staticmethod
    def _try(call, leaves):
        """`call(*leaves)` as a tuple, or None if the executable does not run here (a
        failed call is never fatal: the caller compiles, or runs the program unstored,
        which raises any error of the program's own)."""
        try:
            return jax.block_until_ready(tuple(call(*leaves)))
        except Exception:
            return None

    def lower(self, *args):
        """The lowered program (for inspection), as `eqx.filter_jit(fn).lower`."""
        return self.jitted.lower(*args)

    def _jit(self, args):
        """`fn(*args)` in memory: the array leaves dynamic, the others static, as
        `eqx.filter_jit`, through one `jax.jit` of the array leaves per static structure.
        Why not `eqx.filter_jit` itself: its partition and hashing of the arguments cost
        a sizeable part of a fast concrete solve, several times one flatten and `jax.jit`'s
        C++ dispatch (docs/benchmarks/design-figures.md)."""
        leaves, treedef = jax.tree_util.tree_flatten(args)
        mask = tuple(isinstance(x, _ARRAYS) for x in leaves)
        static = tuple(x for x, a in zip(leaves, mask) if not a)
        options = self.options(*args)
        key = (treedef, mask, static, options)
        try:
            call = self._flat.get(key)
        except TypeError:  # an unhashable static leaf: equinox's own dispatch
            return self.jitted(*args)
        if call is None:
            call = self._flat[key] = jax.jit(self._rebuilt(treedef, mask, static),
                                             compiler_options=dict(options) or None)
        arrays = (x for x, a in zip(leaves, mask) if a)
        if not options:
            return call(*arrays)
        try:
            return call(*arrays)
        except Exception as e:
            if not _unknown_option(e, options):
                raise
            return self._jit(args)  # now without the refused option

    def _rebuilt(self, treedef, mask, static):
        """`fn` of the array leaves alone, the static ones bound."""
        fn = self.fn

        def flat(*arrays):
            it_a, it_s = iter(arrays), iter(static)
            leaves = [next(it_a) if a else next(it_s) for a in mask]
            return fn(*jax.tree_util.tree_unflatten(treedef, leaves))

        flat.__name__ = self.name  # the program's name in JAX's compile logs and events
        return flat

    def _compile(self, leaves, treedef, static, key: str, tag: str, options: tuple = ()):
        """(the executable to run, its serialised bytes or None): the bytes are loaded
        back at once, so what runs now is what later processes will load."""
        fn = self.fn

        def flat(*xs):
            return tuple(fn(*eqx.combine(jax.tree.unflatten(treedef, xs), static)))

        flat.__name__ = f"{self.name}_{tag}"

        avals = [jax.ShapeDtypeStruct(x.shape, x.dtype,
                                      weak_type=bool(getattr(x, "weak_type", False)))
                 for x in leaves]
        lowered = jax.jit(flat).lower(*avals)
        try:
            compiled = lowered.compile(dict(options) if options else None)
        except Exception as e:
            if not (options and _unknown_option(e, options)):
                raise
            compiled = lowered.compile()  # (stored under the options' key: a miss later)
        targets = _custom_calls(lowered.as_text())
        if not all(t.startswith("lapack_") for t in targets):
            return compiled, None
        try:
            from jax.experimental.serialize_executable import serialize

            entry = program_store.Entry(compiled.out_tree.num_leaves, bool(targets),
                                        _device_count(compiled), serialize(compiled)[0])
            return _deserialize(entry, len(leaves)), program_store.pack(key, entry)
        except Exception:  # a program that cannot be stored still runs
            return compiled, None



#: Compile options this process's XLA refused ("No such compile option", a value it cannot
#: parse): left out of every later compile (another jaxlib may have dropped or renamed one).
_UNKNOWN_OPTIONS: set[str] = set()


def _unknown_option(error: Exception, options: tuple) -> bool:
    """Whether `error` is XLA refusing one of `options` (then remembered, see
    [`_UNKNOWN_OPTIONS`][]), not a failure of the program itself."""
    text = str(error)
    bad = {name for name, _ in options if f"'{name}'" in text or f" {name}," in text}
    if bad and ("compile option" in text or "While setting option" in text):
        _UNKNOWN_OPTIONS.update(bad)
        return True
    return False


def _load(path: Path, key: str, n_in: int):
    """The executable stored at `path` under `key`, or None: missing, damaged (its digest
    is checked before anything is deserialised, `program_store.read`) or one that does
    not load here (then discarded, to be compiled and stored anew)."""
    entry = program_store.read(path, key)
    if entry is None:
        return None
    try:
        return _deserialize(entry, n_in)
    except Exception:
        program_store.discard(path)
        return None


def _custom_calls(text: str) -> set[str]:
    """The custom-call targets (the foreign functions) of a lowered program. A program is
    stored only if they are all LAPACK's, which [`_ready_custom_calls`][] registers before
    loading one that calls any: JAX registers custom-call targets while lowering, and an
    executable loaded without lowering, calling one that was never registered, would crash
    the process."""
    targets = set(re.findall(r"call_target_name\s*=\s*\"([^\"]+)\"", text))
    return targets | set(re.findall(r"custom_call\s*@([\w.]+)", text))


def _ready_custom_calls() -> None:
    """Register LAPACK's custom-call targets, as lowering any linear algebra does (once
    per process; mostly importing SciPy's LAPACK)."""
    global _READY
    if _READY:
        return
    from .compat import initialize_lapack  # JAX's private initialiser: see compat.py

    initialize_lapack()
    _READY = True


_READY = False


_MAX_OUTPUTS = 4096


def _device_count(compiled) -> int:
    """The devices a compiled program runs on (its arguments' and results' shardings)."""
    shardings = jax.tree.leaves((compiled.input_shardings, compiled.output_shardings))
    return max([len(s.device_set) for s in shardings] + [1])


def _deserialize(entry: program_store.Entry, n_in: int):
    """Load a stored (intact) executable; `ValueError` for a header it cannot have."""
    from jax.experimental.serialize_executable import deserialize_and_load

    if not 0 < entry.n_out <= _MAX_OUTPUTS or not 0 < entry.n_dev <= jax.local_device_count():
        raise ValueError("not a program for this process")
    if entry.lapack:  # it calls LAPACK (registering its targets costs ~0.15 s: only then)
        _ready_custom_calls()
    in_tree = jax.tree.structure((tuple(range(n_in)), {}))
    out_tree = jax.tree.structure(tuple(range(entry.n_out)))
    # Without `execution_devices` JAX loads it onto every device of a multi-device client
    # (e.g. one CPU device per core, `configure_cpu`), and a one-device program then fails
    # on its first call ("Expected args ... to have 2 shards"). This process's own
    # devices: in a distributed run `jax.devices()` starts with process 0's, and a program
    # loaded there on another process returned arrays it cannot read (issue 37 item 9).
    return deserialize_and_load(entry.payload, in_tree, out_tree,
                                execution_devices=jax.local_devices()[:entry.n_dev])

