"""The package's layout rules (issue 7's measured proxies; issue 39's architecture),
checked on the source text.

No function longer than 60 lines (docstring excluded), no module longer than 400 lines
(issue 39's guides), no import cycle between the package's modules nor between its
subpackages (function-level imports included), no underscore-private name imported from
another module of the package. The architecture (docs/guide/architecture.md): the core,
`model/` and `solve/`, imports nothing outside itself (no runtime, records, fit, sweep,
report, CLI or front door) and no host module (importlib, sysconfig, os, sys, pathlib),
the top level holds only the front door, and no two files
share a name.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "crank_jax"
MODULES = sorted(SRC.rglob("*.py"))
# Issue 39's guide for every function (80 outside the solver core until 2026-11-28, when
# the last eight longer ones were split into named steps; the solver core, which a
# newcomer should follow in one sitting, had 60 since issue 26).
MAX_FUNCTION_LINES = 60
# Issue 39's guide for every module (450 until 2026-11-28, when the last seven longer ones
# gave a part with its own job a module: coordinates, the blocks' stage adjoint, the dense
# output, the text table, the validation figure, `synth`, the progress bar).
MAX_MODULE_LINES = 400


def _name(path: Path) -> str:
    parts = list(path.relative_to(SRC.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _package(path: Path) -> str:
    name = _name(path)
    return name if path.name == "__init__.py" else name.rsplit(".", 1)[0]


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """(absolute module, imported names) for every import of crank-jax (relative ones
    resolved), at any depth (a function-level import too: a lazy import is an import):
    a module's of the package, or an experiment's."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(a.name, []) for a in node.names if a.name.split(".")[0] == "crank_jax"]
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            base = _package(path).split(".")
            base = base[: len(base) - (node.level - 1)]
            mod = ".".join(base + ([node.module] if node.module else []))
            out.append((mod, [a.name for a in node.names]))
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("crank_jax"):
            out.append((node.module, [a.name for a in node.names]))
    return out


