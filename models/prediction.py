"""The predictive-Gaussian interface every dynamics model implements.

``model.predict(params, s, u) -> Prediction`` for ONE particle: the next modelled state is
Gaussian with mean ``mean`` and per-dimension variance ``model_var + noise_var``. Keeping the
two variances apart lets estimators sample either or both (the paper's TP-sigma_f samples only
``noise_var``; TP+sigma_n scales ``noise_var`` by 100).
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol

import jax


class Prediction(NamedTuple):
    """Predictive distribution of the next modelled state, each (S,).

    mean: E[s_tp1]; model_var: the model's (function) uncertainty; noise_var: the learned or
    known noise variance.
    """

    mean: jax.Array
    model_var: jax.Array
    noise_var: jax.Array

    @property
    def var(self) -> jax.Array:
        """Total predictive variance ``model_var + noise_var``."""
        return self.model_var + self.noise_var


class Model(Protocol):
    """A dynamics model: ``predict(params, s (S,), u (U,)) -> Prediction``."""

    def predict(self, params: Any, s: jax.Array, u: jax.Array) -> Prediction: ...
