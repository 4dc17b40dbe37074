"""The task abstraction: physics, cost, features, initial state and noise, defined once.

A task has two state spaces:

- the ODE state ``z`` (``state_names``), in which the true dynamics are integrated and the
  observation noise is added;
- the modelled state ``s`` (``model_state_names``), which the dynamics models predict, the
  cost is evaluated on and the policy sees. For the cart-pole ``s = z``; for the unicycle
  ``s`` is the PILCO augmentation (contact point in the yawed frame, no wheel or turntable
  angle).

Every function here acts on ONE state; ``jax.vmap`` does the batch.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from tasks.forms import SaturatingCost, TrigLinearMap
from tasks.policies import Policy

def check_vector(name: str, value: jax.Array, size: int) -> None:
    """Raise a ValueError unless ``value`` has shape ``(size,)``."""
    shape = jnp.shape(value)
    if shape != (size,):
        raise ValueError(
            f"{name} must have shape ({size},) for one state; got {shape}. "
            "Task functions act on one state: use jax.vmap for a batch."
        )


def hold_where(stopped: jax.Array, z: Any, step: Callable[[Any], Any], safe_z: Any) -> Any:
    """``z`` where ``stopped``, else ``step(z)``. Where stopped, ``step`` sees ``safe_z``
    instead, so that neither it nor its derivative can be NaN behind the ``where``. ``z`` and
    ``safe_z``: arrays or pytrees of one structure (e.g. an MJX ``Data``)."""
    select = lambda a, b: jax.tree.map(lambda x, y: jnp.where(stopped, x, y), a, b)  # noqa: E731
    return select(z, step(select(safe_z, z)))


# RK4's stages: each evaluates f at z + FEED * h * (previous stage's slope); the step adds
# h / 6 * sum(WEIGHT * slope).
RK4_FEED = (0.0, 0.5, 0.5, 1.0)
RK4_WEIGHT = (1.0, 2.0, 2.0, 1.0)


def rk4_step(f, z: jax.Array, u: jax.Array, dt: float, num_substeps: int,
             stop: Callable[[jax.Array], jax.Array] | None = None, safe_z: jax.Array | None = None) -> jax.Array:
    """Integrate ``dz/dt = f(z, u)`` over ``dt`` with ``u`` held, by ``num_substeps`` RK4 steps.

    ``stop(z) -> bool``: an event that ends the integration; the first substep state where it
    holds is kept for the rest of ``dt`` (``hold_where``, with ``safe_z``).

    The four stages are a ``lax.scan``, so ``f`` is traced once, not four times, with the
    same arithmetic as unrolled stages. For the unicycle's long closed-form derivative this
    cuts the compile time of a reverse-mode gradient 3.5-6 fold (one step: 188 s -> 30 s;
    100 particles x 10 steps: 319 s -> 92 s) at about 15 % more run time.
    """
    h = dt / num_substeps
    stages = jnp.array([RK4_FEED, RK4_WEIGHT], dtype=z.dtype).T  # (4, 2)

    def rk4(z):
        def stage(carry, feed_weight):
            slope, weighted_sum = carry
            slope = f(z + (feed_weight[0] * h) * slope, u)
            return (slope, weighted_sum + feed_weight[1] * slope), None

        zero = jnp.zeros_like(z)
        (_, weighted_sum), _ = jax.lax.scan(stage, (zero, zero), stages)
        return z + (h / 6.0) * weighted_sum

    def substep(z, _):
        if stop is None:
            return rk4(z), None
        return hold_where(stop(z), z, rk4, safe_z), None

    z_next, _ = jax.lax.scan(substep, z, None, length=num_substeps)
    return z_next


@dataclasses.dataclass(frozen=True)
class Task:
    """Base class of a task. Subclasses are frozen dataclasses whose fields are the options.

    Subclasses set the class attributes below and implement ``derivative``, ``cost``,
    ``policy_features``, ``gp_features``, ``default_policy`` and the initial-state and noise
    properties; they override ``to_model_state``/``from_model_state`` when ``s != z``, and
    ``to_mujoco``/``from_mujoco`` when they set ``mjcf``.

    A task must be hashable (its bound methods are static metadata of ``estimators.base.Problem``
    under jit), so its fields are immutable scalars (float, int, str, bool), each of a type that
    parses from a string (``tasks.parse_options``, the CLI's ``--task-options``).
    """

    name: ClassVar[str]
    state_names: ClassVar[tuple[str, ...]]
    model_state_names: ClassVar[tuple[str, ...]]
    control_names: ClassVar[tuple[str, ...]]
    u_max: ClassVar[tuple[float, ...]]
    mjcf: ClassVar[str | None] = None
    mjcf_label: ClassVar[str | None] = None
    """Set when the MuJoCo model only approximates ``derivative``; printed with its results."""
    substep_dt: ClassVar[float] = 0.01
    """Length (s) of one RK4 sub-step; a control period of 0.1 s gets 10 sub-steps."""
    value_slice_dims: ClassVar[tuple[str, str]]
    """Two modelled-state dimensions whose 2-D slice of the value function
    ``harness.landscape`` draws by default."""
    presets: ClassVar[dict[str, dict[str, Any]]]

    preset: str
    dt: float
    horizon: int
    noise_k: float
    num_random_trials: int
    num_learned_trials: int

    def __post_init__(self):
        if self.preset not in self.presets:
            raise ValueError(
                f"unknown preset {self.preset!r} for task {self.name!r}; "
                f"valid presets: {sorted(self.presets)}"
            )
        if not self.noise_k >= 0:
            raise ValueError(f"noise_k scales the noise variance and must be >= 0; got {self.noise_k}")
        if not self.dt > 0:
            raise ValueError(f"dt (the control period, s) must be > 0; got {self.dt}")
        if int(self.horizon) != self.horizon or self.horizon < 1:
            raise ValueError(f"horizon (number of control steps) must be an integer >= 1; got {self.horizon}")

    # ----- sizes -------------------------------------------------------------------------
    @property
    def state_dim(self) -> int:
        return len(self.state_names)

    @property
    def model_state_dim(self) -> int:
        return len(self.model_state_names)

    @property
    def control_dim(self) -> int:
        return len(self.control_names)

    @property
    def num_substeps(self) -> int:
        """RK4 sub-steps per control period (about ``substep_dt`` seconds each)."""
        return max(1, round(self.dt / self.substep_dt))

    # ----- true dynamics on the ODE state -----------------------------------------------
    def derivative(self, z: jax.Array, u: jax.Array) -> jax.Array:
        """ODE right-hand side ``dz/dt``; z: (state_dim,), u: (control_dim,) -> (state_dim,)."""
        raise NotImplementedError

    def step(self, z: jax.Array, u: jax.Array) -> jax.Array:
        """The ODE state after one control period ``dt`` with ``u`` held (zero-order hold, RK4).
        The integration stops at the first substep where ``fallen`` holds (the fall is an event:
        past it the equations no longer describe the system; the unicycle's are singular where
        the wheel lies flat)."""
        check_vector("z (ODE state)", z, self.state_dim)
        check_vector("u (control)", u, self.control_dim)
        return rk4_step(self.derivative, z, u, self.dt, self.num_substeps, stop=self.fallen,
                        safe_z=self.init_mean.astype(z.dtype))

    def fallen(self, z: jax.Array) -> jax.Array:
        """True when a real rollout must stop (the system has fallen). Default: never."""
        return jnp.zeros((), bool)

    # ----- modelled state ----------------------------------------------------------------
    def to_model_state(self, z: jax.Array) -> jax.Array:
        """ODE state (state_dim,) -> modelled state (model_state_dim,). Default: identity."""
        return z

    def from_model_state(self, s: jax.Array) -> jax.Array:
        """A modelled state -> an ODE state with the same future (default: identity)."""
        return s

    def model_step(self, s: jax.Array, u: jax.Array) -> jax.Array:
        """True dynamics on the modelled state: ``s_tp1 = to_model(step(from_model(s), u))``."""
        check_vector("s (modelled state)", s, self.model_state_dim)
        return self.to_model_state(self.step(self.from_model_state(s), u))

    def cost(self, s: jax.Array) -> jax.Array:
        """Per-step cost (scalar) of a modelled state s (model_state_dim,)."""
        raise NotImplementedError

    def policy_features(self, s: jax.Array) -> jax.Array:
        """What the policy sees of a modelled state: s (model_state_dim,) -> f (F,)."""
        raise NotImplementedError

    def gp_features(self, s: jax.Array) -> jax.Array:
        """What the GP sees of a modelled state, s (model_state_dim,) -> (G,); the control is
        appended by ``gp_inputs``."""
        raise NotImplementedError

    @property
    def policy_feature_map(self) -> TrigLinearMap | None:
        """``policy_features`` as a declarative form (for moment matching), or None."""
        return None

    @property
    def gp_feature_map(self) -> TrigLinearMap | None:
        """``gp_features`` as a declarative form (for moment matching), or None."""
        return None

    @property
    def cost_form(self) -> SaturatingCost | None:
        """``cost`` as a declarative form (for moment matching), or None."""
        return None

    def gp_inputs(self, s: jax.Array, u: jax.Array) -> jax.Array:
        """GP input ``[gp_features(s), u]``."""
        check_vector("u (control)", u, self.control_dim)
        return jnp.concatenate([self.gp_features(s), u])

    def gp_targets(self, s: jax.Array, s_tp1: jax.Array) -> jax.Array:
        """GP target: the difference of modelled states over one step, ``s_tp1 - s``."""
        return s_tp1 - s

    @property
    def gp_input_dim(self) -> int:
        return int(jax.eval_shape(
            lambda s, u: self.gp_inputs(s, u),
            jax.ShapeDtypeStruct((self.model_state_dim,), jnp.float32),
            jax.ShapeDtypeStruct((self.control_dim,), jnp.float32),
        ).shape[0])

    @property
    def policy_feature_dim(self) -> int:
        return int(jax.eval_shape(
            self.policy_features, jax.ShapeDtypeStruct((self.model_state_dim,), jnp.float32)
        ).shape[0])

    # ----- initial state and noise --------------------------------------------------------
    @property
    def init_mean(self) -> jax.Array:
        """Mean of the initial ODE state, (state_dim,)."""
        raise NotImplementedError

    @property
    def init_std(self) -> jax.Array:
        """Standard deviations of the initial ODE state (diagonal covariance), (state_dim,)."""
        raise NotImplementedError

    @property
    def obs_noise_std(self) -> jax.Array:
        """Observation noise std on the ODE state (variance already scaled by ``noise_k``)."""
        raise NotImplementedError

    @property
    def model_initial_moments(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Mean (S,) and covariance (S, S) of the initial modelled state ``to_model_state(z_0)``
        (PILCO starts from the Gaussian with these moments), or None if unknown. Default: the
        initial distribution itself where the modelled state is the ODE state."""
        if self.model_state_dim != self.state_dim:
            return None
        return np.asarray(self.init_mean, float), np.diag(np.asarray(self.init_std, float) ** 2)

    @property
    def model_noise_std(self) -> jax.Array:
        """Observation noise std carried to the modelled state.

        ``sqrt(diag(J diag(std^2) J^T))`` with J the Jacobian of ``to_model_state`` at the
        initial mean: exact where the augmentation is a signed permutation there (both tasks).
        """
        jac = jax.jacfwd(self.to_model_state)(self.init_mean)
        return jnp.sqrt(jnp.sum((jac * self.obs_noise_std) ** 2, axis=1))

    def sample_initial(self, key: jax.Array) -> jax.Array:
        """One initial ODE state ``z_0 ~ N(init_mean, diag(init_std^2))``."""
        eps = jax.random.normal(key, (self.state_dim,), self.init_mean.dtype)
        return self.init_mean + self.init_std * eps

    def observe(self, z: jax.Array, key: jax.Array) -> jax.Array:
        """A noisy observation of the ODE state: ``z + obs_noise_std * eps``."""
        eps = jax.random.normal(key, z.shape, z.dtype)
        return z + self.obs_noise_std.astype(z.dtype) * eps

    def default_policy(self) -> Policy:
        """The preset's policy (``tasks.policies.Policy``: ``init``, ``network``, ``prepare`` and
        the ``form`` PILCO moment-matches, None for a policy only the particle methods run)."""
        raise NotImplementedError

    def to_mujoco(self, z: jax.Array) -> tuple[jax.Array, jax.Array]:
        """ODE state z (state_dim,) -> MuJoCo ``(qpos (nq,), qvel (nv,))`` of ``mjcf``.

        Needed only with ``mjcf``. ``tasks.mjx_dynamics`` writes the control u (U,) into
        ``ctrl`` as it is, so the MJCF's actuators follow ``control_names``' order, and ``dt``
        must be a whole number of the MJCF's timesteps."""
        raise NotImplementedError(f"task {self.name!r} defines no to_mujoco (needed with an mjcf)")

    def from_mujoco(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        """MuJoCo ``(qpos (nq,), qvel (nv,))`` -> ODE state z (state_dim,); inverse of ``to_mujoco``."""
        raise NotImplementedError(f"task {self.name!r} defines no from_mujoco (needed with an mjcf)")

    @property
    def control_limits(self) -> jax.Array:
        """``u_max`` as an array: controls lie in ``[-u_max, u_max]``."""
        return jnp.asarray(self.u_max)
