"""Distributions for [`crank_jax.sweep`][]: `from crank_jax.distributions import Normal`."""

from .sweep.distributions import (
    DISTRIBUTIONS,
    AbstractDistribution,
    Const,
    LogNormal,
    LogUniform,
    Normal,
    Uniform,
    draw,
    parse_distribution,
)

__all__ = ["AbstractDistribution", "Normal", "Uniform", "LogNormal", "LogUniform", "Const",
           "parse_distribution", "draw", "DISTRIBUTIONS"]
