"""Follow a running machine: online estimation of the free parameters with honest bands,
and change alarms ([`track`][crank_jax.online.tracking.track])."""

from .ekf import FilterSettings, FilterState, Steps, TrackModel, init_state, run_filter
from .tracked import TrackResult
from .tracking import TrackProblem, prepare, track

__all__ = ["track", "TrackResult", "prepare", "TrackProblem", "TrackModel", "FilterSettings",
           "FilterState", "Steps",
           "run_filter", "init_state"]
