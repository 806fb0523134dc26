"""Discrete Elastic Rods: geometry, energy, twist solve, inextensibility (pure torch functions)."""
