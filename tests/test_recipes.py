"""The "Where to add things" recipes of docs/guide/architecture.md, each done once.

A new solver: one entry in `solve/names.py`'s table, in a copy of the package, and
`simulate`, scenes, `fit`'s policy and the CLI's help all take it. A new physics term: every
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
assert "bosh3" in cj.SOLVERS, cj.SOLVERS
scene = dataclasses.replace(cj.load_scene("lab-rig"), solver="bosh3")  # scenes check names
ts = np.linspace(0.0, 2.0, 201)
new = cj.simulate(scene.mech, 1.0, 0.0, ts, solver="bosh3", rtol=1e-9, atol=1e-11)
ref = cj.simulate(scene.mech, 1.0, 0.0, ts, solver="dopri8", rtol=1e-11, atol=1e-13)
assert np.max(np.abs(np.asarray(new.phi - ref.phi))) < 1e-6
assert pick_solver(scene.mech, scene.load, 1e-8, "bosh3") == "bosh3"
print("ok")
"""


def test_a_new_solver_is_one_entry_in_the_table(tmp_path):
    # The recipe names the one place: solve/names.py's DIFFRAX table.
    assert "`solve/names.py`" in DOC.read_text()
    pkg = tmp_path / "crank_jax"
    shutil.copytree(SRC, pkg, ignore=shutil.ignore_patterns("__pycache__"))
    names = pkg / "solve" / "names.py"
    text = names.read_text()
    edited = text.replace('    "kvaerno5": ("Kvaerno5", True),\n',
                          '    "kvaerno5": ("Kvaerno5", True),\n    "bosh3": ("Bosh3", False),\n')
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
        assert tuple(listed) == crank_jax.SOLVERS, (command, opt.help)


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
    listed = re.search(r"one of crank_jax\.SOLVERS: ([\w, -]+)", guide).group(1)
    assert tuple(listed.strip().split(", ")) == crank_jax.SOLVERS
