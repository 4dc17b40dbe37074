"""Estimators against the exact gradient of a linear-Gaussian system (estimators/linear_gaussian.py).

Unbiasedness is a z-test on the mean of N independent estimates (fixed keys): |z| < 4 per
parameter. Each test compares 3 parameters and the file about 20 in all, so a correct
estimator fails the suite with probability about 20 * 6e-5 ~ 1e-3; the keys are fixed, so the
outcome is reproducible.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import estimators
from conftest import OPTIMISED
from estimators.linear_gaussian import LinearGaussianSystem
from tasks.policies import LinearParams

SYSTEM = LinearGaussianSystem()
PROBLEM = SYSTEM.problem()
THETA = LinearParams(jnp.array([[-0.5, -0.8]]), jnp.array([0.1]))
EXACT = np.concatenate([np.ravel(g) for g in jax.tree.leaves(jax.grad(SYSTEM.objective)(THETA))])
Z_MAX = 4.0


def flat(tree, n):
    return np.concatenate([np.asarray(x).reshape(n, -1) for x in jax.tree.leaves(tree)], axis=1)


@functools.cache  # estimators are hashable; the tests share batches and never modify them
def many(est, num_particles, n, seed=0):
    """n estimates with independent keys: (value (n,), grads (n, 3), grad_var (n, 3), aux)."""
    keys = jax.random.split(jax.random.key(seed), n)
    e = jax.jit(jax.vmap(lambda k: est(PROBLEM, THETA, k, num_particles)))(keys)
    return np.asarray(e.value), flat(e.grad, n), flat(e.grad_var, n), e.aux


def z_scores(grads):
    return (grads.mean(0) - EXACT) / (grads.std(0, ddof=1) / np.sqrt(len(grads)))


def relative_bias(grads):
    return (grads.mean(0) - EXACT) / np.abs(EXACT)


@pytest.mark.parametrize(
    "name, options",
    [
        ("rp", {}),
        ("lr", {}),
        ("lr", {"baseline": "none"}),
        ("lr", {"baseline": "importance_sampled"}),  # its baseline uses only the other particles' samples
        ("biw_lr", {"baseline": "none"}),  # without a baseline the mixture weighting is unbiased
        ("tp", {"weighting": "lr", "fixed_k": 0.3}),  # a fixed mix of unbiased estimators
        ("tp", {"weighting": "biw_lr", "fixed_k": 0.0}),
        ("tp", {"weighting": "biw_lr", "baseline": "pairwise", "fixed_k": 1.0}),  # BIW-LR with it
    ],
)
def test_unbiased(name, options):
    _, grads, _, _ = many(estimators.make(name, **options), num_particles=20, n=2000)
    z = z_scores(grads)
    print(name, options, "z =", z.round(2))
    assert np.all(np.abs(z) < Z_MAX), (name, options, z)


def test_value_is_unbiased():
    values, _, _, _ = many(estimators.make("rp"), num_particles=20, n=2000)
    z = (values.mean() - float(SYSTEM.objective(THETA))) / (values.std(ddof=1) / np.sqrt(len(values)))
    assert abs(z) < Z_MAX, z


def test_mixing_weight_is_the_inverse_variance_weight_of_the_lr_part():
    """k_LR = var_RP / (var_RP + var_LR), and its documented edge cases."""
    from estimators.total_propagation import mixing_weight

    var_rp = jnp.array([1.0, 2.0, 3.0, 0.0, 0.0, jnp.inf, 1.0, jnp.nan])
    var_lr = jnp.array([3.0, 2.0, 1.0, 0.0, 1.0, 1.0, jnp.inf, 1.0])
    expected = [0.25, 0.5, 0.75, 0.5, 0.0, 1.0, 0.0, np.nan]
    np.testing.assert_allclose(mixing_weight(var_rp, var_lr), expected, rtol=1e-15)


def test_tp_bias_from_its_data_dependent_weight_is_small():
    """k_LR is computed from the same particles, so TP is not exactly unbiased. Measured here
    (P = 20, N = 2000, seeds 0 and 7): relative bias 0.6-0.8 % with the LR part (|z| 4-6), and
    5.4-6.3 % with the default BIW-LR part, whose baseline's bias (8.6-11.6 %, the next test)
    TP scales down by k_LR. Bounds: 2 % and 8 %, and below BIW-LR's own bias."""
    _, grads_lr, _, aux = many(estimators.make("tp", weighting="lr"), num_particles=20, n=2000)
    print("TP(LR) relative bias", relative_bias(grads_lr).round(4))
    assert np.all(np.abs(relative_bias(grads_lr)) < 0.02)
    assert np.all(np.isfinite(np.asarray(aux["k_lr"])))  # clipped to [0, 1]; NaN would be a bug
    tp = np.abs(relative_bias(many(estimators.make("tp"), num_particles=20, n=2000)[1]))
    biw_lr = np.abs(relative_bias(many(estimators.make("biw_lr"), num_particles=20, n=2000)[1]))
    print("TP relative bias", tp.round(4), "BIW-LR", biw_lr.round(4))
    assert np.all(tp < 0.08) and np.all(tp < biw_lr)


