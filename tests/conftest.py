"""Test configuration: float64 everywhere, a small CPU-only JAX, shared helpers."""

import ast
import inspect
import os
import sys
import threading
from pathlib import Path

os.environ.setdefault("CRANK_JAX_NO_CACHE", "1")  # tests must not depend on a warm cache

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import pytest  # noqa: E402

import crank_jax as cj  # noqa: E402


def tree_allclose(a, b, rtol=1e-10, atol=1e-12) -> bool:
    """True when two pytrees have the same structure and close leaves."""
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    return ta == tb and all(
        np.allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol) for x, y in zip(la, lb)
    )


def flip_byte(i: int):
    """A damage for a stored file: its bytes with bit 0 of byte `i` (mod the length)
    flipped."""
    def damage(b: bytes) -> bytes:
        b = bytearray(b)
        b[i % len(b)] ^= 0x01
        return bytes(b)
    return damage


def experiment(name: str):
    """The module `experiments/<name>.py` (imported once; the path is not left on
    `sys.path`)."""
    import importlib

    sys.path.insert(0, str(Path(__file__).parents[1] / "experiments"))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.pop(0)


def loaded_after(code: str, modules) -> list[str]:
    """Which of `modules` a fresh interpreter has imported after running `code`."""
    import subprocess

    probe = f"{code}\nimport sys; print(sorted(m for m in {tuple(modules)!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True).stdout.strip().splitlines()[-1]
    return ast.literal_eval(out)  # the list the probe printed


def random_mech(rng: np.random.Generator, **overrides) -> "cj.SliderCrank":
    """A random valid mechanism with every body present (geometry spans r/L in 0.05..0.9)."""
    r = rng.uniform(0.02, 0.1)
    L = r / rng.uniform(0.05, 0.9)
    v = dict(
        r=r, L=L, b=rng.uniform(0, L), s=rng.uniform(0, r), m_c=rng.uniform(0.1, 2),
        m_p=rng.uniform(0.1, 2), m_s=rng.uniform(0.1, 2), I_c=rng.uniform(1e-5, 1e-3),
        I_p=rng.uniform(1e-5, 1e-2), k=rng.uniform(1, 10), c=rng.uniform(0, 0.05),
        g=rng.uniform(5, 10),
    )
    v.update(overrides)
    return cj.SliderCrank(**v)


# Each compiled program holds a couple of hundred memory mappings of machine code (about
# 210 for a crank solve, XLA:CPU) until JAX's caches drop it, and Linux refuses a process
# more than `vm.max_map_count` (65530 by default): a run of the full tier in one process
# compiled past it and aborted inside XLA's compiler (about 300 programs). After a module
# whose run left more than a third of the limit, the caches go (what later modules share
# compiles again: the run pays a little time to stay alive).
_MAP_LIMIT = Path("/proc/sys/vm/max_map_count")


def _mappings() -> tuple[int, int]:
    try:
        with open(f"/proc/{os.getpid()}/maps", "rb") as maps:
            return sum(1 for _ in maps), int(_MAP_LIMIT.read_text())
    except OSError:  # not Linux: no such limit to watch
        return 0, 1


@pytest.fixture(autouse=True, scope="module")
def _compiled_code_within_the_map_limit():
    yield
    used, limit = _mappings()
    if used > limit // 3:
        import gc

        jax.clear_caches()
        gc.collect()


@pytest.fixture
def rng():
    return np.random.default_rng(20261121)


@pytest.fixture(scope="session")
def lab_rig():
    return cj.load_scene("lab-rig")


# The fast tier. The README's test command (and CI) runs the tests that are neither `slow`
# nor `full`; `python -m pytest -m "not slow"` runs the full suite. The `full` tests are
# listed in one file, `tests/full_tier.txt` (a test's file and name, one a line; a
# parametrised test by its name alone takes every case), chosen by measured cost so that
# every module keeps tests in the fast tier. An entry that names no collected test fails
# the collection, so the list cannot rot silently.
FULL_TIER = Path(__file__).with_name("full_tier.txt")


