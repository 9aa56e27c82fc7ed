"""The fit's ODE term: its own adapter on the model's vector field (a function object of
its own, so diffrax's trace cache keeps the fit's programs apart from a user's), and the
diffrax solver each solver name runs as."""

from __future__ import annotations

import jax.numpy as jnp

from ..lazy import lazy_import

diffrax = lazy_import("diffrax")  # imported on first use (see lazy.py)

__all__ = ["ode_term", "FIT_SOLVERS"]


def _fit_field(t, y, field):
    """The fit's own ODETerm adapter on the model's vector field (a function object of its
    own: diffrax caches traces by it, see `Problem.simulate_segments`)."""
    return jnp.stack(field(t, (y[0], y[1])))


def _fit_field_no_callbacks(t, y, field):
    """As `_fit_field`, for traces made with equinox's checks as NaN
    (`persistent.checks_without_callbacks`): a separate object, so a trace made in one mode
    (with host callbacks) is never reused in the other."""
    return jnp.stack(field(t, (y[0], y[1])))


def ode_term() -> diffrax.ODETerm:
    from ..compat import checks_are_nan  # the switch `checks_without_callbacks` sets

    nan = checks_are_nan()
    return diffrax.ODETerm(_fit_field_no_callbacks if nan else _fit_field)


# The fit's residuals use diffrax's adaptive solvers; "dopri8-uniform" (uniform save
# times only) runs as the same Dopri8 tableau, adaptively, on the padded segment times.
FIT_SOLVERS = {"tsit5": "Tsit5", "dopri5": "Dopri5", "dopri8": "Dopri8",
            "dopri8-uniform": "Dopri8", "dopri8-adaptive": "Dopri8", "kvaerno5": "Kvaerno5"}
