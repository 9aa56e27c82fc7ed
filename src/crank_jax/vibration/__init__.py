"""Nonlinear vibration analysis of the crank: backbone curves, periodic orbits of the
driven crank (shooting, differentiable by the implicit function theorem), forced response
curves by pseudo-arclength continuation with Floquet stability, and parametric-resonance
charts of the rest position under a harmonic slider force.

Modules, one job each: `flow` (the flow map over a span, the library's solver), `floquet`
(monodromy matrices and multipliers), `orbit` (one periodic orbit), `backbone`,
`continuation` (the pseudo-arclength driver), `response` (forced response curves),
`chart` (stability charts), `drive` (which load drives a scene; refusals).

The function `backbone` is `crank_jax.backbone` (the front door): here `backbone` is the
module of that name, never the function, so that `import crank_jax.vibration.backbone` and
the attribute mean the same.
"""

from .backbone import Backbone
from .chart import Chart, mathieu_tongue, stability_chart
from .drive import VibrationError
from .orbit import Orbit, periodic_orbit
from .response import Branch, ForcedResponse, forced_response

__all__ = ["Backbone", "Chart", "stability_chart", "mathieu_tongue",
           "VibrationError", "Orbit", "periodic_orbit", "Branch", "ForcedResponse",
           "forced_response"]

