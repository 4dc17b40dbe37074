"""Tests of PILCO's analytic moment matching (models/moment_matching.py), in float64.

References: PILCO's own outputs (``tests/data/moment_matching.json``, pilco-matlab under
Octave), Monte Carlo estimates with fixed keys, dense numpy written out from the formulas, and
the project's deterministic GP prediction and RBF policy at near-point inputs.

Tolerances. Reference data: rtol 1e-6 (the brief) with atol 1e-12, which only matters for the
exact zeros of ``gtrig``'s C (the smallest nonzero reference value is 1.1e-4, where rtol 1e-6
is already 1.1e-10). Monte Carlo: every entry within 5 standard errors, each estimated from
the samples (a false alarm has probability ~6e-7 per entry; the keys are fixed anyway).

Two conventions of the reference data, established on all six cases to round-off:
- ``gp2``'s S carries PILCO's jitter: pilco-matlab's gp2 adds 1e-6 to the diagonal of the
  non-central second moment "for numerical reasons". ``gp_moments`` returns the exact
  covariance, so the test subtracts 1e-6 I from the reference.
- ``loss_sat``'s expected_cost is exactly 1 + E[c] (values 1.15 to 1.96 for a cost in [0, 1]);
  its cost_variance is the true variance. The test compares E[c] with expected_cost - 1; the
  Monte Carlo test pins down E[c] itself. W is symmetric positive definite in every case.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from models import gp
from models import moment_matching as mm
from models.form_moments import policy_moments
import tasks
from tasks import policies
from conftest import load_moment_matching_cases

CASES = load_moment_matching_cases()
REF = dict(rtol=1e-6, atol=1e-12)  # see the module docstring
GP2_JITTER = 1e-6  # pilco-matlab's gp2 adds this to S's diagonal
NUM_MC = 400_000  # Monte Carlo samples
NUM_SE = 5.0  # Monte Carlo tolerance in standard errors


# ----- helpers ---------------------------------------------------------------------------------
def np_kernel(log_hyp_a, a, b):
    """SE-ARD kernel of one output, written out: sf^2 exp(-1/2 sum_d (a_d - b_d)^2 / l_d^2)."""
    ls, sf2 = np.exp(log_hyp_a[:-2]), np.exp(2 * log_hyp_a[-2])
    return sf2 * np.exp(-0.5 * np.sum(((a[:, None, :] - b[None, :, :]) / ls) ** 2, axis=-1))


def np_gp(log_hyp, x, y):
    """beta (E, N) = K^-1 y and k_inv (E, N, N) = K^-1 per output, K with noise, dense numpy."""
    k_inv = np.stack([np.linalg.inv(np_kernel(h, x, x) + np.exp(2 * h[-1]) * np.eye(len(x)))
                      for h in log_hyp])
    return np.einsum("enm,me->en", k_inv, y), k_inv


def gp_case(c):
    """A gp0/gp2 JSON case as (inputs, beta, log_hyp (E, D+2), m, s, k_inv)."""
    x = np.array(c["inputs"], float)
    n, d = x.shape
    y = np.array(c["targets"], float).reshape(n, -1)
    log_hyp = np.array(c["log_hyp"], float).reshape(d + 2, -1).T  # JSON (D+2, E) -> (E, D+2)
    beta, k_inv = np_gp(log_hyp, x, y)
    return x, beta, log_hyp, np.array(c["m"], float), np.array(c["s"], float).reshape(d, d), k_inv


def random_gp(key, n=10, d=3, e=2):
    """A small random GP: inputs (n, d), targets (n, e), log_hyp (e, d+2). One shape for all
    tests, so that each jitted primitive compiles once."""
    kx, ky, kl = jax.random.split(key, 3)
    x = np.asarray(jax.random.normal(kx, (n, d)))
    y = np.asarray(jnp.sin(x @ jax.random.normal(ky, (d, e))))
    log_ls = np.asarray(jax.random.uniform(kl, (e, d), minval=-0.3, maxval=0.7))
    log_hyp = np.concatenate([log_ls, np.full((e, 1), np.log(0.8)), np.full((e, 1), np.log(0.1))], axis=1)
    return x, y, log_hyp


def random_cov(key, d, scale):
    """A random covariance (d, d), scale^2 A A^T / d + 0.1 scale^2 I."""
    a = np.asarray(jax.random.normal(key, (d, d)))
    return scale**2 * (a @ a.T / d + 0.1 * np.eye(d))


def gaussian_samples(key, m, s):
    """NUM_MC draws of N(m, s), (NUM_MC, D)."""
    return np.asarray(jax.random.multivariate_normal(key, jnp.asarray(m), jnp.asarray(s), (NUM_MC,)))


def assert_within_se(samples, expected, name):
    """Mean of samples (P, ...) within NUM_SE standard errors of expected, entry by entry."""
    est = samples.mean(axis=0)
    se = samples.std(axis=0) / np.sqrt(len(samples))
    bad = np.abs(est - expected) > NUM_SE * se
    assert not bad.any(), f"{name}: estimate {est} vs analytic {expected}, standard error {se}"


def assert_mc_moments(x, y, mom, s):
    """Sample mean, covariance and cov(x, y) of x (P, D), y (P, E) against ``mom`` (Moments).

    Covariances are means of products of deviations from the sample means; their standard
    errors are those of the products (the O(1/P) bias of the sample mean is far below them).
    """
    xc, yc = x - x.mean(0), y - y.mean(0)
    assert_within_se(y, mom.mean, "mean")
    assert_within_se(yc[:, :, None] * yc[:, None, :], mom.cov, "cov")
    assert_within_se(xc[:, :, None] * yc[:, None, :], s @ mom.io, "cov(x, y) = s io")


# ----- PILCO's reference outputs -----------------------------------------------------------------
@pytest.mark.parametrize("case", range(len(CASES)))
def test_gp0_reference(case):
    c = CASES[case]["gp0"]
    x, beta, log_hyp, m, s, k_inv = gp_case(c)
    mom = mm.gp_moments(x, beta, log_hyp, m, s, k_inv)
    np.testing.assert_allclose(mom.mean, c["M"], **REF)
    np.testing.assert_allclose(mom.cov, c["S"], **REF)
    np.testing.assert_allclose(mom.io, c["V"], **REF)


@pytest.mark.parametrize("case", range(len(CASES)))
def test_gp2_reference(case):
    c = CASES[case]["gp2"]
    x, beta, log_hyp, m, s, _ = gp_case(c)
    mom = mm.gp_moments(x, beta, log_hyp, m, s)
    np.testing.assert_allclose(mom.mean, [c["M"]], **REF)
    np.testing.assert_allclose(mom.cov, [[c["S"] - GP2_JITTER]], **REF)
    np.testing.assert_allclose(mom.io[:, 0], c["V"], **REF)


@pytest.mark.parametrize("case", range(len(CASES)))
def test_saturation_reference(case):
    c = CASES[case]["gsat"]
    mom = mm.saturation_moments(jnp.array([c["m"]]), jnp.array([[c["v"]]]), jnp.array([float(c["e"])]))
    np.testing.assert_allclose(mom.mean, [c["M"]], **REF)
    np.testing.assert_allclose(mom.cov, [[c["S"]]], **REF)
    np.testing.assert_allclose(mom.io, [[c["C"]]], **REF)


@pytest.mark.parametrize("case", range(len(CASES)))
def test_trig_reference(case):
    c = CASES[case]["gtrig"]
    angle_map = np.zeros((1, len(c["m"])))
    angle_map[0, c["i"] - 1] = 1.0  # "i" is 1-based
    mom = mm.trig_moments(jnp.array(c["m"]), jnp.array(c["v"]), jnp.asarray(angle_map))
    np.testing.assert_allclose(mom.mean, c["M"], **REF)
    np.testing.assert_allclose(mom.cov, c["V"], **REF)
    np.testing.assert_allclose(mom.io, c["C"], **REF)


@pytest.mark.parametrize("case", range(len(CASES)))
def test_saturating_cost_reference(case):
    c = CASES[case]["loss_sat"]
    mean, var = mm.saturating_cost_moments(jnp.array(c["m"]), jnp.array(c["s"]), jnp.array(c["z"]),
                                           jnp.array(c["W"]))
    np.testing.assert_allclose(mean, c["expected_cost"] - 1.0, **REF)  # offset: module docstring
    np.testing.assert_allclose(var, c["cost_variance"], **REF)


# ----- Monte Carlo -----------------------------------------------------------------------------
def test_gp_mean_moments_monte_carlo():
    """GP means (k_inv None), D = 3, E = 2, N = 10: y_a(x) = sum_i beta_ai k_a(x, x_i)."""
    x, y, log_hyp = random_gp(jax.random.key(0))
    beta, _ = np_gp(log_hyp, x, y)
    m, s = np.array([0.2, -0.3, 0.1]), random_cov(jax.random.key(1), 3, 0.6)
    xs = gaussian_samples(jax.random.key(2), m, s)
    ys = np.stack([np_kernel(h, xs, x) @ b for h, b in zip(log_hyp, beta)], axis=1)
    assert_mc_moments(xs, ys, mm.gp_moments(x, beta, log_hyp, m, s), s)


def test_saturation_monte_carlo():
    """Two correlated controls: the cross-control covariance is checked too."""
    m, v, u_max = np.array([0.3, -1.0]), np.array([[0.5, 0.3], [0.3, 0.8]]), np.array([2.0, 5.0])
    xs = gaussian_samples(jax.random.key(3), m, v)
    assert_mc_moments(xs, u_max * (9 * np.sin(xs) + np.sin(3 * xs)) / 8,
                      mm.saturation_moments(m, v, u_max), v)


def test_trig_monte_carlo():
    """Two correlated angles a = angle_map x of a 3-vector, one a combination of two entries."""
    m, s = np.array([0.7, -0.4, 1.2]), random_cov(jax.random.key(4), 3, 0.7)
    angle_map = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -0.5]])
    xs = gaussian_samples(jax.random.key(5), m, s)
    a = xs @ angle_map.T
    ys = np.stack([np.sin(a[:, 0]), np.cos(a[:, 0]), np.sin(a[:, 1]), np.cos(a[:, 1])], axis=1)
    assert_mc_moments(xs, ys, mm.trig_moments(m, s, angle_map), s)


def test_saturating_cost_monte_carlo():
    m, s = np.array([0.4, -0.2, 0.9]), random_cov(jax.random.key(6), 3, 0.5)
    target, weight = np.array([0.0, 0.3, 0.5]), random_cov(jax.random.key(7), 3, 1.5)
    xs = gaussian_samples(jax.random.key(8), m, s)
    d = xs - target
    c = 1.0 - np.exp(-0.5 * np.einsum("pi,ij,pj->p", d, weight, d))
    mean, var = mm.saturating_cost_moments(m, s, target, weight)
    assert_within_se(c, mean, "mean")
    assert_within_se((c - c.mean()) ** 2, var, "variance")


# ----- the model-uncertainty term (gp0) ----------------------------------------------------------
def np_q(log_hyp_a, x, m, s):
    """Q_aa (N, N) written out pair by pair from the formula (R^-1 by np.linalg.solve)."""
    ls2, sf2 = np.exp(2 * log_hyp_a[:-2]), np.exp(2 * log_hyp_a[-2])
    nu = x - m
    k = sf2 * np.exp(-0.5 * np.sum(nu**2 / ls2, axis=1))
    r = s @ np.diag(2.0 / ls2) + np.eye(len(m))
    q = np.empty((len(x), len(x)))
    for i in range(len(x)):
        for j in range(len(x)):
            z = nu[i] / ls2 + nu[j] / ls2
            q[i, j] = k[i] * k[j] * np.exp(0.5 * z @ np.linalg.solve(r, s) @ z) / np.sqrt(np.linalg.det(r))
    return q


def test_gp_model_uncertainty_term():
    """gp0 - gp2 = diag(sf_a^2 - tr(K_a^-1 Q_aa)) with Q_aa dense; mean and io unchanged."""
    x, y, log_hyp = random_gp(jax.random.key(9))
    beta, k_inv = np_gp(log_hyp, x, y)
    m, s = np.array([0.1, 0.4, -0.2]), random_cov(jax.random.key(10), 3, 0.5)
    full = mm.gp_moments(x, beta, log_hyp, m, s, k_inv)
    mean_only = mm.gp_moments(x, beta, log_hyp, m, s)
    term = [np.exp(2 * h[-2]) - np.sum(ki * np_q(h, x, m, s)) for h, ki in zip(log_hyp, k_inv)]
    np.testing.assert_allclose(full.cov - mean_only.cov, np.diag(term), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(full.mean, mean_only.mean, rtol=1e-15)
    np.testing.assert_allclose(full.io, mean_only.io, rtol=1e-15)


def test_gp_point_input_is_gp_prediction():
    """At s = 1e-12 I: mean = k^T beta, cov = diag(sf^2 - k^T K^-1 k) (the ordinary predictive
    latent variance; off-diagonals 0), io = the mean's gradient. The moments move by O(s |grad|^2)
    ~ 1e-12 from the point values, hence rtol 1e-6 with atol 1e-10."""
    x, y, log_hyp = random_gp(jax.random.key(11))
    beta, k_inv = np_gp(log_hyp, x, y)
    m, s = np.array([0.3, -0.5, 0.2]), 1e-12 * np.eye(3)
    mom = mm.gp_moments(x, beta, log_hyp, m, s, k_inv)
    k = np.stack([np_kernel(h, m[None], x)[0] for h in log_hyp])  # (E, N)
    np.testing.assert_allclose(mom.mean, np.sum(k * beta, axis=1), rtol=1e-6, atol=1e-10)
    var = np.exp(2 * log_hyp[:, -2]) - np.einsum("en,enm,em->e", k, k_inv, k)
    np.testing.assert_allclose(mom.cov, np.diag(var), rtol=1e-6, atol=1e-10)
    grad = (x - m) / np.exp(2 * log_hyp[:, None, :-2]) * (k * beta)[:, :, None]  # (E, N, D)
    np.testing.assert_allclose(mom.io, np.sum(grad, axis=1).T, rtol=1e-6, atol=1e-10)


# ----- conveniences ----------------------------------------------------------------------------
def test_gp_posterior_moments_handles_padding():
    """A buffer of capacity 14 holding 10 rows equals gp_moments on the 10 rows (dense numpy K^-1).

    The Cholesky-inverse and numpy inverse paths differ by round-off (cond(K) ~ 1e3): rtol 1e-9.
    Without the mask the padding's identity block in K^-1 would change cov (checked too).
    """
    x, y, log_hyp = random_gp(jax.random.key(12))
    data = gp.add_data(gp.empty_data(14, 3, 2, jnp.float64), jnp.asarray(x), jnp.asarray(y))
    post = gp.posterior(jnp.asarray(log_hyp), data)
    assert int(data.num_valid) == 10
    m, s = np.array([0.2, 0.1, -0.3]), random_cov(jax.random.key(13), 3, 0.5)
    beta, k_inv = np_gp(log_hyp, x, y)
    expected = mm.gp_moments(x, beta, log_hyp, m, s, k_inv)
    got = mm.gp_posterior_moments(post, m, s)
    for name in mm.Moments._fields:
        np.testing.assert_allclose(getattr(got, name), getattr(expected, name), rtol=1e-9, atol=1e-12)
    k_inv_padded = jnp.einsum("eki,ekj->eij", post.chol_inv, post.chol_inv)
    unmasked = mm.gp_moments(post.inputs, post.alpha, post.log_hyp, m, s, k_inv_padded)
    assert not np.allclose(unmasked.cov, expected.cov, rtol=1e-3)


def test_rbf_policy_moments_at_point_input():
    """At s = 1e-10 I the pre-activation's mean is rbf_preactivation(net, m) and io its
    Jacobian transposed (cov(x, y) = s J^T); O(s) effects ~1e-10: rtol 1e-6, atol 1e-9."""
    kc, kt, kl, km = jax.random.split(jax.random.key(14), 4)
    theta = policies.RBFParams(
        centres=jax.random.normal(kc, (10, 3)),
        targets=0.5 * jax.random.normal(kt, (10, 2)),
        log_lengthscales=jax.random.uniform(kl, (2, 3), minval=-0.5, maxval=0.5),
    )
    net = policies.rbf_network(theta)
    m = 0.5 * jax.random.normal(km, (3,))
    mom = mm.rbf_policy_moments(net, m, 1e-10 * jnp.eye(3))
    np.testing.assert_allclose(mom.mean, policies.rbf_preactivation(net, m), rtol=1e-6, atol=1e-9)
    jac = jax.jacobian(policies.rbf_preactivation, argnums=1)(net, m)  # (U, F)
    np.testing.assert_allclose(mom.io, jac.T, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("task_name", ["cartpole", "unicycle"])
def test_policy_moments_match_monte_carlo(task_name):
    """``policy_moments`` of the task's policy for Gaussian features near the start, against
    400k samples: mean, covariance and cov(f, u) within 5 standard errors. Where the moments
    are exact: the cart-pole's RBF pre-activation (its form without the saturation; the
    saturation's moments assume a Gaussian input, PILCO's approximation, tested on its own
    above) and the unicycle's linear policy with its saturation."""
    task = tasks.make(task_name)
    policy = task.default_policy()
    net = policy.prepare(policy.init(jax.random.key(21)))
    if task_name == "cartpole":
        form, apply = policy.form._replace(u_max=None), policies.rbf_preactivation
    else:
        form, apply, net = policy.form, policy.network, net._replace(weight=10 * net.weight)
    f_dim = task.policy_feature_map(jnp.zeros(task.model_state_dim)).shape[0]
    m = 0.2 * jax.random.normal(jax.random.key(22), (f_dim,))
    s = random_cov(jax.random.key(23), f_dim, 0.3)
    f = gaussian_samples(jax.random.key(24), m, s)
    u = np.asarray(jax.vmap(lambda x: apply(net, x))(jnp.asarray(f)))
    assert_mc_moments(f, u, policy_moments(form, net, jnp.asarray(m), jnp.asarray(s)), s)


