"""PILCO's analytic moment matching: exact moments of nonlinear maps of a Gaussian input.

Each primitive takes an input x ~ N(m, s) (D,) and returns the mean and covariance of an
output y and ``io = s^-1 cov(x, y)`` (``Moments``): what PILCO chains through a rollout
(Deisenroth, PhD thesis 2010, sec. 2.3 and appendix A; Deisenroth & Rasmussen, ICML 2011).

- ``gp_moments``: E independent SE-ARD GPs, as GP means or with their model uncertainty;
  ``gp_posterior_moments`` for a ``models.gp.GPPosterior`` (fixed-capacity buffer with a mask),
  ``rbf_policy_moments`` for the RBF policy's pre-activation (``tasks.policies.RBFNetwork``);
- ``saturation_moments``: the policy's squashing ``u_max * (9 sin x + sin 3x) / 8``;
- ``trig_moments``: sine and cosine of angles that are linear in x;
- ``saturating_cost_moments``: mean and variance of ``1 - exp(-1/2 (x - z)^T W (x - z))``.

Layout as in ``models.gp``: ``log_hyp`` (E, D+2), row a is ``[log l_a1..l_aD, log sf_a, log sn_a]``
(PILCO and ``tests/data/moment_matching.json`` store the transpose).

Transformations: pure functions of arrays. The only linear algebra is ``linalg.solve_det`` on
(D, D) matrices, Gauss-Jordan elimination written in elementwise ops: no LAPACK call, so jit,
vmap (over outputs inside, over anything outside), grad and jvp all apply (``numerics.linalg``
explains why batched LAPACK calls are avoided under jaxlib 0.10 on CPU).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from numerics.linalg import solve_det
from tasks.policies import RBF_NOISE_STD, RBF_SIGNAL_STD, RBFNetwork


class Moments(NamedTuple):
    """Moments of y = f(x) for x ~ N(m, s), x (D,), y (E,).

    mean (E,): E[y]; cov (E, E): cov(y); io (D, E): s^-1 cov(x, y), i.e. cov(x, y) = s @ io.
    """

    mean: jax.Array
    cov: jax.Array
    io: jax.Array


class CostMoments(NamedTuple):
    """Mean and variance (scalars) of a per-step cost of a Gaussian state."""

    mean: jax.Array
    var: jax.Array


# ----- Gaussian processes ------------------------------------------------------------------------
@jax.jit
def gp_moments(inputs: jax.Array, beta: jax.Array, log_hyp: jax.Array, m: jax.Array, s: jax.Array,
               k_inv: jax.Array | None = None, mask: jax.Array | None = None) -> Moments:
    """Moments of E independent SE-ARD GPs at x ~ N(m (D,), s (D, D)).

    inputs (N, D) training inputs x_i; beta (E, N) = K_a^-1 y_a per output (K_a with noise);
    log_hyp (E, D+2). With nu_i = x_i - m, Lambda_a = diag(l_a^2):

        q_ai = sf_a^2 |s Lambda_a^-1 + I|^-1/2 exp(-1/2 nu_i^T (s + Lambda_a)^-1 nu_i)
        mean_a = beta_a . q_a,   io[:, a] = (s + Lambda_a)^-1 sum_i beta_ai q_ai nu_i
        Q_ab,ij = k_a(x_i, m) k_b(x_j, m) |R_ab|^-1/2 exp(1/2 z_ij^T R_ab^-1 s z_ij),
            R_ab = s (Lambda_a^-1 + Lambda_b^-1) + I,  z_ij = Lambda_a^-1 nu_i + Lambda_b^-1 nu_j
        cov_ab = beta_a^T Q_ab beta_b - mean_a mean_b  [+ (a = b) (sf_a^2 - tr(k_inv_a Q_aa))]

    Q_ba = Q_ab^T, so only the E (E + 1) / 2 pairs a <= b are computed (E = 10, N = 200:
    value and gradient 0.37-0.42 of the time of all E^2 pairs).

    ``k_inv`` (E, N, N) = K_a^-1 adds the model uncertainty of a full GP (PILCO's gp0: the
    covariance of the latent function values, noise not included); without it the GPs are
    deterministic functions (gp2: GP means, e.g. the RBF policy; pilco-matlab's gp2 also adds a
    1e-6 jitter to cov's diagonal, not done here). ``mask`` (N,) bool marks the valid rows of a
    padded buffer: the others get zero weight in beta and k_inv (their inputs must still be
    finite). Exponents are summed in log space before one exp.
    """
    ell = jnp.exp(log_hyp[:, :-2])  # (E, D)
    log_sf2 = 2.0 * log_hyp[:, -2]  # (E,)
    if mask is not None:
        beta = jnp.where(mask, beta, 0.0)
        if k_inv is not None:
            k_inv = jnp.where(mask[:, None] & mask[None, :], k_inv, 0.0)
    nu = inputs - m  # (N, D)
    eye = jnp.eye(m.shape[0], dtype=s.dtype)

    def mean_io(ell_a, log_sf2_a, beta_a):
        # (s + Lambda)^-1 = Lambda^-1/2 A^-1 Lambda^-1/2 with A = Lambda^-1/2 s Lambda^-1/2 + I,
        # |A| = |s Lambda^-1 + I|.
        a_inv_nu, det_a = solve_det(s / jnp.outer(ell_a, ell_a) + eye, (nu / ell_a).T)
        b_inv_nu = a_inv_nu / ell_a[:, None]  # (D, N): column i is (s + Lambda)^-1 nu_i
        q = jnp.exp(log_sf2_a - 0.5 * jnp.log(det_a) - 0.5 * jnp.sum(nu.T * b_inv_nu, axis=0))
        return q @ beta_a, b_inv_nu @ (beta_a * q)

    def q_matrix(ell_a, log_sf2_a, ell_b, log_sf2_b):
        # R^-1 s = (s^-1 + P)^-1 = s - s P^1/2 G^-1 P^1/2 s (Woodbury) and |R| = |G|, with
        # P = Lambda_a^-1 + Lambda_b^-1 and G = P^1/2 s P^1/2 + I (symmetric, eigenvalues >= 1).
        u, w = nu / ell_a**2, nu / ell_b**2  # (N, D)
        sqrt_p = jnp.sqrt(1.0 / ell_a**2 + 1.0 / ell_b**2)
        y = sqrt_p[:, None] * s
        g_inv_y, det_g = solve_det(y * sqrt_p + eye, y)
        t = s - y.T @ g_inv_y  # R^-1 s
        ut = u @ t
        # log k_a(x_i, m) + log k_b(x_j, m) + 1/2 z_ij^T t z_ij, the quadratic form expanded:
        # 1/2 u_i^T t u_i + 1/2 w_j^T t w_j + u_i^T t w_j.
        ea = log_sf2_a - 0.5 * jnp.sum(nu * u, axis=1) + 0.5 * jnp.sum(ut * u, axis=1)
        eb = log_sf2_b - 0.5 * jnp.sum(nu * w, axis=1) + 0.5 * jnp.sum((w @ t) * w, axis=1)
        return jnp.exp(ea[:, None] + eb[None, :] + ut @ w.T - 0.5 * jnp.log(det_g))

    mean, io = jax.vmap(mean_io)(ell, log_sf2, beta)
    num_outputs = beta.shape[0]
    pair_a, pair_b = np.triu_indices(num_outputs)  # Q_ba = Q_ab^T: only the pairs a <= b
    q = jax.vmap(q_matrix)(ell[pair_a], log_sf2[pair_a], ell[pair_b], log_sf2[pair_b])  # (pairs, N, N)
    upper = jnp.einsum("pi,pij,pj->p", beta[pair_a], q, beta[pair_b])  # beta_a^T Q_ab beta_b
    second = jnp.zeros((num_outputs, num_outputs), upper.dtype).at[pair_a, pair_b].set(upper)
    second = second.at[pair_b, pair_a].set(upper)
    cov = second - jnp.outer(mean, mean)
    if k_inv is not None:
        q_diag = q[np.flatnonzero(pair_a == pair_b)]  # Q_aa (E, N, N)
        cov = cov + jnp.diag(jnp.exp(log_sf2) - jnp.sum(k_inv * q_diag, axis=(1, 2)))
    return Moments(mean, cov, io.T)


@jax.jit
def gp_posterior_moments(post, m: jax.Array, s: jax.Array) -> Moments:
    """``gp_moments`` of the project's GP posterior (model uncertainty included, noise not):
    beta = alpha, k_inv = chol_inv^T chol_inv = K^-1, mask = post.mask."""
    k_inv = jnp.einsum("eki,ekj->eij", post.chol_inv, post.chol_inv)
    return gp_moments(post.inputs, post.alpha, post.log_hyp, m, s, k_inv, post.mask)


@jax.jit
def rbf_policy_moments(net: RBFNetwork, m: jax.Array, s: jax.Array) -> Moments:
    """Moments of the RBF policy's pre-activation ``tasks.policies.rbf_preactivation`` (U,) at
    features f ~ N(m (F,), s (F, F)): a GP mean with inputs = centres, beta = weights and
    log_hyp (U, F+2) = [log_lengthscales, log RBF_SIGNAL_STD, log RBF_NOISE_STD]."""
    num_controls = net.log_lengthscales.shape[0]
    consts = jnp.asarray([math.log(RBF_SIGNAL_STD), math.log(RBF_NOISE_STD)], net.log_lengthscales.dtype)
    log_hyp = jnp.concatenate([net.log_lengthscales, jnp.broadcast_to(consts, (num_controls, 2))], axis=1)
    return gp_moments(net.centres, net.weights, log_hyp, m, s)


# ----- sines: saturation and angles ------------------------------------------------------------
def _sin_moments(m: jax.Array, s: jax.Array, lin: jax.Array, shift: jax.Array, weight: jax.Array) -> Moments:
    """Moments of y = weight @ sin(lin @ x + shift) for x ~ N(m (D,), s (D, D)).

    lin (K, D), shift (K,), weight (E, K). With b = lin x + shift ~ N(mu, V):
    E sin b_k = exp(-V_kk/2) sin mu_k, and by the product-to-sum identity
    cov(sin b_i, sin b_j) = 1/2 exp(-(V_ii + V_jj)/2) [expm1(V_ij) cos(mu_i - mu_j)
    - expm1(-V_ij) cos(mu_i + mu_j)] (no cancellation for small V). cov(x, sin b_k) =
    s lin_k^T E cos b_k (Stein's lemma), so io = lin^T diag(E cos b) weight^T: no solve.
    """
    mu = lin @ m + shift
    v = lin @ s @ lin.T
    damp = jnp.exp(-0.5 * jnp.diag(v))  # (K,)
    e_sin, e_cos = damp * jnp.sin(mu), damp * jnp.cos(mu)
    cov_sin = 0.5 * jnp.outer(damp, damp) * (jnp.expm1(v) * jnp.cos(mu[:, None] - mu[None, :])
                                             - jnp.expm1(-v) * jnp.cos(mu[:, None] + mu[None, :]))
    return Moments(weight @ e_sin, weight @ cov_sin @ weight.T, lin.T @ (e_cos[:, None] * weight.T))


@jax.jit
def saturation_moments(m: jax.Array, v: jax.Array, u_max: jax.Array) -> Moments:
    """Moments of u = u_max * (9 sin x + sin 3x) / 8 (elementwise, (U,)) for x ~ N(m (U,), v (U, U)).

    Exact: the joint sine moments of the augmented [x, 3x] (2U,), weighted by
    [9/8 u_max, 1/8 u_max] (``_sin_moments``). io (U, U).
    """
    eye = jnp.eye(m.shape[0], dtype=v.dtype)
    weight = jnp.concatenate([9.0 / 8.0 * jnp.diag(u_max), 1.0 / 8.0 * jnp.diag(u_max)], axis=1)
    return _sin_moments(m, v, jnp.concatenate([eye, 3.0 * eye]), jnp.zeros(2 * m.shape[0], v.dtype), weight)


@jax.jit
def trig_moments(m: jax.Array, s: jax.Array, angle_map: jax.Array) -> Moments:
    """Moments of [sin a_1, cos a_1, sin a_2, cos a_2, ...] (2K,), interleaved, for the angles
    a = angle_map @ x, angle_map (K, D), x ~ N(m (D,), s (D, D)).

    E sin a = exp(-v/2) sin mu, E cos a = exp(-v/2) cos mu and the second moments by the
    product-to-sum identities, via cos a = sin(a + pi/2) (``_sin_moments``). io (D, 2K): the
    columns of angle_map_k^T times E cos a_k and -E sin a_k.
    """
    k = angle_map.shape[0]
    shift = jnp.tile(jnp.asarray([0.0, 0.5 * math.pi], s.dtype), k)
    return _sin_moments(m, s, jnp.repeat(angle_map, 2, axis=0), shift, jnp.eye(2 * k, dtype=s.dtype))


# ----- cost ------------------------------------------------------------------------------------
@jax.jit
def saturating_cost_moments(m: jax.Array, s: jax.Array, target: jax.Array, weight: jax.Array) -> CostMoments:
    """Mean and variance of c = 1 - exp(-1/2 (x - z)^T W (x - z)) for x ~ N(m (Q,), s (Q, Q)).

    z = target (Q,), W = weight (Q, Q). With d = m - z and
    r(k) = E exp(-k/2 (x - z)^T W (x - z)) = |I + k s W|^-1/2 exp(-k/2 d^T W (I + k s W)^-1 d):
    E[c] = 1 - r(1), Var[c] = r(2) - r(1)^2. The quadratic form sees only the symmetric part
    of W, so W is symmetrised first (PILCO's lossSat uses W as given; the two agree for a
    symmetric W, as in every reference case). The variance is not clipped at 0.
    """
    w = 0.5 * (weight + weight.T)
    d = m - target
    eye = jnp.eye(m.shape[0], dtype=s.dtype)

    def r(k):
        x, det = solve_det(eye + k * s @ w, d[:, None])
        return jnp.exp(-0.5 * k * (d @ w @ x[:, 0])) / jnp.sqrt(det)

    r1, r2 = r(1.0), r(2.0)
    return CostMoments(1.0 - r1, r2 - r1**2)
