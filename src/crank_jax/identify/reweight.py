"""The fit's reweighting stage: refits while the channels' noise levels, found from the
fit's own residuals, move (iteratively reweighted least squares, see
[`channel_noise`][crank_jax.identify.channel_noise]). It sits above the optimisation it
repeats, and like every stage takes a [`FitState`][crank_jax.identify.stages.FitState]
and returns a new one.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import channel_noise as ch
from .attempt import attempt
from .stages import FitState

__all__ = ["reweight", "REWEIGHT_ROUNDS"]

#: At most this many refits.
REWEIGHT_ROUNDS = 3


def _weighted(state: FitState, levels: dict[str, float]) -> FitState:
    """`state` with its request and plan weighting each channel by `levels` (SI)."""
    req = dataclasses.replace(state.req, sigmas=levels)
    plan = dataclasses.replace(state.plan, single=ch.reweighted(state.plan.single, levels))
    return state.but(req=req, plan=plan)


def reweight(state: FitState) -> FitState:
    """Refit by single shooting from the estimate `state.best` while the channels' noise
    levels, from the residuals, move; then, for a converged fit whose levels had not
    settled, weigh each channel by its final residuals' level (see `_settle`).
    **Returns:** the new state (its request and plan carry the last weights)."""
    best = state.best
    converged_before = best.converged
    for _ in range(REWEIGHT_ROUNDS):
        if not (np.isfinite(best.cost) and np.all(np.isfinite(best.z))):
            break
        z = best.z[:state.plan.single.p]
        levels = ch.new_levels(state.req, state.plan.single, z)
        if levels is None:
            break
        state = _weighted(state, levels)
        run = attempt(state.req, state.plan, state.plan.single, z, z,
                      "fit (channels reweighted)")
        state = state.but(iterations=state.iterations + run.iterations)
        if np.isfinite(run.cost):
            best = run
    state = state.but(best=best)
    if best.converged and not converged_before:
        state = state.but(notes=superseded(state.notes))
    if best.converged and np.all(np.isfinite(best.z)):
        state = _settle(state)
    sigmas = state.req.sigmas
    if len(sigmas) > 1:
        state = state.but(notes=(*state.notes, "channel noise levels: " + ", ".join(
            f"{n} {v:.3g}" for n, v in sigmas.items()) + " (SI; "
            + ("given" if not state.req.estimated else "estimated from the residuals")
            + "); each channel's residuals are weighted by them"))
    return state


def _settle(state: FitState) -> FitState:
    """A converged fit's channels weighted, for its uncertainty and report, by the levels
    of its own final residuals where the refits stopped before those settled: the level a
    channel reports is then its residuals' (a stale level 35x its residuals' made k's
    standard error 35x too wide)."""
    req, ss = state.req, state.plan.single
    levels = ch.new_levels(req, ss, state.best.z[:ss.p])
    if levels is None:
        return state
    moved = [f"{n} {req.sigmas[n]:.3g} -> {levels[n]:.3g}" for n in levels
             if levels[n] != req.sigmas[n]]
    note = (f"the channels' noise levels had not settled after {REWEIGHT_ROUNDS} refits "
            f"({', '.join(moved)}, SI): the uncertainty weights each channel by its "
            "final residuals' level")
    return _weighted(state, levels).but(notes=(*state.notes, note))


def superseded(notes: tuple[str, ...]) -> tuple[str, ...]:
    """`notes` with those saying that no try converged qualified, once a refit with the
    channels reweighted did: one run never says both "converged" and "none converged"."""
    return tuple(
        f"{note}; with the channels then reweighted by their residuals' levels, the refit "
        "from that try converged: the result is that refit"
        if "none converged" in note or note.startswith("none of the") else note
        for note in notes)
