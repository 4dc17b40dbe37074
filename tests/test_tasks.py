"""Tasks: dynamics against the reference vectors, costs, features, augmentation, bad input."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tasks
from tasks import base, unicycle
from conftest import load_dynamics_vectors


def reference(name):
    task = tasks.make(name)
    df = load_dynamics_vectors(name)
    n, m = task.state_dim, task.control_dim
    z, u = df.iloc[:, :n].to_numpy(), df.iloc[:, n : n + m].to_numpy()
    dz = df[[c for c in df.columns if c.startswith("d_")]].to_numpy()
    z_next = df[[c for c in df.columns if c.startswith("next_")]].to_numpy()
    return task, z, u, dz, z_next


@pytest.mark.parametrize("name", ["cartpole", "unicycle"])
def test_derivative_matches_reference(name):
    task, z, u, dz, _ = reference(name)
    got = jax.jit(jax.vmap(task.derivative))(z, u)
    np.testing.assert_allclose(got, dz, rtol=1e-9, atol=0)


@pytest.mark.parametrize("name", ["cartpole", "unicycle"])
def test_step_matches_reference(name):
    """RK4 (cart-pole: 10 sub-steps of 0.01 s; unicycle: 20 of 0.005 s) against the adaptive
    solver's state after 0.1 s, 1e-5 absolute on every component."""
    task, z, u, _, z_next = reference(name)
    got = jax.jit(jax.vmap(task.step))(z, u)
    np.testing.assert_allclose(got, z_next, rtol=0, atol=1e-5)


