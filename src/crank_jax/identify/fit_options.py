"""The options of a fit that its code branches on, as enums resolved at the front door
([`normalize`][crank_jax.identify.request.normalize]), and the checks of the numeric ones.
"""

from __future__ import annotations

import enum
import math

__all__ = ["Method", "ShootingMode", "Init", "check_options", "MAX_ITERATIONS", "SIGMA_RANGE"]

#: Largest iteration budget per start (`max_steps`): far beyond any fit that converges
#: (tens to hundreds of iterations), and small enough for every integer type it meets.
MAX_ITERATIONS = 1_000_000
#: Range of a given noise level `sigma`, rad: outside it, its square (the variance of the
#: Laplace covariance) under- or overflows, and no angle record has such a noise.
SIGMA_RANGE = (1e-12, 1e6)


class Method(enum.StrEnum):
    """`fit(method=)`: the optimiser (see [`fit`][crank_jax.identify.fit]'s notes)."""

    LM = "lm"  # Levenberg-Marquardt over the residuals and their Jacobian
    OPTAX = "optax"  # Adam, then L-BFGS, on reverse-mode gradients


class ShootingMode(enum.StrEnum):
    """`fit(shooting=)`: judged from the record (`AUTO`, which may escalate), or as asked."""

    AUTO = "auto"
    SINGLE = "single"
    MULTIPLE = "multiple"


class Init(enum.StrEnum):
    """`fit(init=)`: the scene's values, the regressor's, or a dict of start values."""

    SCENE = "scene"
    REGRESSOR = "regressor"
    DICT = "dict"


_METHODS = tuple(m.value for m in Method)
_SHOOTING = tuple(m.value for m in ShootingMode)


def check_options(method, shooting, segments, multistart, max_steps, tol, sigma) -> None:
    """Raise `ValueError` naming the first option of `fit` out of its range."""
    if not isinstance(method, str) or method not in _METHODS:
        raise ValueError(f"method must be 'lm' or 'optax', got {method!r}")
    if not isinstance(shooting, str) or shooting not in _SHOOTING:
        raise ValueError(f"shooting must be 'auto', 'single' or 'multiple', got {shooting!r}")
    if segments is not None and (segments < 1 or shooting == ShootingMode.SINGLE and segments > 1):
        raise ValueError(f"segments = {segments} is not valid with shooting={shooting!r}")
    if multistart < 1:
        raise ValueError(f"multistart must be >= 1, got {multistart}")
    if max_steps is not None and not 1 <= max_steps <= MAX_ITERATIONS:
        raise ValueError(f"max_steps must be an integer from 1 to {MAX_ITERATIONS}, got "
                         f"{max_steps}")
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive number, got {tol}")
    for name, v in (sigma.items() if isinstance(sigma, dict) else [("", sigma)]):
        if v is not None and not (isinstance(v, (int, float)) and not isinstance(v, bool)
                                  and SIGMA_RANGE[0] <= v <= SIGMA_RANGE[1]):
            raise ValueError(f"sigma{' of ' + name if name else ''} must be a noise level "
                             f"from {SIGMA_RANGE[0]:g} to {SIGMA_RANGE[1]:g} (the channel's "
                             f"SI unit{'' if name else ', rad for an angle'}), got {v}")
