"""How an optimisation of a fit ended: the [`Run`][] it returns, its `termination` record
(`fit.json`'s), and the words of its messages, for LM, optax and the fit's result."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = ["Run", "termination", "budget_spent", "failed_message", "stalled_message",
           "finite", "NON_FINITE", "FAILS_AT_END", "FAILS_AT_START"]

#: The messages of a run whose iterates, end point or start cannot be solved.
NON_FINITE = "the iterates became non-finite"
FAILS_AT_END = "the ODE solve fails at the final estimate"
FAILS_AT_START = "the ODE solve fails at the start values; choose other start values"


def finite(x) -> float | None:
    """`x` as a float, or None where it is None or not finite (JSON's null)."""
    return None if x is None or not math.isfinite(x) else float(x)


class Run(NamedTuple):
    """One optimisation: final coordinates, cost `0.5 |r|^2`, iterations, outcome, and
    how it ended (`termination`, see [`termination`][])."""

    z: np.ndarray
    cost: float
    iterations: int
    converged: bool
    message: str
    termination: dict | None = None
    #: `(problem, r, J)`: the residuals (N,) and sensitivities (N, p) of the single-shooting
    #: `problem` at `z`, where the optimiser already holds them (the fleet), so that the
    #: uncertainty need not solve again; None where not.
    solved: tuple | None = None


def termination(verdict: str, words: str, *, predicted_decrease: float | None = None,
                largest_step: float | None = None, falling_per_iteration: float | None = None,
                direction: str | None = None, noise: float | None = None) -> dict:
    """How an optimisation ended, as `fit.json`'s `termination` holds it (its fields: see
    [`FitResult`][crank_jax.identify.fit_result.FitResult]`.termination`); the figures
    non-finite or unknown are null."""
    return {"verdict": verdict, "words": words,
            "predicted_decrease": finite(predicted_decrease),
            "largest_step": finite(largest_step),
            "falling_per_iteration": finite(falling_per_iteration), "direction": direction,
            "noise": finite(noise)}


def budget_spent(max_steps: int, falling: float | None = None,
                  unit: str = "sigma^2") -> str:
    """The message of a run that used its iteration budget without converging, with the
    cost's fall per iteration over the last [`STALL_STEPS`][] (in `unit`) when known."""
    still = ("" if falling is None or not math.isfinite(falling)
             else f", the cost still falling by {falling:.3g} {unit} per iteration")
    return (f"stopped after {max_steps} iteration{'s' if max_steps != 1 else ''} without "
            f"converging{still} (`max_steps=` {max_steps}: raise it to go on)")


def failed_message(failed: int) -> str:
    """The message of a run whose best point still has failed ODE solves."""
    return (f"the ODE solve fails at every point tried ({failed} samples failed at the best "
            "one): the parameters make the model far stiffer or faster than the record; "
            "choose other start values")


def stalled_message(rms: float, noise: float) -> str:
    """The message of a run whose cost stopped falling far above the noise level `noise`
    (both in the residuals' unit)."""
    return (f"stalled: the cost stopped falling at an rms residual {rms / noise:.3g} times "
            "the record's noise level, before the Gauss-Newton step became small (a local "
            "minimum, or a model that cannot follow the record); try start values nearer "
            "the truth or more starts (multistart)")
