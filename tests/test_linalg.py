"""Tests of numerics/linalg.py: the solves against numpy, their derivatives against finite
differences, and the structural guard against the jaxlib 0.10 CPU deadlock: no program the
learning experiment runs may contain a LAPACK call with batch dimensions (float64, fixed seeds).
"""

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import estimators
import tasks
from estimators.base import task_problem
from harness.episodic import evaluate_policy, policy_optimiser
from models import gp
from numerics.linalg import cholesky, cholesky_small, solve_det, solve_lower, solve_lower_t, solve_triangular_small
from tasks.rollout import run_episode

jax.config.update("jax_enable_x64", True)


def random_spd(key, n):
    a = jax.random.normal(key, (n, n))
    return a @ a.T + n * jnp.eye(n)


@pytest.mark.parametrize("n", [5, 20])  # unrolled and looped elimination
def test_solve_det_matches_numpy_and_differentiates(n):
    a = jax.random.normal(jax.random.key(0), (n, n)) + 3.0 * np.sqrt(n) * jnp.eye(n)  # well conditioned
    b = jax.random.normal(jax.random.key(1), (n, 3))
    x, det = jax.jit(solve_det)(a, b)
    np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(det, np.linalg.det(a), rtol=1e-10)
    # pivoting: a zero leading entry is no problem
    swapped = jnp.array([[0.0, 2.0], [3.0, 1.0]])
    np.testing.assert_allclose(solve_det(swapped, jnp.eye(2))[0], np.linalg.inv(swapped), rtol=1e-14)
    np.testing.assert_allclose(solve_det(swapped, jnp.eye(2))[1], -6.0, rtol=1e-14)
    check_grads(solve_det, (a, b), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)
    batched = jax.vmap(solve_det, in_axes=(None, 1))(a, b[:, :, None])[0]
    np.testing.assert_allclose(batched[..., 0].T, x, rtol=1e-12, atol=1e-14)
    with pytest.raises(ValueError, match=r"a \(n, n\) and b \(n, k\)"):
        solve_det(a, b[:, 0])


def test_cholesky_and_triangular_solves_batch_and_differentiate():
    a = jax.vmap(random_spd, in_axes=(0, None))(jax.random.split(jax.random.key(2), 3), 6)
    b = jax.random.normal(jax.random.key(3), (3, 6, 2))
    chol = jax.vmap(cholesky)(a)
    np.testing.assert_allclose(chol, np.linalg.cholesky(a), rtol=1e-12)
    x = jax.vmap(solve_lower)(chol, b)
    np.testing.assert_allclose(np.einsum("bij,bjk->bik", chol, x), b, rtol=1e-12, atol=1e-12)
    xt = jax.vmap(solve_lower_t, in_axes=(None, 0))(chol[0], b)  # shared matrix, batched rhs
    np.testing.assert_allclose(np.einsum("ji,bjk->bik", chol[0], xt), b, rtol=1e-12, atol=1e-12)

    def spd_cholesky(m):  # the derivative of a symmetric input, as the callers use it
        return cholesky(0.5 * (m + m.T))

    check_grads(spd_cholesky, (a[0],), order=1, modes=("rev",), atol=1e-6, rtol=1e-6)
    check_grads(solve_lower, (chol[0], b[0]), order=1, modes=("rev",), atol=1e-6, rtol=1e-6)
    check_grads(solve_lower_t, (chol[0], b[0]), order=1, modes=("rev",), atol=1e-6, rtol=1e-6)
    assert np.isnan(cholesky(-jnp.eye(2))).any()  # failure is NaN, for the callers to check


