"""Tests of the GP dynamics model (models/gp.py), in float64 (conftest enables x64).

References are independent: dense numpy linear algebra written out from the hyperparameters,
PILCO's gp0 outputs (checked by Monte Carlo, see below), and the cart-pole's true dynamics.
All randomness comes from fixed seeds and keys.
"""

import faulthandler

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tasks
from models import gp
from models.prediction import Prediction
from conftest import load_moment_matching_cases

NUM_TRANSITIONS = 200  # cart-pole training set, a full buffer (padding is tested elsewhere)
CARTPOLE_STEPS = 60  # L-BFGS steps: the objective is within 0.1 nats of its limit by step 50
# Box of ODE states [x, xdot, thetadot, theta] for the random cart-pole transitions: broader
# than a swing-up visits in x, covering its velocities and every angle.
STATE_BOX = np.array([1.0, 3.0, 8.0, np.pi])


# ----- dense numpy reference ---------------------------------------------------------------------
def np_kernel(log_hyp_e, a, b):
    """SE-ARD kernel of one output, written out: sf^2 exp(-1/2 sum_d (a_d - b_d)^2 / l_d^2)."""
    ls, sf2 = np.exp(log_hyp_e[:-2]), np.exp(2 * log_hyp_e[-2])
    d = (a[:, None, :] - b[None, :, :]) / ls
    return sf2 * np.exp(-0.5 * np.sum(d**2, axis=-1))


def np_predict(log_hyp, x_train, y_train, x_test):
    """Dense predictive mean, latent variance, noise variance, each (P, E), via np.linalg.inv."""
    means, variances, noises = [], [], []
    for e, lh in enumerate(log_hyp):
        sf2, sn2 = np.exp(2 * lh[-2]), np.exp(2 * lh[-1])
        k_inv = np.linalg.inv(np_kernel(lh, x_train, x_train) + sn2 * np.eye(len(x_train)))
        k_star = np_kernel(lh, x_test, x_train)  # (P, N)
        means.append(k_star @ k_inv @ y_train[:, e])
        variances.append(sf2 - np.einsum("pn,nm,pm->p", k_star, k_inv, k_star))
        noises.append(np.full(len(x_test), sn2))
    return np.stack(means, 1), np.stack(variances, 1), np.stack(noises, 1)


def np_nlml(log_hyp, x_train, y_train):
    """Dense sum over outputs of 1/2 y^T K^-1 y + 1/2 log|K| + n/2 log(2 pi), slogdet."""
    total, n = 0.0, len(x_train)
    for e, lh in enumerate(log_hyp):
        k = np_kernel(lh, x_train, x_train) + np.exp(2 * lh[-1]) * np.eye(n)
        sign, logdet = np.linalg.slogdet(k)
        assert sign > 0
        y = y_train[:, e]
        total += 0.5 * y @ np.linalg.solve(k, y) + 0.5 * logdet + 0.5 * n * np.log(2 * np.pi)
    return total


def random_problem(seed, n=30, d=3, e=2):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-2, 2, (n, d))
    y = np.stack([np.sin(x @ rng.normal(size=d)) + 0.1 * rng.normal(size=n) for _ in range(e)], 1)
    log_hyp = np.concatenate(
        [rng.uniform(-0.3, 0.7, (e, d)), rng.uniform(-0.5, 0.5, (e, 1)), rng.uniform(-2.5, -1.5, (e, 1))], 1
    )
    x_test = rng.uniform(-2.5, 2.5, (20, d))
    return x, y, log_hyp, x_test


def padded(x, y, valid, rng):
    """GPData holding x, y in the rows where ``valid`` is True and garbage (huge values and a
    NaN row) elsewhere: a non-contiguous mask, to show padding is inert wherever it sits."""
    cap = len(valid)
    xs = rng.normal(size=(cap, x.shape[1])) * 1e3
    ys = rng.normal(size=(cap, y.shape[1])) * 1e3
    xs[valid], ys[valid] = x, y
    pad = np.flatnonzero(~valid)[0]
    xs[pad], ys[pad] = np.nan, np.nan
    return gp.GPData(jnp.asarray(xs), jnp.asarray(ys), jnp.asarray(valid))


