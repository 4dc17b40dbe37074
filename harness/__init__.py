"""Experiments; each is ``python -m harness.NAME``."""