@pytest.mark.parametrize("n", [5, 12])  # unrolled and looped
def test_small_cholesky_and_triangular_solves_match_lapack_and_differentiate(n):
    a = random_spd(jax.random.key(0), n)
    b = jax.random.normal(jax.random.key(1), (n, 3))
    chol = jax.jit(cholesky_small)(a)
    np.testing.assert_allclose(chol, np.linalg.cholesky(np.asarray(a)), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(solve_triangular_small(chol, b, lower=True),
                               jax.scipy.linalg.solve_triangular(chol, b, lower=True), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(solve_triangular_small(chol.T, b[:, 0], lower=False),
                               jax.scipy.linalg.solve_triangular(chol.T, b[:, 0], lower=False), rtol=1e-12, atol=1e-13)
    check_grads(lambda m: cholesky_small(m @ m.T + n * jnp.eye(n)), (a,), order=1, modes=("fwd", "rev"),
                atol=1e-6, rtol=1e-6)
    check_grads(lambda t, y: solve_triangular_small(t, y, lower=True), (chol, b), order=1, modes=("fwd", "rev"),
                atol=1e-6, rtol=1e-6)
    assert np.isnan(cholesky_small(-jnp.eye(2))).any()  # not positive definite: NaN


# ----- the deadlock guard -------------------------------------------------------------------------
def batched_lapack_calls(fn, *args) -> list[str]:
    """Names of the LAPACK calls in ``jit(fn)``'s lowered program that carry batch dimensions
    (the calls that deadlock jaxlib 0.10 on CPU when two run at once; see numerics/linalg.py)."""
    text = jax.jit(fn).lower(*args).as_text()
    return [re.search(r"@(\w+)", line).group(1) for line in text.splitlines()
            if "lapack" in line and 'num_batch_dims = "0"' not in line]


def test_the_guard_sees_a_batched_lapack_call():
    a = jnp.stack([jnp.eye(3)] * 2)
    assert batched_lapack_calls(jax.vmap(jnp.linalg.cholesky), a) == ["lapack_dpotrf_ffi"]
    assert batched_lapack_calls(jax.vmap(cholesky), a) == []


def test_off_the_cpu_a_batch_goes_to_the_batched_solver(monkeypatch):
    """The GPU branch, forced on the CPU (``native_batching``): the vmapped Cholesky and solves
    become single batched calls (no loop), with the loop's results and derivatives."""
    a = jax.vmap(random_spd, in_axes=(0, None))(jax.random.split(jax.random.key(4), 3), 6)
    b = jax.random.normal(jax.random.key(5), (3, 6, 2))

    def programs(x, y):
        chol = jax.vmap(cholesky)(x)
        return chol, jax.vmap(solve_lower)(chol, y), jax.vmap(solve_lower_t)(chol, y)

    def loss(x, y):
        return sum(jnp.sum(jnp.sin(z)) for z in programs(0.5 * (x + jnp.swapaxes(x, 1, 2)), y))

    looped, looped_grad = programs(a, b), jax.grad(loss, argnums=(0, 1))(a, b)
    assert batched_lapack_calls(programs, a, b) == []
    monkeypatch.setattr("numerics.linalg.native_batching", lambda: True)
    jax.clear_caches()  # the traces above chose the CPU branch
    assert sorted(set(batched_lapack_calls(programs, a, b))) == ["lapack_dpotrf_ffi", "lapack_dtrsm_ffi"]
    assert "while" not in str(jax.make_jaxpr(programs)(a, b))  # no lax.map left
    for native, loop in zip(programs(a, b) + jax.grad(loss, argnums=(0, 1))(a, b), looped + looped_grad):
        np.testing.assert_allclose(native, loop, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("task_name", [pytest.param("cartpole", marks=pytest.mark.slow), "unicycle"])
def test_the_mjx_step_batches_no_lapack_call(task_name):
    """Regression test for a unicycle TP estimate through contact (P = 300) that hung at 0 % CPU
    in two batched triangular solves: MJX's Cholesky factorisations, vmapped over particles. (The
    cart-pole's MJX step, without contact, has no LAPACK call at all today: its case is slow, for a
    model that gains one.)"""
    from tasks.mjx_dynamics import mjx_step_fn

    task = tasks.make(task_name)
    step = mjx_step_fn(task)
    z, u = jnp.tile(task.init_mean, (3, 1)), jnp.zeros((3, task.control_dim))
    assert batched_lapack_calls(jax.vmap(step), z, u) == []
    assert batched_lapack_calls(jax.vmap(jax.grad(lambda z, u: jnp.sum(step(z, u) ** 2), argnums=(0, 1))), z, u) == []


def batched_learning_programs(task_name: str, options: dict, methods: list[str]):
    """The programs one learning trial runs, each vmapped over two seeds as ``harness.learn``
    runs them: the GP fit, each method's policy optimisation (2 steps, 4 particles), the real
    trial, the evaluation. Yields (name, fn, args)."""
    task = tasks.make(task_name, **options)
    seeds = jax.random.split(jax.random.key(0), 2)
    problem = task_problem(task, gp.GPModel(task))
    data = jax.tree.map(lambda x: jnp.broadcast_to(x, (2,) + x.shape), problem.model.empty_data(2 * task.horizon))
    fit = jax.vmap(lambda d: gp.posterior(gp.train(d, num_steps=2).log_hyp, d))
    yield "gp fit", fit, (data,)
    problem = dataclasses.replace(problem, model_params=jax.eval_shape(fit, data))
    theta = jax.vmap(problem.policy.init)(seeds)
    for method in methods:
        yield method, jax.vmap(policy_optimiser(method, 2, 4)), (problem, theta, seeds)
    yield "trial", jax.vmap(lambda k, th: run_episode(task, k, problem.policy, th)), (seeds, theta)
    yield "evaluation", jax.vmap(lambda k, th: evaluate_policy(task, problem.policy, th, k, 2)), (seeds, theta)


PSEUDO_INPUTS = {"rbf_parameterisation": "pseudo_inputs"}  # the RBF weight solve, under jacfwd in TP


@pytest.mark.parametrize("task_name, options, methods", [
    # GR's resampling Cholesky, the weight solve under TP's jacfwd, PILCO's moment matching:
    ("cartpole", PSEUDO_INPUTS, ["gr", "pilco", "tp"]),
    ("unicycle", {}, []),  # its own LAPACK call was the mass-matrix solve of the real trials
    pytest.param("cartpole", PSEUDO_INPUTS, sorted(estimators.REGISTRY), marks=pytest.mark.slow),
    pytest.param("cartpole", {"rbf_parameterisation": "direct"}, sorted(estimators.REGISTRY), marks=pytest.mark.slow),
])
def test_no_learning_program_batches_a_lapack_call(task_name, options, methods):
    """Regression test for the learning runs that hung at 0 % CPU (GR's resampling Cholesky,
    the RBF policy's weight solve under jacfwd, the unicycle's mass-matrix solve were batched).
    The default suite lowers the three methods with distinct linear algebra; -m slow, all."""
    found = {name: calls for name, fn, args in batched_learning_programs(task_name, options, methods)
             if (calls := batched_lapack_calls(fn, *args))}
    assert found == {}
