"""A linear-Gaussian system whose expected cost has a closed form: the estimators' ground truth.

Dynamics ``s_tp1 = A s + B u + sqrt(v) eps`` (v = model_var + noise_var, per dimension),
affine policy ``u = W s + b``, initial state ``N(mu0, diag(sd0^2))`` and the saturating cost
``c(s) = 1 - exp(-1/2 (s - r)^T Q (s - r))``. With ``F = A + B W`` the state stays Gaussian:

    m_tp1 = F m + B b,    Sigma_tp1 = F Sigma F^T + diag(v)
    E[c(s)] = 1 - det(I + Sigma Q)^(-1/2) exp(-1/2 (m - r)^T Q (I + Sigma Q)^(-1) (m - r))

so ``J(theta) = sum_{t=1..T} E[c(s_t)]`` and its exact gradient (jax.grad) are known.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from estimators.base import Problem
from estimators.base import MomentForms
from models.prediction import Prediction
from tasks.forms import PolicyForm, SaturatingCost, TrigLinearMap
from tasks.policies import LinearParams, Policy


def _array(nested) -> jax.Array:
    return jnp.asarray(nested)


@dataclasses.dataclass(frozen=True)
class LinearGaussianSystem:
    """The system's constants as tuples (hashable, so the model can be a static argument)."""

    A: tuple = ((1.0, 0.1), (-0.3, 0.95))
    B: tuple = ((0.0,), (0.1,))
    model_var: tuple = (0.01, 0.02)
    noise_var: tuple = (0.02, 0.01)
    init_mean: tuple = (1.0, -0.5)
    init_std: tuple = (0.3, 0.2)
    target: tuple = (0.2, 0.0)
    cost_weight: tuple = ((1.0, 0.0), (0.0, 0.5))
    horizon: int = 10

    @property
    def state_dim(self) -> int:
        return len(self.A)

    def predict(self, params, s: jax.Array, u: jax.Array) -> Prediction:
        """Model interface for one particle: mean ``A s + B u``, the two variances."""
        del params
        mean = _array(self.A).astype(s.dtype) @ s + _array(self.B).astype(s.dtype) @ u
        return Prediction(mean, _array(self.model_var).astype(s.dtype), _array(self.noise_var).astype(s.dtype))

    def next_state_moments(self, params, z_mean: jax.Array, z_cov: jax.Array, model_var_scale: float = 1.0,
                           noise_var_scale: float = 1.0):
        """Exact: ``s_tp1 = [A B] z + noise`` for z = [s, u] ~ N(z_mean, z_cov) -> (mean, cov)."""
        del params
        F = jnp.concatenate([_array(self.A), _array(self.B)], axis=1).astype(z_mean.dtype)
        v = model_var_scale * _array(self.model_var) + noise_var_scale * _array(self.noise_var)
        return F @ z_mean, F @ z_cov @ F.T + jnp.diag(v).astype(z_mean.dtype)

    def cost(self, s: jax.Array) -> jax.Array:
        """``1 - exp(-1/2 (s - r)^T Q (s - r))`` for one state."""
        d = s - _array(self.target)
        return 1.0 - jnp.exp(-0.5 * d @ _array(self.cost_weight) @ d)

    def expected_cost(self, mean: jax.Array, cov: jax.Array) -> jax.Array:
        """``E[c(s)]`` for ``s ~ N(mean, cov)``, in closed form."""
        Q = _array(self.cost_weight)
        eye = jnp.eye(self.state_dim, dtype=cov.dtype)
        d = mean - _array(self.target)
        inner = Q @ jnp.linalg.solve(eye + cov @ Q, d)
        return 1.0 - jnp.exp(-0.5 * d @ inner) / jnp.sqrt(jnp.linalg.det(eye + cov @ Q))

    def objective(self, theta: LinearParams, model_var_scale: float = 1.0, noise_var_scale: float = 1.0) -> jax.Array:
        """The exact ``J(theta) = sum_{t=1..T} E[c(s_t)]`` under the affine policy."""
        A, B = _array(self.A), _array(self.B)
        F = A + B @ theta.weight
        v = model_var_scale * _array(self.model_var) + noise_var_scale * _array(self.noise_var)

        def step(carry, _):
            m, S = carry
            m, S = F @ m + B @ theta.bias, F @ S @ F.T + jnp.diag(v)
            return (m, S), self.expected_cost(m, S)

        init = (_array(self.init_mean), jnp.diag(_array(self.init_std) ** 2))
        _, costs = jax.lax.scan(step, init, None, length=self.horizon)
        return costs.sum()

    def policy(self) -> Policy:
        """The affine policy ``u = W s + b`` (no saturation), W (U, S), b (U,)."""
        control_dim = len(self.B[0])

        def init(key):
            weight = 0.1 * jax.random.normal(key, (control_dim, self.state_dim))
            return LinearParams(weight, jnp.zeros((control_dim,), weight.dtype))

        return Policy(init, lambda theta, s: theta.weight @ s + theta.bias, form=PolicyForm("linear", None))

    def initial_state(self, key: jax.Array) -> jax.Array:
        return _array(self.init_mean) + _array(self.init_std) * jax.random.normal(key, (self.state_dim,))

    def problem(self, model_var_scale: float = 1.0, noise_var_scale: float = 1.0) -> Problem:
        """The particle problem of this system (features = the state itself), with the forms
        PILCO needs (moment matching is exact here)."""
        eye = np.eye(self.state_dim)
        forms = MomentForms(
            features=TrigLinearMap.make(np.zeros((0, self.state_dim)), eye),
            cost=SaturatingCost(TrigLinearMap.make(np.zeros((0, self.state_dim)), eye, -np.asarray(self.target)),
                                self.cost_weight),
            init_mean=self.init_mean, init_cov=tuple(map(tuple, np.diag(np.square(self.init_std)).tolist())))
        return Problem(model=self, model_params=None, policy=self.policy(), cost=self.cost,
                       features=lambda s: s, initial_state=self.initial_state, horizon=self.horizon,
                       model_var_scale=model_var_scale, noise_var_scale=noise_var_scale, moment_forms=forms)