def _full_tier() -> set[str]:
    lines = (ln.split("#")[0].strip() for ln in FULL_TIER.read_text().splitlines())
    return {ln for ln in lines if ln}


@pytest.hookimpl(tryfirst=True)  # before `-m` deselects: every collected test is seen
def pytest_collection_modifyitems(config, items):
    listed = _full_tier()
    files = {item.nodeid.split("::")[0] for item in items}
    used = set()
    for item in items:
        key = item.nodeid.split("[")[0]
        if key in listed:
            item.add_marker(pytest.mark.full)
            used.add(key)
    # Only a run of whole folders sees every test a line could name.
    whole = all(Path(a).is_dir() for a in config.args)
    stale = sorted(k for k in listed - used if k.split("::")[0] in files)
    if stale and whole:
        raise pytest.UsageError(f"{FULL_TIER.name} names tests that do not exist: {stale}")


# `--exercised`: which src modules the run exercised. A module counts once one of its
# functions ran (a profile hook records the files of called functions; importing it is not
# enough, since `import crank_jax` imports most modules); a module without functions
# counts once imported. With xdist each worker sends its set to the controller. A module
# none of the run's tests exercised fails the run, so `python -m pytest -q --exercised`
# checks that the fast tier touches every module. Opt-in: a Python-level hook on every
# call slows tracing, so the plain command runs without it.
SRC = Path(cj.__file__).resolve().parent
_CALLED: set[str] = set()


def pytest_addoption(parser):
    parser.addoption("--exercised", action="store_true",
                     help="fail unless every src/crank_jax module was exercised")


def _record_call(frame, event, arg, _function=inspect.CO_OPTIMIZED, _called=_CALLED):
    # CO_OPTIMIZED: a function's frame, not a module's or a class body's (those run at import)
    if event == "call" and frame.f_code.co_flags & _function:
        _called.add(frame.f_code.co_filename)


def _is_controller(config) -> bool:
    return config.pluginmanager.hasplugin("dsession")  # the xdist controller runs no test


def pytest_configure(config):
    if config.getoption("exercised") and not _is_controller(config):
        sys.setprofile(_record_call)
        threading.setprofile(_record_call)


def _exercised() -> set[str]:
    return {f for f in _CALLED if f.startswith(str(SRC))} | {
        m.__file__ for name, m in list(sys.modules.items())
        if name.startswith("crank_jax") and getattr(m, "__file__", None)
        and not any(isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)
                    for n in ast.walk(ast.parse(Path(m.__file__).read_text())))}


def pytest_sessionfinish(session, exitstatus):
    config = session.config
    if not config.getoption("exercised"):
        return
    sys.setprofile(None)
    threading.setprofile(None)
    if hasattr(config, "workerinput"):  # an xdist worker: hand the set to the controller
        config.workeroutput["crank_jax_exercised"] = sorted(_exercised())
        return
    done = set(getattr(config, "_exercised_by_workers", ())) | _exercised()
    missing = sorted(str(p.relative_to(SRC)) for p in SRC.rglob("*.py") if str(p) not in done)
    config._exercised_missing = missing
    if missing and session.exitstatus == 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


@pytest.hookimpl(optionalhook=True)  # an xdist hook: absent under -p no:xdist
def pytest_testnodedown(node, error):
    out = getattr(node, "workeroutput", {}).get("crank_jax_exercised", ())
    node.config._exercised_by_workers = set(getattr(node.config, "_exercised_by_workers",
                                                    ())) | set(out)


def pytest_terminal_summary(terminalreporter, config):
    missing = getattr(config, "_exercised_missing", None)
    if missing is not None:
        terminalreporter.write_line(
            f"--exercised: {len(missing)} src module(s) no test exercised: {missing}"
            if missing else "--exercised: every src/crank_jax module was exercised")
