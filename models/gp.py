"""Gaussian-process dynamics model: one SE-ARD GP per modelled-state dimension.

Inputs are the task's GP inputs ``x = task.gp_inputs(s, u)`` (D,); targets are the state
differences ``s_tp1 - s`` (E = ``task.model_state_dim``). Each output e has a zero prior mean
and the kernel

    k_e(x, x') = sf_e^2 exp(-1/2 sum_d (x_d - x'_d)^2 / l_{e,d}^2),   y = f(x) + N(0, sn_e^2).

Hyperparameters ``log_hyp`` (E, D+2): row e is ``[log l_{e,1..D}, log sf_e, log sn_e]``, PILCO's
layout transposed (PILCO and ``tests/data/moment_matching.json`` store (D+2, E)).

The training set lives in a fixed-capacity buffer (``GPData``) with a mask, so that one
compiled function serves every trial and can be ``vmap``ped over seeds. Masked rows are made
inert: they enter the kernel matrix as rows and columns of the identity and their targets as 0.

Pipeline: ``empty_data`` -> ``add_data`` -> ``train`` (L-BFGS on the penalised negative log
marginal likelihood) -> ``posterior`` (Cholesky factor, its inverse, alpha) -> ``check_posterior``
-> ``predict_difference`` / ``GPModel.predict``. ``fit`` does train + posterior + check on the
host. Everything computes in the dtype of the data; nothing here changes JAX's global config.

Transformations: prediction is elementwise ops and matrix products, so vmap, grad, jvp and
jacfwd all apply. Training and ``posterior`` go through a Cholesky factorisation and triangular
solves written so that vmap never batches a LAPACK call (batched ones deadlock jaxlib 0.10 on
CPU; see ``numerics.linalg``); they support vmap and reverse-mode derivatives, not jvp.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from models.form_moments import map_moments
from models.moment_matching import gp_moments
from models.prediction import Prediction
from numerics.distances import scaled_sq_distances
from numerics.linalg import cholesky, solve_lower, solve_lower_t
from tasks.base import Task, check_vector
from tasks.forms import with_controls


# ----- the training buffer --------------------------------------------------------------------
class GPData(NamedTuple):
    """Fixed-capacity training set. inputs (N, D), targets (N, E), mask (N,) bool.

    Valid rows (mask True) are kept contiguous at the front by ``add_data``; the rest are
    padding whose values are ignored.
    """

    inputs: jax.Array
    targets: jax.Array
    mask: jax.Array

    @property
    def capacity(self) -> int:
        return self.mask.shape[-1]

    @property
    def num_valid(self) -> jax.Array:
        """Number of valid rows (an int array; shape of any leading batch axes)."""
        return jnp.sum(self.mask, axis=-1)


def empty_data(capacity: int, input_dim: int, output_dim: int, dtype=None) -> GPData:
    """An empty buffer: zeros (capacity, input_dim), (capacity, output_dim), mask all False.

    ``dtype`` defaults to JAX's default float (float32, or float64 under ``jax_enable_x64``).
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    return GPData(
        inputs=jnp.zeros((capacity, input_dim), dtype),
        targets=jnp.zeros((capacity, output_dim), dtype),
        mask=jnp.zeros((capacity,), bool),
    )


def trim_data(data: GPData, num_rows: int) -> GPData:
    """The buffer cut to its first ``num_rows`` rows, which must hold every valid row (``add_data``
    keeps them first): the same training set, so the same marginal likelihood and posterior on
    the valid rows, at O(num_rows^3) per fit instead of O(capacity^3). Works on leading batch
    axes (host-level check)."""
    held = int(np.max(np.asarray(data.num_valid)))
    if held > num_rows:
        raise ValueError(f"trim_data: {held} valid rows do not fit in {num_rows}")
    return GPData(inputs=data.inputs[..., :num_rows, :], targets=data.targets[..., :num_rows, :],
                  mask=data.mask[..., :num_rows])


def _is_traced(*arrays) -> bool:
    return any(isinstance(a, jax.core.Tracer) for a in arrays)