# ----- exact formulas against dense numpy ---------------------------------------------------------
def test_predict_difference_matches_dense_numpy_full_and_masked():
    """Tolerance: 1e-9 relative to each output's scale (|y| max for the mean, sf^2 for the
    variances); the Cholesky and np.linalg.inv routes differ by ~cond(K) * 1e-16 (~1e-13 here).
    Also: the stored chol_inv is the inverse of chol."""
    x, y, log_hyp, x_test = random_problem(0)
    rng = np.random.default_rng(1)
    valid = np.zeros(45, bool)
    valid[rng.choice(45, 30, replace=False)] = True
    full = gp.GPData(jnp.asarray(x), jnp.asarray(y), jnp.ones(30, bool))
    for data in (full, padded(x, y, valid, rng)):
        post = gp.check_posterior(gp.posterior(jnp.asarray(log_hyp), data))
        eye = np.broadcast_to(np.eye(data.capacity), post.chol.shape)
        np.testing.assert_allclose(post.chol_inv @ post.chol, eye, rtol=0, atol=1e-12)
        pred = jax.vmap(gp.predict_difference, in_axes=(None, 0))(post, jnp.asarray(x_test))
        mean, var, noise = np_predict(log_hyp, x, y, x_test)
        sf2 = np.exp(2 * log_hyp[:, -2])
        np.testing.assert_allclose(pred.mean, mean, rtol=0, atol=1e-9 * np.abs(y).max())
        np.testing.assert_allclose(pred.model_var, var, rtol=0, atol=1e-9 * sf2.max())
        np.testing.assert_allclose(pred.noise_var, noise, rtol=1e-12)
        assert np.all(var > 1e-6 * sf2)  # the test points are not degenerate ones


def test_truncated_posterior_predicts_like_the_full_buffer():
    """``gp.truncate`` of a buffer filled by add_data (valid rows first) to 30 and 36 of its 45
    rows predicts like dense numpy on the 30 valid rows (tolerances as above); cutting a
    valid row raises."""
    x, y, log_hyp, x_test = random_problem(2)
    data = gp.add_data(gp.empty_data(45, x.shape[1], y.shape[1], jnp.float64), jnp.asarray(x), jnp.asarray(y))
    post = gp.check_posterior(gp.posterior(jnp.asarray(log_hyp), data))
    mean, var, _ = np_predict(log_hyp, x, y, x_test)
    sf2 = np.exp(2 * log_hyp[:, -2])
    for rows in (30, 36):
        cut = gp.truncate(post, rows)
        assert cut.chol_inv.shape == (y.shape[1], rows, rows)
        pred = jax.vmap(gp.predict_difference, in_axes=(None, 0))(cut, jnp.asarray(x_test))
        np.testing.assert_allclose(pred.mean, mean, rtol=0, atol=1e-9 * np.abs(y).max())
        np.testing.assert_allclose(pred.model_var, var, rtol=0, atol=1e-9 * sf2.max())
    with pytest.raises(ValueError, match="valid rows"):
        gp.truncate(post, 29)


def test_trimmed_buffer_has_the_whole_buffers_objective_and_gradient():
    """``gp.trim_data`` of a 45-row buffer holding 30 rows (add_data: valid rows first) to 30
    and 36 rows: the objective of the GP fit and its gradient in the hyperparameters equal the
    whole buffer's to 1e-10 relative (round-off only); cutting a valid row raises."""
    x, y, log_hyp, _ = random_problem(2)
    data = gp.add_data(gp.empty_data(45, x.shape[1], y.shape[1], jnp.float64), jnp.asarray(x), jnp.asarray(y))
    value_and_grad = jax.value_and_grad(gp.objective)
    whole_value, whole_grad = value_and_grad(jnp.asarray(log_hyp), data)
    for rows in (30, 36):
        cut = gp.trim_data(data, rows)
        assert cut.inputs.shape == (rows, x.shape[1]) and int(cut.num_valid) == 30
        value, grad = value_and_grad(jnp.asarray(log_hyp), cut)
        np.testing.assert_allclose(value, whole_value, rtol=1e-10)
        np.testing.assert_allclose(grad, whole_grad, rtol=1e-10, atol=1e-10 * np.abs(whole_grad).max())
    with pytest.raises(ValueError, match="valid rows"):
        gp.trim_data(data, 29)


