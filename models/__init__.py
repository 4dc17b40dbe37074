"""Dynamics models with the predictive-Gaussian interface (``models.prediction``)."""
