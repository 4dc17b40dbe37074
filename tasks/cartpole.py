"""Cart-pole swing-up (PIPPS paper; PILCO `scenarios/cartPole`).

ODE state ``z = [x, xdot, thetadot, theta]``; theta = 0 hangs down, theta = pi is upright.
"""

from __future__ import annotations

import dataclasses
import os
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from tasks.base import Task, check_vector
from tasks.forms import SaturatingCost, TrigLinearMap
from tasks.policies import Policy, rbf_policy

POLE_LENGTH = 0.5  # l (m), pivot at one end
POLE_MASS = 0.5  # m (kg)
CART_MASS = 0.5  # M (kg)
FRICTION = 0.1  # b (N s / m), on the cart only
GRAVITY = 9.82  # g (m / s^2)

TIP_COST_WIDTH = 0.25
ANGLE_TARGET = jnp.pi

COSTS = ("angle", "tip")
RBF_PARAMETERISATIONS = ("direct", "pseudo_inputs")


@dataclasses.dataclass(frozen=True)
class CartPole(Task):
    """Cart-pole swing-up. Options: preset, cost ("angle" | "tip"), angle_cost_scale, noise_k,
    rbf_parameterisation ("direct" | "pseudo_inputs"), dt, horizon, ... (``tasks.options``).

    ``angle_cost_scale`` a: the angle cost is ``1 - exp(-a (x^2 + (theta - pi)^2))``. The paper
    writes a = 1 ("costs of the type"); the authors' own demo (proppo/pipps_demo) and PILCO's
    convention have a = 1/2, the default here. ``rbf_parameterisation``: the policy's weights
    are parameters ("direct", the authors' demo) or PILCO's pseudo-targets
    (``tasks.policies.rbf_policy``)."""

    name: ClassVar[str] = "cartpole"
    state_names: ClassVar[tuple[str, ...]] = ("x", "xdot", "thetadot", "theta")
    model_state_names: ClassVar[tuple[str, ...]] = state_names
    control_names: ClassVar[tuple[str, ...]] = ("force",)
    u_max: ClassVar[tuple[float, ...]] = (10.0,)
    mjcf: ClassVar[str] = os.path.join(os.path.dirname(__file__), "cartpole.xml")
    value_slice_dims: ClassVar[tuple[str, str]] = ("x", "theta")
    presets: ClassVar[dict] = {
        "pipps": dict(dt=0.1, horizon=30, noise_k=1.0, cost_type="angle", angle_cost_scale=0.5, num_random_trials=1,
                      num_learned_trials=15, num_basis=50, rbf_parameterisation="direct"),
        "pilco": dict(dt=0.1, horizon=40, noise_k=1.0, cost_type="tip", angle_cost_scale=0.5, num_random_trials=1,
                      num_learned_trials=15, num_basis=10, rbf_parameterisation="pseudo_inputs"),
    }

    cost_type: str = "angle"
    angle_cost_scale: float = 0.5
    num_basis: int = 50
    rbf_parameterisation: str = "direct"

    def __post_init__(self):
        super().__post_init__()
        if self.cost_type not in COSTS:
            raise ValueError(f"unknown cart-pole cost {self.cost_type!r}; valid costs: {list(COSTS)}")
        if not self.angle_cost_scale > 0:
            raise ValueError(f"angle_cost_scale must be > 0 (1/2: the authors' convention, 1: the paper's text); "
                             f"got {self.angle_cost_scale}")
        if self.rbf_parameterisation not in RBF_PARAMETERISATIONS:
            raise ValueError(f"unknown rbf_parameterisation {self.rbf_parameterisation!r}; "
                             f"valid: {list(RBF_PARAMETERISATIONS)}")

    def derivative(self, z, u):
        """Uniform rod on a cart (spec "Cart-pole swing-up"); z (4,), u (1,) -> dz/dt (4,)."""
        check_vector("z (ODE state)", z, 4)
        check_vector("u (control)", u, 1)
        l, m, M, b, g = POLE_LENGTH, POLE_MASS, CART_MASS, FRICTION, GRAVITY
        _, xdot, thetadot, theta = z
        force = u[0]
        s, c = jnp.sin(theta), jnp.cos(theta)
        xddot = (2 * m * l * thetadot**2 * s + 3 * m * g * s * c + 4 * force - 4 * b * xdot) / (
            4 * (M + m) - 3 * m * c**2
        )
        thetaddot = (
            -3 * m * l * thetadot**2 * s * c - 6 * (M + m) * g * s - 6 * (force - b * xdot) * c
        ) / (4 * l * (M + m) - 3 * m * l * c**2)
        return jnp.stack([xdot, xddot, thetaddot, thetadot])

    @property
    def cost_form(self) -> SaturatingCost:
        """Angle cost ``1 - exp(-a (x^2 + (theta - pi)^2))`` (raw angle; a =
        ``angle_cost_scale``, so W = 2a I) or the tip cost ``1 - exp(-d^2 / (2 * 0.25^2))``,
        ``d^2 = (x + l sin th)^2 + l^2 (cos th + 1)^2``; on y = [x, xdot, thetadot, theta,
        sin theta, cos theta]."""
        if self.cost_type == "angle":
            point = TrigLinearMap.make(np.zeros((0, 4)), [[1, 0, 0, 0], [0, 0, 0, 1]], [0.0, -ANGLE_TARGET])
            weight = 2.0 * self.angle_cost_scale
            return SaturatingCost(point, ((weight, 0.0), (0.0, weight)))
        point = TrigLinearMap.make(np.array([[0.0, 0, 0, 1]]), [[1, 0, 0, 0, POLE_LENGTH, 0],
                                                                 [0, 0, 0, 0, 0, POLE_LENGTH]], [0.0, POLE_LENGTH])
        width2 = TIP_COST_WIDTH**2
        return SaturatingCost(point, ((1 / width2, 0.0), (0.0, 1 / width2)))

    @property
    def policy_feature_map(self) -> TrigLinearMap:
        """``[x, xdot, thetadot, sin(theta), cos(theta)]``."""
        return TrigLinearMap.select(4, angle_dims=(3,), keep=(0, 1, 2, 4, 5))

    gp_feature_map = policy_feature_map

    def cost(self, s):
        """Per-step cost of a modelled state (see ``cost_form``)."""
        check_vector("s (modelled state)", s, 4)
        return self.cost_form(s)

    def policy_features(self, s):
        """``[x, xdot, thetadot, sin(theta), cos(theta)]``, (5,)."""
        check_vector("s (modelled state)", s, 4)
        return self.policy_feature_map(s)

    gp_features = policy_features

    def to_mujoco(self, z):
        """ODE state -> MuJoCo ``(qpos, qvel)`` of ``cartpole.xml``: ``([x, theta], [xdot, thetadot])``."""
        check_vector("z (ODE state)", z, 4)
        return jnp.stack([z[0], z[3]]), jnp.stack([z[1], z[2]])

    def from_mujoco(self, qpos, qvel):
        """MuJoCo ``(qpos, qvel)`` -> ODE state ``[x, xdot, thetadot, theta]``."""
        return jnp.stack([qpos[0], qvel[0], qvel[1], qpos[1]])

    @property
    def init_mean(self):
        return jnp.zeros(4)

    @property
    def init_std(self):
        return jnp.full(4, 0.1)

    @property
    def obs_noise_std(self):
        """pipps: sqrt(k) * [0.01 m, 0.1 m/s, 10 deg/s, 1 deg]; pilco: sqrt(k) * 0.01 on all four."""
        if self.preset == "pipps":
            std = jnp.array([0.01, 0.1, jnp.deg2rad(10.0), jnp.deg2rad(1.0)])
        else:
            std = jnp.full(4, 0.01)
        return jnp.sqrt(self.noise_k) * std

    def sample_policy_centres(self, key: jax.Array, n: int) -> jax.Array:
        """The RBF policy's ``n`` initial centres, (n, 5): features of initial states
        (pseudo-inputs, as PILCO) or, for the direct form, the features of the initial mean
        plus N(0, 1) noise (as the authors' demo)."""
        if self.rbf_parameterisation == "direct":
            mean_features = self.policy_features(self.to_model_state(self.init_mean))
            return mean_features + jax.random.normal(key, (n, mean_features.shape[0]), mean_features.dtype)
        z0 = jax.vmap(self.sample_initial)(jax.random.split(key, n))
        return jax.vmap(lambda z: self.policy_features(self.to_model_state(z)))(z0)

    def default_policy(self) -> Policy:
        """RBF network (``num_basis`` basis functions, ``rbf_parameterisation``), initial
        length-scales [1, 1, 1, 0.7, 0.7]."""
        return rbf_policy(self.num_basis, self.u_max, self.sample_policy_centres, (1.0, 1.0, 1.0, 0.7, 0.7),
                          direct=self.rbf_parameterisation == "direct")
