"""Follow a running machine: online estimation of the free parameters with honest bands,
and change alarms ([`track`][crank_jax.online.tracking.track])."""

from .alarms import name_alarms
from .ekf import FilterSettings, FilterState, Steps, TrackModel, init_state, run_filter
from .runner import run_chunks
from .stream import track_stream
from .tracked import TrackResult
from .tracking import TrackProblem, prepare, track

__all__ = ["track", "track_stream", "run_chunks", "TrackResult", "prepare", "TrackProblem",
           "TrackModel", "FilterSettings", "FilterState", "Steps", "run_filter", "init_state",
           "name_alarms"]
