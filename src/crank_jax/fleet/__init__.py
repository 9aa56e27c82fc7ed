"""Many independent fits at once: each of many records of one scene and free set fitted
by itself, side by side in one compiled Levenberg-Marquardt program per shape.

- `fit_many`: the fits (a [`FleetResult`][crank_jax.fleet.many.FleetResult]: one
  `FitResult` per record, in order, and how each was fitted); `crank-jax fit REC... SCENE
  --each --out DIR` runs it from the command line;
- `FleetResult` and `SUMMARY_COLUMNS` (the first columns of its summary table).

Built above the fit ([`crank_jax.identify`][crank_jax.identify]): each record is planned
as `fit` plans it and reported through the fit's own result.
"""

from .many import SUMMARY_COLUMNS, FleetResult, fit_many

__all__ = ["fit_many", "FleetResult", "SUMMARY_COLUMNS"]
