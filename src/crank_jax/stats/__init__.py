"""Statistics of residual series that know nothing of the mechanism or the fit: whiteness
tests and a covariance that allows for correlated residuals
([`diagnostics`][crank_jax.stats.diagnostics]). NumPy and the standard library only.

The fit ([`crank_jax.identify`][crank_jax.identify], which also re-exports the public
names), the k-step validation and the reports use them."""
