"""Beyond the point estimate: the posterior of a fit's parameters (NUTS from the
Laplace approximation, priors), corner figures, and the design of an experiment that
identifies them best. Each takes what the fit (`crank_jax.identify`) gives."""
