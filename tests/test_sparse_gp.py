"""Tests of the FITC sparse GP (models/sparse_gp.py), in float64 (conftest enables x64).

References: the FITC formulas written out in dense numpy (np.linalg.inv and slogdet), the full
GP (which FITC equals when the inducing inputs are the training inputs), and, on cart-pole
transitions, the full GP's held-out accuracy. Fixed seeds and keys throughout.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tasks
from harness.episodic import add_episode
from models import gp, sparse_gp
from models import moment_matching as mm
from tasks.rollout import run_episode
from test_gp import np_kernel, padded, random_problem


def np_fitc(log_hyp, x, y, inducing, x_test):
    """Dense FITC per output: (nlml summed over outputs, mean (P, E), model_var (P, E),
    K_uu^-1 - Sigma^-1 (E, M, M), K_uu^-1 (E, M, M)), K_uu with the module's jitter."""
    nlml, means, variances, var_mats, k_uu_invs = 0.0, [], [], [], []
    n, m = len(x), len(inducing)
    for e, lh in enumerate(log_hyp):
        sf2, sn2 = np.exp(2 * lh[-2]), np.exp(2 * lh[-1])
        k_uu = np_kernel(lh, inducing, inducing) + sparse_gp.JITTER * sf2 * np.eye(m)
        k_uf = np_kernel(lh, inducing, x)
        q_ff = k_uf.T @ np.linalg.inv(k_uu) @ k_uf
        lam = sf2 - np.diag(q_ff) + sn2
        cov = q_ff + np.diag(lam)
        sign, logdet = np.linalg.slogdet(cov)
        assert sign > 0
        nlml += 0.5 * y[:, e] @ np.linalg.solve(cov, y[:, e]) + 0.5 * logdet + 0.5 * n * np.log(2 * np.pi)
        sigma = k_uu + k_uf @ np.diag(1 / lam) @ k_uf.T
        beta = np.linalg.solve(sigma, k_uf @ (y[:, e] / lam))
        var_mat = np.linalg.inv(k_uu) - np.linalg.inv(sigma)
        k_star = np_kernel(lh, x_test, inducing)
        means.append(k_star @ beta)
        variances.append(sf2 - np.einsum("pm,mk,pk->p", k_star, var_mat, k_star))
        var_mats.append(var_mat)
        k_uu_invs.append(np.linalg.inv(k_uu))
    return nlml, np.stack(means, 1), np.stack(variances, 1), np.stack(var_mats), np.stack(k_uu_invs)


def predict(post, x_test):
    return jax.vmap(gp.predict_difference, in_axes=(None, 0))(post, jnp.asarray(x_test))


def test_fitc_matches_dense_numpy_full_and_masked():
    """12 inducing inputs (training inputs moved by N(0, 0.3^2)) for 30 points, in a full buffer
    and in a padded one with NaN padding: the NLML within 1e-9 relative, the predictive mean
    within 1e-8 |y|max and the model variance within 1e-8 sf^2 of dense numpy (the two routes
    differ by cond(K_uu) ~ 1e5 times round-off); the variance factor W satisfies
    W^T W = K_uu^-1 - Sigma^-1 + JITTER K_uu^-1 (the jitter on I - B^-1) to 1e-9 |K_uu^-1|."""
    x, y, log_hyp, x_test = random_problem(3)
    rng = np.random.default_rng(4)
    inducing = x[rng.choice(30, 12, replace=False)] + 0.3 * rng.normal(size=(12, x.shape[1]))
    nlml, mean, var, var_mat, k_uu_inv = np_fitc(log_hyp, x, y, inducing, x_test)
    valid = np.zeros(40, bool)
    valid[rng.choice(40, 30, replace=False)] = True
    full = gp.GPData(jnp.asarray(x), jnp.asarray(y), jnp.ones(30, bool))
    sf2 = np.exp(2 * log_hyp[:, -2])
    for data in (full, padded(x, y, valid, rng)):
        got = sparse_gp.fitc_neg_log_marginal_likelihood(jnp.asarray(inducing), jnp.asarray(log_hyp), data)
        np.testing.assert_allclose(got, nlml, rtol=1e-9)
        post = gp.check_posterior(sparse_gp.fitc_posterior(jnp.asarray(inducing), jnp.asarray(log_hyp), data))
        pred = predict(post, x_test)
        np.testing.assert_allclose(pred.mean, mean, rtol=0, atol=1e-8 * np.abs(y).max())
        np.testing.assert_allclose(pred.model_var, var, rtol=0, atol=1e-8 * sf2.max())
        w_t_w = np.einsum("eki,ekj->eij", post.chol_inv, post.chol_inv)
        np.testing.assert_allclose(w_t_w, var_mat + sparse_gp.JITTER * k_uu_inv, rtol=0,
                                   atol=1e-9 * np.abs(k_uu_inv).max())
        assert np.all(var > 1e-4 * sf2)  # the test points are not degenerate ones


