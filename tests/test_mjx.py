"""The MuJoCo cart-pole (tasks/cartpole.xml) under MJX (tasks/mjx_dynamics.py) against the
plain-JAX ODE (CartPole.step): per-step agreement, float32 against float64, reverse-mode
gradients against finite differences, and the errors for a task without an MJCF.

MJX compiles slowly (10-100 s per jitted function on 2 CPU cores; a few seconds from the
persistent cache that conftest.py sets up), so this module jits three MJX functions in all:
the batched step in float64 and in float32 (module fixtures, shared by the tests) and the
gradient of a 30-step rollout. The finite differences reuse the batched float64 step.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tasks
from tasks.mjx_dynamics import mjx_dynamics, mjx_step_fn

NUM_STATES = 20  # batch size of every batched MJX call
HORIZON = 30  # control steps in the gradient test (3 s)

PER_STEP_TOL = 1e-11
"""MJX float64 against CartPole.step, absolute, max over components, per control step. Both
integrate the same ODE with RK4 at 0.01 s, so they differ by rounding only: 7e-15 measured,
two ulps of the largest component (|thetadot| 26). 1e-11 leaves room for a few thousand ulps
of accumulated round-off and catches the rod's inertia written to 6 digits in cartpole.xml
(0.0104167: 8e-6 per step, measured; under the former tolerance, 1e-5)."""

FLOAT32_TOL = 1e-5
"""float32 against float64 MJX per control step, on each component, relative to
``1 + |z_next|``. float32 rounds at 6e-8 relative; one control step is ten RK4 sub-steps
(forty forward passes, each a solve with the 2x2 mass matrix), so rounding accumulates to a
few ulps of the largest components (|thetadot| up to 26 rad/s here): 6e-7 measured (2.7e-6
absolute), well inside 1e-5 (about 80 ulps)."""

FD_STEP = 1e-5
"""Central finite-difference step on every input (initial state and controls, all O(1)), near
the optimum (float64 eps)^(1/3) ~ 6e-6 that balances truncation (~ h^2 |f'''|) against rounding
(~ 1e-16 |f| / h). Measured against the reverse-mode gradient: 2.4e-8 relative on the worst
component (5e-9 of the largest); h = 1e-4 gives 6e-7 (truncation), h = 1e-7 gives 8e-6
(rounding)."""

FD_RTOL = 1e-6
"""Per-component relative tolerance of the gradient check, 40 times the measured error; an
absolute floor of 1e-3 FD_RTOL times the largest component covers components near zero."""


@pytest.fixture(scope="module")
def task():
    return tasks.make("cartpole")


@pytest.fixture(scope="module")
def dynamics(task):
    """Both precisions, built before anything is jitted: building the float32 dynamics under
    jax_enable_x64 clears JAX's in-memory caches (see tasks/mjx_dynamics.py)."""
    return {"float64": mjx_dynamics(task, jnp.float64), "float32": mjx_dynamics(task, jnp.float32)}


@pytest.fixture(scope="module")
def batched_step(dynamics):
    """Jitted ``vmap`` of the MJX step per precision: (NUM_STATES, 4), (NUM_STATES, 1) -> (NUM_STATES, 4)."""
    return {name: jax.jit(jax.vmap(dyn.step)) for name, dyn in dynamics.items()}


@pytest.fixture(scope="module")
def states_and_controls():
    """NUM_STATES fixed states and controls: angles evenly over [-pi, 3 pi] (hanging, upright,
    both directions, beyond a full turn), |x| < 2 m, |xdot| < 5 m/s, |thetadot| < 20 rad/s,
    controls in [-10, 10] including both limits."""
    k_z, k_u = jax.random.split(jax.random.PRNGKey(2026))
    low = jnp.array([-2.0, -5.0, -20.0])
    high = jnp.array([2.0, 5.0, 20.0])
    x_xdot_thetadot = jax.random.uniform(k_z, (NUM_STATES, 3), jnp.float64, low, high)
    theta = jnp.linspace(-jnp.pi, 3.0 * jnp.pi, NUM_STATES)
    zs = jnp.concatenate([x_xdot_thetadot, theta[:, None]], axis=1)
    us = jax.random.uniform(k_u, (NUM_STATES, 1), jnp.float64, -10.0, 10.0)
    us = us.at[0, 0].set(10.0).at[1, 0].set(-10.0)
    return zs, us


@pytest.fixture(scope="module")
def next_states(task, batched_step, states_and_controls):
    """One control step from each state: MJX in both precisions (float64 inputs; the float32
    step casts them) and the plain-JAX ODE."""
    zs, us = states_and_controls
    out = {name: np.asarray(step(zs, us)) for name, step in batched_step.items()}
    out["jax"] = np.asarray(jax.vmap(task.step)(zs, us))
    return out


def test_mjx_float64_matches_jax_cartpole_per_step(next_states):
    assert next_states["float64"].dtype == np.float64
    err = np.max(np.abs(next_states["float64"] - next_states["jax"]))
    assert err < PER_STEP_TOL, f"MJX vs JAX cart-pole, one control step: max abs difference {err:.3g}"


def test_mjx_float32_agrees_with_float64(next_states):
    z32, z64 = next_states["float32"], next_states["float64"]
    assert z32.dtype == np.float32
    assert np.all(np.isfinite(z32))
    scaled = np.abs(z32 - z64) / (1.0 + np.abs(z64))
    assert np.max(scaled) < FLOAT32_TOL, f"float32 vs float64 MJX: max scaled difference {np.max(scaled):.3g}"


def _final_state_loss(step, z0, controls):
    """Sum of squares of the state after ``len(controls)`` control steps from z0 (4,); controls (T, 1)."""
    z_final, _ = jax.lax.scan(lambda z, u: (step(z, u), None), z0, controls)
    return jnp.sum(z_final**2)


def _batched_final_state_loss(batched_step, z0s, controls):
    """The same loss for a batch, one batched MJX step at a time (reuses the compiled step).

    z0s (B, 4), controls (B, T, 1) -> (B,); the batch is padded to a multiple of NUM_STATES.
    """
    batch = z0s.shape[0]
    pad = -batch % NUM_STATES
    z = np.concatenate([z0s, np.zeros((pad, 4))])
    controls = np.concatenate([controls, np.zeros((pad,) + controls.shape[1:])])
    for t in range(controls.shape[1]):
        z = np.concatenate([
            np.asarray(batched_step(z[i:i + NUM_STATES], controls[i:i + NUM_STATES, t]))
            for i in range(0, z.shape[0], NUM_STATES)
        ])
    return np.sum(z[:batch] ** 2, axis=1)


def test_mjx_gradient_matches_finite_differences(dynamics, batched_step):
    step = dynamics["float64"].step
    z0 = jnp.array([0.1, -0.2, 0.5, 0.3])
    t = jnp.arange(HORIZON)
    controls = (8.0 * jnp.sin(0.7 * t) + 1.0 * jnp.cos(2.3 * t))[:, None]  # within +-10

    loss_and_grad = jax.jit(jax.value_and_grad(lambda z, u: _final_state_loss(step, z, u), argnums=(0, 1)))
    loss, (grad_z0, grad_controls) = loss_and_grad(z0, controls)
    grad = np.concatenate([np.asarray(grad_z0), np.asarray(grad_controls).ravel()])
    assert np.all(np.isfinite(grad))

    # central differences in all 4 + HORIZON inputs, evaluated as one batch
    n_in = 4 + HORIZON
    flat = np.concatenate([np.asarray(z0), np.asarray(controls).ravel()])
    inputs = np.concatenate([flat[None], flat + FD_STEP * np.eye(n_in), flat - FD_STEP * np.eye(n_in)])
    losses = _batched_final_state_loss(batched_step["float64"], inputs[:, :4], inputs[:, 4:].reshape(-1, HORIZON, 1))
    fd = (losses[1:n_in + 1] - losses[n_in + 1:]) / (2.0 * FD_STEP)

    # the step-by-step batched loss is the loss that was differentiated
    np.testing.assert_allclose(losses[0], float(loss), rtol=1e-12)
    scale = np.max(np.abs(fd))
    assert scale > 0
    np.testing.assert_allclose(grad, fd, rtol=FD_RTOL, atol=1e-3 * FD_RTOL * scale,
                               err_msg="MJX reverse-mode gradient vs central differences")


class _CartPoleWithoutModel(tasks.CartPole):
    name = "cartpole_without_mjcf"
    mjcf = None


def test_task_without_mjcf_raises(task):
    no_model = _CartPoleWithoutModel(**{f.name: getattr(task, f.name) for f in dataclasses.fields(task)})
    with pytest.raises(ValueError, match="'cartpole_without_mjcf' has no MuJoCo model"):
        mjx_step_fn(no_model)
    with pytest.raises(ValueError, match="float32 or float64"):
        mjx_step_fn(task, jnp.int32)
