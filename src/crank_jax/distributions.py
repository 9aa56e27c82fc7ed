"""Distributions for [`crank_jax.sweep`][]: `from crank_jax.distributions import Normal`."""

from .sweep.distributions import (
    DISTRIBUTIONS,
    DRAW_BLOCK,
    AbstractDistribution,
    Const,
    LogNormal,
    LogUniform,
    Normal,
    Spec,
    Uniform,
    draw,
    parse_distribution,
    parse_spec,
)

__all__ = ["AbstractDistribution", "Normal", "Uniform", "LogNormal", "LogUniform", "Const",
           "parse_distribution", "draw", "DISTRIBUTIONS", "DRAW_BLOCK", "Spec", "parse_spec"]
