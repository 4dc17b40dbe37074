"""The true dynamics as a model, with the same predictive interface as the GP.

``predict(params, s, u)``: mean = the task's dynamics over one control period (plain-JAX RK4
or the MuJoCo model under MJX), ``model_var = 0`` (the dynamics are known), ``noise_var`` =
the task's observation-noise variance on the modelled state (``task.model_noise_std ** 2``),
so that particles spread as the real system's observations do and likelihood-ratio
estimators have a density to differentiate. A state the task calls fallen stays where it is
(the real rollout's fall test), up to that noise.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp

from models.prediction import Prediction
from tasks.base import Task, check_vector, hold_where

BACKENDS = ("jax", "mjx")


@dataclasses.dataclass(frozen=True)
class SimulatorModel:
    """True-dynamics model of ``task``; ``backend`` "jax" (the ODE, RK4) or "mjx" (the task's
    MJCF under MuJoCo MJX, simulated in ``mjx_dtype``). ``params`` of ``predict`` is unused."""

    task: Task
    backend: str = "jax"
    mjx_dtype: Any = jnp.float64
    ode_step: Callable[[jax.Array, jax.Array], jax.Array] = dataclasses.field(init=False, repr=False)

    def __post_init__(self):
        if self.backend not in BACKENDS:
            raise ValueError(f"unknown simulator backend {self.backend!r}; valid backends: {list(BACKENDS)}")
        if self.backend == "jax":
            step = self.task.step
        else:
            from tasks.mjx_dynamics import mjx_step_fn  # imports MuJoCo only when asked for

            step = mjx_step_fn(self.task, self.mjx_dtype)
        object.__setattr__(self, "ode_step", step)

    def predict(self, params: Any, s: jax.Array, u: jax.Array) -> Prediction:
        """One particle: s (S,), u (U,) -> Prediction of s_tp1, each (S,)."""
        check_vector("s (modelled state)", s, self.task.model_state_dim)
        check_vector("u (control)", u, self.task.control_dim)
        z = self.task.from_model_state(s)
        # A fallen state is frozen, as on the real system (tasks/rollout.py): past the fall the
        # equations no longer describe the system (the unicycle's wheel would pass through the
        # floor) and can diverge.
        z_tp1 = hold_where(self.task.fallen(z), z, lambda z: self.ode_step(z, u),
                           self.task.init_mean.astype(z.dtype))
        mean = self.task.to_model_state(z_tp1).astype(s.dtype)
        noise_var = (self.task.model_noise_std**2).astype(s.dtype)
        return Prediction(mean, jnp.zeros_like(mean), noise_var)
