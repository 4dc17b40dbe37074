"""The APPROXIMATE MuJoCo unicycle (tasks/unicycle.xml: a wheel in frictional contact with the
floor) under MJX: it loads and steps as MuJoCo in C does, agrees with the ideal-rolling
equations at small torques, and gives finite float64 gradients that match finite differences
over a short horizon (the solver's iterations run in a bounded scan, tasks/mjx_dynamics.py).
Three MJX functions are compiled (about a minute on 2 CPU cores; seconds
from the persistent cache of conftest.py)."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pandas as pd
import pytest

import tasks
from tasks.mjx_dynamics import mjx_dynamics

NUM_STATES = 16
HORIZON = 3  # control steps (0.3 s) in the gradient test

C_TOL = 1e-9
"""MJX float64 against MuJoCo in C, one control step (20 sub-steps with contact) with controls
over their whole range (slip and lift-off included), absolute: the same algorithm (at most 4
solver iterations) in another implementation; 2.5e-13 measured."""

IDEAL_TOL = 0.03
"""MJX against the ideal-rolling equations (Unicycle.step), one control step with controls up to
10 % of their range, absolute on every component: the contact is soft and slips a little; 0.012
measured (yaw and turntable rates), see tasks/unicycle.xml."""

FD_STEP = 1e-6
FD_TOL = 1e-6
"""Central differences against reverse mode on a 3-step loss, absolute, relative to the largest
gradient component (3e4, the frame pitch). Measured: 6e-6 at h = 1e-5 (truncation), 6e-8 at
h = 1e-6, 6e-7 at h = 1e-7 (rounding, which also makes the near-zero wheel-angle component
swing by 1e-3)."""


@pytest.fixture(scope="module")
def task():
    return tasks.make("unicycle")


@pytest.fixture(scope="module")
def dynamics(task):
    return mjx_dynamics(task, jnp.float64)


@pytest.fixture(scope="module")
def states(task):
    """NUM_STATES initial states drawn from the task's initial distribution."""
    key = jax.random.PRNGKey(2026)
    return task.init_mean + task.init_std * jax.random.normal(key, (NUM_STATES, 12), jnp.float64)


def _controls(fraction: float):
    """NUM_STATES controls uniform over ``fraction`` of the range [-10, 10] x [-50, 50]."""
    u = jax.random.uniform(jax.random.PRNGKey(7), (NUM_STATES, 2), jnp.float64, -1.0, 1.0)
    return fraction * u * jnp.array([10.0, 50.0])


@pytest.fixture(scope="module")
def batched_step(dynamics):
    return jax.jit(jax.vmap(dynamics.step))


def _mujoco_c_step(task, model, z, u):
    """One control step of ``model`` (tasks/unicycle.xml, loaded once) with MuJoCo in C."""
    data = mujoco.MjData(model)
    qpos, qvel = task.to_mujoco(z)
    data.qpos[:], data.qvel[:], data.ctrl[:] = np.asarray(qpos), np.asarray(qvel), np.asarray(u)
    for _ in range(round(task.dt / model.opt.timestep)):
        mujoco.mj_step(model, data)
    return np.asarray(task.from_mujoco(jnp.asarray(data.qpos), jnp.asarray(data.qvel)))


def test_mjx_unicycle_steps_as_mujoco_in_c(task, batched_step, states):
    us = _controls(1.0)
    mjx_next = np.asarray(batched_step(states, us))
    assert mjx_next.dtype == np.float64 and np.all(np.isfinite(mjx_next))
    model = mujoco.MjModel.from_xml_path(task.mjcf)
    c_next = np.stack([_mujoco_c_step(task, model, z, u) for z, u in zip(states, us)])
    assert np.max(np.abs(mjx_next - c_next)) < C_TOL


def test_mjx_unicycle_agrees_with_ideal_rolling_at_small_torques(task, batched_step, states):
    us = _controls(0.1)
    err = np.abs(np.asarray(batched_step(states, us)) - np.asarray(jax.vmap(task.step)(states, us)))
    assert np.max(err) < IDEAL_TOL, f"per-component max error {err.max(0)}"
    # the comparison can fail: the full torque range breaks ideal rolling (slip, lift-off)
    us = _controls(1.0)
    err = np.abs(np.asarray(batched_step(states, us)) - np.asarray(jax.vmap(task.step)(states, us)))
    assert np.max(err) > 10 * IDEAL_TOL