def test_tp_variance_against_its_parts():
    """Variance of 2000 estimates at P = 20, per parameter (s.e. of a variance ratio ~4.5 %).
    With the LR part, TP's inverse-variance mix is as good as its better part (RP here): ratio
    to min(RP, LR) measured 0.89-1.04, bound 1.15. With the default BIW-LR part it is worse
    than RP on this system (ratio 1.3-1.9), probably because BIW-LR's reported variance, which
    sets k_LR, is 0.4-0.6 of its spread (test_reported_variance_matches_the_spread_of_estimates),
    so k_LR leans to it; bounds 2.5 x RP's and 0.25 x BIW-LR's (measured 0.07-0.17). A weight that
    favoured the higher-variance part would give about BIW-LR's variance, 7-30 x RP's."""
    parts = dict(rp=("rp", {}), lr=("lr", {}), biw_lr=("biw_lr", {}), tp=("tp", {}), tp_lr=("tp", {"weighting": "lr"}))
    var = {label: many(estimators.make(name, **options), 20, 2000)[1].var(0, ddof=1)
           for label, (name, options) in parts.items()}
    print({label: v.round(4) for label, v in var.items()})
    assert np.all(var["tp_lr"] < 1.15 * np.minimum(var["rp"], var["lr"]))
    assert np.all(var["tp"] < 2.5 * var["rp"]) and np.all(var["tp"] < 0.25 * var["biw_lr"])


def test_biw_lr_baseline_bias_shrinks_with_particles():
    """The paper's normalised importance-sampled leave-one-out baseline depends on the other
    samples, which biases BIW-LR. Measured here: 8.6-10.8 % (relative) at P = 20 and
    2.3-3.7 % at P = 100; bounds 5-15 % and 6 %, and the bias must shrink."""
    biases = {}
    for P, n in ((20, 2000), (100, 500)):
        _, grads, _, _ = many(estimators.make("biw_lr"), num_particles=P, n=n)
        biases[P] = np.abs(relative_bias(grads))
        print(f"BIW-LR P={P}: relative bias {biases[P].round(4)}, z {z_scores(grads).round(1)}")
    assert np.all((biases[20] > 0.05) & (biases[20] < 0.15)) and np.all(biases[100] < 0.06)
    assert np.all(biases[100] < 0.6 * biases[20])


def test_pairwise_baseline_is_unbiased_where_the_papers_is_not():
    """BIW-LR at P = 20 over 2000 estimates (fixed keys): with the paper's leave-one-out
    baseline the mean misses the exact gradient by about 10 % (|z| 9-20); with the pairwise
    baseline every |z| < 3 (the issue's test; measured 0.5-0.8, and under 1 over 8000). Its
    standard deviation sits between the paper's baseline (biased, 0.26-0.28) and no baseline
    (0.72-0.92): measured 0.55-0.79."""
    results = {}
    for baseline in ("leave_one_out", "pairwise", "none"):
        _, grads, _, _ = many(estimators.make("biw_lr", baseline=baseline), num_particles=20, n=2000)
        results[baseline] = (z_scores(grads), grads.std(0, ddof=1))
        print(f"BIW-LR baseline={baseline}: z {results[baseline][0].round(2)}, sd {results[baseline][1].round(3)}")
    assert np.all(np.abs(results["pairwise"][0]) < 3.0)
    assert np.max(np.abs(results["leave_one_out"][0])) > 3.0
    assert np.all(results["pairwise"][1] < results["none"][1])