def test_the_direct_rbf_form_is_pilcos_with_its_weights_as_parameters():
    """The direct form's theta is the network itself: with the weights that PILCO's form solves
    for, the controls and the moments are the same (to 1e-12)."""
    pilco_form = tasks.make("cartpole", rbf_parameterisation="pseudo_inputs").default_policy()
    direct_form = tasks.make("cartpole", rbf_parameterisation="direct").default_policy()
    theta = pilco_form.init(jax.random.key(25))
    net = pilco_form.prepare(theta)
    assert direct_form.prepare(net) is net and direct_form.form == pilco_form.form
    f = jnp.array([0.05, -0.1, 0.2, 0.01, -0.99])
    np.testing.assert_allclose(direct_form.apply(net, f), pilco_form.apply(theta, f), rtol=1e-12)
    m, s = f, random_cov(jax.random.key(26), 5, 0.2)
    for a, b in zip(policy_moments(direct_form.form, direct_form.prepare(net), m, s),
                    policy_moments(pilco_form.form, pilco_form.prepare(theta), m, s)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


# ----- transformations -------------------------------------------------------------------------
def test_gradients_and_vmap():
    """grad and jvp of every primitive match central finite differences (check_grads, order 1),
    and vmap over input means equals one call per mean."""
    x, y, log_hyp = random_gp(jax.random.key(15))
    beta, k_inv = np_gp(log_hyp, x, y)
    m0 = jnp.array([0.1, -0.2, 0.3])
    c0 = jnp.asarray(np.linalg.cholesky(random_cov(jax.random.key(16), 3, 0.5)))
    angle_map = jnp.array([[1.0, 0.0, 0.0], [0.0, 1.0, -0.5]])

    @jax.jit
    def total(m, c, log_hyp):
        s = c @ c.T  # symmetric for every perturbation
        gp_mom = mm.gp_moments(x, beta, log_hyp, m, s, k_inv)
        sat = mm.saturation_moments(gp_mom.mean, gp_mom.cov, jnp.array([2.0, 3.0]))
        trig = mm.trig_moments(m, s, angle_map)
        cost = mm.saturating_cost_moments(m, s, jnp.zeros(3), jnp.eye(3))
        return sum(jnp.sum(jnp.sin(leaf)) for leaf in (*gp_mom, *sat, *trig, *cost))

    check_grads(total, (m0, c0, jnp.asarray(log_hyp)), order=1, modes=("fwd", "rev"))
    ms = jnp.stack([m0, -m0])
    s0 = c0 @ c0.T
    batched = jax.vmap(lambda m: mm.gp_moments(x, beta, log_hyp, m, s0, k_inv))(ms)
    for i, m in enumerate(ms):
        single = mm.gp_moments(x, beta, log_hyp, m, s0, k_inv)
        for name in mm.Moments._fields:
            np.testing.assert_allclose(getattr(batched, name)[i], getattr(single, name), rtol=1e-12)