def test_nlml_matches_dense_numpy_full_and_masked():
    x, y, log_hyp, _ = random_problem(2)
    rng = np.random.default_rng(3)
    valid = np.zeros(41, bool)
    valid[rng.choice(41, 30, replace=False)] = True
    reference = np_nlml(log_hyp, x, y)
    full = gp.GPData(jnp.asarray(x), jnp.asarray(y), jnp.ones(30, bool))
    for data in (full, padded(x, y, valid, rng)):
        value = gp.neg_log_marginal_likelihood(jnp.asarray(log_hyp), data)
        np.testing.assert_allclose(value, reference, rtol=1e-10)


def test_float32_data_stays_float32():
    """A GP built from float32 data computes in float32, and predicts like the float64 numpy
    reference to float32's accuracy: float32 rounds at 6e-8 relative, and the solves with the
    30 x 30 kernel matrix amplify it by its conditioning; measured 2.6e-6 on a mean of size 0.8,
    bound 2e-5."""
    x, y, log_hyp, x_test = random_problem(4)
    data = gp.GPData(jnp.asarray(x, jnp.float32), jnp.asarray(y, jnp.float32), jnp.ones(30, bool))
    post = gp.posterior(jnp.asarray(log_hyp, jnp.float32), data)
    pred = gp.predict_difference(post, jnp.asarray(x_test[0], jnp.float32))
    assert post.chol.dtype == post.chol_inv.dtype == post.alpha.dtype == jnp.float32
    assert all(v.dtype == jnp.float32 for v in pred)
    assert gp.neg_log_marginal_likelihood(post.log_hyp, data).dtype == jnp.float32
    mean, var, _ = np_predict(log_hyp, x, y, x_test[:1])
    np.testing.assert_allclose(pred.mean, mean[0], atol=2e-5)


# ----- PILCO's gp0 reference ------------------------------------------------------------------------
def test_predictions_reproduce_pilco_gp0_by_monte_carlo():
    """``moment_matching.json`` gp0: PILCO's moments of f(x) for a GP (its inputs, targets and
    log_hyp, no training) and a Gaussian input x ~ N(m, s). They are expectations of our point
    predictions: M = E[mu(x)], S = Cov[mu(x)] + diag E[model_var(x)] (latent, no noise), and
    s V = Cov[x, mu(x)]. Each is estimated as a sample mean over 100k draws (fixed key), with
    its own standard error; every entry (6 cases x 44) must satisfy |z| < 4.5 (under exactness
    P(|z| > 4.5) = 7e-6 per entry, about 0.2 % for all of them; measured max 2.7). Leaving
    model_var out of S gives max |z| 9000, adding the noise variance to it 43."""
    cases = [case["gp0"] for case in load_moment_matching_cases()]
    stack = lambda name: jnp.asarray(np.stack([np.asarray(c[name], float) for c in cases]))
    inputs, targets, m, s = stack("inputs"), stack("targets"), stack("m"), stack("s")
    log_hyp = jnp.swapaxes(stack("log_hyp"), 1, 2)  # PILCO's (D+2, E) -> (E, D+2)
    num = 100_000

    @jax.jit
    def moments(key, inputs, targets, log_hyp, m, s):
        data = gp.GPData(inputs, targets, jnp.ones(inputs.shape[0], bool))
        post = gp.posterior(log_hyp, data)
        xs = jax.random.multivariate_normal(key, m, s, (num,))
        pred = jax.vmap(gp.predict_difference, in_axes=(None, 0))(post, xs)
        mean = pred.mean.mean(0)
        d = pred.mean - mean
        s_terms = d[:, :, None] * d[:, None, :] + jax.vmap(jnp.diag)(pred.model_var)
        v_terms = jnp.einsum("ij,nj,nk->nik", jnp.linalg.inv(s), xs - m, d)
        return [(t.mean(0), t.std(0) / np.sqrt(num)) for t in (pred.mean, s_terms, v_terms)]

    keys = jax.random.split(jax.random.key(0), len(cases))
    estimates = jax.vmap(moments)(keys, inputs, targets, log_hyp, m, s)
    worst = 0.0
    for (est, se), name in zip(estimates, ("M", "S", "V")):
        ref = np.stack([np.asarray(c[name], float) for c in cases])
        z = np.abs(np.asarray(est) - ref) / np.asarray(se)
        worst = max(worst, z.max())
        assert z.max() < 4.5, (name, z.max())
    print(f"\ngp0 Monte Carlo check: max |z| = {worst:.2f} over {len(cases)} cases")