def _body_lines(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    body = fn.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
            and isinstance(body[0].value.value, str):
        body = body[1:]
    if not body:
        return 0
    return body[-1].end_lineno - body[0].lineno + 1


def test_modules_are_short():
    long = {_name(p): n for p in MODULES
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules longer than {MAX_MODULE_LINES} lines: {long}"


def _long_functions(paths, limit: int) -> dict[str, int]:
    """`module.function -> body lines` for the functions of `paths` longer than `limit`."""
    long = {}
    for p in paths:
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = _body_lines(node)
                if n > limit:
                    long[f"{_name(p)}.{node.name}"] = n
    return long


def test_functions_are_short():
    long = _long_functions(MODULES, MAX_FUNCTION_LINES)
    assert not long, f"functions longer than {MAX_FUNCTION_LINES} lines: {long}"


def test_no_private_names_across_modules():
    bad = []
    modules = {_name(p) for p in MODULES}
    for p in MODULES:
        for mod, names in _imports(p):
            for n in names:
                # `from . import x` imports a submodule, whose own name may be anything.
                if f"{mod}.{n}" in modules:
                    continue
                if n.startswith("_"):
                    bad.append(f"{_name(p)} imports {mod}.{n}")
    assert not bad, bad


def test_no_import_cycles():
    modules = {_name(p): p for p in MODULES}
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for m, p in modules.items():
        for mod, names in _imports(p):
            for target in [f"{mod}.{n}" for n in names] + [mod]:
                if target in modules and target != m:
                    graph[m].add(target)
                    break
    # A package's __init__ re-exporting its children is not a cycle of logic.
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                cycle = stack[stack.index(t):] + [t]
                if not all(modules[x].name == "__init__.py" or x == t for x in cycle[:-1]):
                    pytest.fail("import cycle: " + " -> ".join(cycle))
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


# --- the architecture (issue 39) ---------------------------------------------------------

#: The core: physics and integration, functions of their arguments.
CORE = ("model", "solve")
#: The top level: the package's front door, nothing else.
FRONT_DOOR = {"__init__.py", "__main__.py", "scene.py", "simulation.py"}


def _group(module: str) -> str:
    """The subpackage (or top-level module) a module belongs to: `crank_jax.solve.erk` ->
    `solve`, `crank_jax.scene` -> `scene`, `crank_jax` -> `crank_jax`."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _targets(path: Path) -> set[str]:
    """The package's modules (or packages) that `path` imports, at any depth."""
    modules = {_name(p) for p in MODULES}
    out = set()
    for mod, names in _imports(path):
        subs = [f"{mod}.{n}" for n in names if f"{mod}.{n}" in modules]
        out.update(subs if subs else [mod])
    return out


#: Breaches of the core's rule still in the code, each with why (issue 39): the test fails
#: on any other breach, and on this one once it is gone (then delete it here).
# None left: the backward pass's program is a static field of the reverse-mode adjoint
# (`DiscreteAdjoint.backward`), chosen at the edge from the XLA flags (issue 39).
CORE_BREACHES_LEFT: set[str] = set()


def test_core_imports_nothing_outside_itself():
    # model/ and solve/ know nothing of the program store, memos, flags, lazy imports,
    # files, records, the fit, sweeps, reports, the CLI or the front door.
    bad = []
    for p in MODULES:
        group = _group(_name(p))
        if group not in CORE:
            continue
        allowed = {"model"} if group == "model" else set(CORE)
        bad += [f"{_name(p)} imports {t}" for t in sorted(_targets(p))
                if _group(t) not in allowed]
    assert set(bad) == CORE_BREACHES_LEFT, sorted(set(bad) ^ CORE_BREACHES_LEFT)


#: The host's modules (the interpreter, the environment, files and where they lie): the
#: core's numbers are functions of its arguments, so it asks the host nothing. Deciding
#: what counts as crank-jax's own code by where its files lie is the program store's
#: business (`runtime/foreign_code.py`), not the physics'.
HOST_MODULES = ("importlib", "sysconfig", "os", "sys", "pathlib")


def _host_imports(path: Path) -> set[str]:
    """The [`HOST_MODULES`][] that `path` imports, at any depth."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module.split(".")[0])
    return out & set(HOST_MODULES)


def test_core_imports_no_host_module():
    bad = [f"{_name(p)} imports {m}" for p in MODULES if _group(_name(p)) in CORE
           for m in sorted(_host_imports(p))]
    assert not bad, f"the core imports host modules: {bad}"


def test_top_level_holds_only_the_front_door():
    top = {p.name for p in SRC.glob("*.py")}
    assert top <= FRONT_DOOR, f"top-level modules beyond the front door: {top - FRONT_DOOR}"


def test_no_two_files_share_a_name():
    seen: dict[str, list[str]] = {}
    for p in MODULES:
        if p.name != "__init__.py":
            seen.setdefault(p.name, []).append(_name(p))
    twice = {n: ms for n, ms in seen.items() if len(ms) > 1}
    assert not twice, f"file names used twice: {twice}"


def test_no_cycles_between_subpackages():
    # A cycle of subpackages (identify -> report -> identify, say) through a lazy import
    # is a cycle all the same: every import counts, at any depth.
    graph: dict[str, set[str]] = {}
    for p in MODULES:
        a = _group(_name(p))
        for t in _targets(p):
            b = _group(t)
            if a != b and a != "crank_jax":  # the package's __init__ re-exports all
                graph.setdefault(a, set()).add(b)
    state: dict[str, int] = {}

    def visit(g, path):
        state[g] = 1
        for h in sorted(graph.get(g, ())):
            if state.get(h) == 1:
                pytest.fail("subpackage cycle: " + " -> ".join(path[path.index(h):] + [h]))
            if h not in state:
                visit(h, path + [h])
        state[g] = 2

    for g in sorted(graph):
        if g not in state:
            visit(g, [g])


def test_the_rules_catch_what_they_forbid(tmp_path, monkeypatch):
    # The checks above would pass on an empty list: each must see a breach when one is there.
    import sys

    mod = sys.modules[__name__]
    fake = tmp_path / "crank_jax"
    for rel, text in {"__init__.py": "", "solve/__init__.py": "", "model/__init__.py": "",
                      "runtime/__init__.py": "", "report/__init__.py": "",
                      "identify/__init__.py": "",
                      "solve/a.py": "def f():\n    from ..runtime import b\n",
                      "runtime/b.py": "", "extra.py": "", "model/b.py": "",
                      "model/h.py": "def f():\n    import importlib.util\n",
                      "report/r.py": "from ..identify import i\n",
                      "identify/i.py": "def g():\n    from ..report import r\n"}.items():
        (fake / rel).parent.mkdir(parents=True, exist_ok=True)
        (fake / rel).write_text(text)
    monkeypatch.setattr(mod, "SRC", fake)
    monkeypatch.setattr(mod, "MODULES", sorted(fake.rglob("*.py")))
    for check in (test_core_imports_nothing_outside_itself, test_core_imports_no_host_module,
                  test_top_level_holds_only_the_front_door, test_no_two_files_share_a_name,
                  test_no_cycles_between_subpackages):
        with pytest.raises((AssertionError, pytest.fail.Exception)):
            check()


EXPERIMENTS = sorted((SRC.parents[1] / "experiments").glob("*.py"))
#: Internal modules the experiments may import (issue 39 asks for the public API only), each
#: with the reason no public route does its job: the experiments' own tooling (a second copy
#: in experiments/_bench.py would be worse than a listed import), and the internals an
#: experiment exists to measure or swap. A module not listed here is public (`crank_jax`, or
#: a namespace's `__all__`) or a new breach; a listed one no experiment imports is stale
#: (both tested below).
EXPERIMENT_INTERNALS = {
    # tooling
    "crank_jax.runtime.io": "tooling: results written atomically (atomic_write)",
    "crank_jax.runtime.xla_flags": "tooling: the XLA CPU flags the benchmarks compare "
                                   "(with_cpu_flags) and the backward program they select "
                                   "(backward_program)",
    "crank_jax.report.plotting": "tooling: the figures' style (pyplot, save_figure)",
    # measured or swapped internals
    "crank_jax.fleet.batch_lm": "bench_fit_many warms up every batch size (BATCHES) of "
                                   "the fleet's programs that its timed call uses",
    "crank_jax.solve.adaptive": "bench_fusion compiles the fused step loop bare "
                                "(solve_adaptive) to count its body's kernels for a plain, a "
                                "packed and a constant field; the public solve's optimization "
                                "barrier on the field's leaves keeps XLA from folding the "
                                "constants (lab rig: 376 kernel operands, not 174)",
    "crank_jax.solve.adjoint": "the discrete adjoint's backward programs, swapped and timed "
                               "(adjoint._deferred, _CHUNK, forward): bench_reverse, "
                               "reverse_chunks, reverse_split, _reverse_programs",
    "crank_jax.model.trig": "bench_fusion times the traced trigonometry's arithmetic forms "
                            "(trig.sincos, trig.rsqrt) against jnp's",
    "crank_jax.identify.problem": "the fit's residual problem built without a fit "
                                  "(build_problem, pick_solver): diffrax_callbacks, "
                                  "identify_design",
    "crank_jax.identify.programs": "the fit's compiled residual and Jacobian programs, "
                                   "lowered and timed or evaluated at the true parameters "
                                   "(jacobian_at, residuals_at): diffrax_callbacks, "
                                   "fit_programs_options, identify_design",
    "crank_jax.identify.request": "fit_programs_options builds the fit's plan (normalize) "
                                  "to compile its Jacobian programs under each option",
    "crank_jax.identify.fit_plan": "fit_programs_options: the plan itself (make_plan)",
    "crank_jax.identify.uncertainty": "identify_design applies the fit's identifiability "
                                      "analysis (analyze) to the Jacobian at the true "
                                      "parameters, without a fit",
    "crank_jax.identify.attempt": "optimiser_variants swaps the optimiser under the fit's "
                                  "tries (attempt)",
    "crank_jax.bayes.corner": "design_end_to_end draws the Design figure that "
                                 "`crank-jax design --plot` draws (plot_design; no public "
                                 "plot API)",
    "crank_jax.vibration.drive": "bench_vibration's brute-force baseline steps the same "
                                 "driven field (field_at) as the continuation",
    "crank_jax.vibration.flow": "bench_vibration's brute-force baseline: the same flow map "
                                "(flow), so that the comparison is of the methods",
    "crank_jax.vibration.orbit": "bench_vibration's brute-force baseline reads the same "
                                 "refined extremes (extremes) as the orbits",
    "crank_jax.vibration.chart": "bench_vibration: the largest Floquet multiplier at one "
                                 "(P1, f) along a fine frequency line for the tongue edges "
                                 "(floquet_max); stability_chart computes a square grid only",
    "crank_jax.vibration.plots": "bench_vibration draws the figures `crank-jax vibration "
                                 "--plot` draws (plot_response, plot_chart; no public plot "
                                 "API)",
}


def test_every_experiment_imports_what_exists():
    # experiments/reverse_chunks.py imported `crank_jax.xla_flags`, gone since the
    # runtime moved into `runtime/`: the script could not start, and nothing ran it.
    import importlib

    missing = []
    for path in EXPERIMENTS:
        for mod, names in _imports(path):
            try:
                m = importlib.import_module(mod)
            except ImportError:
                missing.append(f"{path.name}: {mod}")
                continue
            missing += [f"{path.name}: {mod}.{n}" for n in names
                        if not hasattr(m, n) and not _is_module(f"{mod}.{n}")]
    assert not missing, f"experiments import what does not exist: {missing}"


def _is_module(name: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:  # a name inside a module, not a submodule
        return False


def _experiment_internals(paths) -> dict[str, set[str]]:
    """Internal module -> the experiments importing it (`script.py`, with the name where
    the module itself is imported from): every crank-jax import but `crank_jax` and a
    public name of a namespace's `__all__`."""
    import importlib

    found: dict[str, set[str]] = {}
    for path in paths:
        for mod, names in _imports(path):
            if mod == "crank_jax":
                continue
            public = set(getattr(importlib.import_module(mod), "__all__", ()))
            for n in names or [""]:
                # a public name of a subpackage; else the module it names, or `mod` itself
                used = (f"{mod}.{n}" if n and _is_module(f"{mod}.{n}") else mod)
                if mod.count(".") == 1 and n in public:
                    continue
                found.setdefault(used, set()).add(path.name + (f" ({n})" if n and used == mod
                                                               else ""))
    return found


def test_experiments_import_the_public_api_or_a_listed_internal():
    breaches = {f"{who}: {mod}" for mod, whos in _experiment_internals(EXPERIMENTS).items()
                if mod not in EXPERIMENT_INTERNALS for who in whos}
    assert not breaches, ("experiments import internals not in EXPERIMENT_INTERNALS "
                          f"(use the public API, or list it with its reason): {breaches}")


def test_every_listed_internal_is_imported_by_an_experiment():
    # The list cannot go stale: an entry no experiment needs any more is removed.
    stale = set(EXPERIMENT_INTERNALS) - set(_experiment_internals(EXPERIMENTS))
    assert not stale, f"EXPERIMENT_INTERNALS lists modules no experiment imports: {stale}"


def test_the_experiment_rules_catch_what_they_forbid(tmp_path, monkeypatch):
    import sys

    mod = sys.modules[__name__]
    script = tmp_path / "fake_experiment.py"
    script.write_text("from crank_jax.model import CrankField\n"
                      "from crank_jax.solve.trajectory import solve_trajectory\n")
    monkeypatch.setattr(mod, "EXPERIMENTS", [script])
    assert set(_experiment_internals([script])) == {"crank_jax.solve.trajectory"}
    with pytest.raises(AssertionError, match="solve.trajectory"):
        test_experiments_import_the_public_api_or_a_listed_internal()
    with pytest.raises(AssertionError, match="no experiment imports"):
        test_every_listed_internal_is_imported_by_an_experiment()


#: A docstring names no issue of this project and no date: both go stale the day the code
#: changes (figures belong on the benchmark pages, made by their scripts). An upstream
#: project's issue, named with its project ("CPython issue 114763"), is a reference.
_STALE = re.compile(r"(\w+ )?\b[Ii]ssues? #?\d+|\b20\d\d-\d\d-\d\d\b")
_UPSTREAM = {"CPython ", "jax ", "JAX ", "diffrax ", "equinox ", "NumPy ", "numpy ",
             "XLA ", "scipy ", "SciPy "}


def _docstrings(paths):
    """`(where, docstring)` of every module, class and function in `paths`, `where` as
    `file:name`."""
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef,
                                 ast.ClassDef)):
                yield (f"{path.name}:{getattr(node, 'name', '<module>')}",
                       ast.get_docstring(node, clean=False) or "")


