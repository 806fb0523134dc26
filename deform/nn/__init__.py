"""Learned parts of the model."""
