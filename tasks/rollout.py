"""Episodes on a task's true dynamics (the "real system").

The latent ODE state evolves without noise; the policy sees, and the episode records, noisy
observations; the cost is computed on the latent state. When ``task.fallen`` turns true the
latent state freezes and the remaining steps count at the fallen state's cost.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from tasks.base import Task
from tasks.policies import Policy


class Episode(NamedTuple):
    """One episode of horizon T on the real system.

    latent: (T+1, Z) ODE states z_0..z_T; observed: (T+1, Z) their noisy observations;
    controls: (T, U) u_0..u_{T-1}; costs: (T,) c(s(z_{t+1})) for t = 0..T-1 (the return is
    their sum); alive: (T,) bool, True where transition t happened before any fall.
    """

    latent: jax.Array
    observed: jax.Array
    controls: jax.Array
    costs: jax.Array
    alive: jax.Array

    @property
    def total_cost(self) -> jax.Array:
        """The return: the sum of the per-step costs, shape of the leading batch axes."""
        return self.costs.sum(axis=-1)


def run_episode(task: Task, key: jax.Array, policy: Policy | None = None, theta=None) -> Episode:
    """Run one episode of ``task.horizon`` steps; jittable and vmappable over keys and thetas.

    With ``policy=None`` the controls are uniform in ``[-u_max, u_max]`` at every step
    (the random trials); otherwise ``u_t = policy.apply(theta, policy_features(s(obs_t)))``.
    """
    k_init, k_obs0, k_steps = jax.random.split(key, 3)
    z0 = task.sample_initial(k_init)
    u_max = task.control_limits.astype(z0.dtype)

    def control(obs, k):
        if policy is None:
            return jax.random.uniform(k, (task.control_dim,), z0.dtype, -u_max, u_max)
        return policy.apply(theta, task.policy_features(task.to_model_state(obs)))

    def one_step(carry, k):
        z, obs, done = carry
        k_u, k_obs = jax.random.split(k)
        u = control(obs, k_u)
        z_tp1 = jnp.where(done, z, task.step(z, u))
        obs_tp1 = task.observe(z_tp1, k_obs)
        done_tp1 = done | task.fallen(z_tp1)
        cost = task.cost(task.to_model_state(z_tp1))
        return (z_tp1, obs_tp1, done_tp1), (z_tp1, obs_tp1, u, cost, ~done)

    obs0 = task.observe(z0, k_obs0)
    init = (z0, obs0, task.fallen(z0))
    _, (z, obs, u, cost, alive) = jax.lax.scan(one_step, init, jax.random.split(k_steps, task.horizon))
    return Episode(
        latent=jnp.concatenate([z0[None], z]),
        observed=jnp.concatenate([obs0[None], obs]),
        controls=u,
        costs=cost,
        alive=alive,
    )


def transitions(task: Task, episode: Episode) -> tuple[jax.Array, jax.Array, jax.Array]:
    """GP training data from an episode's observations.

    Returns inputs (T, D) ``gp_inputs(s_t, u_t)``, targets (T, S) ``s_tp1 - s_t`` (modelled
    states of the observations) and mask (T,): ``episode.alive`` without the transition into a
    fall, which is not a transition over one control period (``Task.step`` stops integrating
    at the fall; near the unicycle's singularity its values are meaningless).
    """
    s = jax.vmap(task.to_model_state)(episode.observed)
    inputs = jax.vmap(task.gp_inputs)(s[:-1], episode.controls)
    targets = jax.vmap(task.gp_targets)(s[:-1], s[1:])
    falls = jax.vmap(task.fallen)(episode.latent[1:])
    return inputs, targets, episode.alive & ~falls
