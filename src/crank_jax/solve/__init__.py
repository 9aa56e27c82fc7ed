"""Solvers and the simulation: they know vector fields, not mechanisms."""