@pytest.fixture(scope="module")
def horizon_loss(task, dynamics):
    """``loss(inputs)``: the squared modelled state after HORIZON MJX steps from
    ``inputs = [z0 (12,), u_1, ..., u_HORIZON (2 each)]``."""

    def loss(inputs):
        z0, us = inputs[:12], inputs[12:].reshape(HORIZON, 2)
        z_final, _ = jax.lax.scan(lambda z, u: (dynamics.step(z, u), None), z0, us)
        return jnp.sum(task.to_model_state(z_final) ** 2)

    return loss


@pytest.fixture(scope="module")
def horizon_grad(horizon_loss):
    return jax.jit(jax.grad(horizon_loss))


@pytest.mark.slow
def test_mjx_unicycle_gradient_is_finite_and_matches_finite_differences(states, horizon_loss, horizon_grad):
    """Slow (about 2 min: reverse mode through the contact solver compiles slowly). The default
    suite keeps the cart-pole's MJX gradient against finite differences and lowers this
    gradient's program (test_linalg)."""
    controls = jnp.array([[2.0, 10.0], [-3.0, -8.0], [1.0, 15.0]])
    inputs = jnp.concatenate([states[0], controls.ravel()])
    grad = np.asarray(horizon_grad(inputs))
    assert np.all(np.isfinite(grad))
    offsets = FD_STEP * np.concatenate([np.eye(inputs.size), -np.eye(inputs.size)])
    values = np.asarray(jax.jit(jax.vmap(horizon_loss))(inputs + offsets))
    fd = (values[: inputs.size] - values[inputs.size:]) / (2 * FD_STEP)
    np.testing.assert_allclose(grad, fd, rtol=0.0, atol=FD_TOL * np.max(np.abs(fd)))


def test_mjx_unicycle_stops_at_the_fall(task, batched_step, unicycle_falling_state):
    """As ``Task.step`` (tests/test_policies_rollout.py, the same state): the MJX sub-steps
    stop at the first fallen state. Without the stop this state's step was NaN (the joint
    chain locks at |theta| = pi/2), and so was every gradient through it (the next test)."""
    z, u = unicycle_falling_state
    z1 = np.asarray(batched_step(jnp.tile(z, (NUM_STATES, 1)), jnp.tile(u, (NUM_STATES, 1))))[0]
    assert np.all(np.isfinite(z1)) and bool(task.fallen(z1))
    held = np.asarray(batched_step(jnp.tile(z1, (NUM_STATES, 1)), jnp.tile(u, (NUM_STATES, 1))))[0]
    np.testing.assert_allclose(held, z1, rtol=0, atol=1e-12)  # a fallen state stays put


@pytest.mark.slow
def test_mjx_unicycle_gradient_through_the_fall_is_finite(horizon_grad, unicycle_falling_state):
    """Slow with the gradient test above (they share its compilation)."""
    z, u = unicycle_falling_state
    assert np.all(np.isfinite(np.asarray(horizon_grad(jnp.concatenate([z, jnp.tile(u, HORIZON)])))))


@pytest.mark.slow
def test_mjx_agreement_end_to_end_with_resume(tmp_path):
    """``python -m harness.mjx_agreement`` at a tiny size writes its CSV and markdown (labelled
    approximate), agrees with the equations without control, and a rerun computes nothing."""
    from harness import mjx_agreement

    argv = ["--task", "unicycle", "--states", "3", "--horizon", "2", "--control-fractions", "0,1",
            "--out", str(tmp_path)]
    mjx_agreement.main(argv)
    frame = pd.read_csv(tmp_path / "mjx_agreement_unicycle.csv")
    assert len(frame) == 4 and set(frame.step) == {1, 2}
    first = frame[(frame.control_fraction == 0) & (frame.step == 1)].iloc[0]
    assert first.max_abs_error < IDEAL_TOL and first.nan_states == 0 and first.nan_gradients == 0
    assert "APPROXIMATE" in (tmp_path / "mjx_agreement_unicycle.md").read_text()
    mjx_agreement.main(argv)
    assert len(pd.read_csv(tmp_path / "mjx_agreement_unicycle.csv")) == 4


def test_mjx_agreement_rejects_a_task_without_mujoco_model_or_bad_fractions():
    from harness import mjx_agreement

    with pytest.raises(ValueError, match="fractions"):
        mjx_agreement.Args(task="unicycle", control_fractions="0,2")
    with pytest.raises(ValueError, match="valid tasks"):
        mjx_agreement.Args(task="pendulum")