# ----- the buffer -----------------------------------------------------------------------------------
def test_add_data_appends_after_held_rows_and_respects_mask():
    data = gp.empty_data(6, 2, 1, jnp.float64)
    a_in = jnp.arange(6.0).reshape(3, 2)
    a_out = jnp.arange(3.0)[:, None] + 100
    data = gp.add_data(data, a_in, a_out, jnp.array([True, False, True]))
    np.testing.assert_array_equal(data.mask, [1, 1, 0, 0, 0, 0])
    np.testing.assert_array_equal(data.inputs[:2], a_in[jnp.array([0, 2])])
    np.testing.assert_array_equal(data.targets[:2, 0], [100, 102])
    b_in, b_out = -jnp.ones((3, 2)), -jnp.ones((3, 1))
    jitted = jax.jit(gp.add_data)(data, b_in, b_out, jnp.array([True, True, True]))
    data = gp.add_data(data, b_in, b_out)
    for got, want in zip(jitted, data):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(data.mask, [1, 1, 1, 1, 1, 0])
    np.testing.assert_array_equal(data.inputs[2:5], b_in)
    np.testing.assert_array_equal(data.inputs[:2], a_in[jnp.array([0, 2])])  # untouched
    assert data.inputs.dtype == jnp.float64 and int(data.num_valid) == 5

    # Two more rows would overflow: a concrete call raises, naming capacity and rows asked.
    with pytest.raises(ValueError, match=r"capacity 6.*2 rows asked"):
        gp.add_data(data, b_in[:2], b_out[:2])
    gp.add_data(data, b_in, b_out, jnp.array([False, True, False]))  # exactly fills: fine
    # Traced (inside jit), rows past the capacity are dropped and the held rows kept.
    dropped = jax.jit(gp.add_data)(data, b_in * 7, b_out, jnp.ones(3, bool))
    assert int(dropped.num_valid) == 6
    np.testing.assert_array_equal(dropped.inputs[5], b_in[0] * 7)
    np.testing.assert_array_equal(dropped.inputs[:5], data.inputs[:5])
    with pytest.raises(ValueError, match="inputs"):
        gp.add_data(data, b_in[:, :1], b_out)


# ----- cart-pole: training and prediction on the real dynamics ---------------------------------------
@pytest.fixture(scope="module")
def cartpole():
    """Random cart-pole transitions: ODE states uniform in +-STATE_BOX, u ~ U[-10, 10], the next
    state by task.step, both states observed with the task's noise (pipps preset, k = 1).
    Returns the task, training data, held-out inputs and targets, the training result and the
    checked posterior."""
    task = tasks.make("cartpole")

    @jax.jit
    def transitions(key):
        k_z, k_u, k_o1, k_o2 = jax.random.split(key, 4)
        z = jax.random.uniform(k_z, (NUM_TRANSITIONS, 4), minval=-STATE_BOX, maxval=STATE_BOX)
        u = jax.random.uniform(k_u, (NUM_TRANSITIONS, 1), minval=-10.0, maxval=10.0)
        z_tp1 = jax.vmap(task.step)(z, u)
        o_t = jax.vmap(task.observe)(z, jax.random.split(k_o1, NUM_TRANSITIONS))
        o_tp1 = jax.vmap(task.observe)(z_tp1, jax.random.split(k_o2, NUM_TRANSITIONS))
        return jax.vmap(task.gp_inputs)(o_t, u), jax.vmap(task.gp_targets)(o_t, o_tp1)

    data = gp.add_data(gp.empty_data(NUM_TRANSITIONS, task.gp_input_dim, task.model_state_dim),
                       *transitions(jax.random.key(0)))
    result = gp.train(data, num_steps=CARTPOLE_STEPS)
    return dict(task=task, data=data, test=transitions(jax.random.key(1)), result=result,
                post=gp.check_posterior(gp.posterior(result.log_hyp, data)))