def test_fitc_with_the_training_inputs_as_inducing_inputs_is_the_full_gp():
    """u = x makes K_ff - Q_ff = 0, so FITC is the full GP: means within 1e-6 |y|max and model
    variances within 1e-6 sf^2 (the jitter 1e-8 sf^2 on K_uu, amplified by cond(K_uu) ~ 1e3);
    the NLMLs within 1e-6 relative."""
    x, y, log_hyp, x_test = random_problem(5)
    data = gp.GPData(jnp.asarray(x), jnp.asarray(y), jnp.ones(30, bool))
    full = gp.posterior(jnp.asarray(log_hyp), data)
    sparse = sparse_gp.fitc_posterior(jnp.asarray(x), jnp.asarray(log_hyp), data)
    a, b = predict(full, x_test), predict(sparse, x_test)
    sf2 = np.exp(2 * log_hyp[:, -2])
    np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=1e-6 * np.abs(y).max())
    np.testing.assert_allclose(b.model_var, a.model_var, rtol=0, atol=1e-6 * sf2.max())
    np.testing.assert_allclose(sparse_gp.fitc_neg_log_marginal_likelihood(jnp.asarray(x), jnp.asarray(log_hyp), data),
                               gp.neg_log_marginal_likelihood(jnp.asarray(log_hyp), data), rtol=1e-6)


def test_moment_matching_on_a_fitc_posterior_uses_its_variance_matrix():
    """PILCO's gp0 moments of a FITC posterior equal ``gp_moments`` on the inducing inputs with
    beta and K_uu^-1 - Sigma^-1 from dense numpy (pilco-matlab's gp1): rtol 1e-7."""
    x, y, log_hyp, _ = random_problem(6)
    inducing = x[:10] + 0.1
    _, _, _, var_mat, _ = np_fitc(log_hyp, x, y, inducing, x[:1])
    data = gp.GPData(jnp.asarray(x), jnp.asarray(y), jnp.ones(30, bool))
    post = sparse_gp.fitc_posterior(jnp.asarray(inducing), jnp.asarray(log_hyp), data)
    m, s = np.array([0.2, -0.4, 0.3]), np.diag([0.3, 0.2, 0.4])
    got = mm.gp_posterior_moments(post, jnp.asarray(m), jnp.asarray(s))
    expected = mm.gp_moments(jnp.asarray(inducing), post.alpha, jnp.asarray(log_hyp), jnp.asarray(m), jnp.asarray(s),
                             jnp.asarray(var_mat))
    for name in mm.Moments._fields:
        np.testing.assert_allclose(getattr(got, name), getattr(expected, name), rtol=1e-7, atol=1e-12)


def test_training_the_inducing_inputs_lowers_the_fitc_nlml():
    """From evenly spread training inputs, 30 L-BFGS steps on 10 inducing inputs for 30 points:
    the NLML never rises (line search) and ends at least 1 nat lower; the fit keeps the best."""
    x, y, log_hyp, _ = random_problem(7)
    data = gp.GPData(jnp.asarray(x), jnp.asarray(y), jnp.ones(30, bool))
    np.testing.assert_array_equal(sparse_gp.initial_inducing(data, 10), x[::3])
    fit = sparse_gp.train_inducing(jnp.asarray(log_hyp), data, 10, 30)
    history = np.asarray(fit.history)
    assert np.all(np.diff(history) <= 1e-9 * np.abs(history[:-1]))
    assert history[-1] < history[0] - 1.0
    final = sparse_gp.fitc_neg_log_marginal_likelihood(fit.inducing, jnp.asarray(log_hyp), data)
    np.testing.assert_allclose(final, history.min(), rtol=1e-12)


def test_fitter_switches_to_fitc_past_the_inducing_count():
    assert not sparse_gp.uses_fitc(0, 480) and not sparse_gp.uses_fitc(300, 300)
    assert sparse_gp.uses_fitc(300, 301)
    with pytest.raises(ValueError, match="num_inducing"):
        sparse_gp.fitter(-1, 10, 10)


@pytest.mark.slow
def test_fitc_predicts_held_out_cartpole_transitions_like_the_full_gp():
    """pilco-matlab's cart-pole setting: 16 random-control episodes (480 transitions), the full
    GP's hyperparameters (100 steps), 300 inducing inputs trained 100 steps. On 120 held-out
    transitions FITC's RMSE is within 5 % of the full GP's in every output (measured: at most
    1.7 % worse, theta's difference)."""
    task = tasks.make("cartpole")
    key = jax.random.key(0)

    def episodes(count, base):
        data = gp.GPModel(task).empty_data(count * task.horizon)
        for trial in range(count):
            data = add_episode(task, data, run_episode(task, jax.random.fold_in(jax.random.fold_in(key, base), trial)))
        return data

    data, held = episodes(16, 0), episodes(4, 1)
    log_hyp = gp.train(data, num_steps=100).log_hyp
    fit = sparse_gp.fitter(300, int(data.num_valid), hyp_steps=100)
    posts = {"full": gp.posterior(log_hyp, data), "fitc": gp.check_posterior(jax.jit(fit)(data))}
    rmse = {name: np.sqrt(np.mean((np.asarray(predict(post, held.inputs).mean) - np.asarray(held.targets)) ** 2, 0))
            for name, post in posts.items()}
    print(f"\nheld-out RMSE full {rmse['full']}, FITC {rmse['fitc']}")
    assert np.all(rmse["fitc"] <= 1.05 * rmse["full"])