def _stale_docstrings(paths) -> list[str]:
    return [f"{where}: {m.group(0)!r}" for where, doc in _docstrings(paths)
            for m in _STALE.finditer(doc) if m.group(1) not in _UPSTREAM]


def test_docstrings_name_no_issue_and_no_date(tmp_path):
    assert not _stale_docstrings(MODULES), _stale_docstrings(MODULES)
    # The rule catches what it forbids, and lets an upstream reference through.
    bad = tmp_path / "bad.py"
    bad.write_text('"""Fixed in issue 39."""\n\ndef f():\n    """Measured 2026-11-27."""\n'
                   '\n\ndef g():\n    """A CPython issue 114763 workaround."""\n')
    assert len(_stale_docstrings([bad])) == 2


#: A timing with a sub-second unit (`1.56 ms`, `~40 ns`, `241 us`) in a docstring is a
#: measurement, never a definition: it belongs on docs/benchmarks/design-figures.md or a
#: benchmark page, beside the script that measures it.
_TIMING = re.compile(r"\d(\.\d+)?\s?(ms|us|µs|ns)\b")


def _timed_docstrings(paths) -> list[str]:
    return [f"{where}: {m.group(0)!r}" for where, doc in _docstrings(paths)
            for m in _TIMING.finditer(doc)]


def test_docstrings_hold_no_measured_timings(tmp_path):
    assert not _timed_docstrings(MODULES), _timed_docstrings(MODULES)
    bad = tmp_path / "bad.py"
    bad.write_text('"""A step costs ~8 us."""\n\ndef f():\n    """1.56 ms against 0.40ms."""\n'
                   '\n\ndef g():\n    """5 s at 200 Hz (0.01 s apart), (ns,) in ms_per."""\n')
    assert len(_timed_docstrings([bad])) == 3  # g's times and names are no measurement