@pytest.mark.parametrize("name", sorted(tasks.REGISTRY))
def test_forms_are_the_task_functions(name):
    """PILCO moment-matches the forms (policy_feature_map, gp_feature_map, cost_form), the
    particle methods evaluate the functions: at a point (zero covariance) they must agree, for
    every registered task that declares forms (a new task's included), to 1e-12. (The
    cart-pole defines its functions through its forms, so for it only the cost's moment formula
    at zero covariance is checked against the form; the unicycle's functions are written apart.)"""
    from estimators.base import task_moment_forms
    from models.form_moments import expected_cost

    task = tasks.make(name)
    if task_moment_forms(task) is None or task.gp_feature_map is None:
        pytest.skip(f"{name} declares no forms (particle estimators only)")
    points = jax.random.normal(jax.random.key(0), (8, task.model_state_dim))
    zero = jnp.zeros((task.model_state_dim, task.model_state_dim))
    for s in points:
        np.testing.assert_allclose(task.policy_feature_map(s), task.policy_features(s), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(task.gp_feature_map(s), task.gp_features(s), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(expected_cost(task.cost_form, s, zero), task.cost(s), rtol=1e-12, atol=1e-12)


def test_rk4_step_is_the_fourth_order_taylor_map_on_a_linear_ode():
    """For dz/dt = A z one RK4 step is exactly z + hA z + (hA)^2 z / 2 + (hA)^3 z / 6 +
    (hA)^4 z / 24: checks every stage's feed and weight (to rounding, 1e-13)."""
    a = jax.random.normal(jax.random.key(0), (3, 3))
    z = jnp.array([0.3, -1.2, 0.7])
    h, substeps = 0.05, 3
    taylor = sum(jnp.linalg.matrix_power(h * a, k) / math.factorial(k) for k in range(5))
    want = jnp.linalg.matrix_power(taylor, substeps) @ z
    got = base.rk4_step(lambda z, u: a @ z, z, jnp.zeros(1), h * substeps, substeps)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)


def test_reference_columns_are_in_ode_order():
    for name in ("cartpole", "unicycle"):
        task = tasks.make(name)
        df = load_dynamics_vectors(name)
        header = [c.replace("dx", "xdot").replace("dtheta", "thetadot") if name == "cartpole" else c
                  for c in df.columns[: task.state_dim]]
        assert tuple(header) == task.state_names


# ----- costs at hand-computed points -------------------------------------------------------

@pytest.mark.parametrize("scale", [0.5, 1.0])
def test_cartpole_angle_cost(scale):
    """``1 - exp(-a (x^2 + (theta - pi)^2))``: a = 1/2 the authors' convention, 1 the paper's text."""
    task = tasks.make("cartpole", cost="angle", angle_cost_scale=scale)
    assert float(task.cost(jnp.array([0.0, 3.0, -2.0, math.pi]))) == pytest.approx(0.0, abs=1e-15)
    # x = 1, theta = pi: 1 - exp(-a); velocities do not count (Q = diag(1, 1, 0, 0)).
    assert float(task.cost(jnp.array([1.0, 5.0, 5.0, math.pi]))) == pytest.approx(1 - math.exp(-scale), rel=1e-12)
    # x = 0.3, theta = pi - 0.4: 1 - exp(-a (0.09 + 0.16)).
    assert float(task.cost(jnp.array([0.3, 0.0, 0.0, math.pi - 0.4]))) == pytest.approx(1 - math.exp(-0.25 * scale),
                                                                                        rel=1e-12)
    # Raw angle, not wrapped: theta = -pi is 2 pi from the target.
    assert float(task.cost(jnp.array([0.0, 0.0, 0.0, -math.pi]))) == pytest.approx(
        1 - math.exp(-4 * math.pi**2 * scale), rel=1e-12)


def test_the_pipps_preset_takes_the_authors_conventions():
    """The authors' demo: angle cost scale 1/2 and a direct-weight RBF policy; the pilco
    preset keeps PILCO's pseudo-input policy."""
    task = tasks.make("cartpole")
    assert (task.angle_cost_scale, task.rbf_parameterisation) == (0.5, "direct")
    assert tasks.make("cartpole", preset="pilco").rbf_parameterisation == "pseudo_inputs"


def test_cartpole_tip_cost():
    task = tasks.make("cartpole", cost="tip")
    assert float(task.cost(jnp.array([0.0, 0.0, 0.0, math.pi]))) == pytest.approx(0.0, abs=1e-15)
    # Hanging down at x = 0: d^2 = l^2 (1 + 1)^2 = 1, c = 1 - exp(-1 / (2 * 0.0625)) = 1 - exp(-8).
    assert float(task.cost(jnp.zeros(4))) == pytest.approx(1 - math.exp(-8), rel=1e-12)
    # x = 0.1, theta = pi/2: d^2 = (0.1 + 0.5)^2 + 0.25 = 0.61, c = 1 - exp(-0.61 / 0.125).
    assert float(task.cost(jnp.array([0.1, 0.0, 0.0, math.pi / 2]))) == pytest.approx(1 - math.exp(-0.61 / 0.125), rel=1e-12)


def test_unicycle_cost():
    task = tasks.make("unicycle")
    assert float(task.cost(jnp.zeros(10))) == pytest.approx(0.0, abs=1e-15)
    # Upright (theta = psif = 0) with the contact point at (xc, yc) = (0.2, -0.4), yaw pi:
    # dx = 0.2, dy = -0.4, dz = 0, phi / (4 pi) = 1/4.
    s = jnp.zeros(10).at[5].set(0.2).at[6].set(-0.4).at[8].set(math.pi)
    expected = 1 - math.exp(-0.5 * (0.5 * 0.04 + 0.5 * 0.16 + 0.0625))
    assert float(task.cost(s)) == pytest.approx(expected, rel=1e-12)
    # Frame pitched by psif = pi/2: dx = -0.81, dz = 0.22 + 0.81 - 0.22 - 0 = 0.81.
    s = jnp.zeros(10).at[9].set(math.pi / 2)
    expected = 1 - math.exp(-0.5 * (0.5 * 0.81**2 + 8 * 0.81**2))
    assert float(task.cost(s)) == pytest.approx(expected, rel=1e-12)


# ----- features and augmentation --------------------------------------------------------

def test_cartpole_features():
    task = tasks.make("cartpole")
    s = jnp.array([0.3, -1.0, 2.0, math.pi / 6])
    expected = [0.3, -1.0, 2.0, 0.5, math.sqrt(3) / 2]
    np.testing.assert_allclose(task.policy_features(s), expected, rtol=1e-14)
    np.testing.assert_allclose(task.gp_inputs(s, jnp.array([4.0])), expected + [4.0], rtol=1e-14)
    assert task.gp_input_dim == 6 and task.policy_feature_dim == 5
    np.testing.assert_allclose(task.gp_targets(s, s + 1.0), jnp.ones(4))


def test_unicycle_augmentation():
    task = tasks.make("unicycle")
    z = jnp.arange(1.0, 13.0) / 10  # rates 0.1..0.5, x 0.6, y 0.7, angles 0.8..1.2
    z = z.at[8].set(math.pi / 2)  # yaw phi = pi/2: R = -[[0, 1], [-1, 0]]
    s = task.to_model_state(z)
    # [xc, yc] = -[[0, 1], [-1, 0]] [0.6, 0.7] = [-0.7, 0.6]
    expected = [0.1, 0.2, 0.3, 0.4, 0.5, -0.7, 0.6, 0.8, math.pi / 2, 1.1]
    np.testing.assert_allclose(s, expected, rtol=1e-14, atol=1e-15)
    # GP features drop the yaw; the policy sees all of s.
    np.testing.assert_allclose(task.gp_features(s), np.delete(np.asarray(expected), 8), atol=1e-15)
    assert task.gp_input_dim == 11 and task.policy_feature_dim == 10
    # The lift keeps s and zeroes the wheel and turntable angles.
    lifted = task.from_model_state(s)
    np.testing.assert_allclose(lifted, z.at[9].set(0.0).at[11].set(0.0), atol=1e-15)


def test_unicycle_model_step_is_closed():
    """The dynamics do not depend on psiw, psit or the yaw-frame origin: stepping the modelled
    state equals augmenting the stepped ODE state."""
    task = tasks.make("unicycle")
    key = jax.random.key(0)
    z = 0.2 * jax.random.normal(key, (12,))
    u = jnp.array([3.0, -10.0])
    np.testing.assert_allclose(task.model_step(task.to_model_state(z), u),
                               task.to_model_state(task.step(z, u)), atol=1e-12)


def test_unicycle_fall_test():
    task = tasks.make("unicycle")
    upright = jnp.zeros(12)
    assert not bool(task.fallen(upright))
    assert bool(task.fallen(upright.at[7].set(1.6)))  # roll past pi/2
    assert bool(task.fallen(upright.at[10].set(-1.6)))  # frame pitch past pi/2
    assert not bool(task.fallen(upright.at[8].set(3.0)))  # yaw does not count


def test_unicycle_mujoco_state_map():
    """``to_mujoco`` then ``from_mujoco`` is the identity, and the axle's velocity is that of a
    wheel rolling without slip: ``cdot = omega_wheel x (c - contact)``, with the wheel's angular
    velocity ``phidot e_z - thetadot x1 + psiwdot y2`` (yaw, roll about -x, spin about the axle
    y2 = Rz(phi) Rx(-theta) e_y) written here independently of the task's code."""
    task = tasks.make("unicycle")
    for z in np.random.default_rng(3).normal(0.0, 0.5, (5, 12)):
        qpos, qvel = task.to_mujoco(jnp.asarray(z))
        np.testing.assert_allclose(task.from_mujoco(qpos, qvel), z, atol=1e-14)
        dtheta, dphi, dpsiw, theta, phi = z[0], z[1], z[2], z[7], z[8]
        cp, sp, ct, st = np.cos(phi), np.sin(phi), np.cos(theta), np.sin(theta)
        x1 = np.array([cp, sp, 0.0])
        y2 = np.array([-sp * ct, cp * ct, -st])
        up = np.array([-sp * st, cp * st, ct])
        omega = dphi * np.array([0.0, 0.0, 1.0]) - dtheta * x1 + dpsiw * y2
        np.testing.assert_allclose(qvel[:3], np.cross(omega, unicycle.rw * up), atol=1e-14)
        np.testing.assert_allclose(qpos[:3], np.append(z[5:7], 0.0) + unicycle.rw * up, atol=1e-14)


@pytest.mark.parametrize("psif, dpsiw, dpsif, U", [(0.1, 0.0, 0.0, 0.0), (-0.4, 3.0, -2.0, 20.0), (1.0, -5.0, 4.0, -50.0)])
def test_unicycle_planar_equations(psif, dpsiw, dpsif, U):
    """Upright (theta = 0) without yaw or turntable motion, the reference equations are the
    Lagrangian of a wheel (mw, Cw) under a frame (mf at rf) and turntable (mt at r, At), with
    q = (psiw, psif), M = [[(mw + mf + mt) rw^2 + Cw, K rw cos psif], [., mf rf^2 + mt r^2 + I + At]],
    K = mf rf + mt r, and M qddot = [U + K rw sin(psif) psifdot^2, -U + g K sin(psif)] -- with the
    frame's pitch inertia I = Cw (0.0484), not the spec's frame inertia Cf (0.8292). This pins
    down the equations' rigid-body model, which tasks/unicycle.xml copies."""
    u = unicycle
    z = np.zeros(12)
    z[[2, 3, 10]] = dpsiw, dpsif, psif
    acc = np.asarray(tasks.make("unicycle").derivative(jnp.asarray(z), jnp.array([0.0, U])))
    K = u.mf * u.rf + u.mt * u.r
    force = [U + K * u.rw * np.sin(psif) * dpsif**2, -U + u.g * K * np.sin(psif)]
    for pitch_inertia, matches in ((u.Cw, True), (u.Cf, False)):
        m12 = K * u.rw * np.cos(psif)
        M = [[(u.mw + u.mf + u.mt) * u.rw**2 + u.Cw, m12], [m12, u.mf * u.rf**2 + u.mt * u.r**2 + pitch_inertia + u.At]]
        lagrangian = np.linalg.solve(M, force)
        assert np.allclose(acc[[2, 3]], lagrangian, rtol=1e-12, atol=1e-12) == matches
    np.testing.assert_allclose(acc[[0, 1, 4]], 0.0, atol=1e-12)  # no roll, yaw or turntable acceleration


def test_noise_and_presets():
    cp = tasks.make("cartpole")
    std = [0.01, 0.1, math.radians(10), math.radians(1)]  # [x, xdot, thetadot, theta]
    np.testing.assert_allclose(cp.obs_noise_std, std, rtol=1e-12)
    np.testing.assert_allclose(tasks.make("cartpole", noise_k=4.0).obs_noise_std, 2 * np.asarray(std), rtol=1e-12)
    np.testing.assert_allclose(cp.model_noise_std, std, rtol=1e-12)
    assert (cp.horizon, cp.num_basis, cp.cost_type) == (30, 50, "angle")
    pilco = tasks.make("cartpole", preset="pilco")
    assert (pilco.horizon, pilco.num_basis, pilco.cost_type) == (40, 10, "tip")
    np.testing.assert_allclose(pilco.obs_noise_std, 0.01)
    uni = tasks.make("unicycle")
    assert (uni.dt, uni.horizon, uni.num_random_trials, uni.num_learned_trials) == (0.1, 20, 5, 30)
    assert tasks.make("unicycle", preset="pilco").horizon == 67
    np.testing.assert_allclose(uni.model_noise_std, [0.01] * 5 + [0.003] * 5, rtol=1e-12)


# ----- bad input -----------------------------------------------------------------------------

@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: tasks.make("pendulum"), "valid tasks: \\['cartpole', 'unicycle'\\]"),
        (lambda: tasks.make("cartpole", friction=0.2), "valid options"),
        (lambda: tasks.make("cartpole", preset="paper"), "valid presets"),
        (lambda: tasks.make("cartpole", cost="distance"), "valid costs"),
        (lambda: tasks.make("cartpole", noise_k=-1.0), "noise_k"),
        (lambda: tasks.make("cartpole", angle_cost_scale=0.0), "angle_cost_scale"),
        (lambda: tasks.make("cartpole", rbf_parameterisation="gp"), "valid: \\['direct', 'pseudo_inputs'\\]"),
        (lambda: tasks.parse_options("cartpole", "angle_scale=1"), "NAME one of"),
        (lambda: tasks.make("unicycle", horizon=0), "horizon"),
    ],
)
def test_bad_options(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_options_are_listed_and_parsed():
    assert {"cost", "angle_cost_scale", "rbf_parameterisation"} <= set(tasks.options("cartpole"))
    assert "noise_k" in tasks.options("unicycle")
    parsed = tasks.parse_options("cartpole", "angle_cost_scale=1, rbf_parameterisation=pseudo_inputs,horizon=40")
    assert parsed == {"angle_cost_scale": 1.0, "rbf_parameterisation": "pseudo_inputs", "horizon": 40}
    assert "angle_cost_scale=1.0" in tasks.describe(tasks.make("cartpole", **parsed))


def test_wrong_shapes():
    cp, uni = tasks.make("cartpole"), tasks.make("unicycle")
    with pytest.raises(ValueError, match="z \\(ODE state\\) must have shape \\(4,\\)"):
        cp.step(jnp.zeros(5), jnp.zeros(1))
    with pytest.raises(ValueError, match="u \\(control\\) must have shape \\(1,\\)"):
        cp.step(jnp.zeros(4), jnp.zeros(2))
    with pytest.raises(ValueError, match="u \\(control\\) must have shape \\(2,\\)"):
        uni.derivative(jnp.zeros(12), jnp.zeros(1))
    with pytest.raises(ValueError, match="use jax.vmap"):
        cp.cost(jnp.zeros((3, 4)))
    with pytest.raises(ValueError, match="z \\(ODE state\\) must have shape \\(12,\\)"):
        uni.to_model_state(jnp.zeros(10))
    with pytest.raises(ValueError, match="s \\(modelled state\\) must have shape \\(10,\\)"):
        uni.from_model_state(jnp.zeros(12))
