"""The one table of solver names: `simulate(solver=...)`, scenes, `fit`, `sweep` and the
CLI's `--solver` help all read it. No imports, so the CLI can build its help cheaply.

A diffrax solver is added here and nowhere else: one entry in [`DIFFRAX`][] (the class's
name in `diffrax`, whether it is implicit) makes it a name of [`SOLVERS`][] that
`simulate`, scenes, `fit`, `sweep` and the CLI accept, stepped through diffrax with the
same step control, save times, load-kink clipping and adjoints as the others
(tests/test_recipes.py does it once). The policy picks it only if a rule there names it.
"""

__all__ = ["SOLVERS", "DIFFRAX", "FUSED", "is_implicit"]

#: diffrax's solvers by name: (the class in `diffrax`, implicit?). An implicit solver is
#: not held to an explicit solver's stability limit by `policy.check_time_scale`.
DIFFRAX: dict[str, tuple[str, bool]] = {
    "tsit5": ("Tsit5", False),
    "dopri5": ("Dopri5", False),
    "dopri8": ("Dopri8", False),
    "kvaerno5": ("Kvaerno5", True),
}

#: crank-jax's fused solvers (`solve/adaptive.py`, `solve/uniform.py`), each a branch of
#: `simulate`'s solve core.
FUSED: tuple[str, ...] = ("dopri8-uniform", "dopri8-adaptive")

#: Solver names accepted by `simulate(solver=...)`, scenes, `fit` and `sweep`: `"auto"`
#: (the policy's choice, `solve/policy.py`), diffrax's, then the fused ones. (A sweep
#: stores a solver as its index here.)
SOLVERS: tuple[str, ...] = ("auto", *DIFFRAX, *FUSED)


def is_implicit(name: str) -> bool:
    """Whether solver `name` (not `"auto"`) is implicit (stable on any decaying mode)."""
    return name in DIFFRAX and DIFFRAX[name][1]