def test_training_raises_marginal_likelihood(cartpole):
    """60 L-BFGS steps from ``init_log_hyp`` take the cart-pole NLML from 394.19 to -675.96
    (measured, 200 transitions, 4 outputs): the bound asks for half that gain, 535 nats."""
    data, result = cartpole["data"], cartpole["result"]
    before = float(gp.neg_log_marginal_likelihood(gp.init_log_hyp(data), data))
    after = float(gp.neg_log_marginal_likelihood(result.log_hyp, data))
    print(f"\ncart-pole NLML (200 transitions, 4 outputs): initial {before:.2f}, trained {after:.2f}")
    history = np.asarray(result.history)
    assert np.all(np.isfinite(history))
    assert after < before - 535.0
    # L-BFGS with a line search only accepts decreases of the objective.
    assert np.all(np.diff(history) <= 1e-9 * np.abs(history[:-1]))
    assert np.isclose(history[-1], gp.objective(result.log_hyp, data), rtol=1e-12)


def test_gp_beats_prior_on_held_out_cartpole_transitions(cartpole):
    """R^2 = 1 - SSE / sum (y - mean(y))^2 on 200 held-out noisy transitions, per dimension
    (the usual R^2: stricter than comparing with the zero-mean prior, whose R^2 <= 0).
    Threshold 0.9: measured 0.94-0.996 for six train/test key pairs, the difference of xdot
    lowest (it depends on u, theta and thetadot^2 at once); a broken fit lands near 0 or below.
    The mean squared standardised residual (y - mu)^2 / (model_var + noise_var) must lie in
    [0.5, 2] (measured 0.77-1.42 for those pairs): the variances are calibrated, not just the
    means."""
    x_test, y_test = cartpole["test"]
    pred = jax.vmap(gp.predict_difference, in_axes=(None, 0))(cartpole["post"], x_test)
    y, mu = np.asarray(y_test), np.asarray(pred.mean)
    r2 = 1 - ((y - mu) ** 2).sum(0) / ((y - y.mean(0)) ** 2).sum(0)
    z2 = ((y - mu) ** 2 / np.asarray(pred.var)).mean(0)
    names = cartpole["task"].model_state_names
    print("\nheld-out R^2:", ", ".join(f"d{n} {v:.4f}" for n, v in zip(names, r2)))
    print("mean standardised squared residual:", ", ".join(f"d{n} {v:.3f}" for n, v in zip(names, z2)))
    assert np.all(r2 > 0.9), r2
    assert np.all((z2 > 0.5) & (z2 < 2.0)), z2


@pytest.fixture(scope="module")
def noise_free():
    """60 noise-free rows in a buffer of 64, D = 6, E = 4: smooth functions of x0 and x1 only,
    so the likelihood alone drives the noise to 0 and the other length-scales to infinity."""
    rng = np.random.default_rng(7)
    x = rng.uniform(-2, 2, (60, 6))
    y = np.stack([np.sin(x[:, 0]) * np.cos(x[:, 1]), x[:, 0] * x[:, 1], np.exp(-x[:, 0] ** 2),
                  np.sin(2 * x[:, 1])], 1)
    return gp.add_data(gp.empty_data(64, 6, 4), jnp.asarray(x), jnp.asarray(y))


def test_curb_penalty_formula():
    data = gp.GPData(jnp.asarray([[0.0, 0.0], [1.0, 2.0], [2.0, 4.0]]), jnp.asarray([[0.0], [1.0], [5.0]]),
                     jnp.array([True, True, True]))
    x_std, y_std = np.array([1.0, 2.0]), np.std([0.0, 1.0, 5.0], ddof=1)
    np.testing.assert_allclose(gp.data_scales(data)[0], x_std, rtol=1e-12)
    inside = np.log([[1.0, 2.0, y_std, y_std / 10]])
    assert float(gp.curb_penalty(jnp.asarray(inside), data)) == 0.0
    # length-scale 1 log unit past 100 std, sf/sn 2 past 500 (noise also 0.5 under the floor)
    outside = np.log([[np.e * 100, 2.0, y_std, y_std / (500 * np.e**2)]])
    floor_gap = np.log(1e-3 * y_std) - outside[0, -1]
    expected = 3 * (1.0 + 4.0 + floor_gap**2)  # weight 1, n_valid 3
    np.testing.assert_allclose(gp.curb_penalty(jnp.asarray(outside), data), expected, rtol=1e-12)
    curb = gp.Curb(lengthscale_max_ratio=1e3, snr_max=1e4, noise_min_ratio=1e-9, weight=2.0)
    assert float(gp.curb_penalty(jnp.asarray(outside), data, curb)) == 0.0


