"""Experiments: sweeps of a scenario over a grid of overrides and seeds."""
