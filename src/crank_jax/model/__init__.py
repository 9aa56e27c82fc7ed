"""The physics, written once: parameters, loads, geometry, dynamics, Newton-Euler,
linearisation."""