def test_curb_holds_noise_free_fit_at_bounds(noise_free):
    """With the default Curb every fitted value lies within 0.25 log units of its bound (the
    penalty is soft); the plain NLML's gradient there still pushes outward (noise down,
    irrelevant length-scales up), so the curb, not the data, holds them. Without a curb
    (weight 0) this fit measured sf/sn up to 10.9 log units past 500, the noise 10.7 under the
    floor and length-scales up to 21 past 100 std."""
    data = noise_free
    x_std, y_std = (np.asarray(v) for v in gp.data_scales(data))
    lh = np.asarray(gp.train(data).log_hyp)
    snr_excess = lh[:, -2] - lh[:, -1] - np.log(500.0)
    floor_deficit = np.log(1e-3 * y_std) - lh[:, -1]
    ls_excess = lh[:, :-2] - np.log(100 * x_std)
    assert snr_excess.max() < 0.25 and floor_deficit.max() < 0.25 and ls_excess.max() < 0.25
    assert np.all(np.maximum(snr_excess, floor_deficit) > -0.25)  # each output's noise at a bound
    grad = np.asarray(jax.grad(gp.neg_log_marginal_likelihood)(jnp.asarray(lh), data))
    assert np.all(grad[:, -1] > 1.0), grad[:, -1]  # the likelihood wants less noise
    at_bound = ls_excess > -0.25
    assert at_bound[:, 2:].all() and np.all(grad[:, :-2][at_bound] < -1.0)  # and longer scales


def test_train_vmaps_over_buffers(noise_free):
    """One compiled training for a batch of buffers (as for seeds): the full buffer and its first
    40 rows (mask). Each member reaches the objective value its own unbatched run reaches
    (relative 1e-6: batched and unbatched kernels may round differently, and L-BFGS amplifies).

    Also the regression test for the jaxlib 0.10 CPU deadlock of concurrent batched LAPACK calls
    (see models/gp.py, "linear algebra"): with plain jnp.linalg.cholesky this call hung at 0 %
    CPU on 2 cores. faulthandler ends the run with a traceback after 300 s rather than let CI
    hang."""
    subset = noise_free._replace(mask=noise_free.mask & (jnp.arange(64) < 40))
    batch = jax.tree.map(lambda a, b: jnp.stack([a, b]), noise_free, subset)
    faulthandler.dump_traceback_later(300, exit=True)
    try:
        batched = jax.block_until_ready(jax.jit(jax.vmap(gp.train))(batch))
    finally:
        faulthandler.cancel_dump_traceback_later()
    for i, data in enumerate((noise_free, subset)):
        single = gp.train(data)
        np.testing.assert_allclose(batched.history[i, -1], single.history[-1], rtol=1e-6)
        np.testing.assert_allclose(gp.objective(batched.log_hyp[i], data), single.history.min(), rtol=1e-6)


