"""Monte Carlo sweeps: a scene simulated for many sampled parameter values at once."""