def test_pairwise_baseline_matches_its_formula():
    """``pairwise_baseline`` against a loop over (i, j) in numpy: the ratio moments
    E_{p_k}[(p_i / p_k)^2] by quadrature, partners (moment <= 2), b_ij = G_i (j != i),
    b_ii = the a-weighted importance-sampled mean over partners, and 0 for a row without
    partners (particle 3, far from the others). rtol 1e-9."""
    from scipy import integrate

    from estimators.base import Zeta
    from estimators.likelihood_ratio import PAIRWISE_MAX_RATIO_MOMENT, log_density_matrix, pairwise_baseline

    mean = np.array([[0.0, 0.1], [0.3, -0.2], [-0.4, 0.2], [9.0, 9.0]])
    std = np.array([[1.0, 0.8], [1.1, 0.9], [0.9, 1.0], [1.0, 1.0]])
    s = mean + std * np.array([[0.3, -1.1], [0.8, 0.4], [-0.5, 0.2], [1.2, -0.3]])
    G = np.array([3.0, 5.0, 2.0, 7.0])
    zeta = Zeta(jnp.asarray(mean), jnp.asarray(std))
    log_p = np.asarray(log_density_matrix(zeta, jnp.asarray(s)))
    log_pdf = lambda x, m, sd: -0.5 * ((x - m) / sd) ** 2 - np.log(np.sqrt(2 * np.pi) * sd)  # noqa: E731

    def moment(i, k):  # the integrand p_i^2 / p_k is negligible beyond 20 sds of both means
        def integrand(x, d):
            return np.exp(2 * log_pdf(x, mean[i, d], std[i, d]) - log_pdf(x, mean[k, d], std[k, d]))
        return np.prod([integrate.quad(integrand, -20, 30, args=(d,), points=[mean[i, d], mean[k, d]], limit=200,
                                       epsabs=0, epsrel=1e-12)[0] for d in range(2)])

    expected = np.zeros((4, 4))
    for i in range(4):
        partners = [k for k in range(4) if k != i and moment(i, k) <= PAIRWISE_MAX_RATIO_MOMENT]
        if not partners:
            continue
        a = np.array([1 / moment(i, k) for k in partners])
        r = np.array([np.exp(log_p[i, k] - log_p[k, k]) for k in partners])
        expected[i] = G[i]
        expected[i, i] = np.sum(a * r * G[partners]) / a.sum()
    assert np.count_nonzero(expected[:3, :3] != G[:3, None]) == 3 and np.all(expected[3] == 0)
    np.testing.assert_allclose(pairwise_baseline(zeta, jnp.asarray(log_p), jnp.asarray(G)), expected, rtol=1e-9)


def test_gaussian_resample_has_the_particles_mean_and_covariance():
    """``mu + xi L^T``: xi = 0 gives the particles' mean; xi = I gives the rows of L^T, whose
    Gram matrix is the particles' covariance (ddof 1). Exact to round-off."""
    from estimators.reparameterisation import gaussian_resample

    s = jax.random.normal(jax.random.key(0), (7, 3)) @ jnp.array([[1.0, 0.5, 0.0], [0.0, 2.0, -0.3], [0.0, 0.0, 0.7]])
    mean = np.asarray(s).mean(0)
    np.testing.assert_allclose(gaussian_resample(s, jnp.zeros((1, 3)))[0], mean, rtol=1e-14)
    rows = np.asarray(gaussian_resample(s, jnp.eye(3))) - mean
    np.testing.assert_allclose(rows.T @ rows, np.cov(np.asarray(s).T, ddof=1), rtol=1e-12)
    assert np.allclose(np.tril(rows, -1), 0.0)  # L^T, upper triangular


def test_gr_bias_shrinks_with_particles():
    """GR's refit covariance is noisy for few particles; its bias must fall as P grows.
    Measured (relative to the exact gradient): 5-10 % at P = 4, 0.8-1.6 % at P = 40; bounds:
    under 3 % at P = 40 and half the P = 4 error."""
    errors = {}
    for P, n in ((4, 4000), (40, 1000)):
        _, grads, _, _ = many(estimators.make("gr"), num_particles=P, n=n)
        errors[P] = np.abs(grads.mean(0) - EXACT).max()
        print(f"GR P={P}: max |bias| {errors[P]:.4f}, relative {relative_bias(grads).round(4)}")
        if P == 40:
            assert np.all(np.abs(relative_bias(grads)) < 0.03)
    assert errors[40] < 0.5 * errors[4]