def add_data(data: GPData, inputs: jax.Array, targets: jax.Array, mask: jax.Array | None = None) -> GPData:
    """Append the rows of inputs (M, D), targets (M, E) whose ``mask`` (M,) is True.

    They go right after the ``data.num_valid`` rows already held, in order (positions by a
    cumulative sum, scattered with ``mode="drop"``). Jittable. With concrete arrays an overflow
    raises ValueError; under tracing the rows past the capacity are dropped silently, so check
    ``num_valid`` on the host or size the buffer for every trial in advance.
    """
    m = inputs.shape[0]
    mask = jnp.ones((m,), bool) if mask is None else jnp.asarray(mask, bool)
    if inputs.shape != (m, data.inputs.shape[1]) or targets.shape != (m, data.targets.shape[1]) \
            or mask.shape != (m,):
        raise ValueError(
            f"add_data expects inputs (M, {data.inputs.shape[1]}), targets (M, {data.targets.shape[1]}) "
            f"and mask (M,); got {inputs.shape}, {targets.shape}, {mask.shape}"
        )
    capacity = data.capacity
    if not _is_traced(data.mask, mask):
        held, asked = int(np.sum(data.mask)), int(np.sum(mask))
        if held + asked > capacity:
            raise ValueError(
                f"GPData buffer overflow: capacity {capacity}, {held} rows held, {asked} rows asked "
                f"to be added ({held + asked} > {capacity}). Allocate a larger buffer with "
                "empty_data(capacity=...)."
            )
    pos = jnp.sum(data.mask) + jnp.cumsum(mask) - 1
    pos = jnp.where(mask, pos, capacity)  # out of range: dropped
    dtype = data.inputs.dtype
    return GPData(
        inputs=data.inputs.at[pos].set(inputs.astype(dtype), mode="drop"),
        targets=data.targets.at[pos].set(targets.astype(dtype), mode="drop"),
        mask=data.mask.at[pos].set(True, mode="drop"),
    )


