"""Gradient estimators (the particle estimators issue fills this registry)."""