def test_gr_resampling_noise_is_independent_of_the_sampling_noise():
    """Each resampled particle must get fresh noise xi, not the eps that sampled it (until
    2026-12-06 xi was drawn from ``fold_in(key, 1)``, which in jax is eps's own key, and the
    correlation here was exactly 1). |r| < 4 standard errors of a zero correlation."""
    from estimators.reparameterisation import draw_resampling_noise

    _, eps, xi = draw_resampling_noise(PROBLEM, jax.random.key(0), 100, jnp.float64)
    assert xi.shape == eps.shape
    r = np.corrcoef(np.ravel(eps), np.ravel(xi))[0, 1]
    assert abs(r) < 4 / np.sqrt(eps.size)


def test_rollout_resamples_with_the_noise_it_is_given_and_not_without_it():
    """The resampler receives resample_noise's rows, step by step (not eps's: the bug above);
    a resampling rollout without resample_noise refuses to run rather than fall back on eps."""
    from estimators.base import draw_noise, per_particle, prepared, rollout

    s0, eps = draw_noise(PROBLEM, jax.random.key(0), 7, jnp.float64)
    xi = jax.random.normal(jax.random.key(1), eps.shape)
    nets = per_particle(prepared(PROBLEM, THETA)[0], 7)
    take_the_noise = lambda s_tilde, xi_t: xi_t  # noqa: E731
    traj = rollout(PROBLEM, nets, s0, eps, resample=take_the_noise, resample_noise=xi)
    np.testing.assert_array_equal(traj.states[1:], xi)
    with pytest.raises(ValueError, match="resample_noise"):
        rollout(PROBLEM, nets, s0, eps, resample=take_the_noise)


@pytest.mark.parametrize("name", ["rp_fs", "gr_fs"])
def test_a_fixed_noise_estimate_is_the_gradient_of_its_own_objective(name):
    """GR_FS's objective resamples the particles from their Gaussian at every step: its own J, not the plain
    particle rollout's (so a finite difference of the plain J need not match it)."""
    est = estimators.make(name)
    e = est(PROBLEM, THETA, jax.random.key(3), 30)
    exact = jax.grad(lambda th: est(PROBLEM, th, jax.random.key(3), 30).value)(THETA)
    np.testing.assert_allclose(flat(e.grad, 1), flat(exact, 1), rtol=1e-10)


@pytest.mark.parametrize("name", ["rp_fs", "gr_fs"])
def test_fixed_noise_is_fixed_within_an_optimisation_and_differs_across_repeats(name):
    """The optimiser gives a fixed-noise estimator its optimisation's key at every step: step
    1's estimate is the estimator at theta after step 0 WITH THAT KEY; and two repeats
    (two keys) optimise on different particles. (Before the fix every repeat and trial used
    noise seed 0, whatever its key.)"""
    from harness.episodic import optimise_policy

    est = estimators.make(name)
    run = lambda key, steps: optimise_policy(PROBLEM, THETA, key, estimator=est, num_steps=steps,  # noqa: E731
                                             num_particles=30)
    repeat_a, repeat_b = jax.random.key(5), jax.random.key(6)
    after_one = run(repeat_a, 1).theta
    values = run(repeat_a, 2).values
    same = dict(rel=1e-12)  # jitted inside the optimiser against eager: round-off
    assert float(values[0]) == pytest.approx(float(est(PROBLEM, THETA, repeat_a, 30).value), **same)
    assert float(values[1]) == pytest.approx(float(est(PROBLEM, after_one, repeat_a, 30).value), **same)
    assert float(run(repeat_b, 1).values[0]) != pytest.approx(float(values[0]), rel=1e-3)


@pytest.mark.parametrize("name", ["rp", "lr"])
def test_variance_scales_like_one_over_p(name):
    """Independent particles: the gradient's variance at P = 40 is a quarter of that at
    P = 10. With N = 1000 estimates each variance has relative s.e. ~4.5 %, the ratio ~6 %."""
    est = estimators.make(name)
    var = {P: many(est, P, 1000, seed=P)[1].var(0, ddof=1) for P in (10, 40)}
    ratio = var[10] / var[40]
    print(name, "variance ratio P=10 / P=40:", ratio.round(2))
    assert np.all((ratio > 3.2) & (ratio < 5.0)), ratio


