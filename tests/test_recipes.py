"""The "Where to add things" recipes of docs/guide/architecture.md, each done once.

A new solver: one row in `solve/names.py`'s table (its name and how to make its solver
object), in a copy of the package, and `simulate`, scenes, `fit`'s policy and the CLI's
help all take it. A new physics term: every
optional term of the model is in every place the recipe lists, so the list is complete
(a term added without one of them fails here).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import crank_jax

SRC = Path(crank_jax.__file__).resolve().parent
DOC = Path(__file__).resolve().parents[1] / "docs" / "guide" / "architecture.md"

_NEW_SOLVER = """
import dataclasses
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import crank_jax as cj
from crank_jax.identify.problem import pick_solver
from crank_jax.solve.names import name_of
assert "bosh3" in cj.solve.SOLVERS, cj.solve.SOLVERS
scene = dataclasses.replace(cj.load_scene("lab-rig"), solver="bosh3")  # scenes check names
ts = np.linspace(0.0, 2.0, 201)
new = cj.simulate(scene.mech, 1.0, 0.0, ts, solver="bosh3", rtol=1e-9, atol=1e-11)
ref = cj.simulate(scene.mech, 1.0, 0.0, ts, solver="dopri8", rtol=1e-11, atol=1e-13)
assert np.max(np.abs(np.asarray(new.phi - ref.phi))) < 1e-6
assert name_of(pick_solver(scene.mech, scene.load, 1e-8, "bosh3")) == "bosh3"
rk4 = cj.simulate(scene.mech, 1.0, 0.0, ts, solver="rk4", outputs=("energy",))
assert np.max(np.abs(np.asarray(rk4.phi - ref.phi))) < 1e-6 and int(rk4.num_steps) == 8000
print("ok")
"""


# A solver of one's own, as the recipe says: an `AbstractSolver` whose `run` steps any
# field (here classic RK4, 40 equal steps per save interval, no error control).
_RK4 = """
import jax
import jax.numpy as jnp
from .solvers import Solution


class RK4(AbstractSolver):
    substeps: int = 40

    def run(self, field, ts, y0, args, *, prepare, **_):
        f, m = prepare(field), self.substeps

        def interval(y, t01):
            h = (t01[1] - t01[0]) / m

            def step(i, y):
                t = t01[0] + i * h
                add = lambda y, k, c: jax.tree.map(lambda a, b: a + c * b, y, k)
                k1 = f(t, y, args)
                k2 = f(t + h / 2, add(y, k1, h / 2), args)
                k3 = f(t + h / 2, add(y, k2, h / 2), args)
                k4 = f(t + h, add(y, k3, h), args)
                return jax.tree.map(lambda y, a, b, c, d: y + h / 6 * (a + 2 * b + 2 * c + d),
                                    y, k1, k2, k3, k4)

            y = jax.lax.fori_loop(0, m, step, y)
            return y, y

        _, ys = jax.lax.scan(interval, y0, (ts[:-1], ts[1:]))
        ys = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), y0, ys)
        import diffrax  # (names.py imports diffrax only when a diffrax solver is made)

        return Solution(ys, diffrax.RESULTS.successful, jnp.asarray((ts.shape[0] - 1) * m))
"""


def test_a_new_solver_is_one_entry_in_the_table(tmp_path):
    # The recipe names the one place: solve/names.py's TABLE.
    assert "`solve/names.py`" in DOC.read_text()
    pkg = tmp_path / "crank_jax"
    shutil.copytree(SRC, pkg, ignore=shutil.ignore_patterns("__pycache__"))
    names = pkg / "solve" / "names.py"
    text = names.read_text()
    # One of diffrax's: one row. A solver of one's own: its class and one row.
    row = '    "kvaerno5": lambda: _diffrax("Kvaerno5"),\n'
    assert row in text  # the table's row format, as the recipe shows it
    edited = text.replace(row, row + '    "bosh3": lambda: _diffrax("Bosh3"),\n'
                          '    "rk4": RK4,\n')
    edited = edited.replace("#: Each solver's name", _RK4 + "\n\n#: Each solver's name")
    assert edited != text
    names.write_text(edited)
    env = dict(os.environ, PYTHONPATH=str(tmp_path), CRANK_JAX_NO_CACHE="1")
    run = subprocess.run([sys.executable, "-c", _NEW_SOLVER], capture_output=True, text=True,
                         env=env, timeout=600, cwd=tmp_path)
    assert run.returncode == 0 and run.stdout.strip().endswith("ok"), run.stderr[-3000:]
    helped = subprocess.run([sys.executable, "-m", "crank_jax", "simulate", "--help"],
                            capture_output=True, text=True, env=env, timeout=300,
                            cwd=tmp_path)
    assert helped.returncode == 0 and "bosh3" in " ".join(helped.stdout.split())


def test_cli_solver_help_lists_exactly_the_table():
    from crank_jax.cli.main import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.choices)  # noqa: SLF001 (argparse has no API)
    for command in ("simulate", "sweep"):
        opt = next(a for a in sub.choices[command]._actions if "--solver" in a.option_strings)
        listed = re.search(r"one of ([\w, -]+?) \(", opt.help).group(1).split(", ")
        assert tuple(listed) == crank_jax.solve.SOLVERS, (command, opt.help)


# The places a new physics term goes, as the recipe lists them (file: what marks the term
# there). Each optional term below must be in each.
_TERM_PLACES = ("model/params.py", "model/structure.py", "model/coefficients.py",
                "model/dynamics.py", "model/linear.py", "model/newton_euler.py", "scene.py")
# Optional terms and how each file spells them (a one-letter field by its attribute read).
_TERMS = {"e": r"\.e\b|\"e\"", "T_c": r"\bT_c\b", "c_s": r"\bc_s\b", "F_s": r"\bF_s\b",
          "gravity_angle": r"\bgravity_angle\b|\bgamma\b"}
# A term that changes the kinematics (the offset) reaches the dynamics, the linearisation
# and the reactions through `geometry()`, as the recipe says: there it is in geometry.py.
_KINEMATIC = {"e"}
_VIA_GEOMETRY = ("model/dynamics.py", "model/linear.py", "model/newton_euler.py")


@pytest.mark.parametrize("term", sorted(_TERMS))
def test_every_physics_term_is_in_every_listed_place(term):
    doc = DOC.read_text()
    recipe = doc[doc.index("**A new physics term:**"):doc.index("**A term of your own")]
    missing = []
    for place in _TERM_PLACES:
        assert f"`{place.split('/')[-1]}`" in recipe or f"`{place}`" in recipe, place
        where = ("model/geometry.py" if term in _KINEMATIC and place in _VIA_GEOMETRY
                 else place)
        if not re.search(_TERMS[term], (SRC / where).read_text()):
            missing.append(where)
    assert not missing, f"{term} is missing from {missing}"


def test_scene_file_guide_lists_exactly_the_table():
    guide = (DOC.parent.parent / "how-to" / "scene-files.md").read_text()
    listed = re.search(r"one of crank_jax\.solve\.SOLVERS: ([\w, -]+)", guide).group(1)
    assert tuple(listed.strip().split(", ")) == crank_jax.solve.SOLVERS
