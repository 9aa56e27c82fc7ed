"""A fitted scene judged on a second record: k-step-ahead prediction over a horizon,
the state window that starts each prediction, and the scores (`crank_jax.validate`)."""