@pytest.mark.parametrize("name, band", [("rp", (0.85, 1.15)), ("lr", (0.85, 1.15)), ("biw_lr", (0.30, 0.70)),
                                        ("tp", (0.45, 0.80))])
def test_reported_variance_matches_the_spread_of_estimates(name, band):
    """``grad_var`` (per-particle variance / P) against the variance of 2000 estimates (s.e. of
    the ratio ~3 %). For RP and LR (independent particles) it must agree: 0.85-1.15. For BIW-LR
    and TP the per-particle terms are coupled (the self-normalised weights, the leave-one-out
    baseline, k_LR), and the reported variance underestimates the spread: measured 0.41-0.60
    (BIW-LR) and 0.55-0.68 (TP) at seeds 0 and 7. Their bands, 3-9 s.e. beyond those, hold it
    where it is: it sets the optimiser's step (``harness.optim``) and TP's k_LR."""
    _, grads, grad_var, _ = many(estimators.make(name), 20, 2000, seed=7)
    ratio = grad_var.mean(0) / grads.var(0, ddof=1)
    print(name, "reported / empirical variance:", ratio.round(3))
    assert np.all((ratio > band[0]) & (ratio < band[1])), ratio


def test_tp_with_fixed_weights_reduces_to_rp_and_biw_lr():
    key = jax.random.key(5)
    for k, other in ((0.0, estimators.make("rp")), (1.0, estimators.make("biw_lr"))):
        tp = estimators.make("tp", fixed_k=k)(PROBLEM, THETA, key, 25)
        ref = other(PROBLEM, THETA, key, 25)
        np.testing.assert_allclose(flat(tp.grad, 1), flat(ref.grad, 1), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(float(tp.value), float(ref.value), rtol=1e-12)
    lr_tp = estimators.make("tp", weighting="lr", fixed_k=1.0)(PROBLEM, THETA, key, 25)
    lr = estimators.make("lr")(PROBLEM, THETA, key, 25)
    np.testing.assert_allclose(flat(lr_tp.grad, 1), flat(lr.grad, 1), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("name", sorted(estimators.REGISTRY))
def test_deterministic_and_jit_agrees(name):
    est = estimators.make(name)
    key = jax.random.key(11)
    eager = est(PROBLEM, THETA, key, 12)
    jitted = jax.jit(est, static_argnums=3)(PROBLEM, THETA, key, 12)
    again = jax.jit(est, static_argnums=3)(PROBLEM, THETA, key, 12)
    np.testing.assert_allclose(flat(eager.grad, 1), flat(jitted.grad, 1), rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(flat(jitted.grad, 1), flat(again.grad, 1))
    assert int(eager.aux["nan_count"]) == 0


def test_nan_gradients_are_counted_not_hidden():
    """A cost whose gradient is NaN for some particles: every estimator reports it."""
    bad = PROBLEM.__class__(**{**PROBLEM.__dict__, "cost": lambda s: jnp.sqrt(s[0])})
    for name in ("rp", "lr", "tp"):
        e = estimators.make(name)(bad, THETA, jax.random.key(0), 10)
        assert int(e.aux["nan_count"]) > 0, name
    e = estimators.make("tp")(bad, THETA, jax.random.key(0), 10)
    assert bool(jnp.any(jnp.isnan(e.aux["k_lr"])))


def test_registry_errors():
    with pytest.raises(ValueError, match="valid estimators: .*'biw_lr'.*'tp'"):
        estimators.make("reinforce")
    with pytest.raises(ValueError, match="bad option for estimator 'rp_fs'"):
        estimators.make("rp_fs", seed=1)


def test_wrong_shapes_are_named_while_tracing():
    """A theta not shaped like the policy's parameters, or a model whose prediction is not
    shaped like the state, fails with what was expected instead of a broadcasting error."""
    from models.prediction import Prediction

    with pytest.raises(ValueError, match=r"not shaped like the policy's parameters LinearParams\(weight=\(1, 2\)"):
        estimators.make("rp")(PROBLEM, LinearParams(jnp.zeros((1, 3)), jnp.zeros(1)), jax.random.key(0), 5)

    @dataclasses.dataclass(frozen=True)
    class ThreeVariances:
        def predict(self, params, s, u):
            return Prediction(s, jnp.ones(3), jnp.ones_like(s))

    with pytest.raises(ValueError, match=r"ThreeVariances.predict.*'model_var': \(3,\).*state of shape \(2,\)"):
        estimators.make("lr")(dataclasses.replace(PROBLEM, model=ThreeVariances()), THETA, jax.random.key(0), 5)


def test_a_registry_entry_must_be_a_factory(monkeypatch):
    monkeypatch.setitem(estimators.REGISTRY, "my_rp", estimators.make("rp"))  # the estimator, not its factory
    with pytest.raises(TypeError, match="REGISTRY\\['my_rp'\\] is a Reparameterisation object; it must be a factory"):
        estimators.make("my_rp")


def test_biw_statistics_match_the_pairwise_formulas():
    """The matrix-product forms of BIW-LR's statistics against the (P, P, S) formulas written
    out in numpy: log p(s_j | zeta_i), and A_i = sum_j W_ij (s_j - m_i)^2, B_i = sum_j W_ij
    (s_j - m_i) with W the baselined weights. Samples far from the origin (offset 30) and
    sds down to 0.003 (the unicycle's observation noise) test the expansion's round-off:
    rtol 1e-8."""
    from estimators.base import Zeta
    from estimators.likelihood_ratio import biw_statistics, log_density_matrix

    k = jax.random.split(jax.random.key(3), 4)
    mean = 30.0 + jax.random.normal(k[0], (40, 3))
    std = jnp.exp(jax.random.uniform(k[1], (40, 3), minval=np.log(0.003), maxval=np.log(2.0)))
    s = mean + std * jax.random.normal(k[2], (40, 3))
    G = 10.0 * jax.random.uniform(k[3], (40,))
    m, sd, x = np.asarray(mean), np.asarray(std), np.asarray(s)
    r = x[None, :, :] - m[:, None, :]  # [i, j, d]
    log_p = np.sum(-0.5 * (r / sd[:, None, :]) ** 2 - np.log(sd[:, None, :]) - 0.5 * np.log(2 * np.pi), -1)
    np.testing.assert_allclose(log_density_matrix(Zeta(mean, std), s), log_p, rtol=1e-8)
    log_c = log_p - np.logaddexp.reduce(log_p, axis=0, keepdims=True)
    others = np.where(np.eye(40, dtype=bool), -np.inf, log_c)  # b_i: a softmax over j != i, in log space
    soft = np.exp(others - others.max(axis=1, keepdims=True))
    baseline = (soft / soft.sum(axis=1, keepdims=True)) @ np.asarray(G)
    W = np.exp(log_c) * (np.asarray(G)[None, :] - baseline[:, None])
    stats, _ = biw_statistics(Zeta(mean, std), s, G)
    np.testing.assert_allclose(stats.A, np.einsum("ij,ijd->id", W, r**2), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(stats.B, np.einsum("ij,ijd->id", W, r), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(stats.w, W.sum(1), rtol=1e-10, atol=1e-12)


def test_score_surrogate_has_the_gradient_of_the_weighted_log_density():
    """LR's and BIW-LR's score ``d/dzeta_i sum_j W_ij log N(s_j; m_i, sd_i)`` through m AND sd
    (the linear-Gaussian tests exercise only m: their sd is constant; on a GP the sd terms are
    about 1 % of LR's gradient, too little for a test of its mean to see). Against autodiff of
    the textbook log-density, arbitrary weights W, sds 0.003-2: rtol 1e-8."""
    from estimators.base import Zeta
    from estimators.likelihood_ratio import ScoreStatistics, score_surrogate

    k = jax.random.split(jax.random.key(4), 4)
    mean = 3.0 + jax.random.normal(k[0], (30, 3))
    std = jnp.exp(jax.random.uniform(k[1], (30, 3), minval=np.log(0.003), maxval=np.log(2.0)))
    s = mean + std * jax.random.normal(k[2], (30, 3))
    W = jax.random.normal(k[3], (30, 30))

    def weighted_log_density(zeta):  # sum_j W_ij log N(s_j; m_i, sd_i), summed over i
        r = s[None, :, :] - zeta.mean[:, None, :]
        log_p = jnp.sum(-0.5 * (r / zeta.std[:, None, :]) ** 2 - jnp.log(zeta.std[:, None, :]), axis=-1)
        return jnp.sum(W * log_p)

    r = s[None, :, :] - mean[:, None, :]
    stats = ScoreStatistics(mean, jnp.einsum("ij,ijd->id", W, r**2), jnp.einsum("ij,ijd->id", W, r), W.sum(1))
    want = jax.grad(weighted_log_density)(Zeta(mean, std))
    got = jax.grad(lambda zeta: score_surrogate(zeta, stats).sum())(Zeta(mean, std))
    np.testing.assert_allclose(got.mean, want.mean, rtol=1e-8)
    np.testing.assert_allclose(got.std, want.std, rtol=1e-8)


def test_biw_baseline_is_finite_when_particles_do_not_overlap():
    """Particles 1e3 standard deviations apart: every off-diagonal mixture weight underflows,
    and the log-space baseline must stay finite. In that limit b_i is the cost-to-go of the
    nearest other particle(s) (their weight dominates): b = [G_1, (G_0 + G_2) / 2, G_1]."""
    from estimators.base import Zeta
    from estimators.likelihood_ratio import biw_statistics

    s = jnp.array([[0.0], [10.0], [20.0]])
    zeta = Zeta(s, jnp.full((3, 1), 0.01))
    G = jnp.array([1.0, 2.0, 4.0])
    stats, ess = biw_statistics(zeta, s, G)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in stats)
    np.testing.assert_allclose(float(ess), 1.0)
    np.testing.assert_allclose(stats.w, G - jnp.array([2.0, 2.5, 2.0]), rtol=1e-12)
    # The pairwise baseline has no partner sample for any row there: no baseline, finite.
    stats, _ = biw_statistics(zeta, s, G, baseline="pairwise")
    np.testing.assert_allclose(stats.w, G, rtol=1e-12)


@pytest.mark.parametrize("backend", ["jax", pytest.param("mjx", marks=pytest.mark.slow)])
def test_estimators_run_on_the_true_dynamics(backend):
    """Every particle estimator works with the simulator model (the task's dynamics as a
    model): finite gradients, no NaN, and a finite TP weight. (PILCO needs moment
    propagation, which only the GP has: tests/test_pilco.py.)"""
    import tasks
    from models.simulator import SimulatorModel

    task = tasks.make("cartpole", horizon=5)
    problem = estimators.task_problem(task, SimulatorModel(task, backend=backend))
    theta = problem.policy.init(jax.random.key(0))
    for name in sorted(set(estimators.REGISTRY) - {"pilco"}):
        e = jax.jit(estimators.make(name), static_argnums=3)(problem, theta, jax.random.key(1), 8)
        assert int(e.aux["nan_count"]) == 0, name
        assert np.all(np.isfinite(flat(e.grad, 1))), name
        if name == "tp":
            assert bool(jnp.all(jnp.isfinite(e.aux["k_lr"])))  # clipped to [0, 1]; NaN would be a bug


def cartpole_gp_problem(horizon: int | None = None):
    """(problem, theta): the cart-pole on a GP fitted (float64) to 60 random transitions, whose
    predictive variance depends on the state (the linear-Gaussian system's does not), at a
    policy with controls of a few newtons."""
    import tasks
    from models import gp

    task = tasks.make("cartpole", **({} if horizon is None else {"horizon": horizon}))
    keys = jax.random.split(jax.random.key(7), 3)
    z = 0.8 * jax.random.normal(keys[0], (60, 4))
    u = jax.random.uniform(keys[1], (60, 1), minval=-10.0, maxval=10.0)
    data = gp.add_data(gp.empty_data(60, task.gp_input_dim, 4), jax.vmap(task.gp_inputs)(z, u),
                       jax.vmap(task.gp_targets)(z, jax.vmap(task.step)(z, u)))
    problem = estimators.task_problem(task, gp.GPModel(task), gp.fit(data, num_steps=30))
    theta = problem.policy.init(keys[2])
    return problem, theta._replace(weights=30.0 * theta.weights)


def test_tp_reduces_to_rp_and_biw_lr_where_the_variance_depends_on_the_state():
    """On the linear-Gaussian system sd is constant, so TP's hand-written cotangent for it
    (dG/ds_t * eps_t) is never exercised there; on a GP it is. TP with k = 0 must equal RP
    (autodiff through ``m + sd * eps``) and with k = 1 BIW-LR, to round-off: rtol 1e-9, or 1e-9
    of the largest entry for the small ones (measured: 5e-12 of it; a wrong sd term is O(1))."""
    problem, theta = cartpole_gp_problem(horizon=10)
    key = jax.random.key(5)
    for k, other in ((0.0, "rp"), (1.0, "biw_lr")):
        tp = estimators.make("tp", fixed_k=k)(problem, theta, key, 20)
        ref = estimators.make(other)(problem, theta, key, 20)
        scale = np.abs(flat(ref.grad, 1)).max()
        np.testing.assert_allclose(flat(tp.grad, 1), flat(ref.grad, 1), rtol=1e-9, atol=1e-9 * scale, err_msg=other)


def test_float32_estimates_batched_are_each_estimate_alone():
    """vmap must not change an estimate beyond round-off. jaxlib 0.10.2's CPU backend broke
    this (jax-ml/jax#39103, "wrong results for vmapped matrix-vector product followed by
    reduction"): BIW-LR in float32 at P = 20, vmapped over 200 keys, came out wrong from the
    82nd estimate on (effective sample sizes 7.8 for 6.3, gradients off by up to 17 x) while
    each estimate alone was right; float64 was not hit here. Measured under 0.10.1: at most
    1.7e-6 of the largest entry over the 200 keys (float32 round-off), bound 1e-5; pyproject
    excludes 0.10.2 (``reports/diagnostics/vmap_float32_check.py`` compares versions)."""
    from harness.episodic import cast_floating

    est = estimators.make("biw_lr")
    theta = cast_floating(THETA, jnp.float32)
    keys = jax.random.split(jax.random.key(0), 200)
    batched = jax.jit(jax.vmap(lambda th, k: est(PROBLEM, th, k, 20), in_axes=(None, 0)))(theta, keys)
    alone = jax.jit(lambda th, k: est(PROBLEM, th, k, 20))
    for i, key in enumerate(keys):
        want = flat(alone(theta, key).grad, 1)[0]
        got = flat(jax.tree.map(lambda leaf: leaf[i], batched.grad), 1)[0]
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * np.abs(want).max(), err_msg=f"estimate {i}")


def test_float32_rollouts_agree_with_float64_to_the_estimators_noise():
    """TP on the cart-pole's GP (trained and factorised in float64), P = 50, at a policy with
    controls of a few newtons: 200 keys, each estimated with the model and theta cast to
    float32 (``harness.episodic.in_precision``'s cast) and in float64, from the same draws
    rounded (``estimators.base.standard_normal``). The closed loop is chaotic, so the paired
    estimates differ by about the estimator's own spread (f32 round-off, amplified), and the
    comparison is statistical: the paired differences' mean must be within 4 standard errors
    of 0, for J and for each of the 305 gradient entries. Measured: J z 0.07, gradient max |z|
    2.0. The same test on J detects dropping the model variance (z 4.4); on the gradient it
    does not (max |z| 2.2): at P = 50 the gradient's noise hides even that, which is the sense
    in which float32 agrees "to the estimators' noise"."""
    from harness.episodic import cast_floating

    problem, theta = cartpole_gp_problem()
    tp = estimators.make("tp")
    estimate = jax.jit(jax.vmap(lambda pr, th, k: tp(pr, th, k, 50), in_axes=(None, None, 0)),
                       compiler_options=OPTIMISED)
    n, runs = 200, {}
    for dtype in (jnp.float64, jnp.float32):
        pr = dataclasses.replace(problem, model_params=cast_floating(problem.model_params, dtype))
        e = estimate(pr, cast_floating(theta, dtype), jax.random.split(jax.random.key(8), n))
        grad = np.concatenate([np.asarray(leaf, np.float64).reshape(n, -1) for leaf in jax.tree.leaves(e.grad)], 1)
        runs[dtype] = np.concatenate([np.asarray(e.value, np.float64)[:, None], grad], 1)  # (n, 1 + 305)
    assert np.isfinite(runs[jnp.float32]).all()
    d = runs[jnp.float32] - runs[jnp.float64]
    z = d.mean(0) / (d.std(0, ddof=1) / np.sqrt(n))
    print(f"float32 - float64, paired: J z {z[0]:.2f}, gradient max |z| {np.abs(z[1:]).max():.2f}")
    assert np.abs(z).max() < 4.0