def test_gp_model_predict_and_shape_errors(cartpole):
    task, post = cartpole["task"], cartpole["post"]
    model = gp.GPModel(task)
    s, u = jnp.array([0.1, -0.2, 0.3, 3.0]), jnp.array([2.0])
    pred = jax.jit(model.predict)(post, s, u)
    diff = gp.predict_difference(post, task.gp_inputs(s, u))
    sf2 = np.exp(2 * np.asarray(post.log_hyp[:, -2]))
    assert isinstance(pred, Prediction) and pred.mean.shape == (4,)
    np.testing.assert_allclose(pred.mean, s + diff.mean, rtol=1e-12)
    # jit and eager round differently; model_var = sf^2 - k^T K^-1 k loses digits by cancellation
    np.testing.assert_allclose(pred.model_var, diff.model_var, rtol=0, atol=1e-12 * sf2.max())
    np.testing.assert_allclose(pred.noise_var, np.exp(2 * np.asarray(post.log_hyp[:, -1])), rtol=1e-12)
    # prediction supports forward- and reverse-mode derivatives alike
    jac_fwd = jax.jacfwd(lambda s: model.predict(post, s, u).mean)(s)
    jac_rev = jax.jacrev(lambda s: model.predict(post, s, u).mean)(s)
    np.testing.assert_allclose(jac_fwd, jac_rev, rtol=1e-10, atol=1e-12)
    # one step of the learned model is close to the truth at a typical state
    np.testing.assert_allclose(pred.mean, task.step(s, u), atol=4 * np.sqrt(np.asarray(pred.var)).max())
    for bad_s, bad_u in [(s[:3], u), (s[:, None], u), (s, jnp.array([1.0, 2.0])), (s, u[0])]:
        with pytest.raises(ValueError, match="shape"):
            model.predict(post, bad_s, bad_u)
        with pytest.raises(ValueError, match="shape"):
            jax.jit(model.predict)(post, bad_s, bad_u)


# ----- failures are loud ------------------------------------------------------------------------------
def test_nan_inputs_make_fit_raise(noise_free):
    broken = noise_free._replace(inputs=noise_free.inputs.at[17, 2].set(jnp.nan))
    with pytest.raises(gp.CholeskyError, match="jax_enable_x64") as info:
        gp.fit(broken)
    assert isinstance(info.value, ValueError)
    assert "valid rows of the training inputs contain NaN" in str(info.value)
    # NaN in a padding row is inert
    gp.check_posterior(gp.posterior(gp.init_log_hyp(noise_free), noise_free._replace(
        inputs=noise_free.inputs.at[62].set(jnp.nan))))


def test_numerically_singular_kernel_makes_check_posterior_raise():
    """Each input three times and a noise std of e^-40: K + sn^2 I is positive definite on paper
    but singular in float64, so the Cholesky factorisation returns NaN. In a batch (as from a
    vmap over seeds) only the broken member is named."""
    rng = np.random.default_rng(5)
    x = np.tile(rng.uniform(-2, 2, (5, 3)), (3, 1))
    y = rng.normal(size=(15, 2))
    data = gp.GPData(jnp.asarray(x), jnp.asarray(y), jnp.ones(15, bool))
    good = np.zeros((2, 5))
    good[:, -1] = -2.0
    bad = good.copy()
    bad[1, -1] = -40.0
    gp.check_posterior(gp.posterior(jnp.asarray(good), data))
    with pytest.raises(gp.CholeskyError, match="duplicate"):
        gp.check_posterior(gp.posterior(jnp.asarray(bad), data))
    batch = jax.vmap(gp.posterior, in_axes=(0, None))(jnp.asarray(np.stack([good, bad])), data)
    with pytest.raises(gp.CholeskyError, match=r"\[\[1, 1\]\]"):
        gp.check_posterior(batch)


def test_explained_variance_and_its_custom_derivatives():
    """``|L^-1 k|^2`` and its custom JVP (tangent ``2 (K^-1 k) . dk``, plus the term of a
    perturbed L^-1) against autodiff of the plain expression and finite differences, forward
    and reverse mode, to second order (jax.test_util.check_grads)."""
    from jax.test_util import check_grads

    chol = jnp.tril(jax.random.normal(jax.random.key(0), (6, 6))) + 3.0 * jnp.eye(6)
    chol_inv, k = jnp.linalg.inv(chol), jax.random.normal(jax.random.key(1), (6,))
    plain = lambda a, b: jnp.sum((a @ b) ** 2)  # noqa: E731
    np.testing.assert_allclose(gp.explained_variance(chol_inv, k), plain(chol_inv, k), rtol=1e-14)
    for got, want in zip(jax.grad(gp.explained_variance, argnums=(0, 1))(chol_inv, k),
                         jax.grad(plain, argnums=(0, 1))(chol_inv, k)):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(jax.jacfwd(gp.explained_variance, argnums=1)(chol_inv, k),
                               jax.grad(plain, argnums=1)(chol_inv, k), rtol=1e-12, atol=1e-14)
    check_grads(gp.explained_variance, (chol_inv, k), order=2, modes=["fwd", "rev"])