def clean(data: GPData) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Inputs (N, D) and targets (N, E) with padding rows zeroed (so NaN padding stays inert)."""
    x = jnp.where(data.mask[:, None], data.inputs, 0.0)
    y = jnp.where(data.mask[:, None], data.targets, 0.0)
    return x, y, data.mask


def data_scales(data: GPData) -> tuple[jax.Array, jax.Array]:
    """Masked standard deviations (ddof 1, as MATLAB's ``std``) of the inputs (D,) and the
    targets (E,). A zero spread (a constant column, or fewer than two rows) is replaced by 1."""
    x, y, mask = clean(data)
    w = mask.astype(x.dtype)[:, None]
    n = jnp.sum(w)

    def std(v):
        mean = jnp.sum(w * v, axis=0) / jnp.maximum(n, 1.0)
        s = jnp.sqrt(jnp.sum(w * (v - mean) ** 2, axis=0) / jnp.maximum(n - 1.0, 1.0))
        return jnp.where(s > 0, s, 1.0)

    return std(x), std(y)


# ----- hyperparameters and the marginal likelihood ----------------------------------------------
def init_log_hyp(data: GPData) -> jax.Array:
    """PILCO's initialisation, (E, D+2): l_{e,d} = std(x_d), sf_e = std(y_e), sn_e = sf_e / 10."""
    x_std, y_std = data_scales(data)
    e = y_std.shape[0]
    log_ls = jnp.broadcast_to(jnp.log(x_std), (e, x_std.shape[0]))
    log_sf = jnp.log(y_std)
    return jnp.concatenate([log_ls, log_sf[:, None], (log_sf - math.log(10.0))[:, None]], axis=1)


def split_hyp(log_hyp_e: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(D+2,) -> length-scales (D,), signal variance sf^2, noise variance sn^2."""
    return jnp.exp(log_hyp_e[:-2]), jnp.exp(2.0 * log_hyp_e[-2]), jnp.exp(2.0 * log_hyp_e[-1])


def kernel_matrix(log_hyp_e: jax.Array, x: jax.Array) -> jax.Array:
    """SE-ARD Gram matrix (N, N) of one output on inputs x (N, D), without noise."""
    ls, sf2, _ = split_hyp(log_hyp_e)
    z = x / ls
    sq = jnp.sum(z * z, axis=1)
    d2 = jnp.maximum(sq[:, None] + sq[None, :] - 2.0 * z @ z.T, 0.0)  # round-off can go below 0
    return sf2 * jnp.exp(-0.5 * d2)


def _factor(log_hyp_e: jax.Array, x: jax.Array, y: jax.Array, mask: jax.Array):
    """Cholesky factor L (N, N) of ``K_ij m_i m_j + diag(m_i sn^2 + (1 - m_i))`` and
    ``alpha = (L L^T)^-1 y`` (N,) for one output; x (N, D), y (N,) with padding zeroed."""
    _, _, sn2 = split_hyp(log_hyp_e)
    k = kernel_matrix(log_hyp_e, x)
    k = jnp.where(mask[:, None] & mask[None, :], k, 0.0)
    k = k + jnp.diag(jnp.where(mask, sn2, 1.0))
    chol = cholesky(k)
    alpha = solve_lower_t(chol, solve_lower(chol, y))
    return chol, alpha


def _nlml_one(log_hyp_e, x, y, mask):
    """``1/2 y^T K^-1 y + 1/2 log|K| + n_valid/2 log(2 pi)`` for one output (padding inert)."""
    chol, alpha = _factor(log_hyp_e, x, y, mask)
    n = jnp.sum(mask).astype(x.dtype)
    return 0.5 * y @ alpha + jnp.sum(jnp.log(jnp.diag(chol))) + 0.5 * n * math.log(2.0 * math.pi)


@jax.jit
def neg_log_marginal_likelihood(log_hyp: jax.Array, data: GPData) -> jax.Array:
    """Exact negative log marginal likelihood summed over the E outputs (scalar).

    log_hyp (E, D+2); only the valid rows of ``data`` count (padding rows are inert).
    """
    x, y, mask = clean(data)
    return jnp.sum(jax.vmap(_nlml_one, in_axes=(0, None, 1, None))(log_hyp, x, y, mask))


class Curb(NamedTuple):
    """Bounds against degenerate fits (in the spirit of PILCO's ``hypCurb``, own form).

    With ``std_x`` (D,), ``std_y`` (E,) the masked data spreads (``data_scales``) and
    ``h(v) = max(v, 0)^2``, the penalty added to the negative log marginal likelihood is

        weight * n_valid * sum_e [ sum_d h(log l_{e,d} - log(lengthscale_max_ratio * std_x_d))
                                   + h(log sf_e - log sn_e - log snr_max)
                                   + h(log(noise_min_ratio * std_y_e) - log sn_e) ]

    zero inside the bounds and smooth (C1) outside. Weighting by n_valid keeps it on the scale
    of the likelihood. The bounds are soft: a fit may cross one by a fraction of a log unit
    where the data pull hard. A NamedTuple of numbers: a pytree, so changing a bound does not
    recompile ``train`` (and bounds can be ``vmap``ped).
    """

    lengthscale_max_ratio: float = 100.0
    snr_max: float = 500.0
    noise_min_ratio: float = 1e-3
    weight: float = 1.0


def curb_penalty(log_hyp: jax.Array, data: GPData, curb: Curb = Curb()) -> jax.Array:
    """The ``Curb`` penalty (scalar) of log_hyp (E, D+2) on ``data`` (formula in ``Curb``)."""
    x_std, y_std = data_scales(data)
    log_ls, log_sf, log_sn = log_hyp[:, :-2], log_hyp[:, -2], log_hyp[:, -1]

    def hinge2(v):
        return jnp.sum(jnp.maximum(v, 0.0) ** 2)

    total = (
        hinge2(log_ls - jnp.log(curb.lengthscale_max_ratio * x_std))
        + hinge2(log_sf - log_sn - jnp.log(curb.snr_max))
        + hinge2(jnp.log(curb.noise_min_ratio * y_std) - log_sn)
    )
    return curb.weight * jnp.sum(data.mask).astype(log_hyp.dtype) * total


@jax.jit
def objective(log_hyp: jax.Array, data: GPData, curb: Curb = Curb()) -> jax.Array:
    """The training objective: ``neg_log_marginal_likelihood + curb_penalty`` (scalar)."""
    return neg_log_marginal_likelihood(log_hyp, data) + curb_penalty(log_hyp, data, curb)


class TrainResult(NamedTuple):
    """log_hyp (E, D+2): the iterate with the lowest finite objective; history
    (num_steps + 1,): the objective at the initial value and after each step."""

    log_hyp: jax.Array
    history: jax.Array


def train(data: GPData, log_hyp0: jax.Array | None = None, num_steps: int = 100,
          curb: Curb = Curb()) -> TrainResult:
    """Minimise ``objective`` (penalised NLML) by ``num_steps`` L-BFGS steps (optax, zoom line
    search) in a ``lax.scan``: jitted, and ``vmap``pable over buffers, initial values and curbs.

    log_hyp0 (E, D+2) defaults to ``init_log_hyp(data)``. An update whose parameters or
    objective are not finite is rejected: the previous iterate is kept and, as a retry from the
    same state would fail the same way, the remaining steps are skipped (``lax.cond``; under
    ``vmap`` they are computed and discarded). The lowest finite objective seen is returned.
    """
    # curb always goes in as an argument: one compiled function whatever the bounds.
    return _train(data, log_hyp0, curb, num_steps)


@functools.partial(jax.jit, static_argnums=(3,))
def _train(data: GPData, log_hyp0: jax.Array | None, curb: Curb, num_steps: int) -> TrainResult:
    params0 = init_log_hyp(data) if log_hyp0 is None else jnp.asarray(log_hyp0, data.inputs.dtype)
    return TrainResult(*lbfgs_minimise(functools.partial(objective, data=data, curb=curb), params0, num_steps))


def lbfgs_minimise(fun, params0: jax.Array, num_steps: int) -> tuple[jax.Array, jax.Array]:
    """``num_steps`` L-BFGS steps (optax, zoom line search) on the scalar ``fun`` from params0,
    in a ``lax.scan`` (trace it inside jit). An update whose parameters or value are not finite
    is rejected and ends the run (the remaining steps keep the last good iterate, computed
    under ``lax.cond``). Returns (the iterate with the lowest finite value, the history
    (num_steps + 1,) of values, the first at params0)."""
    opt = optax.lbfgs()
    value_and_grad = optax.value_and_grad_from_state(fun)

    def update(params, state):
        value, grad = value_and_grad(params, state=state)
        updates, new_state = opt.update(grad, state, params, value=value, grad=grad, value_fn=fun)
        new_params = optax.apply_updates(params, updates)
        new_value = optax.tree_utils.tree_get(new_state, "value")
        ok = jnp.all(jnp.isfinite(new_params)) & jnp.isfinite(new_value)
        params, state = jax.tree.map(lambda a, b: jnp.where(ok, a, b), (new_params, new_state), (params, state))
        return params, state, value, ~ok

    def step(carry, _):
        params, state, stopped = carry
        params, state, value, failed = jax.lax.cond(
            stopped, lambda p, s: (p, s, fun(p), stopped), update, params, state
        )
        return (params, state, stopped | failed), (params, value)

    _, (iterates, history) = jax.lax.scan(
        step, (params0, opt.init(params0), jnp.zeros((), bool)), None, length=num_steps
    )
    # iterates[i] is the iterate after step i; history[i] the value before it.
    iterates = jnp.concatenate([params0[None], iterates])
    history = jnp.append(history, fun(iterates[-1]))
    best = jnp.argmin(jnp.where(jnp.isfinite(history), history, jnp.inf))
    return iterates[best], history


# ----- the posterior and prediction ----------------------------------------------------------------
class GPPosterior(NamedTuple):
    """What prediction needs. inputs (N, D) (padding zeroed), mask (N,), log_hyp (E, D+2),
    chol (E, N, N) lower Cholesky factors L of the masked noisy kernel matrices K, chol_inv
    (E, N, N) their inverses L^-1 (by triangular solves, once), alpha (E, N) ``= K^-1 y``.
    These are the ``params`` of ``GPModel.predict``."""

    inputs: jax.Array
    mask: jax.Array
    log_hyp: jax.Array
    chol: jax.Array
    chol_inv: jax.Array
    alpha: jax.Array


def _posterior_one(log_hyp_e, x, y, mask):
    chol, alpha = _factor(log_hyp_e, x, y, mask)
    return chol, solve_lower(chol, jnp.eye(x.shape[0], dtype=x.dtype)), alpha


@jax.jit
def posterior(log_hyp: jax.Array, data: GPData) -> GPPosterior:
    """Factorise the masked noisy kernel matrix of each output (jittable; no checks: a failed
    factorisation shows as NaN, see ``check_posterior``)."""
    x, y, mask = clean(data)
    chol, chol_inv, alpha = jax.vmap(_posterior_one, in_axes=(0, None, 1, None))(log_hyp, x, y, mask)
    return GPPosterior(inputs=x, mask=mask, log_hyp=log_hyp, chol=chol, chol_inv=chol_inv, alpha=alpha)


def truncate(post: GPPosterior, num_rows: int) -> GPPosterior:
    """The posterior on the buffer's first ``num_rows`` rows, which must hold every valid row
    (``add_data`` keeps them first). Predictions are unchanged: masked rows are decoupled in
    K, so the leading blocks of L and L^-1 are those of the valid rows, and prediction costs
    O(num_rows^2) instead of O(capacity^2). Works on leading batch axes (host-level check)."""
    held = int(np.max(np.asarray(post.mask).sum(axis=-1)))
    if held > num_rows:
        raise ValueError(f"truncate: {held} valid rows do not fit in {num_rows}")
    return GPPosterior(inputs=post.inputs[..., :num_rows, :], mask=post.mask[..., :num_rows],
                       log_hyp=post.log_hyp, chol=post.chol[..., :num_rows, :num_rows],
                       chol_inv=post.chol_inv[..., :num_rows, :num_rows], alpha=post.alpha[..., :num_rows])


class CholeskyError(np.linalg.LinAlgError):
    """The GP's kernel matrix could not be factorised (a ValueError, via numpy's LinAlgError)."""


def check_posterior(post: GPPosterior) -> GPPosterior:
    """Raise ``CholeskyError`` unless chol, chol_inv and alpha are finite; return ``post``.

    Host-level (needs concrete arrays); works on a batch of posteriors (leading axes, e.g. the
    output of a ``vmap`` over seeds) and names the failing (batch..., output) indices.
    """
    chol, chol_inv, alpha = np.asarray(post.chol), np.asarray(post.chol_inv), np.asarray(post.alpha)
    bad = ~(np.isfinite(chol).all(axis=(-1, -2)) & np.isfinite(chol_inv).all(axis=(-1, -2))
            & np.isfinite(alpha).all(axis=-1))
    if not bad.any():
        return post
    causes = []
    if not np.isfinite(np.asarray(post.log_hyp)).all():
        causes.append("the hyperparameters are not finite")
    valid_inputs = np.where(np.asarray(post.mask)[..., None], np.asarray(post.inputs), 0.0)
    if not np.isfinite(valid_inputs).all():
        causes.append("valid rows of the training inputs contain NaN or inf")
    cause = "; ".join(causes) if causes else (
        "the noisy kernel matrix is not positive definite in "
        f"{chol.dtype} (signal-to-noise ratio too high for the precision, or duplicate inputs)"
    )
    raise CholeskyError(
        f"GP posterior is not finite (Cholesky factor, its inverse or alpha contains NaN/inf) at "
        f"(batch..., output) indices {np.argwhere(bad).tolist()}: {cause}. What to do: run in "
        'float64 (jax.config.update("jax_enable_x64", True) at start-up, or the harness\'s --x64 '
        "flag, and build the GPData in float64); raise the noise floor (Curb(noise_min_ratio=...)) "
        "or lower Curb(snr_max=...); remove duplicate or near-duplicate inputs; check the "
        "training data for NaN or inf."
    )


def fit(data: GPData, log_hyp0: jax.Array | None = None, num_steps: int = 100,
        curb: Curb = Curb()) -> GPPosterior:
    """Host-level convenience: ``train``, ``posterior``, ``check_posterior``. Raises
    ``CholeskyError`` rather than returning a posterior with NaN."""
    result = train(data, log_hyp0, num_steps=num_steps, curb=curb)
    return check_posterior(posterior(result.log_hyp, data))


@jax.custom_jvp
def explained_variance(chol_inv: jax.Array, k: jax.Array) -> jax.Array:
    """``|L^-1 k|^2 = k^T K^-1 k`` for the stored ``L^-1`` (N, N) and k (N,): the part of the
    prior variance the data explain. Its derivative with respect to k, ``2 K^-1 k``, is formed
    from the primal values (one more N^2 product), so that the tangent, and in reverse mode
    each cotangent, is an O(N) product instead of an N^2 one: TP maps two cotangents through
    every particle's prediction. Forward and reverse mode both apply."""
    v = chol_inv @ k
    return v @ v


@functools.partial(explained_variance.defjvp, symbolic_zeros=True)
def _explained_variance_jvp(primals, tangents):
    chol_inv, k = primals
    d_chol_inv, d_k = tangents
    v = chol_inv @ k
    tangent = jnp.zeros_like(v[0])
    if not isinstance(d_k, jax.custom_derivatives.SymbolicZero):
        tangent = tangent + 2.0 * (chol_inv.T @ v) @ d_k
    if not isinstance(d_chol_inv, jax.custom_derivatives.SymbolicZero):
        tangent = tangent + 2.0 * v @ (d_chol_inv @ k)
    return v @ v, tangent


def _predict_one(log_hyp_e, chol_inv, alpha, inputs, mask, x):
    ls, sf2, sn2 = split_hyp(log_hyp_e)
    k = sf2 * jnp.exp(-0.5 * scaled_sq_distances(inputs, x, ls))
    k = jnp.where(mask, k, 0.0)
    # sf^2 - |L^-1 k|^2 >= 0 in exact arithmetic; the clip only removes round-off below 0.
    return k @ alpha, jnp.maximum(sf2 - explained_variance(chol_inv, k), 0.0), sn2


def predict_difference(post: GPPosterior, x: jax.Array) -> Prediction:
    """Predictive distribution of the target (the state difference) at ONE GP input x (D,).

    Per output e: mean = k_*^T alpha; model_var = sf^2 - |L^-1 k_*|^2 (= sf^2 - k_*^T K^-1 k_*,
    clipped at 0 against round-off), with L^-1 the stored ``chol_inv``; noise_var = sn^2. Each
    (E,), in the posterior's dtype. Only elementwise ops and matrix products: O(N^2) per output
    (``explained_variance`` carries a custom JVP), and every transformation (vmap over
    particles, grad, jvp, jacfwd) applies.
    """
    check_vector("x (GP input)", x, post.inputs.shape[-1])
    x = jnp.asarray(x, post.inputs.dtype)
    mean, model_var, noise_var = jax.vmap(_predict_one, in_axes=(0, 0, 0, None, None, None))(
        post.log_hyp, post.chol_inv, post.alpha, post.inputs, post.mask, x
    )
    return Prediction(mean=mean, model_var=model_var, noise_var=noise_var)


@dataclasses.dataclass(frozen=True)
class GPModel:
    """The GP dynamics model of a task (implements ``models.prediction.Model``).

    ``predict(post, s (S,), u (U,))``: mean = s + predicted difference at
    ``task.gp_inputs(s, u)``; model_var, noise_var (S,) as in ``predict_difference``.
    """

    task: Task

    def empty_data(self, capacity: int, dtype=None) -> GPData:
        """An empty buffer sized for this task's GP inputs (D) and targets (S)."""
        return empty_data(capacity, self.task.gp_input_dim, self.task.model_state_dim, dtype)

    def predict(self, params: GPPosterior, s: jax.Array, u: jax.Array) -> Prediction:
        check_vector("s (modelled state)", s, self.task.model_state_dim)
        check_vector("u (control)", u, self.task.control_dim)
        if params.alpha.shape[0] != self.task.model_state_dim:
            raise ValueError(
                f"the GP has {params.alpha.shape[0]} outputs but task {self.task.name!r} models "
                f"{self.task.model_state_dim} state dimensions"
            )
        diff = predict_difference(params, self.task.gp_inputs(s, u))
        return Prediction(mean=s + diff.mean, model_var=diff.model_var, noise_var=diff.noise_var)

    def next_state_moments(self, params: GPPosterior, z_mean: jax.Array, z_cov: jax.Array,
                           model_var_scale: float = 1.0, noise_var_scale: float = 1.0):
        """PILCO's step for z = [s, u] ~ N(z_mean (S+U,), z_cov): the GP input g = [gp features
        of s, u] by moment matching, the difference delta ~ GP(g) (with the model's uncertainty
        unless ``model_var_scale`` is 0, plus ``noise_var_scale`` sn^2), and
        ``s_tp1 = s + delta`` with ``cov(s, delta) = cov(s, z) io_g io_delta``. Returns
        (mean (S,), cov (S, S))."""
        if self.task.gp_feature_map is None:
            raise ValueError(f"task {self.task.name!r} declares no gp_feature_map: no moment matching")
        S = self.task.model_state_dim
        g = map_moments(with_controls(self.task.gp_feature_map, self.task.control_dim), z_mean, z_cov)
        k_inv = None if model_var_scale == 0 else jnp.swapaxes(params.chol_inv, -1, -2) @ params.chol_inv
        delta = gp_moments(params.inputs, params.alpha, params.log_hyp, g.mean, g.cov, k_inv, params.mask)
        cross = (z_cov @ g.io @ delta.io)[:S]  # cov(s, delta)
        noise = noise_var_scale * jnp.exp(2.0 * params.log_hyp[:, -1])
        cov = z_cov[:S, :S] + delta.cov + cross + cross.T + jnp.diag(noise)
        return z_mean[:S] + delta.mean, cov
